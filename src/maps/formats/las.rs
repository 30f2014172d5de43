//! ASPRS LAS 1.0–1.4 (uncompressed), read with the `las` crate: x, y, z (scale and offset applied,
//! metres in the file's own coordinate system) and intensity (the raw 16-bit value).
//!
//! The crate trusts the header it reads (it allocates the declared point data and extended VLRs),
//! so the raw header is checked against the bytes present first: the point count against
//! [`Limits`], the point records and any EVLR against the file length. LAZ (compressed points) is
//! refused: decompress it (e.g. `laszip`, `pdal translate`) and upload the LAS.

use std::io::Cursor;

use super::{check_count, CloudBuilder, FormatError, Limits, Parsed};

/// Points read per batch, so the raw record buffer stays small beside the cloud.
const BATCH: usize = 1 << 16;

pub(crate) fn parse(bytes: &[u8], limits: Limits) -> Result<Parsed, FormatError> {
    let (count, offset) = check_header(bytes, limits)?;
    // The checks above bound every allocation; this only keeps a library bug from taking the
    // server down with it.
    std::panic::catch_unwind(|| read_points(bytes, count, offset, limits))
        .unwrap_or_else(|_| Err(FormatError::Corrupt("the LAS reader failed on this file".into())))
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
        for (((x, y), z), i) in data.x().zip(data.y()).zip(data.z()).zip(data.intensity()) {
            builder.push(x, y, z, i as f64)?;
        }
    }
    Ok(builder.finish())
}

/// The point count and the offset of the first record, once the header's sizes are known to fit
/// in `bytes`.
fn check_header(bytes: &[u8], limits: Limits) -> Result<(usize, usize), FormatError> {
    let raw = las::raw::Header::read_from(Cursor::new(bytes)).map_err(|e| match e {
        las::Error::Io(_) => FormatError::Truncated(format!("the LAS header is cut short ({} bytes)", bytes.len())),
        other => FormatError::Header(format!("LAS: {other}")),
    })?;
    if raw.point_data_record_format & 0xc0 != 0 {
        return Err(FormatError::Unsupported("LAZ (compressed LAS); decompress it to LAS first".into()));
    }
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
    if end > bytes.len() as u64 {
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
    Ok((count, raw.offset_to_point_data as usize))
}

fn las_error(e: las::Error) -> FormatError {
    match e {
        las::Error::Io(io) => FormatError::Truncated(format!("LAS: {io}")),
        las::Error::LaszipNotEnabled => FormatError::Unsupported("LAZ (compressed LAS); decompress it to LAS first".into()),
        other => FormatError::Header(format!("LAS: {other}")),
    }
}
