//! The ONNX Runtime implementation of [`Backend`]: one session per graph.
//!
//! `Session::run` needs `&mut self`, so an `OrtBackend` belongs to one thread at a time: every
//! worker creates its own from the shared, validated `ModelSet`.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result, anyhow, bail};
use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::TensorRef;

use super::manifest::{Manifest, dims_from_onnx, format_shape, shapes_compatible, GRAPH_NAMES};
use super::runtime;
use super::{AgentOutput, Backend, Points, point_tensor};

/// How sessions are created.
#[derive(Debug, Clone)]
pub struct BackendOptions {
    /// ONNX Runtime intra-op threads per session.
    pub intra_threads: usize,
    /// Explicit path of `libonnxruntime.so` (otherwise the search order of `runtime::candidate_paths`).
    pub ort_lib: Option<PathBuf>,
}

impl Default for BackendOptions {
    fn default() -> Self {
        Self { intra_threads: 1, ort_lib: None }
    }
}

/// A validated model directory; cheap to clone, shared by every worker.
#[derive(Debug, Clone)]
pub struct ModelSet {
    pub dir: PathBuf,
    pub manifest: Arc<Manifest>,
    pub options: BackendOptions,
}

impl ModelSet {
    /// Loads ONNX Runtime and the manifest, then builds one backend to check that every graph's
    /// real inputs and outputs match the contract. Any problem becomes one start-up error.
    pub fn load(dir: &Path, options: BackendOptions) -> Result<Self> {
        let manifest = Arc::new(Manifest::load(dir)?);
        if let Some(warning) = manifest.int8_saturation_warning() {
            tracing::warn!(models = %dir.display(), "{warning}");
        }
        runtime::environment(options.ort_lib.as_deref())?;
        let set = ModelSet { dir: dir.to_path_buf(), manifest, options };
        set.backend()?;
        Ok(set)
    }

    /// A fresh set of sessions for one thread.
    pub fn backend(&self) -> Result<OrtBackend> {
        let env = runtime::environment(self.options.ort_lib.as_deref())?;
        let mut sessions = Vec::with_capacity(4);
        for name in GRAPH_NAMES {
            let path = self.manifest.graph_path(&self.dir, name);
            let session = Session::builder(env)
                .map_err(|e| anyhow!("{e}"))?
                .with_optimization_level(GraphOptimizationLevel::Level3)
                .map_err(|e| anyhow!("{e}"))?
                .with_intra_threads(self.options.intra_threads.max(1))
                .map_err(|e| anyhow!("{e}"))?
                // Four sessions run back to back on the same cores; a pool left spinning after its
                // graph finishes steals those cores from the next graph and from state building
                // (measured: frustum head 7.8 ms after the image encoder with spinning, 3.0 without).
                .with_intra_op_spinning(false)
                .map_err(|e| anyhow!("{e}"))?
                .commit_from_file(&path)
                .map_err(|e| anyhow!("graph {name:?}: ONNX Runtime cannot load {}: {e}", path.display()))?;
            check_session(&self.manifest, name, &session)?;
            sessions.push(session);
        }
        let mut it = sessions.into_iter();
        let mut next = || it.next().expect("four sessions");
        Ok(OrtBackend {
            manifest: self.manifest.clone(),
            point_encoder: next(),
            image_encoder: next(),
            frustum_head: next(),
            agent: next(),
        })
    }
}

