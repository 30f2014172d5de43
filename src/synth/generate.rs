//! From a seed to KITTI-odometry sequences on disk: plan each sequence (street, style, path),
//! then render and scan every frame in parallel, writing each file atomically.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::lidar::{scan, LidarConfig};
use super::noise::hash;
use super::render::{render, CameraView, Lighting, Rendered};
use super::rig::{calibration, Trajectory};
use super::scene::{build_street, Scene};
use super::style::{Style, StyleOverrides, StylePreset};
use crate::geometry::Pose;
use crate::atomic_file::write_atomic;
use crate::kitti::{write_poses, write_velodyne, Calib, LidarPoint};

/// Bumped whenever the same flags would produce different bytes.
pub const GENERATOR_VERSION: &str = "cmr-agent-synth/1";

/// Everything that determines the output bytes.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct GeneratorConfig {
    pub seed: u64,
    pub sequences: usize,
    /// Index of the first sequence (directory names continue from here).
    pub first_sequence: usize,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    /// Distance driven between frames.
    pub spacing_m: f64,
    pub lidar: LidarConfig,
    pub preset: StylePreset,
    pub overrides: StyleOverrides,
}

impl GeneratorConfig {
    pub fn validate(&self) -> Result<()> {
        if self.frames == 0 || self.sequences == 0 {
            bail!("need at least one sequence and one frame");
        }
        if self.width < 16 || self.height < 16 || self.width > 8192 || self.height > 8192 {
            bail!("image size {}x{} out of range (16..=8192 per side)", self.width, self.height);
        }
        if !(self.spacing_m > 0.0 && self.spacing_m <= 50.0) {
            bail!("frame spacing {} m must be within (0, 50]", self.spacing_m);
        }
        self.lidar.validate().map_err(anyhow::Error::msg)?;
        // Drawn values are always in range; this catches out-of-range overrides up front.
        Style::draw(self.preset, &self.overrides, &mut ChaCha8Rng::seed_from_u64(0)).validate().map_err(anyhow::Error::msg)
    }
}

/// One sequence, ready to render any frame on demand.
pub struct SequencePlan {
    pub index: usize,
    pub name: String,
    pub scene: Scene,
    pub style: Style,
    pub lighting: Lighting,
    pub trajectory: Trajectory,
    /// The calibration exactly as readers will parse it back from calib.txt.
    pub calib: Calib,
    pub seed: u64,
}

/// What one frame produces.
pub struct FrameOutput {
    pub rendered: Rendered,
    pub points: Vec<LidarPoint>,
    pub world_from_lidar: Pose,
}

/// Scene margin beyond the driven stretch: the LiDAR's range plus room for what the camera sees.
const SCENE_MARGIN_M: f32 = 110.0;

impl SequencePlan {
    pub fn new(config: &GeneratorConfig, index: usize) -> Result<Self> {
        let seed = hash(&[config.seed, index as u64, 0x5EC]);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let style = Style::draw(config.preset, &config.overrides, &mut rng);
        style.validate().map_err(anyhow::Error::msg)?;
        let length = config.spacing_m * config.frames.saturating_sub(1) as f64;
        let scene = build_street(&mut rng, (0.0, length as f32), SCENE_MARGIN_M, &style);
        let road = scene.street.road_half_width as f64;
        let driving_edge = if scene.street.parking { road - 2.2 } else { road };
        let lane_y = -driving_edge * 0.5;
        let trajectory = Trajectory {
            start_x: 0.0,
            spacing_m: config.spacing_m,
            lane_y,
            weave_amplitude_m: (driving_edge * 0.5 - 1.1).clamp(0.0, 0.9) * rng.random_range(0.3..1.0),
            weave_wavelength_m: rng.random_range(60.0..140.0),
            weave_phase: rng.random_range(0.0..std::f64::consts::TAU),
        };
        let written = calibration(config.width, config.height);
        let calib = Calib::parse(&written.to_text(), "generated calib.txt")?;
        Ok(SequencePlan {
            index,
            name: format!("{index:02}"),
            lighting: Lighting::from_style(&style),
            scene,
            style,
            trajectory,
            calib,
            seed,
        })
    }

    /// Renders and scans frame `i`; deterministic in (seed, sequence, frame).
    pub fn frame(&self, config: &GeneratorConfig, i: usize) -> Result<FrameOutput> {
        let world_from_lidar = self.trajectory.world_from_lidar(i);
        let camera_from_lidar = self.calib.color_camera_from_lidar()?;
        let view = CameraView {
            intrinsics: self.calib.color_intrinsics()?,
            width: config.width,
            height: config.height,
            world_from_camera: world_from_lidar.compose(&camera_from_lidar.inverse()),
        };
        let frame_seed = hash(&[self.seed, i as u64]);
        let rendered = render(&self.scene, &self.lighting, &view, frame_seed ^ 0xCA);
        let points = scan(&self.scene, &config.lidar, &world_from_lidar, frame_seed ^ 0x11);
        Ok(FrameOutput { rendered, points, world_from_lidar })
    }

