//! Round trips through files the tests write themselves, every refusal path, and a
//! mutation fuzz that must never panic.

use super::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn sample_cloud(n: usize) -> PointCloud {
    let xyz = (0..n).map(|i| [i as f32 * 0.5 - 3.0, (i as f32).sin() * 10.0, 1.25 + i as f32 * 0.01]).collect();
    let intensity = Some((0..n).map(|i| (i % 7) as f32 / 7.0).collect());
    PointCloud { xyz, intensity }
}

/// A PCD with fields in an unusual order and an extra multi-count field, in any encoding.
fn write_pcd(cloud: &PointCloud, data: &str) -> Vec<u8> {
    let n = cloud.len();
    let mut out = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS intensity normal z y x label\nSIZE 4 4 8 4 4 2\n\
         TYPE F F F F F U\nCOUNT 1 3 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    )
    .into_bytes();
    let intensity = cloud.intensity.as_ref().unwrap();
    match data {
        "ascii" => {
            for (p, i) in cloud.xyz.iter().zip(intensity) {
                out.extend_from_slice(format!("{i} 0 0 1 {} {} {} 7\n", p[2] as f64, p[1], p[0]).as_bytes());
            }
        }
        "binary" => {
            for (p, i) in cloud.xyz.iter().zip(intensity) {
                out.extend_from_slice(&i.to_le_bytes());
                for v in [0f32, 0.0, 1.0] {
                    out.extend_from_slice(&v.to_le_bytes());
                }
                out.extend_from_slice(&(p[2] as f64).to_le_bytes());
                out.extend_from_slice(&p[1].to_le_bytes());
                out.extend_from_slice(&p[0].to_le_bytes());
                out.extend_from_slice(&7u16.to_le_bytes());
            }
        }
        "binary_compressed" => {
            let mut raw = Vec::new();
            intensity.iter().for_each(|i| raw.extend_from_slice(&i.to_le_bytes()));
            cloud.xyz.iter().for_each(|_| [0f32, 0.0, 1.0].iter().for_each(|v| raw.extend_from_slice(&v.to_le_bytes())));
            cloud.xyz.iter().for_each(|p| raw.extend_from_slice(&(p[2] as f64).to_le_bytes()));
            cloud.xyz.iter().for_each(|p| raw.extend_from_slice(&p[1].to_le_bytes()));
            cloud.xyz.iter().for_each(|p| raw.extend_from_slice(&p[0].to_le_bytes()));
            cloud.xyz.iter().for_each(|_| raw.extend_from_slice(&7u16.to_le_bytes()));
            let packed = lzf::compress_literal_only(&raw);
            out.extend_from_slice(&(packed.len() as u32).to_le_bytes());
            out.extend_from_slice(&(raw.len() as u32).to_le_bytes());
            out.extend_from_slice(&packed);
        }
        _ => unreachable!(),
    }
    out
}

/// A PLY with an element before `vertex` (with a list), extra vertex properties and faces after.
fn write_ply(cloud: &PointCloud, format: &str) -> Vec<u8> {
    let n = cloud.len();
    let mut out = format!(
        "ply\nformat {format} 1.0\ncomment made by a test\nelement camera 2\nproperty list uchar int ids\nproperty double f\n\
         element vertex {n}\nproperty uchar red\nproperty double x\nproperty float y\nproperty float z\nproperty list uint8 float extra\n\
         property float intensity\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
    )
    .into_bytes();
    let intensity = cloud.intensity.as_ref().unwrap();
    if format == "ascii" {
        out.extend_from_slice(b"2 5 6 1.5\n0 2.5\n");
        for (p, i) in cloud.xyz.iter().zip(intensity) {
            out.extend_from_slice(format!("200 {} {} {} 2 0.5 0.25 {i}\n", p[0] as f64, p[1], p[2]).as_bytes());
        }
        out.extend_from_slice(b"3 0 1 2\n");
        return out;
    }
    let big = format == "binary_big_endian";
    macro_rules! put {
        ($v:expr) => {
            if big { out.extend_from_slice(&$v.to_be_bytes()) } else { out.extend_from_slice(&$v.to_le_bytes()) }
        };
    }
    put!(2u8);
    put!(5i32);
    put!(6i32);
    put!(1.5f64);
    put!(0u8);
    put!(2.5f64);
    for (p, i) in cloud.xyz.iter().zip(intensity) {
        put!(200u8);
        put!(p[0] as f64);
        put!(p[1]);
        put!(p[2]);
        put!(1u8);
        put!(0.5f32);
        put!(*i);
    }
    put!(3u8);
    for k in 0..3i32 {
        put!(k);
    }
    out
}

