//! `velodyne/NNNNNN.bin`: a flat array of little-endian float32 (x, y, z, intensity) records.

use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::atomic_file::write_atomic;

/// One LiDAR return in the velodyne frame (x forward, y left, z up), intensity in [0, 1].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LidarPoint {
    pub x: f32,
    pub y: f32,
    pub z: f32,
    pub intensity: f32,
}

/// Parses the bytes of a KITTI `.bin`; `origin` names the source in errors.
pub fn parse_velodyne(bytes: &[u8], origin: &str) -> Result<Vec<LidarPoint>> {
    if bytes.len() % 16 != 0 {
        bail!("{origin}: {} bytes is not a whole number of 16-byte (x, y, z, intensity) float32 records", bytes.len());
    }
    let mut points = Vec::with_capacity(bytes.len() / 16);
    for (i, record) in bytes.chunks_exact(16).enumerate() {
        let f = |k: usize| f32::from_le_bytes(record[4 * k..4 * k + 4].try_into().unwrap());
        let p = LidarPoint { x: f(0), y: f(1), z: f(2), intensity: f(3) };
        if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
            bail!("{origin}: point {i} has a non-finite coordinate");
        }
        points.push(p);
    }
    Ok(points)
}

pub fn read_velodyne(path: &Path) -> Result<Vec<LidarPoint>> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    parse_velodyne(&bytes, &path.display().to_string())
}

pub fn velodyne_to_bytes(points: &[LidarPoint]) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(points.len() * 16);
    for p in points {
        for v in [p.x, p.y, p.z, p.intensity] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    bytes
}

pub fn write_velodyne(path: &Path, points: &[LidarPoint]) -> Result<()> {
    Ok(write_atomic(path, &velodyne_to_bytes(points))?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_bad_lengths() {
        let points = vec![
            LidarPoint { x: 1.5, y: -2.25, z: 0.125, intensity: 0.5 },
            LidarPoint { x: -80.0, y: 3.0, z: -1.73, intensity: 0.0 },
        ];
        let bytes = velodyne_to_bytes(&points);
        assert_eq!(bytes.len(), 32);
        assert_eq!(parse_velodyne(&bytes, "mem").unwrap(), points);
        let err = parse_velodyne(&bytes[..30], "x.bin").unwrap_err().to_string();
        assert!(err.contains("x.bin") && err.contains("30 bytes"), "{err}");
        let mut nan = bytes.clone();
        nan[4..8].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(parse_velodyne(&nan, "n.bin").unwrap_err().to_string().contains("point 0"));
    }
}
