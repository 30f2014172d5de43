//! The shipped demo: one held-out, test-style frame turned into a map region (the scan moved by
//! a seeded map-frame motion Q, as in the paper's protocol) and a localize request whose true
//! answer (camera_from_lidar · Q⁻¹) is kept beside it.

use std::path::{Path, PathBuf};

use anyhow::Result;
use base64::Engine;
use nalgebra::Point3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::json;

use super::args::{parse_size, WorldArgs};
use super::generate::{SequencePlan, CLASSIC_GENERATOR_VERSION};
use super::style::StylePreset;
use crate::geometry::pose::PoseMatrix;
use crate::geometry::PoseError;
use crate::atomic_file::write_atomic;
use crate::kitti::{velodyne_to_bytes, LidarPoint};

#[derive(Debug, clap::Args)]
pub struct DemoArgs {
    /// Where demo.bin and demo.json go.
    #[arg(long, default_value = "maps")]
    pub maps_dir: PathBuf,
    /// Where localize-demo.json and localize-demo.truth.json go.
    #[arg(long, default_value = "examples")]
    pub examples_dir: PathBuf,
    /// Seed of the held-out, test-style street (far from the training and test sets' seeds).
    #[arg(long, default_value_t = 90_001)]
    pub seed: u64,
    /// Which frame along the street to use.
    #[arg(long, default_value_t = 12)]
    pub frame: usize,
    /// Seed of the map-frame motion Q.
    #[arg(long, default_value_t = 7)]
    pub motion_seed: u64,
    #[arg(long, default_value = "1241x376", value_parser = parse_size)]
    pub image_size: (u32, u32),
}

pub fn run(args: &DemoArgs) -> Result<()> {
    // Today's street, rig and look: the demo's bytes are those of generator version 1.
    let world = WorldArgs { image_size: Some(args.image_size), ..WorldArgs::classic(StylePreset::Test, args.seed) };
    let config = world.config(1, 0, args.frame + 1);
    config.validate()?;
    let plan = SequencePlan::new(&config, 0)?;
    let output = plan.frame(args.frame)?;
    let camera_from_lidar = plan.calib.color_camera_from_lidar()?;
    let intrinsics = plan.calib.color_intrinsics()?;

    // The paper's protocol: map = Q · scan, Q = yaw about z in [−180°, 180°) then (dx, dy) in ±10 m.
    let mut rng = ChaCha8Rng::seed_from_u64(args.motion_seed);
    let yaw_deg: f64 = rng.random_range(-180.0..180.0);
    let (dx, dy): (f64, f64) = (rng.random_range(-10.0..10.0), rng.random_range(-10.0..10.0));
    let q = crate::geometry::Pose::ground_motion(yaw_deg.to_radians(), dx, dy);
    let map_points: Vec<LidarPoint> = output
        .points
        .iter()
        .map(|p| {
            let m = q.transform(&Point3::new(p.x as f64, p.y as f64, p.z as f64));
            LidarPoint { x: m.x as f32, y: m.y as f32, z: m.z as f32, intensity: p.intensity }
        })
        .collect();
    let truth = camera_from_lidar.compose(&q.inverse());
    let initial_error = PoseError::between(&camera_from_lidar, &truth);

    let source = json!({
        "generator": CLASSIC_GENERATOR_VERSION,
        "seed": config.seed,
        "style": plan.style,
        "sequence": plan.index,
        "frame": args.frame,
        "image_size": [plan.rig.width, plan.rig.height],
        "points": map_points.len(),
    });
    std::fs::create_dir_all(&args.maps_dir)?;
    std::fs::create_dir_all(&args.examples_dir)?;
    write_atomic(&args.maps_dir.join("demo.bin"), &velodyne_to_bytes(&map_points))?;
    write_json(
        &args.maps_dir.join("demo.json"),
        &json!({
            "description": "Synthetic test-style street (held-out seed): one HDL-64E-like sweep moved into its own map frame by a seeded ground-plane motion.",
            "initial_camera_from_map": PoseMatrix::from(camera_from_lidar),
            "source": source,
        }),
    )?;
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90).encode_image(&output.rendered.image)?;
    write_json(
        &args.examples_dir.join("localize-demo.json"),
        &json!({
            "image": base64::engine::general_purpose::STANDARD.encode(&jpeg),
            "intrinsics": {"fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy},
            "max_iterations": 10,
        }),
    )?;
    write_json(
        &args.examples_dir.join("localize-demo.truth.json"),
        &json!({
            "camera_from_map": PoseMatrix::from(truth),
            "map_from_lidar": PoseMatrix::from(q),
            "motion": {"yaw_deg": yaw_deg, "dx_m": dx, "dy_m": dy, "seed": args.motion_seed},
            "initial_camera_from_map": PoseMatrix::from(camera_from_lidar),
            "initial_error": initial_error,
            "map": "maps/demo.bin",
            "source": source,
        }),
    )?;
    tracing::info!(points = map_points.len(), yaw_deg, dx, dy, "wrote the demo map and request");
    Ok(())
}

fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    let mut bytes = serde_json::to_vec_pretty(value)?;
    bytes.push(b'\n');
    Ok(write_atomic(path, &bytes)?)
}
