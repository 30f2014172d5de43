//! The serving path: agent workers with iteration-level batching (see `Scheduler`).
