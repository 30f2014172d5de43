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
        (CloudFormat::Las, write_las(&cloud, (1, 2), 1)),
        (CloudFormat::Las, write_las(&cloud, (1, 4), 6)),
        (CloudFormat::Las, write_laz(&cloud, (1, 2), 3)),
        (CloudFormat::Las, write_laz(&cloud, (1, 4), 3)),
    ]
}

/// The same as `write_las`, compressed (LAZ).
pub(super) fn write_laz(cloud: &PointCloud, version: (u8, u8), point_format: u8) -> Vec<u8> {
    write_las_with(cloud, version, point_format, true)
}

/// A LAS file written by the `las` crate (intensity as the 16-bit value of `cloud`'s).
pub(super) fn write_las(cloud: &PointCloud, version: (u8, u8), point_format: u8) -> Vec<u8> {
    write_las_with(cloud, version, point_format, false)
}

fn write_las_with(cloud: &PointCloud, version: (u8, u8), point_format: u8, compressed: bool) -> Vec<u8> {
    let mut builder = ::las::Builder::from(version);
    builder.point_format = ::las::point::Format::new(point_format).unwrap();
    builder.point_format.is_compressed = compressed;
    // Millimetres from an offset near the first point, as LAS writers store UTM-size coordinates.
    let t = |axis: usize| ::las::Transform { scale: 0.001, offset: (cloud.xyz[0][axis] as f64 / 1000.0).floor() * 1000.0 };
    builder.transforms = ::las::Vector { x: t(0), y: t(1), z: t(2) };
    let mut writer = ::las::Writer::new(std::io::Cursor::new(Vec::new()), builder.into_header().unwrap()).unwrap();
    let intensity = cloud.intensity.as_ref().unwrap();
    let builder_format = ::las::point::Format::new(point_format).unwrap();
    for (p, i) in cloud.xyz.iter().zip(intensity) {
        let point = ::las::Point {
            x: p[0] as f64,
            y: p[1] as f64,
            z: p[2] as f64,
            intensity: *i as u16,
            gps_time: builder_format.has_gps_time.then_some(1.0),
            color: builder_format.has_color.then(::las::Color::default),
            nir: builder_format.has_nir.then_some(0),
            ..Default::default()
        };
        writer.write_point(point).unwrap();
    }
    writer.into_inner().unwrap().into_inner()
}

/// The cloud as LAS stores it: millimetre coordinates, integer intensity.
fn as_las_stores(cloud: &PointCloud) -> PointCloud {
    let mm = |v: f32| ((v as f64 * 1000.0).round() / 1000.0) as f32;
    PointCloud {
        xyz: cloud.xyz.iter().map(|p| [mm(p[0]), mm(p[1]), mm(p[2])]).collect(),
        intensity: cloud.intensity.as_ref().map(|i| i.iter().map(|v| (*v as u16) as f32).collect()),
    }
}

#[test]
fn every_format_round_trips_the_points_and_intensity() {
    let cloud = sample_cloud(12);
    for (format, bytes) in valid_files() {
        assert_eq!(CloudFormat::sniff(&bytes), Some(format));
        let parsed = parse(&bytes, format).unwrap_or_else(|e| panic!("{format:?}: {e}"));
        let want = if format == CloudFormat::Las { as_las_stores(&cloud) } else { cloud.clone() };
        assert_eq!(parsed, want, "{format:?}");
    }
}

#[test]
fn las_keeps_coordinates_at_their_scale_and_16_bit_intensity() {
    let mut cloud = sample_cloud(5);
    cloud.intensity = Some(vec![0.0, 1.0, 255.0, 4096.0, 65535.0]);
    // UTM-size coordinates (kept to float32 precision: 0.5 m at 5.4e6)
    cloud.xyz.iter_mut().for_each(|p| *p = [p[0].round() + 500_000.0, p[1].round() + 5_400_000.0, p[2] + 300.0]);
    for (version, point_format) in [((1, 2), 0), ((1, 2), 3), ((1, 3), 1), ((1, 4), 7)] {
        let parsed = parse(&write_las(&cloud, version, point_format), CloudFormat::Las).unwrap_or_else(|e| panic!("{version:?}/{point_format}: {e}"));
        assert_eq!(parsed, as_las_stores(&cloud), "{version:?} format {point_format}");
    }
}

