//! Pins the geometry conventions (and the point encoder's intensity rank) that Rust and Python
//! share.
//!
//! `fixtures/conventions.json` holds inputs and the outputs this crate computes for them;
//! `training/tests/test_conventions.py` checks the Python implementation against the same file.
//! Regenerate (after a deliberate convention change) with
//! `REGENERATE_FIXTURES=1 cargo test --test conventions_fixture`.

use cmr_agent::geometry::actions::{apply_action, ground_heading, needed_motion};
use cmr_agent::geometry::{ActionFrame, ActionSet, Intrinsics, PoseError, PreprocessPlan, Pose, ROTATION_TOLERANCE, check_rotation, input_scale, p2p_distance, step_reward};
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};

mod common;

const FIXTURE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/conventions.json");

fn random_pose(rng: &mut ChaCha8Rng) -> Pose {
    let rig = Pose::from_rt(Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0), Vector3::new(0.06, -0.08, -0.27));
    let tilt = Pose::from_rt(
        Rotation3::from_euler_angles(rng.random_range(-0.02..0.02), rng.random_range(-0.02..0.02), 0.0).into_inner(),
        Vector3::zeros(),
    );
    tilt.compose(&rig).compose(&Pose::ground_motion(
        rng.random_range(-3.14..3.14),
        rng.random_range(-10.0..10.0),
        rng.random_range(-10.0..10.0),
    ))
}

/// A rig pitched by up to ±12° and rolled by up to ±8° relative to the map's up axis (a tilt in the
/// camera frame: about camera x, then camera z), at a random heading and place.
fn tilted_rig(rng: &mut ChaCha8Rng) -> Pose {
    let rig = Pose::from_rt(Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0), Vector3::new(0.06, -0.08, -0.27));
    let (pitch, roll) = (rng.random_range(-0.21..0.21), rng.random_range(-0.14..0.14));
    Pose::from_rt(Rotation3::from_euler_angles(pitch, 0.0, roll).into_inner(), Vector3::zeros()).compose(&rig)
}

fn ground(rng: &mut ChaCha8Rng) -> Pose {
    Pose::ground_motion(rng.random_range(-3.14..3.14), rng.random_range(-10.0..10.0), rng.random_range(-10.0..10.0))
}

/// The `map_z` action frame (yaw about the map's up axis, translation in its ground plane along
/// the camera's heading) on pitched and rolled rigs. Even cases: current and target are the same
/// rig at two ground poses (the protocol's error); odd cases: two unrelated tilted rigs. Drawn
/// from their own seed so the `camera_y` cases above stay as they were.
fn map_z_cases() -> (Vec<Value>, Vec<Value>) {
    let mut rng = ChaCha8Rng::seed_from_u64(20260511);
    let set = ActionSet::default().with_frame(ActionFrame::MapZ);
    let poses = (0..16)
        .map(|i| {
            let rig = tilted_rig(&mut rng);
            let current = rig.compose(&ground(&mut rng));
            let target = if i % 2 == 0 { rig.compose(&ground(&mut rng)) } else { tilted_rig(&mut rng).compose(&ground(&mut rng)) };
            let pivot = point(&mut rng);
            let indices = [rng.random_range(0..11), rng.random_range(0..11), rng.random_range(0..11)];
            let moved = set.apply(&current, &pivot, &set.action(indices));
            let (yaw, tx, tz) = needed_motion(ActionFrame::MapZ, &current, &target, &pivot);
            let (right, forward) = ground_heading(&current);
            json!({
                "current": rows(&current), "target": rows(&target), "pivot_map": [pivot.x, pivot.y, pivot.z],
                "same_rig": i % 2 == 0, "ground_right": [right.x, right.y, right.z], "ground_forward": [forward.x, forward.y, forward.z],
                "action_indices": indices, "after_action": rows(&moved),
                "needed_motion": [yaw, tx, tz], "expert_indices": set.expert(&current, &target, &pivot).indices,
            })
        })
        .collect();
    // The greedy expert from a large ground error on a tilted rig: every step's indices and the
    // pose it ends at (about zero error; the camera_y expert cannot get there on these rigs).
    let rollouts = (0..4)
        .map(|_| {
            let truth = tilted_rig(&mut rng).compose(&ground(&mut rng));
            let start = truth.compose(&ground(&mut rng));
            let pivot = point(&mut rng);
            let mut pose = start;
            let mut steps = Vec::new();
            for _ in 0..12 {
                let action = set.expert(&pose, &truth, &pivot);
                pose = set.apply(&pose, &pivot, &action);
                steps.push(action.indices);
            }
            let error = PoseError::between(&pose, &truth);
            json!({
                "start": rows(&start), "truth": rows(&truth), "pivot_map": [pivot.x, pivot.y, pivot.z],
                "expert_steps": steps, "final": rows(&pose), "final_rte_m": error.rte_m, "final_rre_geodesic_deg": error.rre_geodesic_deg,
            })
        })
        .collect();
    (poses, rollouts)
}

