//! Point clouds from the files a LiDAR user has: KITTI `.bin`, PCD, PLY and LAS.
//!
//! Everything here parses untrusted bytes (map uploads), so every reader:
//! - never panics and never allocates more than the input justifies (declared counts are checked
//!   against the bytes present and against [`Limits::max_points`]);
//! - answers with a [`FormatError`] that says what is wrong (truncated data, header/data mismatch,
//!   bad numbers, unsupported variants, coordinates out of range, no points);
//! - **drops** points whose x, y or z is not finite (organised PCD clouds mark missing returns with
//!   NaN, so rejecting them would refuse ordinary files), counts them in
//!   [`Parsed::dropped_non_finite`], and fails with [`FormatError::NoPoints`] when nothing finite
//!   is left. A non-finite intensity is kept as it is;
//! - **refuses** the whole file ([`FormatError::OutOfRange`]) when a finite coordinate is beyond
//!   ±[`Limits::max_abs_coordinate`] metres: such values are a wrong format or a broken export,
//!   and would overflow the point encoder.
//!
//! Only x, y, z and an optional intensity are kept; every other field or element is skipped.
//! Intensity is read from the first field/property named (case-insensitively) one of
//! [`INTENSITY_NAMES`]. PCD's VIEWPOINT is ignored (points are taken as written, like most tools do).
//!
//! [`sniff::content`] names a body by its magic bytes (cloud formats, gzip, images, archives) and
//! [`gzip::decompress`] inflates gzip under a size bound.

pub mod gzip;
mod kitti_bin;
mod las;
mod lzf;
mod pcd;
mod ply;
mod scalar;
pub mod sniff;

use std::io::Write;

use crate::geometry::LocalFrame;

pub use kitti_bin::write_kitti_bin;
pub use ply::write_ply_f64;

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
    /// ASPRS LAS 1.0-1.4, point formats 0-10, uncompressed or LAZ (`format=las` or `laz`).
    Las,
}

impl CloudFormat {
    /// Guesses the format from the first bytes (PLY, PCD and LAS by their headers, see
    /// [`sniff::content`]). Headerless KITTI `.bin` is recognised only by its length being a
    /// non-zero multiple of 16 bytes and no other known signature; anything else is `None`.
    pub fn sniff(bytes: &[u8]) -> Option<CloudFormat> {
        match sniff::content(bytes) {
            sniff::Content::Cloud(format) => Some(format),
            sniff::Content::Unknown if !bytes.is_empty() && bytes.len() % kitti_bin::RECORD_BYTES == 0 => Some(CloudFormat::KittiBin),
            _ => None,
        }
    }

    /// The format conventionally stored under a file extension (`bin`, `pcd`, `ply`, `las`).
    pub fn from_extension(extension: &str) -> Option<CloudFormat> {
        match extension.to_ascii_lowercase().as_str() {
            "bin" => Some(CloudFormat::KittiBin),
            "pcd" => Some(CloudFormat::Pcd),
            "ply" => Some(CloudFormat::Ply),
            "las" | "laz" => Some(CloudFormat::Las),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            CloudFormat::KittiBin => "kitti_bin",
            CloudFormat::Pcd => "pcd",
            CloudFormat::Ply => "ply",
            CloudFormat::Las => "las",
        }
    }

    /// What a person calls it, for messages.
    pub fn label(self) -> &'static str {
        match self {
            CloudFormat::KittiBin => "KITTI .bin",
            CloudFormat::Pcd => "PCD",
            CloudFormat::Ply => "PLY",
            CloudFormat::Las => "LAS",
        }
    }
}

/// The formats an upload may be in, for messages.
pub const ACCEPTED: &str = "KITTI .bin, PCD, PLY, LAS 1.0-1.4 or LAZ (point formats 0-5), each optionally gzip-compressed";

/// Names of the intensity field (PCD) or vertex property (PLY), compared case-insensitively, in
/// order of preference: PCL, CloudCompare (`scalar_Intensity`), KITTI/SemanticKITTI
/// (`reflectance`, `remission`) and short (`i`) spellings.
pub const INTENSITY_NAMES: [&str; 5] = ["intensity", "scalar_intensity", "reflectance", "remission", "i"];