    /// KITTI's ground truth: world_from_cam0 of every frame, relative to cam0 at frame 0.
    pub fn kitti_poses(&self, frames: usize) -> Vec<Pose> {
        let cam0_from_lidar = self.calib.velo_to_cam0;
        let world_from_cam0 = |i: usize| self.trajectory.world_from_lidar(i).compose(&cam0_from_lidar.inverse());
        let origin_inv = world_from_cam0(0).inverse();
        (0..frames).map(|i| origin_inv.compose(&world_from_cam0(i))).collect()
    }
}

/// The per-sequence record written to synth.json.
#[derive(Serialize)]
struct SequenceRecord<'a> {
    generator: &'a str,
    seed: u64,
    sequence: usize,
    sequence_seed: u64,
    frames: usize,
    image_size: [u32; 2],
    spacing_m: f64,
    lidar: &'a LidarConfig,
    style: &'a Style,
    overrides: &'a StyleOverrides,
    scene: SceneRecord,
    trajectory: &'a Trajectory,
}

#[derive(Serialize)]
struct SceneRecord {
    shapes: usize,
    road_half_width_m: f32,
    sidewalk_width_m: f32,
    parking_lanes: bool,
    side_streets: usize,
}

#[derive(Debug, Clone, Copy)]
pub struct GenerationSummary {
    pub frames: usize,
    pub seconds: f64,
    pub points: usize,
}

pub fn sequence_dir(out: &Path, plan: &SequencePlan) -> PathBuf {
    out.join(&plan.name)
}

/// Writes `config.sequences` sequences under `out`. Refuses to touch an existing non-empty
/// sequence directory unless `overwrite`.
pub fn generate(config: &GeneratorConfig, out: &Path, overwrite: bool, progress: bool) -> Result<GenerationSummary> {
    config.validate()?;
    let started = Instant::now();
    let plans: Vec<SequencePlan> = (config.first_sequence..config.first_sequence + config.sequences)
        .into_par_iter()
        .map(|i| SequencePlan::new(config, i))
        .collect::<Result<_>>()?;
    for plan in &plans {
        let dir = sequence_dir(out, plan);
        if dir.exists() && std::fs::read_dir(&dir)?.next().is_some() && !overwrite {
            bail!("{} already exists and is not empty (pass --overwrite to replace it)", dir.display());
        }
        for sub in ["velodyne", "image_2"] {
            std::fs::create_dir_all(dir.join(sub)).with_context(|| format!("creating {}", dir.join(sub).display()))?;
        }
        plan.calib.write(&dir.join("calib.txt"))?;
        write_poses(&dir.join("poses.txt"), &plan.kitti_poses(config.frames))?;
    }
    let jobs: Vec<(usize, usize)> = (0..plans.len()).flat_map(|s| (0..config.frames).map(move |f| (s, f))).collect();
    let bar = if progress { ProgressBar::new(jobs.len() as u64) } else { ProgressBar::hidden() };
    bar.set_style(ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} frames ({per_sec}, eta {eta})").unwrap());
    let points: usize = jobs
        .par_iter()
        .map(|&(s, f)| -> Result<usize> {
            let plan = &plans[s];
            let output = plan.frame(config, f)?;
            let dir = sequence_dir(out, plan);
            write_velodyne(&dir.join("velodyne").join(format!("{f:06}.bin")), &output.points)?;
            write_atomic(&dir.join("image_2").join(format!("{f:06}.png")), &encode_png(&output.rendered.image)?)?;
            bar.inc(1);
            Ok(output.points.len())
        })
        .collect::<Result<Vec<_>>>()?
        .into_iter()
        .sum();
    bar.finish_and_clear();
    for plan in &plans {
        let record = SequenceRecord {
            generator: GENERATOR_VERSION,
            seed: config.seed,
            sequence: plan.index,
            sequence_seed: plan.seed,
            frames: config.frames,
            image_size: [config.width, config.height],
            spacing_m: config.spacing_m,
            lidar: &config.lidar,
            style: &plan.style,
            overrides: &config.overrides,
            scene: SceneRecord {
                shapes: plan.scene.len(),
                road_half_width_m: plan.scene.street.road_half_width,
                sidewalk_width_m: plan.scene.street.sidewalk_width,
                parking_lanes: plan.scene.street.parking,
                side_streets: plan.scene.street.side_streets.len(),
            },
            trajectory: &plan.trajectory,
        };
        let json = serde_json::to_vec_pretty(&record)?;
        write_atomic(&sequence_dir(out, plan).join("synth.json"), &json)?;
    }
    Ok(GenerationSummary { frames: jobs.len(), seconds: started.elapsed().as_secs_f64(), points })
}

pub fn encode_png(image: &image::RgbImage) -> Result<Vec<u8>> {
    let mut bytes = Vec::new();
    image.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png).context("encoding PNG")?;
    Ok(bytes)
}