fn point(rng: &mut ChaCha8Rng) -> Point3<f64> {
    Point3::new(rng.random_range(-30.0..30.0), rng.random_range(-30.0..30.0), rng.random_range(-2.0..3.0))
}

fn rows(p: &Pose) -> Value {
    json!(p.to_rows())
}

/// A tiled region's virtual scan (`maps::tiles::virtual_scan`): scattered points, some out of
/// the radius or the elevation span, plus pairs on one ray from the sensor (the nearer must win
/// its cell), and the indices the scan keeps. Its own seed, so the other cases stay as they were.
fn virtual_scan_case() -> Value {
    let mut rng = ChaCha8Rng::seed_from_u64(20261202);
    let sensor = [3.25, -1.5, 0.4];
    let radius_m = 25.0;
    let mut points: Vec<[f32; 3]> = (0..600)
        .map(|_| [rng.random_range(-30.0..36.0), rng.random_range(-32.0..30.0), rng.random_range(-3.0..6.0)])
        .collect();
    for _ in 0..150 {
        let (azimuth, elevation) = (rng.random_range(-3.1..3.1f64), rng.random_range(-0.4..0.04f64));
        let near = rng.random_range(2.0..18.0);
        for range in [near * rng.random_range(1.1..1.6), near] {
            let (ground, z) = (range * elevation.cos(), range * elevation.sin());
            points.push([(sensor[0] + ground * azimuth.cos()) as f32, (sensor[1] + ground * azimuth.sin()) as f32, (sensor[2] + z) as f32]);
        }
    }
    let r2 = radius_m * radius_m;
    let candidates: Vec<u32> = (0..points.len() as u32)
        .filter(|&i| {
            let p = points[i as usize];
            let (dx, dy) = (p[0] as f64 - sensor[0], p[1] as f64 - sensor[1]);
            dx * dx + dy * dy <= r2
        })
        .collect();
    let kept = cmr_agent::maps::tiles::virtual_scan(&candidates, |i| points[i as usize], sensor);
    use cmr_agent::maps::tiles::{SCAN_BEAMS, SCAN_COLUMNS, SCAN_ELEVATION_DEG};
    json!({
        "beams": SCAN_BEAMS, "columns": SCAN_COLUMNS, "elevation_deg": [SCAN_ELEVATION_DEG.0, SCAN_ELEVATION_DEG.1],
        "points": points, "sensor": sensor, "radius_m": radius_m, "indices": kept,
    })
}

/// `maps::intensity_rank` (each value's mid-rank among its cloud, what an intensity model reads):
/// a few dozen intensities on a coarse grid, so many tie, with 0 and −0 (equal) and a far
/// outlier; a constant cloud (0.5 everywhere), one value, and none. Its own seed.
fn intensity_rank_case() -> Value {
    let mut rng = ChaCha8Rng::seed_from_u64(20261207);
    let mut mixed: Vec<f32> = (0..40).map(|_| (rng.random_range(0..12) as f32) * 0.025).collect();
    mixed.extend([0.0, -0.0, 0.3, 254.0, 0.125, 0.125]);
    let cases = [("mixed", mixed), ("constant", vec![0.37; 12]), ("one", vec![5.0]), ("empty", vec![])];
    let cases: Vec<Value> = cases
        .into_iter()
        .map(|(name, values)| json!({"name": name, "ranks": cmr_agent::maps::intensity_rank(&values), "values": values}))
        .collect();
    json!(cases)
}

