//! Synthetic world v2: every rig's calibration against its rendered depth (level and pitched
//! cameras, flat and hilly ground), ring counts, determinism per world family, and clear errors
//! for unknown names.

mod common;

use cmr_agent::synth::rigs::{named, RIG_NAMES};
use cmr_agent::synth::{generate, GeneratorConfig, LookMode, RigChoice, SensorOverrides, SequencePlan, StyleOverrides, StylePreset, WorldKind};
use nalgebra::Point3;

use common::snapshot;

/// One sequence of `world` seen by `rig`, its image scaled to 480 px wide, 1000 LiDAR columns.
fn config(world: WorldKind, rig: RigChoice, seed: u64, frames: usize) -> GeneratorConfig {
    let (w, h) = match &rig {
        RigChoice::Named(r) => (480, (480.0 * r.height as f64 / r.width as f64).round() as u32),
        RigChoice::Random => (480, 200),
    };
    GeneratorConfig {
        seed,
        sequences: 1,
        first_sequence: 0,
        frames,
        spacing_m: 2.5,
        rig,
        sensor: SensorOverrides { image_size: Some((w, h)), lidar_beams: None, lidar_columns: Some(1000), image_scale: None },
        world: Some(world),
        look: LookMode::Random,
        preset: StylePreset::Train,
        overrides: StyleOverrides::default(),
    }
}

fn rig(name: &str) -> RigChoice {
    RigChoice::Named(named(name).unwrap())
}

#[derive(Debug, Default)]
struct Agreement {
    matched: usize,
    occluded: usize,
    in_front: usize,
    total: usize,
}

impl Agreement {
    fn share(&self, n: usize) -> f64 {
        n as f64 / self.total.max(1) as f64
    }
}

/// LiDAR points moved by the calibration's camera_from_lidar and projected with P2's
/// intrinsics, compared with the rendered depth of the 2×2 pixels around them (tolerance 3σ of
/// the range noise + 2 cm). `camera_override` replaces the calibration (to show the test bites).
fn agreement(plan: &SequencePlan, frames: &[usize], camera_override: Option<cmr_agent::geometry::Pose>) -> Agreement {
    let camera_from_lidar = camera_override.unwrap_or_else(|| plan.calib.color_camera_from_lidar().unwrap());
    let k = plan.calib.color_intrinsics().unwrap();
    let tolerance = 3.0 * plan.rig.lidar.range_noise_m as f64 + 0.02;
    let (w, h) = (plan.rig.width, plan.rig.height);
    let mut a = Agreement::default();
    for &index in frames {
        let output = plan.frame(index).unwrap();
        for p in &output.points {
            let c = camera_from_lidar.transform(&Point3::new(p.x as f64, p.y as f64, p.z as f64));
            let Some((u, v)) = k.project(&c) else { continue };
            if u < 0.0 || v < 0.0 || u > (w - 1) as f64 || v > (h - 1) as f64 {
                continue;
            }
            a.total += 1;
            let (u0, v0) = (u.floor() as u32, v.floor() as u32);
            let (u1, v1) = ((u0 + 1).min(w - 1), (v0 + 1).min(h - 1));
            let around = [(u0, v0), (u1, v0), (u0, v1), (u1, v1)].map(|(x, y)| output.rendered.depth_at(x, y));
            let lo = around.iter().cloned().fold(f32::INFINITY, f32::min) as f64;
            let hi = around.iter().cloned().fold(f32::NEG_INFINITY, f32::max) as f64;
            if c.z >= lo - tolerance && c.z <= hi + tolerance {
                a.matched += 1;
            } else if c.z > hi {
                a.occluded += 1;
            } else {
                a.in_front += 1;
            }
        }
    }
    a
}

