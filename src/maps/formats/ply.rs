//! PLY files: ascii, binary_little_endian and binary_big_endian.
//!
//! The `vertex` element must have scalar x, y, z (any numeric type, names case-insensitive) and
//! may have an intensity (any of [`super::INTENSITY_NAMES`], e.g. CloudCompare's
//! `scalar_Intensity`); its other properties, and every other element before it (with list
//! properties too), are skipped. Elements after `vertex` are not read.

use super::scalar::Scalar;
use super::{check_count, intensity_field, CloudBuilder, FormatError, Limits, Parsed};

const MAX_HEADER_BYTES: usize = 64 * 1024;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Ascii,
    LittleEndian,
    BigEndian,
}

#[derive(Debug)]
enum Property {
    Scalar { name: String, scalar: Scalar },
    List { count: Scalar, item: Scalar },
}

#[derive(Debug)]
struct Element {
    name: String,
    count: u64,
    properties: Vec<Property>,
}

pub(crate) fn parse(bytes: &[u8], limits: Limits) -> Result<Parsed, FormatError> {
    let (encoding, elements, data_start) = parse_header(bytes)?;
    let vertex_index = elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| FormatError::Unsupported("PLY without a vertex element".into()))?;
    let vertex = &elements[vertex_index];
    let count = check_count(vertex.count, limits)?;
    // Property names of the vertex element ("" for lists, which are never read).
    let names = vertex.properties.iter().map(|p| match p {
        Property::Scalar { name, .. } => name.as_str(),
        Property::List { .. } => "",
    });
    let need = |n: &str| {
        names.clone().position(|p| p.eq_ignore_ascii_case(n)).ok_or_else(|| FormatError::Unsupported(format!("PLY vertex element without a scalar {n:?} property")))
    };
    let wanted = [Some(need("x")?), Some(need("y")?), Some(need("z")?), intensity_field(names.clone())];
    let data = &bytes[data_start..];
    match encoding {
        Encoding::Ascii => {
            let text = std::str::from_utf8(data).map_err(|e| FormatError::BadNumber {
                token: "<non-UTF-8 bytes>".into(),
                context: format!("ascii PLY data at byte {}", e.valid_up_to()),
            })?;
            let mut tokens = AsciiTokens { inner: text.split_ascii_whitespace(), read: 0 };
            for element in &elements[..vertex_index] {
                skip_ascii(&mut tokens, element)?;
            }
            read_vertices(count, limits, wanted, vertex, |props| read_ascii_row(&mut tokens, &vertex.properties, props))
        }
        Encoding::LittleEndian | Encoding::BigEndian => {
            let big = encoding == Encoding::BigEndian;
            let mut cursor = Cursor { data, pos: 0, big };
            for element in &elements[..vertex_index] {
                skip_binary(&mut cursor, element)?;
            }
            // Fixed-size vertex rows (the usual case): check the length once, up front.
            if vertex.properties.iter().all(|p| matches!(p, Property::Scalar { .. })) {
                let row: usize = vertex.properties.iter().map(|p| if let Property::Scalar { scalar, .. } = p { scalar.size() } else { 0 }).sum();
                let available = cursor.data.len() - cursor.pos;
                if (count as u128) * (row as u128) > available as u128 {
                    return Err(FormatError::Truncated(format!("{count} vertices × {row} bytes do not fit in the {available} bytes left")));
                }
            }
            read_vertices(count, limits, wanted, vertex, |props| read_binary_row(&mut cursor, &vertex.properties, props))
        }
    }
}

fn read_vertices(
    count: usize,
    limits: Limits,
    wanted: [Option<usize>; 4],
    vertex: &Element,
    mut read_row: impl FnMut(&mut [f64]) -> Result<(), FormatError>,
) -> Result<Parsed, FormatError> {
    let mut builder = CloudBuilder::new(count.min(1 << 20), wanted[3].is_some(), limits);
    let mut row = vec![0.0f64; vertex.properties.len()];
    for _ in 0..count {
        read_row(&mut row)?;
        let get = |slot: Option<usize>| slot.map_or(0.0, |i| row[i]);
        builder.push(get(wanted[0]), get(wanted[1]), get(wanted[2]), get(wanted[3]))?;
    }
    Ok(builder.finish())
}

