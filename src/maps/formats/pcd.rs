//! PCD (Point Cloud Library) files: DATA ascii, binary and binary_compressed (LZF, columns).
//!
//! Fields may come in any order with types F/U/I of sizes 1/2/4/8 (type letters, header keys and
//! DATA values in either case, as PCL and Open3D read them); fields other than x, y, z and the
//! intensity (any of [`super::INTENSITY_NAMES`]) are skipped with any COUNT (`rgb`, `normal_x`,
//! PCL's `_` padding, ...); x, y, z and intensity need COUNT 1.

use super::scalar::Scalar;
use super::{check_count, intensity_field, lzf, CloudBuilder, FormatError, Limits, Parsed};

/// Headers longer than this are refused rather than scanned (a real one is a few hundred bytes).
const MAX_HEADER_BYTES: usize = 64 * 1024;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Ascii,
    Binary,
    BinaryCompressed,
}

#[derive(Debug)]
struct Field {
    name: String,
    scalar: Scalar,
    count: usize,
    /// Byte offset of this field within one binary row.
    offset: usize,
}

#[derive(Debug)]
struct Header {
    fields: Vec<Field>,
    points: usize,
    encoding: Encoding,
    row_bytes: usize,
    /// Where the data section starts in the file.
    data_start: usize,
}

/// Indices of the fields the reader keeps.
struct Columns {
    x: usize,
    y: usize,
    z: usize,
    intensity: Option<usize>,
}

pub(crate) fn looks_like_pcd(bytes: &[u8]) -> bool {
    let head = String::from_utf8_lossy(&bytes[..bytes.len().min(4096)]);
    if head.starts_with("# .PCD") {
        return true;
    }
    head.lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .map(|l| l.split_ascii_whitespace().next().unwrap_or_default().to_ascii_uppercase())
        .is_some_and(|key| key == "VERSION" || key == "FIELDS")
}

pub(crate) fn parse(bytes: &[u8], limits: Limits) -> Result<Parsed, FormatError> {
    let header = parse_header(bytes, limits)?;
    let columns = find_columns(&header.fields)?;
    let data = &bytes[header.data_start..];
    match header.encoding {
        Encoding::Ascii => parse_ascii(data, &header, &columns, limits),
        Encoding::Binary => {
            let needed = header.points.checked_mul(header.row_bytes).ok_or_else(|| FormatError::Header("POINTS × row size overflows".into()))?;
            if data.len() < needed {
                return Err(FormatError::Truncated(format!(
                    "binary data holds {} bytes, POINTS {} × {} bytes per point needs {needed}",
                    data.len(),
                    header.points,
                    header.row_bytes
                )));
            }
            read_rows(&header, &columns, limits, |field, i| {
                let f = &header.fields[field];
                field_value(f.scalar, &data[i * header.row_bytes + f.offset..])
            })
        }
        Encoding::BinaryCompressed => {
            let raw = decompress_columns(data, &header)?;
            let points = header.points;
            read_rows(&header, &columns, limits, |field, i| {
                let f = &header.fields[field];
                // Columns: all points of field 0, then all points of field 1, ...
                field_value(f.scalar, &raw[f.offset * points + i * f.scalar.size() * f.count..])
            })
        }
    }
}

fn field_value(scalar: Scalar, at: &[u8]) -> f64 {
    scalar.read(at, false)
}

fn read_rows(header: &Header, c: &Columns, limits: Limits, value: impl Fn(usize, usize) -> f64) -> Result<Parsed, FormatError> {
    let mut builder = CloudBuilder::new(header.points, c.intensity.is_some(), limits);
    for i in 0..header.points {
        let intensity = c.intensity.map_or(0.0, |f| value(f, i));
        builder.push(value(c.x, i), value(c.y, i), value(c.z, i), intensity)?;
    }
    Ok(builder.finish())
}

fn decompress_columns(data: &[u8], header: &Header) -> Result<Vec<u8>, FormatError> {
    let word = |at: usize| -> Result<usize, FormatError> {
        let b = data.get(at..at + 4).ok_or_else(|| FormatError::Truncated("binary_compressed data lacks its 8-byte size prefix".into()))?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
    };
    let (compressed_len, raw_len) = (word(0)?, word(4)?);
    let expected = header.points.checked_mul(header.row_bytes).ok_or_else(|| FormatError::Header("POINTS × row size overflows".into()))?;
    if raw_len != expected {
        return Err(FormatError::Mismatch(format!(
            "binary_compressed declares {raw_len} uncompressed bytes, POINTS {} × {} bytes per point is {expected}",
            header.points, header.row_bytes
        )));
    }
    let compressed = data.get(8..8 + compressed_len).ok_or_else(|| {
        FormatError::Truncated(format!("binary_compressed declares {compressed_len} compressed bytes, {} present", data.len().saturating_sub(8)))
    })?;
    // LZF expands at most ~88× (a 3-byte back-reference yields 264 bytes): anything claiming
    // more is corrupt, and this keeps the allocation proportional to the upload.
    if raw_len > compressed_len.saturating_mul(100).saturating_add(64) {
        return Err(FormatError::Corrupt(format!("{compressed_len} compressed bytes cannot hold {raw_len} bytes")));
    }
    lzf::decompress(compressed, raw_len)
}

