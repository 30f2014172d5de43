//! What a real camera does to the light before the image is written, drawn per frame for
//! `--look random`: exposure errors (over and under), white-balance errors, vignetting, defocus
//! and motion blur, tone curve, sensor noise (Gaussian read noise, signal-dependent shot noise,
//! row banding, hot and dead pixels) and JPEG compression artefacts.

use image::RgbImage;
use rayon::prelude::*;
use serde::Serialize;

use super::noise::{gaussian, hash, unit};

/// One frame's camera effects; pixel lengths at the rendered size.
#[derive(Debug, Clone, Serialize)]
pub struct FrameFx {
    /// Exposure error in stops (negative = darker).
    pub exposure_ev: f32,
    pub white_balance: [f32; 3],
    /// Brightness lost at the corners (0..0.6).
    pub vignetting: f32,
    /// Defocus blur radius, pixels.
    pub defocus_px: u32,
    /// Motion blur length along x and along y, pixels.
    pub motion_px: [u32; 2],
    /// Tone-curve exponent applied after sRGB (1 = none).
    pub contrast: f32,
    /// Read noise σ (8-bit levels), shot noise factor, row banding σ, hot/dead pixel share.
    pub read_noise: f32,
    pub shot_noise: f32,
    pub row_noise: f32,
    pub bad_pixels: f32,
    /// JPEG quality of a compress-decompress round trip (None: not compressed).
    pub jpeg_quality: Option<u8>,
}

impl FrameFx {
    /// Draws a frame's effects from `seed`; `scale` = image width / 1241 (blur lengths follow).
    pub fn draw(seed: u64, scale: f32) -> FrameFx {
        let u = |k: u64| unit(hash(&[seed, k]));
        let g = |k: u64| gaussian(hash(&[seed, k]));
        let px = |v: f32| (v * scale).round() as u32;
        let motion = if u(1) < 0.3 { u(2) * 7.0 } else { 0.0 };
        let angle = (u(3) - 0.5) * 0.8;
        FrameFx {
            exposure_ev: (0.55 * g(4)).clamp(-1.6, 1.6),
            white_balance: [(0.09 * g(5)).exp(), 1.0, (0.12 * g(6)).exp()],
            vignetting: if u(7) < 0.6 { u(8) * 0.6 } else { 0.0 },
            defocus_px: if u(9) < 0.25 { px(0.5 + u(10) * 2.0) } else { 0 },
            motion_px: [px(motion * angle.cos().abs()), px(motion * angle.sin().abs())],
            contrast: (0.15 * g(11)).exp(),
            read_noise: 0.5 + u(12) * 5.0,
            shot_noise: if u(13) < 0.6 { u(14) * 0.6 } else { 0.0 },
            row_noise: if u(15) < 0.2 { u(16) * 2.5 } else { 0.0 },
            bad_pixels: if u(17) < 0.2 { u(18) * 5e-4 } else { 0.0 },
            jpeg_quality: (u(19) < 0.5).then(|| 35 + (u(20) * 60.0) as u8),
        }
    }
}

/// Box blur of radius `r` along rows (`horizontal`) or columns, in place.
fn box_blur(buf: &mut [[f32; 3]], w: usize, h: usize, r: usize, horizontal: bool) {
    if r == 0 {
        return;
    }
    let (n, lines) = if horizontal { (w, h) } else { (h, w) };
    let mut line = vec![[0f32; 3]; n];
    for l in 0..lines {
        let idx = |i: usize| if horizontal { l * w + i } else { i * w + l };
        for i in 0..n {
            line[i] = buf[idx(i)];
        }
        let mut sum = [0f32; 3];
        // Running sum over [i - r, i + r], clamped at the edges.
        for k in 0..=r.min(n - 1) {
            for c in 0..3 {
                sum[c] += line[k][c];
            }
        }
        for i in 0..n {
            let lo = i.saturating_sub(r);
            let hi = (i + r).min(n - 1);
            let count = (hi - lo + 1) as f32;
            buf[idx(i)] = sum.map(|s| s / count);
            if i + r + 1 < n {
                for c in 0..3 {
                    sum[c] += line[i + r + 1][c];
                }
            }
            if i >= r {
                for c in 0..3 {
                    sum[c] -= line[i - r][c];
                }
            }
        }
    }
}

fn linear_to_srgb(x: f32) -> f32 {
    if x <= 0.003_130_8 { 12.92 * x } else { 1.055 * x.powf(1.0 / 2.4) - 0.055 }
}

/// Turns linear radiance into an 8-bit image through the frame's camera.
pub fn develop(mut radiance: Vec<[f32; 3]>, w: usize, h: usize, exposure: f32, fx: &FrameFx, seed: u64) -> anyhow::Result<RgbImage> {
    let gain = exposure * 2f32.powf(fx.exposure_ev);
    let (cx, cy) = (w as f32 * 0.5, h as f32 * 0.5);
    let norm = 1.0 / (cx * cx + cy * cy);
    radiance.par_chunks_mut(w).enumerate().for_each(|(row, line)| {
        let y = row as f32 - cy;
        for (col, p) in line.iter_mut().enumerate() {
            let x = col as f32 - cx;
            let v = 1.0 - fx.vignetting * (x * x + y * y) * norm;
            for c in 0..3 {
                p[c] *= gain * fx.white_balance[c] * v;
            }
        }
    });
    let d = fx.defocus_px as usize;
    for _ in 0..2 {
        box_blur(&mut radiance, w, h, d, true);
        box_blur(&mut radiance, w, h, d, false);
    }
    box_blur(&mut radiance, w, h, fx.motion_px[0] as usize / 2, true);
    box_blur(&mut radiance, w, h, fx.motion_px[1] as usize / 2, false);
    let mut pixels = vec![0u8; w * h * 3];
    pixels.par_chunks_mut(w * 3).zip(radiance.par_chunks(w)).enumerate().for_each(|(row, (rgb, line))| {
        let row_offset = fx.row_noise * gaussian(hash(&[seed, 0xB0, row as u64]));
        for (col, p) in line.iter().enumerate() {
            let i = (row * w + col) as u64;
            let bad = unit(hash(&[seed, 0xBAD, i]));
            for c in 0..3 {
                let mapped = p[c] / (1.0 + 0.15 * p[c]);
                let srgb = linear_to_srgb(mapped.clamp(0.0, 1.0)).powf(fx.contrast) * 255.0;
                let sigma = (fx.read_noise * fx.read_noise + fx.shot_noise * fx.shot_noise * srgb).sqrt();
                let mut value = srgb + sigma * gaussian(hash(&[seed, i, c as u64])) + row_offset;
                if bad < fx.bad_pixels {
                    value = if bad < fx.bad_pixels * 0.5 { 255.0 } else { 0.0 };
                }
                rgb[col * 3 + c] = value.round().clamp(0.0, 255.0) as u8;
            }
        }
    });
    let image = RgbImage::from_raw(w as u32, h as u32, pixels).expect("buffer size");
    let Some(quality) = fx.jpeg_quality else { return Ok(image) };
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, quality).encode_image(&image)?;
    Ok(image::load_from_memory_with_format(&jpeg, image::ImageFormat::Jpeg)?.to_rgb8())
}
