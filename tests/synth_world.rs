//! The synthetic world written as KITTI and read back through `cmr_agent::kitti`:
//! determinism, format round trip, and agreement between the LiDAR and the camera.

mod common;

use std::path::Path;

use cmr_agent::kitti::{discover_sequences, read_velodyne, Sequence};
use cmr_agent::synth::{generate, GeneratorConfig, SensorOverrides, SequencePlan};
use nalgebra::Point3;

use common::snapshot;

/// Today's generator (kitti rig, classic street and look) at a small size.
fn small_config(seed: u64) -> GeneratorConfig {
    GeneratorConfig {
        spacing_m: 3.0,
        sensor: SensorOverrides { image_size: Some((310, 94)), lidar_beams: Some(16), lidar_columns: Some(400), image_scale: None },
        ..GeneratorConfig::classic(seed, 2, 3)
    }
}


#[test]
fn same_seed_and_flags_give_identical_bytes() {
    let (a, b, c) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    generate(&small_config(11), a.path(), false, false).unwrap();
    generate(&small_config(11), b.path(), false, false).unwrap();
    let (sa, sb) = (snapshot(a.path()), snapshot(b.path()));
    // 2 sequences × (calib, poses, synth.json + 3 frames × (bin, png)).
    assert_eq!(sa.len(), 2 * (3 + 3 * 2));
    assert!(sa == sb, "two runs with the same seed differ");
    generate(&small_config(12), c.path(), false, false).unwrap();
    let sc = snapshot(c.path());
    let differing = sa.iter().zip(&sc).filter(|(x, y)| x.1 != y.1).count();
    assert!(differing >= 12, "another seed should change every frame, changed {differing} files");
    // Existing output is never silently replaced.
    let err = generate(&small_config(11), a.path(), false, false).unwrap_err().to_string();
    assert!(err.contains("already exists"), "{err}");
}

#[test]
fn written_sequences_read_back_through_the_kitti_module() {
    let dir = tempfile::tempdir().unwrap();
    let config = small_config(5);
    generate(&config, dir.path(), false, false).unwrap();
    let sequences = discover_sequences(dir.path()).unwrap();
    assert_eq!(sequences.iter().map(|s| s.name.as_str()).collect::<Vec<_>>(), ["00", "01"]);
    for seq in &sequences {
        let plan = SequencePlan::new(&config, seq.name.parse().unwrap()).unwrap();
        assert_eq!(seq.frame_indices, vec![0, 1, 2]);
        // Calibration: the reader's image_2 extrinsics and intrinsics are the generator's.
        let frame = seq.frame(1).unwrap();
        let want = plan.calib.color_camera_from_lidar().unwrap();
        assert!((frame.camera_from_lidar.matrix() - want.matrix()).abs().max() < 1e-12);
        assert_eq!(frame.intrinsics, plan.calib.color_intrinsics().unwrap());
        assert_eq!(frame.image_size().unwrap(), (310, 94));
        // P2 has the non-zero 4th column of a camera offset from cam0.
        assert!(seq.calib.projections[2].unwrap()[3] > 1.0);
        // Poses: frame 0 is the identity; consecutive frames move ~spacing forward (cam0 z).
        let poses = seq.poses.as_ref().unwrap();
        assert!((poses[0].matrix() - nalgebra::Matrix4::identity()).abs().max() < 1e-12);
        let step = poses[1].translation() - poses[0].translation();
        assert!((step.norm() - 3.0).abs() < 0.05 && step.z > 2.9, "{step:?}");
        let expected = plan.kitti_poses(3);
        for (a, b) in poses.iter().zip(&expected) {
            assert!((a.matrix() - b.matrix()).abs().max() < 1e-9);
        }
        // Points: the file holds exactly what the LiDAR produced.
        let output = plan.frame(1).unwrap();
        assert_eq!(frame.read_points().unwrap(), output.points);
        assert_eq!(frame.read_image().unwrap(), output.rendered.image);
        // The ground is 1.73 m below the LiDAR: the lowest points sit near z = -1.73.
        let ground = output.points.iter().filter(|p| (p.z + 1.73).abs() < 0.1).count();
        assert!(ground > output.points.len() / 5, "{ground} of {} points on the ground", output.points.len());
    }
    // A KITTI `dataset/` root: sequences/NN plus poses/NN.txt.
    let kitti = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(kitti.path().join("sequences")).unwrap();
    std::fs::create_dir_all(kitti.path().join("poses")).unwrap();
    std::fs::rename(dir.path().join("01"), kitti.path().join("sequences/01")).unwrap();
    std::fs::rename(kitti.path().join("sequences/01/poses.txt"), kitti.path().join("poses/01.txt")).unwrap();
    let found = discover_sequences(kitti.path()).unwrap();
    assert_eq!(found.len(), 1);
    assert_eq!(found[0].poses.as_ref().map(Vec::len), Some(3));
    // A single sequence directory is a root too.
    let single = Sequence::open(&kitti.path().join("sequences/01"), None).unwrap();
    assert!(single.poses.is_none() && single.len() == 3);
    assert!(discover_sequences(&kitti.path().join("poses")).is_err());
}

