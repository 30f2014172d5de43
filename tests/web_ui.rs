//! The web page in a real browser: Debian's headless Chromium driven through chromedriver
//! (WebDriver, the `fantoccini` crate) against a real server on loopback with the project's
//! default model. It loads the page, picks an image through the file input and drops one on the
//! page, runs the demo, checks that the pose the page shows is the API's answer to the same
//! request, that both canvases are drawn (the top view without narrowing UTM-size coordinates to
//! float32) and the iteration slider redraws, that an API error is
//! shown as the API's `{error, error_type}`, and that a region can be uploaded and deleted with
//! the admin token.
//! It saves a screenshot to `target/web-ui.png` (and to `docs/web-ui.png` with
//! `CMR_UPDATE_DOCS=1`).
//!
//! Chromium and chromedriver come from `scripts/install-chromium.sh` (run by `make test`); set
//! `CHROMIUM` / `CHROMEDRIVER` to use others. Without them the test says SKIPPED, and why, on
//! the terminal (not captured) and returns; with `CMR_REQUIRE_BROWSER=1` it fails instead.

mod server_common;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::{Value, json};
use server_common::*;

const ADMIN_TOKEN: &str = "web-ui-test-token";

/// Writes past the test harness's output capture, so a skip is never silent.
fn say(line: &str) {
    let _ = writeln!(std::io::stderr(), "{line}");
}

/// `$env` when set (it must name a file), else the first of `names` on PATH; Err says why not.
fn find_program(env: &str, names: &[&str]) -> Result<PathBuf, String> {
    if let Some(p) = std::env::var_os(env).filter(|p| !p.is_empty()) {
        let p = PathBuf::from(p);
        return if p.is_file() { Ok(p) } else { Err(format!("{env}={} is not a file", p.display())) };
    }
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .flat_map(|dir| names.iter().map(move |n| dir.join(n)))
        .find(|p| p.is_file())
        .ok_or_else(|| format!("none of {names:?} on PATH"))
}

