//! Request images: base64 → JPEG/PNG → RGB → the image encoder's tensor, with every size
//! checked BEFORE the memory is spent: the header's dimensions against the decode budget, the
//! preprocessing plan's resized size against the same budget, and the decoder's allocations
//! against a hard cap. Callers hold a decode permit (`admission`) while this runs.

use std::io::Cursor;

use base64::Engine;
use image::{ImageFormat, ImageReader, RgbImage};

use crate::agent::ViewInput;
use crate::geometry::{Intrinsics, PreprocessPlan, input_scale, max_input_scale};
use crate::model::Manifest;

use super::error::LocalizeError;

/// What one decode may cost.
#[derive(Debug, Clone, Copy)]
pub struct ImageLimits {
    /// Largest width or height, pixels.
    pub max_side: u32,
    /// Largest decoded image AND largest resized image (before the centre crop), pixels.
    pub max_pixels: u64,
}

/// The image as sent: base64 text from a JSON body, or raw bytes.
pub enum ImagePayload {
    Base64(String),
    Raw(bytes::Bytes),
}

/// One request image as the search reads it.
pub struct PreparedRequestImage {
    /// The image encoder's [3, H, W] input (`agent::prepare_image`).
    pub tensor: Vec<f32>,
    /// The crop's intrinsics.
    pub intrinsics: Intrinsics,
    /// The judge's views (`agent::prepare_views`; empty when the judge zoom is 0).
    pub views: Vec<ViewInput>,
    /// The decoded image (for pictures; callers that do not draw drop it).
    pub image: RgbImage,
}

/// Decodes, resizes and crops one request image to the manifest's input, with the judge's
/// views at `judge_zoom` (0: none). Errors: 400 `bad_request` (base64), 400 `corrupt_image` (cut
/// or broken bytes), 413 (over the budget), 415 (not JPEG/PNG), 422 (zero size, extreme aspect
/// ratio, bad intrinsics, a judge view's resize over the pixel budget).
pub fn prepare_request_image(
    payload: ImagePayload,
    intrinsics: &Intrinsics,
    manifest: &Manifest,
    limits: ImageLimits,
    judge_zoom: f64,
) -> Result<PreparedRequestImage, LocalizeError> {
    let image = decode_payload(payload, manifest, limits)?;
    let invalid = |e: anyhow::Error| LocalizeError::Invalid(format!("{e:#}"));
    let (tensor, crop_k) = crate::agent::prepare_image(&image, intrinsics, manifest).map_err(invalid)?;
    if judge_zoom > 0.0 {
        let (w, h) = image.dimensions();
        let spec = &manifest.image;
        let scale = input_scale(spec.nominal_scale, spec.focal_range_px, intrinsics.fx);
        let (rw, rh) = PreprocessPlan::resized_size_zoomed(w, h, scale, spec.width, spec.height, judge_zoom);
        if rw as u64 * rh as u64 > limits.max_pixels {
            return Err(LocalizeError::Invalid(format!(
                "image is {w}x{h}: the judge's views (zoom {judge_zoom}) would resize it to {rw}x{rh}, over the budget of {} pixels; \
                 send an image with an aspect ratio nearer {:.2}",
                limits.max_pixels,
                spec.width as f64 / spec.height as f64
            )));
        }
    }
    let views = crate::agent::prepare_views(&image, intrinsics, manifest, judge_zoom).map_err(invalid)?;
    Ok(PreparedRequestImage { tensor, intrinsics: crop_k, views, image })
}

/// Decodes one request image (base64 or raw bytes) within `limits`, without preparing it for the
/// model: the explicit-pose overlay's path, with the same checks and errors as localize's.
pub fn decode_payload(payload: ImagePayload, manifest: &Manifest, limits: ImageLimits) -> Result<RgbImage, LocalizeError> {
    let bytes = match payload {
        ImagePayload::Base64(text) => base64::engine::general_purpose::STANDARD
            .decode(text.trim().as_bytes())
            .map_err(|e| LocalizeError::BadRequest(format!("image is not valid base64: {e}")))?
            .into(),
        ImagePayload::Raw(bytes) => bytes,
    };
    decode_image(&bytes, manifest, limits)
}