fn check(label: &str, a: &Agreement, min_points: usize) {
    println!(
        "{label}: {} in-image points, matched {:.4}, occluded {:.4}, in front {:.4}",
        a.total,
        a.share(a.matched),
        a.share(a.occluded),
        a.share(a.in_front)
    );
    assert!(a.total > min_points, "{label}: too few points in the image: {}", a.total);
    assert!(a.share(a.matched) > 0.95, "{label}: only {:.4} of the points match the rendered depth", a.share(a.matched));
    assert!(a.share(a.in_front) < 0.01, "{label}: {:.4} of the points float in front of the rendered surfaces", a.share(a.in_front));
}

#[test]
fn every_rigs_calibration_reprojects_its_lidar_onto_the_rendered_depth() {
    for (i, name) in RIG_NAMES.iter().enumerate() {
        let plan = SequencePlan::new(&config(WorldKind::Urban, rig(name), 100 + i as u64, 8), 0).unwrap();
        check(&format!("rig {name}"), &agreement(&plan, &[1, 6], None), 2_000);
    }
    for seed in [7, 8] {
        let plan = SequencePlan::new(&config(WorldKind::Arterial, RigChoice::Random, seed, 8), 0).unwrap();
        check(&format!("random rig (seed {seed}, {} beams)", plan.rig.lidar.beams), &agreement(&plan, &[3], None), 1_000);
    }
}

/// A camera pitched 4° down and rolled 1.5°: the written Tr must carry the tilt. Using the
/// level camera's Tr instead must fail the same check clearly.
#[test]
fn a_pitched_and_rolled_camera_still_agrees() {
    let mut tilted = named("kitti").unwrap();
    tilted.camera_pitch_deg = 4.0;
    tilted.camera_roll_deg = 1.5;
    let plan = SequencePlan::new(&config(WorldKind::Classic, RigChoice::Named(tilted), 3, 8), 0).unwrap();
    let good = agreement(&plan, &[2, 7], None);
    check("kitti pitched 4°, rolled 1.5°", &good, 5_000);
    let level = named("kitti").unwrap().with_image_size(plan.rig.width, plan.rig.height).calibration();
    let wrong = agreement(&plan, &[2, 7], Some(level.color_camera_from_lidar().unwrap()));
    println!("same frames through the level camera's calibration: matched {:.4}", wrong.share(wrong.matched));
    assert!(wrong.share(wrong.matched) < good.share(good.matched) - 0.2, "a 4° calibration error went unnoticed");
}

/// Hilly rural roads: the vehicle climbs, pitches and rolls with the road, and the sensors agree.
#[test]
fn non_flat_terrain_frames_still_agree() {
    let mut checked = 0;
    for seed in 0..12u64 {
        let plan = SequencePlan::new(&config(WorldKind::Rural, rig("kitti"), seed, 30), 0).unwrap();
        let (a, b) = (plan.trajectory.world_from_lidar(0), plan.trajectory.world_from_lidar(29));
        let climb = (b.translation().z - a.translation().z).abs();
        let tilt = (0..30).map(|i| plan.trajectory.world_from_lidar(i).rotation()[(2, 0)].abs().max(plan.trajectory.world_from_lidar(i).rotation()[(2, 1)].abs())).fold(0.0, f64::max);
        if climb < 0.5 || tilt < 0.01 {
            continue;
        }
        println!("seed {seed}: climbs {climb:.2} m over 72.5 m, largest pitch/roll component {:.2}°", tilt.asin().to_degrees());
        check(&format!("rural seed {seed}"), &agreement(&plan, &[5, 20, 29], None), 3_000);
        checked += 1;
        if checked == 2 {
            break;
        }
    }
    assert_eq!(checked, 2, "no hilly rural sequence among the seeds tried");
}

