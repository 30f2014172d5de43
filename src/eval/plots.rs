//! PNG plots of success rate against rotation and translation thresholds (the paper's Fig. 5),
//! drawn with plotters into a memory buffer and encoded with the `image` crate.

use std::path::Path;

use anyhow::{Result, anyhow};
use plotters::prelude::*;

use crate::atomic_file::write_atomic;
use super::calibration::CalibrationReport;
use super::report::EvalReport;

const PALETTE: [RGBColor; 6] = [
    RGBColor(214, 39, 40),
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(127, 127, 127),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
];

/// One line per method: (name, y values in 0..1 at `xs`).
pub fn success_plot(path: &Path, title: &str, x_label: &str, xs: &[f64], series: &[(String, Vec<f64>)]) -> Result<()> {
    crate::render::register_font();
    let (w, h) = (960u32, 520u32);
    let mut buffer = vec![0u8; (w * h * 3) as usize];
    let x_max = xs.last().copied().unwrap_or(1.0);
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        let err = |e| anyhow!("plotting {}: {e:?}", path.display());
        root.fill(&WHITE).map_err(err)?;
        // Plot on the left, legend on the right, so no curve is hidden behind the legend.
        let (plot_area, legend_area) = root.split_horizontally(720);
        let mut chart = ChartBuilder::on(&plot_area)
            .caption(title, ("sans-serif", 24))
            .margin(16)
            .x_label_area_size(48)
            .y_label_area_size(60)
            .build_cartesian_2d(0f64..x_max, 0f64..102f64)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc("success rate (%)")
            .label_style(("sans-serif", 15))
            .axis_desc_style(("sans-serif", 17))
            .draw()
            .map_err(err)?;
        for (i, (_, ys)) in series.iter().enumerate() {
            let color = PALETTE[i % PALETTE.len()];
            chart
                .draw_series(LineSeries::new(xs.iter().zip(ys).map(|(x, y)| (*x, 100.0 * y)), color.stroke_width(3)))
                .map_err(err)?;
        }
        for (i, (name, _)) in series.iter().enumerate() {
            let color = PALETTE[i % PALETTE.len()];
            let y = 70 + 28 * i as i32;
            legend_area.draw(&PathElement::new(vec![(4, y), (30, y)], color.stroke_width(3))).map_err(err)?;
            legend_area.draw(&Text::new(name.clone(), (36, y - 8), ("sans-serif", 15))).map_err(err)?;
        }
        root.present().map_err(err)?;
    }
    let image = image::RgbImage::from_raw(w, h, buffer).ok_or_else(|| anyhow!("plot buffer has the wrong size"))?;
    let mut png = Vec::new();
    image.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
    Ok(write_atomic(path, &png)?)
}

/// The two Fig. 5 panels for every method of the report, at each method's last iteration.
pub fn write_figure5(report: &EvalReport, out_dir: &Path) -> Result<()> {
    let series = |pick: fn(&super::report::MethodReport) -> &Vec<f64>| -> Vec<(String, Vec<f64>)> {
        report.methods.iter().map(|m| (m.method.clone(), pick(m).clone())).collect()
    };
    success_plot(
        &out_dir.join("fig5_rotation.png"),
        &format!("Success rate vs rotation threshold ({} cases)", report.cases),
        "RRE threshold (°, Euler sum)",
        &report.rotation_thresholds_deg,
        &series(|m| &m.rotation_curve),
    )?;
    success_plot(
        &out_dir.join("fig5_translation.png"),
        &format!("Success rate vs translation threshold ({} cases)", report.cases),
        "RTE threshold (m)",
        &report.translation_thresholds_m,
        &series(|m| &m.translation_curve),
    )
}

/// The reliability diagram's file in an evaluation's output directory.
pub const RELIABILITY_PNG: &str = "reliability.png";

