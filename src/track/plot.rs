//! Top view of a tracked drive (PNG, plotters): the map's points (grey, map x/y), the true camera
//! centres (green line), the estimated ones (red line; fallback frames ringed orange, the
//! first frame's coarse prior a blue cross). Equal scale on both axes.

use std::path::Path;

use anyhow::{Result, anyhow};
use plotters::prelude::*;

use super::Mode;
use super::output::TrackRun;
use crate::atomic_file::write_atomic;

const TRUTH: RGBColor = RGBColor(44, 160, 44);
const ESTIMATE: RGBColor = RGBColor(214, 39, 40);
const FALLBACK: RGBColor = RGBColor(255, 127, 14);
const PRIOR: RGBColor = RGBColor(31, 119, 180);

/// Draws `run` over `map_points` (map frame, metres) into `path`. The view is the trajectories'
/// extent (and the first prior) plus a 15 m margin; points outside it are not drawn.
pub fn top_view(path: &Path, run: &TrackRun, map_points: &[[f32; 3]]) -> Result<()> {
    crate::render::register_font();
    let truth: Vec<(f64, f64)> = run.truth.iter().map(|p| p.camera_position_in_map()).map(|c| (c.x, c.y)).collect();
    let estimate: Vec<(f64, f64)> = run.frames.iter().map(|f| f.estimate.camera_position_in_map()).map(|c| (c.x, c.y)).collect();
    let prior = run.frames.first().map(|f| f.prior.camera_position_in_map()).map(|c| (c.x, c.y));
    let all = truth.iter().chain(&estimate).chain(prior.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, y) in all {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    if !x0.is_finite() {
        return Err(anyhow!("nothing to plot: the drive has no frames"));
    }
    let margin = 15.0;
    // Equal scale: widen the shorter side to the picture's aspect ratio.
    let (w, h) = (1200u32, 900u32);
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    let half_w = ((x1 - x0) / 2.0 + margin).max(((y1 - y0) / 2.0 + margin) * w as f64 / h as f64);
    let half_h = half_w * h as f64 / w as f64;
    let (x_range, y_range) = ((cx - half_w)..(cx + half_w), (cy - half_h)..(cy + half_h));

    let mut buffer = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        let err = |e| anyhow!("plotting {}: {e:?}", path.display());
        root.fill(&WHITE).map_err(err)?;
        let summary = run.summary()?;
        let title = format!(
            "{} frames: ATE {:.3} m, RPE {:.3} m / {:.2}°, {} fallbacks, {} dead-reckoned",
            summary.frames,
            summary.error.ate_rmse_m,
            summary.error.rpe_translation_rmse_m,
            summary.error.rpe_rotation_rmse_deg,
            summary.modes.fallback,
            summary.modes.dead_reckoning
        );
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(14)
            .x_label_area_size(44)
            .y_label_area_size(60)
            .build_cartesian_2d(x_range.clone(), y_range.clone())
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("map x (m)")
            .y_desc("map y (m)")
            .label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 16))
            .light_line_style(WHITE)
            .draw()
            .map_err(err)?;
        let inside = map_points
            .iter()
            .map(|p| (p[0] as f64, p[1] as f64))
            .filter(|(x, y)| x_range.contains(x) && y_range.contains(y));
        chart.draw_series(inside.map(|p| Pixel::new(p, RGBColor(150, 150, 150)))).map_err(err)?;
        chart
            .draw_series(LineSeries::new(truth.iter().copied(), TRUTH.stroke_width(3)))
            .map_err(err)?
            .label("truth")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], TRUTH.stroke_width(3)));
        chart
            .draw_series(LineSeries::new(estimate.iter().copied(), ESTIMATE.stroke_width(2)))
            .map_err(err)?
            .label("estimate")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], ESTIMATE.stroke_width(2)));
        chart.draw_series(estimate.iter().map(|&p| Circle::new(p, 2, ESTIMATE.filled()))).map_err(err)?;
        let fallbacks = run.frames.iter().filter(|f| f.mode == Mode::Fallback).map(|f| estimate[f.position]);
        chart
            .draw_series(fallbacks.map(|p| Circle::new(p, 7, FALLBACK.stroke_width(2))))
            .map_err(err)?
            .label("fallback to the full search")
            .legend(|(x, y)| Circle::new((x + 12, y), 6, FALLBACK.stroke_width(2)));
        if let Some(p) = prior {
            chart
                .draw_series(std::iter::once(Cross::new(p, 8, PRIOR.stroke_width(3))))
                .map_err(err)?
                .label("first frame's coarse prior")
                .legend(|(x, y)| Cross::new((x + 12, y), 6, PRIOR.stroke_width(3)));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 15))
            .draw()
            .map_err(err)?;
        root.present().map_err(err)?;
    }
    let image = image::RgbImage::from_raw(w, h, buffer).ok_or_else(|| anyhow!("plot buffer has the wrong size"))?;
    write_atomic(path, &crate::render::encode_png(&image)?)?;
    Ok(())
}