fn valid_files() -> Vec<(CloudFormat, Vec<u8>)> {
    let cloud = sample_cloud(12);
    vec![
        (CloudFormat::KittiBin, write_kitti_bin(&cloud)),
        (CloudFormat::Pcd, write_pcd(&cloud, "ascii")),
        (CloudFormat::Pcd, write_pcd(&cloud, "binary")),
        (CloudFormat::Pcd, write_pcd(&cloud, "binary_compressed")),
        (CloudFormat::Ply, write_ply(&cloud, "ascii")),
        (CloudFormat::Ply, write_ply(&cloud, "binary_little_endian")),
        (CloudFormat::Ply, write_ply(&cloud, "binary_big_endian")),
    ]
}

#[test]
fn every_format_round_trips_the_points_and_intensity() {
    let cloud = sample_cloud(12);
    for (format, bytes) in valid_files() {
        assert_eq!(CloudFormat::sniff(&bytes), Some(format));
        let parsed = parse(&bytes, format).unwrap_or_else(|e| panic!("{format:?}: {e}"));
        assert_eq!(parsed, cloud, "{format:?}");
    }
}

#[test]
fn kitti_bin_refuses_partial_records() {
    let mut bytes = write_kitti_bin(&sample_cloud(3));
    bytes.pop();
    assert!(matches!(parse(&bytes, CloudFormat::KittiBin), Err(FormatError::Truncated(_))));
    assert_eq!(parse(&[], CloudFormat::KittiBin), Err(FormatError::Empty));
    let mut sink = Vec::new();
    write_kitti_bin_to(&PointCloud { xyz: vec![[1.0, 2.0, 3.0]], intensity: None }, &mut sink).unwrap();
    assert_eq!(parse(&sink, CloudFormat::KittiBin).unwrap().intensity, Some(vec![0.0]));
}

#[test]
fn non_finite_points_are_dropped_and_an_all_nan_cloud_is_refused() {
    let mut cloud = sample_cloud(4);
    cloud.xyz[1][2] = f32::NAN;
    cloud.xyz[3][0] = f32::INFINITY;
    let parsed = parse(&write_kitti_bin(&cloud), CloudFormat::KittiBin).unwrap();
    assert_eq!(parsed.xyz, vec![cloud.xyz[0], cloud.xyz[2]]);
    assert_eq!(parsed.intensity.unwrap().len(), 2);
    let parsed = parse(&write_pcd(&cloud, "ascii"), CloudFormat::Pcd).unwrap();
    assert_eq!(parsed.len(), 2);
    let all_nan = PointCloud { xyz: vec![[f32::NAN; 3]; 3], intensity: Some(vec![0.0; 3]) };
    assert_eq!(parse(&write_kitti_bin(&all_nan), CloudFormat::KittiBin), Err(FormatError::NoPoints));
}

