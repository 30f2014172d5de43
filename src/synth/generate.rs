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

use super::camera_fx::FrameFx;
use super::lidar::scan;
use super::look::{Look, LookMode};
use super::noise::hash;
use super::render::{render, render_with_effects, CameraView, Lighting, Rendered};
use super::rig::Rig;
use super::rigs::{random_rig, RigChoice};
use super::scene::{Ground, Scene};
use super::style::{Style, StyleOverrides, StylePreset};
use super::trajectory::Trajectory;
use super::worlds::{self, WorldKind};
use crate::geometry::Pose;
use crate::atomic_file::write_atomic;
use crate::kitti::{write_poses, write_velodyne, Calib, LidarPoint};

/// Bumped whenever the same flags would produce different bytes.
pub const GENERATOR_VERSION: &str = "cmr-agent-synth/2";
/// The version whose bytes `--world classic --look classic --rig kitti` still reproduces
/// (recorded by the shipped demo, which is made that way).
pub const CLASSIC_GENERATOR_VERSION: &str = "cmr-agent-synth/1";

/// Sensor settings given on the command line on top of the rig.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct SensorOverrides {
    /// Image size; the rig's intrinsics scale with it.
    pub image_size: Option<(u32, u32)>,
    /// Beam count, evenly spaced between the rig's top and bottom beams.
    pub lidar_beams: Option<u32>,
    pub lidar_columns: Option<u32>,
    /// Scales the (rig's or given) image size, intrinsics following; e.g. 0.5 for training
    /// sets, whose preprocessing halves every image of KITTI size or larger anyway.
    #[serde(default)]
    pub image_scale: Option<f64>,
}

/// Everything that determines the output bytes.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct GeneratorConfig {
    pub seed: u64,
    pub sequences: usize,
    /// Index of the first sequence (directory names continue from here).
    pub first_sequence: usize,
    pub frames: usize,
    /// Distance driven between frames, metres.
    pub spacing_m: f64,
    pub rig: RigChoice,
    pub sensor: SensorOverrides,
    /// `None`: each sequence draws its family from `worlds::DRAWN`.
    pub world: Option<WorldKind>,
    pub look: LookMode,
    pub preset: StylePreset,
    pub overrides: StyleOverrides,
}

impl GeneratorConfig {
    /// Today's generator: the kitti rig, the classic street and look, train style.
    pub fn classic(seed: u64, sequences: usize, frames: usize) -> Self {
        GeneratorConfig {
            seed,
            sequences,
            first_sequence: 0,
            frames,
            spacing_m: 2.5,
            rig: RigChoice::default(),
            sensor: SensorOverrides::default(),
            world: Some(WorldKind::Classic),
            look: LookMode::Classic,
            preset: StylePreset::Train,
            overrides: StyleOverrides::default(),
        }
    }

    /// The rig of a sequence with sequence seed `seed`, overrides applied.
    pub fn rig_for(&self, seed: u64) -> Rig {
        let mut rig = match &self.rig {
            RigChoice::Named(rig) => rig.clone(),
            RigChoice::Random => random_rig(&mut ChaCha8Rng::seed_from_u64(hash(&[seed, 0x816]))),
        };
        if let Some((w, h)) = self.sensor.image_size {
            rig = rig.with_image_size(w, h);
        }
        if let Some(scale) = self.sensor.image_scale {
            let (w, h) = (((rig.width as f64) * scale).round() as u32, ((rig.height as f64) * scale).round() as u32);
            rig = rig.with_image_size(w, h);
        }
        if let Some(beams) = self.sensor.lidar_beams {
            rig = rig.with_beams(beams);
        }
        if let Some(columns) = self.sensor.lidar_columns {
            rig.lidar.columns = columns;
        }
        rig
    }

    pub fn validate(&self) -> Result<()> {
        if self.frames == 0 || self.sequences == 0 {
            bail!("need at least one sequence and one frame");
        }
        if let Some(scale) = self.sensor.image_scale {
            if !(scale > 0.0 && scale <= 4.0) {
                bail!("image scale {scale} must be within (0, 4]");
            }
        }
        if !(self.spacing_m > 0.0 && self.spacing_m <= 50.0) {
            bail!("frame spacing {} m must be within (0, 50]", self.spacing_m);
        }
        self.rig_for(0).validate().map_err(anyhow::Error::msg)?;
        // Drawn values are always in range; this catches out-of-range overrides up front.
        Style::draw(self.preset, &self.overrides, &mut ChaCha8Rng::seed_from_u64(0)).validate().map_err(anyhow::Error::msg)
    }
}

/// One sequence, ready to render any frame on demand.
pub struct SequencePlan {
    pub index: usize,
    pub name: String,
    pub world: WorldKind,
    pub rig: Rig,
    pub scene: Scene,
    pub style: Style,
    /// `None` with `--look classic`.
    pub look: Option<Look>,
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
    /// The camera effects used (`--look random`).
    pub effects: Option<FrameFx>,
}

