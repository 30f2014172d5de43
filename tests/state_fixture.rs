//! Pins the agent's observation across languages: the server builds it in Rust
//! (`agent::state::write_state`), training builds it in PyTorch (`training/cmr/state.py`), and
//! the policy only works if both produce the same tensors. `fixtures/state.json` holds a small
//! scene and the Rust result (sparse: occupied cells of F_k, and state_3d);
//! `training/tests/test_state_fixture.py` checks Python against it. The fixture also holds the
//! pose's alignment score, which the multi-start search ranks hypotheses by. Regenerate with
//! `REGENERATE_FIXTURES=1 cargo test --release --test state_fixture`.

use cmr_agent::agent::state::{Form2d, ImageGrid, Shifts, StateLayout, write_state};
use cmr_agent::geometry::{Intrinsics, Pose};
use nalgebra::{Matrix3, Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};

mod common;

const FIXTURE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/state.json");
const NUM_POINTS: usize = 96;
const DIM: usize = 64;

fn layout() -> StateLayout {
    StateLayout {
        dim: DIM,
        stride: 4,
        grid_height: 40,
        grid_width: 128,
        image_width: 512,
        image_height: 160,
        num_state_points: 2048,
        xyz_scale_m: 10.0,
        form: Form2d::Features,
    }
}

/// The shifts of `training/cmr/models.py` (ROW_SHIFTS, COLUMN_SHIFTS), which every
/// correlation-form model so far lists in its manifest.
const ROW_SHIFTS: [i32; 13] = [-24, -16, -10, -6, -3, -1, 0, 1, 3, 6, 10, 16, 24];
const COLUMN_SHIFTS: [i32; 4] = [-4, -2, 2, 4];

/// Points are kept away from cell borders so f32 (PyTorch) and f64 (Rust) agree on their cell.
fn far_from_cell_borders(k: &Intrinsics, p: &Point3<f64>) -> bool {
    match k.project(p) {
        None => true,
        Some((u, v)) => [u, v].iter().all(|x| {
            let f = ((x + 0.5) / 4.0).fract();
            f > 0.01 && f < 0.99
        }),
    }
}

fn compute() -> Value {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let layout = layout();
    let k = Intrinsics { fx: 359.4, fy: 359.4, cx: 249.8, cy: 78.1 };
    let rig = Pose::from_rt(Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0), Vector3::new(0.06, -0.08, -0.27));
    let pose = rig.compose(&Pose::ground_motion(0.4, 1.5, -2.0));
    let mut points = Vec::new();
    while points.len() < NUM_POINTS {
        // Mostly ahead of the camera (several points share cells), some behind or outside.
        let p = Point3::new(rng.random_range(-5.0..25.0), rng.random_range(-12.0..12.0), rng.random_range(-1.7..2.0));
        let p_cam = pose.transform(&p);
        if far_from_cell_borders(&k, &p_cam) {
            points.push([p.x as f32, p.y as f32, p.z as f32]);
        }
    }
    let features: Vec<f32> = (0..NUM_POINTS * DIM).map(|_| rng.random_range(-1.0..1.0)).collect();
    let probs: Vec<f32> = (0..NUM_POINTS).map(|_| rng.random_range(0.0..1.0)).collect();
    let image: Vec<f32> = (0..layout.image_feature_len()).map(|i| (i % 7) as f32 * 0.1).collect();
    let mut state_2d = vec![f32::NAN; layout.state_2d_len()];
    let mut state_3d = vec![f32::NAN; NUM_POINTS * 5];
    let grid = ImageGrid::new(&layout, image.clone());
    let alignment = write_state(&layout, &points, &features, &probs, &grid, &k, &pose, &mut Default::default(), &mut state_2d, &mut state_3d);

    // The same scene in the correlation form: same 3D state and score, and the volume.
    let correlation_layout = StateLayout { form: Form2d::Correlation(Shifts::new(&ROW_SHIFTS, &COLUMN_SHIFTS)), ..layout };
    let grid = ImageGrid::new(&correlation_layout, image.clone());
    let mut volume = vec![f32::NAN; correlation_layout.state_2d_len()];
    let mut state_3d_again = vec![f32::NAN; NUM_POINTS * 5];
    let score = write_state(&correlation_layout, &points, &features, &probs, &grid, &k, &pose, &mut Default::default(), &mut volume, &mut state_3d_again);
    assert_eq!((score, &state_3d_again), (alignment, &state_3d), "the form changes only the 2D state");

    let cells = layout.cells();
    let image_part_ok = state_2d[..DIM * cells].iter().zip(&image).all(|(a, b)| a == b);
    assert!(image_part_ok, "state_2d must start with the image features");
    let projected = &state_2d[DIM * cells..];
    let occupied: Vec<Value> = (0..cells)
        .filter(|&c| (0..DIM).any(|ch| projected[ch * cells + c] != 0.0))
        .map(|c| json!({"cell": c, "mean": (0..DIM).map(|ch| projected[ch * cells + c]).collect::<Vec<_>>()}))
        .collect();
    // Sparse: the cells with any non-zero channel (the test checks all others are zero).
    let channels = ROW_SHIFTS.len() + COLUMN_SHIFTS.len() + 1;
    let correlated: Vec<Value> = (0..cells)
        .filter(|&c| (0..channels).any(|ch| volume[ch * cells + c] != 0.0))
        .map(|c| json!({"cell": c, "values": (0..channels).map(|ch| volume[ch * cells + c]).collect::<Vec<_>>()}))
        .collect();
    json!({
        "about": "Agent observation built by src/agent/state.rs; read by training/tests/test_state_fixture.py.",
        "intrinsics": k, "camera_from_map": pose.to_rows(), "points_map": points,
        "point_features": features, "frustum_probs": probs,
        "occupied_cells": occupied, "state_3d": state_3d, "alignment": alignment,
        "correlation": {
            "row_shifts": ROW_SHIFTS, "column_shifts": COLUMN_SHIFTS,
            "cells": correlated,
        },
    })
}

#[test]
fn state_building_matches_the_shared_fixture() {
    let computed = compute();
    let stored = common::stored_fixture(FIXTURE, &computed, |v| serde_json::to_string(v).unwrap());
    common::assert_json_close(&stored, &computed, 1e-6, "state");
    assert!(computed["occupied_cells"].as_array().unwrap().len() > 10, "the scene must exercise the scatter");
}