/// Compares a loaded graph's real inputs/outputs (names, element type, shapes) with the contract.
fn check_session(manifest: &Manifest, name: &str, session: &Session) -> Result<()> {
    let contract = manifest.contract(name);
    let check = |kind: &str, outlets: &[ort::value::Outlet], expected: &[(&'static str, Vec<super::manifest::Dim>)]| -> Result<()> {
        for (tensor, shape) in expected {
            let outlet = outlets
                .iter()
                .find(|o| o.name() == *tensor)
                .with_context(|| format!("graph {name:?}: the ONNX file has no {kind} named {tensor:?}"))?;
            let dtype = outlet.dtype();
            if dtype.tensor_type() != Some(ort::value::TensorElementType::Float32) {
                bail!("graph {name:?}: {kind} {tensor:?} must be float32, the ONNX file says {dtype}");
            }
            let dims = dims_from_onnx(dtype.tensor_shape().map(|s| &s[..]).unwrap_or(&[]));
            if !shapes_compatible(&dims, shape) {
                bail!(
                    "graph {name:?}: {kind} {tensor:?} has shape {} in the ONNX file; the contract needs {}",
                    format_shape(&dims),
                    format_shape(shape)
                );
            }
        }
        if outlets.len() != expected.len() {
            bail!("graph {name:?}: the ONNX file has {} {kind}s, the contract {}", outlets.len(), expected.len());
        }
        Ok(())
    };
    check("input", session.inputs(), &contract.inputs)?;
    check("output", session.outputs(), &contract.outputs)
}

/// One thread's sessions. Inputs and outputs are flat row-major f32 buffers in contract layout.
pub struct OrtBackend {
    manifest: Arc<Manifest>,
    point_encoder: Session,
    image_encoder: Session,
    frustum_head: Session,
    agent: Session,
}

impl Backend for OrtBackend {
    fn manifest(&self) -> &Arc<Manifest> {
        &self.manifest
    }

    fn encode_points(&mut self, points: Points<'_>) -> Result<Vec<f32>> {
        let n = points.len();
        let dim = self.manifest.features.dim;
        let flat = point_tensor(&self.manifest, points)?;
        let input = TensorRef::from_array_view(([1usize, n, self.manifest.point_channels()], &*flat))?;
        let outputs = self.point_encoder.run(ort::inputs!["points" => input])?;
        let features = extract(&outputs["point_features"], n * dim, "point_features")?;
        Ok(features)
    }

    fn encode_image(&mut self, image: &[f32]) -> Result<Vec<f32>> {
        let spec = &self.manifest.image;
        let (h, w) = (spec.height as usize, spec.width as usize);
        if image.len() != 3 * h * w {
            bail!("image tensor has {} values, expected 3x{h}x{w}", image.len());
        }
        let expected = self.manifest.image_feature_len();
        let input = TensorRef::from_array_view(([1usize, 3, h, w], image))?;
        let outputs = self.image_encoder.run(ort::inputs!["image" => input])?;
        extract(&outputs["image_features"], expected, "image_features")
    }

    fn frustum_logits(&mut self, point_features: &[f32], image_features: &[f32]) -> Result<Vec<f32>> {
        let d = self.manifest.features.dim;
        let n = point_features.len() / d;
        let f = self.manifest.features.clone();
        let pf = TensorRef::from_array_view(([1usize, n, d], point_features))?;
        let imf = TensorRef::from_array_view(([1usize, d, f.grid_height, f.grid_width], image_features))?;
        let outputs = self.frustum_head.run(ort::inputs!["point_features" => pf, "image_features" => imf])?;
        extract(&outputs["frustum_logits"], n, "frustum_logits")
    }

    fn agent_step(&mut self, state_2d: &[f32], state_3d: &[f32], batch: usize) -> Result<AgentOutput> {
        let f = self.manifest.features.clone();
        let m = self.manifest.points.num_state_points;
        let a = self.manifest.num_actions();
        if state_2d.len() != batch * self.manifest.state_2d_len() || state_3d.len() != batch * m * 5 {
            bail!("agent inputs do not hold {batch} states");
        }
        let spec = &self.manifest.state_2d;
        let s2 = TensorRef::from_array_view(([batch, spec.channels(f.dim), f.grid_height, f.grid_width], state_2d))?;
        let s3 = TensorRef::from_array_view(([batch, m, 5usize], state_3d))?;
        let outputs = self.agent.run(ort::inputs![spec.input_name() => s2, "state_3d" => s3])?;
        // Not checked for finiteness here: one row's NaN must fail only that row's request,
        // which the step loop decides (`agent::batch`).
        Ok(AgentOutput {
            policy_logits: extract_raw(&outputs["policy_logits"], batch * 3 * a, "policy_logits")?,
            value: extract_raw(&outputs["value"], batch, "value")?,
        })
    }
}

/// An output's values, checked for length and finiteness.
fn extract(value: &ort::value::DynValue, expected_len: usize, name: &str) -> Result<Vec<f32>> {
    let data = extract_raw(value, expected_len, name)?;
    if data.iter().any(|v| !v.is_finite()) {
        bail!("output {name:?} contains non-finite values");
    }
    Ok(data)
}

/// An output's values, checked for length only.
fn extract_raw(value: &ort::value::DynValue, expected_len: usize, name: &str) -> Result<Vec<f32>> {
    let (_, data) = value.try_extract_tensor::<f32>().with_context(|| format!("output {name:?}"))?;
    if data.len() != expected_len {
        bail!("output {name:?} has {} values, expected {expected_len}", data.len());
    }
    Ok(data.to_vec())
}