#[test]
fn las_problems_are_named() {
    let cloud = sample_cloud(20);
    let las = write_las(&cloud, (1, 2), 1);
    let cut = parse(&las[..las.len() - 10], CloudFormat::Las).unwrap_err();
    assert!(matches!(cut, FormatError::Truncated(_)), "{cut}");
    assert!(matches!(parse(&las[..100], CloudFormat::Las), Err(FormatError::Truncated(_))));
    let mut many = las.clone();
    many[107..111].copy_from_slice(&u32::MAX.to_le_bytes()); // legacy number of point records
    assert!(matches!(parse(&many, CloudFormat::Las), Err(FormatError::TooManyPoints { .. })));
    // LAZ: the compressed stream cut short, or a count inflated past the limit (refused from the
    // header, before anything is decompressed), or the point data start past the end.
    let laz = write_laz(&sample_cloud(3000), (1, 2), 1);
    for cut in [laz.len() - 40, laz.len() / 2] {
        let e = parse(&laz[..cut], CloudFormat::Las).unwrap_err();
        assert!(matches!(e, FormatError::Truncated(_) | FormatError::Corrupt(_) | FormatError::Header(_)), "{cut}: {e}");
    }
    let mut many = laz.clone();
    many[107..111].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(matches!(parse(&many, CloudFormat::Las), Err(FormatError::TooManyPoints { .. })));
    let layered = parse(&write_laz(&sample_cloud(20), (1, 4), 6), CloudFormat::Las).unwrap_err();
    assert!(matches!(layered, FormatError::Unsupported(_)), "{layered}");
    let mut far = laz.clone();
    far[96..100].copy_from_slice(&(laz.len() as u32 + 1).to_le_bytes()); // offset to point data
    assert!(parse(&far, CloudFormat::Las).is_err());
    // LAS 1.4 with an extended VLR claiming far more bytes than the file has.
    let mut v14 = write_las(&cloud, (1, 4), 6);
    let start = v14.len() as u64;
    v14[235..243].copy_from_slice(&start.to_le_bytes()); // start of first EVLR
    v14[243..247].copy_from_slice(&1u32.to_le_bytes()); // number of EVLRs
    v14.extend_from_slice(&[0u8; 20]);
    v14.extend_from_slice(&u64::MAX.to_le_bytes());
    v14.extend_from_slice(&[0u8; 32]);
    assert!(matches!(parse(&v14, CloudFormat::Las), Err(FormatError::Truncated(_))));
}

#[test]
fn coordinates_beyond_the_bound_refuse_the_file() {
    let mut cloud = sample_cloud(4);
    cloud.xyz[2][1] = 3.0e38;
    let err = parse(&write_kitti_bin(&cloud), CloudFormat::KittiBin).unwrap_err();
    assert!(matches!(err, FormatError::OutOfRange { index: 2, axis: 'y', .. }), "{err}");
    assert!(err.to_string().contains("beyond"), "{err}");
    cloud.xyz[2][1] = -1.0e7; // the bound itself passes
    assert!(parse(&write_kitti_bin(&cloud), CloudFormat::KittiBin).is_ok());
    cloud.xyz[2][1] = 2.0e7;
    for data in ["ascii", "binary", "binary_compressed"] {
        assert!(matches!(parse(&write_pcd(&cloud, data), CloudFormat::Pcd), Err(FormatError::OutOfRange { .. })), "{data}");
    }
    assert!(matches!(parse(&write_ply(&cloud, "ascii"), CloudFormat::Ply), Err(FormatError::OutOfRange { .. })));
    // A double that overflows float32 is out of range, not a dropped non-finite point.
    let ply = String::from_utf8(write_ply(&sample_cloud(3), "ascii")).unwrap().replacen("200 -3", "200 1e300", 1);
    assert!(matches!(parse(ply.as_bytes(), CloudFormat::Ply), Err(FormatError::OutOfRange { index: 0, axis: 'x', .. })));
    let tight = Limits { max_abs_coordinate: 1.0, ..Limits::default() };
    assert!(matches!(parse_with_limits(&write_kitti_bin(&sample_cloud(3)), CloudFormat::KittiBin, tight), Err(FormatError::OutOfRange { .. })));
}

#[test]
fn dropped_non_finite_points_are_counted() {
    let mut cloud = sample_cloud(5);
    cloud.xyz[0][0] = f32::NAN;
    cloud.xyz[4][2] = f32::NEG_INFINITY;
    let parsed = parse_counted(&write_kitti_bin(&cloud), CloudFormat::KittiBin, Limits::default()).unwrap();
    assert_eq!((parsed.cloud.len(), parsed.dropped_non_finite), (3, 2));
}

