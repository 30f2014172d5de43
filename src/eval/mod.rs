//! The evaluation harness: the paper's protocol on a KITTI-odometry directory, every method on
//! the same frozen cases, tables and plots in the paper's layouts.
//!
//! - `perturbations`: the frozen random map motions (JSON file, seed-reproducible);
//! - `methods`: the `Method` trait and the reference methods (no-op, greedy expert);
//! - `pnp`: the one-shot baseline's ground-plane 2-point RANSAC solver;
//! - `data`: cases from a KITTI-odometry directory (through `crate::kitti`);
//! - `learned`: the agent (the server's `agent::localize`) and the one-shot baseline on the
//!   same embeddings (`matching` + `pnp`);
//! - `summary`: protocol A / B aggregation; `report`: per-case records and tables; `plots`: Fig. 5
//!   and the reliability diagram; `calibration`: the calibrated verdict's figures;
//! - `run`: the whole evaluation; `cli`: `cmr-agent eval`.

pub mod calibration;
pub mod cli;
pub mod data;
pub mod learned;
pub mod matching;
pub mod methods;
pub mod perturbations;
pub mod plots;
pub mod pnp;
pub mod report;
pub mod run;
pub mod summary;
