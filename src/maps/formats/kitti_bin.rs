//! KITTI velodyne `.bin`: headerless little-endian float32 records (x, y, z, intensity).

use super::{check_count, CloudBuilder, FormatError, Limits, Parsed, PointCloud};

pub(crate) const RECORD_BYTES: usize = 16;

pub(crate) fn parse(bytes: &[u8], limits: Limits) -> Result<Parsed, FormatError> {
    if bytes.len() % RECORD_BYTES != 0 {
        return Err(FormatError::Truncated(format!(
            "KITTI .bin length {} is not a multiple of {RECORD_BYTES} bytes (float32 x, y, z, intensity)",
            bytes.len()
        )));
    }
    let count = check_count((bytes.len() / RECORD_BYTES) as u64, limits)?;
    let mut builder = CloudBuilder::new(count, true, limits);
    for record in bytes.chunks_exact(RECORD_BYTES) {
        let f = |i: usize| f32::from_le_bytes([record[4 * i], record[4 * i + 1], record[4 * i + 2], record[4 * i + 3]]) as f64;
        builder.push(f(0), f(1), f(2), f(3))?;
    }
    Ok(builder.finish())
}

/// The cloud as KITTI `.bin` bytes (intensity 0 when the cloud has none). Write them atomically.
pub fn write_kitti_bin(cloud: &PointCloud) -> Vec<u8> {
    let mut out = Vec::with_capacity(cloud.xyz.len() * RECORD_BYTES);
    for (i, p) in cloud.xyz.iter().enumerate() {
        let intensity = cloud.intensity.as_ref().and_then(|v| v.get(i).copied()).unwrap_or(0.0);
        for value in [p[0], p[1], p[2], intensity] {
            out.extend_from_slice(&value.to_le_bytes());
        }
    }
    out
}
