//! The overlay picture: `POST /v1/maps/{id}/overlay` through the localize path (real server, the
//! tiny ONNX model), the explicit-pose variant, localize's errors, and the evaluator's
//! worst-case pictures.

mod server_common;

use cmr_agent::geometry::{Intrinsics, Pose};
use cmr_agent::render::{Overlay, PosePanel};
use serde_json::json;
use server_common::*;

const LABEL_BAR: u32 = 26;

async fn post_overlay(server: &TestServer, map: &str, query: &str, body: &serde_json::Value) -> (u16, reqwest::header::HeaderMap, Vec<u8>) {
    let r = server.client.post(server.url(&format!("/v1/maps/{map}/overlay{query}"))).json(body).send().await.unwrap();
    let status = r.status().as_u16();
    let headers = r.headers().clone();
    (status, headers, r.bytes().await.unwrap().to_vec())
}

fn error_type(body: &[u8]) -> String {
    let v: serde_json::Value = serde_json::from_slice(body).unwrap_or_else(|_| panic!("JSON error body, got {:?}", String::from_utf8_lossy(body)));
    assert!(v["error"].as_str().is_some_and(|s| !s.is_empty()), "{v}");
    v["error_type"].as_str().unwrap().to_string()
}

/// Pixels of `panel` (a KITTI-sized panel of the picture) that differ from the darkened image.
fn changed_pixels(picture: &image::RgbImage, top: u32, plain: &image::RgbImage) -> usize {
    let mut n = 0;
    for y in 0..plain.height() {
        for x in 0..plain.width() {
            let dark = plain.get_pixel(x, y).0.map(|c| (c as f32 * 0.7) as u8);
            if picture.get_pixel(x, top + y).0 != dark {
                n += 1;
            }
        }
    }
    n
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_overlay_draws_prior_final_and_iterations_through_the_localize_path() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &[]).await;
    let plain = test_image(1241, 376);

    let (status, headers, body) = post_overlay(&server, "street", "", &kitti_request(3)).await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    assert_eq!(headers["content-type"], "image/png");
    let picture = image::load_from_memory(&body).unwrap().to_rgb8();
    // Two panels (prior, final) at the image's own resolution, each under its label bar.
    assert_eq!(picture.dimensions(), (1241, 2 * (LABEL_BAR + 376)));
    // The street's points project into the prior (the rig pose): many pixels are dots.
    let prior_dots = changed_pixels(&picture, LABEL_BAR, &plain);
    assert!(prior_dots > 2000, "{prior_dots} pixels changed in the prior panel");
    // Away from any dot the background is the darkened image (sky, top-left corner).
    assert_eq!(picture.get_pixel(3, LABEL_BAR + 3).0, plain.get_pixel(3, 3).0.map(|c| (c as f32 * 0.7) as u8));
    let matrix: Vec<f64> = headers["x-camera-from-map"].to_str().unwrap().split(',').map(|v| v.parse().unwrap()).collect();
    assert_eq!(matrix.len(), 16);

    // The same request as localize answers the pose the picture's header names.
    let (status, answer, _) = server.localize("street", &kitti_request(3)).await;
    assert_eq!(status, 200);
    let rows = answer["pose"]["camera_from_map"].as_array().unwrap();
    for (i, row) in rows.iter().enumerate() {
        for (j, v) in row.as_array().unwrap().iter().enumerate() {
            assert!((v.as_f64().unwrap() - matrix[i * 4 + j]).abs() < 1e-5, "[{i}][{j}]");
        }
    }

    // ?iterations=true adds the chosen start's every pose: start + 3 steps in one row of four.
    let request = json!({"image": kitti_request(3)["image"], "intrinsics": kitti_request(3)["intrinsics"], "max_iterations": 3, "hypotheses": 1});
    let (status, _, body) = post_overlay(&server, "street", "?iterations=true", &request).await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    let picture = image::load_from_memory(&body).unwrap().to_rgb8();
    let thumb_h = (376.0f64 * (1241 / 4) as f64 / 1241.0).round() as u32;
    assert_eq!(picture.dimensions(), (1241, 2 * (LABEL_BAR + 376) + 18 + thumb_h));

    // The raw-image variant, intrinsics in the query.
    let r = server
        .client
        .post(server.url("/v1/maps/street/overlay?fx=718.856&fy=718.856&cx=607.1928&cy=185.2157&max_iterations=2"))
        .header("content-type", "image/png")
        .body(png_bytes(&plain))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let picture = image::load_from_memory(&r.bytes().await.unwrap()).unwrap();
    assert_eq!((picture.width(), picture.height()), (1241, 2 * (LABEL_BAR + 376)));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_explicit_pose_is_drawn_without_the_agent_and_large_images_are_scaled() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &[]).await;
    // 3200 px wide: drawn at half size (the 1600 px limit), with the intrinsics scaled to match.
    let plain = test_image(3200, 960);
    let k = json!({"fx": 1800.0, "fy": 1800.0, "cx": 1599.5, "cy": 479.5});
    let body = json!({"image": b64(&png_bytes(&plain)), "intrinsics": k, "camera_from_map": rig_matrix()});
    let (status, headers, png) = post_overlay(&server, "street", "", &body).await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&png));
    let picture = image::load_from_memory(&png).unwrap().to_rgb8();
    assert_eq!(picture.dimensions(), (1600, LABEL_BAR + 480));
    let header: Vec<f64> = headers["x-camera-from-map"].to_str().unwrap().split(',').map(|v| v.parse().unwrap()).collect();
    assert_eq!(header, rig_matrix().iter().flatten().copied().collect::<Vec<_>>());

    // Pixel for pixel the library's drawing of the region's prepared points at that pose.
    let state = server.state.clone();
    let map = tokio::task::spawn_blocking(move || {
        let entry = state.maps.store.get("street").unwrap();
        // A whole region: the crop is the region's sample.
        state.maps.prepared_for(&entry).unwrap().around([0.0; 3], 0.0, 0, true).unwrap()
    })
    .await
    .unwrap();
    let expected = Overlay {
        image: &plain,
        intrinsics: Intrinsics { fx: 1800.0, fy: 1800.0, cx: 1599.5, cy: 479.5 },
        points: &map.points,
        panels: vec![PosePanel::new("camera_from_map (as given)", Pose::from_matrix(&rig_matrix()).unwrap())],
        strip: Vec::new(),
    }
    .draw()
    .unwrap();
    assert!(expected == picture, "the served picture is the library's drawing");
    let small = image::imageops::resize(&plain, 1600, 480, image::imageops::FilterType::Triangle);
    assert!(changed_pixels(&picture, LABEL_BAR, &small) > 2000);

    // The pose is validated as localize validates its prior, and combinations are refused.
    let bent = json!({"image": b64(&png_bytes(&plain)), "intrinsics": k,
        "camera_from_map": [[2.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]});
    let (status, _, body) = post_overlay(&server, "street", "", &bent).await;
    assert_eq!((status, error_type(&body).as_str()), (422, "invalid_input"));
    let both = json!({"image": b64(&png_bytes(&plain)), "intrinsics": k, "camera_from_map": rig_matrix(), "max_iterations": 3});
    let (status, _, body) = post_overlay(&server, "street", "", &both).await;
    assert_eq!((status, error_type(&body).as_str()), (422, "invalid_input"));
    let (status, _, body) = post_overlay(&server, "street", "?iterations=true", &body_with_pose(&plain)).await;
    assert_eq!((status, error_type(&body).as_str()), (422, "invalid_input"));
    server.stop().await;
}

