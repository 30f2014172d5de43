//! cmr-agent: tells a vehicle where its camera is inside a pre-built LiDAR map.
//!
//! The folder layout mirrors the architecture (see docs/architecture.md):
//! - `geometry`: frames, projection, poses, the action set, metrics: one home for conventions;
//! - `kitti`: the KITTI-odometry layout, read by everything and written by `synth`;
//! - `synth`: the procedural street world generator;
//! - `maps`: point-cloud formats, the map store, the embedding cache;
//! - `model`: ONNX Runtime and the model manifest;
//! - `agent`: state building, one trajectory, the multi-start search and the step loop;
//! - `serving`: the localize path (admission, validation, decode, deadline) and the batching
//!   scheduler, shared by the HTTP server and the CLI;
//! - `api`: the HTTP transport: routes, errors, configuration, lifecycle;
//! - `render`: pictures of a pose (map points projected onto the image), for the API and `eval`;
//! - `eval`: the paper's metrics and tables over a KITTI-layout data set;
//! - `track`: following a drive frame after frame (the loop, its errors, trajectory files, plot);
//! - `logging`: the log output every subcommand shares (stderr, `RUST_LOG`, `NO_COLOR`);
//! - `atomic_file`: the one crash-safe file writer everything uses.

pub mod agent;
pub mod atomic_file;
pub mod api;
pub mod eval;
pub mod geometry;
pub mod kitti;
pub mod logging;
pub mod maps;
pub mod model;
pub mod render;
pub mod serving;
pub mod synth;
pub mod track;
