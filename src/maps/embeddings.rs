//! `<id>.emb`: a map's prepared points and embeddings, persisted so a restart does not recompute
//! them. The header names the point encoder's sha256 and the source cloud's sha256, so a new model
//! or a replaced map file invalidates it.
//!
//! Layout (little-endian): magic `CMREMB01`, 64 ASCII hex model sha, 64 ASCII hex source sha,
//! u64 N, u64 D, u64 source point count, 3 × f64 pivot, N × 3 f32 points, N × D f32 features.

use std::io::Write;

use nalgebra::Point3;

use super::PreparedMap;

const MAGIC: &[u8; 8] = b"CMREMB01";
const HEADER: usize = 8 + 64 + 64 + 8 * 3 + 8 * 3;

/// Writes the file to `out` in the layout above, streaming the floats (no copy of the whole).
pub fn write(out: &mut impl Write, map: &PreparedMap, model_sha: &str, source_sha: &str) -> std::io::Result<()> {
    let d = map.features.len() / map.points.len().max(1);
    out.write_all(MAGIC)?;
    out.write_all(&fixed_hex(model_sha))?;
    out.write_all(&fixed_hex(source_sha))?;
    for v in [map.points.len() as u64, d as u64, map.source_points as u64] {
        out.write_all(&v.to_le_bytes())?;
    }
    for v in [map.pivot.x, map.pivot.y, map.pivot.z] {
        out.write_all(&v.to_le_bytes())?;
    }
    write_f32s(out, map.points.as_flattened())?;
    write_f32s(out, &map.features)
}

fn write_f32s(out: &mut impl Write, values: &[f32]) -> std::io::Result<()> {
    let mut buf = [0u8; 1 << 14];
    for chunk in values.chunks(buf.len() / 4) {
        for (b, v) in buf.chunks_exact_mut(4).zip(chunk) {
            b.copy_from_slice(&v.to_le_bytes());
        }
        out.write_all(&buf[..chunk.len() * 4])?;
    }
    Ok(())
}

/// The stored map, or `None` when the file is for another model/source or is damaged.
pub fn decode(bytes: &[u8], model_sha: &str, source_sha: &str) -> Option<PreparedMap> {
    if bytes.len() < HEADER || &bytes[..8] != MAGIC {
        return None;
    }
    if bytes[8..72] != fixed_hex(model_sha) || bytes[72..136] != fixed_hex(source_sha) {
        return None;
    }
    let u = |at: usize| u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap()) as usize;
    let f = |at: usize| f64::from_le_bytes(bytes[at..at + 8].try_into().unwrap());
    let (n, d, source_points) = (u(136), u(144), u(152));
    let pivot = Point3::new(f(160), f(168), f(176));
    let expected = n.checked_mul(12)?.checked_add(n.checked_mul(d)?.checked_mul(4)?)?.checked_add(HEADER)?;
    if bytes.len() != expected {
        return None;
    }
    let floats = |from: usize, count: usize| -> Vec<f32> {
        bytes[from..from + count * 4].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
    };
    let flat = floats(HEADER, n * 3);
    let points = flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    let features = floats(HEADER + n * 12, n * d);
    Some(PreparedMap { points, features, pivot, source_points, intensity: None })
}

/// A sha256 hex string as the 64 fixed bytes the embedding files' headers hold (lower case).
pub(crate) fn fixed_hex(s: &str) -> [u8; 64] {
    let mut out = [b'0'; 64];
    for (o, b) in out.iter_mut().zip(s.to_ascii_lowercase().bytes()) {
        *o = b;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_invalidation() {
        let map = PreparedMap {
            points: vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]],
            features: vec![0.5; 8],
            pivot: Point3::new(2.5, 3.5, 4.5),
            source_points: 7,
            intensity: None,
        };
        let mut bytes = Vec::new();
        write(&mut bytes, &map, "ab", "cd").unwrap();
        let back = decode(&bytes, "ab", "cd").unwrap();
        assert_eq!(back.points, map.points);
        assert_eq!(back.features, map.features);
        assert_eq!(back.pivot, map.pivot);
        assert_eq!(back.source_points, 7);
        assert!(decode(&bytes, "other", "cd").is_none());
        assert!(decode(&bytes, "ab", "other").is_none());
        assert!(decode(&bytes[..bytes.len() - 1], "ab", "cd").is_none());
    }
}
