//! The files of a tracked drive, written into one directory (each atomically):
//!
//! - `trajectory.kitti.txt`: the estimates as `poses.txt` lines (12 numbers, row-major 3×4 of
//!   world_from_cam0, world = cam0 at the sequence's frame 0), so they compare line by line with
//!   the sequence's own poses file (e.g. `evo_ape kitti poses.txt trajectory.kitti.txt`);
//! - `trajectory.tum.txt`: the same poses as `timestamp tx ty tz qx qy qz qw` (seconds from
//!   `times.txt`; when the sequence has none, frame index × 0.1 s, KITTI's 10 Hz);
//! - `frames.csv`: one row per frame: mode, confidences, latency, errors (see [`FrameRow`]);
//! - `summary.json`: [`Summary`];
//! - `track.png`: top view of the estimated and true camera centres over the map ([`super::plot`]).

use std::path::Path;

use anyhow::{Context, Result};
use serde::Serialize;

use super::metrics::{FrameError, TrajectoryError, frame_errors, trajectory_error};
use super::{ColdFrame, Mode, Odometry, TrackConfig, TrackedFrame};
use crate::atomic_file::write_atomic;
use crate::geometry::Pose;
use crate::kitti::{Sequence, format_kitti_number, poses::poses_to_text};

/// A tracked drive and what it is measured against.
pub struct TrackRun<'a> {
    pub sequence: &'a Sequence,
    pub map_id: &'a str,
    /// File index (the NNNNNN of the file names) of each position of the drive.
    pub file_indices: &'a [usize],
    pub frames: &'a [TrackedFrame],
    /// True camera_from_map per position.
    pub truth: &'a [Pose],
    pub cold: &'a [ColdFrame],
    pub config: TrackConfig,
    pub prior_noise_m: f64,
    pub prior_noise_deg: f64,
    pub seed: u64,
    /// The odometry the predictions followed, and how it was made (`None`: constant velocity).
    pub odometry: Option<(&'a Odometry, OdometrySource)>,
}

/// Where the odometry came from and the noise added to it (`track::Odometry::with_noise`).
#[derive(Debug, Clone, Serialize)]
pub struct OdometrySource {
    /// `poses` (the sequence's own poses.txt: the truth) or the file given.
    pub source: String,
    pub noise_pct: f64,
    pub noise_deg: f64,
}

/// The odometry beside the tracker: what it alone gives from the first frame's answer.
#[derive(Debug, Clone, Serialize)]
pub struct OdometrySummary {
    #[serde(flatten)]
    pub source: OdometrySource,
    /// The odometry's own motions chained from the first frame's answer, no registration after
    /// it (`Odometry::dead_reckoned`): the baseline the tracked frames have to beat.
    pub dead_reckoned: TrajectoryError,
}

/// One row of `frames.csv`.
#[derive(Debug, Serialize)]
pub struct FrameRow {
    pub position: usize,
    pub frame: usize,
    pub timestamp_s: f64,
    pub mode: &'static str,
    pub confidence: f32,
    /// The small search's confidence (empty for the first frame).
    pub tracked_confidence: Option<f32>,
    pub iterations: usize,
    pub latency_ms: f64,
    /// How far the search's start was from the truth (camera centres), metres.
    pub prior_error_m: f64,
    /// Where the small search's answer started along the prediction's optical axis, metres (empty for
    /// the first frame; `agent::AxisStarts::priors`).
    pub axis_shift_m: Option<f64>,
    pub position_error_m: f64,
    pub heading_error_deg: f64,
    pub rte_m: f64,
    pub rre_deg: f64,
    pub rpe_translation_m: Option<f64>,
    pub rpe_rotation_deg: Option<f64>,
    /// Camera centres in the map frame, metres.
    pub estimate_x: f64,
    pub estimate_y: f64,
    pub truth_x: f64,
    pub truth_y: f64,
    /// The kept answer's calibrated probability (empty without a calibrator) and verdict (for a
    /// dead-reckoned frame: the full search's, which was not localized).
    pub p_registered: Option<f64>,
    pub localized: bool,
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct ModeCounts {
    pub cold: usize,
    pub tracked: usize,
    pub fallback: usize,
    /// Frames neither search localized: the estimate is the prediction (constant velocity, or
    /// the odometry's motion).
    pub dead_reckoning: usize,
}

/// Per-frame latency, milliseconds (a fallback frame counts both of its searches).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct LatencySummary {
    /// Every frame after the first: what following the drive costs per frame.
    pub mean_per_frame_ms: f64,
    pub p50_per_frame_ms: f64,
    pub p95_per_frame_ms: f64,
    pub max_per_frame_ms: f64,
    /// Frames answered by the small search alone.
    pub mean_tracked_ms: Option<f64>,
    pub mean_fallback_ms: Option<f64>,
    /// The first frame (the full search from the coarse prior).
    pub first_frame_ms: f64,
}

