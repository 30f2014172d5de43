//! Pinhole intrinsics, projection, the frustum test and the image preprocessing rule
//! (resize, then crop to the model's input) that training and serving share.

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

/// Points closer than this to the camera plane count as outside the frustum.
pub const MIN_DEPTH_M: f64 = 0.1;

/// Pinhole intrinsics in pixels, pixel centres at integer coordinates (OpenCV convention).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// Checks the values a client may send: finite, positive focal lengths, finite centre.
    pub fn validate(&self) -> Result<(), String> {
        let all = [self.fx, self.fy, self.cx, self.cy];
        if all.iter().any(|v| !v.is_finite()) {
            return Err("intrinsics must be finite numbers".into());
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Err("focal lengths fx and fy must be positive".into());
        }
        Ok(())
    }

    /// Projects a camera-frame point to pixel coordinates; `None` when it is behind the camera.
    #[inline]
    pub fn project(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        if p.z < MIN_DEPTH_M {
            return None;
        }
        Some((self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }

    /// Back-projects pixel (u, v) at depth z to a camera-frame point (inverse of `project`).
    pub fn back_project(&self, u: f64, v: f64, z: f64) -> Point3<f64> {
        Point3::new((u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z)
    }

    /// The camera-frame direction through pixel (u, v), scaled so its z is 1: a point at
    /// parameter t along it has depth z = t (what the synthetic renderer casts).
    pub fn ray_direction(&self, u: f64, v: f64) -> nalgebra::Vector3<f64> {
        nalgebra::Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0)
    }

    /// Whether a camera-frame point lies in the frustum of a `width` × `height` image.
    #[inline]
    pub fn in_frustum(&self, p: &Point3<f64>, width: u32, height: u32) -> bool {
        match self.project(p) {
            Some((u, v)) => u >= -0.5 && v >= -0.5 && u < width as f64 - 0.5 && v < height as f64 - 0.5,
            None => false,
        }
    }

    /// KITTI's `P2` (3x4, row-major) for these intrinsics with a zero baseline term.
    pub fn to_projection_3x4(&self) -> [f64; 12] {
        [self.fx, 0.0, self.cx, 0.0, 0.0, self.fy, self.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    }
}

/// How an input image of any size becomes the model's `out_width` × `out_height` input:
/// resize by `scale` (never below the model's nominal scale, and at least enough to cover the
/// output), then crop the window at (`crop_x`, `crop_y`). The intrinsics follow the same steps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PreprocessPlan {
    pub resized_width: u32,
    pub resized_height: u32,
    pub crop_x: u32,
    pub crop_y: u32,
    pub out_width: u32,
    pub out_height: u32,
}

impl PreprocessPlan {
    /// The centre-crop plan used at test time and by the server.
    pub fn centered(in_width: u32, in_height: u32, nominal_scale: f64, out_width: u32, out_height: u32) -> Self {
        let (rw, rh) = Self::resized_size(in_width, in_height, nominal_scale, out_width, out_height);
        Self {
            resized_width: rw,
            resized_height: rh,
            crop_x: (rw - out_width) / 2,
            crop_y: (rh - out_height) / 2,
            out_width,
            out_height,
        }
    }

    /// The resized size: scale s = max(nominal, out_h / in_h, out_w / in_w), rounded to pixels.
    pub fn resized_size(in_width: u32, in_height: u32, nominal_scale: f64, out_width: u32, out_height: u32) -> (u32, u32) {
        let s = nominal_scale
            .max(out_height as f64 / in_height as f64)
            .max(out_width as f64 / in_width as f64);
        let rw = ((in_width as f64 * s).round() as u32).max(out_width);
        let rh = ((in_height as f64 * s).round() as u32).max(out_height);
        (rw, rh)
    }

    /// Intrinsics of the output crop, given the intrinsics of the input image.
    /// Pixel centres map as u' = (u + 0.5) · sx − 0.5 under resizing.
    pub fn adjust(&self, k: &Intrinsics, in_width: u32, in_height: u32) -> Intrinsics {
        let sx = self.resized_width as f64 / in_width as f64;
        let sy = self.resized_height as f64 / in_height as f64;
        Intrinsics {
            fx: k.fx * sx,
            fy: k.fy * sy,
            cx: (k.cx + 0.5) * sx - 0.5 - self.crop_x as f64,
            cy: (k.cy + 0.5) * sy - 0.5 - self.crop_y as f64,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn project_then_back_project() {
        let k = Intrinsics { fx: 359.0, fy: 359.0, cx: 256.0, cy: 80.0 };
        let p = Point3::new(1.5, -0.4, 12.0);
        let (u, v) = k.project(&p).unwrap();
        let q = k.back_project(u, v, p.z);
        assert!((p - q).norm() < 1e-12);
        assert!(k.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn ray_direction_reprojects_to_its_pixel() {
        let k = Intrinsics { fx: 718.856, fy: 718.856, cx: 607.1928, cy: 185.2157 };
        let d = k.ray_direction(100.0, 300.0);
        assert_eq!(d.z, 1.0);
        let (u, v) = k.project(&Point3::from(d * 17.5)).unwrap();
        assert!((u - 100.0).abs() < 1e-9 && (v - 300.0).abs() < 1e-9);
    }

    #[test]
    fn kitti_image_uses_the_nominal_half_scale() {
        let plan = PreprocessPlan::centered(1241, 376, 0.5, 512, 160);
        assert_eq!((plan.resized_width, plan.resized_height), (621, 188));
        assert_eq!((plan.crop_x, plan.crop_y), (54, 14));
    }

    #[test]
    fn small_images_are_upscaled_to_cover_the_input() {
        let plan = PreprocessPlan::centered(640, 160, 0.5, 512, 160);
        assert_eq!((plan.resized_width, plan.resized_height), (640, 160));
        let k = Intrinsics { fx: 500.0, fy: 500.0, cx: 319.5, cy: 79.5 };
        let adjusted = plan.adjust(&k, 640, 160);
        assert!((adjusted.cx - 255.5).abs() < 1e-12);
    }
}
