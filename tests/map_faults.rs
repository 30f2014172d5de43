//! Map-side faults of issue 14, each through the real server: bad input gets the documented 4xx
//! `{error, error_type}` and an existing region with the same id stays byte-identical.
//! Every input is made here (KITTI, PCD, PLY, LAS via the `las` crate, gzip via `flate2`).

mod server_common;

use std::io::{Read, Write};
use std::path::Path;
use std::time::{Duration, Instant};

use cmr_agent::maps::formats::{write_kitti_bin, PointCloud};
use server_common::*;

const AUTH: &str = "Bearer s3cret";

/// `<id>.bin`, `.json` and `.emb` as they are on disk now.
fn snapshot(dir: &Path, id: &str) -> Vec<Vec<u8>> {
    ["bin", "json", "emb"].iter().map(|ext| std::fs::read(dir.join(format!("{id}.{ext}"))).unwrap_or_default()).collect()
}

fn gzip(data: &[u8]) -> Vec<u8> {
    let mut encoder = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    encoder.write_all(data).unwrap();
    encoder.finish().unwrap()
}

fn las_file(cloud: &PointCloud, version: (u8, u8)) -> Vec<u8> {
    las_file_with(cloud, version, 1, false)
}

/// A LAS file of point format `format`, LAZ-compressed when `laz`.
fn las_file_with(cloud: &PointCloud, version: (u8, u8), format: u8, laz: bool) -> Vec<u8> {
    let mut builder = las::Builder::from(version);
    builder.point_format = las::point::Format::new(format).unwrap();
    builder.point_format.is_compressed = laz;
    let mut writer = las::Writer::new(std::io::Cursor::new(Vec::new()), builder.into_header().unwrap()).unwrap();
    for (k, p) in cloud.xyz.iter().enumerate() {
        let point = las::Point { x: p[0] as f64, y: p[1] as f64, z: p[2] as f64, intensity: (k % 300) as u16, gps_time: Some(0.0), ..Default::default() };
        writer.write_point(point).unwrap();
    }
    writer.into_inner().unwrap().into_inner()
}

fn ascii_pcd(cloud: &PointCloud, types: &str) -> String {
    let n = cloud.len();
    let mut text = format!("VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE {types}\nCOUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA ascii\n");
    for (k, p) in cloud.xyz.iter().enumerate() {
        text.push_str(&format!("{} {} {} {}\n", p[0], p[1], p[2], (k % 10) as f32 / 10.0));
    }
    text
}

/// Stored intensity of a region (the fourth float of each KITTI record).
fn stored_intensity(dir: &Path, id: &str) -> Vec<f32> {
    std::fs::read(dir.join(format!("{id}.bin"))).unwrap().chunks_exact(16).map(|r| f32::from_le_bytes(r[12..16].try_into().unwrap())).collect()
}

