//! Turning a request's image into the image encoder's input tensor (the map's side is
//! `maps::prepared`).

use anyhow::{Result, bail};
use fast_image_resize::{FilterType, ResizeAlg, ResizeOptions, Resizer};
use image::RgbImage;

use crate::geometry::{CropAnchor, Intrinsics, PreprocessPlan, input_scale};
use crate::model::Manifest;

/// `image` resized to `width` x `height` with a bilinear (triangle) filter widened by the scale
/// when shrinking, the filter of training's `PIL.Image.resize(..., BILINEAR)`; `fast_image_resize`
/// computes it in fixed point with SIMD (a tenth of the CPU time of `image::imageops::resize`).
pub fn resize(image: &RgbImage, width: u32, height: u32) -> Result<RgbImage> {
    let mut out = RgbImage::new(width, height);
    let options = ResizeOptions::new().resize_alg(ResizeAlg::Convolution(FilterType::Bilinear));
    Resizer::new().resize(image, &mut out, &options)?;
    Ok(out)
}

/// Resizes (`ImageSpec::plan`: by the model's scale for the image's focal length) and
/// centre-crops an image to the model input and normalises it to the contract's [3, H, W] tensor;
/// returns the intrinsics of the crop.
pub fn prepare_image(image: &RgbImage, intrinsics: &Intrinsics, manifest: &Manifest) -> Result<(Vec<f32>, Intrinsics)> {
    let (w, h) = checked_size(image, intrinsics)?;
    let plan = manifest.image.plan(w, h, intrinsics.fx);
    let resized = resized_for(image, &plan)?;
    Ok((normalised_crop(&resized, &plan, manifest), plan.adjust(intrinsics, w, h)))
}

/// Crops of an image that the search's judge reads besides the served one, each with its crop's
/// intrinsics: the image resized `zoom` times more than [`prepare_image`] resizes it, cropped to
/// the model input at the left edge, the centre and the right edge (`PreprocessPlan::zoomed`;
/// one resize for the three). None when `zoom` is 0. Errors as [`prepare_image`]'s; `zoom` must
/// be 0 or in [`JUDGE_ZOOM_RANGE`].
pub fn prepare_views(image: &RgbImage, intrinsics: &Intrinsics, manifest: &Manifest, zoom: f64) -> Result<Vec<ViewInput>> {
    if zoom == 0.0 {
        return Ok(Vec::new());
    }
    if !JUDGE_ZOOM_RANGE.contains(&zoom) {
        bail!("a judge view's zoom must be 0 or within {JUDGE_ZOOM_RANGE:?}, got {zoom}");
    }
    let (w, h) = checked_size(image, intrinsics)?;
    let spec = &manifest.image;
    let scale = input_scale(spec.nominal_scale, spec.focal_range_px, intrinsics.fx);
    let plans = JUDGE_ANCHORS.map(|anchor| PreprocessPlan::zoomed(w, h, scale, spec.width, spec.height, zoom, anchor));
    let resized = resized_for(image, &plans[0])?;
    Ok(plans.iter().map(|plan| ViewInput { tensor: normalised_crop(&resized, plan, manifest), intrinsics: plan.adjust(intrinsics, w, h) }).collect())
}

/// One of the judge's views ([`prepare_views`]): the image encoder's [3, H, W] input and the
/// crop's intrinsics (pixels of that input).
#[derive(Debug, Clone)]
pub struct ViewInput {
    pub tensor: Vec<f32>,
    pub intrinsics: Intrinsics,
}

/// The zooms a judge view may have (`--judge-zoom`).
pub const JUDGE_ZOOM_RANGE: std::ops::RangeInclusive<f64> = 1.0..=3.0;

/// Where the judge's views are cropped, in the order [`prepare_views`] returns them.
pub const JUDGE_ANCHORS: [CropAnchor; 3] = [CropAnchor::Left, CropAnchor::Centre, CropAnchor::Right];

fn checked_size(image: &RgbImage, intrinsics: &Intrinsics) -> Result<(u32, u32)> {
    intrinsics.validate().map_err(anyhow::Error::msg)?;
    let (w, h) = image.dimensions();
    if w == 0 || h == 0 {
        bail!("image has zero width or height");
    }
    Ok((w, h))
}

/// `image` resized to `plan`'s resized size (itself when that is its size).
fn resized_for<'a>(image: &'a RgbImage, plan: &PreprocessPlan) -> Result<std::borrow::Cow<'a, RgbImage>> {
    if (plan.resized_width, plan.resized_height) == image.dimensions() {
        Ok(std::borrow::Cow::Borrowed(image))
    } else {
        Ok(std::borrow::Cow::Owned(resize(image, plan.resized_width, plan.resized_height)?))
    }
}

/// `plan`'s crop of the resized image, normalised by the manifest's mean and std, [3, H, W].
fn normalised_crop(resized: &RgbImage, plan: &PreprocessPlan, manifest: &Manifest) -> Vec<f32> {
    let spec = &manifest.image;
    let (ow, oh) = (spec.width as usize, spec.height as usize);
    let plane = ow * oh;
    let mut tensor = vec![0f32; 3 * plane];
    let scale: [f32; 3] = std::array::from_fn(|c| 1.0 / (255.0 * spec.std[c]));
    let offset: [f32; 3] = std::array::from_fn(|c| spec.mean[c] / spec.std[c]);
    for y in 0..oh {
        for x in 0..ow {
            let px = resized.get_pixel(plan.crop_x + x as u32, plan.crop_y + y as u32).0;
            for c in 0..3 {
                tensor[c * plane + y * ow + x] = px[c] as f32 * scale[c] - offset[c];
            }
        }
    }
    tensor
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};

    /// The bilinear filter, widened when shrinking (not e.g. the library's default Lanczos): on a
    /// noise image, within one grey level of the `image` crate's Triangle filter, which is within
    /// one level of training's PIL BILINEAR (`training/tests/test_data.py`).
    #[test]
    fn resize_is_the_triangle_filter_to_one_grey_level() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let noise = image::RgbImage::from_fn(310, 94, |_, _| image::Rgb([rng.random(), rng.random(), rng.random()]));
        for (w, h) in [(133, 40), (155, 47), (400, 120)] {
            let ours = super::resize(&noise, w, h).unwrap();
            let triangle = image::imageops::resize(&noise, w, h, image::imageops::FilterType::Triangle);
            let most = ours.as_raw().iter().zip(triangle.as_raw()).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
            assert!(most <= 1, "{w}x{h}: differs by {most} levels");
        }
    }
}
