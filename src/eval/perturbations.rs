//! The frozen test cases: one random map-frame motion Q per evaluated frame.
//!
//! Drawn once from a seed and written to a JSON file; every later run (on any machine) reads the
//! file back, so two evaluations compare exactly the same cases. Q = rotation about the map's z
//! axis by `yaw_deg` ∈ [−180°, 180°), then translation (`dx_m`, `dy_m`) ∈ [−10, 10] m each; the
//! map is Q·scan and the ground truth camera_from_map is camera_from_lidar · Q⁻¹.
//!
//! A file drawn [`NearPrior`] instead (`cmr-agent eval --max-yaw-deg 30 --max-shift-m 5`) holds
//! the priors a fleet has: yaw uniform in ±`max_yaw_deg`, the shift uniform in the disc of radius
//! `max_shift_m` (so the no-op's error is at most that); the file records the bounds.

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

/// Bounds of a near-prior draw (the fleet regime): |yaw| ≤ `max_yaw_deg`, √(dx² + dy²) ≤
/// `max_shift_m`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NearPrior {
    pub max_yaw_deg: f64,
    pub max_shift_m: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PerturbationFile {
    pub format: String,
    /// The seed the motions were drawn from.
    pub seed: u64,
    /// The seed of the N-point sampling (see [`SAMPLING_SEED`]).
    pub sampling_seed: u64,
    /// Present when the motions were drawn near the prior (not the paper's protocol).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub near: Option<NearPrior>,
    pub cases: Vec<Perturbation>,
}

impl PerturbationFile {
    /// Draws one motion per frame, in the order given, from `seed`.
    pub fn generate(frames: &[(String, usize)], seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let cases = frames
            .iter()
            .map(|(sequence, frame)| Perturbation {
                sequence: sequence.clone(),
                frame: *frame,
                yaw_deg: micro(rng.random_range(-MAX_YAW_DEG..MAX_YAW_DEG)).clamp(-MAX_YAW_DEG, MAX_YAW_DEG - 1e-6),
                dx_m: micro(rng.random_range(-MAX_SHIFT_M..=MAX_SHIFT_M)),
                dy_m: micro(rng.random_range(-MAX_SHIFT_M..=MAX_SHIFT_M)),
            })
            .collect();
        PerturbationFile { format: FORMAT.into(), seed, sampling_seed: SAMPLING_SEED, near: None, cases }
    }

    /// Draws one motion per frame near the prior, in the order given, from `seed`: yaw uniform
    /// in [−max_yaw_deg, max_yaw_deg], the shift at a uniform angle and radius max_shift_m·√u
    /// (uniform over the disc; `training/cmr/data.py`'s `near_start_p` draws the same way).
    pub fn generate_near(frames: &[(String, usize)], seed: u64, near: NearPrior) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let cases = frames
            .iter()
            .map(|(sequence, frame)| {
                let yaw_deg = micro(rng.random_range(-near.max_yaw_deg..=near.max_yaw_deg));
                let radius = near.max_shift_m * rng.random_range(0.0f64..1.0).sqrt();
                let angle = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
                // Rounding must not leave the disc.
                let (dx_m, dy_m) = (micro(radius * angle.cos() * (1.0 - 1e-6)), micro(radius * angle.sin() * (1.0 - 1e-6)));
                Perturbation { sequence: sequence.clone(), frame: *frame, yaw_deg, dx_m, dy_m }
            })
            .collect();
        PerturbationFile { format: FORMAT.into(), seed, sampling_seed: SAMPLING_SEED, near: Some(near), cases }
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
            if !finite || c.yaw_deg.abs() > MAX_YAW_DEG || c.dx_m.abs() > MAX_SHIFT_M || c.dy_m.abs() > MAX_SHIFT_M {
                bail!("case {i} ({} frame {}) is outside the protocol's range", c.sequence, c.frame);
            }
            let outside_near = self.near.is_some_and(|n| c.yaw_deg.abs() > n.max_yaw_deg || c.dx_m.hypot(c.dy_m) > n.max_shift_m);
            if outside_near {
                bail!("case {i} ({} frame {}) is outside the file's near-prior bounds", c.sequence, c.frame);
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

    /// Reads `path` when it exists; otherwise draws the cases for `frames` from `seed` (the
    /// paper's protocol, or `near` the prior) and writes them there. Returns the file and
    /// whether it was created. Either way the cases are the ones parsed from the file, so every
    /// run evaluates the file's text, bit for bit.
    pub fn load_or_create(path: &Path, frames: &[(String, usize)], seed: u64, near: Option<NearPrior>) -> Result<(Self, bool)> {
        if path.exists() {
            return Ok((Self::read(path)?, false));
        }
        let file = match near {
            Some(near) => Self::generate_near(frames, seed, near),
            None => Self::generate(frames, seed),
        };
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
        let a = PerturbationFile::generate(&frames(), 7);
        assert_eq!(a, PerturbationFile::generate(&frames(), 7));
        assert_ne!(a, PerturbationFile::generate(&frames(), 8));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cases.json");
        let (created, fresh) = PerturbationFile::load_or_create(&path, &frames(), 7, None).unwrap();
        assert!(fresh);
        // A second run reads the file, whatever seed or frames it is given.
        let (read, fresh) = PerturbationFile::load_or_create(&path, &frames()[..3], 99, None).unwrap();
        assert!(!fresh);
        assert_eq!(read, created);
        assert_eq!(read, a);
        assert!(a.cases.iter().all(|c| c.yaw_deg >= -180.0 && c.yaw_deg < 180.0 && c.dx_m.abs() <= 10.0));
    }

    /// The fleet regime: every case within the bounds, filling them (some near each edge),
    /// seeded, recorded in the file and checked when read back.
    #[test]
    fn near_prior_draws_stay_within_their_bounds() {
        let near = NearPrior { max_yaw_deg: 30.0, max_shift_m: 5.0 };
        let frames: Vec<(String, usize)> = (0..400).map(|i| ("00".to_string(), i)).collect();
        let a = PerturbationFile::generate_near(&frames, 3, near);
        assert_eq!(a, PerturbationFile::generate_near(&frames, 3, near));
        assert!(a.cases.iter().all(|c| c.yaw_deg.abs() <= 30.0 && c.dx_m.hypot(c.dy_m) <= 5.0));
        assert!(a.cases.iter().any(|c| c.yaw_deg > 28.0) && a.cases.iter().any(|c| c.yaw_deg < -28.0));
        assert!(a.cases.iter().any(|c| c.dx_m.hypot(c.dy_m) > 4.8));
        // Uniform over the disc: about a quarter of the cases within half the radius.
        let inner = a.cases.iter().filter(|c| c.dx_m.hypot(c.dy_m) < 2.5).count();
        assert!((70..130).contains(&inner), "{inner}");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fleet.json");
        let (created, fresh) = PerturbationFile::load_or_create(&path, &frames, 3, Some(near)).unwrap();
        assert!(fresh && created == a && created.near == Some(near));
        let mut outside = a.clone();
        outside.cases[0].yaw_deg = 31.0;
        outside.write(&path).unwrap();
        assert!(format!("{:#}", PerturbationFile::read(&path).unwrap_err()).contains("near-prior bounds"));
    }

    #[test]
    fn foreign_or_broken_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cases.json");
        let mut file = PerturbationFile::generate(&frames(), 1);
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
