//! The pinhole camera: ray-cast shading (Lambert sun + sky ambient, hard shadows, a sky
//! gradient with a sun glow), exposure, sRGB, sensor noise. Keeps the depth buffer so tests can
//! check that the two sensors see the same geometry.

use image::RgbImage;
use rayon::prelude::*;

use super::camera_fx::{develop, FrameFx};
use super::noise::{gaussian, hash};
use super::scene::Scene;
use super::shapes::V3;
use super::style::Style;
use crate::geometry::{Intrinsics, Pose};

/// Lighting derived from a style.
#[derive(Debug, Clone, Copy)]
pub struct Lighting {
    /// Unit vector towards the sun (scene frame).
    pub sun_dir: V3,
    pub sun: [f32; 3],
    pub sky_ambient: [f32; 3],
    pub zenith: [f32; 3],
    pub horizon: [f32; 3],
    pub exposure: f32,
    pub noise_sigma: f32,
    pub shadows: bool,
}

impl Lighting {
    pub fn from_style(style: &Style) -> Self {
        let elevation = style.sun_elevation_deg().to_radians();
        let azimuth = style.sun_azimuth_deg.to_radians();
        let sun_dir = V3::new(elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin());
        // Low sun: warmer, weaker; more of the light comes from the sky.
        let low = 1.0 - (elevation / 62f32.to_radians()).clamp(0.0, 1.0);
        let sun_strength = 2.6 * (0.45 + 0.55 * (1.0 - low));
        let sun = [sun_strength, sun_strength * (0.93 - 0.18 * low), sun_strength * (0.85 - 0.35 * low)];
        Lighting {
            sun_dir,
            sun,
            sky_ambient: [0.42 - 0.05 * low, 0.48 - 0.08 * low, 0.60 - 0.12 * low],
            zenith: [0.16, 0.32 - 0.06 * low, 0.70 - 0.15 * low],
            horizon: [0.72 + 0.2 * low, 0.78 - 0.05 * low, 0.85 - 0.25 * low],
            exposure: style.exposure,
            noise_sigma: style.noise_sigma,
            shadows: style.shadows,
        }
    }

    fn sky(&self, dir: &V3) -> [f32; 3] {
        let d = dir.normalize();
        let up = d.z.clamp(0.0, 1.0).powf(0.6);
        let glow = d.dot(&self.sun_dir).max(0.0).powi(64) * 1.5;
        std::array::from_fn(|c| (self.horizon[c] * (1.0 - up) + self.zenith[c] * up) * 1.25 + glow * self.sun[c] * 0.4)
    }
}

/// A camera looking into the scene.
#[derive(Debug, Clone, Copy)]
pub struct CameraView {
    pub intrinsics: Intrinsics,
    pub width: u32,
    pub height: u32,
    /// The camera's pose in the scene frame.
    pub world_from_camera: Pose,
}

pub struct Rendered {
    pub image: RgbImage,
    /// Camera-frame z of the surface seen at each pixel (row-major), +∞ for sky.
    pub depth: Vec<f32>,
}

impl Rendered {
    pub fn depth_at(&self, u: u32, v: u32) -> f32 {
        self.depth[(v * self.image.width() + u) as usize]
    }
}

/// Renders one image with today's camera (exposure, tone map, sRGB, Gaussian noise). Rows run
/// in parallel; noise is hashed from (seed, pixel), so the result does not depend on scheduling.
pub fn render(scene: &Scene, lighting: &Lighting, view: &CameraView, seed: u64) -> Rendered {
    let (w, h) = (view.width as usize, view.height as usize);
    let (radiance, depth) = trace(scene, lighting, view);
    let mut pixels = vec![0u8; w * h * 3];
    pixels.par_chunks_mut(w * 3).zip(radiance.par_chunks(w)).enumerate().for_each(|(row, (rgb, light))| {
        for col in 0..w {
            let radiance = light[col];
            let pixel = (row * w + col) as u64;
            for c in 0..3 {
                let exposed = radiance[c] * lighting.exposure;
                let mapped = exposed / (1.0 + 0.15 * exposed);
                let srgb = linear_to_srgb(mapped.clamp(0.0, 1.0)) * 255.0;
                let noisy = srgb + lighting.noise_sigma * gaussian(hash(&[seed, pixel, c as u64]));
                rgb[col * 3 + c] = noisy.round().clamp(0.0, 255.0) as u8;
            }
        }
    });
    Rendered { image: RgbImage::from_raw(view.width, view.height, pixels).expect("buffer size"), depth }
}

/// Renders one image through a camera with this frame's effects (`camera_fx`).
pub fn render_with_effects(scene: &Scene, lighting: &Lighting, view: &CameraView, seed: u64, fx: &FrameFx) -> anyhow::Result<Rendered> {
    let (radiance, depth) = trace(scene, lighting, view);
    let image = develop(radiance, view.width as usize, view.height as usize, lighting.exposure, fx, seed)?;
    Ok(Rendered { image, depth })
}

/// Linear radiance and camera-frame depth of every pixel (row-major).
pub fn trace(scene: &Scene, lighting: &Lighting, view: &CameraView) -> (Vec<[f32; 3]>, Vec<f32>) {
    let (w, h) = (view.width as usize, view.height as usize);
    let r = view.world_from_camera.rotation().cast::<f32>();
    let origin: V3 = view.world_from_camera.translation().cast::<f32>();
    let mut radiance = vec![[0f32; 3]; w * h];
    let mut depth = vec![f32::INFINITY; w * h];
    radiance.par_chunks_mut(w).zip(depth.par_chunks_mut(w)).enumerate().for_each(|(row, (light, depth_row))| {
        for col in 0..w {
            // z = 1 in the camera frame, so the hit parameter is the depth.
            let d_cam = view.intrinsics.ray_direction(col as f64, row as f64).cast::<f32>();
            let dir = r * d_cam;
            light[col] = match scene.intersect(&origin, &dir, 1.0e4) {
                Some(hit) => {
                    depth_row[col] = hit.t;
                    let p = origin + dir * hit.t;
                    shade(scene, lighting, &hit, &p, &dir)
                }
                None => lighting.sky(&dir),
            };
        }
    });
    (radiance, depth)
}

fn shade(scene: &Scene, lighting: &Lighting, hit: &super::scene::Hit, p: &V3, dir: &V3) -> [f32; 3] {
    let surface = scene.surface(hit, p);
    // Shapes are solid, but flip the normal if we see a face from behind (caps, thin plates).
    let n = if hit.normal.dot(dir) > 0.0 { -hit.normal } else { hit.normal };
    let lambert = n.dot(&lighting.sun_dir).max(0.0);
    let lit = if lambert > 0.0 && lighting.shadows {
        let start = p + n * 0.01;
        // The ground plane casts no shadows; only shapes can block the sun.
        if scene.occluded(&start, &lighting.sun_dir, 500.0) { 0.0 } else { lambert }
    } else {
        lambert
    };
    // Sky light: full from above, less on vertical faces, some bounce from the ground.
    let sky = 0.55 + 0.45 * n.z;
    std::array::from_fn(|c| surface.albedo[c] * (lighting.sun[c] * lit + lighting.sky_ambient[c] * sky + 0.04))
}

fn linear_to_srgb(x: f32) -> f32 {
    if x <= 0.003_130_8 { 12.92 * x } else { 1.055 * x.powf(1.0 / 2.4) - 0.055 }
}
