//! The frozen test cases: one random map-frame motion Q per evaluated frame.
//!
//! Drawn once from a seed and written to a JSON file; every later run (on any machine) reads the
//! file back, so two evaluations compare exactly the same cases. Q = rotation about the map's z
//! axis by `yaw_deg` ∈ [−180°, 180°), then translation (`dx_m`, `dy_m`) ∈ [−10, 10] m each; the
//! map is Q·scan and the ground truth camera_from_map is camera_from_lidar · Q⁻¹.
//!
//! A second regime, [`Priors::Fleet`], draws what a fleet backend sends: a prior from odometry or
//! GNSS, `yaw_deg` ∈ [−30°, 30°) and the shift uniform in a disc of 5 m. The file records the
//! regime (`"priors"`, absent in older files: the protocol).

use std::path::Path;

use anyhow::{Context, Result, bail};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::atomic_file::write_atomic;
use crate::geometry::Pose;

pub const FORMAT: &str = "cmr-agent-perturbations/1";
/// The seed of the N-point sampling (ChaCha8) every Rust code path uses; recorded so that a
/// file made by a build with another sampling is refused instead of silently compared.
pub const SAMPLING_SEED: u64 = 0;
pub const MAX_YAW_DEG: f64 = 180.0;
pub const MAX_SHIFT_M: f64 = 10.0;
/// The fleet regime's bounds: a prior within ±30° of heading and 5 m of position.
pub const FLEET_MAX_YAW_DEG: f64 = 30.0;
pub const FLEET_MAX_SHIFT_M: f64 = 5.0;

/// How far from the truth the cases' priors are drawn.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Priors {
    /// The paper's protocol: any heading, each ground shift in ±10 m.
    #[default]
    Protocol,
    /// A fleet-grade prior: heading within ±30°, position within a 5 m disc.
    Fleet,
}

/// One evaluated case.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Perturbation {
    pub sequence: String,
    pub frame: usize,
    pub yaw_deg: f64,
    pub dx_m: f64,
    pub dy_m: f64,
}

impl Perturbation {
    /// Q: the motion applied to the scan to make the map.
    pub fn map_from_lidar(&self) -> Pose {
        Pose::ground_motion(self.yaw_deg.to_radians(), self.dx_m, self.dy_m)
    }

    /// Ground truth camera_from_map for a rig with this `camera_from_lidar`.
    pub fn truth(&self, camera_from_lidar: &Pose) -> Pose {
        camera_from_lidar.compose(&self.map_from_lidar().inverse())
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PerturbationFile {
    pub format: String,
    /// The seed the motions were drawn from.
    pub seed: u64,
    /// The seed of the N-point sampling (see [`SAMPLING_SEED`]).
    pub sampling_seed: u64,
    /// The regime the motions were drawn in.
    #[serde(default, skip_serializing_if = "is_protocol")]
    pub priors: Priors,
    pub cases: Vec<Perturbation>,
}

fn is_protocol(p: &Priors) -> bool {
    *p == Priors::Protocol
}

impl PerturbationFile {
    /// Draws one motion per frame, in the order given, from `seed`, in the regime `priors`
    /// (the protocol's draws are those of every earlier file with the same seed).
    pub fn generate(frames: &[(String, usize)], seed: u64, priors: Priors) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let cases = frames
            .iter()
            .map(|(sequence, frame)| {
                let (yaw_deg, dx_m, dy_m) = match priors {
                    Priors::Protocol => (
                        rng.random_range(-MAX_YAW_DEG..MAX_YAW_DEG),
                        rng.random_range(-MAX_SHIFT_M..=MAX_SHIFT_M),
                        rng.random_range(-MAX_SHIFT_M..=MAX_SHIFT_M),
                    ),
                    Priors::Fleet => {
                        let yaw = rng.random_range(-FLEET_MAX_YAW_DEG..FLEET_MAX_YAW_DEG);
                        let radius = FLEET_MAX_SHIFT_M * rng.random_range(0.0..=1.0f64).sqrt();
                        let heading = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
                        (yaw, radius * heading.cos(), radius * heading.sin())
                    }
                };
                Perturbation {
                    sequence: sequence.clone(),
                    frame: *frame,
                    yaw_deg: micro(yaw_deg).clamp(-MAX_YAW_DEG, MAX_YAW_DEG - 1e-6),
                    dx_m: micro(dx_m),
                    dy_m: micro(dy_m),
                }
            })
            .collect();
        PerturbationFile { format: FORMAT.into(), seed, sampling_seed: SAMPLING_SEED, priors, cases }
    }

    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let file: PerturbationFile = serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        file.validate().with_context(|| format!("checking {}", path.display()))?;
        Ok(file)
    }

    pub fn validate(&self) -> Result<()> {
        if self.format != FORMAT {
            bail!("unknown perturbation file format {:?} (this build reads {FORMAT:?})", self.format);
        }
        if self.sampling_seed != SAMPLING_SEED {
            bail!("the file was made with point-sampling seed {}, this build samples with {SAMPLING_SEED}", self.sampling_seed);
        }
        if self.cases.is_empty() {
            bail!("the file lists no cases");
        }
        for (i, c) in self.cases.iter().enumerate() {
            let finite = c.yaw_deg.is_finite() && c.dx_m.is_finite() && c.dy_m.is_finite();
            let inside = match self.priors {
                Priors::Protocol => c.yaw_deg.abs() <= MAX_YAW_DEG && c.dx_m.abs() <= MAX_SHIFT_M && c.dy_m.abs() <= MAX_SHIFT_M,
                Priors::Fleet => c.yaw_deg.abs() <= FLEET_MAX_YAW_DEG && c.dx_m.hypot(c.dy_m) <= FLEET_MAX_SHIFT_M + 1e-6,
            };
            if !finite || !inside {
                bail!("case {i} ({} frame {}) is outside the {:?} regime's range", c.sequence, c.frame, self.priors);
            }
        }
        Ok(())
    }