/// Each rig's scan has exactly as many rings (distinct beam elevations) as the rig has beams.
#[test]
fn ring_count_equals_the_rigs_beam_count() {
    let mut rigs: Vec<RigChoice> = RIG_NAMES.iter().map(|n| rig(n)).collect();
    rigs.push(RigChoice::Random);
    for (i, choice) in rigs.into_iter().enumerate() {
        let mut cfg = config(WorldKind::Urban, choice, 40 + i as u64, 4);
        cfg.sensor.lidar_columns = None;
        let plan = SequencePlan::new(&cfg, 0).unwrap();
        let points = plan.frame(2).unwrap().points;
        let mut elevations: Vec<f64> = points.iter().map(|p| (p.z as f64).atan2((p.x as f64).hypot(p.y as f64)).to_degrees()).collect();
        elevations.sort_by(f64::total_cmp);
        let rings = 1 + elevations.windows(2).filter(|w| w[1] - w[0] > 0.05).count();
        println!("rig {}: {} points, {rings} rings, {} beams", plan.rig.name, points.len(), plan.rig.lidar.beams);
        assert_eq!(rings, plan.rig.lidar.beams as usize, "rig {}", plan.rig.name);
    }
}


/// Same seed and flags give the same bytes in every world family (random rig and look on).
#[test]
fn every_world_is_deterministic() {
    let worlds = [WorldKind::Classic, WorldKind::Urban, WorldKind::Suburban, WorldKind::Rural, WorldKind::Arterial, WorldKind::Highway, WorldKind::Industrial];
    let mut images = Vec::new();
    for world in worlds {
        let mut cfg = config(world, RigChoice::Random, 5, 2);
        cfg.sensor = SensorOverrides { image_size: Some((240, 90)), lidar_beams: Some(16), lidar_columns: Some(360), image_scale: None };
        let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        generate(&cfg, a.path(), false, false).unwrap();
        generate(&cfg, b.path(), false, false).unwrap();
        let (sa, sb) = (snapshot(a.path()), snapshot(b.path()));
        assert_eq!(sa.len(), 3 + 2 * 2, "{world:?}");
        assert!(sa == sb, "{world:?}: two runs with the same seed differ");
        let json: serde_json::Value = serde_json::from_slice(&std::fs::read(a.path().join("00/synth.json")).unwrap()).unwrap();
        assert_eq!(json["world"], serde_json::json!(world.name()));
        images.push(std::fs::read(a.path().join("00/image_2/000001.png")).unwrap());
    }
    for i in 0..images.len() {
        for j in i + 1..images.len() {
            assert!(images[i] != images[j], "worlds {i} and {j} rendered the same image");
        }
    }
}

#[test]
fn unknown_rig_or_world_names_are_clear_errors() {
    let bin = env!("CARGO_BIN_EXE_cmr-agent");
    let run = |args: &[&str]| std::process::Command::new(bin).args(args).output().unwrap();
    let out = run(&["synth", "--rig", "hdl64", "--out", "/nonexistent"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("kitti, nuscenes, wide, vlp16, os128, random"), "{err}");
    let out = run(&["synth", "--world", "desert", "--out", "/nonexistent"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("classic, urban, suburban, rural, arterial, highway, industrial"), "{err}");
    let out = run(&["synth", "--list-rigs"]);
    let listing = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success());
    for name in RIG_NAMES.iter().chain(&["random"]) {
        assert!(listing.contains(name), "{name} missing from --list-rigs: {listing}");
    }
}

/// The families differ where it matters for registration: the arterial is lined with
/// vegetation, the classic street with buildings.
#[test]
fn point_shares_differ_between_worlds() {
    use cmr_agent::synth::args::WorldArgs;
    use cmr_agent::synth::scene::Class;
    use cmr_agent::synth::stats::class_counts;
    let mut args = WorldArgs::classic(StylePreset::Train, 3);
    args.lidar_columns = Some(700);
    let share = |world: WorldKind, class: Class| {
        let (counts, _) = class_counts(&args, world, 2, 1).unwrap();
        *counts.get(&class).unwrap_or(&0) as f64 / counts.values().sum::<usize>() as f64
    };
    let (classic, arterial) = (share(WorldKind::Classic, Class::Vegetation), share(WorldKind::Arterial, Class::Vegetation));
    println!("vegetation share: classic {classic:.3}, arterial {arterial:.3}");
    assert!(arterial > 2.0 * classic && arterial > 0.1, "classic {classic}, arterial {arterial}");
}
