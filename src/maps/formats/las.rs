//! ASPRS LAS 1.0–1.4 and LAZ (its compressed form, LASzip), read with the `las` crate (LAZ through
//! its `laz` feature): x, y, z (scale and offset applied, metres in the file's own coordinate
//! system) and intensity (the raw 16-bit value).
//!
//! The crate trusts the header it reads (it allocates the declared point data and extended VLRs),
//! so the raw header is checked against the bytes present first: the point count against
//! [`Limits`], and for LAS the point records and any EVLR against the file length. A LAZ file's
//! records are compressed, so its declared count (already within the limits) is what bounds the
//! decompressed cloud; a stream that ends early is a truncated file.

use std::io::Cursor;

use super::{check_count, CloudBuilder, FormatError, Limits, Parsed};

/// The LASzip layout of a LAS point data format byte (offset 104 of the header): LAZ writers set
/// bit 7 (and some bit 6); the point format is the low six bits.
pub(crate) struct PointFormatByte(pub u8);

impl PointFormatByte {
    pub(crate) fn compressed(&self) -> bool {
        self.0 & 0xc0 != 0
    }

    pub(crate) fn format(&self) -> u8 {
        self.0 & 0x3f
    }

    /// LAZ of formats 6-10, compressed in layers whose sizes the `laz` crate allocates as the
    /// stream declares them (up to 4 GB each, before reading a byte): not taken from uploads.
    pub(crate) fn layered_laz(&self) -> bool {
        self.compressed() && self.format() > 5
    }
}

/// Points read per batch, so the raw record buffer stays small beside the cloud.
const BATCH: usize = 1 << 16;

/// A LAZ batch's decompressed records at most (its records are not bounded by the file size).
const LAZ_BATCH_BYTES: usize = 4 << 20;

/// The longest LAZ point record taken: the largest standard format (10, 67 bytes) with ample
/// extra bytes. The decompressor sizes buffers by it before it reads a point.
const MAX_LAZ_RECORD: u16 = 1024;

pub(crate) fn parse(bytes: &[u8], limits: Limits) -> Result<Parsed, FormatError> {
    let header = check_header(bytes, limits)?;
    // The checks above bound every allocation; this only keeps a library bug from taking the
    // server down with it.
    std::panic::catch_unwind(|| match header.compressed {
        false => read_points(bytes, header.count, header.offset, limits),
        true => read_compressed(bytes, header.count, limits),
    })
    .unwrap_or_else(|_| Err(FormatError::Corrupt("the LAS reader failed on this file".into())))
}

/// Decompresses a LAZ file's points in batches of at most `LAZ_BATCH_BYTES` of records (the
/// reader needs an owned stream: one copy of the compressed bytes).
fn read_compressed(bytes: &[u8], count: usize, limits: Limits) -> Result<Parsed, FormatError> {
    let mut reader = las::Reader::new(Cursor::new(bytes.to_vec())).map_err(las_error)?;
    let mut data = las::PointDataBuilder::new().for_header(reader.header()).build();
    let batch = (LAZ_BATCH_BYTES / usize::from(reader.header().point_format().len()).max(1)).clamp(1, BATCH);
    let mut builder = CloudBuilder::new(count, true, limits);
    let mut read = 0;
    while read < count {
        let want = (count - read).min(batch) as u64;
        let got = reader.fill_points(want, &mut data).map_err(las_error)? as usize;
        if got == 0 {
            return Err(FormatError::Truncated(format!("LAZ declares {count} points, the compressed data holds {read}")));
        }
        push_batch(&data, &mut builder)?;
        read += got;
    }
    Ok(builder.finish())
}

/// Decodes the point records in batches straight from `bytes` (no copy of the whole file).
fn read_points(bytes: &[u8], count: usize, offset: usize, limits: Limits) -> Result<Parsed, FormatError> {
    let header = las::Header::new(Cursor::new(bytes)).map_err(las_error)?;
    let record = usize::from(header.point_format().len());
    let records = offset
        .checked_add(count.checked_mul(record).ok_or_else(|| FormatError::Header("point records overflow".into()))?)
        .and_then(|end| bytes.get(offset..end))
        .ok_or_else(|| FormatError::Truncated(format!("{count} LAS point records of {record} bytes do not fit in the file")))?;
    let mut builder = CloudBuilder::new(count, true, limits);
    for chunk in records.chunks(BATCH * record.max(1)) {
        let data = las::PointDataBuilder::new().for_header(&header).build_from_bytes(chunk.to_vec()).map_err(las_error)?;
        push_batch(&data, &mut builder)?;
    }
    Ok(builder.finish())
}

/// A batch's x, y, z (scale and offset applied) and raw intensity into the cloud.
fn push_batch(data: &las::PointData, builder: &mut CloudBuilder) -> Result<(), FormatError> {
    for (((x, y), z), i) in data.x().zip(data.y()).zip(data.z()).zip(data.intensity()) {
        builder.push(x, y, z, i as f64)?;
    }
    Ok(())
}