/// `geometry::check_rotation` on rotations (exact, rounded to 7 significant digits as KITTI's
/// poses.txt, scaled just inside the tolerance) and on what is not one (a lost track's zeros,
/// R00 = 2, scaled just outside, sheared, reflections): the verdict and the exact message.
fn rotation_check_case() -> Value {
    let mut rng = ChaCha8Rng::seed_from_u64(20261203);
    let random = Rotation3::from_euler_angles(rng.random_range(-3.1..3.1), rng.random_range(-1.5..1.5), rng.random_range(-3.1..3.1)).into_inner();
    let rig = Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
    let round7 = |m: Matrix3<f64>| m.map(|v| if v == 0.0 { 0.0 } else { let e = 10f64.powi(6 - v.abs().log10().floor() as i32); (v * e).round() / e });
    let mut r00 = Matrix3::identity();
    r00[(0, 0)] = 2.0;
    let mut sheared = Matrix3::identity();
    sheared[(0, 1)] = 0.1;
    let mut flipped_rig = rig;
    flipped_rig.set_row(2, &(-rig.row(2)));
    let cases = [
        ("identity", Matrix3::identity()),
        ("kitti_rig", rig),
        ("random", random),
        ("random_7_digits", round7(random)),
        ("scaled_inside", random * (1.0 + 4e-4)),
        ("scaled_outside", random * (1.0 + 6e-4)),
        ("lost_track_zeros", Matrix3::zeros()),
        ("r00_is_2", r00),
        ("sheared", sheared),
        ("reflection", Matrix3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0)),
        ("rig_with_a_negated_row", flipped_rig),
    ];
    let cases: Vec<Value> = cases
        .iter()
        .map(|(name, m)| {
            let rows: Vec<Vec<f64>> = (0..3).map(|r| (0..3).map(|c| m[(r, c)]).collect()).collect();
            json!({"name": name, "matrix": rows, "error": check_rotation(m).err()})
        })
        .collect();
    json!({"tolerance": ROTATION_TOLERANCE, "cases": cases})
}

