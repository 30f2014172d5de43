//! Pictures of a pose: a map region's points projected onto a camera image, coloured by depth.
//! One drawing code for the HTTP overlay (`POST /v1/maps/{id}/overlay`) and the evaluator's
//! worst-case pictures, so what a curl user sees and what a report shows are the same thing.
//!
//! Layering: uses `geometry` only (points are plain `[f32; 3]` in the map frame); `api` and
//! `eval` both call it, so it sits below both.
//!
//! - [`Overlay`]: panels (one pose each, labelled) stacked top to bottom, and an optional strip of
//!   small panels (e.g. every iteration of a trajectory) in rows below them;
//! - [`depth_color`]: the colour scale (red near, through yellow and green, to blue far; log depth);
//! - [`register_font`]: the bundled font every picture's text uses.

use std::sync::Once;

use anyhow::{Result, anyhow};
use image::{Rgb, RgbImage};
use nalgebra::Point3;
use plotters::prelude::*;

use crate::geometry::{Intrinsics, Pose};

/// DejaVu Sans (Bitstream Vera licence, see assets/fonts/DejaVuSans.LICENSE): plotters'
/// bitmap backend has no system-font access without extra native libraries.
static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");
static REGISTER: Once = Once::new();

/// Registers the bundled font as plotters' "sans-serif" (once per process).
pub fn register_font() {
    REGISTER.call_once(|| {
        // A bundled, known-good TTF: failure here is a build defect, reported by the tests.
        if plotters::style::register_font("sans-serif", FontStyle::Normal, FONT).is_err() {
            tracing::error!("bundled font failed to load; picture text will be missing");
        }
    });
}

/// Widest picture drawn: larger images are scaled down to this width.
pub const MAX_WIDTH: u32 = 1600;
/// Height of the label bar above every panel, pixels.
const LABEL_BAR: u32 = 26;
/// Height of the label bar above every strip panel, pixels.
const STRIP_LABEL_BAR: u32 = 18;
/// Strip panels per row.
const STRIP_COLUMNS: u32 = 4;
/// Depth colour scale: red at or before NEAR_M, blue at or beyond FAR_M (log scale between).
pub const NEAR_M: f64 = 2.0;
pub const FAR_M: f64 = 60.0;
/// The camera image under the points is darkened to this fraction so the dots stand out.
const BACKGROUND: f32 = 0.7;

/// One pose to draw, with the text of its label bar.
#[derive(Debug, Clone)]
pub struct PosePanel {
    pub label: String,
    pub camera_from_map: Pose,
}

impl PosePanel {
    pub fn new(label: impl Into<String>, camera_from_map: Pose) -> Self {
        Self { label: label.into(), camera_from_map }
    }
}

/// What to draw: the image and its intrinsics, the map points, the panels and the strip.
pub struct Overlay<'a> {
    pub image: &'a RgbImage,
    /// Intrinsics of `image` at its own resolution.
    pub intrinsics: Intrinsics,
    /// Map-frame points, metres.
    pub points: &'a [[f32; 3]],
    /// Full-width panels, top to bottom.
    pub panels: Vec<PosePanel>,
    /// Small panels below, `STRIP_COLUMNS` per row (empty: none).
    pub strip: Vec<PosePanel>,
}

/// The scale a `width`-pixel image is drawn at (at most [`MAX_WIDTH`] wide, never enlarged).
pub fn scale_for(width: u32, max_width: u32) -> f64 {
    if width <= max_width { 1.0 } else { max_width as f64 / width as f64 }
}

/// The intrinsics of an image scaled by `s` (pixel centres at integers on both sides).
pub fn scaled_intrinsics(k: &Intrinsics, s: f64) -> Intrinsics {
    Intrinsics { fx: k.fx * s, fy: k.fy * s, cx: (k.cx + 0.5) * s - 0.5, cy: (k.cy + 0.5) * s - 0.5 }
}

/// The colour of a point `depth_m` in front of the camera: red near, yellow, green, cyan, blue far
/// (log depth between [`NEAR_M`] and [`FAR_M`]), a turbo-like ramp readable on photos.
pub fn depth_color(depth_m: f64) -> Rgb<u8> {
    // Stops of the ramp, near to far.
    const STOPS: [[f32; 3]; 7] = [
        [200.0, 20.0, 20.0],
        [250.0, 90.0, 20.0],
        [250.0, 210.0, 40.0],
        [120.0, 240.0, 60.0],
        [30.0, 220.0, 200.0],
        [40.0, 120.0, 250.0],
        [60.0, 40.0, 180.0],
    ];
    let t = ((depth_m.max(1e-3) / NEAR_M).ln() / (FAR_M / NEAR_M).ln()).clamp(0.0, 1.0) as f32;
    let x = t * (STOPS.len() - 1) as f32;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f32;
    let c = |j: usize| (STOPS[i][j] * (1.0 - f) + STOPS[i + 1][j] * f).round() as u8;
    Rgb([c(0), c(1), c(2)])
}

