//! Every endpoint of the real server over loopback HTTP, good and bad input.

mod server_common;

use server_common::*;
use serde_json::json;
use std::time::Duration;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn service_endpoints_and_a_localization() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &[]).await;
    let c = &server.client;

    let health: serde_json::Value = c.get(server.url("/health")).send().await.unwrap().json().await.unwrap();
    assert_eq!(health["status"], "ok");
    let ready: serde_json::Value = c.get(server.url("/ready")).send().await.unwrap().json().await.unwrap();
    assert_eq!(ready["ready"], true);
    let info: serde_json::Value = c.get(server.url("/v1/info")).send().await.unwrap().json().await.unwrap();
    assert_eq!(info["manifest"]["format"], "cmr-agent-manifest/1");
    assert_eq!(info["limits"]["max_iterations"], 50);

    let list: serde_json::Value = c.get(server.url("/v1/maps")).send().await.unwrap().json().await.unwrap();
    assert_eq!(list["maps"][0]["id"], "street");
    assert_eq!(list["maps"][0]["num_points"], 200 * 90);
    assert_eq!(list["maps"][0]["cached"], true, "maps are prepared during warm-up");
    let one: serde_json::Value = c.get(server.url("/v1/maps/street")).send().await.unwrap().json().await.unwrap();
    assert_eq!(one["metadata"]["description"], "test street");

    let (status, body, headers) = server.localize("street", &kitti_request(7)).await;
    assert_eq!(status, 200, "{body}");
    let iterations = body["iterations"].as_u64().unwrap();
    assert!(iterations <= 7, "the first round's steps, or a refinement start's (up to 3)");
    assert_eq!(body["trajectory"].as_array().unwrap().len() as u64, iterations);
    assert_close(&body["prior_camera_from_map"], rig_matrix(), "the prior defaults to the map's initial pose");
    assert_eq!(body["prior_source"], "region");
    if iterations == 0 {
        // The answer took no step of its own: the prior kept, or a refinement start that scored best.
        let chosen = &body["hypotheses"][body["chosen_hypothesis"].as_u64().unwrap() as usize];
        let unmoved = if body["kept_prior"] == true { &body["prior_camera_from_map"] } else { &chosen["start_camera_from_map"] };
        assert_eq!(unmoved, &body["polish"]["from_camera_from_map"]);
    } else {
        let last = &body["trajectory"][iterations as usize - 1];
        assert_eq!(last["camera_from_map"], body["polish"]["from_camera_from_map"], "the polish starts at the search's answer");
        assert_eq!(body["converged"], last["action"]["yaw_deg"] == 0.0 && last["action"]["tx_m"] == 0.0 && last["action"]["tz_m"] == 0.0);
        assert_eq!(last["probabilities"]["yaw_deg"].as_array().unwrap().len(), 11);
    }
    for key in ["queue", "decode", "image_encoder", "frustum_head", "agent_steps", "total"] {
        assert!(body["timings_ms"][key].as_f64().unwrap() >= 0.0, "{key}");
    }
    let timing = headers.get("server-timing").unwrap().to_str().unwrap();
    assert!(timing.contains("image_encoder;dur=") && timing.contains("total;dur="));
    let score = body["confidence"]["score"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&score));
    // The default multi-start search: 4 starts, the answer is the best-aligned one.
    assert_eq!(info["limits"]["default_hypotheses"], 4);
    assert_eq!(info["limits"]["merge_duplicates"], true);
    assert_eq!((&info["limits"]["keep_prior"], &info["limits"]["refine"]), (&true.into(), &true.into()));
    // The continuous polish: from the search's answer, never to a lower score, within its reach.
    assert_eq!(info["limits"]["polish"], true);
    let polish = &body["polish"];
    assert!(polish["alignment"].as_f64().unwrap() >= polish["from_alignment"].as_f64().unwrap(), "{polish}");
    let reach = cmr_agent::agent::polish::REACH;
    assert!(polish["rotation_deg"].as_f64().unwrap() <= reach.rotation_deg + 1e-6 && polish["translation_m"].as_f64().unwrap() <= reach.translation_m + 1e-6, "{polish}");
    // The polished choice: the answer and up to POLISH_CANDIDATES final poses apart from it,
    // each climbed within its own budget.
    let candidates = polish["candidates"].as_u64().unwrap();
    assert!((1..=1 + cmr_agent::agent::search::POLISH_CANDIDATES as u64).contains(&candidates), "{polish}");
    assert!((1..=candidates * cmr_agent::agent::polish::MAX_SCORES as u64).contains(&polish["scores"].as_u64().unwrap()), "{polish}");
    // Then the refinement round: four starts around the first round's answer, four around it
    // turned by 180°; the polished answer scores at least as well as every first-round final
    // pose (the polished choice compares peaks, so the pose it polished may score below one).
    let hypotheses = body["hypotheses"].as_array().unwrap();
    let offsets: Vec<f64> = hypotheses.iter().map(|h| h["start_yaw_offset_deg"].as_f64().unwrap()).collect();
    assert_eq!(offsets, vec![0.0, 90.0, 180.0, -90.0, 0.0, 30.0, -30.0, 15.0, 0.0, 30.0, -30.0, 15.0]);
    let refinement: Vec<bool> = hypotheses.iter().map(|h| h["refinement"].as_bool().unwrap()).collect();
    assert_eq!(refinement, [[false; 4], [true; 4], [true; 4]].concat());
    let polished = polish["alignment"].as_f64().unwrap();
    assert!(hypotheses[..4].iter().all(|h| h["alignment"].as_f64().unwrap() <= polished));
    let answer = body["confidence"]["alignment"].as_f64().unwrap();
    if iterations > 0 {
        assert_eq!(body["trajectory"][iterations as usize - 1]["alignment"].as_f64().unwrap(), answer);
    }

    // A JPEG and an explicit prior work too.
    let img = test_image(800, 300);
    let prior = [[0.0, -1.0, 0.0, 1.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 0.0, 1.0]];
    let req = json!({"image": b64(&jpeg_bytes(&img)), "intrinsics": {"fx": 500.0, "fy": 500.0, "cx": 399.5, "cy": 149.5},
        "prior_camera_from_map": prior, "max_iterations": 2, "hypotheses": 1});
    let (status, body, _) = server.localize("street", &req).await;
    assert_eq!(status, 200, "{body}");
    assert_close(&body["prior_camera_from_map"], prior, "explicit prior");
    assert_eq!(body["prior_source"], "request");
    assert_eq!((body["hypotheses"].as_array().unwrap().len(), body["chosen_hypothesis"].as_u64()), (1, Some(0)));

    // The raw-bytes variant: the image is the body, the intrinsics are in the query.
    let raw = c.post(server.url("/v1/maps/street/localize?fx=500&fy=500&cx=399.5&cy=149.5&max_iterations=2&hypotheses=2"))
        .header("content-type", "image/jpeg").body(jpeg_bytes(&img)).send().await.unwrap();
    assert_eq!(raw.status(), 200);
    let raw: serde_json::Value = raw.json().await.unwrap();
    assert!(raw["iterations"].as_u64().unwrap() <= 2);
    let first_round = raw["hypotheses"].as_array().unwrap().iter().filter(|h| h["refinement"] == false).count();
    assert_eq!(first_round, 2);
    let raw = c.post(server.url("/v1/maps/street/localize?fx=500&fy=500&cx=399.5"))
        .header("content-type", "image/png").body(png_bytes(&img)).send().await.unwrap();
    assert_eq!(raw.status(), 422, "cy is missing");
    let raw = c.post(server.url("/v1/maps/street/localize?fx=500&fy=500&cx=1&cy=1&fz=3"))
        .header("content-type", "image/png").body(png_bytes(&img)).send().await.unwrap();
    assert_eq!(raw.status(), 422, "unknown query parameter");

    let metrics = c.get(server.url("/metrics")).send().await.unwrap().text().await.unwrap();
    for name in ["cmr_http_requests_total", "cmr_requests_total", "cmr_phase_seconds", "cmr_batch_size", "cmr_queue_depth", "cmr_cache_hits_total", "cmr_cache_bytes"] {
        assert!(metrics.contains(name), "/metrics lacks {name}");
    }
    assert!(metrics.contains("outcome=\"ok\""));

    let missing = c.get(server.url("/no/such/thing")).send().await.unwrap();
    assert_eq!(missing.status(), 404);

    // Every answer carries a request id: the client's own when it sends a sane one, else a new one.
    let r = c.get(server.url("/health")).header("x-request-id", "fleet-7.a:1").send().await.unwrap();
    assert_eq!(r.headers()["x-request-id"], "fleet-7.a:1");
    let ids: Vec<String> = [c.get(server.url("/health")).header("x-request-id", "has space").send().await.unwrap(), missing]
        .iter()
        .map(|r| r.headers()["x-request-id"].to_str().unwrap().to_string())
        .collect();
    assert!(ids[0] != ids[1] && ids.iter().all(|id| id.len() > 8 && id.contains('-') && !id.contains(' ')), "{ids:?}");
    server.stop().await;
}