    /// Writes atomically (temporary file in the same directory, fsync, rename).
    pub fn write(&self, path: &Path) -> Result<()> {
        let json = serde_json::to_string_pretty(self)?;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        Ok(write_atomic(path, json.as_bytes())?)
    }

    /// Reads `path` when it exists; otherwise draws the cases for `frames` from `seed` and
    /// writes them there. Returns the file and whether it was created. Either way the cases are
    /// the ones parsed from the file, so every run evaluates the file's text, bit for bit.
    /// `priors` only matters when the file is created.
    pub fn load_or_create(path: &Path, frames: &[(String, usize)], seed: u64, priors: Priors) -> Result<(Self, bool)> {
        if path.exists() {
            return Ok((Self::read(path)?, false));
        }
        let file = Self::generate(frames, seed, priors);
        file.validate()?;
        file.write(path)?;
        Ok((Self::read(path)?, true))
    }
}

/// Rounds to 1e-6 (µm, µdeg): short, exact-looking numbers in the file.
fn micro(x: f64) -> f64 {
    (x * 1e6).round() / 1e6
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::PoseError;

    fn frames() -> Vec<(String, usize)> {
        (0..20).map(|i| (format!("{:02}", i % 2), i)).collect()
    }

    #[test]
    fn same_seed_same_cases_and_the_file_round_trips() {
        let a = PerturbationFile::generate(&frames(), 7, Priors::Protocol);
        assert_eq!(a, PerturbationFile::generate(&frames(), 7, Priors::Protocol));
        assert_ne!(a, PerturbationFile::generate(&frames(), 8, Priors::Protocol));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cases.json");
        let (created, fresh) = PerturbationFile::load_or_create(&path, &frames(), 7, Priors::Protocol).unwrap();
        assert!(fresh);
        // A second run reads the file, whatever seed or frames it is given.
        let (read, fresh) = PerturbationFile::load_or_create(&path, &frames()[..3], 99, Priors::Protocol).unwrap();
        assert!(!fresh);
        assert_eq!(read, created);
        assert_eq!(read, a);
        assert!(a.cases.iter().all(|c| c.yaw_deg >= -180.0 && c.yaw_deg < 180.0 && c.dx_m.abs() <= 10.0));
    }

    #[test]
    fn fleet_priors_stay_within_30_degrees_and_5_metres_and_round_trip() {
        let a = PerturbationFile::generate(&frames(), 7, Priors::Fleet);
        assert!(a.cases.iter().all(|c| c.yaw_deg.abs() <= FLEET_MAX_YAW_DEG && c.dx_m.hypot(c.dy_m) <= FLEET_MAX_SHIFT_M + 1e-6));
        // drawn over the whole range, not a corner of it
        assert!(a.cases.iter().any(|c| c.yaw_deg < -15.0) && a.cases.iter().any(|c| c.yaw_deg > 15.0));
        assert!(a.cases.iter().any(|c| c.dx_m.hypot(c.dy_m) > 3.0));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fleet.json");
        a.write(&path).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains("\"priors\": \"fleet\""), "{text}");
        assert_eq!(PerturbationFile::read(&path).unwrap(), a);
        // a protocol file does not name its regime (older files read the same), and a case
        // outside the fleet bounds is refused
        assert!(!serde_json::to_string(&PerturbationFile::generate(&frames(), 7, Priors::Protocol)).unwrap().contains("priors"));
        let mut wide = a.clone();
        wide.cases[0].dx_m = 6.0;
        assert!(wide.validate().is_err());
    }

    #[test]
    fn foreign_or_broken_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cases.json");
        let mut file = PerturbationFile::generate(&frames(), 1, Priors::Protocol);
        file.sampling_seed = 5;
        std::fs::write(&path, serde_json::to_string(&file).unwrap()).unwrap();
        assert!(PerturbationFile::read(&path).unwrap_err().to_string().contains("checking"));
        file.sampling_seed = SAMPLING_SEED;
        file.cases[0].dx_m = 30.0;
        file.write(&path).unwrap();
        assert!(PerturbationFile::read(&path).is_err());
        std::fs::write(&path, "{").unwrap();
        assert!(PerturbationFile::read(&path).is_err());
    }

    #[test]
    fn truth_undoes_the_map_motion() {
        let case = Perturbation { sequence: "00".into(), frame: 0, yaw_deg: 30.0, dx_m: 3.0, dy_m: -4.0 };
        let rig = Pose::ground_motion(0.1, 0.5, 0.2);
        let truth = case.truth(&rig);
        let p = nalgebra::Point3::new(5.0, 1.0, -1.5);
        let moved = case.map_from_lidar().transform(&p);
        assert!((truth.transform(&moved) - rig.transform(&p)).norm() < 1e-12);
        // Starting at the rig pose, the error is the perturbation itself.
        let e = PoseError::between(&rig, &truth);
        assert!((e.rre_geodesic_deg - 30.0).abs() < 1e-9);
    }
}
