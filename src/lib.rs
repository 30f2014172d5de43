//! cmr-agent: tells a vehicle where its camera is inside a pre-built LiDAR map.
//!
//! The folder layout mirrors the architecture (see docs/architecture.md):
//! geometry conventions shared by everything, the KITTI-odometry layout, the synthetic world
//! generator, and the serving stack.

pub mod eval;
pub mod geometry;
pub mod maps;
pub mod kitti;
pub mod synth;