/// A region added the README's way (a bare scan, no metadata) answers a request without a prior
/// from the documented default (a level camera at the map's origin looking along +x, which sees
/// the scan), and says so; a region whose map-frame origin is not inside it has no default: 422
/// naming prior_camera_from_map, until its metadata gives an initial pose.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_region_without_a_prior_starts_from_the_documented_default_or_says_what_is_missing() {
    let maps = tempfile::tempdir().unwrap();
    let server = TestServer::start(&tiny_model(), maps.path(), &[]).await;
    let c = &server.client;
    let cloud = street_cloud();
    let r = c.put(server.url("/v1/maps/my-street?format=kitti_bin")).body(cmr_agent::maps::formats::write_kitti_bin(&cloud)).send().await.unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    let (status, body, _) = server.localize("my-street", &kitti_request(2)).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["prior_source"], "default");
    let default = cmr_agent::geometry::Pose::level_camera_along_x(nalgebra::Vector3::zeros());
    assert_close(&body["prior_camera_from_map"], default.to_rows(), "the default prior");
    let k = cmr_agent::geometry::Intrinsics { fx: 718.856, fy: 718.856, cx: 607.1928, cy: 185.2157 };
    let in_view = cloud.xyz.iter().filter(|p| {
        let q = default.transform(&nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64));
        k.in_frustum(&q, 1241, 376)
    });
    assert!(in_view.count() > 2000, "the default prior looks at the scan");

    // The same street at UTM-size coordinates: the map frame's origin is 5,000 km away.
    let ply = utm_ply(&cloud, [500_000.0, 5_049_000.0, 100.0]);
    let r = c.put(server.url("/v1/maps/utm-street?format=ply")).body(ply).send().await.unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    let (status, body, _) = server.localize("utm-street", &kitti_request(2)).await;
    assert_eq!(status, 422, "{body}");
    assert_eq!(body["error_type"], "invalid_input");
    let error = body["error"].as_str().unwrap();
    assert!(error.starts_with("prior_camera_from_map: map \"utm-street\" has no initial_camera_from_map") && error.contains("/v1/maps/utm-street/metadata"), "{error}");
    let rig = cmr_agent::geometry::Pose::level_camera_along_x(nalgebra::Vector3::new(500_000.0, 5_049_000.0, 100.0));
    let r = c.put(server.url("/v1/maps/utm-street/metadata")).json(&json!({"initial_camera_from_map": rig.to_rows()})).send().await.unwrap();
    assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
    let (status, body, _) = server.localize("utm-street", &kitti_request(2)).await;
    assert_eq!((status, &body["prior_source"]), (200, &json!("region")), "{body}");
    server.stop().await;
}

