//! Appearance knobs: colour palette, clutter, sun and sky, exposure and sensor noise.
//! A preset (`train`, `test`) gives ranges; each sequence draws its own values from them, and
//! any value fixed on the command line overrides the draw.

use rand::Rng;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Palette {
    /// Brick, ochre, cream facades; yellow-green foliage.
    Warm,
    /// Grey, slate, white, pale blue facades; dark blue-green foliage.
    Cool,
    /// Muted, low-saturation colours.
    Muted,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum StylePreset {
    Train,
    Test,
}

/// The style overrides a user can give; `None` = draw from the preset's range.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct StyleOverrides {
    pub palette: Option<Palette>,
    pub clutter: Option<f32>,
    pub time_of_day_h: Option<f32>,
    pub sun_azimuth_deg: Option<f32>,
    pub exposure: Option<f32>,
    pub noise_sigma: Option<f32>,
    pub shadows: Option<bool>,
}

/// One sequence's resolved style, recorded in its synth.json.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Style {
    pub preset: StylePreset,
    pub palette: Palette,
    /// Multiplies the density of small objects (trees, poles, cars, street furniture).
    pub clutter: f32,
    /// Local solar time in hours (6 = sunrise, 12 = noon, 18 = sunset).
    pub time_of_day_h: f32,
    /// Sun azimuth in the scene frame, degrees counter-clockwise from the street's +x direction.
    pub sun_azimuth_deg: f32,
    /// Linear multiplier on radiance before tone mapping.
    pub exposure: f32,
    /// Standard deviation of per-pixel sensor noise, in 8-bit levels.
    pub noise_sigma: f32,
    pub shadows: bool,
}

impl Style {
    pub fn draw(preset: StylePreset, overrides: &StyleOverrides, rng: &mut impl Rng) -> Style {
        let palettes: &[Palette] = match preset {
            StylePreset::Train => &[Palette::Warm, Palette::Muted],
            StylePreset::Test => &[Palette::Cool],
        };
        let drawn_palette = palettes[rng.random_range(0..palettes.len())];
        let (clutter, hours, exposure, noise) = match preset {
            StylePreset::Train => (rng.random_range(0.7..1.3), rng.random_range(8.5..15.5), rng.random_range(0.85..1.15), 2.0),
            StylePreset::Test => (rng.random_range(1.0..1.5), rng.random_range(16.5..17.8), rng.random_range(0.75..0.95), 3.0),
        };
        let azimuth = rng.random_range(0.0..360.0);
        Style {
            preset,
            palette: overrides.palette.unwrap_or(drawn_palette),
            clutter: overrides.clutter.unwrap_or(clutter),
            time_of_day_h: overrides.time_of_day_h.unwrap_or(hours),
            sun_azimuth_deg: overrides.sun_azimuth_deg.unwrap_or(azimuth),
            exposure: overrides.exposure.unwrap_or(exposure),
            noise_sigma: overrides.noise_sigma.unwrap_or(noise),
            shadows: overrides.shadows.unwrap_or(true),
        }
    }

    /// Sun elevation from the time of day: 0° at 6 h and 18 h, 62° at noon (a mid-latitude summer).
    pub fn sun_elevation_deg(&self) -> f32 {
        let phase = ((self.time_of_day_h - 6.0) / 12.0 * std::f32::consts::PI).sin();
        (62.0 * phase).max(3.0)
    }

    pub fn validate(&self) -> Result<(), String> {
        if !(0.0..=4.0).contains(&self.clutter) {
            return Err(format!("clutter {} must be within [0, 4]", self.clutter));
        }
        if !(0.0..=24.0).contains(&self.time_of_day_h) {
            return Err(format!("time of day {} h must be within [0, 24]", self.time_of_day_h));
        }
        if !(self.exposure > 0.0 && self.exposure <= 8.0) {
            return Err(format!("exposure {} must be within (0, 8]", self.exposure));
        }
        if !(0.0..=50.0).contains(&self.noise_sigma) {
            return Err(format!("noise sigma {} must be within [0, 50]", self.noise_sigma));
        }
        Ok(())
    }
}

/// Linear-RGB colour choices of a palette.
pub struct Colors {
    pub facades: &'static [[f32; 3]],
    pub trims: &'static [[f32; 3]],
    pub roofs: &'static [[f32; 3]],
    pub foliage: &'static [[f32; 3]],
    pub cars: &'static [[f32; 3]],
    pub pavement: [f32; 3],
    pub asphalt: [f32; 3],
    pub lot: [f32; 3],
}

impl Palette {
    pub fn colors(self) -> Colors {
        const CARS: &[[f32; 3]] = &[
            [0.80, 0.80, 0.80], [0.03, 0.03, 0.035], [0.45, 0.46, 0.48], [0.55, 0.05, 0.04],
            [0.06, 0.12, 0.40], [0.20, 0.22, 0.24], [0.70, 0.62, 0.45], [0.10, 0.30, 0.15],
        ];
        match self {
            Palette::Warm => Colors {
                facades: &[
                    [0.45, 0.17, 0.10], [0.62, 0.48, 0.30], [0.75, 0.68, 0.52], [0.55, 0.30, 0.14],
                    [0.70, 0.55, 0.40], [0.40, 0.25, 0.18], [0.80, 0.74, 0.62], [0.60, 0.38, 0.22],
                ],
                trims: &[[0.85, 0.82, 0.75], [0.30, 0.20, 0.14], [0.65, 0.60, 0.50]],
                roofs: &[[0.30, 0.12, 0.08], [0.22, 0.21, 0.20], [0.35, 0.28, 0.22]],
                foliage: &[[0.16, 0.30, 0.06], [0.24, 0.34, 0.08], [0.12, 0.24, 0.05]],
                cars: CARS,
                pavement: [0.48, 0.44, 0.38],
                asphalt: [0.11, 0.105, 0.10],
                lot: [0.26, 0.28, 0.12],
            },
            Palette::Cool => Colors {
                facades: &[
                    [0.55, 0.58, 0.62], [0.30, 0.33, 0.38], [0.82, 0.84, 0.85], [0.42, 0.50, 0.56],
                    [0.62, 0.68, 0.66], [0.22, 0.24, 0.28], [0.70, 0.72, 0.78], [0.48, 0.52, 0.46],
                ],
                trims: &[[0.92, 0.93, 0.95], [0.12, 0.13, 0.16], [0.50, 0.55, 0.60]],
                roofs: &[[0.18, 0.19, 0.22], [0.30, 0.32, 0.35], [0.12, 0.14, 0.16]],
                foliage: &[[0.06, 0.18, 0.10], [0.08, 0.22, 0.14], [0.05, 0.14, 0.09]],
                cars: CARS,
                pavement: [0.40, 0.42, 0.44],
                asphalt: [0.085, 0.09, 0.10],
                lot: [0.14, 0.20, 0.12],
            },
            Palette::Muted => Colors {
                facades: &[
                    [0.50, 0.46, 0.42], [0.38, 0.36, 0.34], [0.66, 0.63, 0.58], [0.44, 0.40, 0.34],
                    [0.58, 0.56, 0.52], [0.30, 0.28, 0.27],
                ],
                trims: &[[0.75, 0.74, 0.70], [0.22, 0.21, 0.20]],
                roofs: &[[0.20, 0.20, 0.20], [0.28, 0.26, 0.24]],
                foliage: &[[0.14, 0.22, 0.09], [0.18, 0.24, 0.12]],
                cars: CARS,
                pavement: [0.42, 0.41, 0.39],
                asphalt: [0.10, 0.10, 0.10],
                lot: [0.22, 0.23, 0.15],
            },
        }
    }
}
