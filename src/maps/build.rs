//! `cmr-agent map build`: fuses the LiDAR scans of a KITTI-layout sequence (real KITTI odometry,
//! or `cmr-agent synth`'s drives) with its poses into one map region file that an upload accepts.
//!
//! The map frame: KITTI's poses are world_from_cam0 (camera 0's frame: x right, y **down**, z
//! forward, of the first frame), but the point encoder and the tiling want a z-up frame, so the
//! map frame is the **LiDAR frame of the first pose**: map_from_lidar_i = Tr⁻¹ · pose_i · Tr
//! (Tr = cam0_from_velo from calib.txt; for KITTI, pose_0 = I). A frame's true camera_from_map
//! is then camera_from_lidar · (map_from_lidar_i)⁻¹ ([`camera_from_map`]). `--offset` adds a
//! translation (e.g. a UTM easting, northing and height) to every point, in float64.
//!
//! It writes a binary PLY file with `double x, y, z` and `float intensity` ([`write_ply_f64`],
//! `--out`), and/or the region itself into a map store (`--store DIR --id ID`): those PLY bytes
//! taken exactly as `PUT /v1/maps/{id}` takes an upload ([`super::ingest`], then
//! [`MapStore::stage`] and [`MapStore::commit`], atomic), with metadata naming the drive and
//! the first frame's camera as the region's `initial_camera_from_map`. `serve --maps DIR` and
//! `track --maps DIR --id ID` read it as they read an uploaded region; its embeddings are
//! computed the first time either prepares it.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, anyhow, bail};
use nalgebra::{Point3, Vector3};

use super::formats::{CloudFormat, write_ply_f64};
use super::{MapEntry, MapMetadata, MapStore, RegionConfig, Upload, UploadOptions, validate_id};
use crate::atomic_file::{AtomicWriter, write_atomic};
use crate::geometry::Pose;
use crate::geometry::voxel::{validate_voxel, voxel_downsample};
use crate::kitti::sequence::{Frame, Sequence};

#[derive(Debug, Clone, clap::Args)]
pub struct MapArgs {
    #[command(subcommand)]
    pub command: MapCommand,
}

#[derive(Debug, Clone, clap::Subcommand)]
pub enum MapCommand {
    /// Fuse a KITTI-layout sequence's scans with its poses into one map region, in the LiDAR
    /// frame of the first pose (z up): a map file (`--out`, binary PLY) and/or a region in a map
    /// store (`--store DIR --id ID`) that `serve` and `track` read by id.
    Build(BuildArgs),
}

#[derive(Debug, Clone, clap::Args)]
#[command(group(clap::ArgGroup::new("destination").required(true).multiple(true).args(["out", "store"])))]
pub struct BuildArgs {
    /// The sequence directory (calib.txt, poses.txt or --poses, velodyne/).
    #[arg(long)]
    pub sequence: PathBuf,
    /// The poses file when not `<sequence>/poses.txt` (real KITTI's `poses/NN.txt`).
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Write the fused cloud to this file: binary PLY (double x, y, z + float intensity), so its
    /// name must end in `.ply`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write the region into this map store (the directory `serve --maps` serves and
    /// `track --maps` reads; created if missing) as region `--id`, stored exactly as
    /// `PUT /v1/maps/{id}` stores the PLY file. A region with that id is replaced.
    #[arg(long, requires = "id")]
    pub store: Option<PathBuf>,
    /// The region's id in `--store`: 1-64 characters of a-z, 0-9, '_' or '-', starting with a
    /// letter or digit.
    #[arg(long, requires = "store")]
    pub id: Option<String>,
    /// The region's description in `--store` (default: the sequence and frames it was built from).
    #[arg(long, requires = "store")]
    pub description: Option<String>,
    /// Most points the region in `--store` may hold (after `--voxel-m`), as `serve
    /// --max-map-points` bounds an upload; more is an error (use --voxel-m or --step).
    #[arg(long, default_value_t = RegionConfig::default().max_points)]
    pub max_map_points: usize,
    /// Voxel downsampling of the fused cloud: one centroid per cube of this side, metres.
    #[arg(long)]
    pub voxel_m: Option<f64>,
    /// Use every K-th frame (frames 0, K, 2K, ...): the others are held out.
    #[arg(long, default_value_t = 1)]
    pub step: usize,
    /// Use at most this many frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Drop returns farther than this from their sensor, metres.
    #[arg(long)]
    pub max_range_m: Option<f32>,
    /// Added to every point (map frame), metres: `x,y,z`, e.g. `500000,5400000,100`.
    #[arg(long, value_parser = parse_offset)]
    pub offset: Option<[f64; 3]>,
}