fn compute() -> Value {
    let mut rng = ChaCha8Rng::seed_from_u64(20241014);
    let set = ActionSet::default();
    let k = Intrinsics { fx: 359.5, fy: 359.5, cx: 255.3, cy: 78.9 };

    let projection: Vec<Value> = (0..24)
        .map(|_| {
            let p = Point3::new(rng.random_range(-20.0..20.0), rng.random_range(-5.0..5.0), rng.random_range(-5.0..40.0));
            json!({"point_cam": [p.x, p.y, p.z], "uv": k.project(&p).map(|(u, v)| [u, v]), "in_frustum": k.in_frustum(&p, 512, 160)})
        })
        .collect();

    // Each size with the nominal scale alone (no focal range), then with a focal range for lenses
    // inside it, longer (shrunk), wider (enlarged) and much wider (capped at its own resolution).
    let range = Some([353.5456, 360.76885]);
    let lenses = [(None, 718.856), (range, 718.856), (range, 2152.8), (range, 398.4), (range, 100.0)];
    let preprocess: Vec<Value> = [(1241u32, 376u32), (1242, 375), (640, 480), (512, 160), (3000, 900), (400, 100)]
        .iter()
        .flat_map(|&(w, h)| lenses.iter().map(move |&(range, fx)| (w, h, range, fx)))
        .map(|(w, h, focal_range_px, fx)| {
            let scale = input_scale(0.5, focal_range_px, fx);
            let plan = PreprocessPlan::centered(w, h, scale, 512, 160);
            let src = Intrinsics { fx, fy: fx, cx: w as f64 / 2.0 - 0.3, cy: h as f64 / 2.0 + 0.7 };
            json!({"in_size": [w, h], "nominal_scale": 0.5, "focal_range_px": focal_range_px, "intrinsics": src, "scale": scale, "plan": plan, "adjusted": plan.adjust(&src, w, h)})
        })
        .collect();
    // The judge's zoomed views (agent::prepare_views): the same images, resized 1.5 (and 1.3)
    // times more, cropped at the left edge, centre and right edge.
    let zoomed: Vec<Value> = [(1241u32, 376u32, 718.856), (1936, 1216, 1266.4), (640, 480, 500.0), (400, 100, 300.0)]
        .iter()
        .flat_map(|&(w, h, fx)| [1.5, 1.3].map(move |zoom| (w, h, fx, zoom)))
        .flat_map(|(w, h, fx, zoom)| cmr_agent::agent::input::JUDGE_ANCHORS.map(move |anchor| (w, h, fx, zoom, anchor)))
        .map(|(w, h, fx, zoom, anchor)| {
            let scale = input_scale(0.5, Some([353.5456, 360.76885]), fx);
            let plan = PreprocessPlan::zoomed(w, h, scale, 512, 160, zoom, anchor);
            let src = Intrinsics { fx, fy: fx, cx: w as f64 / 2.0 - 0.3, cy: h as f64 / 2.0 + 0.7 };
            json!({"in_size": [w, h], "scale": scale, "zoom": zoom, "anchor": anchor, "plan": plan, "adjusted": plan.adjust(&src, w, h), "intrinsics": src})
        })
        .collect();

    let poses: Vec<Value> = (0..16)
        .map(|_| {
            let current = random_pose(&mut rng);
            let target = random_pose(&mut rng);
            let pivot = point(&mut rng);
            let indices = [rng.random_range(0..11), rng.random_range(0..11), rng.random_range(0..11)];
            let moved = apply_action(ActionFrame::CameraY, &current, &pivot, &set.action(indices));
            let (yaw, tx, tz) = needed_motion(ActionFrame::CameraY, &current, &target, &pivot);
            let points: Vec<Point3<f64>> = (0..8).map(|_| point(&mut rng)).collect();
            let before = p2p_distance(&current, &target, &points);
            let after = p2p_distance(&moved, &target, &points);
            let error = PoseError::between(&current, &target);
            json!({
                "current": rows(&current), "target": rows(&target), "pivot_map": [pivot.x, pivot.y, pivot.z],
                "action_indices": indices, "after_action": rows(&moved),
                "needed_motion": [yaw, tx, tz], "expert_indices": set.expert(&current, &target, &pivot).indices,
                "points_map": points.iter().map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>(),
                "p2p_before": before, "p2p_after": after, "reward": step_reward(before, after),
                "rte_m": error.rte_m, "rre_euler_deg": error.rre_euler_deg, "rre_geodesic_deg": error.rre_geodesic_deg,
            })
        })
        .collect();
    // The multi-start search's starts (agent::search), for a few search sizes.
    let starts: serde_json::Map<String, Value> =
        [1, 2, 4, 8].iter().map(|&h| (h.to_string(), json!(cmr_agent::agent::start_yaw_offsets(h)))).collect();

    let (map_z_poses, map_z_rollouts) = map_z_cases();
    let virtual_scan = virtual_scan_case();
    let rotation_check = rotation_check_case();
    let intensity_rank = intensity_rank_case();

    json!({
        "about": "Shared geometry conventions; generated by tests/conventions_fixture.rs, read by Rust and Python tests.",
        "action_set": set, "intrinsics": k, "image_size": [512, 160],
        "projection": projection, "preprocess": preprocess, "preprocess_zoomed": zoomed, "poses": poses,
        "start_yaw_offsets_deg": starts,
        "map_z_poses": map_z_poses, "map_z_expert_rollouts": map_z_rollouts,
        "virtual_scan": virtual_scan,
        "rotation_check": rotation_check,
        "intensity_rank": intensity_rank,
    })
}

#[test]
fn geometry_matches_the_shared_fixture() {
    let computed = compute();
    let stored = common::stored_fixture(FIXTURE, &computed, |v| serde_json::to_string_pretty(v).unwrap());
    common::assert_json_close(&stored, &computed, 1e-9, "fixture");
}

/// The `map_z` expert reaches the truth on every tilted rig of the fixture, and for these rigs
/// the two frames differ (so the cases pin something the `camera_y` ones do not).
#[test]
fn map_z_expert_reaches_the_truth_on_tilted_rigs() {
    let (poses, rollouts) = map_z_cases();
    for r in &rollouts {
        assert!(r["final_rte_m"].as_f64().unwrap() < 0.1 && r["final_rre_geodesic_deg"].as_f64().unwrap() < 0.06, "{r}");
    }
    let differ = poses.iter().filter(|c| {
        let m = |key: &str| -> [[f64; 4]; 4] { serde_json::from_value(c[key].clone()).unwrap() };
        let (current, target) = (Pose::from_matrix(&m("current")).unwrap(), Pose::from_matrix(&m("target")).unwrap());
        let pivot: [f64; 3] = serde_json::from_value(c["pivot_map"].clone()).unwrap();
        let pivot = Point3::from(pivot);
        let a = needed_motion(ActionFrame::CameraY, &current, &target, &pivot);
        let b = needed_motion(ActionFrame::MapZ, &current, &target, &pivot);
        (a.0 - b.0).abs() > 1e-3
    });
    assert!(differ.count() >= 12);
}
