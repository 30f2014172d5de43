//! gzip (RFC 1952) bodies, decompressed with `flate2` under a hard bound on the output size, so a
//! small upload that inflates to gigabytes (a "gzip bomb") costs at most `max_bytes + 1` bytes.

use std::io::Read;

/// Why a gzip body was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum GzipError {
    /// The stream inflates to more than the bound (bytes).
    #[error("the gzip body inflates to more than {0} bytes")]
    TooLarge(usize),
    /// Not a valid gzip stream (bad header, corrupt deflate data, wrong CRC, cut short).
    #[error("corrupt gzip data: {0}")]
    Corrupt(String),
}

/// Inflates every member of a gzip stream (`cat a.gz b.gz` is valid gzip), stopping with
/// [`GzipError::TooLarge`] once the output would exceed `max_bytes`.
pub fn decompress(compressed: &[u8], max_bytes: usize) -> Result<Vec<u8>, GzipError> {
    let mut out = Vec::with_capacity(compressed.len().saturating_mul(4).min(max_bytes));
    let limit = (max_bytes as u64).saturating_add(1);
    flate2::read::MultiGzDecoder::new(compressed)
        .take(limit)
        .read_to_end(&mut out)
        .map_err(|e| GzipError::Corrupt(e.to_string()))?;
    if out.len() > max_bytes {
        return Err(GzipError::TooLarge(max_bytes));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn gzip(data: &[u8]) -> Vec<u8> {
        let mut encoder = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        encoder.write_all(data).unwrap();
        encoder.finish().unwrap()
    }

    #[test]
    fn round_trip_bound_and_corruption() {
        let data: Vec<u8> = (0..10_000u32).flat_map(|i| (i % 251).to_le_bytes()).collect();
        let packed = gzip(&data);
        assert_eq!(decompress(&packed, data.len()).unwrap(), data);
        assert_eq!(decompress(&packed, data.len() - 1), Err(GzipError::TooLarge(data.len() - 1)));
        let mut two = packed.clone();
        two.extend_from_slice(&gzip(b"tail"));
        assert_eq!(decompress(&two, 1 << 20).unwrap().len(), data.len() + 4, "every member is read");
        assert!(matches!(decompress(&packed[..packed.len() / 2], 1 << 20), Err(GzipError::Corrupt(_))));
        let mut flipped = packed.clone();
        let at = flipped.len() - 6;
        flipped[at] ^= 0xff;
        assert!(matches!(decompress(&flipped, 1 << 20), Err(GzipError::Corrupt(_))), "the CRC is checked");
    }

    #[test]
    fn a_bomb_stops_at_the_bound() {
        let bomb = gzip(&vec![0u8; 64 << 20]); // 64 MiB of zeros, ~65 KB packed
        assert!(bomb.len() < 100_000);
        assert_eq!(decompress(&bomb, 1 << 20), Err(GzipError::TooLarge(1 << 20)));
    }
}