fn parse_offset(text: &str) -> Result<[f64; 3], String> {
    let values: Vec<f64> = text.split(',').map(|v| v.trim().parse::<f64>().map_err(|e| format!("{e} in {text:?}"))).collect::<Result<_, _>>()?;
    match values.as_slice() {
        [x, y, z] if values.iter().all(|v| v.is_finite()) => Ok([*x, *y, *z]),
        _ => Err(format!("{text:?}: give x,y,z in metres")),
    }
}

/// What a build made.
#[derive(Debug, Clone)]
pub struct BuildSummary {
    pub frames: usize,
    pub fused_points: usize,
    pub written_points: usize,
    /// The region written into `--store`, and whether it replaced one with the same id.
    pub stored: Option<(MapEntry, bool)>,
    pub seconds: f64,
}

/// The checks made before any scan is read. Errors: a zero `--step`, a voxel size out of range,
/// an `--out` not named `.ply`, an invalid `--id`.
fn check_args(args: &BuildArgs) -> Result<()> {
    if args.step == 0 {
        bail!("--step must be at least 1");
    }
    if let Some(v) = args.voxel_m {
        validate_voxel(v).map_err(anyhow::Error::msg)?;
    }
    if let Some(out) = &args.out {
        let named = out.extension().and_then(|e| e.to_str()).and_then(CloudFormat::from_extension);
        if named != Some(CloudFormat::Ply) {
            bail!(
                "--out {}: map build writes binary PLY (double x, y, z + float intensity), which a reader would not take for {}; name the file *.ply, or write a region that `serve` and `track` read by id with --store DIR --id ID",
                out.display(),
                match out.extension().and_then(|e| e.to_str()) {
                    Some(ext) => format!("a .{ext} file"),
                    None => "a file without an extension".to_string(),
                }
            );
        }
    }
    if let Some(id) = &args.id {
        validate_id(id).map_err(|e| anyhow!("--id: {e}"))?;
    }
    Ok(())
}

/// Fuses the selected frames and writes the map file and/or the stored region (each atomically).
/// Errors: [`check_args`]'s, an unreadable sequence, no frames, a cloud the store refuses (e.g.
/// more than `--max-map-points` points), I/O.
pub fn build(args: &BuildArgs) -> Result<BuildSummary> {
    let started = Instant::now();
    check_args(args)?;
    let sequence = Sequence::open(&args.sequence, args.poses.as_deref())?;
    if sequence.poses.is_none() {
        bail!("{}: no poses.txt (pass --poses for real KITTI's poses/NN.txt)", args.sequence.display());
    }
    let frames: Vec<Frame> = sequence.frames()?.into_iter().step_by(args.step).take(args.max_frames.unwrap_or(usize::MAX)).collect();
    if frames.is_empty() {
        bail!("{}: no frames selected", args.sequence.display());
    }
    let mut xyz: Vec<[f32; 3]> = Vec::new();
    let mut intensity: Vec<f32> = Vec::new();
    for frame in &frames {
        let pose = sequence.map_from_lidar(frame.index)?;
        for p in frame.read_points()? {
            if args.max_range_m.is_some_and(|r| p.x * p.x + p.y * p.y + p.z * p.z > r * r) {
                continue;
            }
            let q = pose.transform(&Point3::new(p.x as f64, p.y as f64, p.z as f64));
            xyz.push([q.x as f32, q.y as f32, q.z as f32]);
            intensity.push(p.intensity);
        }
    }
    let fused_points = xyz.len();
    let (xyz, intensity) = match args.voxel_m {
        Some(v) => {
            let (x, i) = voxel_downsample(&xyz, Some(&intensity), v);
            (x, i.unwrap_or_default())
        }
        None => (xyz, intensity),
    };
    let offset = Vector3::from(args.offset.unwrap_or([0.0; 3]));
    let points = || xyz.iter().zip(&intensity).map(|(p, &i)| ([p[0] as f64 + offset.x, p[1] as f64 + offset.y, p[2] as f64 + offset.z], i));
    let stored = match (&args.store, &args.id) {
        (Some(dir), Some(id)) => {
            let mut ply = Vec::with_capacity(300 + xyz.len() * 28);
            write_ply_f64(&mut ply, xyz.len(), points())?;
            if let Some(out) = &args.out {
                write_atomic(out, &ply).with_context(|| format!("writing {}", out.display()))?;
            }
            // The first camera in the map frame the points are written in (moved by --offset).
            let first = sequence.camera_from_map(frames[0].index)?;
            let first = if args.offset.is_some() { first.compose(&Pose::from_rt(nalgebra::Matrix3::identity(), -offset)) } else { first };
            let metadata = MapMetadata {
                description: Some(args.description.clone().unwrap_or_else(|| description(args, &frames))),
                initial_camera_from_map: Some(first.to_rows()),
                source: Some(source(args, &frames)),
            };
            Some(store_region(dir, id, &ply, metadata, args.max_map_points)?)
        }
        _ => {
            let out = args.out.as_ref().expect("clap requires --out or --store");
            let mut file = AtomicWriter::create(out)?;
            write_ply_f64(&mut file, xyz.len(), points()).with_context(|| format!("writing {}", out.display()))?;
            file.commit()?;
            None
        }
    };
    Ok(BuildSummary { frames: frames.len(), fused_points, written_points: xyz.len(), stored, seconds: started.elapsed().as_secs_f64() })
}