/// LiDAR points moved by image_2's camera_from_lidar and projected with P2's intrinsics must
/// land where the renderer saw a surface at the same depth. Depth is compared with the 2×2
/// pixels around the projection (a plane's depth between pixel centres lies within theirs),
/// with a tolerance of 3σ of the range noise plus 2 cm.
#[test]
fn lidar_points_agree_with_the_rendered_depth() {
    let config = GeneratorConfig {
        sequences: 1,
        frames: 12,
        sensor: SensorOverrides { image_size: Some((620, 188)), lidar_beams: None, lidar_columns: Some(1000), image_scale: None },
        ..small_config(21)
    };
    let tolerance = 3.0 * config.rig_for(0).lidar.range_noise_m as f64 + 0.02;
    let dir = tempfile::tempdir().unwrap();
    generate(&config, dir.path(), false, false).unwrap();
    let seq = &discover_sequences(dir.path()).unwrap()[0];
    let plan = SequencePlan::new(&config, 0).unwrap();
    let (mut matched, mut occluded, mut in_front, mut total) = (0usize, 0usize, 0usize, 0usize);
    for index in [0usize, 7, 11] {
        let frame = seq.frame(index).unwrap();
        let rendered = plan.frame(index).unwrap().rendered;
        let (w, h) = frame.image_size().unwrap();
        for p in read_velodyne(&frame.velodyne_path).unwrap() {
            let c = frame.camera_from_lidar.transform(&Point3::new(p.x as f64, p.y as f64, p.z as f64));
            let Some((u, v)) = frame.intrinsics.project(&c) else { continue };
            if u < 0.0 || v < 0.0 || u > (w - 1) as f64 || v > (h - 1) as f64 {
                continue;
            }
            total += 1;
            let (u0, v0) = (u.floor() as u32, v.floor() as u32);
            let (u1, v1) = ((u0 + 1).min(w - 1), (v0 + 1).min(h - 1));
            let around = [(u0, v0), (u1, v0), (u0, v1), (u1, v1)].map(|(x, y)| rendered.depth_at(x, y));
            let lo = around.iter().cloned().fold(f32::INFINITY, f32::min) as f64;
            let hi = around.iter().cloned().fold(f32::NEG_INFINITY, f32::max) as f64;
            if c.z >= lo - tolerance && c.z <= hi + tolerance {
                matched += 1;
            } else if c.z > hi {
                occluded += 1; // hidden from the camera (it sits ~30 cm from the LiDAR)
            } else {
                in_front += 1; // a point in front of every surface the camera saw: a real mismatch
            }
        }
    }
    let share = |n: usize| n as f64 / total as f64;
    println!(
        "lidar/camera agreement over {total} in-image points: matched {:.4}, occluded {:.4}, in front {:.4} (tolerance {tolerance:.3} m)",
        share(matched),
        share(occluded),
        share(in_front)
    );
    assert!(total > 10_000, "too few points in the image: {total}");
    assert!(share(matched) > 0.97, "only {:.4} of the points match the rendered depth", share(matched));
    assert!(share(in_front) < 0.002, "{:.4} of the points float in front of the rendered surfaces", share(in_front));
}

/// The shipped demo (maps/demo.*, examples/localize-demo*) is exactly what `synth demo`
/// produces, and its ground truth follows the protocol: camera_from_map = camera_from_lidar · Q⁻¹.
#[test]
fn shipped_demo_is_reproducible_and_consistent() {
    use cmr_agent::geometry::{pose::PoseMatrix, Pose};
    use cmr_agent::synth::demo::{run, DemoArgs};
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = tempfile::tempdir().unwrap();
    let args = DemoArgs {
        maps_dir: out.path().join("maps"),
        examples_dir: out.path().join("examples"),
        seed: 90_001,
        frame: 12,
        motion_seed: 7,
        image_size: (1241, 376),
    };
    run(&args).unwrap();
    for file in ["maps/demo.bin", "maps/demo.json", "examples/localize-demo.json", "examples/localize-demo.truth.json"] {
        let shipped = std::fs::read(repo.join(file)).unwrap();
        let fresh = std::fs::read(out.path().join(file)).unwrap();
        assert!(shipped == fresh, "{file} is stale: regenerate with `cmr-agent synth demo`");
    }
    let truth: serde_json::Value = serde_json::from_slice(&std::fs::read(repo.join("examples/localize-demo.truth.json")).unwrap()).unwrap();
    let pose = |key: &str| -> Pose { serde_json::from_value::<PoseMatrix>(truth[key].clone()).unwrap().try_into().unwrap() };
    let (gt, initial, q) = (pose("camera_from_map"), pose("initial_camera_from_map"), pose("map_from_lidar"));
    assert!((gt.matrix() - initial.compose(&q.inverse()).matrix()).abs().max() < 1e-9);
    // Q is a ground-plane motion within the protocol's ±10 m.
    let t = q.translation();
    assert!(t.z.abs() < 1e-12 && t.x.abs() <= 10.0 && t.y.abs() <= 10.0);
    // Seen through the true pose, a good share of the map lies in the camera's frustum.
    let points = read_velodyne(&repo.join("maps/demo.bin")).unwrap();
    assert!(points.len() > 50_000 && points.len() * 16 < 3_000_000);
    let request: serde_json::Value = serde_json::from_slice(&std::fs::read(repo.join("examples/localize-demo.json")).unwrap()).unwrap();
    let k: cmr_agent::geometry::Intrinsics = serde_json::from_value(request["intrinsics"].clone()).unwrap();
    let visible = points
        .iter()
        .filter(|p| k.in_frustum(&gt.transform(&Point3::new(p.x as f64, p.y as f64, p.z as f64)), 1241, 376))
        .count();
    assert!(visible > points.len() / 10, "only {visible} of {} map points in the true frustum", points.len());
    assert_eq!(request["max_iterations"], 10);
}
