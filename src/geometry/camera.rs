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

/// Most a model's focal range may enlarge an image beyond its nominal scale: to the image's own
/// resolution (covering the input still may enlarge it further).
pub const MAX_FOCAL_SCALE: f64 = 1.0;

/// The factor an image whose focal length is `fx` (pixels, > 0) is resized by before the centre
/// crop. A model set resizes every image by `nominal_scale`, or, when its manifest names the
/// focal lengths it was trained at, `focal_range_px` = [lo, hi] (model-input pixels, lo <= hi),
/// by the factor nearest `nominal_scale` that brings `fx` into that range: a camera already in it
/// keeps the nominal scale, a longer lens is shrunk to `hi`, a wider one enlarged to `lo` (at
/// most to its own resolution, [`MAX_FOCAL_SCALE`]). So a camera's pixels reach the model at
/// about the angular size it learnt, whatever the lens and whatever resolution the image is sent
/// at. `PreprocessPlan::centered` then raises the factor where the image would not cover the
/// model input. Twin: `training/cmr/geometry.py::input_scale` (fixtures/conventions.json).
pub fn input_scale(nominal_scale: f64, focal_range_px: Option<[f64; 2]>, fx: f64) -> f64 {
    match focal_range_px {
        None => nominal_scale,
        Some([lo, hi]) => nominal_scale.clamp(lo / fx, hi / fx).min(max_input_scale(nominal_scale, focal_range_px)),
    }
}

/// The largest factor [`input_scale`] gives for any focal length: what a size budget checked
/// before the intrinsics are read must allow.
pub fn max_input_scale(nominal_scale: f64, focal_range_px: Option<[f64; 2]>) -> f64 {
    if focal_range_px.is_some() { MAX_FOCAL_SCALE.max(nominal_scale) } else { nominal_scale }
}

/// Where a zoomed view's crop lies across its resized image ([`PreprocessPlan::zoomed`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CropAnchor {
    Left,
    Centre,
    Right,
}

/// How an input image of any size becomes the model's `out_width` × `out_height` input:
/// resize by the model's scale for it ([`input_scale`], raised to at least enough to cover the
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
    /// The centre-crop plan used at test time and by the server, for an image resized by `scale`
    /// ([`input_scale`]) or more where that does not cover the output.
    pub fn centered(in_width: u32, in_height: u32, scale: f64, out_width: u32, out_height: u32) -> Self {
        let (rw, rh) = Self::resized_size(in_width, in_height, scale, out_width, out_height);
        Self {
            resized_width: rw,
            resized_height: rh,
            crop_x: (rw - out_width) / 2,
            crop_y: (rh - out_height) / 2,
            out_width,
            out_height,
        }
    }

    /// A zoomed view of the same image: resized `zoom` (≥ 1) times more than
    /// [`PreprocessPlan::centered`] would, then cropped at `anchor` across the width and centred
    /// down the height. The search's judge reads these views besides the served one
    /// (`agent::input::prepare_views`). Twin: `training/cmr/geometry.py::preprocess_plan` with
    /// `zoom` and the crop's corner (fixtures/conventions.json).
    pub fn zoomed(in_width: u32, in_height: u32, scale: f64, out_width: u32, out_height: u32, zoom: f64, anchor: CropAnchor) -> Self {
        let (rw, rh) = Self::resized_size_zoomed(in_width, in_height, scale, out_width, out_height, zoom);
        let crop_x = match anchor {
            CropAnchor::Left => 0,
            CropAnchor::Centre => (rw - out_width) / 2,
            CropAnchor::Right => rw - out_width,
        };
        Self { resized_width: rw, resized_height: rh, crop_x, crop_y: (rh - out_height) / 2, out_width, out_height }
    }

    /// The resized size: s = max(scale, out_h / in_h, out_w / in_w), rounded to pixels.
    pub fn resized_size(in_width: u32, in_height: u32, scale: f64, out_width: u32, out_height: u32) -> (u32, u32) {
        Self::resized_size_zoomed(in_width, in_height, scale, out_width, out_height, 1.0)
    }

    /// [`PreprocessPlan::resized_size`] with s multiplied by `zoom` (1: the same size).
    pub fn resized_size_zoomed(in_width: u32, in_height: u32, scale: f64, out_width: u32, out_height: u32, zoom: f64) -> (u32, u32) {
        let mut s = scale
            .max(out_height as f64 / in_height as f64)
            .max(out_width as f64 / in_width as f64);
        if zoom != 1.0 {
            s *= zoom;
        }
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

    /// The shipped model set's range (the KITTI rigs' focal lengths at the nominal scale).
    const RANGE: Option<[f64; 2]> = Some([353.5456, 360.76885]);

    /// The focal length a camera reaches the model input with.
    fn input_fx(w: u32, h: u32, fx: f64, range: Option<[f64; 2]>) -> f64 {
        let plan = PreprocessPlan::centered(w, h, input_scale(0.5, range, fx), 512, 160);
        plan.adjust(&Intrinsics { fx, fy: fx, cx: w as f64 / 2.0, cy: h as f64 / 2.0 }, w, h).fx
    }

    #[test]
    fn a_focal_range_keeps_the_cameras_inside_it_and_brings_the_others_in() {
        // KITTI's colour camera and the synthetic rig are inside: the scale stays 0.5 exactly.
        assert_eq!(input_scale(0.5, RANGE, 721.5377), 0.5);
        assert_eq!(input_scale(0.5, RANGE, 718.856), 0.5);
        assert_eq!(input_scale(0.5, None, 2152.8), 0.5);
        // A longer lens is shrunk to the upper end, a wider one enlarged to the lower end...
        assert!((input_fx(1920, 1200, 1000.0, None) - 500.0).abs() < 0.5);
        assert!((input_fx(1920, 1200, 1000.0, RANGE) - 360.8).abs() < 0.5);
        assert!((input_fx(1600, 900, 500.0, RANGE) - 353.5).abs() < 0.5);
        // ... but never beyond the image's own resolution, and never below covering the input:
        // a 1920-pixel-wide image with a 2152.8 px lens keeps its whole width (574 px).
        assert_eq!(input_scale(0.5, RANGE, 100.0), MAX_FOCAL_SCALE);
        assert!((input_fx(1920, 1200, 2152.8, RANGE) - 574.1).abs() < 0.5);
    }

    #[test]
    fn with_a_focal_range_the_model_input_does_not_depend_on_the_resolution_sent() {
        // One camera sent at 1920x1200, halved and doubled: the model reads about the same focal
        // length (353.5-360.8 px); at the nominal scale it reads 500, 267 (raised to cover the
        // input) and 1000.
        let sizes = [(1920, 1200, 1000.0), (960, 600, 500.0), (3840, 2400, 2000.0)];
        let with: Vec<f64> = sizes.iter().map(|&(w, h, fx)| input_fx(w, h, fx, RANGE)).collect();
        assert!(with.iter().all(|f| (f / with[0] - 1.0).abs() < 0.025), "{with:?}");
        let without: Vec<f64> = sizes.iter().map(|&(w, h, fx)| input_fx(w, h, fx, None)).collect();
        assert!((without[2] / without[0] - 2.0).abs() < 0.01, "{without:?}");
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
