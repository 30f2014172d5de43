//! What an uploaded body is, from its first bytes: one of the point-cloud formats we read, a gzip
//! stream (which may hold one), or something else that we can name in the refusal (an image, an
//! archive, a document).
//!
//! Magic numbers checked, in order: gzip `1f 8b 08` with the reserved flag bits clear; LAS `LASF`
//! (LAZ too: the LAS reader decompresses it); PLY `ply` + newline; PCD (`# .PCD` or a first header key);
//! PNG `89 50 4e 47 0d 0a 1a 0a`; JPEG `ff d8 ff` + an APPn/DQT/COM marker; zip `PK 03 04` (also
//! an empty `PK 05 06`); 7z, xz, bzip2, zstd, PDF; then text that starts like JSON, HTML or XML.
//! Read as KITTI float32 records, each binary prefix is either 4 or more exact bytes (a chance
//! below 2⁻³² for a scan), or makes the first x a value no scan holds (gzip: 0 < |x| < 3e-20 m;
//! the JPEG markers: |x| > 7e16 m), so a headerless KITTI `.bin` is not mistaken for one of them.

use super::{las, pcd, CloudFormat};

/// What the body looks like.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Content {
    /// A point-cloud format with a header (PCD, PLY, LAS).
    Cloud(CloudFormat),
    /// A gzip stream (RFC 1952, deflate method).
    Gzip,
    /// Something that is not a point cloud we read, named for the error message
    /// (e.g. "a PNG image", "a zip archive").
    NotACloud(&'static str),
    /// No known signature: headerless KITTI `.bin`, or garbage.
    Unknown,
}

/// Names the body by its signature. Headerless KITTI `.bin` comes back as `Unknown`.
pub fn content(bytes: &[u8]) -> Content {
    let starts = |magic: &[u8]| bytes.starts_with(magic);
    if starts(&[0x1f, 0x8b, 0x08]) && bytes.get(3).is_some_and(|flags| flags & 0xe0 == 0) {
        return Content::Gzip;
    }
    if starts(b"LASF") {
        // LAS or LAZ (the point data format byte at offset 104), which the LAS reader
        // decompresses, except the layered formats 6-10.
        return match bytes.get(104) {
            Some(&f) if las::PointFormatByte(f).layered_laz() => Content::NotACloud("LAZ with a layered point format (6-10)"),
            _ => Content::Cloud(CloudFormat::Las),
        };
    }
    if starts(b"ply\n") || starts(b"ply\r\n") {
        return Content::Cloud(CloudFormat::Ply);
    }
    if pcd::looks_like_pcd(bytes) {
        return Content::Cloud(CloudFormat::Pcd);
    }
    let named = |what| Content::NotACloud(what);
    if starts(&[0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a]) {
        return named("a PNG image");
    }
    if starts(&[0xff, 0xd8, 0xff]) && bytes.get(3).is_some_and(|m| (0xe0..=0xef).contains(m) || *m == 0xdb || *m == 0xfe) {
        return named("a JPEG image");
    }
    if starts(b"PK\x03\x04") || starts(b"PK\x05\x06") {
        return named("a zip archive");
    }
    if starts(b"7z\xbc\xaf\x27\x1c") {
        return named("a 7z archive");
    }
    if starts(b"\xfd7zXZ\x00") {
        return named("an xz stream");
    }
    if starts(b"BZh") && bytes.get(3).is_some_and(|b| (b'1'..=b'9').contains(b)) && bytes.get(4..10) == Some(b"\x31\x41\x59\x26\x53\x59") {
        return named("a bzip2 stream");
    }
    if starts(&[0x28, 0xb5, 0x2f, 0xfd]) {
        return named("a zstd stream");
    }
    if starts(b"%PDF-") {
        return named("a PDF document");
    }
    let text = bytes.iter().skip_while(|b| b.is_ascii_whitespace()).take(16).copied().collect::<Vec<u8>>();
    let text = String::from_utf8_lossy(&text).to_ascii_lowercase();
    if text.starts_with("<!doctype html") || text.starts_with("<html") {
        return named("an HTML document");
    }
    if text.starts_with("<?xml") {
        return named("an XML document");
    }
    if (text.starts_with('{') || text.starts_with('[')) && serde_json::from_slice::<serde::de::IgnoredAny>(bytes).is_ok() {
        return named("a JSON document");
    }
    Content::Unknown
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signatures() {
        assert_eq!(content(&[0x1f, 0x8b, 0x08, 0, 0]), Content::Gzip);
        let mut las = b"LASF".to_vec();
        las.resize(227, 0);
        assert_eq!(content(&las), Content::Cloud(CloudFormat::Las));
        las[104] = 0x83; // LAZ
        assert_eq!(content(&las), Content::Cloud(CloudFormat::Las));
        las[104] = 0x86; // LAZ, layered
        assert_eq!(content(&las), Content::NotACloud("LAZ with a layered point format (6-10)"));
        assert_eq!(content(b"ply\nformat ascii 1.0\n"), Content::Cloud(CloudFormat::Ply));
        assert_eq!(content(b"# .PCD v0.7\nVERSION 0.7\n"), Content::Cloud(CloudFormat::Pcd));
        assert_eq!(content(b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR"), Content::NotACloud("a PNG image"));
        assert_eq!(content(&[0xff, 0xd8, 0xff, 0xe0, 0, 0x10]), Content::NotACloud("a JPEG image"));
        assert_eq!(content(b"PK\x03\x04\x14\0"), Content::NotACloud("a zip archive"));
        assert_eq!(content(b" {\"a\": 1}"), Content::NotACloud("a JSON document"));
        assert_eq!(content(b"<!DOCTYPE html><html>"), Content::NotACloud("an HTML document"));
        assert_eq!(content(&[0u8; 32]), Content::Unknown);
        // A KITTI record whose x starts like a JPEG SOF marker (x ≈ -8.0) is not taken for one.
        assert_eq!(content(&[0xff, 0xd8, 0xff, 0xc0, 0, 0, 0, 0]), Content::Unknown);
    }
}