/// Scene margin beyond the driven stretch: the LiDAR's range plus room for what the camera sees.
const SCENE_MARGIN_M: f32 = 110.0;

impl SequencePlan {
    pub fn new(config: &GeneratorConfig, index: usize) -> Result<Self> {
        let seed = hash(&[config.seed, index as u64, 0x5EC]);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let style = Style::draw(config.preset, &config.overrides, &mut rng);
        style.validate().map_err(anyhow::Error::msg)?;
        let world = config.world.unwrap_or(worlds::DRAWN[(hash(&[seed, 0x3011D]) % worlds::DRAWN.len() as u64) as usize]);
        let rig = config.rig_for(seed);
        rig.validate().map_err(anyhow::Error::msg)?;
        let length = config.spacing_m * config.frames.saturating_sub(1) as f64;
        let built = worlds::build(world, &mut rng, (0.0, length as f32), SCENE_MARGIN_M, &style);
        let mut scene = built.scene;
        let trajectory = Trajectory {
            start_x: 0.0,
            spacing_m: config.spacing_m,
            lane_y: built.lane_y,
            weave_amplitude_m: built.weave_limit_m * rng.random_range(0.3..1.0),
            weave_wavelength_m: rng.random_range(60.0..140.0),
            weave_phase: rng.random_range(0.0..std::f64::consts::TAU),
            lidar_height_m: rig.lidar_height_m,
            terrain: scene.terrain.clone(),
        };
        let look = match config.look {
            LookMode::Classic => None,
            LookMode::Random => Some(Look::draw(&mut ChaCha8Rng::seed_from_u64(hash(&[seed, 0x100C])), &style, config.overrides.time_of_day_h.is_some())),
        };
        let lighting = look.as_ref().map_or_else(|| Lighting::from_style(&style), |l| l.lighting(&style));
        scene.textures = look.as_ref().map(|l| l.textures.clone());
        let calib = Calib::parse(&rig.calibration().to_text(), "generated calib.txt")?;
        Ok(SequencePlan { index, name: format!("{index:02}"), world, rig, lighting, look, scene, style, trajectory, calib, seed })
    }

    /// Renders and scans frame `i`; deterministic in (seed, sequence, frame).
    pub fn frame(&self, i: usize) -> Result<FrameOutput> {
        let world_from_lidar = self.trajectory.world_from_lidar(i);
        let camera_from_lidar = self.calib.color_camera_from_lidar()?;
        let view = CameraView {
            intrinsics: self.calib.color_intrinsics()?,
            width: self.rig.width,
            height: self.rig.height,
            world_from_camera: world_from_lidar.compose(&camera_from_lidar.inverse()),
        };
        let frame_seed = hash(&[self.seed, i as u64]);
        let (rendered, effects) = if self.look.is_some() {
            let fx = FrameFx::draw(frame_seed ^ 0xF0, self.rig.width as f32 / 1241.0);
            (render_with_effects(&self.scene, &self.lighting, &view, frame_seed ^ 0xCA, &fx)?, Some(fx))
        } else {
            (render(&self.scene, &self.lighting, &view, frame_seed ^ 0xCA), None)
        };
        let points = scan(&self.scene, &self.rig.lidar, &world_from_lidar, frame_seed ^ 0x11);
        Ok(FrameOutput { rendered, points, world_from_lidar, effects })
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
    world: WorldKind,
    rig: &'a Rig,
    look: &'a Option<Look>,
    style: &'a Style,
    overrides: &'a StyleOverrides,
    scene: SceneRecord<'a>,
    trajectory: &'a Trajectory,
}

#[derive(Serialize)]
struct SceneRecord<'a> {
    shapes: usize,
    /// The classic street's layout.
    #[serde(skip_serializing_if = "Option::is_none")]
    street: Option<StreetRecord>,
    /// Any other world's road paint and shape.
    #[serde(skip_serializing_if = "Option::is_none")]
    road: Option<&'a super::paint::RoadPaint>,
    #[serde(skip_serializing_if = "Option::is_none")]
    road_shape: Option<&'a super::terrain::RoadShape>,
}

#[derive(Serialize)]
struct StreetRecord {
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
            let output = plan.frame(f)?;
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
            image_size: [plan.rig.width, plan.rig.height],
            spacing_m: config.spacing_m,
            world: plan.world,
            rig: &plan.rig,
            look: &plan.look,
            style: &plan.style,
            overrides: &config.overrides,
            scene: SceneRecord {
                shapes: plan.scene.len(),
                street: match &plan.scene.ground {
                    Ground::Street(street) => Some(StreetRecord {
                        road_half_width_m: street.road_half_width,
                        sidewalk_width_m: street.sidewalk_width,
                        parking_lanes: street.parking,
                        side_streets: street.side_streets.len(),
                    }),
                    Ground::Road(_) => None,
                },
                road: match &plan.scene.ground {
                    Ground::Road(paint) => Some(paint),
                    Ground::Street(_) => None,
                },
                road_shape: plan.scene.terrain.as_ref().map(|t| &t.shape),
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
