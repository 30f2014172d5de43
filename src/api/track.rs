//! `cmr-agent track`: follows a KITTI-layout drive in a stored map region, frame after frame,
//! through the server's own localize path ([`OfflineLocalizer`], the one `cmr-agent localize`
//! uses), and writes the trajectory, its errors, latencies and a plot (`track::output`).
//!
//! The region is a stored one (`--id` in the `--maps` store, e.g. written by `cmr-agent map build
//! --store`) or a point-cloud file (`--map`, as `cmr-agent localize --map`). The map frame is the
//! sequence's (`kitti::Sequence::map_from_lidar`: the LiDAR at frame 0), so the region must be
//! in that frame, e.g. built from the same drive's scans.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use bytes::Bytes;

use crate::geometry::Pose;
use crate::geometry::pose::Matrix4x4;
use crate::kitti::{Frame, Sequence};
use crate::maps::{MapError, MapStore};
use crate::agent::AxisStarts;
use crate::serving::request::AxisStartsBody;
use crate::serving::{ImagePayload, IntrinsicsBody, LocalizeError, LocalizeRequest};
use crate::track::output::{OdometrySource, TrackRun};
use crate::track::{FrameAnswer, FrameLocalizer, Odometry, SearchSize, TrackConfig, coarse_prior, cold_reference, spread, track};

use super::config::EngineArgs;
use super::offline::{FILE_REGION_ID, OfflineLocalizer, map_file_name};

#[derive(Debug, Clone, clap::Args)]
#[command(group(clap::ArgGroup::new("region").required(true).args(["id", "map"])))]
pub struct TrackArgs {
    /// Map region id in the `--maps` store (written by `cmr-agent map build --store DIR --id ID`,
    /// or uploaded to a server serving that directory). The region must be in the sequence's map
    /// frame: the LiDAR's frame at frame 0.
    #[arg(long)]
    pub id: Option<String>,
    /// The map store `--id` is read from: the directory `serve --maps` serves. It must exist
    /// (it is not created).
    #[arg(long, env = "CMR_MAPS", default_value = "maps")]
    pub maps: PathBuf,
    /// Instead of `--id`: a point-cloud file as the region (KITTI .bin, PCD, PLY, LAS/LAZ, e.g.
    /// `map build --out`'s), registered as an upload would be, with `<stem>.json` beside it as
    /// its metadata when present (as `cmr-agent localize --map`).
    #[arg(long)]
    pub map: Option<PathBuf>,
    /// A KITTI-layout sequence directory (calib.txt, poses.txt, image_2/, velodyne/).
    #[arg(long)]
    pub sequence: PathBuf,
    /// Where the trajectory files, summary, CSV and plot go (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// First frame (file index) of the drive.
    #[arg(long, default_value_t = 0)]
    pub first: usize,
    /// Frames to follow (default: to the end of the sequence).
    #[arg(long)]
    pub frames: Option<usize>,
    /// The first frame's prior is the truth with the camera moved this far (metres, ground plane,
    /// direction drawn from --seed) ...
    #[arg(long, default_value_t = 5.0)]
    pub prior_noise_m: f64,
    /// ... and turned this much (degrees about the vertical, sign drawn from --seed).
    #[arg(long, default_value_t = 30.0)]
    pub prior_noise_deg: f64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Starts of a tracked frame's search (from the constant-velocity prediction).
    #[arg(long, default_value_t = 1)]
    pub tracked_hypotheses: u32,
    /// Policy steps of a tracked frame's search.
    #[arg(long, default_value_t = 3)]
    pub tracked_iterations: u32,
    /// A tracked answer whose confidence score is below this is redone with the full search
    /// (`--default-hypotheses` starts, `--default-max-iterations` steps) from the same prior.
    #[arg(long, default_value_t = 0.3)]
    pub fallback_below: f32,
    /// Starts of a tracked frame's search also from the prediction moved forward and back along
    /// its optical axis, each way (0 = the prediction alone; the request's `axis_starts`); the
    /// answer scoring highest is kept (docs/tracking.md, "Starts along the optical axis").
    /// `--tracked-hypotheses` × (2·this + 1) may not exceed 16.
    #[arg(long, env = "CMR_TRACK_AXIS_STARTS", default_value_t = 2)]
    pub tracked_axis_starts: u32,
    /// Their spacing, metres (0.1..=10).
    #[arg(long, env = "CMR_TRACK_AXIS_STEP_M", default_value_t = 1.25)]
    pub tracked_axis_step_m: f64,
    /// A start along the axis must outscore the prediction's own answer by more than this
    /// (alignment-score units, 0..=1).
    #[arg(long, env = "CMR_TRACK_AXIS_MARGIN", default_value_t = 0.005)]
    pub tracked_axis_margin: f32,
    /// Predict each frame with odometry instead of the constant-velocity model: `poses` (the
    /// sequence's own poses.txt, i.e. the truth: simulated odometry, with the noise below) or a
    /// file in poses.txt's layout (the camera-0 poses of the same frame indices, any origin; e.g.
    /// a wheel or visual odometry's track). A dead-reckoned frame then follows it too.
    #[arg(long, value_name = "poses|FILE")]
    pub odometry: Option<String>,
    /// Noise added to every odometry step: the translation's scale error, percent (standard
    /// deviation; drawn from --seed).
    #[arg(long, default_value_t = 0.0, requires = "odometry")]
    pub odometry_noise_pct: f64,
    /// ... and a heading error per step, degrees (standard deviation).
    #[arg(long, default_value_t = 0.0, requires = "odometry")]
    pub odometry_noise_deg: f64,
    /// After tracking, localize this many frames (spread over the drive) cold: the full search
    /// from a coarse prior, for the summary's latency and accuracy comparison.
    #[arg(long, default_value_t = 0)]
    pub cold_reference: usize,
    /// The localize path's settings (models, limits, search defaults), as `serve` takes them.
    #[command(flatten)]
    pub engine: EngineArgs,
}