fn parse_ascii(data: &[u8], header: &Header, c: &Columns, limits: Limits) -> Result<Parsed, FormatError> {
    let text = std::str::from_utf8(data).map_err(|e| FormatError::BadNumber {
        token: "<non-UTF-8 bytes>".into(),
        context: format!("ascii PCD data at byte {}", e.valid_up_to()),
    })?;
    // Token positions of each field within a row (a field with COUNT n takes n tokens).
    let mut first_token = Vec::with_capacity(header.fields.len());
    let mut tokens_per_row = 0usize;
    for f in &header.fields {
        first_token.push(tokens_per_row);
        tokens_per_row += f.count;
    }
    let wanted: Vec<(usize, Scalar)> = [Some(c.x), Some(c.y), Some(c.z), c.intensity]
        .into_iter()
        .flatten()
        .map(|f| (first_token[f], header.fields[f].scalar))
        .collect();
    let mut builder = CloudBuilder::new(header.points.min(data.len() / 6 + 1), c.intensity.is_some(), limits);
    let mut rows = 0usize;
    let mut values = [0.0f64; 4];
    for (line_no, line) in text.lines().map(str::trim).filter(|l| !l.is_empty()).enumerate() {
        if rows == header.points {
            return Err(FormatError::Mismatch(format!("ascii data has more rows than POINTS {}", header.points)));
        }
        let tokens: Vec<&str> = line.split_ascii_whitespace().collect();
        if tokens.len() != tokens_per_row {
            return Err(FormatError::Mismatch(format!(
                "data row {} has {} values, the fields declare {tokens_per_row}",
                line_no + 1,
                tokens.len()
            )));
        }
        for (slot, (token_index, scalar)) in wanted.iter().enumerate() {
            let token = tokens[*token_index];
            values[slot] = scalar.parse_ascii(token).ok_or_else(|| FormatError::BadNumber {
                token: token.chars().take(40).collect(),
                context: format!("data row {}", line_no + 1),
            })?;
        }
        builder.push(values[0], values[1], values[2], values[3])?;
        rows += 1;
    }
    if rows < header.points {
        return Err(FormatError::Truncated(format!("ascii data has {rows} rows, POINTS declares {}", header.points)));
    }
    Ok(builder.finish())
}

fn find_columns(fields: &[Field]) -> Result<Columns, FormatError> {
    let names = fields.iter().map(|f| f.name.as_str());
    let check = |hit: Option<usize>| -> Result<Option<usize>, FormatError> {
        let Some(i) = hit else { return Ok(None) };
        let name = &fields[i].name;
        if fields.iter().filter(|f| f.name.eq_ignore_ascii_case(name)).count() > 1 {
            return Err(FormatError::Header(format!("field {name:?} appears twice")));
        }
        if fields[i].count != 1 {
            return Err(FormatError::Unsupported(format!("field {name:?} with COUNT {}", fields[i].count)));
        }
        Ok(Some(i))
    };
    let need = |name: &str| {
        check(names.clone().position(|f| f.eq_ignore_ascii_case(name)))?.ok_or_else(|| FormatError::Unsupported(format!("PCD without a {name:?} field")))
    };
    Ok(Columns { x: need("x")?, y: need("y")?, z: need("z")?, intensity: check(intensity_field(names.clone()))? })
}