fn body_with_pose(plain: &image::RgbImage) -> serde_json::Value {
    json!({"image": b64(&png_bytes(plain)), "intrinsics": {"fx": 700.0, "fy": 700.0, "cx": 600.0, "cy": 180.0}, "camera_from_map": rig_matrix()})
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_overlay_requests_get_localize_errors() {
    let extend = |base: &serde_json::Value, more: serde_json::Value| {
        let mut r = base.clone();
        for (k, v) in more.as_object().unwrap() {
            r[k] = v.clone();
        }
        r
    };
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &[]).await;
    let jpeg = jpeg_bytes(&test_image(1241, 376));
    let with = |image: &[u8]| {
        let mut r = kitti_request(2);
        r["image"] = json!(b64(image));
        r
    };
    let cases = [
        ("cut jpeg", "street", with(&jpeg[..jpeg.len() * 2 / 3]), 400, "corrupt_image"),
        ("not base64", "street", json!({"image": "%%%", "intrinsics": kitti_request(1)["intrinsics"]}), 400, "bad_request"),
        ("unknown map", "nowhere", kitti_request(2), 404, "not_found"),
        ("bad intrinsics", "street", json!({"image": kitti_request(1)["image"], "intrinsics": {"fx": -1.0, "fy": 700.0, "cx": 1.0, "cy": 1.0}}), 422, "invalid_input"),
        ("too many iterations", "street", extend(&with(&jpeg), json!({"max_iterations": 99})), 422, "invalid_input"),
        ("too many starts along the axis", "street", extend(&with(&jpeg), json!({"hypotheses": 4, "axis_starts": {"each_way": 2}})), 422, "invalid_input"),
        ("a drawn pose with axis starts", "street", json!({"image": b64(&jpeg), "intrinsics": kitti_request(1)["intrinsics"], "camera_from_map": [[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], "axis_starts": {"each_way": 1}}), 422, "invalid_input"),
    ];
    for (name, map, body, status, kind) in cases {
        let (got, headers, bytes) = post_overlay(&server, map, "", &body).await;
        assert_eq!((got, error_type(&bytes).as_str()), (status, kind), "{name}");
        assert!(headers["content-type"].to_str().unwrap().starts_with("application/json"), "{name}");
        // localize answers the same request the same way.
        if body.get("camera_from_map").is_none() {
            let (got, answer, _) = server.localize(map, &body).await;
            assert_eq!((got, answer["error_type"].as_str().unwrap()), (status, kind), "{name} via localize");
        }
    }
    // An unknown field or query parameter, and a wrong content type.
    let mut extra = kitti_request(1);
    extra["colour"] = json!("red");
    let (status, _, body) = post_overlay(&server, "street", "", &extra).await;
    assert_eq!((status, error_type(&body).as_str()), (422, "invalid_input"));
    let (status, _, body) = post_overlay(&server, "street", "?zoom=2", &kitti_request(1)).await;
    assert_eq!((status, error_type(&body).as_str()), (422, "invalid_input"));
    let r = server.client.post(server.url("/v1/maps/street/overlay")).header("content-type", "text/plain").body("hi").send().await.unwrap();
    assert_eq!(r.status(), 415);
    server.stop().await;
}

/// `cmr-agent eval` with a model writes the agent's K worst cases as three-panel pictures.
#[test]
fn eval_writes_worst_case_pictures() {
    let dir = tempfile::tempdir().unwrap();
    let (data, out) = (dir.path().join("data"), dir.path().join("out"));
    write_sequence(&data, 3);
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_cmr-agent"))
        .args(["eval", "--data", data.to_str().unwrap(), "--perturbations", out.join("p.json").to_str().unwrap()])
        .args(["--out", out.to_str().unwrap(), "--models", tiny_model().to_str().unwrap(), "--iterations", "2", "--hypotheses", "1"])
        .args(["--worst", "2", "--quiet", "--threads", "1"])
        .stdout(std::process::Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
    let index: Vec<serde_json::Value> = serde_json::from_str(&std::fs::read_to_string(out.join("worst/index.json")).unwrap()).unwrap();
    assert_eq!(index.len(), 2);
    assert_eq!(index[0]["method"], "cmr-agent");
    assert!(index[0]["final_rte_m"].as_f64().unwrap() >= index[1]["final_rte_m"].as_f64().unwrap());
    let pngs: Vec<_> = std::fs::read_dir(out.join("worst")).unwrap().flatten().filter(|e| e.path().extension().is_some_and(|x| x == "png")).collect();
    assert_eq!(pngs.len(), 2);
    for w in &index {
        let img = image::open(out.join("worst").join(w["file"].as_str().unwrap())).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (1241, 3 * (LABEL_BAR + 376)), "prior, final and truth");
    }
}

/// `cmr-agent eval` without `--models` evaluates `models/` of the working directory, as `serve`
/// serves it; `--reference-only` runs the expert and the no-op alone; with neither flag nor a
/// model set there it refuses, naming both ways out.
#[test]
fn eval_uses_the_served_models_by_default() {
    let dir = tempfile::tempdir().unwrap();
    let (data, out) = (dir.path().join("data"), dir.path().join("out"));
    write_sequence(&data, 2);
    let eval = |cwd: &std::path::Path, extra: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_cmr-agent"))
            .current_dir(cwd)
            .env_remove("CMR_MODELS")
            .args(["eval", "--data", data.to_str().unwrap(), "--perturbations", out.join("p.json").to_str().unwrap()])
            .args(["--out", out.to_str().unwrap(), "--iterations", "2", "--hypotheses", "1", "--worst", "0", "--quiet", "--threads", "1"])
            .args(extra)
            .output()
            .unwrap()
    };
    let methods = || -> std::collections::BTreeSet<String> {
        let cases: Vec<serde_json::Value> = serde_json::from_str(&std::fs::read_to_string(out.join("cases.json")).unwrap()).unwrap();
        cases.iter().map(|c| c["method"].as_str().unwrap().to_string()).collect()
    };
    let empty = tempfile::tempdir().unwrap();
    let refused = eval(empty.path(), &[]);
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && stderr.contains("--models") && stderr.contains("--reference-only"), "{stderr}");
    assert!(!out.join("p.json").exists(), "a refused run writes nothing");
    assert!(eval(empty.path(), &["--reference-only"]).status.success());
    assert_eq!(methods(), ["expert (oracle)", "no-op"].map(String::from).into());
    let served = tempfile::tempdir().unwrap();
    copy_dir(&tiny_model(), &served.path().join("models"));
    assert!(eval(served.path(), &[]).status.success());
    assert!(methods().contains("cmr-agent"), "{:?}", methods());
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap().flatten() {
        std::fs::copy(entry.path(), to.join(entry.file_name())).unwrap();
    }
}

/// A tiny KITTI-odometry sequence: the street cloud as every scan (velodyne axes), KITTI-like
/// calibration, the test image.
fn write_sequence(root: &std::path::Path, frames: usize) {
    let seq = root.join("00");
    std::fs::create_dir_all(seq.join("velodyne")).unwrap();
    std::fs::create_dir_all(seq.join("image_2")).unwrap();
    let p = |tx: f64| format!("7.0e+02 0 6.2e+02 {tx} 0 7.0e+02 1.87e+02 0 0 0 1 0");
    let calib = format!("P0: {}\nP1: {}\nP2: {}\nP3: {}\nTr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27\n", p(0.0), p(-386.0), p(45.0), p(-337.0));
    std::fs::write(seq.join("calib.txt"), calib).unwrap();
    let scan = cmr_agent::maps::formats::write_kitti_bin(&street_cloud());
    for f in 0..frames {
        std::fs::write(seq.join("velodyne").join(format!("{f:06}.bin")), &scan).unwrap();
        test_image(1241, 376).save(seq.join("image_2").join(format!("{f:06}.png"))).unwrap();
    }
}
