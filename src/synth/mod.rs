//! The synthetic world: procedural streets seen by a KITTI-like rig (a spinning 64-beam LiDAR
//! and a colour camera), written as KITTI-odometry sequences through `crate::kitti`.
//!
//! Layers, bottom up: `noise` (stateless hashing), `shapes` + `bvh` (ray casting), `style`
//! (appearance knobs), `scene` (the street and its materials), `rig` (calibration and path),
//! `lidar` and `render` (the two sensors), `generate` (sequences on disk), then the extras:
//! `demo` (the shipped demo map and request) and `contact_sheet` (a visual check).

pub mod bench;
pub mod bvh;
pub mod cli;
pub mod contact_sheet;
pub mod demo;
pub mod generate;
pub mod lidar;
pub mod noise;
pub mod render;
pub mod rig;
pub mod scene;
pub mod shapes;
pub mod style;

pub use generate::{generate, GeneratorConfig, SequencePlan, GENERATOR_VERSION};
pub use lidar::LidarConfig;
pub use style::{Palette, Style, StyleOverrides, StylePreset};