#[test]
fn pcd_header_and_data_problems_are_named() {
    let cloud = sample_cloud(5);
    let binary = write_pcd(&cloud, "binary");
    assert!(matches!(parse(&binary[..binary.len() - 3], CloudFormat::Pcd), Err(FormatError::Truncated(_))));

    let ascii = String::from_utf8(write_pcd(&cloud, "ascii")).unwrap();
    let mismatch = ascii.replace("POINTS 5", "POINTS 6");
    assert!(matches!(parse(mismatch.as_bytes(), CloudFormat::Pcd), Err(FormatError::Mismatch(_))));
    let fewer_rows = ascii.replace("WIDTH 5", "WIDTH 6").replace("POINTS 5", "POINTS 6");
    assert!(matches!(parse(fewer_rows.as_bytes(), CloudFormat::Pcd), Err(FormatError::Truncated(_))));
    let more_rows = ascii.replace("WIDTH 5", "WIDTH 4").replace("POINTS 5", "POINTS 4");
    assert!(matches!(parse(more_rows.as_bytes(), CloudFormat::Pcd), Err(FormatError::Mismatch(_))));
    let bad_number = ascii.replacen(" 7\n", " 1.2.3\n", 1).replacen("label\nSIZE 4 4 8 4 4 2\nTYPE F F F F F U", "label\nSIZE 4 4 8 4 4 4\nTYPE F F F F F F", 1).replacen("FIELDS intensity normal z y x label", "FIELDS intensity normal z y label x", 1);
    assert!(matches!(parse(bad_number.as_bytes(), CloudFormat::Pcd), Err(FormatError::BadNumber { .. })));
    let lzf = ascii.replace("DATA ascii", "DATA lz4");
    assert!(matches!(parse(lzf.as_bytes(), CloudFormat::Pcd), Err(FormatError::Unsupported(_))));
    let no_z = ascii.replace("FIELDS intensity normal z y x", "FIELDS intensity normal w y x");
    assert!(matches!(parse(no_z.as_bytes(), CloudFormat::Pcd), Err(FormatError::Unsupported(_))));
    let odd_type = ascii.replace("TYPE F F F F F U", "TYPE F F F F F X");
    assert!(matches!(parse(odd_type.as_bytes(), CloudFormat::Pcd), Err(FormatError::Unsupported(_))));
    let huge = ascii.replace("WIDTH 5", "WIDTH 4000000000").replace("POINTS 5", "POINTS 4000000000");
    assert!(matches!(parse(huge.as_bytes(), CloudFormat::Pcd), Err(FormatError::TooManyPoints { .. })));
    let zero = ascii.replace("WIDTH 5", "WIDTH 0").replace("POINTS 5", "POINTS 0");
    assert!(parse(zero.as_bytes(), CloudFormat::Pcd).is_err());
}

#[test]
fn pcd_binary_compressed_follows_lzf_back_references() {
    // One field x (F4) over 3 points whose raw columns repeat: 4 literal bytes, then a
    // back-reference copying 8 bytes from distance 4.
    let one = 1.5f32.to_le_bytes();
    let mut packed = vec![3u8];
    packed.extend_from_slice(&one);
    packed.extend_from_slice(&[(6u8 << 5), 3]); // length (6 + 2) = 8, distance 3 + 1 = 4
    let mut x_only = b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary_compressed\n".to_vec();
    x_only.extend_from_slice(&(packed.len() as u32).to_le_bytes());
    x_only.extend_from_slice(&12u32.to_le_bytes());
    x_only.extend_from_slice(&packed);
    assert_eq!(parse(&x_only, CloudFormat::Pcd).unwrap().xyz, vec![[1.5, 1.5, 1.5]]);
    let mut wrong_size = x_only.clone();
    let at = wrong_size.len() - packed.len() - 4;
    wrong_size[at..at + 4].copy_from_slice(&16u32.to_le_bytes());
    assert!(matches!(parse(&wrong_size, CloudFormat::Pcd), Err(FormatError::Mismatch(_))));
}