/// The points in front of the camera and inside a `width`×`height` image: (u, v, depth), far
/// first (so near points are drawn last, on top).
pub fn project_points(points: &[[f32; 3]], k: &Intrinsics, camera_from_map: &Pose, width: u32, height: u32) -> Vec<(f64, f64, f64)> {
    let mut out: Vec<(f64, f64, f64)> = points
        .iter()
        .filter_map(|p| {
            let c = camera_from_map.transform(&Point3::new(p[0] as f64, p[1] as f64, p[2] as f64));
            let (u, v) = k.project(&c)?;
            let inside = u >= -0.5 && v >= -0.5 && u < width as f64 - 0.5 && v < height as f64 - 0.5;
            inside.then_some((u, v, c.z))
        })
        .collect();
    out.sort_by(|a, b| b.2.total_cmp(&a.2));
    out
}

/// `image` (already at the panel's scale, darkened) with the points drawn as dots of `radius`.
fn draw_dots(canvas: &mut RgbImage, points: &[[f32; 3]], k: &Intrinsics, pose: &Pose, radius: i64) -> usize {
    let (w, h) = canvas.dimensions();
    let projected = project_points(points, k, pose, w, h);
    let r2 = radius * radius + radius / 2;
    for &(u, v, z) in &projected {
        let color = depth_color(z);
        let (cu, cv) = (u.round() as i64, v.round() as i64);
        for dy in -radius..=radius {
            for dx in -radius..=radius {
                if dx * dx + dy * dy > r2 {
                    continue;
                }
                let (x, y) = (cu + dx, cv + dy);
                if x >= 0 && y >= 0 && x < w as i64 && y < h as i64 {
                    canvas.put_pixel(x as u32, y as u32, color);
                }
            }
        }
    }
    projected.len()
}

/// The image scaled to `width` pixels wide and darkened (the background of every panel).
fn background(image: &RgbImage, width: u32) -> RgbImage {
    let (w, h) = image.dimensions();
    let height = ((h as f64 * width as f64 / w as f64).round() as u32).max(1);
    let mut scaled = if width == w { image.clone() } else { image::imageops::resize(image, width, height, image::imageops::FilterType::Triangle) };
    for p in scaled.pixels_mut() {
        for c in p.0.iter_mut() {
            *c = (*c as f32 * BACKGROUND) as u8;
        }
    }
    scaled
}

/// A label drawn onto the picture later: its bar's top-left corner, text and size.
struct Label {
    x: i32,
    y: i32,
    text: String,
    size: u32,
}

impl Overlay<'_> {
    /// Draws the picture. Errors only on an empty image.
    pub fn draw(&self) -> Result<RgbImage> {
        let (w, h) = self.image.dimensions();
        if w == 0 || h == 0 {
            return Err(anyhow!("the image is empty"));
        }
        let s = scale_for(w, MAX_WIDTH);
        let pw = ((w as f64 * s).round() as u32).max(1);
        let base = background(self.image, pw);
        let ph = base.height();
        let k = scaled_intrinsics(&self.intrinsics, s);
        let radius = if pw >= 900 { 2 } else { 1 };

        let columns = STRIP_COLUMNS.min(self.strip.len() as u32).max(1);
        let tw = (pw / STRIP_COLUMNS.max(columns)).max(1);
        let ts = tw as f64 / w as f64;
        let strip_base = (!self.strip.is_empty()).then(|| background(self.image, tw));
        let th = strip_base.as_ref().map_or(0, |b| b.height());
        let rows = (self.strip.len() as u32).div_ceil(columns);

        let total_h = self.panels.len() as u32 * (LABEL_BAR + ph) + rows * (STRIP_LABEL_BAR + th);
        let mut out = RgbImage::from_pixel(pw, total_h.max(1), Rgb([24, 24, 24]));
        let mut labels = Vec::new();
        let mut y = 0u32;
        for panel in &self.panels {
            let mut canvas = base.clone();
            let n = draw_dots(&mut canvas, self.points, &k, &panel.camera_from_map, radius);
            labels.push(Label { x: 8, y: y as i32, text: format!("{}  ({n} points in view)", panel.label), size: 17 });
            image::imageops::replace(&mut out, &canvas, 0, (y + LABEL_BAR) as i64);
            y += LABEL_BAR + ph;
        }
        if let Some(strip_base) = &strip_base {
            let tk = scaled_intrinsics(&self.intrinsics, ts);
            for (i, panel) in self.strip.iter().enumerate() {
                let (col, row) = (i as u32 % columns, i as u32 / columns);
                let (x0, y0) = (col * tw, y + row * (STRIP_LABEL_BAR + th));
                let mut canvas = strip_base.clone();
                draw_dots(&mut canvas, self.points, &tk, &panel.camera_from_map, 0);
                labels.push(Label { x: x0 as i32 + 4, y: y0 as i32, text: panel.label.clone(), size: 13 });
                image::imageops::replace(&mut out, &canvas, x0 as i64, (y0 + STRIP_LABEL_BAR) as i64);
            }
        }
        draw_labels(out, &labels)
    }

    /// [`Overlay::draw`], PNG-encoded.
    pub fn png(&self) -> Result<Vec<u8>> {
        encode_png(&self.draw()?)
    }
}

