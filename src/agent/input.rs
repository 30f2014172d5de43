//! Turning a request's image into the image encoder's input tensor (the map's side is
//! `maps::prepared`).

use anyhow::{Result, bail};
use image::RgbImage;
use image::imageops::{self, FilterType};

use crate::geometry::{Intrinsics, PreprocessPlan};
use crate::model::Manifest;

/// Resizes and centre-crops an image to the model input and normalises it to the contract's
/// [3, H, W] tensor; returns the intrinsics of the crop.
pub fn prepare_image(image: &RgbImage, intrinsics: &Intrinsics, manifest: &Manifest) -> Result<(Vec<f32>, Intrinsics)> {
    intrinsics.validate().map_err(anyhow::Error::msg)?;
    let (w, h) = image.dimensions();
    if w == 0 || h == 0 {
        bail!("image has zero width or height");
    }
    let spec = &manifest.image;
    let plan = PreprocessPlan::centered(w, h, spec.nominal_scale, spec.width, spec.height);
    let resized = if (plan.resized_width, plan.resized_height) == (w, h) {
        image.clone()
    } else {
        imageops::resize(image, plan.resized_width, plan.resized_height, FilterType::Triangle)
    };
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
    Ok((tensor, plan.adjust(intrinsics, w, h)))
}