#[test]
fn pcd_quirks_that_pcl_and_open3d_read() {
    let n = 3;
    let header = |fields: &str, size: &str, kind: &str, count: &str| {
        format!("VERSION .7\nFIELDS {fields}\nSIZE {size}\nTYPE {kind}\nCOUNT {count}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n")
    };
    // Lower-case type letters.
    let lower = header("x y z intensity", "4 4 4 4", "f f f f", "1 1 1 1") + "1 2 3 0.5\n4 5 6 0.25\n7 8 9 1\n";
    let parsed = parse(lower.as_bytes(), CloudFormat::Pcd).unwrap();
    assert_eq!(parsed.xyz[2], [7.0, 8.0, 9.0]);
    assert_eq!(parsed.intensity, Some(vec![0.5, 0.25, 1.0]));
    // Packed rgb (a float) and PCL's `_` padding are skipped; CRLF line ends.
    let rgb = (header("x y z rgb _", "4 4 4 4 1", "F F F F U", "1 1 1 1 4") + "1 2 3 4.2e-38 0 0 0 0\n4 5 6 4.2e-38 0 0 0 0\n7 8 9 4.2e-38 0 0 0 0\n").replace('\n', "\r\n");
    let parsed = parse(rgb.as_bytes(), CloudFormat::Pcd).unwrap();
    assert_eq!((parsed.xyz[1], parsed.intensity), ([4.0, 5.0, 6.0], None));
    // Intensity under other names; upper-case coordinates; lower-case keys and DATA.
    for name in ["reflectance", "Intensity", "remission", "i", "scalar_Intensity"] {
        let text = header(&format!("X Y Z {name}"), "4 4 4 4", "F F F F", "1 1 1 1").to_lowercase().replace("data ascii", "DATA Ascii") + "1 2 3 9\n4 5 6 8\n7 8 9 7\n";
        assert_eq!(CloudFormat::sniff(text.as_bytes()), Some(CloudFormat::Pcd), "{name}");
        assert_eq!(parse(text.as_bytes(), CloudFormat::Pcd).unwrap().intensity, Some(vec![9.0, 8.0, 7.0]), "{name}");
    }
    // NaN rows of an organised cloud are dropped.
    let nan = header("x y z", "4 4 4", "F F F", "1 1 1") + "1 2 3\nnan nan nan\nNaN 1 1\n";
    assert_eq!(parse_counted(nan.as_bytes(), CloudFormat::Pcd, Limits::default()).unwrap().dropped_non_finite, 2);
}

#[test]
fn ply_keeps_intensity_under_its_usual_names() {
    let cloud = sample_cloud(4);
    for name in ["scalar_Intensity", "Intensity", "reflectance", "remission", "i"] {
        for format in ["ascii", "binary_little_endian"] {
            let ply = write_ply(&cloud, format);
            let at = ply.windows(18).position(|w| w == b"property float int").unwrap();
            let mut renamed = ply[..at].to_vec();
            renamed.extend_from_slice(format!("property float {name}").as_bytes());
            renamed.extend_from_slice(&ply[at + "property float intensity".len()..]);
            let parsed = parse(&renamed, CloudFormat::Ply).unwrap_or_else(|e| panic!("{name}/{format}: {e}"));
            assert_eq!(parsed.intensity, cloud.intensity, "{name}/{format}");
        }
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
    let limits = Limits { max_points: 4, ..Limits::default() };
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
    assert_eq!("las".parse::<CloudFormat>(), Ok(CloudFormat::Las));
    assert_eq!(CloudFormat::from_extension("LAS"), Some(CloudFormat::Las));
    assert_eq!("laz".parse::<CloudFormat>(), Ok(CloudFormat::Las));
    assert_eq!(CloudFormat::from_extension("laz"), Some(CloudFormat::Las));
    // A PNG whose length is a multiple of 16 is no longer taken for KITTI .bin.
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    png.resize(64, 0);
    assert_eq!(CloudFormat::sniff(&png), None);
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
                if let Ok(cloud) = parse_with_limits(&bytes, f, Limits { max_points: 1000, ..Limits::default() }) {
                    assert!(!cloud.is_empty());
                    assert!(cloud.xyz.iter().flatten().all(|c| c.is_finite()));
                    assert!(cloud.intensity.as_ref().is_none_or(|i| i.len() == cloud.len()));
                }
            }
        }
    }
}

#[test]
fn double_ply_keeps_utm_precision_relative_to_its_origin() {
    let points: Vec<([f64; 3], f32)> = vec![([500_000.125, 5_400_000.0625, 100.5], 0.5), ([500_120.001, 5_399_950.002, 101.25], 0.25)];
    let mut bytes = Vec::new();
    write_ply_f64(&mut bytes, 2, points.iter().copied()).unwrap();
    let parsed = parse_counted(&bytes, CloudFormat::Ply, Limits::default()).unwrap();
    assert_eq!(parsed.origin, [500_000.0, 5_400_000.0, 0.0], "the first point rounded to 1 km");
    for ((p, _), q) in points.iter().zip(&parsed.cloud.xyz) {
        for c in 0..3 {
            assert!((q[c] as f64 + parsed.origin[c] - p[c]).abs() < 1e-5, "{p:?} vs {q:?}");
        }
    }
    assert_eq!(parsed.min, [500_000.125, 5_399_950.002, 100.5]);
    assert_eq!(parsed.cloud.intensity, Some(vec![0.5, 0.25]));
    // The float32 view of the same file loses what float32 cannot hold at 5.4e6 m.
    let flat = parse(&bytes, CloudFormat::Ply).unwrap();
    assert_eq!(flat.xyz[0][1], 5_400_000.0);
    assert!(write_ply_f64(&mut Vec::new(), 3, points.iter().copied()).is_err());
}
