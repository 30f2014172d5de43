//! An uploaded map body, from bytes to a cloud: gzip is inflated (under the map byte bound), the
//! content is named by its magic bytes, then parsed as the format it is.
//!
//! Refusals, as [`MapError`]s: a body recognised as something other than a point cloud (PNG,
//! JPEG, zip, gzip inside gzip, ...) is `Unsupported` (HTTP 415) and says what it looks like
//! and what is accepted; gzip that inflates past the bound, or a file with more points than `limits.max_points`, is
//! `TooLarge` (413); bytes with no known
//! signature that are not KITTI `.bin` either, a cloud that does not parse, corrupt gzip, or a
//! `format` that contradicts the body's own header are `BadCloud` (422).

use super::formats::sniff::{content, Content};
use super::formats::{self, gzip, CloudFormat, FormatError, Limits, Parsed, ACCEPTED};
use super::MapError;

/// One upload as the client sent it.
#[derive(Debug, Clone, Copy)]
pub struct Upload<'a> {
    pub bytes: &'a [u8],
    /// The format the client named (`?format=`); sniffed when `None`.
    pub format: Option<CloudFormat>,
    /// The body was sent with `Content-Encoding: gzip` (a gzip body is also recognised without it).
    pub gzip: bool,
    /// The most bytes the cloud file may have once inflated.
    pub max_bytes: usize,
}

/// Parses an upload within `limits`, naming what was received when it is not a cloud we read.
pub fn read_upload(upload: Upload, limits: Limits) -> Result<Parsed, MapError> {
    let inflated;
    let (bytes, what) = if upload.gzip || content(upload.bytes) == Content::Gzip {
        inflated = gzip::decompress(upload.bytes, upload.max_bytes).map_err(|e| match e {
            gzip::GzipError::TooLarge(_) => MapError::TooLarge(format!("{e} (the map limit)")),
            gzip::GzipError::Corrupt(_) => MapError::BadCloud(e.to_string()),
        })?;
        (inflated.as_slice(), "the gzip body holds")
    } else {
        (upload.bytes, "the body is")
    };
    let format = match (content(bytes), upload.format) {
        (Content::Gzip, _) => return Err(MapError::Unsupported(format!("{what} another gzip stream; compress once; send {ACCEPTED}"))),
        (Content::NotACloud(kind), _) => return Err(MapError::Unsupported(format!("{what} {kind}, not a point cloud; send {ACCEPTED}"))),
        (Content::Cloud(found), Some(named)) if found != named => {
            return Err(MapError::BadCloud(format!(
                "format={} was given but {what} a {} file; pass format={} or omit format",
                named.name(),
                found.label(),
                found.name()
            )))
        }
        (Content::Cloud(found), _) => found,
        (Content::Unknown, Some(named)) => named,
        (Content::Unknown, None) if bytes.is_empty() => return Err(MapError::BadCloud(FormatError::Empty.to_string())),
        (Content::Unknown, None) => CloudFormat::sniff(bytes).ok_or_else(|| {
            MapError::BadCloud(format!(
                "{what} {} bytes with no known signature and not a KITTI .bin (a multiple of 16 bytes); send {ACCEPTED}",
                bytes.len()
            ))
        })?,
    };
    formats::parse_counted(bytes, format, limits).map_err(|e| match e {
        FormatError::TooManyPoints { count, max } => {
            MapError::TooLarge(format!("the {} file holds {count} points; this server accepts at most {max} per region (--max-map-points)", format.label()))
        }
        e => MapError::BadCloud(format!("{}: {e}", format.label())),
    })
}