/// chromedriver on a free loopback port, killed on drop.
struct Driver {
    child: Child,
    url: String,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

async fn start_driver(chromedriver: &Path) -> Driver {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let child = Command::new(chromedriver)
        .arg(format!("--port={port}"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {}: {e}", chromedriver.display()));
    let driver = Driver { child, url: format!("http://127.0.0.1:{port}") };
    let client = reqwest::Client::new();
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        if let Ok(r) = client.get(format!("{}/status", driver.url)).send().await {
            if r.status().is_success() {
                return driver;
            }
        }
        assert!(Instant::now() < deadline, "chromedriver did not answer on {}", driver.url);
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn open_browser(driver: &Driver, chromium: &Path, profile: &Path) -> Client {
    let args = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        "--hide-scrollbars",
        "--window-size=1440,1150",
        &format!("--user-data-dir={}", profile.display()),
    ];
    let mut caps = serde_json::Map::new();
    caps.insert("goog:chromeOptions".into(), json!({"binary": chromium, "args": args}));
    ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(caps)
        .connect(&driver.url)
        .await
        .expect("a Chromium session")
}

/// Polls `script` (a JS expression) until it is truthy; its last value is returned.
async fn wait_for(c: &Client, script: &str, timeout: Duration, what: &str) -> Value {
    let deadline = Instant::now() + timeout;
    loop {
        let v = c.execute(&format!("return {script};"), vec![]).await.unwrap();
        let truthy = !matches!(&v, Value::Null | Value::Bool(false)) && v != json!("") && v != json!(0);
        if truthy {
            return v;
        }
        if Instant::now() >= deadline {
            let error = c.execute("return document.getElementById('error').textContent", vec![]).await.unwrap();
            panic!("timed out waiting for {what} ({script}); the page's error box: {error}");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn text(c: &Client, css: &str) -> String {
    c.find(Locator::Css(css)).await.unwrap_or_else(|e| panic!("{css}: {e}")).text().await.unwrap()
}

async fn js(c: &Client, script: &str) -> Value {
    c.execute(script, vec![]).await.unwrap_or_else(|e| panic!("{script}: {e}"))
}

/// Pixels of the image canvas that the drawn points changed: the canvas compared with the same
/// image drawn and darkened the same way without points.
const CHANGED_PIXELS: &str = r#"
const c = document.getElementById('image-canvas');
const a = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
const o = document.createElement('canvas');
o.width = c.width; o.height = c.height;
const x = o.getContext('2d');
x.drawImage(state.image.el, 0, 0, o.width, o.height);
x.fillStyle = 'rgba(0,0,0,0.35)';
x.fillRect(0, 0, o.width, o.height);
const b = x.getImageData(0, 0, o.width, o.height).data;
let n = 0;
for (let i = 0; i < a.length; i += 4) {
  if (Math.abs(a[i] - b[i]) + Math.abs(a[i + 1] - b[i + 1]) + Math.abs(a[i + 2] - b[i + 2]) > 60) n++;
}
return n;
"#;

/// Pixels of the top view that are not its background, and the orange of the selected camera.
const TOP_VIEW_PIXELS: &str = r#"
const c = document.getElementById('top-canvas');
const a = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
let drawn = 0, orange = 0;
for (let i = 0; i < a.length; i += 4) {
  if (a[i] !== 0x14 || a[i + 1] !== 0x17 || a[i + 2] !== 0x1c) drawn++;
  if (Math.abs(a[i] - 255) < 20 && Math.abs(a[i + 1] - 159) < 25 && Math.abs(a[i + 2] - 28) < 30) orange++;
}
return [drawn, orange];
"#;

/// Draws the top view of 41 rows of points 5 cm apart at a UTM-size northing (y ≈ 5,049,158 m,
/// where float32 steps are 0.5 m: narrowed, they would fall on 5 rows) and counts the bands of
/// drawn pixel rows above the scale bar; then puts the page's own points back.
const TOP_VIEW_UTM_ROWS: &str = r#"
const saved = [state.points, state.result];
const pts = [];
for (let i = 0; i <= 40; i++) for (let j = 0; j < 40; j++) pts.push(512345.0 + 0.1 * j, 5049158.0 + 0.05 * i, 0.0);
state.points = Float64Array.from(pts);
state.result = null;
drawTopView();
const c = document.getElementById('top-canvas');
const a = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
let bands = 0, previous = false;
for (let y = 0; y < c.height - 40; y++) {
  let any = false;
  for (let x = 0; x < c.width && !any; x++) {
    const i = 4 * (y * c.width + x);
    any = a[i] !== 0x14 || a[i + 1] !== 0x17 || a[i + 2] !== 0x1c;
  }
  if (any && !previous) bands++;
  previous = any;
}
[state.points, state.result] = saved;
draw();
return bands;
"#;

/// Sets an input's value as a person would (an `input` event follows).
async fn set_value(c: &Client, id: &str, value: &str) {
    c.execute(
        "const e = document.getElementById(arguments[0]); e.value = arguments[1]; e.dispatchEvent(new Event('input', {bubbles: true})); e.dispatchEvent(new Event('change', {bubbles: true}));",
        vec![json!(id), json!(value)],
    )
    .await
    .unwrap();
}

async fn run_and_wait(c: &Client) -> String {
    js(c, "document.body.dataset.state = 'clicked'; document.getElementById('run').click();").await;
    let s = wait_for(c, "['done', 'error'].includes(document.body.dataset.state) && document.body.dataset.state", Duration::from_secs(180), "the localization").await;
    s.as_str().unwrap().to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn web_page_in_chromium() {
    let required = std::env::var("CMR_REQUIRE_BROWSER").is_ok_and(|v| v == "1");
    let chromium = find_program("CHROMIUM", &["chromium", "chromium-browser", "google-chrome"]);
    let chromedriver = find_program("CHROMEDRIVER", &["chromedriver"]);
    let (chromium, chromedriver) = match (chromium, chromedriver) {
        (Ok(a), Ok(b)) => (a, b),
        (a, b) => {
            let reasons: Vec<String> = [a.err(), b.err()].into_iter().flatten().collect();
            let why = format!(
                "web_page_in_chromium SKIPPED: no browser: {} (run scripts/install-chromium.sh, or set CHROMIUM and CHROMEDRIVER)",
                reasons.join("; ")
            );
            say(&why);
            assert!(!required, "{why}, and CMR_REQUIRE_BROWSER=1");
            return;
        }
    };

    // A real server with the default model, the demo region and an admin token.
    let maps = tempfile::tempdir().unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for f in ["demo.bin", "demo.json"] {
        std::fs::copy(root.join("maps").join(f), maps.path().join(f)).unwrap();
    }
    let server = TestServer::start(&default_model(), maps.path(), &["--admin-token", ADMIN_TOKEN]).await;

    let driver = start_driver(&chromedriver).await;
    let profile = tempfile::tempdir().unwrap();
    let c = open_browser(&driver, &chromium, profile.path()).await;
    c.goto(&server.url("/")).await.unwrap();
    wait_for(&c, "document.body.dataset.state === 'idle'", Duration::from_secs(30), "the page to load the regions").await;
    assert_eq!(text(&c, "#regions button.selected").await.split_whitespace().next(), Some("demo"));
    assert!(text(&c, "#region-info").await.contains("Synthetic"), "the region's description is shown");
    // The top view shows the region before any localization.
    let top: Vec<u64> = serde_json::from_value(js(&c, TOP_VIEW_PIXELS).await).unwrap();
    assert!(top[0] > 3000, "top view drawn before localizing: {top:?}");

    // A person's own file through the file input: the KITTI-sized demo JPEG picks the KITTI preset.
    let demo: Value = serde_json::from_slice(&std::fs::read(root.join("examples/localize-demo.json")).unwrap()).unwrap();
    let jpeg = base64::Engine::decode(&base64::engine::general_purpose::STANDARD, demo["image"].as_str().unwrap()).unwrap();
    let picked = profile.path().join("street.jpg");
    std::fs::write(&picked, &jpeg).unwrap();
    set_value(&c, "preset", "custom").await;
    c.find(Locator::Id("file")).await.unwrap().send_keys(picked.to_str().unwrap()).await.unwrap();
    wait_for(&c, "document.getElementById('image-info').textContent.includes('street.jpg')", Duration::from_secs(10), "the picked image").await;
    assert_eq!(text(&c, "#image-info").await, "street.jpg: 1241×376");
    assert_eq!(js(&c, "return document.getElementById('preset').value").await, json!("kitti"));

    // A file dropped on the page (a real `drop` event carrying a File).
    let drop_file = r#"
        const bytes = Uint8Array.from(atob(arguments[0]), (ch) => ch.charCodeAt(0));
        const data = new DataTransfer();
        data.items.add(new File([bytes], 'dropped.jpg', {type: 'image/jpeg'}));
        document.getElementById('drop').dispatchEvent(new DragEvent('drop', {dataTransfer: data, bubbles: true, cancelable: true}));
    "#;
    c.execute(drop_file, vec![demo["image"].clone()]).await.unwrap();
    wait_for(&c, "document.getElementById('image-info').textContent === 'dropped.jpg: 1241×376'", Duration::from_secs(10), "the dropped image").await;

    // The demo, through the page.
    c.find(Locator::Id("demo")).await.unwrap().click().await.unwrap();
    wait_for(&c, "document.getElementById('image-info').textContent.startsWith('demo image')", Duration::from_secs(10), "the demo image").await;
    let outcome = run_and_wait(&c).await;
    assert_eq!(outcome, "done", "the page's error: {}", text(&c, "#error").await);
    let shown: Value = serde_json::from_str(c.find(Locator::Id("pose")).await.unwrap().attr("data-camera-from-map").await.unwrap().unwrap().as_str()).unwrap();

    // The same request straight to the API.
    let (status, answer, _) = server.localize("demo", &demo).await;
    assert_eq!(status, 200, "{answer}");
    let api_pose = &answer["pose"]["camera_from_map"];
    for i in 0..4 {
        for j in 0..4 {
            let (a, b) = (shown[i][j].as_f64().unwrap(), api_pose[i][j].as_f64().unwrap());
            assert!((a - b).abs() < 1e-9, "pose[{i}][{j}]: page {a}, API {b}");
        }
    }
    // ...and the numbers a person reads are the API's too.
    let cells: Vec<String> = serde_json::from_value(js(&c, "return [...document.querySelectorAll('#pose td')].map(td => td.textContent)").await).unwrap();
    assert_eq!(cells.len(), 16);
    for (k, cell) in cells.iter().enumerate() {
        let (shown, api) = (cell.parse::<f64>().unwrap(), api_pose[k / 4][k % 4].as_f64().unwrap());
        assert!(cell.split('.').nth(1).is_some_and(|d| d.len() == 6) && (shown - api).abs() <= 5e-7, "cell {k}: {cell:?}, API {api}");
    }
    let iterations = answer["iterations"].as_u64().unwrap();
    assert_eq!(text(&c, "#r-iterations").await, iterations.to_string());
    assert_eq!(text(&c, "#r-converged").await.starts_with("yes"), answer["converged"].as_bool().unwrap());
    assert!(text(&c, "#r-confidence").await.starts_with(&format!("{:.3}", answer["confidence"]["score"].as_f64().unwrap())));
    // The calibrated verdict beside the pose: the API's probability and yes/no.
    let verdict = text(&c, "#r-verdict").await;
    match answer["confidence"]["p_registered"].as_f64() {
        Some(p) => {
            let localized = answer["confidence"]["localized"].as_bool().unwrap();
            assert!(verdict.starts_with(if localized { "localized" } else { "NOT localized" }), "{verdict}");
            assert!(verdict.contains(&format!("p_registered {p:.3}")), "{verdict} vs {p}");
        }
        None => assert!(verdict.starts_with("not localized: the model set has no calibrator"), "{verdict}"),
    }
    assert!(text(&c, "#timings").await.contains("agent steps"));

    // The page's projection (app.js projectPoints) is src/geometry's: the same points, pose and
    // intrinsics give the same pixels and depths as render::project_points.
    let page_points: Vec<[f64; 3]> = serde_json::from_value(
        js(&c, "const p = projectPoints(state.points, state.poses[state.poses.length - 1], state.intrinsicsUsed, state.image.width, state.image.height); return p;").await,
    )
    .unwrap();
    let n_points = js(&c, "return state.points.length / 3").await.as_u64().unwrap() as usize;
    let entry = server.state.maps.store.get("demo").unwrap();
    let prepared = server.state.maps.prepared_for(&entry).unwrap();
    let rows: [[f64; 4]; 4] = serde_json::from_value(api_pose.clone()).unwrap();
    let k = cmr_agent::geometry::Intrinsics { fx: 718.856, fy: 718.856, cx: 607.1928, cy: 185.2157 };
    assert_eq!(serde_json::to_value(k).unwrap(), demo["intrinsics"]);
    let pose = cmr_agent::geometry::Pose::from_matrix(&rows).unwrap();
    let rust_points = cmr_agent::render::project_points(&prepared.drawing_sample(n_points).0, &k, &pose, 1241, 376);
    assert!(rust_points.len() > 500, "{} points in view", rust_points.len());
    assert_eq!(page_points.len(), rust_points.len(), "points in view: page {}, Rust {}", page_points.len(), rust_points.len());
    let key = |p: &[f64; 3]| ((p[0] * 1e3).round() as i64, (p[1] * 1e3).round() as i64);
    let mut a: Vec<[f64; 3]> = page_points.clone();
    let mut b: Vec<[f64; 3]> = rust_points.iter().map(|&(u, v, z)| [u, v, z]).collect();
    a.sort_by_key(key);
    b.sort_by_key(key);
    for (p, q) in a.iter().zip(&b) {
        assert!((0..3).all(|i| (p[i] - q[i]).abs() < 1e-6), "page {p:?}, Rust {q:?}");
    }

    // Both canvases are drawn: points changed the image's pixels; the top view has the cloud
    // and the selected camera.
    let changed_final = js(&c, CHANGED_PIXELS).await.as_u64().unwrap();
    let drawn: u64 = c.find(Locator::Id("image-canvas")).await.unwrap().attr("data-drawn-points").await.unwrap().unwrap().parse().unwrap();
    assert!(drawn > 500 && changed_final > 2000, "points on the image: {drawn} drawn, {changed_final} pixels changed");
    let top: Vec<u64> = serde_json::from_value(js(&c, TOP_VIEW_PIXELS).await).unwrap();
    assert!(top[0] > 3000 && top[1] > 20, "top view pixels (drawn, selected camera): {top:?}");

    // The top view keeps float64 map coordinates (no narrowing of UTM-size ones to float32).
    let bands = js(&c, TOP_VIEW_UTM_ROWS).await.as_u64().unwrap();
    assert_eq!(bands, 41, "rows of points 5 cm apart at y ≈ 5,049,158 m drawn as {bands} bands");

    // The slider: the start, each step, and the polished answer when the polish moved it; the
    // start redraws the points elsewhere.
    let polished = answer["polish"]["rotation_deg"].as_f64().unwrap_or(0.0) > 0.0 || answer["polish"]["translation_m"].as_f64().unwrap_or(0.0) > 0.0;
    let last = js(&c, "return document.getElementById('iteration').max").await;
    assert_eq!(last, json!((iterations + polished as u64).to_string()));
    if polished {
        assert!(text(&c, "#iter-label").await.starts_with("polished: turned"));
    }
    if iterations > 0 {
        let before = js(&c, "return document.getElementById('image-canvas').toDataURL()").await;
        set_value(&c, "iteration", "0").await;
        assert!(text(&c, "#iter-label").await.starts_with("start"));
        let after = js(&c, "return document.getElementById('image-canvas').toDataURL()").await;
        assert_ne!(before, after, "moving the slider redraws the image");
        set_value(&c, "iteration", &iterations.to_string()).await;
        assert!(text(&c, "#iter-label").await.starts_with(&format!("step {iterations} of {iterations}")));
    }

    // The screenshot the docs use: the demo's answer at its last iteration.
    let png = c.screenshot().await.unwrap();
    let image = image::load_from_memory(&png).unwrap();
    assert!(image.width() >= 1000, "screenshot {}x{}", image.width(), image.height());
    let target = root.join("target/web-ui.png");
    std::fs::write(&target, &png).unwrap();
    if std::env::var("CMR_UPDATE_DOCS").is_ok_and(|v| v == "1") {
        std::fs::write(root.join("docs/web-ui.png"), &png).unwrap();
    }
    say(&format!("web_page_in_chromium: screenshot {}x{} in {}", image.width(), image.height(), target.display()));

    // An API error is shown as the API's own message.
    set_value(&c, "fx", "-5").await;
    assert_eq!(run_and_wait(&c).await, "error");
    let mut bad = demo.clone();
    bad["intrinsics"]["fx"] = json!(-5.0);
    let (status, err, _) = server.localize("demo", &bad).await;
    assert_eq!(status, 422);
    let shown_error = text(&c, "#error").await;
    assert_eq!(
        shown_error,
        format!("{}: {} (HTTP 422)", err["error_type"].as_str().unwrap(), err["error"].as_str().unwrap())
    );

    // Regions: upload needs the token (the API's 401 is shown), then works; delete removes it.
    let cloud = profile.path().join("street.bin");
    std::fs::write(&cloud, cmr_agent::maps::formats::write_kitti_bin(&street_cloud())).unwrap();
    js(&c, "document.getElementById('admin').open = true").await;
    set_value(&c, "upload-id", "street-ui").await;
    c.find(Locator::Id("upload-file")).await.unwrap().send_keys(cloud.to_str().unwrap()).await.unwrap();
    set_value(&c, "token", "wrong").await;
    js(&c, "document.getElementById('error').hidden = true; document.getElementById('upload').click()").await;
    wait_for(&c, "!document.getElementById('error').hidden", Duration::from_secs(20), "the refused upload").await;
    assert_eq!(text(&c, "#error").await, "unauthorized: missing or wrong bearer token (HTTP 401)");
    set_value(&c, "token", ADMIN_TOKEN).await;
    c.find(Locator::Id("upload")).await.unwrap().click().await.unwrap();
    wait_for(&c, "document.querySelector('#regions button.selected')?.dataset.id === 'street-ui'", Duration::from_secs(60), "the uploaded region").await;
    assert!(text(&c, "#admin-info").await.starts_with("registered street-ui: 18,000 points"));
    assert_eq!(server.client.get(server.url("/v1/maps/street-ui")).send().await.unwrap().status(), 200);
    c.find(Locator::Id("delete")).await.unwrap().click().await.unwrap();
    c.accept_alert().await.unwrap();
    wait_for(&c, "document.getElementById('admin-info').textContent === 'deleted street-ui'", Duration::from_secs(20), "the deletion").await;
    wait_for(&c, "document.querySelector('#regions button.selected')?.dataset.id === 'demo'", Duration::from_secs(20), "the list after the deletion").await;
    assert_eq!(server.client.get(server.url("/v1/maps/street-ui")).send().await.unwrap().status(), 404);

    c.close().await.unwrap();
    drop(driver);
    server.stop().await;
}