/// Decodes JPEG or PNG bytes (the format is read from the bytes, not from any header) within
/// `limits`, after checking that the preprocessing plan's resize stays within them too.
pub fn decode_image(bytes: &[u8], manifest: &Manifest, limits: ImageLimits) -> Result<RgbImage, LocalizeError> {
    if bytes.is_empty() {
        return Err(LocalizeError::CorruptImage("image is empty".into()));
    }
    let format = image::guess_format(bytes).map_err(|_| LocalizeError::UnsupportedMediaType("image must be JPEG or PNG".into()))?;
    if !matches!(format, ImageFormat::Jpeg | ImageFormat::Png) {
        return Err(LocalizeError::UnsupportedMediaType(format!("image must be JPEG or PNG, got {format:?}")));
    }
    if format == ImageFormat::Jpeg && !ends_with_eoi(bytes) {
        // The JPEG decoder fills a cut-off scan with grey and reports success.
        return Err(LocalizeError::CorruptImage("the JPEG is truncated: no end-of-image marker".into()));
    }
    let mut decode_limits = image::Limits::default();
    decode_limits.max_image_width = Some(limits.max_side);
    decode_limits.max_image_height = Some(limits.max_side);
    // The decoded buffer (up to 16-bit RGBA) plus the decoder's own working memory.
    decode_limits.max_alloc = Some(limits.max_pixels.saturating_mul(8) + (64 << 20));
    let mut reader = ImageReader::with_format(Cursor::new(bytes), format);
    reader.limits(decode_limits.clone());
    let (w, h) = reader.into_dimensions().map_err(|e| classify(e, "cannot read the image header"))?;
    check_size(w, h, manifest, limits)?;
    let mut reader = ImageReader::with_format(Cursor::new(bytes), format);
    reader.limits(decode_limits);
    let decoded = reader.decode().map_err(|e| classify(e, "cannot decode the image"))?;
    Ok(decoded.into_rgb8())
}

/// The header's size against the side and pixel budgets, and the resize the preprocessing plan
/// would make (an extreme aspect ratio is scaled up enormously to cover the model input).
fn check_size(w: u32, h: u32, manifest: &Manifest, limits: ImageLimits) -> Result<(), LocalizeError> {
    if w == 0 || h == 0 {
        return Err(LocalizeError::Invalid(format!("image has zero size ({w}x{h})")));
    }
    if w > limits.max_side || h > limits.max_side {
        return Err(LocalizeError::PayloadTooLarge(format!("image is {w}x{h}; the limit is {} pixels per side", limits.max_side)));
    }
    let pixels = w as u64 * h as u64;
    if pixels > limits.max_pixels {
        return Err(LocalizeError::PayloadTooLarge(format!("image is {w}x{h} = {pixels} pixels; the limit is {}", limits.max_pixels)));
    }
    // The largest resize any intrinsics can ask for, so the check holds before they are read.
    let spec = &manifest.image;
    let scale = max_input_scale(spec.nominal_scale, spec.focal_range_px);
    let plan = PreprocessPlan::centered(w, h, scale, spec.width, spec.height);
    let resized = plan.resized_width as u64 * plan.resized_height as u64;
    if resized > limits.max_pixels {
        return Err(LocalizeError::Invalid(format!(
            "image is {w}x{h}: covering the model input {}x{} would resize it to {}x{}, over the budget of {} pixels; \
             send an image with an aspect ratio nearer {:.2}",
            spec.width,
            spec.height,
            plan.resized_width,
            plan.resized_height,
            limits.max_pixels,
            spec.width as f64 / spec.height as f64
        )));
    }
    Ok(())
}

/// A complete JPEG ends with the EOI marker (FF D9); trailing zero padding is tolerated.
fn ends_with_eoi(bytes: &[u8]) -> bool {
    let end = bytes.iter().rposition(|&b| b != 0).map_or(0, |i| i + 1);
    bytes[..end].ends_with(&[0xFF, 0xD9])
}