/// Writes the label texts in white onto the bars.
fn draw_labels(image: RgbImage, labels: &[Label]) -> Result<RgbImage> {
    register_font();
    let (w, h) = image.dimensions();
    let mut buffer = image.into_raw();
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        for l in labels {
            let style = ("sans-serif", l.size).into_font().color(&WHITE);
            let dy = if l.size >= 16 { 4 } else { 2 };
            root.draw(&Text::new(l.text.clone(), (l.x, l.y + dy), style)).map_err(|e| anyhow!("drawing a label: {e:?}"))?;
        }
        root.present().map_err(|e| anyhow!("drawing labels: {e:?}"))?;
    }
    RgbImage::from_raw(w, h, buffer).ok_or_else(|| anyhow!("label buffer has the wrong size"))
}

/// PNG bytes of an image.
pub fn encode_png(image: &RgbImage) -> Result<Vec<u8>> {
    let mut png = Vec::new();
    image.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
    Ok(png)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rig() -> Pose {
        Pose::from_matrix(&[[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]).unwrap()
    }

    #[test]
    fn the_depth_ramp_runs_from_red_to_blue() {
        let near = depth_color(1.0);
        let far = depth_color(100.0);
        assert!(near.0[0] > 150 && near.0[2] < 60, "{near:?}");
        assert!(far.0[2] > 150 && far.0[0] < 100, "{far:?}");
        assert_eq!(depth_color(NEAR_M), depth_color(0.5));
    }

    #[test]
    fn panels_stack_and_points_land_where_projected() {
        let image = RgbImage::from_pixel(2000, 600, Rgb([100, 100, 100]));
        let k = Intrinsics { fx: 1000.0, fy: 1000.0, cx: 999.5, cy: 299.5 };
        // One point 10 m straight ahead of the rig camera (map +x), projecting to the centre.
        let points = [[10.0f32, 0.0, 0.0]];
        let overlay = Overlay {
            image: &image,
            intrinsics: k,
            points: &points,
            panels: vec![PosePanel::new("prior", rig()), PosePanel::new("final", rig())],
            strip: (0..5).map(|i| PosePanel::new(format!("it {i}"), rig())).collect(),
        };
        let out = overlay.draw().unwrap();
        // 2000 px wide is scaled to 1600: each panel 480 high; 5 strip panels in 2 rows of 400x120.
        assert_eq!(out.width(), MAX_WIDTH);
        assert_eq!(out.height(), 2 * (LABEL_BAR + 480) + 2 * (STRIP_LABEL_BAR + 120));
        let centre = out.get_pixel(800, LABEL_BAR + 240);
        assert_eq!(*centre, depth_color(10.0));
        let second = out.get_pixel(800, 2 * LABEL_BAR + 480 + 240);
        assert_eq!(*second, depth_color(10.0));
        // The background is the darkened image; the label bar has white-ish text.
        assert_eq!(out.get_pixel(100, LABEL_BAR + 100).0, [70, 70, 70]);
        assert!((0..LABEL_BAR).any(|y| (0..300).any(|x| out.get_pixel(x, y).0[0] > 200)));
        let png = overlay.png().unwrap();
        assert_eq!(&png[1..4], b"PNG");
    }

    #[test]
    fn points_behind_or_outside_are_not_drawn() {
        let k = Intrinsics { fx: 100.0, fy: 100.0, cx: 49.5, cy: 49.5 };
        let points = [[-5.0f32, 0.0, 0.0], [5.0, 100.0, 0.0], [5.0, 0.0, 0.0], [20.0, 0.0, 0.0]];
        let p = project_points(&points, &k, &rig(), 100, 100);
        assert_eq!(p.len(), 2);
        assert!(p[0].2 > p[1].2, "far first");
    }
}
