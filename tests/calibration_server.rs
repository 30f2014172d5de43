//! The calibrated verdict is one computation: the server's answer to a request and `cmr-agent
//! eval`'s record of the same case give the same `p_registered` and `localized`; a model set
//! without a calibrator gives `p_registered: null, localized: false` everywhere; `serve
//! --localized-threshold` moves only the verdict. Real HTTP, real ONNX graphs (the tiny model,
//! with a calibrator section added to a copy of its manifest).

mod server_common;

use std::path::{Path, PathBuf};

use cmr_agent::agent::SearchTuning;
use cmr_agent::eval::learned::AGENT;
use cmr_agent::eval::matching::MatchStrategy;
use cmr_agent::eval::perturbations::Priors;
use cmr_agent::eval::pnp::RansacOptions;
use cmr_agent::eval::report::CaseRecord;
use cmr_agent::eval::run::{EvalConfig, run};
use cmr_agent::maps::formats::write_kitti_bin;
use serde_json::json;
use server_common::*;

/// The tiny model with a calibrator over every signal (weights made up: what matters here is
/// that both paths apply the same one).
fn calibrated_model(dir: &Path, threshold: f64) -> PathBuf {
    for entry in std::fs::read_dir(tiny_model()).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), dir.join(entry.file_name())).unwrap();
    }
    let path = dir.join("manifest.json");
    let mut manifest: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    manifest["calibrator"] = json!({
        "kind": "logistic",
        "target": "test",
        "features": cmr_agent::model::calibrator::SIGNAL_NAMES,
        "mean": [0.0, 0.0, 0.0, 0.3, 0.2, 0.5, 0.5, 0.5, 0.1, 1.0, 0.2, 0.3, 0.02],
        "std": [0.2, 0.1, 0.05, 0.4, 0.2, 0.3, 0.5, 0.3, 0.1, 1.0, 0.4, 0.2, 0.03],
        "weights": [1.1, 0.5, 0.4, 0.6, -0.3, 0.8, -0.2, 0.3, 0.5, 0.1, 0.7, 0.6, 0.5],
        "bias": 0.2,
        "threshold": threshold,
    });
    std::fs::write(&path, serde_json::to_string_pretty(&manifest).unwrap()).unwrap();
    dir.to_path_buf()
}

/// A one-frame KITTI-layout sequence: the test street as the scan, a KITTI-size image, the
/// KITTI rig (velodyne axes permuted into the camera's), and one perturbation that leaves the
/// map where the scan is (so the server's stored region is the eval's map, point for point).
fn one_frame_case(root: &Path) -> (PathBuf, PathBuf) {
    let seq = root.join("data/00");
    std::fs::create_dir_all(seq.join("velodyne")).unwrap();
    std::fs::create_dir_all(seq.join("image_2")).unwrap();
    let p = "7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0";
    std::fs::write(seq.join("calib.txt"), format!("P0: {p}\nP1: {p}\nP2: {p}\nP3: {p}\nTr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27\n")).unwrap();
    std::fs::write(seq.join("velodyne/000000.bin"), write_kitti_bin(&street_cloud())).unwrap();
    std::fs::write(seq.join("image_2/000000.png"), png_bytes(&test_image(1241, 376))).unwrap();
    let perturbations = root.join("perturbations.json");
    let file = json!({"format": "cmr-agent-perturbations/1", "seed": 0, "sampling_seed": 0,
        "cases": [{"sequence": "00", "frame": 0, "yaw_deg": 0.0, "dx_m": 0.0, "dy_m": 0.0}]});
    std::fs::write(&perturbations, file.to_string()).unwrap();
    (root.join("data"), perturbations)
}

fn eval_config(data: &Path, perturbations: &Path, out: &Path, models: &Path) -> EvalConfig {
    EvalConfig {
        data: data.to_path_buf(),
        perturbations: perturbations.to_path_buf(),
        out: out.to_path_buf(),
        models: Some(models.to_path_buf()),
        ort_lib: None,
        threads: 1,
        iterations: 10,
        hypotheses: 4,
        // The server's defaults, so both run the same search.
        tuning: SearchTuning::default(),
        prior_bound: None,
        seed: 0,
        frame_stride: 1,
        max_cases: None,
        cases_per_frame: 1,
        action_frame: None,
        num_points: 40_960,
        ransac: RansacOptions::default(),
        matching: MatchStrategy::Ratio,
        progress: false,
        command: "tests/calibration_server.rs".into(),
        worst: 0,
        record_hypotheses: false,
        baseline: false,
        priors: Priors::Protocol,
    }
}

/// The server's answer to the eval's case, as `cmr-agent eval` would send it: the case's image,
/// intrinsics and initial pose (the rig), the eval's search.
fn request_for_the_case(data: &Path) -> serde_json::Value {
    let sequence = cmr_agent::kitti::Sequence::open(&data.join("00"), None).unwrap();
    let frame = sequence.frame(0).unwrap();
    let k = frame.intrinsics;
    json!({
        "image": b64(&std::fs::read(&frame.image_path).unwrap()),
        "intrinsics": {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy},
        "prior_camera_from_map": frame.camera_from_lidar.to_rows(),
        "hypotheses": 4,
        "max_iterations": 10,
    })
}