/// What `check_header` found: the point count, the offset of the first record, and whether the
/// records are LAZ-compressed.
struct CheckedHeader {
    count: usize,
    offset: usize,
    compressed: bool,
}

/// The header's point count within the limits and, for uncompressed records, its sizes known to
/// fit in `bytes`.
fn check_header(bytes: &[u8], limits: Limits) -> Result<CheckedHeader, FormatError> {
    let raw = las::raw::Header::read_from(Cursor::new(bytes)).map_err(|e| match e {
        las::Error::Io(_) => FormatError::Truncated(format!("the LAS header is cut short ({} bytes)", bytes.len())),
        other => FormatError::Header(format!("LAS: {other}")),
    })?;
    let format = PointFormatByte(raw.point_data_record_format);
    let compressed = format.compressed();
    let legacy = u64::from(raw.number_of_point_records);
    let declared = match raw.large_file {
        Some(large) if legacy == 0 => large.number_of_point_records,
        _ => legacy,
    };
    let count = check_count(declared, limits)?;
    let record = u64::from(raw.point_data_record_length);
    let end = (count as u64)
        .checked_mul(record)
        .and_then(|b| b.checked_add(u64::from(raw.offset_to_point_data)))
        .ok_or_else(|| FormatError::Header("point records overflow".into()))?;
    if end > bytes.len() as u64 && !compressed {
        return Err(FormatError::Truncated(format!(
            "LAS declares {count} points of {record} bytes from offset {}, the file has {} bytes",
            raw.offset_to_point_data,
            bytes.len()
        )));
    }
    if let Some(evlr) = raw.evlr {
        // An EVLR header is 60 bytes; its u64 data length sits at offset 20.
        let start = evlr.start_of_first_evlr;
        let length = start
            .checked_add(20)
            .and_then(|at| bytes.get(at as usize..at as usize + 8))
            .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")));
        let fits = length.and_then(|l| start.checked_add(60)?.checked_add(l)).is_some_and(|e| e <= bytes.len() as u64);
        if !fits {
            return Err(FormatError::Truncated(format!("LAS extended VLR at offset {start} does not fit in the {} bytes", bytes.len())));
        }
    }
    if compressed {
        if format.layered_laz() {
            return Err(FormatError::Unsupported(format!(
                "LAZ with point format {} (LAS 1.4 layered compression); upload LAZ with point formats 0-5 or the decompressed LAS",
                format.format()
            )));
        }
        if raw.point_data_record_length > MAX_LAZ_RECORD {
            return Err(FormatError::Header(format!(
                "LAZ point records of {} bytes (at most {MAX_LAZ_RECORD} are read)",
                raw.point_data_record_length
            )));
        }
        check_chunk_table(bytes, raw.offset_to_point_data as usize, count)?;
    }
    Ok(CheckedHeader { count, offset: raw.offset_to_point_data as usize, compressed })
}

/// LASzip's chunk table, as the `laz` crate will find it (an i64 offset at the start of the point
/// data, or in the file's last 8 bytes when the writer could not go back), must count no more
/// chunks than there are points (at least one each) and than there are bytes of chunk data
/// between the offset and the table: the crate allocates the declared number of entries before
/// it reads any, so a forged count would otherwise take the process down.
fn check_chunk_table(bytes: &[u8], data_start: usize, count: usize) -> Result<(), FormatError> {
    let read_i64 = |at: usize| bytes.get(at..at.checked_add(8)?).map(|b| i64::from_le_bytes(b.try_into().expect("8 bytes")));
    let truncated = || FormatError::Truncated(format!("LAZ point data from offset {data_start} does not fit in the {} bytes", bytes.len()));
    let mut table = read_i64(data_start).ok_or_else(truncated)?;
    if table <= data_start as i64 {
        table = read_i64(bytes.len().saturating_sub(8)).ok_or_else(truncated)?;
    }
    if table <= data_start as i64 {
        return Err(FormatError::Corrupt("LAZ without a chunk table offset".into()));
    }
    let table = table as u64;
    let chunks = table
        .checked_add(4)
        .and_then(|at| bytes.get(at as usize..at as usize + 4))
        .map(|b| u64::from(u32::from_le_bytes(b.try_into().expect("4 bytes"))))
        .ok_or_else(|| FormatError::Truncated(format!("the LAZ chunk table at offset {table} is past the end of the {} bytes", bytes.len())))?;
    let chunk_bytes = table - (data_start as u64 + 8).min(table);
    if chunks > (count as u64).max(1) || chunks > chunk_bytes.max(1) {
        return Err(FormatError::Corrupt(format!("the LAZ chunk table lists {chunks} chunks for {count} points in {chunk_bytes} bytes")));
    }
    Ok(())
}

fn las_error(e: las::Error) -> FormatError {
    match e {
        las::Error::Io(io) => FormatError::Truncated(format!("LAS: {io}")),
        other => FormatError::Header(format!("LAS: {other}")),
    }
}