/// The index of the first of `fields` that names intensity (see [`INTENSITY_NAMES`]).
pub(crate) fn intensity_field<'a>(fields: impl Iterator<Item = &'a str> + Clone) -> Option<usize> {
    INTENSITY_NAMES.iter().find_map(|want| fields.clone().position(|f| f.eq_ignore_ascii_case(want)))
}

impl std::str::FromStr for CloudFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "kitti_bin" | "kitti" | "bin" => Ok(CloudFormat::KittiBin),
            "pcd" => Ok(CloudFormat::Pcd),
            "ply" => Ok(CloudFormat::Ply),
            "las" | "laz" => Ok(CloudFormat::Las),
            other => Err(format!("unknown point-cloud format {other:?} (expected kitti_bin, pcd, ply, las or laz)")),
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
    /// The points with their intensity, as the point encoder takes them.
    pub fn points(&self) -> crate::model::Points<'_> {
        crate::model::Points::new(&self.xyz, self.intensity.as_deref())
    }
}

/// A parsed cloud and what was left out of it. Coordinates are read as float64 and stored as
/// float32 **relative to `origin`** (a multiple of 1 km near the first point, see
/// [`crate::geometry::frame`]), so a cloud at UTM-size coordinates keeps its full precision;
/// [`Parsed::rebase`] moves it to another origin.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Parsed {
    /// Points relative to `origin`.
    pub cloud: PointCloud,
    /// Map-frame coordinates of the cloud's frame origin, metres.
    pub origin: [f64; 3],
    /// Bounding box of the kept points in the file's frame (map frame), metres.
    pub min: [f64; 3],
    pub max: [f64; 3],
    /// Points dropped because x, y or z was NaN or infinite.
    pub dropped_non_finite: usize,
}

impl Parsed {
    /// The cloud's points relative to `frame` instead (exact when the origin does not change).
    pub fn rebase(&mut self, frame: LocalFrame) {
        let to = frame.origin();
        if to == self.origin {
            return;
        }
        let shift = [self.origin[0] - to[0], self.origin[1] - to[1], self.origin[2] - to[2]];
        for p in &mut self.cloud.xyz {
            for c in 0..3 {
                p[c] = (p[c] as f64 + shift[c]) as f32;
            }
        }
        self.origin = to;
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
    #[error("point {index} has {axis} = {value:e} m, beyond the ±{max:e} m this server accepts (a wrong format, or coordinates not in metres?)")]
    OutOfRange { index: usize, axis: char, value: f64, max: f64 },
    #[error("corrupt compressed data: {0}")]
    Corrupt(String),
}

/// Bounds against absurd inputs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    /// The most points (finite or not) a file may declare or contain.
    pub max_points: usize,
    /// The largest |x|, |y| or |z| accepted, metres.
    pub max_abs_coordinate: f64,
    /// The frame to store the points in ([`Parsed::origin`]); default: the first finite point
    /// rounded to 1 km. Given, each point is converted once, from float64.
    pub frame: Option<LocalFrame>,
}

/// 10,000 km ([`crate::geometry::MAX_COORDINATE_M`], the bound of every map-frame coordinate):
/// every UTM easting/northing (northing ≤ 10,000,000 m) and ECEF coordinate passes, while
/// garbage read as floats (3e38, 1e20) does not.
pub const MAX_ABS_COORDINATE_M: f64 = crate::geometry::MAX_COORDINATE_M;

impl Default for Limits {
    /// 20 million points (a dense multi-scan map region, about 320 MB as KITTI `.bin`) within
    /// ±[`MAX_ABS_COORDINATE_M`].
    fn default() -> Self {
        Limits { max_points: 20_000_000, max_abs_coordinate: MAX_ABS_COORDINATE_M, frame: None }
    }
}

/// Parses `bytes` as `format` with the default [`Limits`].
pub fn parse(bytes: &[u8], format: CloudFormat) -> Result<PointCloud, FormatError> {
    parse_with_limits(bytes, format, Limits::default())
}