fn parse_header(bytes: &[u8], limits: Limits) -> Result<Header, FormatError> {
    let mut names: Option<Vec<String>> = None;
    let mut sizes: Option<Vec<usize>> = None;
    let mut types: Option<Vec<String>> = None;
    let mut counts: Option<Vec<usize>> = None;
    let (mut width, mut height, mut points): (Option<u64>, Option<u64>, Option<u64>) = (None, None, None);
    let mut pos = 0usize;
    loop {
        if pos >= bytes.len() {
            return Err(FormatError::Header("no DATA line".into()));
        }
        if pos > MAX_HEADER_BYTES {
            return Err(FormatError::Header(format!("no DATA line within the first {MAX_HEADER_BYTES} bytes")));
        }
        let end = bytes[pos..].iter().position(|&b| b == b'\n').map_or(bytes.len(), |i| pos + i);
        let line = std::str::from_utf8(&bytes[pos..end]).map_err(|_| FormatError::Header("header line is not text".into()))?.trim();
        let next = (end + 1).min(bytes.len());
        pos = next;
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut parts = line.split_ascii_whitespace();
        let key = parts.next().unwrap_or_default().to_ascii_uppercase();
        let rest: Vec<&str> = parts.collect();
        let number = |what: &str, token: &str| -> Result<u64, FormatError> {
            token.parse::<u64>().map_err(|_| FormatError::BadNumber { token: token.chars().take(40).collect(), context: format!("PCD {what}") })
        };
        let single = |what: &str| -> Result<u64, FormatError> {
            match rest.as_slice() {
                [one] => number(what, one),
                _ => Err(FormatError::Header(format!("{what} needs one value, got {:?}", rest))),
            }
        };
        match key.as_str() {
            "VERSION" | "VIEWPOINT" => {}
            "FIELDS" => names = Some(rest.iter().map(|s| s.to_string()).collect()),
            "SIZE" => sizes = Some(rest.iter().map(|t| number("SIZE", t).map(|v| v as usize)).collect::<Result<_, _>>()?),
            "TYPE" => types = Some(rest.iter().map(|s| s.to_string()).collect()),
            "COUNT" => {
                let parsed: Vec<usize> = rest.iter().map(|t| number("COUNT", t).map(|v| v as usize)).collect::<Result<_, _>>()?;
                if parsed.iter().any(|&c| c == 0 || c > 1 << 16) {
                    return Err(FormatError::Unsupported(format!("COUNT values {parsed:?} (each must be 1..=65536)")));
                }
                counts = Some(parsed);
            }
            "WIDTH" => width = Some(single("WIDTH")?),
            "HEIGHT" => height = Some(single("HEIGHT")?),
            "POINTS" => points = Some(single("POINTS")?),
            "DATA" => {
                let encoding = match rest.iter().map(|w| w.to_ascii_lowercase()).collect::<Vec<_>>().as_slice() {
                    [one] if one == "ascii" => Encoding::Ascii,
                    [one] if one == "binary" => Encoding::Binary,
                    [one] if one == "binary_compressed" => Encoding::BinaryCompressed,
                    _ => return Err(FormatError::Unsupported(format!("PCD DATA {:?} (ascii, binary or binary_compressed)", rest.join(" ")))),
                };
                return build_header(names, sizes, types, counts, (width, height, points), encoding, next, limits);
            }
            other => return Err(FormatError::Header(format!("unknown PCD header key {:?}", other.chars().take(40).collect::<String>()))),
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn build_header(
    names: Option<Vec<String>>,
    sizes: Option<Vec<usize>>,
    types: Option<Vec<String>>,
    counts: Option<Vec<usize>>,
    (width, height, points): (Option<u64>, Option<u64>, Option<u64>),
    encoding: Encoding,
    data_start: usize,
    limits: Limits,
) -> Result<Header, FormatError> {
    let names = names.ok_or_else(|| FormatError::Header("no FIELDS line".into()))?;
    let sizes = sizes.ok_or_else(|| FormatError::Header("no SIZE line".into()))?;
    let types = types.ok_or_else(|| FormatError::Header("no TYPE line".into()))?;
    let counts = counts.unwrap_or_else(|| vec![1; names.len()]);
    if names.is_empty() || sizes.len() != names.len() || types.len() != names.len() || counts.len() != names.len() {
        return Err(FormatError::Header(format!(
            "FIELDS ({}), SIZE ({}), TYPE ({}) and COUNT ({}) must list the same number of fields",
            names.len(),
            sizes.len(),
            types.len(),
            counts.len()
        )));
    }
    let mut fields = Vec::with_capacity(names.len());
    let mut offset = 0usize;
    for (((name, size), kind), count) in names.into_iter().zip(sizes).zip(types).zip(counts) {
        let scalar = Scalar::from_pcd(&kind, size)
            .ok_or_else(|| FormatError::Unsupported(format!("field {name:?} of TYPE {kind} SIZE {size} (types F/U/I with sizes 1, 2, 4, 8)")))?;
        fields.push(Field { name, scalar, count, offset });
        offset += size * count;
    }
    let declared = match (points, width, height) {
        (Some(p), Some(w), Some(h)) if w.checked_mul(h) != Some(p) => {
            return Err(FormatError::Mismatch(format!("POINTS {p} is not WIDTH {w} × HEIGHT {h}")));
        }
        (Some(p), _, _) => p,
        (None, Some(w), h) => w.checked_mul(h.unwrap_or(1)).ok_or_else(|| FormatError::Header("WIDTH × HEIGHT overflows".into()))?,
        (None, None, _) => return Err(FormatError::Header("neither POINTS nor WIDTH given".into())),
    };
    let points = check_count(declared, limits)?;
    Ok(Header { fields, points, encoding, row_bytes: offset, data_start })
}
