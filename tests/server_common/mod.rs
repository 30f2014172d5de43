//! Shared helpers for the HTTP integration tests: a real server on 127.0.0.1:0 with real ONNX
//! graphs, small maps and images made by the tests themselves.

#![allow(dead_code)]

use std::io::Cursor;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use base64::Engine;
use cmr_agent::api::{self, AppState, ServeArgs};
use cmr_agent::maps::formats::{PointCloud, write_kitti_bin};
use tokio::sync::oneshot;

pub fn tiny_model() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model")
}

/// The project's default model set (`models/`), or the candidate set named by `CMR_TEST_MODELS`
/// (to run the model-dependent tests, e.g. the ignored fleet bar, against a model before it ships).
pub fn default_model() -> PathBuf {
    std::env::var_os("CMR_TEST_MODELS").map(PathBuf::from).unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models"))
}

pub struct TestServer {
    pub base: String,
    /// The probe port's base URL (`serve --probe-port`: /health, /ready, /metrics only).
    pub probe_base: String,
    pub state: Arc<AppState>,
    pub client: reqwest::Client,
    shutdown: Option<oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<anyhow::Result<()>>>,
}

impl TestServer {
    /// Starts a server on an ephemeral port, with its probe port on another, and waits until
    /// /ready says so.
    pub async fn start(models: &Path, maps: &Path, extra: &[&str]) -> TestServer {
        let mut flags: Vec<String> = vec![
            "--models".into(),
            models.display().to_string(),
            "--maps".into(),
            maps.display().to_string(),
            "--intra-threads".into(),
            "1".into(),
        ];
        flags.extend(extra.iter().map(|s| s.to_string()));
        let config = ServeArgs::from_flags(flags).expect("flags parse");
        let state = tokio::task::spawn_blocking(move || api::build_state(config)).await.unwrap().expect("server state builds");
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let base = format!("http://{}", listener.local_addr().unwrap());
        let probe = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let probe_base = format!("http://{}", probe.local_addr().unwrap());
        let (tx, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(api::serve(state.clone(), listener, Some(probe), async move {
            let _ = rx.await;
        }));
        let server = TestServer { base, probe_base, state, client: reqwest::Client::new(), shutdown: Some(tx), task: Some(task) };
        server.wait_ready().await;
        server
    }

    pub async fn wait_ready(&self) {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if let Ok(r) = self.client.get(self.url("/ready")).send().await {
                if r.status() == 200 {
                    return;
                }
            }
            assert!(Instant::now() < deadline, "server never became ready");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    /// host:port, for raw TCP clients.
    pub fn addr(&self) -> String {
        self.base.trim_start_matches("http://").to_string()
    }

    /// Sends the shutdown signal (SIGTERM's stand-in) without waiting for the server to stop.
    pub fn signal_shutdown(&mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
    }

    pub async fn stop(mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(task) = self.task.take() {
            tokio::time::timeout(Duration::from_secs(30), task).await.expect("server stops in time").unwrap().unwrap();
        }
    }

    /// Waits until the `<id>.emb` files queued so far are written (they follow a registration's answer).
    pub async fn flush_writes(&self) {
        let state = self.state.clone();
        tokio::task::spawn_blocking(move || state.maps.flush_writes()).await.unwrap();
    }

    pub async fn localize(&self, map: &str, body: &serde_json::Value) -> (u16, serde_json::Value, reqwest::header::HeaderMap) {
        let r = self.client.post(self.url(&format!("/v1/maps/{map}/localize"))).json(body).send().await.unwrap();
        let status = r.status().as_u16();
        let headers = r.headers().clone();
        let json = r.json::<serde_json::Value>().await.unwrap_or(serde_json::Value::Null);
        (status, json, headers)
    }
}

/// A street-like cloud in a z-up map frame: ground plane plus two facades.
pub fn street_cloud() -> PointCloud {
    let mut xyz = Vec::new();
    for i in 0..200 {
        let x = i as f32 * 0.4 - 20.0;
        for j in 0..50 {
            xyz.push([x, j as f32 * 0.3 - 7.5, -1.7]);
        }
        for h in 0..20 {
            let z = -1.7 + h as f32 * 0.3;
            xyz.push([x, 7.0, z]);
            xyz.push([x, -8.0, z]);
        }
    }
    PointCloud { xyz, intensity: None }
}

/// The KITTI rig pose: camera looking along the map's +x axis.
pub fn rig_matrix() -> [[f64; 4]; 4] {
    [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27], [0.0, 0.0, 0.0, 1.0]]
}

/// A maps directory holding `street` (KITTI .bin + sidecar with the rig pose).
pub fn maps_dir_with_street() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("street.bin"), write_kitti_bin(&street_cloud())).unwrap();
    let sidecar = serde_json::json!({"description": "test street", "initial_camera_from_map": rig_matrix()});
    std::fs::write(dir.path().join("street.json"), serde_json::to_vec(&sidecar).unwrap()).unwrap();
    dir
}

pub fn test_image(width: u32, height: u32) -> image::RgbImage {
    image::RgbImage::from_fn(width, height, |x, y| {
        let sky = y < height / 2;
        image::Rgb(if sky { [120, 160, 220] } else { [(x % 97) as u8 + 60, (y % 31) as u8 + 60, 70] })
    })
}

pub fn png_bytes(img: &image::RgbImage) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

pub fn jpeg_bytes(img: &image::RgbImage) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Jpeg).unwrap();
    out.into_inner()
}

pub fn b64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// A KITTI-sized request body (1241x376 PNG, KITTI image_2 intrinsics).
pub fn kitti_request(max_iterations: u32) -> serde_json::Value {
    serde_json::json!({
        "image": b64(&png_bytes(&test_image(1241, 376))),
        "intrinsics": {"fx": 718.856, "fy": 718.856, "cx": 607.1928, "cy": 185.2157},
        "max_iterations": max_iterations,
    })
}