async fn put(server: &TestServer, path: &str, headers: &[(&str, &str)], body: Vec<u8>) -> (u16, serde_json::Value) {
    let mut request = server.client.put(server.url(path)).header("authorization", AUTH).body(body);
    for (k, v) in headers {
        request = request.header(*k, *v);
    }
    let r = request.send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(serde_json::Value::Null))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_map_bodies_get_4xx_that_name_them_and_leave_the_region_alone() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--admin-token", "s3cret", "--max-map-bytes", "2000000"]).await;
    let before = snapshot(maps.path(), "street");

    // Bit 7 of the point format set on uncompressed records: no LASzip chunk table behind it.
    let mut fake_laz = las_file(&street_cloud(), (1, 2));
    fake_laz[104] |= 0x80;
    let mut zip = b"PK\x03\x04\x14\x00\x00\x00\x00\x00".to_vec();
    zip.resize(160, 7);
    let mut huge = street_cloud();
    huge.xyz[10] = [1.0, 3.0e38, 2.0];
    let mut far = street_cloud();
    far.xyz[0][2] = -2.0e7;
    let bomb = gzip(&vec![0u8; 8_000_000]);
    let cases: Vec<(&str, &str, Vec<(&str, &str)>, Vec<u8>, u16, &str, &str)> = vec![
        ("png", "", vec![], png_bytes(&test_image(64, 48)), 415, "unsupported_media_type", "PNG image"),
        ("png as kitti_bin", "?format=kitti_bin", vec![], png_bytes(&test_image(64, 64)), 415, "unsupported_media_type", "PNG image"),
        ("jpeg", "", vec![], jpeg_bytes(&test_image(64, 48)), 415, "unsupported_media_type", "JPEG image"),
        ("zip", "", vec![], zip, 415, "unsupported_media_type", "zip archive"),
        ("layered LAZ", "", vec![], las_file_with(&street_cloud(), (1, 4), 6, true), 415, "unsupported_media_type", "LAZ with a layered point format"),
        ("fake LAZ", "", vec![], fake_laz, 422, "invalid_input", "LAZ"),
        ("gzip in gzip", "", vec![], gzip(&gzip(&write_kitti_bin(&street_cloud()))), 415, "unsupported_media_type", "another gzip stream"),
        ("gzip png", "", vec![], gzip(&png_bytes(&test_image(8, 8))), 415, "unsupported_media_type", "gzip body holds a PNG image"),
        ("brotli", "", vec![("content-encoding", "br")], write_kitti_bin(&street_cloud()), 415, "unsupported_media_type", "Content-Encoding"),
        ("gzip bomb", "", vec![], bomb, 413, "payload_too_large", "inflates to more than 2000000 bytes"),
        ("not gzip", "", vec![("content-encoding", "gzip")], write_kitti_bin(&street_cloud()), 422, "invalid_input", "corrupt gzip"),
        ("cut gzip", "", vec![], { let g = gzip(&write_kitti_bin(&street_cloud())); g[..g.len() / 2].to_vec() }, 422, "invalid_input", "corrupt gzip"),
        ("3e38 coordinate", "?format=kitti_bin", vec![], write_kitti_bin(&huge), 422, "invalid_input", "point 10 has y = 3.0"),
        ("2e7 coordinate, gzip", "", vec![], gzip(&write_kitti_bin(&far)), 422, "invalid_input", "beyond the ±1e7 m"),
        ("LAS named ply", "?format=ply", vec![], las_file(&street_cloud(), (1, 2)), 422, "invalid_input", "format=ply was given but the body is a LAS file"),
        ("unknown bytes", "", vec![], vec![1, 2, 3], 422, "invalid_input", "no known signature"),
    ];
    for (what, query, headers, body, status, error_type, says) in cases {
        let (got, json) = put(&server, &format!("/v1/maps/street{query}"), &headers, body).await;
        assert_eq!((got, json["error_type"].as_str().unwrap_or("")), (status, error_type), "{what}: {json}");
        assert!(json["error"].as_str().unwrap().contains(says), "{what}: {json}");
        assert_eq!(snapshot(maps.path(), "street"), before, "{what}: the stored region is untouched");
    }
    let (status, _, _) = server.localize("street", &kitti_request(1)).await;
    assert_eq!(status, 200, "the region still localizes");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn las_gzip_and_pcd_ply_quirks_are_read() {
    let maps = tempfile::tempdir().unwrap();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--admin-token", "s3cret"]).await;
    let cloud = street_cloud();
    let n = cloud.len();

    // LAS 1.2 and 1.4, sniffed or named; intensity is the 16-bit value.
    for (id, version, query) in [("las12", (1, 2), ""), ("las14", (1, 4), "?format=las")] {
        let (status, json) = put(&server, &format!("/v1/maps/{id}{query}"), &[], las_file(&cloud, version)).await;
        assert_eq!(status, 201, "{id}: {json}");
        assert_eq!(json["map"]["num_points"], n);
        assert_eq!(stored_intensity(maps.path(), id)[..3], [0.0, 1.0, 2.0]);
    }
    // LAZ (compressed LAS), sniffed or named `laz`: the same points as the LAS.
    for (id, query) in [("laz", ""), ("laz-named", "?format=laz")] {
        let (status, json) = put(&server, &format!("/v1/maps/{id}{query}"), &[], las_file_with(&cloud, (1, 2), 1, true)).await;
        assert_eq!(status, 201, "{id}: {json}");
        assert_eq!(json["map"]["num_points"], n);
        assert_eq!(stored_intensity(maps.path(), id), stored_intensity(maps.path(), "las12"));
    }
    // gzip-compressed PCD, recognised by its magic bytes and by Content-Encoding.
    let pcd = ascii_pcd(&cloud, "F F F F");
    for (id, headers) in [("gz-magic", vec![]), ("gz-header", vec![("content-encoding", "gzip")])] {
        let (status, json) = put(&server, &format!("/v1/maps/{id}"), &headers, gzip(pcd.as_bytes())).await;
        assert_eq!(status, 201, "{id}: {json}");
        assert_eq!(json["map"]["num_points"], n);
    }
    // PCD with lower-case TYPE letters (as PCL and Open3D accept).
    let (status, json) = put(&server, "/v1/maps/lower", &[], ascii_pcd(&cloud, "f f f f").into_bytes()).await;
    assert_eq!(status, 201, "{json}");
    assert_eq!(stored_intensity(maps.path(), "lower")[..3], [0.0, 0.1, 0.2]);
    // PLY with CloudCompare's scalar_Intensity keeps it.
    let mut ply = format!("ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nproperty float scalar_Intensity\nend_header\n");
    for (k, p) in cloud.xyz.iter().enumerate() {
        ply.push_str(&format!("{} {} {} {}\n", p[0], p[1], p[2], (k % 4) as f32 * 0.25));
    }
    let (status, json) = put(&server, "/v1/maps/cc", &[], ply.into_bytes()).await;
    assert_eq!(status, 201, "{json}");
    assert_eq!(stored_intensity(maps.path(), "cc")[..4], [0.0, 0.25, 0.5, 0.75]);
    // UTM-size coordinates pass the bound.
    let mut utm = street_cloud();
    utm.xyz.iter_mut().for_each(|p| *p = [p[0] + 500_000.0, p[1] + 5_400_000.0, p[2] + 300.0]);
    let (status, json) = put(&server, "/v1/maps/utm?format=kitti_bin", &[], write_kitti_bin(&utm)).await;
    assert_eq!(status, 201, "{json}");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metadata_follows_its_schema() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--admin-token", "s3cret"]).await;
    let before = snapshot(maps.path(), "street");
    let bad = [
        (serde_json::json!({"source": 5}), "source must be a JSON object, got a number"),
        (serde_json::json!({"source": [1, 2]}), "source must be a JSON object, got an array"),
        (serde_json::json!({"description": 7}), "description:"),
        (serde_json::json!({"initial_camera_from_map": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}), "initial_camera_from_map:"),
        (serde_json::json!({"descripton": "typo"}), "unknown field"),
        (serde_json::json!(["test street", null, null]), "must be a JSON object"),
        (serde_json::json!("street"), "must be a JSON object"),
    ];
    for (body, says) in bad {
        let (status, json) = put(&server, "/v1/maps/street/metadata", &[("content-type", "application/json")], serde_json::to_vec(&body).unwrap()).await;
        assert_eq!((status, json["error_type"].as_str().unwrap_or("")), (422, "invalid_input"), "{body}: {json}");
        assert!(json["error"].as_str().unwrap().contains(says), "{body}: {json}");
        assert_eq!(snapshot(maps.path(), "street"), before, "{body}");
    }
    let good = serde_json::json!({"description": "d", "source": {"survey": "2026-11", "sensor": "HDL-64"}, "initial_camera_from_map": rig_matrix()});
    let (status, json) = put(&server, "/v1/maps/street/metadata", &[], serde_json::to_vec(&good).unwrap()).await;
    assert_eq!(status, 200, "{json}");
    assert_eq!(json["metadata"]["source"]["sensor"], "HDL-64");
    server.stop().await;
}

