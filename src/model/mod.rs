//! Models: the manifest contract, ONNX Runtime loading, and the synchronous backend.

pub mod backend;
pub mod manifest;
pub mod runtime;

pub use backend::{AgentOutput, Backend, BackendOptions, ModelSet};
pub use manifest::{Manifest, MANIFEST_FORMAT};
