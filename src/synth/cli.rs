//! `cmr-agent synth ...`: generate sequences (the default), `synth demo`, `synth contact-sheet`.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};

use super::generate::{generate, GeneratorConfig};
use super::lidar::LidarConfig;
use super::style::{Palette, StyleOverrides, StylePreset};

#[derive(Debug, clap::Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct Args {
    #[command(subcommand)]
    pub action: Option<Action>,
    #[command(flatten)]
    pub generate: GenerateArgs,
}

#[derive(Debug, clap::Subcommand)]
pub enum Action {
    /// Write the shipped demo map (maps/demo.*) and localize request (examples/localize-demo*).
    Demo(super::demo::DemoArgs),
    /// Render a grid of frames with the LiDAR projected onto them (a visual sensor check).
    ContactSheet(super::contact_sheet::ContactSheetArgs),
    /// Time the camera render, LiDAR sweep and PNG encoding per frame (writes nothing).
    Bench(super::bench::BenchArgs),
}

/// Scene and sensor options shared by every synth command.
#[derive(Debug, Clone, clap::Args)]
pub struct WorldArgs {
    /// Base seed: the same seed and flags give byte-identical output.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Style preset: `train` (daytime, warm/muted palettes) or `test` (evening, cool palette).
    #[arg(long, value_enum, default_value_t = StylePreset::Train)]
    pub style: StylePreset,
    /// Override the preset's palette.
    #[arg(long, value_enum)]
    pub palette: Option<Palette>,
    /// Density multiplier for trees, poles, street furniture and parked cars (0..4).
    #[arg(long)]
    pub clutter: Option<f32>,
    /// Local solar time in hours; sets the sun's elevation and colour.
    #[arg(long)]
    pub time_of_day: Option<f32>,
    /// Sun azimuth, degrees counter-clockwise from the street's direction.
    #[arg(long)]
    pub sun_azimuth_deg: Option<f32>,
    /// Camera exposure multiplier.
    #[arg(long)]
    pub exposure: Option<f32>,
    /// Per-pixel sensor noise standard deviation in 8-bit levels.
    #[arg(long)]
    pub noise_sigma: Option<f32>,
    /// Disable cast shadows (faster).
    #[arg(long)]
    pub no_shadows: bool,
    /// Image size WIDTHxHEIGHT; intrinsics scale with the width.
    #[arg(long, default_value = "1241x376", value_parser = parse_size)]
    pub image_size: (u32, u32),
    /// LiDAR beams (HDL-64E: 64).
    #[arg(long, default_value_t = 64)]
    pub lidar_beams: u32,
    /// LiDAR azimuth steps per revolution (HDL-64E at 10 Hz: ~2083).
    #[arg(long, default_value_t = 2083)]
    pub lidar_columns: u32,
    /// Distance driven between frames, metres.
    #[arg(long, default_value_t = 2.5)]
    pub spacing_m: f64,
}

#[derive(Debug, clap::Args)]
pub struct GenerateArgs {
    /// Output root; sequences are written to OUT/00, OUT/01, ...
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[arg(long, default_value_t = 1)]
    pub sequences: usize,
    #[arg(long, default_value_t = 20)]
    pub frames: usize,
    /// Number of the first sequence (so sets can be extended without clashing).
    #[arg(long, default_value_t = 0)]
    pub first_sequence: usize,
    /// Replace existing sequence directories.
    #[arg(long)]
    pub overwrite: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    #[command(flatten)]
    pub world: WorldArgs,
}

pub fn parse_size(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text.split_once(['x', 'X']).ok_or_else(|| format!("`{text}` is not WIDTHxHEIGHT"))?;
    let w: u32 = w.trim().parse().map_err(|_| format!("`{w}` is not a width"))?;
    let h: u32 = h.trim().parse().map_err(|_| format!("`{h}` is not a height"))?;
    Ok((w, h))
}

impl WorldArgs {
    /// The defaults of the command line for a preset and seed.
    pub fn preset(style: StylePreset, seed: u64) -> Self {
        WorldArgs {
            seed,
            style,
            palette: None,
            clutter: None,
            time_of_day: None,
            sun_azimuth_deg: None,
            exposure: None,
            noise_sigma: None,
            no_shadows: false,
            image_size: (super::rig::KITTI_WIDTH, super::rig::KITTI_HEIGHT),
            lidar_beams: 64,
            lidar_columns: 2083,
            spacing_m: 2.5,
        }
    }

    pub fn config(&self, sequences: usize, first_sequence: usize, frames: usize) -> GeneratorConfig {
        GeneratorConfig {
            seed: self.seed,
            sequences,
            first_sequence,
            frames,
            width: self.image_size.0,
            height: self.image_size.1,
            spacing_m: self.spacing_m,
            lidar: LidarConfig { beams: self.lidar_beams, columns: self.lidar_columns, ..LidarConfig::default() },
            preset: self.style,
            overrides: StyleOverrides {
                palette: self.palette,
                clutter: self.clutter,
                time_of_day_h: self.time_of_day,
                sun_azimuth_deg: self.sun_azimuth_deg,
                exposure: self.exposure,
                noise_sigma: self.noise_sigma,
                shadows: self.no_shadows.then_some(false),
            },
        }
    }
}

pub fn run(args: Args) -> Result<()> {
    match args.action {
        Some(Action::Demo(demo)) => super::demo::run(&demo),
        Some(Action::ContactSheet(sheet)) => super::contact_sheet::run(&sheet),
        Some(Action::Bench(bench)) => super::bench::run(&bench),
        None => {
            let g = args.generate;
            let Some(out) = g.out else { bail!("--out DIR is required (where the sequences are written)") };
            let config = g.world.config(g.sequences, g.first_sequence, g.frames);
            config.validate()?;
            std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
            let summary = generate(&config, &out, g.overwrite, !g.quiet)?;
            tracing::info!(
                frames = summary.frames,
                seconds = format!("{:.1}", summary.seconds),
                frames_per_s = format!("{:.2}", summary.frames as f64 / summary.seconds),
                mean_points = summary.points / summary.frames.max(1),
                "wrote {} sequence(s) to {}",
                config.sequences,
                out.display()
            );
            Ok(())
        }
    }
}
