//! Models: the manifest contract, ONNX Runtime loading, and the [`Backend`] every inference goes
//! through: [`OrtBackend`] for the real graphs, [`FakeBackend`] for fast deterministic tests of
//! everything around them (scheduler, search, admission).

pub mod backend;
pub mod calibrator;
pub mod fake;
pub mod manifest;
pub mod runtime;

use std::borrow::Cow;
use std::sync::Arc;

use anyhow::{Result, bail};

pub use backend::{BackendOptions, ModelSet, OrtBackend};
pub use calibrator::{Calibration, Calibrator, Signals, Verdict};
pub use fake::FakeBackend;
pub use manifest::{MANIFEST_FORMAT, MAX_CORRELATION_SHIFTS, Manifest, POINT_CHANNELS_INTENSITY, POINT_CHANNELS_XYZ, State2dSpec};

/// The point encoder's input: the points (map frame, metres) and, where the cloud has it, each
/// one's raw intensity (any scale: the backend reads it as its rank among these points).
#[derive(Debug, Clone, Copy)]
pub struct Points<'a> {
    pub xyz: &'a [[f32; 3]],
    /// One value per point of `xyz`; `None` for a cloud without intensity (read as a constant).
    pub intensity: Option<&'a [f32]>,
}

impl<'a> Points<'a> {
    pub fn new(xyz: &'a [[f32; 3]], intensity: Option<&'a [f32]>) -> Self {
        Points { xyz, intensity }
    }

    /// Points without intensity.
    pub fn xyz(xyz: &'a [[f32; 3]]) -> Self {
        Points { xyz, intensity: None }
    }

    pub fn len(&self) -> usize {
        self.xyz.len()
    }

    pub fn is_empty(&self) -> bool {
        self.xyz.is_empty()
    }

    /// Fails when `intensity` does not hold one value per point.
    pub fn check(&self) -> Result<()> {
        match self.intensity {
            Some(i) if i.len() != self.xyz.len() => bail!("{} intensity values for {} points", i.len(), self.xyz.len()),
            _ => Ok(()),
        }
    }
}

/// The point encoder's input tensor [1, N, C], row-major, for `manifest`'s `points.channels`:
/// C = 3, the xyz as given (no copy), intensity ignored; C = 4, x, y, z and each point's
/// `maps::intensity_rank` among these N points (0.5 for every point without intensity, the rank
/// of a constant). Errors: an intensity that is not one value per point.
pub fn point_tensor<'a>(manifest: &Manifest, points: Points<'a>) -> Result<Cow<'a, [f32]>> {
    points.check()?;
    if !manifest.reads_intensity() {
        return Ok(Cow::Borrowed(bytemuck::cast_slice(points.xyz)));
    }
    let ranks = match points.intensity {
        Some(values) => crate::maps::intensity_rank(values),
        None => vec![0.5; points.len()],
    };
    let mut flat = Vec::with_capacity(points.len() * 4);
    for (p, r) in points.xyz.iter().zip(ranks) {
        flat.extend_from_slice(&[p[0], p[1], p[2], r]);
    }
    Ok(Cow::Owned(flat))
}

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

    /// `points` N map-frame xyz (metres), with their raw intensity where the cloud has it →
    /// `point_features` [N, D], L2-normalised. The graph's input is [`point_tensor`]: [1, N, 3],
    /// or [1, N, 4] with each point's intensity rank among these N for a set whose manifest names
    /// `intensity_rank` (`Manifest::reads_intensity`). Errors: an intensity that is not one
    /// value per point, and the graph's.
    fn encode_points(&mut self, points: Points<'_>) -> Result<Vec<f32>>;

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
        let point_features = self.encode_points(Points::xyz(&points))?;
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The point encoder's input: the xyz as given for a three-column set (intensity ignored),
    /// x, y, z, rank interleaved for a four-column one (0.5 without intensity), and a refusal
    /// of an intensity that is not one value per point.
    #[test]
    fn the_point_tensor_follows_the_manifests_channels() {
        let mut manifest = Manifest::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model")).unwrap();
        let xyz = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]];
        let intensity = [0.2, 0.9, 0.2];
        let three = point_tensor(&manifest, Points::new(&xyz, Some(&intensity))).unwrap();
        assert!(matches!(three, Cow::Borrowed(_)));
        assert_eq!(&*three, xyz.as_flattened());
        manifest.points.channels = Some(POINT_CHANNELS_INTENSITY.map(String::from).to_vec());
        let four = point_tensor(&manifest, Points::new(&xyz, Some(&intensity))).unwrap();
        assert_eq!(&*four, &[1.0, 2.0, 3.0, 1.0 / 3.0, 4.0, 5.0, 6.0, 5.0 / 6.0, 7.0, 8.0, 9.0, 1.0 / 3.0]);
        let blind = point_tensor(&manifest, Points::xyz(&xyz)).unwrap();
        assert_eq!(&*blind, &[1.0, 2.0, 3.0, 0.5, 4.0, 5.0, 6.0, 0.5, 7.0, 8.0, 9.0, 0.5]);
        assert!(point_tensor(&manifest, Points::new(&xyz, Some(&intensity[..2]))).is_err());
        assert!(point_tensor(&manifest, Points::xyz(&[])).unwrap().is_empty());
    }
}
