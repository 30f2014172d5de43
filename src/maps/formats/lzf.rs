//! LZF decompression (the codec of PCD's `binary_compressed`), bounds-checked throughout.
//!
//! Stream: a control byte c; c < 32 means c + 1 literal bytes follow; otherwise a back-reference
//! of length (c >> 5) + 2 (with 7 meaning "add the next byte") at distance ((c & 31) << 8 | next) + 1.

use super::FormatError;

pub(crate) fn decompress(input: &[u8], expected_len: usize) -> Result<Vec<u8>, FormatError> {
    let mut out = Vec::with_capacity(expected_len);
    let mut ip = 0;
    let byte_at = |ip: usize| input.get(ip).copied().ok_or_else(|| FormatError::Corrupt("stream ends inside a back-reference".into()));
    while ip < input.len() {
        let ctrl = input[ip] as usize;
        ip += 1;
        if ctrl < 32 {
            let len = ctrl + 1;
            let literal = input.get(ip..ip + len).ok_or_else(|| FormatError::Corrupt("stream ends inside a literal run".into()))?;
            if out.len() + len > expected_len {
                return Err(FormatError::Corrupt("decompresses to more bytes than declared".into()));
            }
            out.extend_from_slice(literal);
            ip += len;
        } else {
            let mut len = ctrl >> 5;
            if len == 7 {
                len += byte_at(ip)? as usize;
                ip += 1;
            }
            len += 2;
            let distance = ((ctrl & 0x1f) << 8 | byte_at(ip)? as usize) + 1;
            ip += 1;
            if distance > out.len() {
                return Err(FormatError::Corrupt("back-reference before the start of the output".into()));
            }
            if out.len() + len > expected_len {
                return Err(FormatError::Corrupt("decompresses to more bytes than declared".into()));
            }
            let start = out.len() - distance;
            for k in 0..len {
                out.push(out[start + k]);
            }
        }
    }
    if out.len() != expected_len {
        return Err(FormatError::Corrupt(format!("decompressed to {} bytes, header declares {expected_len}", out.len())));
    }
    Ok(out)
}

/// A valid LZF stream made of literal runs only: enough to write test files and small exports.
#[cfg(test)]
pub(crate) fn compress_literal_only(data: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(data.len() + data.len() / 32 + 1);
    for chunk in data.chunks(32) {
        out.push((chunk.len() - 1) as u8);
        out.extend_from_slice(chunk);
    }
    out
}