/// Stores the PLY bytes `ply` as region `id` of the store in `dir` (created if missing), as
/// `PUT /v1/maps/{id}` would store them: [`super::ingest`] (default origin, no voxel), then
/// stage and commit with `metadata`, each file atomic. No `<id>.emb` is written (it depends on the
/// model set): `serve` and `track` write it when they first prepare the region (a tiled region's
/// cell table and points, about a second for 2.5 M points). Returns the entry and whether it
/// replaced a region.
fn store_region(dir: &Path, id: &str, ply: &[u8], metadata: MapMetadata, max_points: usize) -> Result<(MapEntry, bool)> {
    let (store, warnings) = MapStore::open(dir).map_err(|e| anyhow!("{e}"))?;
    for w in warnings {
        tracing::warn!("map store: {w}");
    }
    let upload = Upload { bytes: ply, format: Some(CloudFormat::Ply), gzip: false, max_bytes: usize::MAX };
    let (cloud, frame) = super::ingest(id, upload, UploadOptions::default(), max_points).map_err(|e| anyhow!("region {id}: {e}"))?;
    let replaced = store.get(id).is_ok();
    let staged = store.stage(id, &cloud, frame).map_err(|e| anyhow!("region {id}: {e}"))?;
    let entry = store.commit(id, staged, None, Some(metadata)).map_err(|e| anyhow!("region {id}: {e}"))?;
    Ok((entry, replaced))
}

/// The default description of a stored region.
fn description(args: &BuildArgs, frames: &[Frame]) -> String {
    format!(
        "cmr-agent map build of {}: {} frames ({}..={}, every {})",
        args.sequence.display(),
        frames.len(),
        frames[0].index,
        frames[frames.len() - 1].index,
        args.step
    )
}

/// The stored region's `source` metadata: what it was built from and with which options.
fn source(args: &BuildArgs, frames: &[Frame]) -> serde_json::Value {
    serde_json::json!({
        "built_by": "cmr-agent map build",
        "sequence": args.sequence.display().to_string(),
        "poses": args.poses.as_ref().map(|p| p.display().to_string()),
        "frames": {"first": frames[0].index, "last": frames[frames.len() - 1].index, "count": frames.len(), "step": args.step},
        "voxel_m": args.voxel_m,
        "max_range_m": args.max_range_m,
        "offset": args.offset,
    })
}

pub fn run(args: MapArgs) -> Result<()> {
    match args.command {
        MapCommand::Build(b) => {
            let s = build(&b)?;
            let mut wrote = Vec::new();
            if let Some(out) = &b.out {
                wrote.push(out.display().to_string());
            }
            if let (Some((entry, replaced)), Some(dir)) = (&s.stored, &b.store) {
                wrote.push(format!("region {:?} in {} ({}, origin {:?})", entry.id, dir.display(), if *replaced { "replaced" } else { "new" }, entry.origin));
            }
            eprintln!("{}: {} frames, {} points fused, {} written, {:.1} s", wrote.join(" and "), s.frames, s.fused_points, s.written_points, s.seconds);
            Ok(())
        }
    }
}
