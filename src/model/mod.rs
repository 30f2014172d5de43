//! Models: the manifest contract, ONNX Runtime loading, and the [`Backend`] every inference goes
//! through: [`OrtBackend`] for the real graphs, [`FakeBackend`] for fast deterministic tests of
//! everything around them (scheduler, search, admission).

pub mod backend;
pub mod calibrator;
pub mod fake;
pub mod manifest;
pub mod runtime;

use std::sync::Arc;

use anyhow::Result;

pub use backend::{BackendOptions, ModelSet, OrtBackend};
pub use calibrator::{Calibration, Calibrator, Signals, Verdict};
pub use fake::FakeBackend;
pub use manifest::{MANIFEST_FORMAT, MAX_CORRELATION_SHIFTS, Manifest, State2dSpec};

/// The agent's raw outputs for a batch of B states.
#[derive(Debug, Clone)]
pub struct AgentOutput {
    /// [B, 3, A] row-major: DoF rows, ascending-step columns. Not checked for finiteness: the
    /// step loop checks each row, so one bad row fails only its own request.
    pub policy_logits: Vec<f32>,
    /// [B].
    pub value: Vec<f32>,
}

/// The four graphs of the model contract (`docs/architecture.md`, "Model contract"), as one
/// thread's synchronous calls. Inputs and outputs are flat row-major f32 buffers in contract
/// layout. `encode_points`, `encode_image` and `frustum_logits` fail on non-finite outputs.
pub trait Backend: Send {
    fn manifest(&self) -> &Arc<Manifest>;

    /// `points` [N, 3] map-frame xyz (metres) → `point_features` [N, D], L2-normalised.
    fn encode_points(&mut self, points: &[[f32; 3]]) -> Result<Vec<f32>>;

    /// `image` [3, H, W] normalised RGB → `image_features` [D, H/stride, W/stride].
    fn encode_image(&mut self, image: &[f32]) -> Result<Vec<f32>>;

    /// In-frustum logits [N] for the map's point features [N, D] given one image's features.
    fn frustum_logits(&mut self, point_features: &[f32], image_features: &[f32]) -> Result<Vec<f32>>;

    /// One batched policy step: the 2D input [B, C, GH, GW] (`Manifest::state_2d`: the features
    /// form's C = 2D, the correlation form's C = shifts + 1) and `state_3d` [B, M, 5].
    fn agent_step(&mut self, state_2d: &[f32], state_3d: &[f32], batch: usize) -> Result<AgentOutput>;

    /// Runs every graph once on synthetic inputs so the first real request does not pay for
    /// ONNX Runtime's lazy initialisation.
    fn warm_up(&mut self) -> Result<()> {
        let manifest = self.manifest().clone();
        let m = manifest.points.num_state_points;
        let points = synthetic_cloud(m, 10.0, 2.0);
        let point_features = self.encode_points(&points)?;
        let (w, h) = (manifest.image.width as usize, manifest.image.height as usize);
        let image: Vec<f32> = (0..3 * w * h).map(|i| ((i % 251) as f32 / 251.0) - 0.5).collect();
        let image_features = self.encode_image(&image)?;
        self.frustum_logits(&point_features, &image_features)?;
        let state_2d = vec![0f32; manifest.state_2d_len()];
        let state_3d = vec![0.1f32; m * 5];
        self.agent_step(&state_2d, &state_3d, 1)?;
        Ok(())
    }
}

/// `n` points spread over a `side_m` x `side_m` square and `height_m` of height, centred on the
/// origin (a low-discrepancy sequence, no randomness): an input for warming up the point encoder.
pub fn synthetic_cloud(n: usize, side_m: f32, height_m: f32) -> Vec<[f32; 3]> {
    (0..n)
        .map(|i| {
            let t = i as f32 * 0.618_034;
            [side_m * (t.fract() - 0.5), side_m * ((t * 1.7).fract() - 0.5), height_m * ((t * 2.3).fract() - 0.5)]
        })
        .collect()
}

/// Makes one backend per worker thread.
pub type BackendFactory = Arc<dyn Fn() -> Result<Box<dyn Backend>> + Send + Sync>;

impl ModelSet {
    /// A factory of ONNX Runtime backends over this model set.
    pub fn factory(&self) -> BackendFactory {
        let set = self.clone();
        Arc::new(move || Ok(Box::new(set.backend()?) as Box<dyn Backend>))
    }
}