/// Localizes frames of one sequence in one stored region through [`OfflineLocalizer`].
struct StoredRegion<'a> {
    offline: &'a OfflineLocalizer,
    id: &'a str,
    frames: &'a [Frame],
}

impl FrameLocalizer for StoredRegion<'_> {
    /// `Ok(None)` for a request the localize path refuses for its values (`LocalizeError::Invalid`,
    /// the server's 422: in a drive, a prior or a start along its axis outside the region or with
    /// too few points around it), logged as a warning.
    fn localize(&mut self, position: usize, prior: &Pose, search: SearchSize, axis: AxisStarts) -> Result<Option<FrameAnswer>> {
        let frame = &self.frames[position];
        let bytes = std::fs::read(&frame.image_path).with_context(|| format!("reading {}", frame.image_path.display()))?;
        let k = frame.intrinsics;
        let request = LocalizeRequest {
            image: String::new(),
            intrinsics: IntrinsicsBody { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy },
            prior_camera_from_map: Some(Matrix4x4::from_rows(prior.to_rows())),
            max_iterations: Some(search.max_iterations),
            hypotheses: Some(search.hypotheses),
            radius_m: None,
            prior_bound: None,
            // Without starts along the axis (a full search), the engine's `--axis-starts` default.
            axis_starts: (axis.each_way > 0).then_some(AxisStartsBody { each_way: axis.each_way as u32, step_m: Some(axis.step_m), margin: Some(axis.margin as f64) }),
        };
        let started = std::time::Instant::now();
        let done = match self.offline.localize(self.id, &request, ImagePayload::Raw(Bytes::from(bytes))) {
            Ok(done) => done,
            Err(LocalizeError::Invalid(why)) => {
                tracing::warn!(frame = frame.index, "refused: {why}");
                return Ok(None);
            }
            Err(e) => bail!("frame {} ({}): {e}", frame.index, frame.image_path.display()),
        };
        let latency_ms = crate::agent::ms(started);
        let loc = &done.localization;
        Ok(Some(FrameAnswer {
            camera_from_map: loc.camera_from_map(),
            confidence: loc.confidence.score,
            alignment: loc.confidence.alignment,
            verdict: loc.verdict,
            iterations: loc.answer_steps().len(),
            axis_shift_m: loc.best().start_axis_shift_m,
            latency_ms,
        }))
    }
}