/// The reliability diagram: per method, each non-empty bin's mean p_registered (x) against the
/// share of its cases that registered (y), marked with its case count; the diagonal is a perfect
/// calibrator. The legend gives each method's Brier score, base rate's Brier and ECE.
pub fn write_reliability(reports: &[CalibrationReport], path: &Path) -> Result<()> {
    crate::render::register_font();
    let (w, h) = (960u32, 620u32);
    let mut buffer = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        let err = |e| anyhow!("plotting {}: {e:?}", path.display());
        root.fill(&WHITE).map_err(err)?;
        let (plot_area, legend_area) = root.split_horizontally(620);
        let cases = reports.first().map_or(0, |r| r.cases);
        let mut chart = ChartBuilder::on(&plot_area)
            .caption(format!("Reliability of p_registered ({cases} cases)"), ("sans-serif", 24))
            .margin(16)
            .x_label_area_size(48)
            .y_label_area_size(60)
            .build_cartesian_2d(0f64..1f64, 0f64..1.02f64)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("mean p_registered in the bin")
            .y_desc("share registered (protocol A)")
            .label_style(("sans-serif", 15))
            .axis_desc_style(("sans-serif", 17))
            .draw()
            .map_err(err)?;
        chart.draw_series(LineSeries::new([(0.0, 0.0), (1.0, 1.0)], RGBColor(160, 160, 160).stroke_width(1))).map_err(err)?;
        for (i, r) in reports.iter().enumerate() {
            let color = PALETTE[i % PALETTE.len()];
            let points: Vec<(f64, f64, usize)> = r.bins.iter().filter(|b| b.cases > 0).map(|b| (b.mean_p, b.registered_share, b.cases)).collect();
            chart.draw_series(LineSeries::new(points.iter().map(|(x, y, _)| (*x, *y)), color.stroke_width(3))).map_err(err)?;
            chart.draw_series(points.iter().map(|(x, y, _)| Circle::new((*x, *y), 5, color.filled()))).map_err(err)?;
            // Each bin's case count, just up and right of its point.
            chart
                .draw_series(points.iter().map(|(x, y, n)| {
                    EmptyElement::at((*x, *y)) + Text::new(format!("{n}"), (6, -18), ("sans-serif", 13).into_font().color(&color))
                }))
                .map_err(err)?;
        }
        if let Some(t) = reports.first().map(|r| r.threshold).filter(|t| *t <= 1.0) {
            chart.draw_series(LineSeries::new([(t, 0.0), (t, 1.02)], RGBColor(60, 60, 60).stroke_width(1))).map_err(err)?;
        }
        for (i, r) in reports.iter().enumerate() {
            let color = PALETTE[i % PALETTE.len()];
            let y = 70 + 84 * i as i32;
            legend_area.draw(&PathElement::new(vec![(4, y), (30, y)], color.stroke_width(3))).map_err(err)?;
            legend_area.draw(&Text::new(r.method.clone(), (36, y - 8), ("sans-serif", 15))).map_err(err)?;
            let lines = [
                format!("Brier {:.3} (base rate {:.3}), ECE {:.3}", r.brier, r.brier_base_rate, r.ece),
                format!("localized {} of {} (p >= {:.2}), {} right", r.localized, r.cases, r.threshold, r.localized_registered),
            ];
            for (k, line) in lines.iter().enumerate() {
                legend_area.draw(&Text::new(line.clone(), (36, y + 12 + 20 * k as i32), ("sans-serif", 13))).map_err(err)?;
            }
        }
        root.present().map_err(err)?;
    }
    let image = image::RgbImage::from_raw(w, h, buffer).ok_or_else(|| anyhow!("plot buffer has the wrong size"))?;
    let mut png = Vec::new();
    image.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)?;
    Ok(write_atomic(path, &png)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reliability_diagram_draws_every_method() {
        use super::super::calibration::Judged;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(RELIABILITY_PNG);
        let judged: Vec<Judged> = (0..50).map(|i| Judged { p: i as f64 / 50.0, localized: i >= 40, registered: i % 3 != 0 && i > 20 }).collect();
        let reports = vec![CalibrationReport::of("a", 0.8, &judged), CalibrationReport::of("b", 0.8, &judged[10..])];
        write_reliability(&reports, &path).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (960, 620));
        assert!(img.pixels().any(|p| p.0 == [214, 39, 40]) && img.pixels().any(|p| p.0 == [31, 119, 180]));
    }

    #[test]
    fn writes_a_png_with_text_and_lines() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plot.png");
        let xs: Vec<f64> = (0..=10).map(f64::from).collect();
        let ys: Vec<f64> = xs.iter().map(|x| x / 10.0).collect();
        success_plot(&path, "title", "x (m)", &xs, &[("a".into(), ys.clone()), ("b".into(), ys.iter().map(|y| y * y).collect())]).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (960, 520));
        // Red line pixels and dark text pixels both exist.
        assert!(img.pixels().any(|p| p.0 == [214, 39, 40]));
        assert!(img.pixels().filter(|p| p.0[0] < 60 && p.0[1] < 60 && p.0[2] < 60).count() > 200);
    }
}