/// Sends the head of a PUT that announces `length` body bytes (plus `first` of them), then waits
/// for the answer without sending more: the server must answer from the head alone.
fn answer_to_head(base: &str, head: &str, first: usize, wait: Duration) -> Option<String> {
    let mut socket = std::net::TcpStream::connect(base.trim_start_matches("http://")).unwrap();
    socket.write_all(head.as_bytes()).unwrap();
    socket.write_all(&vec![0u8; first]).unwrap();
    socket.set_read_timeout(Some(wait)).unwrap();
    let mut answer = vec![0u8; 512];
    let n = socket.read(&mut answer).ok()?;
    Some(String::from_utf8_lossy(&answer[..n]).into_owned())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_token_is_checked_before_the_body_is_read() {
    let maps = maps_dir_with_street();
    let server = TestServer::start(&tiny_model(), maps.path(), &["--admin-token", "s3cret"]).await;
    let before = snapshot(maps.path(), "street");
    let base = server.base.clone();
    let answers = tokio::task::spawn_blocking(move || {
        let started = Instant::now();
        // 250 MB announced, 64 KiB sent: reading the body first would wait for the rest (30 s).
        let big = "PUT /v1/maps/street?format=kitti_bin HTTP/1.1\r\nhost: x\r\ncontent-length: 250000000\r\n\r\n";
        let a = answer_to_head(&base, big, 64 * 1024, Duration::from_secs(5));
        let wrong = "PUT /v1/maps/street HTTP/1.1\r\nhost: x\r\nauthorization: Bearer nope\r\ncontent-length: 250000000\r\nexpect: 100-continue\r\n\r\n";
        let b = answer_to_head(&base, wrong, 0, Duration::from_secs(5));
        let meta = "PUT /v1/maps/street/metadata HTTP/1.1\r\nhost: x\r\ncontent-type: application/json\r\ncontent-length: 900000\r\n\r\n";
        let c = answer_to_head(&base, meta, 10, Duration::from_secs(5));
        (a, b, c, started.elapsed())
    })
    .await
    .unwrap();
    for (what, answer) in [("no token", &answers.0), ("wrong token, 100-continue", &answers.1), ("metadata", &answers.2)] {
        let answer = answer.as_deref().unwrap_or_else(|| panic!("{what}: no answer before the body was sent"));
        assert!(answer.starts_with("HTTP/1.1 401"), "{what}: {answer}");
        assert!(answer.contains("\"error_type\":\"unauthorized\""), "{what}: {answer}");
        assert!(!answer.contains("100 Continue"), "{what}: the body was never asked for");
    }
    assert!(answers.3 < Duration::from_secs(5), "answered in {:?}", answers.3);
    let r = server.client.delete(server.url("/v1/maps/street")).send().await.unwrap();
    assert_eq!(r.status(), 401);
    assert_eq!(snapshot(maps.path(), "street"), before);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_starting_replica_spares_another_replicas_upload_in_progress() {
    let maps = maps_dir_with_street();
    // Another replica, mid-upload: its temp file is locked (flock locks conflict between open
    // files, so in one process this is what another process's lock looks like).
    let live = maps.path().join(".yard.bin.tmp-1-0-1234abcd");
    let held = std::fs::File::create(&live).unwrap();
    held.lock().unwrap();
    // A replica killed mid-upload left this one, unlocked.
    let orphan = maps.path().join(".yard.emb.tmp-1-1-1234abcd");
    std::fs::write(&orphan, b"half an upload").unwrap();

    let server = TestServer::start(&tiny_model(), maps.path(), &[]).await;
    assert!(live.exists(), "the live upload's temp file survives a replica's start");
    assert!(!orphan.exists(), "the orphan is swept");
    // Uploads of this replica still work beside it, and leave no temp file of their own.
    let (status, json) = put(&server, "/v1/maps/yard?format=kitti_bin", &[], write_kitti_bin(&street_cloud())).await;
    assert_eq!(status, 201, "{json}");
    server.flush_writes().await; // the region's .emb follows the answer, through a temp file too
    let temps: Vec<String> = std::fs::read_dir(maps.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).filter(|n| n.contains(".tmp-")).collect();
    assert_eq!(temps, [".yard.bin.tmp-1-0-1234abcd"]);
    drop(held);
    server.stop().await;
}
