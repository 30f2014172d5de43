//! A model whose manifest says `actions.frame = "map_z"` is stepped in that frame, end to end
//! (prepare_map / prepare_image / localize on the committed tiny contract model): every start
//! of the search and every step follows `geometry::actions` in the map_z frame, and the camera's
//! tilt relative to the map's up axis never changes.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use cmr_agent::agent::{self, AxisStarts, SearchConfig};
use cmr_agent::geometry::actions::{apply_action, apply_motion};
use cmr_agent::geometry::{ActionFrame, Intrinsics, Pose};
use cmr_agent::maps::{PreparedMap, prepare_map};
use cmr_agent::model::{BackendOptions, ModelSet, Points};
use nalgebra::{Matrix3, Rotation3, Vector3};

fn tiny_model_with_frame(dir: &Path, frame: &str) -> ModelSet {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model");
    for entry in std::fs::read_dir(&src).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), dir.join(entry.file_name())).unwrap();
    }
    let path = dir.join("manifest.json");
    let mut manifest: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    manifest["actions"]["frame"] = frame.into();
    std::fs::write(&path, serde_json::to_string_pretty(&manifest).unwrap()).unwrap();
    ModelSet::load(dir, BackendOptions::default()).expect("tiny model loads")
}

/// Ground plane plus two walls in a z-up map frame.
fn cloud() -> Vec<[f32; 3]> {
    let mut pts = Vec::new();
    for i in 0..120 {
        for j in 0..60 {
            pts.push([i as f32 * 0.5 - 10.0, j as f32 * 0.3 - 9.0, -1.7]);
        }
        for h in 0..15 {
            pts.push([i as f32 * 0.5 - 10.0, 6.0, -1.7 + h as f32 * 0.3]);
            pts.push([i as f32 * 0.5 - 10.0, -8.0, -1.7 + h as f32 * 0.3]);
        }
    }
    pts
}

/// A KITTI-like rig pitched by 6° and rolled by -4° relative to the map's up axis.
fn tilted_rig() -> Pose {
    let level = Pose::from_rt(Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0), Vector3::new(0.0, -0.08, -0.27));
    let tilt = Rotation3::from_euler_angles(6f64.to_radians(), 0.0, (-4f64).to_radians()).into_inner();
    Pose::from_rt(tilt, Vector3::zeros()).compose(&level)
}

#[test]
fn a_map_z_model_steps_about_the_map_up_axis() {
    let dir = tempfile::tempdir().unwrap();
    let set = tiny_model_with_frame(dir.path(), "map_z");
    assert_eq!(set.manifest.action_frame(), ActionFrame::MapZ);
    let mut backend = set.backend().unwrap();
    let map: Arc<PreparedMap> = Arc::new(prepare_map(&mut backend, Points::xyz(&cloud())).unwrap());
    let image = image::RgbImage::from_fn(1241, 376, |x, y| image::Rgb([(x % 251) as u8, (y % 253) as u8, ((x + y) % 7) as u8]));
    let k = Intrinsics { fx: 718.856, fy: 718.856, cx: 607.1928, cy: 185.2157 };
    let (tensor, crop_k) = agent::prepare_image(&image, &k, &set.manifest).unwrap();
    let prior = tilted_rig().compose(&Pose::ground_motion(0.4, 2.0, -1.0));
    let up_seen = |p: &Pose| p.rotation() * Vector3::z();

    let four = SearchConfig { hypotheses: 4, max_iterations: 6, narrow_after: None, merge_duplicates: false, keep_prior: false, prior_bound: None, refine: false, polish: false, prior_margin: 0.0, axis: AxisStarts::NONE, judge_zoom: 0.0, judge_gate: 1.0 };
    let result = agent::localize(&mut backend, &map, &tensor, crop_k, prior, four).unwrap();
    assert_eq!(result.hypotheses.len(), 4);
    let mut moved = false;
    for h in &result.hypotheses {
        let turned = apply_motion(ActionFrame::MapZ, &prior, &map.pivot, h.start_yaw_offset_deg, 0.0, 0.0);
        assert!((h.start.matrix() - turned.matrix()).abs().max() < 1e-12, "start {}", h.start_yaw_offset_deg);
        let mut pose = h.start;
        for step in &h.steps {
            pose = apply_action(ActionFrame::MapZ, &pose, &map.pivot, &step.action);
            assert_eq!(pose, step.camera_from_map);
            assert!((up_seen(&pose) - up_seen(&prior)).norm() < 1e-9, "the tilt is kept");
            moved |= !step.action.is_zero();
        }
    }
    assert!(moved, "the tiny model takes at least one non-zero step");
}

#[test]
fn an_unknown_frame_is_refused_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model");
    for entry in std::fs::read_dir(&src).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), dir.path().join(entry.file_name())).unwrap();
    }
    let path = dir.path().join("manifest.json");
    let mut manifest: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    manifest["actions"]["frame"] = "map_y".into();
    std::fs::write(&path, serde_json::to_string(&manifest).unwrap()).unwrap();
    let err = match ModelSet::load(dir.path(), BackendOptions::default()) {
        Ok(_) => panic!("a manifest with an unknown action frame loaded"),
        Err(e) => format!("{e:#}"),
    };
    assert!(err.contains("actions.frame"), "{err}");
}