pub fn run(args: TrackArgs) -> Result<()> {
    let sequence = Sequence::open(&args.sequence, None)?;
    if sequence.poses.is_none() {
        bail!("{}: no poses.txt; tracking needs the truth for the first prior and the errors", args.sequence.display());
    }
    let file_indices: Vec<usize> = sequence
        .frame_indices
        .iter()
        .copied()
        .filter(|&i| i >= args.first)
        .take(args.frames.unwrap_or(usize::MAX))
        .collect();
    if file_indices.is_empty() {
        bail!("{}: no frames from {} on", args.sequence.display(), args.first);
    }
    let tracked = crate::agent::SearchTuning { axis_starts: args.tracked_axis_starts, ..args.engine.search };
    tracked.check(args.tracked_hypotheses).map_err(|e| anyhow!("--tracked-hypotheses and --tracked-axis-starts: {e} per tracked frame"))?;
    let frames = file_indices.iter().map(|&i| sequence.frame(i)).collect::<Result<Vec<_>>>()?;
    let truth = file_indices.iter().map(|&i| sequence.camera_from_map(i)).collect::<Result<Vec<_>>>()?;
    let odometry = odometry(&args, &file_indices, &truth)?;
    let config = TrackConfig {
        tracked: SearchSize { hypotheses: args.tracked_hypotheses, max_iterations: args.tracked_iterations },
        full: SearchSize { hypotheses: args.engine.default_hypotheses, max_iterations: args.engine.default_max_iterations },
        fallback_below: args.fallback_below,
        axis_starts: args.tracked_axis_starts,
        axis_step_m: args.tracked_axis_step_m,
        axis_margin: args.tracked_axis_margin,
    };

    let (offline, id, name) = match (&args.map, &args.id) {
        (Some(file), _) => (OfflineLocalizer::with_map_file(&args.engine, file)?, FILE_REGION_ID.to_string(), map_file_name(file)),
        (None, Some(id)) => {
            let store = open_store(&args.maps, id)?;
            (OfflineLocalizer::new(&args.engine, store)?, id.clone(), id.clone())
        }
        (None, None) => bail!("give --id ID (a region in the --maps store) or --map FILE"),
    };
    let entry = offline.localizer.maps.store.get(&id).map_err(|e| anyhow!("map {name}: {e}"))?;
    // Prepare the region's embeddings before the clock of the first frame starts.
    let map = offline.localizer.maps.prepared_for(&entry).map_err(|e| anyhow!("map {name}: {e}"))?;

    let mut region = StoredRegion { offline: &offline, id: &id, frames: &frames };
    let first_prior = coarse_prior(&truth[0], args.prior_noise_m, args.prior_noise_deg, args.seed);
    let tracked = track(&mut region, frames.len(), first_prior, odometry.as_ref().map(|(o, _)| o), &config, |f| {
        let c = f.estimate.camera_position_in_map();
        let gt = truth[f.position].camera_position_in_map();
        tracing::info!(
            frame = file_indices[f.position],
            mode = f.mode.name(),
            confidence = format!("{:.2}", f.confidence),
            error_m = format!("{:.3}", (c - gt).norm()),
            latency_ms = format!("{:.1}", f.latency_ms),
            "tracked"
        );
    })?;
    let cold = cold_reference(&mut region, &spread(frames.len(), args.cold_reference), &truth, args.prior_noise_m, args.prior_noise_deg, args.seed ^ 0xC01D, &config)?;
    drop(region);
    drop(offline);

    let run = TrackRun {
        sequence: &sequence,
        map_id: &name,
        file_indices: &file_indices,
        frames: &tracked,
        truth: &truth,
        cold: &cold,
        config,
        prior_noise_m: args.prior_noise_m,
        prior_noise_deg: args.prior_noise_deg,
        seed: args.seed,
        odometry: odometry.as_ref().map(|(o, source)| (o, source.clone())),
    };
    // The plot's points, map frame (stored relative to the region's origin).
    let (local, _) = map.drawing_sample(40_960);
    let frame = entry.frame();
    let points: Vec<[f32; 3]> = local.iter().map(|&p| frame.point_to_map(p).map(|v| v as f32)).collect();
    let summary = run.write(&args.out, &points)?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}

/// `--odometry`'s poses for the drive's frames (camera_from_odom of image_2), with its noise, or
/// `None` without it. Errors: a file that is unreadable, or lacks a line for a frame of the drive.
fn odometry(args: &TrackArgs, file_indices: &[usize], truth: &[Pose]) -> Result<Option<(Odometry, OdometrySource)>> {
    let Some(source) = &args.odometry else { return Ok(None) };
    for (flag, value) in [("--odometry-noise-pct", args.odometry_noise_pct), ("--odometry-noise-deg", args.odometry_noise_deg)] {
        if !(value.is_finite() && value >= 0.0) {
            bail!("{flag} {value}: give a standard deviation of 0 or more");
        }
    }
    let poses = if source == "poses" {
        truth.to_vec()
    } else {
        // The file read as the sequence's poses.txt would be: the same rig, the same conversion.
        let own = Sequence::open(&args.sequence, Some(Path::new(source))).with_context(|| format!("--odometry {source}"))?;
        file_indices.iter().map(|&i| own.camera_from_map(i)).collect::<Result<Vec<_>>>().with_context(|| format!("--odometry {source}"))?
    };
    // Its own stream of draws: the first prior's seed stays the one without odometry.
    let odometry = Odometry::new(poses).with_noise(args.odometry_noise_pct, args.odometry_noise_deg, args.seed ^ 0x0D0);
    Ok(Some((odometry, OdometrySource { source: source.clone(), noise_pct: args.odometry_noise_pct, noise_deg: args.odometry_noise_deg })))
}

/// The existing map store `dir` holding region `id`. Errors: the directory does not exist
/// (a mistyped `--maps` is not created), or it has no region `id` (the message lists those it
/// has).
fn open_store(dir: &Path, id: &str) -> Result<MapStore> {
    if !dir.is_dir() {
        bail!(
            "--maps {}: no such directory; give the map store that `serve --maps` serves, or write a region into one with `cmr-agent map build --sequence DIR --store DIR --id {id}`",
            dir.display()
        );
    }
    let (store, warnings) = MapStore::open(dir).map_err(|e| anyhow!("{e}"))?;
    for w in warnings {
        tracing::warn!("map store: {w}");
    }
    match store.get(id) {
        Ok(_) => Ok(store),
        Err(MapError::NotFound(_)) => {
            let ids = store.ids();
            let has = if ids.is_empty() { "it holds no regions".to_string() } else { format!("its regions: {}", ids.join(", ")) };
            bail!("no map named {id:?} in {} ({has}); `cmr-agent map build --sequence DIR --store {} --id ID` writes one", dir.display(), dir.display())
        }
        Err(e) => Err(anyhow!("map {id}: {e}")),
    }
}
