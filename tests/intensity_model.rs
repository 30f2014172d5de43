//! A model set whose point encoder reads intensity (manifest `points.channels` names
//! `intensity_rank`), end to end on real ONNX graphs: the committed tiny fixture
//! `tests/fixtures/tiny-model-intensity` (`python -m cmr.fixture_models --intensity`), whose
//! features move with the fourth column. The library's `prepare_map`; a region registered, and
//! read back from its `<id>.bin`; a tiled region's crops; the server over HTTP. And the
//! three-column tiny set, whose features do not depend on intensity.

mod server_common;

use std::collections::HashMap;
use std::path::PathBuf;

use cmr_agent::maps::formats::{CloudFormat, PointCloud, write_kitti_bin};
use cmr_agent::maps::{CropEmbeddings, MapCache, MapStore, Maps, Prepared, RegionConfig, Upload, UploadOptions, prepare_map, sample_indices};
use cmr_agent::model::{Backend, BackendOptions, ModelSet, OrtBackend, Points};
use server_common::*;

fn set(name: &str) -> ModelSet {
    ModelSet::load(&PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name), BackendOptions::default()).expect("the fixture set loads")
}

/// A street-like cloud (ground, two walls; 10,800 points) and an intensity per point: dull
/// asphalt, bright painted stripes, walls brighter with height.
fn street() -> (Vec<[f32; 3]>, Vec<f32>) {
    let (mut xyz, mut intensity) = (Vec::new(), Vec::new());
    for i in 0..120 {
        let x = i as f32 * 0.5 - 10.0;
        for j in 0..60 {
            xyz.push([x, j as f32 * 0.3 - 9.0, -1.7]);
            intensity.push(if j % 10 == 0 { 0.6 } else { 0.05 + (i % 3) as f32 * 0.01 });
        }
        for h in 0..15 {
            for y in [6.0, -8.0] {
                xyz.push([x, y, -1.7 + h as f32 * 0.3]);
                intensity.push(0.2 + h as f32 * 0.01);
            }
        }
    }
    (xyz, intensity)
}

fn largest_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max)
}

fn features(backend: &mut OrtBackend, points: Points<'_>) -> (Vec<[f32; 3]>, Vec<f32>) {
    let map = prepare_map(backend, points).unwrap();
    (map.points, map.features)
}

/// The encoder reads each sampled point's intensity as its rank among the N: the features move
/// with the intensity; a cloud without intensity reads as a constant one (0.5); any increasing
/// rescaling of the intensity changes nothing; the sampled points are the same either way.
#[test]
fn prepare_map_gives_a_four_channel_encoder_each_points_intensity_rank() {
    let set = set("tiny-model-intensity");
    assert!(set.manifest.reads_intensity());
    let mut backend = set.backend().unwrap();
    let (xyz, intensity) = street();
    let (points, with) = features(&mut backend, Points::new(&xyz, Some(&intensity)));
    let (points_without, without) = features(&mut backend, Points::xyz(&xyz));
    assert_eq!(points, points_without, "the sample does not depend on intensity");
    assert!(largest_difference(&with, &without) > 0.05, "the features follow the intensity");
    let (_, constant) = features(&mut backend, Points::new(&xyz, Some(&vec![0.3; xyz.len()])));
    assert_eq!(constant, without, "no intensity reads as a constant");
    let rescaled: Vec<f32> = intensity.iter().map(|v| v * 255.0 + 3.0).collect();
    assert_eq!(features(&mut backend, Points::new(&xyz, Some(&rescaled))).1, with, "ranks, not values");
    // The ranks are over the N input points: the encoder on the sample and its own intensities.
    let chosen = sample_indices(&xyz, set.manifest.points.num_points).unwrap();
    let sampled: Vec<f32> = chosen.iter().map(|&i| intensity[i]).collect();
    assert_eq!(backend.encode_points(Points::new(&points, Some(&sampled))).unwrap(), with);
    let err = prepare_map(&mut backend, Points::new(&xyz, Some(&intensity[1..]))).unwrap_err().to_string();
    assert!(err.contains("intensity values for"), "{err}");
}

/// A set without `points.channels` feeds x, y, z alone: intensity changes nothing.
#[test]
fn a_three_channel_set_ignores_intensity() {
    let set = set("tiny-model");
    assert!(!set.manifest.reads_intensity());
    let mut backend = set.backend().unwrap();
    let (xyz, intensity) = street();
    let with = features(&mut backend, Points::new(&xyz, Some(&intensity)));
    assert_eq!(with, features(&mut backend, Points::xyz(&xyz)));
}

fn maps(dir: &std::path::Path, set: &ModelSet, config: RegionConfig) -> Maps {
    let (store, _) = MapStore::open(dir).unwrap();
    Maps::new(store, MapCache::new(256 << 20), Box::new(set.backend().unwrap()), config)
}

fn register(maps: &Maps, id: &str, cloud: &PointCloud) {
    let bytes = write_kitti_bin(cloud);
    let upload = Upload { bytes: &bytes, format: Some(CloudFormat::KittiBin), gzip: false, max_bytes: usize::MAX };
    maps.register(id, upload, UploadOptions { origin: Some([0.0; 3]), voxel_m: None }, None).unwrap();
}