/// Parses `bytes` as `format` within `limits` (points, coordinate range), as float32 in the
/// file's own frame (use [`parse_counted`] to keep the precision of large coordinates).
pub fn parse_with_limits(bytes: &[u8], format: CloudFormat, limits: Limits) -> Result<PointCloud, FormatError> {
    let mut parsed = parse_counted(bytes, format, limits)?;
    parsed.rebase(LocalFrame::default());
    Ok(parsed.cloud)
}

/// Like [`parse_with_limits`], keeping float64 precision (points relative to [`Parsed::origin`])
/// and saying how many non-finite points were dropped.
pub fn parse_counted(bytes: &[u8], format: CloudFormat, limits: Limits) -> Result<Parsed, FormatError> {
    if bytes.is_empty() {
        return Err(FormatError::Empty);
    }
    let parsed = match format {
        CloudFormat::KittiBin => kitti_bin::parse(bytes, limits)?,
        CloudFormat::Pcd => pcd::parse(bytes, limits)?,
        CloudFormat::Ply => ply::parse(bytes, limits)?,
        CloudFormat::Las => las::parse(bytes, limits)?,
    };
    if parsed.cloud.is_empty() {
        return Err(FormatError::NoPoints);
    }
    Ok(parsed)
}

/// Collects points while reading: drops the ones with non-finite coordinates, refuses finite
/// ones beyond the coordinate bound.
pub(crate) struct CloudBuilder {
    parsed: Parsed,
    /// Set by the first finite point: its coordinates rounded to 1 km.
    frame: Option<LocalFrame>,
    max_abs: f64,
    index: usize,
}

impl CloudBuilder {
    /// `capacity_hint` must already be bounded by the input size.
    pub(crate) fn new(capacity_hint: usize, with_intensity: bool, limits: Limits) -> Self {
        let cloud = PointCloud {
            xyz: Vec::with_capacity(capacity_hint),
            intensity: with_intensity.then(|| Vec::with_capacity(capacity_hint)),
        };
        let mut parsed = Parsed { cloud, origin: [0.0; 3], min: [f64::INFINITY; 3], max: [f64::NEG_INFINITY; 3], dropped_non_finite: 0 };
        if let Some(f) = limits.frame {
            parsed.origin = f.origin();
        }
        CloudBuilder { parsed, frame: limits.frame, max_abs: limits.max_abs_coordinate, index: 0 }
    }

    /// Adds the file's next point (`x, y, z` in metres).
    pub(crate) fn push(&mut self, x: f64, y: f64, z: f64, intensity: f64) -> Result<(), FormatError> {
        let index = self.index;
        self.index += 1;
        let out_of_range = ['x', 'y', 'z'].into_iter().zip([x, y, z]).find(|(_, v)| v.is_finite() && v.abs() > self.max_abs);
        if let Some((axis, value)) = out_of_range {
            return Err(FormatError::OutOfRange { index, axis, value, max: self.max_abs });
        }
        if !(x.is_finite() && y.is_finite() && z.is_finite()) {
            self.parsed.dropped_non_finite += 1;
            return Ok(());
        }
        let xyz = [x, y, z];
        let frame = *self.frame.get_or_insert_with(|| {
            let origin = LocalFrame::centred_on(xyz, xyz);
            self.parsed.origin = origin.origin();
            origin
        });
        for c in 0..3 {
            self.parsed.min[c] = self.parsed.min[c].min(xyz[c]);
            self.parsed.max[c] = self.parsed.max[c].max(xyz[c]);
        }
        let cloud = &mut self.parsed.cloud;
        cloud.xyz.push(frame.point_to_local(xyz));
        if let Some(i) = cloud.intensity.as_mut() {
            i.push(intensity as f32);
        }
        Ok(())
    }

    pub(crate) fn finish(self) -> Parsed {
        if self.parsed.dropped_non_finite > 0 {
            tracing::debug!(dropped = self.parsed.dropped_non_finite, kept = self.parsed.cloud.len(), "dropped points with non-finite coordinates");
        }
        self.parsed
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