fn agent_record(out: &Path) -> CaseRecord {
    let records: Vec<CaseRecord> = serde_json::from_str(&std::fs::read_to_string(out.join("cases.json")).unwrap()).unwrap();
    records.into_iter().find(|r| r.method == AGENT).expect("the agent's record")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_and_eval_give_the_same_verdict() {
    let root = tempfile::tempdir().unwrap();
    let models = root.path().join("models");
    std::fs::create_dir_all(&models).unwrap();
    let models = calibrated_model(&models, 0.5);
    let (data, perturbations) = one_frame_case(root.path());
    let out = root.path().join("eval");
    let config = eval_config(&data, &perturbations, &out, &models);
    let report = tokio::task::spawn_blocking(move || run(&config).unwrap()).await.unwrap();
    let record = agent_record(&out);
    let p_eval = record.notes["p_registered"].as_f64().expect("a calibrated eval records p_registered");
    assert_eq!(record.notes["localized"], p_eval >= 0.5);
    assert_eq!(report.calibration.len(), 2, "the served search and the single start are scored");
    assert_eq!(report.calibration[0].cases, 1);
    assert!(out.join("reliability.png").is_file());
    assert!(std::fs::read_to_string(out.join("tables.md")).unwrap().contains("| cmr-agent | 1 |"));

    let maps = tempfile::tempdir().unwrap();
    std::fs::copy(data.join("00/velodyne/000000.bin"), maps.path().join("case.bin")).unwrap();
    let server = TestServer::start(&models, maps.path(), &[]).await;
    let (status, body, _) = server.localize("case", &request_for_the_case(&data)).await;
    assert_eq!(status, 200, "{body}");
    let confidence = &body["confidence"];
    let p_server = confidence["p_registered"].as_f64().unwrap();
    assert!((p_server - p_eval).abs() < 1e-9, "server {p_server} vs eval {p_eval}");
    assert_eq!(confidence["localized"], record.notes["localized"]);
    common_signals_match(&confidence["signals"], &record.notes["signals"]);
    assert!(p_server > 0.0 && p_server < 1.0);
    let info: serde_json::Value = server.client.get(server.url("/v1/info")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["localized_threshold"], 0.5);
    assert_eq!(info["manifest"]["calibrator"]["threshold"], 0.5);
    server.stop().await;

    // The override moves the verdict, not the probability.
    let strict = format!("{}", (p_server + 1.0) / 2.0);
    let server = TestServer::start(&models, maps.path(), &["--localized-threshold", &strict]).await;
    let (_, body, _) = server.localize("case", &request_for_the_case(&data)).await;
    assert_eq!(body["confidence"]["p_registered"].as_f64(), Some(p_server));
    assert_eq!(body["confidence"]["localized"], false);
    server.stop().await;
    let lenient = format!("{}", p_server / 2.0);
    let server = TestServer::start(&models, maps.path(), &["--localized-threshold", &lenient]).await;
    let (_, body, _) = server.localize("case", &request_for_the_case(&data)).await;
    assert_eq!(body["confidence"]["localized"], true);
    // The overlay's caption says it too (its label bar is drawn, not asserted pixel by pixel).
    let picture = server.client.post(server.url("/v1/maps/case/overlay")).json(&request_for_the_case(&data)).send().await.unwrap();
    assert_eq!(picture.status(), 200);
    server.stop().await;
}

fn common_signals_match(server: &serde_json::Value, eval: &serde_json::Value) {
    for name in cmr_agent::model::calibrator::SIGNAL_NAMES {
        let (a, b) = (server[name].as_f64().unwrap(), eval[name].as_f64().unwrap());
        assert!((a - b).abs() < 1e-9, "{name}: server {a}, eval {b}");
    }
}

/// An older model set (no `calibrator` in its manifest): nothing is vouched for, in the server's
/// answers, `/v1/info`, and eval's records and tables, and the threshold flag changes nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_a_calibrator_nothing_is_localized() {
    let root = tempfile::tempdir().unwrap();
    let (data, perturbations) = one_frame_case(root.path());
    let out = root.path().join("eval");
    let config = eval_config(&data, &perturbations, &out, &tiny_model());
    let report = tokio::task::spawn_blocking(move || run(&config).unwrap()).await.unwrap();
    assert!(report.calibration.is_empty());
    let record = agent_record(&out);
    assert!(record.notes["p_registered"].is_null() && record.notes["localized"] == false);
    assert!(record.notes["signals"]["alignment"].is_number(), "the signals are recorded all the same");
    assert!(!out.join("reliability.png").exists());
    assert!(std::fs::read_to_string(out.join("tables.md")).unwrap().contains("No calibrator in this model set"));

    let maps = tempfile::tempdir().unwrap();
    std::fs::copy(data.join("00/velodyne/000000.bin"), maps.path().join("case.bin")).unwrap();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--localized-threshold", "0"]).await;
    let (status, body, _) = server.localize("case", &request_for_the_case(&data)).await;
    assert_eq!(status, 200, "{body}");
    assert!(body["confidence"]["p_registered"].is_null(), "{}", body["confidence"]);
    assert_eq!(body["confidence"]["localized"], false);
    let info: serde_json::Value = server.client.get(server.url("/v1/info")).send().await.unwrap().json().await.unwrap();
    assert!(info["localized_threshold"].is_null() && info["manifest"].get("calibrator").is_none());
    server.stop().await;
    // A threshold that is not a probability is refused at start-up.
    for bad in ["-0.1", "NaN", "x"] {
        assert!(cmr_agent::api::ServeArgs::from_flags(["--localized-threshold", bad]).is_err(), "{bad}");
    }
}