struct AsciiTokens<'a> {
    inner: std::str::SplitAsciiWhitespace<'a>,
    read: usize,
}

impl AsciiTokens<'_> {
    fn value(&mut self, scalar: Scalar) -> Result<f64, FormatError> {
        let token = self.inner.next().ok_or_else(|| FormatError::Truncated(format!("ascii PLY data ends after {} values", self.read)))?;
        self.read += 1;
        scalar.parse_ascii(token).ok_or_else(|| FormatError::BadNumber {
            token: token.chars().take(40).collect(),
            context: format!("ascii PLY value {}", self.read),
        })
    }
}

fn list_len(value: f64) -> Result<usize, FormatError> {
    if value < 0.0 || value.fract() != 0.0 || value > (1u64 << 32) as f64 {
        return Err(FormatError::BadNumber { token: value.to_string(), context: "PLY list length".into() });
    }
    Ok(value as usize)
}

fn read_ascii_row(tokens: &mut AsciiTokens, properties: &[Property], out: &mut [f64]) -> Result<(), FormatError> {
    for (slot, property) in properties.iter().enumerate() {
        match property {
            Property::Scalar { scalar, .. } => out[slot] = tokens.value(*scalar)?,
            Property::List { count, item } => {
                for _ in 0..list_len(tokens.value(*count)?)? {
                    tokens.value(*item)?;
                }
            }
        }
    }
    Ok(())
}

fn skip_ascii(tokens: &mut AsciiTokens, element: &Element) -> Result<(), FormatError> {
    if element.properties.is_empty() {
        return Ok(());
    }
    let mut scratch = vec![0.0; element.properties.len()];
    // Each instance consumes at least one token, so a huge count ends at the end of the text.
    for _ in 0..element.count {
        read_ascii_row(tokens, &element.properties, &mut scratch)?;
    }
    Ok(())
}

struct Cursor<'a> {
    data: &'a [u8],
    pos: usize,
    big: bool,
}

impl Cursor<'_> {
    fn value(&mut self, scalar: Scalar) -> Result<f64, FormatError> {
        let end = self.pos + scalar.size();
        let bytes = self.data.get(self.pos..end).ok_or_else(|| FormatError::Truncated(format!("binary PLY data ends at byte {}", self.data.len())))?;
        self.pos = end;
        Ok(scalar.read(bytes, self.big))
    }

    fn skip(&mut self, bytes: u128) -> Result<(), FormatError> {
        let left = (self.data.len() - self.pos) as u128;
        if bytes > left {
            return Err(FormatError::Truncated(format!("binary PLY data needs {bytes} more bytes, {left} left")));
        }
        self.pos += bytes as usize;
        Ok(())
    }
}

fn read_binary_row(cursor: &mut Cursor, properties: &[Property], out: &mut [f64]) -> Result<(), FormatError> {
    for (slot, property) in properties.iter().enumerate() {
        match property {
            Property::Scalar { scalar, .. } => out[slot] = cursor.value(*scalar)?,
            Property::List { count, item } => {
                let n = list_len(cursor.value(*count)?)?;
                cursor.skip(n as u128 * item.size() as u128)?;
            }
        }
    }
    Ok(())
}

fn skip_binary(cursor: &mut Cursor, element: &Element) -> Result<(), FormatError> {
    if element.properties.iter().all(|p| matches!(p, Property::Scalar { .. })) {
        let row: u128 = element.properties.iter().map(|p| if let Property::Scalar { scalar, .. } = p { scalar.size() as u128 } else { 0 }).sum();
        return cursor.skip(row * element.count as u128);
    }
    let mut scratch = vec![0.0; element.properties.len()];
    // Each instance reads at least one list length, so this ends at the end of the data.
    for _ in 0..element.count {
        read_binary_row(cursor, &element.properties, &mut scratch)?;
    }
    Ok(())
}

