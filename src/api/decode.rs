//! Request image decoding with limits: base64 → JPEG/PNG → RGB, refusing what would be too
//! large to decode before decoding it.

use std::io::Cursor;

use base64::Engine;
use image::{ImageFormat, ImageReader, Limits, RgbImage};

use super::error::ApiError;

pub fn decode_base64_image(base64_text: &str, max_side: u32) -> Result<RgbImage, ApiError> {
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(base64_text.trim().as_bytes())
        .map_err(|e| ApiError::BadRequest(format!("image is not valid base64: {e}")))?;
    decode_image(&bytes, max_side)
}

/// Decodes JPEG or PNG bytes (the format is taken from the bytes, not from any header).
pub fn decode_image(bytes: &[u8], max_side: u32) -> Result<RgbImage, ApiError> {
    if bytes.is_empty() {
        return Err(ApiError::CorruptImage("image is empty".into()));
    }
    let format = image::guess_format(bytes)
        .map_err(|_| ApiError::UnsupportedMediaType("image must be JPEG or PNG".into()))?;
    if !matches!(format, ImageFormat::Jpeg | ImageFormat::Png) {
        return Err(ApiError::UnsupportedMediaType(format!("image must be JPEG or PNG, got {format:?}")));
    }
    let mut reader = ImageReader::with_format(Cursor::new(bytes), format);
    let mut limits = Limits::default();
    limits.max_image_width = Some(max_side);
    limits.max_image_height = Some(max_side);
    limits.max_alloc = Some(512 * 1024 * 1024);
    reader.limits(limits.clone());
    let (w, h) = reader
        .into_dimensions()
        .map_err(|e| classify(e, "cannot read the image header"))?;
    if w == 0 || h == 0 {
        return Err(ApiError::Invalid(format!("image has zero size ({w}x{h})")));
    }
    if w > max_side || h > max_side {
        return Err(ApiError::PayloadTooLarge(format!("image is {w}x{h}; the limit is {max_side} pixels per side")));
    }
    let mut reader = ImageReader::with_format(Cursor::new(bytes), format);
    reader.limits(limits);
    let decoded = reader.decode().map_err(|e| classify(e, "cannot decode the image"))?;
    Ok(decoded.to_rgb8())
}

fn classify(e: image::ImageError, context: &str) -> ApiError {
    match e {
        image::ImageError::Limits(l) => ApiError::PayloadTooLarge(format!("{context}: image exceeds decode limits ({l})")),
        image::ImageError::Unsupported(u) => ApiError::UnsupportedMediaType(format!("{context}: {u}")),
        other => ApiError::CorruptImage(format!("{context}: {other}")),
    }
}

#[cfg(test)]
mod timing {
    /// Manual timing: `cargo test --release --lib decode_timing -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn decode_timing() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/localize-demo.json");
        let v: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
        let text = v["image"].as_str().unwrap();
        let manifest = crate::model::Manifest::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models")).unwrap();
        let k = crate::geometry::Intrinsics { fx: 700.0, fy: 700.0, cx: 620.0, cy: 188.0 };
        let reps = 20;
        let t = std::time::Instant::now();
        for _ in 0..reps {
            super::decode_base64_image(text, 8192).unwrap();
        }
        let decode = t.elapsed().as_secs_f64() * 1000.0 / reps as f64;
        let image = super::decode_base64_image(text, 8192).unwrap();
        let t = std::time::Instant::now();
        for _ in 0..reps {
            crate::agent::prepare_image(&image, &k, &manifest).unwrap();
        }
        let prep = t.elapsed().as_secs_f64() * 1000.0 / reps as f64;
        println!("base64 + JPEG decode {decode:.2} ms, resize + crop + normalise {prep:.2} ms ({:?})", image.dimensions());
    }
}
