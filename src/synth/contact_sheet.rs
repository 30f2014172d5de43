//! A contact sheet: generated frames with their LiDAR points projected through the written
//! calibration (camera_from_lidar of image_2, P2's intrinsics), coloured by depth. If the two
//! sensors disagree, edges of buildings, poles and cars visibly miss their points.

use std::path::PathBuf;

use anyhow::Result;
use image::{imageops, Rgb, RgbImage};
use nalgebra::Point3;

use super::cli::WorldArgs;
use super::generate::{encode_png, SequencePlan};
use super::style::StylePreset;
use crate::atomic_file::write_atomic;

#[derive(Debug, clap::Args)]
pub struct ContactSheetArgs {
    #[arg(long, default_value = "docs/synth-contact-sheet.png")]
    pub out: PathBuf,
    /// Sequences per style (each gives two rows: two frames, image | image + LiDAR).
    #[arg(long, default_value_t = 1)]
    pub per_style: usize,
    /// Tile scale relative to the rendered image.
    #[arg(long, default_value_t = 0.5)]
    pub tile_scale: f32,
    #[command(flatten)]
    pub world: WorldArgs,
}

pub fn run(args: &ContactSheetArgs) -> Result<()> {
    let mut tiles = Vec::new();
    for preset in [StylePreset::Train, StylePreset::Test] {
        let mut world = args.world.clone();
        world.style = preset;
        let config = world.config(args.per_style, 0, 8);
        config.validate()?;
        for s in 0..args.per_style {
            let plan = SequencePlan::new(&config, s)?;
            for frame in [2usize, 7] {
                // Each row: the camera image, then the same image with the LiDAR drawn on it.
                let (plain, overlay) = tile(&plan, &config, frame, args.tile_scale)?;
                tiles.push(plain);
                tiles.push(overlay);
            }
        }
    }
    let (tw, th) = tiles[0].dimensions();
    let columns = 2u32;
    let rows = (tiles.len() as u32).div_ceil(columns);
    let gap = 4;
    let mut sheet = RgbImage::from_pixel(columns * tw + (columns - 1) * gap, rows * th + (rows - 1) * gap, Rgb([255, 255, 255]));
    for (i, t) in tiles.iter().enumerate() {
        let (c, r) = (i as u32 % columns, i as u32 / columns);
        imageops::replace(&mut sheet, t, (c * (tw + gap)) as i64, (r * (th + gap)) as i64);
    }
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    write_atomic(&args.out, &encode_png(&sheet)?)?;
    tracing::info!(tiles = tiles.len(), "wrote {}", args.out.display());
    Ok(())
}

/// One frame, scaled: as rendered, and with every LiDAR point inside the image drawn as a
/// depth-coloured dot.
fn tile(plan: &SequencePlan, config: &super::GeneratorConfig, frame: usize, scale: f32) -> Result<(RgbImage, RgbImage)> {
    let output = plan.frame(config, frame)?;
    let camera_from_lidar = plan.calib.color_camera_from_lidar()?;
    let k = plan.calib.color_intrinsics()?;
    let (w, h) = output.rendered.image.dimensions();
    let (tw, th) = (((w as f32) * scale).round() as u32, ((h as f32) * scale).round() as u32);
    let plain = imageops::resize(&output.rendered.image, tw, th, imageops::FilterType::Triangle);
    let mut img = plain.clone();
    // Far points first so near ones stay on top.
    let mut projected: Vec<(f64, f64, f64)> = output
        .points
        .iter()
        .filter_map(|p| {
            let c = camera_from_lidar.transform(&Point3::new(p.x as f64, p.y as f64, p.z as f64));
            if !k.in_frustum(&c, w, h) {
                return None;
            }
            let (u, v) = k.project(&c)?;
            Some((u, v, c.z))
        })
        .collect();
    projected.sort_by(|a, b| b.2.total_cmp(&a.2));
    for (u, v, z) in projected {
        let x = ((u + 0.5) * scale as f64 - 0.5).round();
        let y = ((v + 0.5) * scale as f64 - 0.5).round();
        if x >= 0.0 && y >= 0.0 && (x as u32) < tw && (y as u32) < th {
            img.put_pixel(x as u32, y as u32, depth_color(z));
        }
    }
    Ok((plain, img))
}

/// Near = red, through yellow and green, to far = blue (0..40 m).
fn depth_color(z: f64) -> Rgb<u8> {
    let t = (z / 40.0).clamp(0.0, 1.0) as f32;
    let stops = [[230.0, 30.0, 30.0], [245.0, 220.0, 40.0], [40.0, 210.0, 80.0], [40.0, 120.0, 255.0]];
    let x = t * 3.0;
    let i = (x.floor() as usize).min(2);
    let f = x - i as f32;
    Rgb(std::array::from_fn(|c| (stops[i][c] * (1.0 - f) + stops[i + 1][c] * f) as u8))
}