/// The binary's own log: one access line per request (method, path without the query, status,
/// latency, request id), and no ANSI colour codes when stderr is not a terminal (a pipe here).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_logs_one_plain_access_line_per_request() {
    use std::io::BufRead;
    let maps = maps_dir_with_street();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_cmr-agent"))
        .args(["serve", "--host", "127.0.0.1", "--port", "0", "--intra-threads", "1", "--models"])
        .arg(tiny_model())
        .arg("--maps")
        .arg(maps.path())
        .env_remove("NO_COLOR")
        .env("RUST_LOG", "info")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let (tx, rx) = std::sync::mpsc::channel::<String>();
    let stderr = child.stderr.take().unwrap();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let mut seen = Vec::new();
    let next_line = |what: &str, seen: &mut Vec<String>| -> String {
        let line = rx.recv_timeout(Duration::from_secs(60)).unwrap_or_else(|_| panic!("no {what} in the log: {seen:#?}"));
        seen.push(line.clone());
        line
    };
    let base = loop {
        let line = next_line("listening line", &mut seen);
        if let Some(at) = line.find("listening on http://") {
            break line[at + "listening on ".len()..].trim().to_string();
        }
    };
    let client = reqwest::Client::new();
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while client.get(format!("{base}/ready")).send().await.map(|r| r.status() != 200).unwrap_or(true) {
        assert!(std::time::Instant::now() < deadline, "never ready: {seen:#?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let r = client.get(format!("{base}/v1/maps/nothing-here?token=secret")).header("x-request-id", "log-test-1").send().await.unwrap();
    assert_eq!(r.status(), 404);
    let access = loop {
        let line = next_line("access line", &mut seen);
        if line.contains("request_id=log-test-1") {
            break line;
        }
    };
    let _ = child.kill();
    let _ = child.wait();
    assert!(access.contains("INFO access: method=GET path=/v1/maps/nothing-here status=404 latency_ms="), "{access}");
    assert!(!access.contains("secret"), "the query is not logged: {access}");
    assert!(seen.iter().all(|l| !l.contains('\u{1b}')), "colour codes in a piped log: {seen:#?}");
}

/// A float64 PLY of `cloud` moved by `offset` (UTM-size coordinates stay exact).
fn utm_ply(cloud: &cmr_agent::maps::formats::PointCloud, offset: [f64; 3]) -> Vec<u8> {
    let mut out = Vec::new();
    let points = cloud.xyz.iter().map(|p| ([p[0] as f64 + offset[0], p[1] as f64 + offset[1], p[2] as f64 + offset[2]], 0.0f32));
    cmr_agent::maps::formats::write_ply_f64(&mut out, cloud.xyz.len(), points).unwrap();
    out
}

/// The compact points route gives the prepared sample's prefix as little-endian float32; the
/// web page's files are served from the binary; each hypothesis names its start.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn points_route_page_files_and_hypothesis_starts() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &[]).await;
    let c = &server.client;
    let entry = server.state.maps.store.get("street").unwrap();
    let prepared = server.state.maps.prepared_for(&entry).unwrap();

    let r = c.get(server.url("/v1/maps/street/points?max=100")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "application/octet-stream");
    assert_eq!(r.headers()["x-point-count"], "100");
    assert_eq!(r.headers()["x-points-total"], (200 * 90).to_string().as_str());
    let r_origin = r.headers()["x-map-origin"].to_str().unwrap().to_string();
    let bytes = r.bytes().await.unwrap();
    assert_eq!(bytes.len(), 100 * 12);
    let got: Vec<f32> = bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
    let want: Vec<f32> = prepared.drawing_sample(100).0.iter().flatten().copied().collect();
    assert_eq!(got, want, "the first 100 points of the prepared sample, x y z little-endian");
    assert_eq!(r_origin, "0,0,0", "a region near the map origin is stored unshifted");

    let r = c.get(server.url("/v1/maps/street/points")).send().await.unwrap();
    let count = prepared.drawing_sample(usize::MAX).0.len().min(20_000);
    assert_eq!(r.headers()["x-point-count"], count.to_string().as_str());
    assert_eq!(r.bytes().await.unwrap().len(), count * 12, "default max 20000, at most the sample");
    for (query, status, kind) in [
        ("max=0", 422, "invalid_input"),
        ("max=100001", 422, "invalid_input"),
        ("max=-3", 422, "invalid_input"),
        ("max=lots", 422, "invalid_input"),
        ("limit=5", 422, "invalid_input"),
    ] {
        let r = c.get(server.url(&format!("/v1/maps/street/points?{query}"))).send().await.unwrap();
        assert_eq!(r.status(), status, "{query}");
        let body: serde_json::Value = r.json().await.unwrap();
        assert_eq!(body["error_type"], kind, "{query}: {body}");
    }
    for (path, status, kind) in [("/v1/maps/nowhere/points", 404, "not_found"), ("/v1/maps/Bad%21/points", 400, "bad_request")] {
        let r = c.get(server.url(path)).send().await.unwrap();
        assert_eq!(r.status(), status, "{path}");
        let body: serde_json::Value = r.json().await.unwrap();
        assert_eq!(body["error_type"], kind, "{path}: {body}");
    }

    // The page and its files, from the binary, allowed to load from this origin only.
    let page = c.get(server.url("/")).send().await.unwrap();
    assert_eq!(page.status(), 200);
    assert_eq!(page.headers()["content-type"], "text/html; charset=utf-8");
    assert!(page.headers()["content-security-policy"].to_str().unwrap().starts_with("default-src 'self'"));
    let html = page.text().await.unwrap();
    assert!(html.contains(r#"<script src="/ui/app.js""#) && html.contains(r#"href="/ui/style.css""#));
    assert!(!html.contains("http://") && !html.contains("https://"), "nothing from outside");
    for (asset, kind) in [("app.js", "text/javascript; charset=utf-8"), ("style.css", "text/css; charset=utf-8"), ("demo.json", "application/json")] {
        let r = c.get(server.url(&format!("/ui/{asset}"))).send().await.unwrap();
        assert_eq!(r.status(), 200, "{asset}");
        assert_eq!(r.headers()["content-type"], kind, "{asset}");
        let text = r.text().await.unwrap();
        assert_eq!(text.as_bytes(), std::fs::read(std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(match asset {
            "demo.json" => "examples/localize-demo.json".to_string(),
            a => format!("web/{a}"),
        })).unwrap(), "{asset} is the committed file");
    }
    for (path, status, kind) in [("/ui/secrets.txt", 404, "not_found"), ("/ui/%FF", 400, "bad_request"), ("/ui/a/b", 404, "not_found")] {
        let r = c.get(server.url(path)).send().await.unwrap();
        assert_eq!(r.status(), status, "{path}");
        assert_eq!(r.json::<serde_json::Value>().await.unwrap()["error_type"], kind, "{path}");
    }

    // Each hypothesis's start: the first is the prior, the second the prior turned by 180°.
    let mut req = kitti_request(2);
    req["hypotheses"] = json!(2);
    let (status, body, _) = server.localize("street", &req).await;
    assert_eq!(status, 200, "{body}");
    let h = body["hypotheses"].as_array().unwrap();
    assert_close(&h[0]["start_camera_from_map"], rig_matrix(), "the first start is the prior");
    assert_eq!(h[1]["start_yaw_offset_deg"], 180.0);
    let turned = &h[1]["start_camera_from_map"];
    assert!((turned[0][1].as_f64().unwrap() - 1.0).abs() < 1e-9, "a half turn about the vertical flips the heading: {turned}");
    server.stop().await;
}

fn assert_close(got: &serde_json::Value, want: [[f64; 4]; 4], what: &str) {
    for r in 0..4 {
        for c in 0..4 {
            let g = got[r][c].as_f64().unwrap();
            assert!((g - want[r][c]).abs() < 1e-9, "{what}: [{r}][{c}] = {g}, want {}", want[r][c]);
        }
    }
}

/// A PNG header claiming `width` x `height` (valid CRC), followed by nothing.
fn png_header_only(width: u32, height: u32) -> Vec<u8> {
    let mut ihdr = b"IHDR".to_vec();
    ihdr.extend_from_slice(&width.to_be_bytes());
    ihdr.extend_from_slice(&height.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    out.extend_from_slice(&13u32.to_be_bytes());
    out.extend_from_slice(&ihdr);
    out.extend_from_slice(&crc32(&ihdr).to_be_bytes());
    out
}

/// A PNG that declares `width` x `height` and holds no pixel data: a decoder learns the size
/// from it (the header and the start of the image data) before it would allocate anything.
fn png_declaring(width: u32, height: u32) -> Vec<u8> {
    let mut out = png_header_only(width, height);
    out.extend_from_slice(&0u32.to_be_bytes());
    out.extend_from_slice(b"IDAT");
    out.extend_from_slice(&crc32(b"IDAT").to_be_bytes());
    out
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xffff_ffffu32;
    for b in bytes {
        crc ^= *b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 { (crc >> 1) ^ 0xedb8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_localize_requests_get_clear_errors() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--max-body-bytes", "400000"]).await;
    let good = kitti_request(2);
    let png = png_bytes(&test_image(640, 200));
    let jpeg = jpeg_bytes(&test_image(640, 200));
    let k = json!({"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 99.5});
    let with = |patch: serde_json::Value| {
        let mut v = json!({"image": b64(&png), "intrinsics": k, "max_iterations": 2});
        for (key, value) in patch.as_object().unwrap() {
            v[key] = value.clone();
        }
        v
    };
    let cases: Vec<(&str, serde_json::Value, u16, &str)> = vec![
        ("unknown map", good.clone(), 404, "not_found"),
        ("truncated png", with(json!({"image": b64(&png[..png.len() / 2])})), 400, "corrupt_image"),
        ("garbage image", with(json!({"image": b64(b"\x89PNG\r\n\x1a\nthis is not a png at all")})), 400, "corrupt_image"),
        ("not base64", with(json!({"image": "%%% not base64 %%%"})), 400, "bad_request"),
        ("gif", with(json!({"image": b64(b"GIF89a\x01\x00\x01\x00\x00\x00\x00;")})), 415, "unsupported_media_type"),
        ("zero width", with(json!({"image": b64(&png_header_only(0, 100))})), 400, "corrupt_image"),
        ("huge dimensions", with(json!({"image": b64(&png_header_only(100_000, 100_000))})), 413, "payload_too_large"),
        ("negative fx", with(json!({"intrinsics": {"fx": -500.0, "fy": 500.0, "cx": 1.0, "cy": 1.0}})), 422, "invalid_input"),
        ("null fy", with(json!({"intrinsics": {"fx": 500.0, "fy": null, "cx": 1.0, "cy": 1.0}})), 422, "invalid_input"),
        ("zero iterations", with(json!({"max_iterations": 0})), 422, "invalid_input"),
        ("too many iterations", with(json!({"max_iterations": 51})), 422, "invalid_input"),
        ("zero hypotheses", with(json!({"hypotheses": 0})), 422, "invalid_input"),
        ("too many hypotheses", with(json!({"hypotheses": 17})), 422, "invalid_input"),
        ("non-rigid prior", with(json!({"prior_camera_from_map": [[2.0,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]})), 422, "invalid_input"),
        ("missing image", json!({"intrinsics": k}), 422, "invalid_input"),
        ("unknown field", with(json!({"imgae": "x"})), 422, "invalid_input"),
        // Well-formed JSON of the wrong shape is 422, not a syntax error.
        ("prior row of 5", with(json!({"prior_camera_from_map": [[1,0,0,0,7],[0,1,0,0],[0,0,1,0],[0,0,0,1]]})), 422, "invalid_input"),
        ("prior of 3 rows", with(json!({"prior_camera_from_map": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]})), 422, "invalid_input"),
        ("absurd prior", with(json!({"prior_camera_from_map": [[1,0,0,3e38],[0,1,0,0],[0,0,1,0],[0,0,0,1]]})), 422, "invalid_input"),
        ("truncated jpeg", with(json!({"image": b64(&jpeg[..jpeg.len() * 2 / 3])})), 400, "corrupt_image"),
        // Inside the side limit, over the pixel budget: refused from the header alone.
        ("64 MP image", with(json!({"image": b64(&png_declaring(8000, 8000))})), 413, "payload_too_large"),
        // Covering the model input would resize a 1x8192 strip to 512x4,194,304 pixels.
        ("thin strip", with(json!({"image": b64(&png_bytes(&test_image(1, 8192)))})), 422, "invalid_input"),
    ];
    for (name, body, status, error_type) in cases {
        let map = if name == "unknown map" { "nowhere" } else { "street" };
        let (got, json, _) = server.localize(map, &body).await;
        assert_eq!(got, status, "{name}: {json}");
        assert_eq!(json["error_type"], error_type, "{name}: {json}");
        assert!(!json["error"].as_str().unwrap().is_empty(), "{name}");
    }

    let raw = |body: &'static str, ct: &'static str| {
        server.client.post(server.url("/v1/maps/street/localize")).header("content-type", ct).body(body).send()
    };
    let r = raw("{\"image\": ", "application/json").await.unwrap();
    assert_eq!(r.status(), 400);
    assert_eq!(r.json::<serde_json::Value>().await.unwrap()["error_type"], "malformed_json");
    // NaN is not JSON: the request is malformed, not a number.
    let r = raw("{\"image\": \"\", \"intrinsics\": {\"fx\": NaN, \"fy\": 1, \"cx\": 1, \"cy\": 1}}", "application/json").await.unwrap();
    assert_eq!(r.status(), 400);
    let r = raw("hello", "text/plain").await.unwrap();
    assert_eq!(r.status(), 415);
    let r = server.client.post(server.url("/v1/maps/Bad.Id/localize")).json(&with(json!({}))).send().await.unwrap();
    assert_eq!(r.status(), 400);
    assert_eq!(r.json::<serde_json::Value>().await.unwrap()["error_type"], "bad_request");

    let big = with(json!({"image": "A".repeat(500_000)}));
    let (status, json, _) = server.localize("street", &big).await;
    assert_eq!(status, 413, "{json}");
    assert_eq!(json["error_type"], "payload_too_large");

    // Nothing above disturbed the stored map.
    let (status, _, _) = server.localize("street", &with(json!({}))).await;
    assert_eq!(status, 200);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn map_management_is_atomic_and_persistent() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--admin-token", "s3cret"]).await;
    let c = &server.client;
    let auth = "Bearer s3cret";

    // An ASCII PLY upload (sniffed) registers a new region.
    let mut ply = String::from("ply\nformat ascii 1.0\nelement vertex 3000\nproperty float x\nproperty float y\nproperty float z\nend_header\n");
    for i in 0..3000 {
        ply.push_str(&format!("{} {} {}\n", (i % 100) as f32 * 0.3, (i / 100) as f32 * 0.5 - 7.0, -1.7 + (i % 7) as f32 * 0.2));
    }
    let r = c.put(server.url("/v1/maps/yard")).body(ply.clone()).send().await.unwrap();
    assert_eq!(r.status(), 401, "map management needs the token");
    let r = c.put(server.url("/v1/maps/yard?description=a%20yard")).header("authorization", auth).body(ply.clone()).send().await.unwrap();
    assert_eq!(r.status(), 201);
    let reg: serde_json::Value = r.json().await.unwrap();
    assert_eq!(reg["map"]["num_points"], 3000);
    assert_eq!(reg["map"]["metadata"]["description"], "a yard");
    assert_eq!(reg["replaced"], false);
    assert!(maps.path().join("yard.bin").exists());
    server.flush_writes().await; // the embeddings follow the answer
    let emb = std::fs::read(maps.path().join("yard.emb")).unwrap();
    assert_eq!(&emb[72..136], reg["map"]["source_sha256"].as_str().unwrap().as_bytes(), "yard.emb names the stored cloud");

    // A corrupt upload is refused and leaves the stored region as it was.
    let before = std::fs::read(maps.path().join("yard.bin")).unwrap();
    let corrupt = "ply\nformat ascii 1.0\nelement vertex 3000\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 three\n";
    for (body, query) in [(corrupt.as_bytes().to_vec(), ""), (vec![1u8, 2, 3], ""), (vec![0u8; 32], "?format=pcd"), (vec![0u8; 32], "?format=xyz")] {
        let r = c.put(server.url(&format!("/v1/maps/yard{query}"))).header("authorization", auth).body(body).send().await.unwrap();
        assert_eq!(r.status(), 422, "{query}");
        let e: serde_json::Value = r.json().await.unwrap();
        assert!(!e["error"].as_str().unwrap().is_empty());
    }
    assert_eq!(std::fs::read(maps.path().join("yard.bin")).unwrap(), before);
    let (status, _, _) = server.localize("yard", &kitti_request(1)).await;
    assert_eq!(status, 200, "the previous region still localizes");

    // Replacing with a KITTI .bin answers 200 and keeps the metadata.
    let r = c.put(server.url("/v1/maps/yard?format=kitti_bin")).header("authorization", auth)
        .body(cmr_agent::maps::formats::write_kitti_bin(&street_cloud())).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let reg: serde_json::Value = r.json().await.unwrap();
    assert_eq!(reg["replaced"], true);
    assert_eq!(reg["map"]["metadata"]["description"], "a yard");

    // Metadata: valid and invalid.
    let r = c.put(server.url("/v1/maps/yard/metadata")).header("authorization", auth)
        .json(&serde_json::json!({"description": "moved", "initial_camera_from_map": rig_matrix()})).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let r = c.put(server.url("/v1/maps/yard/metadata")).header("authorization", auth)
        .json(&serde_json::json!({"initial_camera_from_map": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[1,0,0,1]]})).send().await.unwrap();
    assert_eq!(r.status(), 422);
    let r = c.put(server.url("/v1/maps/Bad!/metadata")).header("authorization", auth).json(&serde_json::json!({})).send().await.unwrap();
    assert_eq!(r.status(), 400);

    // Restart: the embeddings come from yard.emb, not recomputed (the file is not rewritten).
    server.flush_writes().await;
    let emb_modified = std::fs::metadata(maps.path().join("yard.emb")).unwrap().modified().unwrap();
    server.stop().await;
    let server = TestServer::start(&tiny_model(), maps.path(), &["--admin-token", "s3cret"]).await;
    let one: serde_json::Value = server.client.get(server.url("/v1/maps/yard")).send().await.unwrap().json().await.unwrap();
    assert_eq!(one["metadata"]["description"], "moved");
    assert_eq!(one["cached"], true);
    assert_eq!(std::fs::metadata(maps.path().join("yard.emb")).unwrap().modified().unwrap(), emb_modified);

    // Delete.
    let c = &server.client;
    let r = c.delete(server.url("/v1/maps/yard")).send().await.unwrap();
    assert_eq!(r.status(), 401);
    let r = c.delete(server.url("/v1/maps/yard")).header("authorization", auth).send().await.unwrap();
    assert_eq!(r.status(), 204);
    assert!(!maps.path().join("yard.bin").exists() && !maps.path().join("yard.emb").exists());
    let r = c.delete(server.url("/v1/maps/yard")).header("authorization", auth).send().await.unwrap();
    assert_eq!(r.status(), 404);
    let (status, _, _) = server.localize("yard", &kitti_request(1)).await;
    assert_eq!(status, 404);
    let (status, _, _) = server.localize("street", &kitti_request(1)).await;
    assert_eq!(status, 200, "other regions are untouched");
    server.stop().await;
}

#[test]
fn a_broken_model_directory_is_one_clear_start_up_error() {
    let dir = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(tiny_model()).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), dir.path().join(entry.file_name())).unwrap();
    }
    std::fs::write(dir.path().join("agent.onnx"), b"not an onnx file").unwrap();
    let maps = tempfile::tempdir().unwrap();
    let config = cmr_agent::api::ServeArgs::from_flags(["--models", dir.path().to_str().unwrap(), "--maps", maps.path().to_str().unwrap()]).unwrap();
    let err = format!("{:#}", cmr_agent::api::build_state(config).err().expect("refused"));
    assert!(err.contains("sha256") && err.contains("agent"), "{err}");
}

#[test]
fn committed_openapi_document_is_current() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("openapi/openapi.json");
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == cmr_agent::api::openapi::schema_json(),
        "openapi/openapi.json is stale: run `./target/release/cmr-agent print-schema > openapi/openapi.json`"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cache_budget_evicts_and_reloads_from_disk() {
    // Each prepared map holds 40,960 x (12 + 256) bytes, about 10.5 MiB: a 16 MiB budget fits one.
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--cache-mb", "16"]).await;
    let r = server.client.put(server.url("/v1/maps/second?format=kitti_bin"))
        .body(cmr_agent::maps::formats::write_kitti_bin(&street_cloud())).send().await.unwrap();
    assert_eq!(r.status(), 201);
    for map in ["street", "second", "street", "second"] {
        let (status, body, _) = server.localize(map, &kitti_request(1)).await;
        assert_eq!(status, 200, "{map}: {body}");
        assert!(server.state.maps.cache.weighted_bytes() <= 16 * 1024 * 1024, "the budget holds");
    }
    use std::sync::atomic::Ordering::Relaxed;
    let maps_state = &server.state.maps;
    assert!(maps_state.cache.evictions.load(Relaxed) >= 3, "each switch evicts the other map");
    assert!(maps_state.loaded_from_disk.load(Relaxed) >= 3, "evicted maps come back from <id>.emb");
    assert_eq!(maps_state.computed.load(Relaxed), 1, "only street, at warm-up (no .emb yet), was computed");
    let metrics = server.client.get(server.url("/metrics")).send().await.unwrap().text().await.unwrap();
    assert!(metrics.contains("cmr_cache_evictions_total") && metrics.contains("cmr_embeddings_loaded_total"));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deadlines_and_draining_answer_503() {
    let maps = maps_dir_with_street();
    // A 1 ms deadline passes while the 1241x376 image is decoded: the worker refuses the job.
    let server = TestServer::start(&tiny_model(), maps.path(), &["--request-timeout-ms", "1"]).await;
    let (status, body, _) = server.localize("street", &kitti_request(5)).await;
    assert_eq!(status, 503, "{body}");
    assert_eq!(body["error_type"], "deadline_exceeded");

    server.state.lifecycle.start_drain();
    let r = server.client.get(server.url("/ready")).send().await.unwrap();
    assert_eq!(r.status(), 503);
    let (status, body, _) = server.localize("street", &kitti_request(1)).await;
    assert_eq!(status, 503);
    assert_eq!(body["error_type"], "draining");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trickled_upload_gets_408_and_leaves_the_region_intact() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let maps = maps_dir_with_street();
    let before = std::fs::read(maps.path().join("street.bin")).unwrap();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--body-timeout-ms", "400"]).await;
    let addr = server.base.trim_start_matches("http://").to_string();
    let stream = tokio::net::TcpStream::connect(&addr).await.unwrap();
    let (mut reader, mut writer) = stream.into_split();
    // A client that keeps sending a few bytes at a time: each gap is short, the whole is too slow.
    let trickle = tokio::spawn(async move {
        let head = format!("PUT /v1/maps/street?format=kitti_bin HTTP/1.1\r\nhost: {addr}\r\ncontent-length: 160000\r\n\r\n");
        writer.write_all(head.as_bytes()).await.ok();
        for _ in 0..100 {
            if writer.write_all(&[0u8; 16]).await.is_err() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    });
    let started = std::time::Instant::now();
    let mut response = Vec::new();
    let mut buf = [0u8; 4096];
    while !String::from_utf8_lossy(&response).contains("}") {
        let n = tokio::time::timeout(Duration::from_secs(5), reader.read(&mut buf)).await.expect("answered in time").unwrap();
        if n == 0 {
            break;
        }
        response.extend_from_slice(&buf[..n]);
    }
    trickle.abort();
    let text = String::from_utf8_lossy(&response);
    assert!(text.starts_with("HTTP/1.1 408"), "{text}");
    assert!(text.contains("\"error_type\":\"body_timeout\""), "{text}");
    assert!(started.elapsed() < Duration::from_secs(3), "answered at the deadline, not when the client gave up");
    assert_eq!(std::fs::read(maps.path().join("street.bin")).unwrap(), before);
    let (status, _, _) = server.localize("street", &kitti_request(1)).await;
    assert_eq!(status, 200);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_replicas_on_one_map_directory_stay_consistent() {
    let maps = maps_dir_with_street();
    let a = TestServer::start(&tiny_model(), maps.path(), &[]).await;
    let b = TestServer::start(&tiny_model(), maps.path(), &[]).await;
    let cloud = |n: usize| {
        let mut c = street_cloud();
        c.xyz.truncate(n);
        c.intensity = None;
        cmr_agent::maps::formats::write_kitti_bin(&c)
    };
    let count = |server: &TestServer| {
        let url = server.url("/v1/maps/yard");
        let client = server.client.clone();
        async move {
            let r = client.get(url).send().await.unwrap();
            (r.status().as_u16(), r.json::<serde_json::Value>().await.unwrap_or_default()["num_points"].as_u64())
        }
    };
    // Uploaded through one replica: the other serves it.
    let r = a.client.put(a.url("/v1/maps/yard?format=kitti_bin")).body(cloud(5000)).send().await.unwrap();
    assert_eq!(r.status(), 201);
    assert_eq!(count(&b).await, (200, Some(5000)));
    let (status, first, _) = b.localize("yard", &kitti_request(2)).await;
    assert_eq!(status, 200, "{first}");
    // Replaced through one replica: the other drops its prepared copy and serves the new cloud.
    tokio::time::sleep(Duration::from_millis(20)).await; // a distinct mtime on coarse clocks
    let r = a.client.put(a.url("/v1/maps/yard?format=kitti_bin")).body(cloud(7000)).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(count(&b).await, (200, Some(7000)));
    let (status, _, _) = b.localize("yard", &kitti_request(2)).await;
    assert_eq!(status, 200);
    let source_points = |p: cmr_agent::maps::Prepared| match p {
        cmr_agent::maps::Prepared::Whole(m) => m.source_points,
        cmr_agent::maps::Prepared::Tiled(t) => t.points,
    };
    assert_eq!(b.state.maps.cache.get("yard").map(source_points), Some(7000), "B re-prepared the new cloud");
    // Deleted through one replica: gone on the other.
    let r = a.client.delete(a.url("/v1/maps/yard")).send().await.unwrap();
    assert_eq!(r.status(), 204);
    assert_eq!(count(&b).await.0, 404);
    let (status, _, _) = b.localize("yard", &kitti_request(2)).await;
    assert_eq!(status, 404);
    a.stop().await;
    b.stop().await;
}
