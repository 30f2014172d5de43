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
//! The file is binary PLY with `double x, y, z` and `float intensity` ([`write_ply_f64`]).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use nalgebra::{Point3, Vector3};

use super::formats::write_ply_f64;
use crate::atomic_file::AtomicWriter;
use crate::geometry::voxel::{validate_voxel, voxel_downsample};
use crate::kitti::sequence::{Frame, Sequence};

#[derive(Debug, Clone, clap::Args)]
pub struct MapArgs {
    #[command(subcommand)]
    pub command: MapCommand,
}

#[derive(Debug, Clone, clap::Subcommand)]
pub enum MapCommand {
    /// Fuse a KITTI-layout sequence's scans with its poses into one map file (binary PLY, double
    /// x, y, z + float intensity), in the LiDAR frame of the first pose (z up).
    Build(BuildArgs),
}

#[derive(Debug, Clone, clap::Args)]
pub struct BuildArgs {
    /// The sequence directory (calib.txt, poses.txt or --poses, velodyne/).
    #[arg(long)]
    pub sequence: PathBuf,
    /// The poses file when not `<sequence>/poses.txt` (real KITTI's `poses/NN.txt`).
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Output map file (.ply).
    #[arg(long)]
    pub out: PathBuf,
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
#[derive(Debug, Clone, Copy)]
pub struct BuildSummary {
    pub frames: usize,
    pub fused_points: usize,
    pub written_points: usize,
    pub seconds: f64,
}

/// Fuses the selected frames and writes the map file (atomically).
pub fn build(args: &BuildArgs) -> Result<BuildSummary> {
    let started = Instant::now();
    if args.step == 0 {
        bail!("--step must be at least 1");
    }
    if let Some(v) = args.voxel_m {
        validate_voxel(v).map_err(anyhow::Error::msg)?;
    }
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
    let mut out = AtomicWriter::create(&args.out)?;
    let points = xyz.iter().zip(&intensity).map(|(p, &i)| ([p[0] as f64 + offset.x, p[1] as f64 + offset.y, p[2] as f64 + offset.z], i));
    write_ply_f64(&mut out, xyz.len(), points).with_context(|| format!("writing {}", args.out.display()))?;
    out.commit()?;
    Ok(BuildSummary { frames: frames.len(), fused_points, written_points: xyz.len(), seconds: started.elapsed().as_secs_f64() })
}

pub fn run(args: MapArgs) -> Result<()> {
    match args.command {
        MapCommand::Build(b) => {
            let s = build(&b)?;
            eprintln!(
                "{}: {} frames, {} points fused, {} written, {:.1} s",
                b.out.display(),
                s.frames,
                s.fused_points,
                s.written_points,
                s.seconds
            );
            Ok(())
        }
    }
}