fn parse_header(bytes: &[u8]) -> Result<(Encoding, Vec<Element>, usize), FormatError> {
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut pos = 0usize;
    let mut first = true;
    loop {
        if pos >= bytes.len() || pos > MAX_HEADER_BYTES {
            return Err(FormatError::Header("no end_header line".into()));
        }
        let end = bytes[pos..].iter().position(|&b| b == b'\n').map_or(bytes.len(), |i| pos + i);
        let line = std::str::from_utf8(&bytes[pos..end]).map_err(|_| FormatError::Header("header line is not text".into()))?.trim();
        pos = (end + 1).min(bytes.len());
        let words: Vec<&str> = line.split_ascii_whitespace().collect();
        if first {
            if line != "ply" {
                return Err(FormatError::Header("a PLY file starts with the line \"ply\"".into()));
            }
            first = false;
            continue;
        }
        match words.as_slice() {
            [] | ["comment", ..] | ["obj_info", ..] => {}
            ["format", kind, _version] => {
                encoding = Some(match *kind {
                    "ascii" => Encoding::Ascii,
                    "binary_little_endian" => Encoding::LittleEndian,
                    "binary_big_endian" => Encoding::BigEndian,
                    other => return Err(FormatError::Unsupported(format!("PLY format {other:?}"))),
                })
            }
            ["element", name, count] => {
                let count = count.parse::<u64>().map_err(|_| FormatError::BadNumber { token: count.chars().take(40).collect(), context: format!("PLY element {name} count") })?;
                elements.push(Element { name: name.to_string(), count, properties: Vec::new() });
            }
            ["property", "list", count, item, _name] => {
                let element = elements.last_mut().ok_or_else(|| FormatError::Header("property before any element".into()))?;
                let count = Scalar::from_ply(count).filter(|s| s.is_integer()).ok_or_else(|| FormatError::Unsupported(format!("PLY list count type {count:?}")))?;
                let item = Scalar::from_ply(item).ok_or_else(|| FormatError::Unsupported(format!("PLY type {item:?}")))?;
                element.properties.push(Property::List { count, item });
            }
            ["property", kind, name] => {
                let element = elements.last_mut().ok_or_else(|| FormatError::Header("property before any element".into()))?;
                let scalar = Scalar::from_ply(kind).ok_or_else(|| FormatError::Unsupported(format!("PLY type {kind:?}")))?;
                element.properties.push(Property::Scalar { name: name.to_string(), scalar });
            }
            ["end_header"] => {
                let encoding = encoding.ok_or_else(|| FormatError::Header("no format line".into()))?;
                return Ok((encoding, elements, pos));
            }
            _ => return Err(FormatError::Header(format!("unexpected PLY header line {:?}", line.chars().take(60).collect::<String>()))),
        }
    }
}

/// Writes a binary little-endian PLY of `count` vertices with `double x, y, z` (metres, full
/// precision at any coordinate this server accepts) and `float intensity`: the map file
/// `cmr-agent map build` produces, readable by this module, CloudCompare, Open3D and PDAL.
/// `points` must yield exactly `count` items.
pub fn write_ply_f64(out: &mut dyn std::io::Write, count: usize, points: impl Iterator<Item = ([f64; 3], f32)>) -> std::io::Result<()> {
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment written by cmr-agent\nelement vertex {count}\nproperty double x\nproperty double y\nproperty double z\nproperty float intensity\nend_header\n"
    )?;
    let mut written = 0usize;
    let mut record = [0u8; 28];
    for (p, intensity) in points {
        for (k, v) in p.iter().enumerate() {
            record[8 * k..8 * k + 8].copy_from_slice(&v.to_le_bytes());
        }
        record[24..28].copy_from_slice(&intensity.to_le_bytes());
        out.write_all(&record)?;
        written += 1;
    }
    if written != count {
        return Err(std::io::Error::other(format!("PLY header says {count} vertices, {written} were written")));
    }
    Ok(())
}