fn classify(e: image::ImageError, context: &str) -> LocalizeError {
    match e {
        image::ImageError::Limits(l) => LocalizeError::PayloadTooLarge(format!("{context}: image exceeds decode limits ({l})")),
        image::ImageError::Unsupported(u) => LocalizeError::UnsupportedMediaType(format!("{context}: {u}")),
        other => LocalizeError::CorruptImage(format!("{context}: {other}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manifest() -> Manifest {
        Manifest::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model")).unwrap()
    }

    fn png(w: u32, h: u32) -> Vec<u8> {
        let mut out = Vec::new();
        RgbImage::new(w, h).write_to(&mut Cursor::new(&mut out), ImageFormat::Png).unwrap();
        out
    }

    fn jpeg(w: u32, h: u32) -> Vec<u8> {
        let mut out = Vec::new();
        let img = RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 7) as u8, (y * 3) as u8, 90]));
        img.write_to(&mut Cursor::new(&mut out), ImageFormat::Jpeg).unwrap();
        out
    }

    const LIMITS: ImageLimits = ImageLimits { max_side: 8192, max_pixels: 16_000_000 };

    /// The judge's views resize the image 1.5 times more: a strip whose served resize fits the
    /// pixel budget but whose views would not is refused with 422; without views it prepares.
    #[test]
    fn the_judges_views_stay_within_the_pixel_budget() {
        let m = manifest();
        let limits = ImageLimits { max_side: 8192, max_pixels: 3_000_000 };
        let k = Intrinsics { fx: 300.0, fy: 300.0, cx: 2000.0, cy: 20.0 };
        let strip = || ImagePayload::Raw(png(4000, 40).into());
        // Covering 512 x 160: x4, 16,000 x 160 = 2.56 MP; the views: 24,000 x 240 = 5.76 MP.
        let e = prepare_request_image(strip(), &k, &m, limits, 1.5).err().expect("over the budget");
        assert!(matches!(&e, LocalizeError::Invalid(msg) if msg.contains("judge's views")), "{e:?}");
        let served = prepare_request_image(strip(), &k, &m, limits, 0.0).unwrap();
        assert!(served.views.is_empty());
        let viewed = prepare_request_image(ImagePayload::Raw(png(1241, 376).into()), &k, &m, LIMITS, 1.5).unwrap();
        assert_eq!(viewed.views.len(), 3);
    }

    #[test]
    fn budgets_refuse_from_the_header() {
        let m = manifest();
        assert!(decode_image(&png(1241, 376), &m, LIMITS).is_ok());
        let big = decode_image(&png(5000, 4000), &m, LIMITS).unwrap_err();
        assert!(matches!(big, LocalizeError::PayloadTooLarge(_)), "{big}");
        // A thin strip would be resized to 512 x 4 million pixels to cover the model input.
        let strip = decode_image(&png(1, 8192), &m, LIMITS).unwrap_err();
        assert!(matches!(strip, LocalizeError::Invalid(ref s) if s.contains("aspect ratio")), "{strip}");
    }

    /// With a focal range the header check bounds the resize any intrinsics can ask for: an image
    /// at the pixel budget passes and then prepares within it for a lens of any focal length (a
    /// tiny `fx` asks to enlarge it many times: capped at its own resolution); a thin strip is
    /// still refused before decoding.
    #[test]
    fn with_a_focal_range_the_budget_holds_for_any_intrinsics() {
        let mut m = manifest();
        m.image.focal_range_px = Some([353.5456, 360.76885]);
        let limits = ImageLimits { max_side: 8192, max_pixels: 2000 * 600 };
        let bytes = png(2000, 600);
        assert!(decode_image(&bytes, &m, limits).is_ok());
        for fx in [1e-3, 10.0, 400.0, 2000.0, 1e7] {
            let k = Intrinsics { fx, fy: fx, cx: 1000.0, cy: 300.0 };
            let plan = m.image.plan(2000, 600, fx);
            assert!(plan.resized_width as u64 * plan.resized_height as u64 <= limits.max_pixels, "fx {fx}: {plan:?}");
            let PreparedRequestImage { tensor, intrinsics: crop_k, .. } = prepare_request_image(ImagePayload::Raw(bytes.clone().into()), &k, &m, limits, 0.0).unwrap();
            assert_eq!(tensor.len(), 3 * (m.image.width * m.image.height) as usize);
            assert!(crop_k.fx > 0.0 && crop_k.fx <= fx.max(m.image.width as f64), "fx {fx}: {crop_k:?}");
        }
        let strip = decode_image(&png(1, 8192), &m, LIMITS).unwrap_err();
        assert!(matches!(strip, LocalizeError::Invalid(ref s) if s.contains("aspect ratio")), "{strip}");
    }

    #[test]
    fn a_cut_jpeg_is_corrupt_and_a_whole_one_decodes() {
        let m = manifest();
        let whole = jpeg(640, 200);
        assert!(decode_image(&whole, &m, LIMITS).is_ok());
        let mut padded = whole.clone();
        padded.extend([0, 0, 0]);
        assert!(decode_image(&padded, &m, LIMITS).is_ok());
        let cut = decode_image(&whole[..whole.len() * 2 / 3], &m, LIMITS).unwrap_err();
        assert!(matches!(cut, LocalizeError::CorruptImage(_)), "{cut}");
        let gif = decode_image(b"GIF89a\x01\x00\x01\x00", &m, LIMITS).unwrap_err();
        assert!(matches!(gif, LocalizeError::UnsupportedMediaType(_)), "{gif}");
    }
}
