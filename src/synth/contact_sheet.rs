//! A contact sheet: one frame of every world family (rows) seen by a few rigs (columns), each
//! with its LiDAR points projected through the written calibration (camera_from_lidar of
//! image_2, P2's intrinsics) and coloured by depth. If the two sensors disagree, edges of
//! buildings, poles and cars visibly miss their points.

use std::path::PathBuf;

use anyhow::Result;
use image::{imageops, Rgb, RgbImage};
use nalgebra::Point3;

use super::args::WorldArgs;
use super::generate::{encode_png, SequencePlan};
use super::rigs::parse_rig;
use super::worlds::{WorldKind, DRAWN};
use crate::atomic_file::write_atomic;

#[derive(Debug, clap::Args)]
pub struct ContactSheetArgs {
    #[arg(long, default_value = "docs/synth-contact-sheet.png")]
    pub out: PathBuf,
    /// Rigs, one column each (comma-separated names).
    #[arg(long, default_value = "kitti,nuscenes,wide", value_delimiter = ',')]
    pub rigs: Vec<String>,
    /// Tile width in pixels (every rig's frame is scaled to it).
    #[arg(long, default_value_t = 400)]
    pub tile_width: u32,
    /// Frame of each sequence to show.
    #[arg(long, default_value_t = 6)]
    pub frame: usize,
    /// Add a row for the classic world.
    #[arg(long)]
    pub with_classic: bool,
    #[command(flatten)]
    pub world: WorldArgs,
}

pub fn run(args: &ContactSheetArgs) -> Result<()> {
    let worlds: Vec<WorldKind> = if args.with_classic { std::iter::once(WorldKind::Classic).chain(DRAWN).collect() } else { DRAWN.to_vec() };
    let gap = 4u32;
    let mut rows: Vec<Vec<RgbImage>> = Vec::new();
    for (r, &world) in worlds.iter().enumerate() {
        let mut row = Vec::new();
        for (c, rig) in args.rigs.iter().enumerate() {
            let rig = parse_rig(rig).map_err(anyhow::Error::msg)?;
            let seed = args.world.seed + (r * 31 + c) as u64;
            let config = WorldArgs { world: Some(world), rig, seed, ..args.world.clone() }.config(1, 0, args.frame + 1);
            config.validate()?;
            let plan = SequencePlan::new(&config, 0)?;
            row.push(tile(&plan, args.frame, args.tile_width)?);
        }
        rows.push(row);
    }
    let columns = args.rigs.len() as u32;
    let heights: Vec<u32> = rows.iter().map(|row| row.iter().map(|t| t.height()).max().unwrap_or(0)).collect();
    let width = columns * args.tile_width + (columns - 1) * gap;
    let height = heights.iter().sum::<u32>() + (heights.len() as u32 - 1) * gap;
    let mut sheet = RgbImage::from_pixel(width, height, Rgb([255, 255, 255]));
    let mut y = 0;
    for (row, h) in rows.iter().zip(&heights) {
        for (c, t) in row.iter().enumerate() {
            imageops::replace(&mut sheet, t, (c as u32 * (args.tile_width + gap)) as i64, y as i64);
        }
        y += h + gap;
    }
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    write_atomic(&args.out, &encode_png(&sheet)?)?;
    tracing::info!(rows = rows.len(), columns, "wrote {}", args.out.display());
    Ok(())
}

/// One frame scaled to `tile_width`, with every LiDAR point inside the image drawn as a
/// depth-coloured dot.
fn tile(plan: &SequencePlan, frame: usize, tile_width: u32) -> Result<RgbImage> {
    let output = plan.frame(frame)?;
    let camera_from_lidar = plan.calib.color_camera_from_lidar()?;
    let k = plan.calib.color_intrinsics()?;
    let (w, h) = output.rendered.image.dimensions();
    let scale = tile_width as f64 / w as f64;
    let th = ((h as f64) * scale).round() as u32;
    let mut img = imageops::resize(&output.rendered.image, tile_width, th, imageops::FilterType::Triangle);
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
        let x = ((u + 0.5) * scale - 0.5).round();
        let y = ((v + 0.5) * scale - 0.5).round();
        if x >= 0.0 && y >= 0.0 && (x as u32) < tile_width && (y as u32) < th {
            img.put_pixel(x as u32, y as u32, depth_color(z));
        }
    }
    Ok(img)
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