#[test]
fn ply_problems_are_named() {
    let cloud = sample_cloud(5);
    let binary = write_ply(&cloud, "binary_little_endian");
    // Cut inside the vertex data (the trailing face takes 13 bytes).
    assert!(matches!(parse(&binary[..binary.len() - 20], CloudFormat::Ply), Err(FormatError::Truncated(_))));
    let ascii = String::from_utf8(write_ply(&cloud, "ascii")).unwrap();
    let no_vertex = ascii.replace("element vertex", "element points");
    assert!(matches!(parse(no_vertex.as_bytes(), CloudFormat::Ply), Err(FormatError::Unsupported(_))));
    let bad = ascii.replacen("200 ", "200 x", 1);
    assert!(matches!(parse(bad.as_bytes(), CloudFormat::Ply), Err(FormatError::BadNumber { .. })));
    let more = ascii.replace("element vertex 5", "element vertex 50");
    assert!(parse(more.as_bytes(), CloudFormat::Ply).is_err());
    let no_end = ascii.replace("end_header", "end_heder");
    assert!(matches!(parse(no_end.as_bytes(), CloudFormat::Ply), Err(FormatError::Header(_))));
    let huge = ascii.replace("element vertex 5", "element vertex 99999999999");
    assert!(matches!(parse(huge.as_bytes(), CloudFormat::Ply), Err(FormatError::TooManyPoints { .. })));
}

#[test]
fn limits_apply_to_every_format() {
    let limits = Limits { max_points: 4 };
    for (format, bytes) in valid_files() {
        assert!(matches!(parse_with_limits(&bytes, format, limits), Err(FormatError::TooManyPoints { .. })), "{format:?}");
    }
}

#[test]
fn sniff_and_extension() {
    assert_eq!(CloudFormat::sniff(b"hello"), None);
    assert_eq!(CloudFormat::sniff(b""), None);
    assert_eq!(CloudFormat::sniff(b"# comment\nVERSION 0.7\n"), Some(CloudFormat::Pcd));
    assert_eq!(CloudFormat::from_extension("PLY"), Some(CloudFormat::Ply));
    assert_eq!("pcd".parse::<CloudFormat>(), Ok(CloudFormat::Pcd));
    assert!("las".parse::<CloudFormat>().is_err());
}

/// Random byte flips, insertions, deletions and truncations of valid files: parsing must end
/// with a cloud or an error, never a panic, and never with an empty cloud.
#[test]
fn mutated_files_never_panic() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let interesting: &[&[u8]] = &[b"0", b"9", b" ", b"\n", b"-", b"nan", b"99999999999", b"\xff", b"list", b"element"];
    for (format, original) in valid_files() {
        for _ in 0..1500 {
            let mut bytes = original.clone();
            for _ in 0..rng.random_range(1..4) {
                let at = rng.random_range(0..bytes.len().max(1));
                match rng.random_range(0..5) {
                    0 if !bytes.is_empty() => {
                        let i = at.min(bytes.len() - 1);
                        bytes[i] = rng.random();
                    }
                    1 => bytes.truncate(at),
                    2 if at < bytes.len() => {
                        bytes.remove(at);
                    }
                    3 => {
                        let token = interesting[rng.random_range(0..interesting.len())];
                        let at = at.min(bytes.len());
                        bytes.splice(at..at, token.iter().copied());
                    }
                    _ => {
                        if !bytes.is_empty() {
                            let len = rng.random_range(1..=8).min(bytes.len() - at.min(bytes.len() - 1));
                            let at = at.min(bytes.len() - 1);
                            let v: u8 = rng.random();
                            bytes[at..at + len].fill(v);
                        }
                    }
                }
            }
            for f in [format, CloudFormat::KittiBin, CloudFormat::Pcd, CloudFormat::Ply] {
                if let Ok(cloud) = parse_with_limits(&bytes, f, Limits { max_points: 1000 }) {
                    assert!(!cloud.is_empty());
                    assert!(cloud.xyz.iter().flatten().all(|c| c.is_finite()));
                    assert!(cloud.intensity.as_ref().is_none_or(|i| i.len() == cloud.len()));
                }
            }
        }
    }
}
