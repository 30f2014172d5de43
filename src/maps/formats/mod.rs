//! Point clouds from the files a LiDAR user has: KITTI `.bin`, PCD and PLY.
//!
//! Everything here parses untrusted bytes (map uploads), so every reader:
//! - never panics and never allocates more than the input justifies (declared counts are checked
//!   against the bytes present and against [`Limits::max_points`]);
//! - answers with a [`FormatError`] that says what is wrong (truncated data, header/data mismatch,
//!   bad numbers, unsupported variants, no points);
//! - **drops** points whose x, y or z is not finite (organised PCD clouds mark missing returns with
//!   NaN, so rejecting them would refuse ordinary files) and fails with [`FormatError::NoPoints`]
//!   when nothing finite is left. A non-finite intensity is kept as it is.
//!
//! Only x, y, z and an optional intensity are kept; every other field or element is skipped.
//! PCD's VIEWPOINT is ignored (points are taken as written, like most tools do).

mod kitti_bin;
mod lzf;
mod pcd;
mod ply;
mod scalar;

use std::io::Write;

pub use kitti_bin::write_kitti_bin;

/// A point-cloud file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CloudFormat {
    /// KITTI velodyne scan: little-endian float32 records (x, y, z, intensity), no header.
    KittiBin,
    /// Point Cloud Library's PCD (DATA ascii, binary or binary_compressed).
    Pcd,
    /// Stanford PLY (ascii, binary_little_endian or binary_big_endian).
    Ply,
}

impl CloudFormat {
    /// Guesses the format from the first bytes. Headerless KITTI `.bin` is recognised only by
    /// its length being a non-zero multiple of 16 bytes, so call this after ruling out the rest.
    pub fn sniff(bytes: &[u8]) -> Option<CloudFormat> {
        if bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n") {
            return Some(CloudFormat::Ply);
        }
        if pcd::looks_like_pcd(bytes) {
            return Some(CloudFormat::Pcd);
        }
        if !bytes.is_empty() && bytes.len() % kitti_bin::RECORD_BYTES == 0 {
            return Some(CloudFormat::KittiBin);
        }
        None
    }

    /// The format conventionally stored under a file extension (`bin`, `pcd`, `ply`).
    pub fn from_extension(extension: &str) -> Option<CloudFormat> {
        match extension.to_ascii_lowercase().as_str() {
            "bin" => Some(CloudFormat::KittiBin),
            "pcd" => Some(CloudFormat::Pcd),
            "ply" => Some(CloudFormat::Ply),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            CloudFormat::KittiBin => "kitti_bin",
            CloudFormat::Pcd => "pcd",
            CloudFormat::Ply => "ply",
        }
    }
}

impl std::str::FromStr for CloudFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "kitti_bin" | "kitti" | "bin" => Ok(CloudFormat::KittiBin),
            "pcd" => Ok(CloudFormat::Pcd),
            "ply" => Ok(CloudFormat::Ply),
            other => Err(format!("unknown point-cloud format {other:?} (expected kitti_bin, pcd or ply)")),
        }
    }
}

/// Points in the file's own frame; `intensity`, when present, has one value per point.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    pub xyz: Vec<[f32; 3]>,
    pub intensity: Option<Vec<f32>>,
}

impl PointCloud {
    pub fn len(&self) -> usize {
        self.xyz.len()
    }

    pub fn is_empty(&self) -> bool {
        self.xyz.is_empty()
    }
}

/// Why a point-cloud file was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FormatError {
    #[error("empty point-cloud file")]
    Empty,
    #[error("bad header: {0}")]
    Header(String),
    #[error("unsupported: {0}")]
    Unsupported(String),
    #[error("truncated data: {0}")]
    Truncated(String),
    #[error("data does not match the header: {0}")]
    Mismatch(String),
    #[error("bad number {token:?} ({context})")]
    BadNumber { token: String, context: String },
    #[error("too many points: {count} (this server accepts at most {max})")]
    TooManyPoints { count: u64, max: usize },
    #[error("the cloud has no point with finite coordinates")]
    NoPoints,
    #[error("corrupt compressed data: {0}")]
    Corrupt(String),
}

/// Bounds against absurd inputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// The most points (finite or not) a file may declare or contain.
    pub max_points: usize,
}

impl Default for Limits {
    /// 20 million points: a dense multi-scan map region, about 320 MB as KITTI `.bin`.
    fn default() -> Self {
        Limits { max_points: 20_000_000 }
    }
}

/// Parses `bytes` as `format` with the default [`Limits`].
pub fn parse(bytes: &[u8], format: CloudFormat) -> Result<PointCloud, FormatError> {
    parse_with_limits(bytes, format, Limits::default())
}

/// Parses `bytes` as `format`, refusing files that declare or hold more than `limits.max_points`.
pub fn parse_with_limits(bytes: &[u8], format: CloudFormat, limits: Limits) -> Result<PointCloud, FormatError> {
    if bytes.is_empty() {
        return Err(FormatError::Empty);
    }
    let cloud = match format {
        CloudFormat::KittiBin => kitti_bin::parse(bytes, limits)?,
        CloudFormat::Pcd => pcd::parse(bytes, limits)?,
        CloudFormat::Ply => ply::parse(bytes, limits)?,
    };
    if cloud.is_empty() {
        return Err(FormatError::NoPoints);
    }
    Ok(cloud)
}

/// Collects points while reading, dropping the ones with non-finite coordinates.
pub(crate) struct CloudBuilder {
    cloud: PointCloud,
    dropped: usize,
}

impl CloudBuilder {
    /// `capacity_hint` must already be bounded by the input size.
    pub(crate) fn new(capacity_hint: usize, with_intensity: bool) -> Self {
        CloudBuilder {
            cloud: PointCloud {
                xyz: Vec::with_capacity(capacity_hint),
                intensity: with_intensity.then(|| Vec::with_capacity(capacity_hint)),
            },
            dropped: 0,
        }
    }

    pub(crate) fn push(&mut self, x: f64, y: f64, z: f64, intensity: f64) {
        let p = [x as f32, y as f32, z as f32];
        if p.iter().all(|c| c.is_finite()) {
            self.cloud.xyz.push(p);
            if let Some(i) = self.cloud.intensity.as_mut() {
                i.push(intensity as f32);
            }
        } else {
            self.dropped += 1;
        }
    }

    pub(crate) fn finish(self) -> PointCloud {
        if self.dropped > 0 {
            tracing::debug!(dropped = self.dropped, kept = self.cloud.xyz.len(), "dropped points with non-finite coordinates");
        }
        self.cloud
    }
}

pub(crate) fn check_count(count: u64, limits: Limits) -> Result<usize, FormatError> {
    if count > limits.max_points as u64 {
        return Err(FormatError::TooManyPoints { count, max: limits.max_points });
    }
    Ok(count as usize)
}

/// Writes `cloud` as KITTI `.bin` into any writer (intensity 0 when the cloud has none).
pub fn write_kitti_bin_to<W: Write>(cloud: &PointCloud, mut out: W) -> std::io::Result<()> {
    out.write_all(&write_kitti_bin(cloud))
}

#[cfg(test)]
mod tests;