/// Cold localizations (the full search from a coarse prior) of some frames of the same drive.
#[derive(Debug, Clone, Serialize)]
pub struct ColdSummary {
    pub positions: Vec<usize>,
    pub mean_latency_ms: f64,
    pub mean_position_error_m: f64,
    pub registration_recall: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub sequence: String,
    pub map_id: String,
    pub frames: usize,
    pub first_frame: usize,
    pub config: TrackConfig,
    pub prior_noise_m: f64,
    pub prior_noise_deg: f64,
    pub seed: u64,
    /// ATE / RPE, no alignment (see `track::metrics`).
    pub error: TrajectoryError,
    pub modes: ModeCounts,
    pub latency: LatencySummary,
    pub cold_reference: Option<ColdSummary>,
    /// With `--odometry`: its source, noise and its own errors from the first frame's answer.
    pub odometry: Option<OdometrySummary>,
    /// latency.mean_per_frame_ms / cold_reference.mean_latency_ms.
    pub tracked_to_cold_latency: Option<f64>,
    /// Where the TUM file's timestamps come from.
    pub timestamps: &'static str,
}

impl TrackRun<'_> {
    pub fn estimates(&self) -> Vec<Pose> {
        self.frames.iter().map(|f| f.estimate).collect()
    }

    pub fn errors(&self) -> Vec<FrameError> {
        frame_errors(&self.estimates(), self.truth)
    }

    /// Timestamps per position and their source.
    pub fn timestamps(&self) -> Result<(Vec<f64>, &'static str)> {
        Ok(match self.sequence.times()? {
            Some(times) => (self.file_indices.iter().map(|&i| times[i]).collect(), "times.txt"),
            None => (self.file_indices.iter().map(|&i| i as f64 * 0.1).collect(), "frame index x 0.1 s (no times.txt)"),
        })
    }

    pub fn summary(&self) -> Result<Summary> {
        let errors = self.errors();
        let count = |mode| self.frames.iter().filter(|f| f.mode == mode).count();
        let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
        let later: Vec<f64> = self.frames.iter().skip(1).map(|f| f.latency_ms).collect();
        let of_mode = |mode| -> Vec<f64> { self.frames.iter().filter(|f| f.mode == mode).map(|f| f.latency_ms).collect() };
        let mut sorted = later.clone();
        sorted.sort_by(f64::total_cmp);
        let quantile = |q: f64| if sorted.is_empty() { 0.0 } else { sorted[((sorted.len() - 1) as f64 * q).round() as usize] };
        let latency = LatencySummary {
            mean_per_frame_ms: mean(&later).unwrap_or(0.0),
            p50_per_frame_ms: quantile(0.5),
            p95_per_frame_ms: quantile(0.95),
            max_per_frame_ms: sorted.last().copied().unwrap_or(0.0),
            mean_tracked_ms: mean(&of_mode(Mode::Tracked)),
            mean_fallback_ms: mean(&of_mode(Mode::Fallback)),
            first_frame_ms: self.frames.first().map(|f| f.latency_ms).unwrap_or(0.0),
        };
        let cold_reference = (!self.cold.is_empty()).then(|| {
            let estimates: Vec<Pose> = self.cold.iter().map(|c| c.answer.camera_from_map).collect();
            let truth: Vec<Pose> = self.cold.iter().map(|c| self.truth[c.position]).collect();
            let e = trajectory_error(&frame_errors(&estimates, &truth));
            let latencies: Vec<f64> = self.cold.iter().map(|c| c.answer.latency_ms).collect();
            ColdSummary {
                positions: self.cold.iter().map(|c| c.position).collect(),
                mean_latency_ms: mean(&latencies).unwrap_or(0.0),
                mean_position_error_m: e.ate_mean_m,
                registration_recall: e.registration_recall,
            }
        });
        let odometry = match (self.odometry.as_ref(), self.frames.first()) {
            (Some((odometry, source)), Some(first)) => {
                let alone = odometry.dead_reckoned(&first.estimate);
                let n = self.frames.len().min(alone.len());
                Some(OdometrySummary { source: source.clone(), dead_reckoned: trajectory_error(&frame_errors(&alone[..n], &self.truth[..n])) })
            }
            _ => None,
        };
        let tracked_to_cold_latency = cold_reference.as_ref().filter(|c| c.mean_latency_ms > 0.0).map(|c| latency.mean_per_frame_ms / c.mean_latency_ms);
        Ok(Summary {
            sequence: self.sequence.dir.display().to_string(),
            map_id: self.map_id.to_string(),
            frames: self.frames.len(),
            first_frame: self.file_indices.first().copied().unwrap_or(0),
            config: self.config,
            prior_noise_m: self.prior_noise_m,
            prior_noise_deg: self.prior_noise_deg,
            seed: self.seed,
            error: trajectory_error(&errors),
            modes: ModeCounts { cold: count(Mode::Cold), tracked: count(Mode::Tracked), fallback: count(Mode::Fallback), dead_reckoning: count(Mode::DeadReckoning) },
            latency,
            cold_reference,
            odometry,
            tracked_to_cold_latency,
            timestamps: self.timestamps()?.1,
        })
    }

    pub fn rows(&self) -> Result<Vec<FrameRow>> {
        let errors = self.errors();
        let (times, _) = self.timestamps()?;
        Ok(self
            .frames
            .iter()
            .zip(&errors)
            .map(|(f, e)| {
                let truth = &self.truth[f.position];
                let (est_c, gt_c) = (f.estimate.camera_position_in_map(), truth.camera_position_in_map());
                FrameRow {
                    position: f.position,
                    frame: self.file_indices[f.position],
                    timestamp_s: times[f.position],
                    mode: f.mode.name(),
                    confidence: f.confidence,
                    tracked_confidence: f.tracked_confidence,
                    iterations: f.iterations,
                    latency_ms: f.latency_ms,
                    prior_error_m: (f.prior.camera_position_in_map() - gt_c).norm(),
                    axis_shift_m: f.axis_shift_m,
                    position_error_m: e.position_m,
                    heading_error_deg: e.heading_deg,
                    rte_m: e.pose.rte_m,
                    rre_deg: e.pose.rre_euler_deg,
                    rpe_translation_m: e.rpe_translation_m,
                    rpe_rotation_deg: e.rpe_rotation_deg,
                    estimate_x: est_c.x,
                    estimate_y: est_c.y,
                    truth_x: gt_c.x,
                    truth_y: gt_c.y,
                    p_registered: f.verdict.p_registered,
                    localized: f.verdict.localized,
                }
            })
            .collect())
    }

    /// The estimates as `poses.txt` lines (world_from_cam0).
    pub fn kitti_text(&self) -> Result<String> {
        let poses = self.estimates().iter().map(|p| self.sequence.world_from_cam0(p)).collect::<Result<Vec<_>>>()?;
        Ok(poses_to_text(&poses))
    }

    /// The estimates as TUM lines: `timestamp tx ty tz qx qy qz qw` of world_from_cam0.
    pub fn tum_text(&self) -> Result<String> {
        let (times, _) = self.timestamps()?;
        let mut text = String::new();
        for (pose, t) in self.estimates().iter().zip(&times) {
            let p = self.sequence.world_from_cam0(pose)?;
            let (v, q) = (p.0.translation.vector, p.0.rotation);
            let numbers = [*t, v.x, v.y, v.z, q.i, q.j, q.k, q.w];
            text.push_str(&numbers.iter().map(|x| format_kitti_number(*x)).collect::<Vec<_>>().join(" "));
            text.push('\n');
        }
        Ok(text)
    }

    /// Writes every file of the module doc into `out` (created if missing); `map_points` (map
    /// frame) are drawn under the trajectories.
    pub fn write(&self, out: &Path, map_points: &[[f32; 3]]) -> Result<Summary> {
        std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
        write_atomic(&out.join("trajectory.kitti.txt"), self.kitti_text()?.as_bytes())?;
        write_atomic(&out.join("trajectory.tum.txt"), self.tum_text()?.as_bytes())?;
        let mut csv = csv::Writer::from_writer(Vec::new());
        for row in self.rows()? {
            csv.serialize(row)?;
        }
        write_atomic(&out.join("frames.csv"), &csv.into_inner().map_err(|e| anyhow::anyhow!("{e}"))?)?;
        let summary = self.summary()?;
        let mut json = serde_json::to_vec_pretty(&summary)?;
        json.push(b'\n');
        write_atomic(&out.join("summary.json"), &json)?;
        super::plot::top_view(&out.join("track.png"), self, map_points)?;
        Ok(summary)
    }
}
