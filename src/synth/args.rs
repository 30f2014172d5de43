//! Command-line options shared by every synth command (generation, bench, contact sheet,
//! stats). Subcommands depend on this module, `cli` depends on them; nothing here depends on
//! `cli`.

use super::generate::{GeneratorConfig, SensorOverrides};
use super::look::LookMode;
use super::rigs::{parse_rig, RigChoice};
use super::style::{Palette, StyleOverrides, StylePreset};
use super::worlds::WorldKind;

/// Scene and sensor options shared by every synth command.
#[derive(Debug, Clone, clap::Args)]
pub struct WorldArgs {
    /// Base seed: the same seed and flags give byte-identical output.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// World family; drawn per sequence (from every family but classic) when not given.
    #[arg(long, value_enum)]
    pub world: Option<WorldKind>,
    /// Sensor rig: kitti, nuscenes, wide, vlp16, os128, or random (drawn per sequence);
    /// `--list-rigs` prints their parameters.
    #[arg(long, default_value = "kitti", value_parser = parse_rig)]
    pub rig: RigChoice,
    /// Appearance: `random` (sky, sun, textures and camera effects drawn per sequence and
    /// frame) or `classic` (today's rendering).
    #[arg(long, value_enum, default_value_t = LookMode::Random)]
    pub look: LookMode,
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
    /// Per-pixel sensor noise standard deviation in 8-bit levels (classic look).
    #[arg(long)]
    pub noise_sigma: Option<f32>,
    /// Disable cast shadows (faster).
    #[arg(long)]
    pub no_shadows: bool,
    /// Image size WIDTHxHEIGHT (default: the rig's); intrinsics scale with the width.
    #[arg(long, value_parser = parse_size)]
    pub image_size: Option<(u32, u32)>,
    /// Scale every rig's image size by this factor (intrinsics follow), e.g. 0.5.
    #[arg(long)]
    pub image_scale: Option<f64>,
    /// LiDAR beams, evenly spaced between the rig's top and bottom beams (default: the rig's).
    #[arg(long)]
    pub lidar_beams: Option<u32>,
    /// LiDAR azimuth steps per revolution (default: the rig's).
    #[arg(long)]
    pub lidar_columns: Option<u32>,
    /// Distance driven between frames, metres.
    #[arg(long, default_value_t = 2.5)]
    pub spacing_m: f64,
}

pub fn parse_size(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text.split_once(['x', 'X']).ok_or_else(|| format!("`{text}` is not WIDTHxHEIGHT"))?;
    let w: u32 = w.trim().parse().map_err(|_| format!("`{w}` is not a width"))?;
    let h: u32 = h.trim().parse().map_err(|_| format!("`{h}` is not a height"))?;
    Ok((w, h))
}

impl WorldArgs {
    /// Today's generator for a preset and seed: kitti rig, classic world, classic look.
    pub fn classic(style: StylePreset, seed: u64) -> Self {
        WorldArgs {
            seed,
            world: Some(WorldKind::Classic),
            rig: RigChoice::default(),
            look: LookMode::Classic,
            style,
            palette: None,
            clutter: None,
            time_of_day: None,
            sun_azimuth_deg: None,
            exposure: None,
            noise_sigma: None,
            no_shadows: false,
            image_size: None,
            image_scale: None,
            lidar_beams: None,
            lidar_columns: None,
            spacing_m: 2.5,
        }
    }

    pub fn config(&self, sequences: usize, first_sequence: usize, frames: usize) -> GeneratorConfig {
        GeneratorConfig {
            seed: self.seed,
            sequences,
            first_sequence,
            frames,
            spacing_m: self.spacing_m,
            rig: self.rig.clone(),
            sensor: SensorOverrides {
                image_size: self.image_size,
                lidar_beams: self.lidar_beams,
                lidar_columns: self.lidar_columns,
                image_scale: self.image_scale,
            },
            world: self.world,
            look: self.look,
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