fn whole(prepared: Prepared) -> std::sync::Arc<cmr_agent::maps::PreparedMap> {
    match prepared {
        Prepared::Whole(m) => m,
        Prepared::Tiled(_) => panic!("a whole region"),
    }
}

/// A registered region's embeddings are those of its points with their intensity (0, a
/// constant, where the upload had none), when registered and when computed again from the
/// stored `<id>.bin`.
#[test]
fn a_region_gives_the_encoder_its_stored_intensity() {
    let set = set("tiny-model-intensity");
    let mut backend = set.backend().unwrap();
    let (xyz, intensity) = street();
    let (_, expected) = features(&mut backend, Points::new(&xyz, Some(&intensity)));
    let (_, expected_without) = features(&mut backend, Points::xyz(&xyz));
    let dir = tempfile::tempdir().unwrap();
    {
        let maps = maps(dir.path(), &set, RegionConfig::default());
        register(&maps, "street", &PointCloud { xyz: xyz.clone(), intensity: Some(intensity.clone()) });
        register(&maps, "bare", &PointCloud { xyz: xyz.clone(), intensity: None });
        for (id, want) in [("street", &expected), ("bare", &expected_without)] {
            let entry = maps.store.get(id).unwrap();
            assert_eq!(&whole(maps.prepared_for(&entry).unwrap()).features, want, "{id} as registered");
        }
        maps.finish_writes();
    }
    // A fresh server without the `<id>.emb` files: from `<id>.bin`.
    for id in ["street", "bare"] {
        std::fs::remove_file(dir.path().join(format!("{id}.emb"))).unwrap();
    }
    let maps = maps(dir.path(), &set, RegionConfig::default());
    for (id, want) in [("street", &expected), ("bare", &expected_without)] {
        let entry = maps.store.get(id).unwrap();
        assert_eq!(&whole(maps.prepared_for(&entry).unwrap()).features, want, "{id} read back");
    }
    assert_eq!(maps.computed.load(std::sync::atomic::Ordering::Relaxed), 2);
}

/// A tiled region's crop carries each of its points' stored intensity, and the crop's
/// re-encoding (`--crop-embeddings encode`) reads it; also for a server started after the
/// tiles were written.
#[test]
fn a_tiled_regions_crops_carry_their_points_intensity() {
    let set = set("tiny-model-intensity");
    let mut backend = set.backend().unwrap();
    let (xyz, intensity) = street();
    let of: HashMap<[u32; 3], f32> = xyz.iter().zip(&intensity).map(|(p, &v)| (p.map(f32::to_bits), v)).collect();
    assert_eq!(of.len(), xyz.len(), "distinct points");
    let config = RegionConfig { tile_above_points: 1000, crop_embeddings: CropEmbeddings::Encode, ..RegionConfig::default() };
    let dir = tempfile::tempdir().unwrap();
    for fresh in [false, true] {
        let maps = maps(dir.path(), &set, config);
        if !fresh {
            register(&maps, "street", &PointCloud { xyz: xyz.clone(), intensity: Some(intensity.clone()) });
        }
        let entry = maps.store.get("street").unwrap();
        let prepared = maps.prepared_for(&entry).unwrap();
        assert!(matches!(prepared, Prepared::Tiled(_)));
        let crop = prepared.around([4.0, -1.0, 0.0], 30.0, 100, false).unwrap();
        let kept = crop.intensity.clone().expect("the crop's intensity");
        assert_eq!(kept, crop.points.iter().map(|p| of[&p.map(f32::to_bits)]).collect::<Vec<_>>());
        assert!(kept.iter().any(|&v| v == 0.6) && kept.iter().any(|&v| v < 0.1), "stripes and asphalt in the crop");
        let encoded = maps.reencode(&crop).unwrap();
        assert_eq!(encoded.features, backend.encode_points(Points::new(&crop.points, Some(&kept))).unwrap());
        let blind = backend.encode_points(Points::xyz(&crop.points)).unwrap();
        assert!(largest_difference(&encoded.features, &blind) > 0.05, "the crop's features follow its intensity");
    }
}

/// The server with the four-channel set: it warms up, and localizes on a region with intensity
/// (uploaded), one without (a stored scan), and a tiled one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_localizes_with_a_four_channel_set() {
    let model = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model-intensity");
    for extra in [&[][..], &["--tile-above-points", "5000"][..]] {
        let maps = maps_dir_with_street();
        let server = TestServer::start(&model, maps.path(), extra).await;
        let info: serde_json::Value = server.client.get(server.url("/v1/info")).send().await.unwrap().json().await.unwrap();
        assert_eq!(info["manifest"]["points"]["channels"], serde_json::json!(["x", "y", "z", "intensity_rank"]));
        let (xyz, intensity) = street();
        let bytes = write_kitti_bin(&PointCloud { xyz, intensity: Some(intensity) });
        let r = server.client.put(server.url("/v1/maps/painted?format=kitti_bin")).body(bytes).send().await.unwrap();
        assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
        let mut request = kitti_request(3);
        request["prior_camera_from_map"] = serde_json::json!(rig_matrix());
        for id in ["street", "painted"] {
            let (status, body, _) = server.localize(id, &request).await;
            assert_eq!(status, 200, "{extra:?} {id}: {body}");
        }
        server.stop().await;
    }
}
