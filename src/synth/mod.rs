//! The synthetic world: procedural places of several families (classic and urban streets,
//! suburbs, rural roads, tree-lined arterials, highways, industrial yards) seen by one of
//! several sensor rigs (a spinning multi-beam LiDAR and a colour camera), written as
//! KITTI-odometry sequences through `crate::kitti`.
//!
//! Layers, bottom up: `noise` (stateless hashing), `shapes` + `bvh` (ray casting), `terrain`
//! (the road's shape and the ground height), `materials`, `street` and `paint` (surfaces),
//! `scene` (shapes + ground + classes), `worlds` (one builder per family, the shared `kit`,
//! `bend` onto the terrain), `style` + `look` (appearance), `rig` + `rigs` (calibration,
//! catalogue), `trajectory`, the two sensors `lidar` and `render` (+ `camera_fx`), `generate`
//! (sequences on disk); then the commands: `args` (shared options), `demo`, `contact_sheet`,
//! `bench`, `stats`, and `cli` on top, which depends on them and never the reverse.

pub mod args;
pub mod bench;
pub mod bvh;
pub mod camera_fx;
pub mod cli;
pub mod contact_sheet;
pub mod demo;
pub mod generate;
pub mod lidar;
pub mod look;
pub mod materials;
pub mod noise;
pub mod paint;
pub mod render;
pub mod rig;
pub mod rigs;
pub mod scene;
pub mod shapes;
pub mod stats;
pub mod street;
pub mod style;
pub mod terrain;
pub mod trajectory;
pub mod worlds;

pub use generate::{generate, GeneratorConfig, SensorOverrides, SequencePlan, GENERATOR_VERSION};
pub use lidar::LidarConfig;
pub use look::LookMode;
pub use rig::Rig;
pub use rigs::RigChoice;
pub use style::{Palette, Style, StyleOverrides, StylePreset};
pub use worlds::WorldKind;
