//! Turning user inputs into model inputs: the N-point sample of a map and the image tensor.

use anyhow::{Result, bail};
use image::RgbImage;
use image::imageops::{self, FilterType};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use crate::geometry::{Intrinsics, PreprocessPlan};
use crate::model::Manifest;

/// The contract's sampling: a ChaCha8(seed 0) permutation of the finite points, first `n` of it;
/// a cloud smaller than `n` is filled by drawing with replacement from the same stream.
pub fn sample_points(cloud: &[[f32; 3]], n: usize) -> Result<Vec<[f32; 3]>> {
    let finite: Vec<[f32; 3]> = cloud.iter().copied().filter(|p| p.iter().all(|v| v.is_finite())).collect();
    if finite.is_empty() {
        bail!("the point cloud has no finite points");
    }
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut order: Vec<usize> = (0..finite.len()).collect();
    order.shuffle(&mut rng);
    let mut out: Vec<[f32; 3]> = order.iter().take(n).map(|&i| finite[i]).collect();
    while out.len() < n {
        out.push(finite[rng.random_range(0..finite.len())]);
    }
    Ok(out)
}

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampling_is_deterministic_and_fills_small_clouds() {
        let cloud: Vec<[f32; 3]> = (0..10).map(|i| [i as f32, 0.0, 0.0]).collect();
        let a = sample_points(&cloud, 25).unwrap();
        assert_eq!(a, sample_points(&cloud, 25).unwrap());
        assert_eq!(a.len(), 25);
        let mut first: Vec<f32> = a[..10].iter().map(|p| p[0]).collect();
        first.sort_by(f32::total_cmp);
        assert_eq!(first, (0..10).map(|i| i as f32).collect::<Vec<_>>(), "every point once before refilling");
        assert!(sample_points(&[[f32::NAN, 0.0, 0.0]], 4).is_err());
    }
}
