//! `models/manifest.json`: every convention a model set was trained with, checked before any
//! graph is loaded so that a mismatched model fails at start-up with one clear message instead of
//! producing nonsense poses.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::geometry::{ActionFrame, ActionSet, PreprocessPlan, input_scale};

use super::calibrator::Calibrator;

/// The only manifest format this build understands.
pub const MANIFEST_FORMAT: &str = "cmr-agent-manifest/1";

/// The graph names of the contract, in load order.
pub const GRAPH_NAMES: [&str; 4] = ["point_encoder", "image_encoder", "frustum_head", "agent"];

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub image: ImageSpec,
    pub features: FeatureSpec,
    pub points: PointSpec,
    pub actions: ActionSpec,
    pub graphs: BTreeMap<String, GraphSpec>,
    /// How the agent reads the 2D half of its state; absent = [`State2dSpec::features`].
    #[serde(default, skip_serializing_if = "State2dSpec::is_features")]
    pub state_2d: State2dSpec,
    #[serde(default)]
    pub provenance: serde_json::Value,
    #[serde(default)]
    pub validation: serde_json::Value,
    #[serde(default)]
    pub parameters: serde_json::Value,
    /// How sure an answer is (`model::calibrator`): fitted on `cmr-agent eval` outputs by
    /// `python -m cmr.calibrate`; absent in model sets made before it (then every answer is
    /// `p_registered: null, localized: false`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibrator: Option<Calibrator>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ImageSpec {
    pub width: u32,
    pub height: u32,
    /// The resize factor of an image (before the crop), unless `focal_range_px` moves it.
    pub nominal_scale: f64,
    /// [lo, hi]: the focal lengths (model-input pixels) the model was trained at; an image whose
    /// focal length at `nominal_scale` lies outside is resized into the range
    /// (`geometry::input_scale`). Absent in model sets before 2026-12-05: `nominal_scale` always.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub focal_range_px: Option<[f64; 2]>,
    pub mean: [f32; 3],
    pub std: [f32; 3],
}

impl ImageSpec {
    /// How an image of `width` × `height` pixels with focal length `fx` (pixels, > 0) becomes the
    /// model's input: `geometry::input_scale`, then `PreprocessPlan::centered`.
    pub fn plan(&self, width: u32, height: u32, fx: f64) -> PreprocessPlan {
        PreprocessPlan::centered(width, height, input_scale(self.nominal_scale, self.focal_range_px, fx), self.width, self.height)
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FeatureSpec {
    pub dim: usize,
    pub stride: usize,
    pub grid_height: usize,
    pub grid_width: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PointSpec {
    pub num_points: usize,
    pub num_state_points: usize,
    pub state_xyz_scale_m: f64,
    /// The point encoder's input columns, named ([`POINT_CHANNELS_XYZ`] or
    /// [`POINT_CHANNELS_INTENSITY`]); absent (every set before intensity encoders) means x, y, z.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub channels: Option<Vec<String>>,
}

/// The point encoder's input columns without intensity: map-frame metres.
pub const POINT_CHANNELS_XYZ: [&str; 3] = ["x", "y", "z"];

/// ... and with each point's intensity as its mid-rank among the N input points
/// (`maps::intensity_rank`, the twin of `training/cmr/data.py::intensity_rank`).
pub const POINT_CHANNELS_INTENSITY: [&str; 4] = ["x", "y", "z", "intensity_rank"];

impl PointSpec {
    fn validate_channels(&self) -> Result<(), String> {
        match &self.channels {
            None => Ok(()),
            Some(c) if c.as_slice() == POINT_CHANNELS_XYZ || c.as_slice() == POINT_CHANNELS_INTENSITY => Ok(()),
            Some(c) => Err(format!(
                "points.channels must be {POINT_CHANNELS_XYZ:?} or {POINT_CHANNELS_INTENSITY:?} (or absent, meaning {POINT_CHANNELS_XYZ:?}), got {c:?}"
            )),
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ActionSpec {
    pub dofs: Vec<String>,
    pub rotation_deg: Vec<f64>,
    pub translation_m: Vec<f64>,
    /// The axes the actions act along (`geometry::actions::ActionFrame`): `"camera_y"` (yaw about
    /// camera y, translation along camera x / z; what every model up to v3 was trained with, and
    /// the meaning when the field is absent) or `"map_z"` (yaw about the map's up axis,
    /// translation in the map's ground plane along the camera's heading).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<String>,
}

/// Most shifts a correlation-form model may list (rows and columns together).
pub const MAX_CORRELATION_SHIFTS: usize = 32;

/// The 2D half of the agent's state (manifest `state_2d`).
///
/// - `"features"` (every model up to v3, and the meaning when the section is absent): the agent
///   graph takes `state_2d` [B, 2D, GH, GW], the image features followed by the scatter-mean of
///   the projected point features, and correlates them itself.
/// - `"correlation"`: the server computes that correlation (`agent::state`, the twin of
///   `training/cmr/models.py::Agent.correlate`) and the agent graph takes `correlation`
///   [B, S + 1, GH, GW]: for each row shift s the cosine of a cell's unit point feature with the
///   image feature s cells to the right, then for each column shift the one s cells down, each 0
///   off the grid and at empty cells, and last the occupancy (1 where points project). Same
///   numbers into the same layers, without the 2D·GH·GW copy per row and the dense product
///   the graph spends most of its time on.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct State2dSpec {
    pub form: String,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub row_shifts: Vec<i32>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub column_shifts: Vec<i32>,
}

impl Default for State2dSpec {
    fn default() -> Self {
        Self::features()
    }
}

impl State2dSpec {
    pub fn features() -> Self {
        Self { form: "features".into(), row_shifts: Vec::new(), column_shifts: Vec::new() }
    }

    pub fn is_features(&self) -> bool {
        self.form == "features"
    }

    /// Channels of one row of the agent's 2D input.
    pub fn channels(&self, dim: usize) -> usize {
        if self.is_features() { 2 * dim } else { self.row_shifts.len() + self.column_shifts.len() + 1 }
    }

    /// The agent graph's name for its 2D input.
    pub fn input_name(&self) -> &'static str {
        if self.is_features() { "state_2d" } else { "correlation" }
    }

    fn validate(&self, f: &FeatureSpec) -> Result<(), String> {
        match self.form.as_str() {
            "features" if self.row_shifts.is_empty() && self.column_shifts.is_empty() => Ok(()),
            "features" => Err("state_2d: the features form takes no shifts".into()),
            "correlation" => {
                let n = self.row_shifts.len() + self.column_shifts.len();
                if self.row_shifts.is_empty() || n > MAX_CORRELATION_SHIFTS {
                    return Err(format!("state_2d: a correlation needs 1..={MAX_CORRELATION_SHIFTS} shifts with at least one row shift"));
                }
                let wide = |s: &[i32], limit: usize| s.iter().any(|d| d.unsigned_abs() as usize >= limit);
                if wide(&self.row_shifts, f.grid_width) || wide(&self.column_shifts, f.grid_height) {
                    return Err("state_2d: every shift must stay inside the feature grid".into());
                }
                Ok(())
            }
            other => Err(format!("state_2d.form must be \"features\" or \"correlation\", got {other:?}")),
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct GraphSpec {
    pub file: String,
    pub sha256: String,
    pub inputs: BTreeMap<String, Vec<serde_json::Value>>,
    pub outputs: BTreeMap<String, Vec<serde_json::Value>>,
    /// Floating-point operations of one run (N points, batch 1: per policy row for the agent),
    /// counted from the ONNX file by `training/cmr/flops.py`; absent in older manifests.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flops: Option<u64>,
}

/// One expected dimension: a fixed size, or any size (a dynamic axis such as N or B).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dim {
    Fixed(i64),
    Any,
}

impl Dim {
    /// A declared dimension from a manifest (integer = fixed; string or null = dynamic) or from
    /// ONNX Runtime (negative = dynamic).
    fn from_declared(v: i64) -> Self {
        if v < 0 { Dim::Any } else { Dim::Fixed(v) }
    }

    fn from_json(v: &serde_json::Value) -> Self {
        v.as_i64().map(Dim::from_declared).unwrap_or(Dim::Any)
    }

    fn compatible(self, other: Dim) -> bool {
        match (self, other) {
            (Dim::Fixed(a), Dim::Fixed(b)) => a == b,
            _ => true,
        }
    }
}

/// Whether a declared shape can hold the tensors the contract says we will feed or read.
pub fn shapes_compatible(declared: &[Dim], expected: &[Dim]) -> bool {
    declared.len() == expected.len() && declared.iter().zip(expected).all(|(a, b)| a.compatible(*b))
}

pub fn format_shape(shape: &[Dim]) -> String {
    let parts: Vec<String> = shape
        .iter()
        .map(|d| match d {
            Dim::Fixed(v) => v.to_string(),
            Dim::Any => "?".into(),
        })
        .collect();
    format!("[{}]", parts.join(", "))
}

/// The inputs and outputs (name, expected shape) the contract prescribes for one graph.
pub struct GraphContract {
    pub inputs: Vec<(&'static str, Vec<Dim>)>,
    pub outputs: Vec<(&'static str, Vec<Dim>)>,
}

#[derive(Debug, thiserror::Error)]
#[error("model manifest {path}: {message}")]
pub struct ManifestError {
    pub path: PathBuf,
    pub message: String,
}

impl Manifest {
    /// Reads and fully validates `dir/manifest.json`, including the sha256 of every graph file.
    pub fn load(dir: &Path) -> Result<Self, ManifestError> {
        let path = dir.join("manifest.json");
        let fail = |message: String| ManifestError { path: path.clone(), message };
        let text = std::fs::read_to_string(&path).map_err(|e| fail(format!("cannot read: {e}")))?;
        let raw: serde_json::Value = serde_json::from_str(&text).map_err(|e| fail(format!("not valid JSON: {e}")))?;
        // Check the format before the structure, so a future format gets the helpful message.
        match raw.get("format").and_then(|f| f.as_str()) {
            Some(MANIFEST_FORMAT) => {}
            Some(other) => {
                return Err(fail(format!("unknown format {other:?}; this build understands {MANIFEST_FORMAT:?}")));
            }
            None => return Err(fail(format!("missing \"format\" (expected {MANIFEST_FORMAT:?})"))),
        }
        let manifest: Manifest = serde_json::from_value(raw).map_err(|e| fail(format!("malformed: {e}")))?;
        manifest.validate(dir).map_err(fail)?;
        Ok(manifest)
    }

    fn validate(&self, dir: &Path) -> Result<(), String> {
        let f = &self.features;
        let img = &self.image;
        if f.dim == 0 || f.stride == 0 || img.width == 0 || img.height == 0 {
            return Err("image size, feature dim and stride must be positive".into());
        }
        if f.grid_height * f.stride != img.height as usize || f.grid_width * f.stride != img.width as usize {
            return Err(format!(
                "feature grid {}x{} at stride {} does not cover the {}x{} image",
                f.grid_width, f.grid_height, f.stride, img.width, img.height
            ));
        }
        if !(img.nominal_scale > 0.0) || img.std.iter().any(|s| !(*s > 0.0)) {
            return Err("image.nominal_scale and image.std must be positive".into());
        }
        if img.focal_range_px.is_some_and(|[lo, hi]| !(lo.is_finite() && hi.is_finite() && lo > 0.0 && lo <= hi)) {
            return Err("image.focal_range_px must be [lo, hi] pixels with 0 < lo <= hi".into());
        }
        let p = &self.points;
        if p.num_points == 0 || p.num_state_points == 0 || p.num_state_points > p.num_points {
            return Err("points.num_state_points must be in 1..=num_points".into());
        }
        if !(p.state_xyz_scale_m > 0.0) {
            return Err("points.state_xyz_scale_m must be positive".into());
        }
        p.validate_channels()?;
        if self.actions.dofs != ["yaw_deg", "tx_m", "tz_m"] {
            return Err(format!("actions.dofs must be [\"yaw_deg\", \"tx_m\", \"tz_m\"], got {:?}", self.actions.dofs));
        }
        if let Some(frame) = &self.actions.frame {
            ActionFrame::parse(frame).map_err(|e| format!("actions.frame: {e}"))?;
        }
        self.action_set().validate().map_err(|e| format!("actions: {e}"))?;
        self.state_2d.validate(f)?;
        if let Some(calibrator) = &self.calibrator {
            calibrator.validate()?;
        }
        for name in GRAPH_NAMES {
            let spec = self.graphs.get(name).ok_or_else(|| format!("graph {name:?} is missing"))?;
            let contract = self.contract(name);
            check_declared(name, "input", &spec.inputs, &contract.inputs)?;
            check_declared(name, "output", &spec.outputs, &contract.outputs)?;
            let file = self.graph_path(dir, name);
            let bytes = std::fs::read(&file).map_err(|e| format!("graph {name:?}: cannot read {}: {e}", file.display()))?;
            let actual = hex(&Sha256::digest(&bytes));
            if !actual.eq_ignore_ascii_case(&spec.sha256) {
                return Err(format!(
                    "graph {name:?}: sha256 of {} is {actual}, manifest says {}",
                    file.display(),
                    spec.sha256
                ));
            }
        }
        Ok(())
    }

    pub fn graph_path(&self, dir: &Path, name: &str) -> PathBuf {
        dir.join(&self.graphs[name].file)
    }

    /// The model's steps, acting in the model's frame.
    pub fn action_set(&self) -> ActionSet {
        ActionSet {
            rotation_deg: self.actions.rotation_deg.clone(),
            translation_m: self.actions.translation_m.clone(),
            frame: self.action_frame(),
        }
    }

    /// `actions.frame`; `camera_y` when absent (checked by `load`, so an unknown name read
    /// without `load` falls back to `camera_y` too).
    pub fn action_frame(&self) -> ActionFrame {
        self.actions.frame.as_deref().and_then(|f| ActionFrame::parse(f).ok()).unwrap_or_default()
    }

    /// Values of one image's features: D · GH · GW.
    pub fn image_feature_len(&self) -> usize {
        let f = &self.features;
        f.dim * f.grid_height * f.grid_width
    }

    /// Values of one row of the agent's 2D input (`state_2d` section): channels · GH · GW.
    pub fn state_2d_len(&self) -> usize {
        let f = &self.features;
        self.state_2d.channels(f.dim) * f.grid_height * f.grid_width
    }

    pub fn num_actions(&self) -> usize {
        self.actions.rotation_deg.len()
    }

    /// A warning when this set's int8 graphs answer worse on this CPU than on the one they were
    /// judged on: `provenance.quantized` (written by `python -m cmr.quantize`) names int8 weights
    /// without saying they are "within 7 bits" (sets quantised before 2026-12-07), and the CPU is
    /// x86-64 without VNNI, where ONNX Runtime's u8 × s8 kernels add pairs of products in int16
    /// and saturate with 8-bit weights (training/README.md, "Quantised graphs"). `None` otherwise,
    /// and for float sets.
    pub fn int8_saturation_warning(&self) -> Option<String> {
        self.int8_saturation_warning_on(cpu_has_vnni())
    }

    /// [`Self::int8_saturation_warning`] for a CPU with (`true`) or without VNNI.
    pub fn int8_saturation_warning_on(&self, cpu_has_vnni: bool) -> Option<String> {
        let quantized = self.provenance.get("quantized")?;
        let format = quantized.get("format").and_then(|f| f.as_str()).unwrap_or_default();
        if cpu_has_vnni || format.contains("within 7 bits") {
            return None;
        }
        let graphs: Vec<&str> = quantized.get("graphs").and_then(|g| g.as_array()).map(|g| g.iter().filter_map(|n| n.as_str()).collect()).unwrap_or_default();
        Some(format!(
            "the {} graph(s) of this model set hold 8-bit int8 weights, and this CPU has no VNNI: ONNX Runtime's integer \
             kernels saturate with them here and the answers are not the ones the set was judged with (measured: the \
             8-bit v11 set registered 20 fewer of 712 cases on an AVX2-only CPU); requantise it with `python -m \
             cmr.quantize` (7-bit weights) or serve its float graphs",
            graphs.join(", ")
        ))
    }

    /// Columns of one point of the point encoder's input (`points.channels`): 3, or 4 with the
    /// intensity rank.
    pub fn point_channels(&self) -> usize {
        self.points.channels.as_ref().map_or(POINT_CHANNELS_XYZ.len(), Vec::len)
    }

    /// Whether the point encoder reads each point's intensity (`points.channels` names
    /// `intensity_rank`).
    pub fn reads_intensity(&self) -> bool {
        self.point_channels() == POINT_CHANNELS_INTENSITY.len()
    }

    /// The sha256 of the point encoder: cached map embeddings are valid only for this value.
    pub fn point_encoder_sha256(&self) -> &str {
        &self.graphs["point_encoder"].sha256
    }

    /// Names and shapes of one graph's tensors as the contract defines them for this manifest.
    pub fn contract(&self, graph: &str) -> GraphContract {
        use Dim::{Any, Fixed};
        let d = self.features.dim as i64;
        let (gh, gw) = (self.features.grid_height as i64, self.features.grid_width as i64);
        let (h, w) = (self.image.height as i64, self.image.width as i64);
        let m = self.points.num_state_points as i64;
        let a = self.num_actions() as i64;
        match graph {
            "point_encoder" => GraphContract {
                inputs: vec![("points", vec![Fixed(1), Any, Fixed(self.point_channels() as i64)])],
                outputs: vec![("point_features", vec![Fixed(1), Any, Fixed(d)])],
            },
            "image_encoder" => GraphContract {
                inputs: vec![("image", vec![Fixed(1), Fixed(3), Fixed(h), Fixed(w)])],
                outputs: vec![("image_features", vec![Fixed(1), Fixed(d), Fixed(gh), Fixed(gw)])],
            },
            "frustum_head" => GraphContract {
                inputs: vec![
                    ("point_features", vec![Fixed(1), Any, Fixed(d)]),
                    ("image_features", vec![Fixed(1), Fixed(d), Fixed(gh), Fixed(gw)]),
                ],
                outputs: vec![("frustum_logits", vec![Fixed(1), Any])],
            },
            "agent" => GraphContract {
                inputs: vec![
                    (self.state_2d.input_name(), vec![Any, Fixed(self.state_2d.channels(d as usize) as i64), Fixed(gh), Fixed(gw)]),
                    ("state_3d", vec![Any, Fixed(m), Fixed(5)]),
                ],
                outputs: vec![("policy_logits", vec![Any, Fixed(3), Fixed(a)]), ("value", vec![Any, Fixed(1)])],
            },
            other => panic!("no contract for graph {other:?}"),
        }
    }
}

fn check_declared(
    graph: &str,
    kind: &str,
    declared: &BTreeMap<String, Vec<serde_json::Value>>,
    expected: &[(&'static str, Vec<Dim>)],
) -> Result<(), String> {
    for (name, shape) in expected {
        let got = declared
            .get(*name)
            .ok_or_else(|| format!("graph {graph:?}: {kind} {name:?} is not declared"))?;
        let got: Vec<Dim> = got.iter().map(Dim::from_json).collect();
        if !shapes_compatible(&got, shape) {
            return Err(format!(
                "graph {graph:?}: {kind} {name:?} is declared {} but the contract needs {}",
                format_shape(&got),
                format_shape(shape)
            ));
        }
    }
    if declared.len() != expected.len() {
        let extra: Vec<&String> = declared.keys().filter(|k| !expected.iter().any(|(n, _)| n == k)).collect();
        return Err(format!("graph {graph:?}: unexpected {kind}s {extra:?}"));
    }
    Ok(())
}

/// Converts ONNX Runtime's declared dims (negative = dynamic) to contract dims.
pub fn dims_from_onnx(dims: &[i64]) -> Vec<Dim> {
    dims.iter().map(|d| Dim::from_declared(*d)).collect()
}

pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

/// Whether this CPU has a VNNI instruction set (AVX512-VNNI or AVX-VNNI), with which ONNX
/// Runtime's u8 × s8 kernels sum in int32; `true` off x86-64, where the question does not arise.
fn cpu_has_vnni() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx512vnni") || std::is_x86_feature_detected!("avxvnni")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model")
    }

    fn copy_fixture(to: &Path) {
        for entry in std::fs::read_dir(fixture_dir()).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), to.join(entry.file_name())).unwrap();
        }
    }

    fn edit_manifest(dir: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
        let path = dir.join("manifest.json");
        let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        edit(&mut v);
        std::fs::write(path, serde_json::to_string(&v).unwrap()).unwrap();
    }

    #[test]
    fn fixture_manifest_is_valid() {
        let m = Manifest::load(&fixture_dir()).unwrap();
        assert_eq!(m.points.num_points, 40960);
        assert_eq!(m.num_actions(), 11);
    }

    #[test]
    fn refuses_unknown_format_missing_graph_bad_sha_and_bad_shape() {
        let cases: Vec<(Box<dyn FnOnce(&mut serde_json::Value)>, &str)> = vec![
            (Box::new(|v| v["format"] = "cmr-agent-manifest/2".into()), "unknown format"),
            (Box::new(|v| { v["graphs"].as_object_mut().unwrap().remove("agent"); }), "\"agent\" is missing"),
            (Box::new(|v| v["graphs"]["image_encoder"]["sha256"] = "00".into()), "sha256"),
            (Box::new(|v| v["graphs"]["agent"]["inputs"]["state_3d"] = serde_json::json!(["B", 2048, 4])), "contract needs"),
            (Box::new(|v| v["actions"]["dofs"] = serde_json::json!(["tx_m", "yaw_deg", "tz_m"])), "actions.dofs"),
            (Box::new(|v| v["actions"]["frame"] = "camera_z".into()), "actions.frame"),
            (Box::new(|v| v["actions"]["frame"] = serde_json::json!(3)), "malformed"),
            (Box::new(|v| v["image"]["focal_range_px"] = serde_json::json!([600.0, 300.0])), "focal_range_px"),
            (Box::new(|v| v["image"]["focal_range_px"] = serde_json::json!([0.0, 300.0])), "focal_range_px"),
            (Box::new(|v| v["image"]["focal_range_px"] = serde_json::json!([300.0])), "malformed"),
            (Box::new(|v| v["state_2d"] = serde_json::json!({"form": "pixels"})), "state_2d.form"),
            (Box::new(|v| v["state_2d"] = serde_json::json!({"form": "features", "row_shifts": [1]})), "takes no shifts"),
            (Box::new(|v| v["state_2d"] = serde_json::json!({"form": "correlation", "row_shifts": [], "column_shifts": [1]})), "at least one row shift"),
            (Box::new(|v| v["state_2d"] = serde_json::json!({"form": "correlation", "row_shifts": [128]})), "inside the feature grid"),
            (Box::new(|v| v["state_2d"] = serde_json::json!({"form": "correlation", "row_shifts": [0], "column_shifts": [-40]})), "inside the feature grid"),
            // The tiny agent reads the features form: a manifest claiming the correlation form
            // must not load it (its graph's 2D input is `state_2d`).
            (Box::new(|v| v["state_2d"] = serde_json::json!({"form": "correlation", "row_shifts": [0, 1]})), "\"correlation\" is not declared"),
        ];
        for (edit, needle) in cases {
            let dir = tempfile::tempdir().unwrap();
            copy_fixture(dir.path());
            edit_manifest(dir.path(), edit);
            let err = Manifest::load(dir.path()).unwrap_err().to_string();
            assert!(err.contains(needle), "{err} should mention {needle}");
        }
    }

    /// A set quantised with 8-bit weights warns on a CPU without VNNI only; float sets, 7-bit sets
    /// (the format `cmr.quantize` writes since 2026-12-07) and the shipped set never do.
    #[test]
    fn an_eight_bit_int8_set_is_flagged_only_on_a_cpu_without_vnni() {
        let mut m = Manifest::load(&fixture_dir()).unwrap();
        assert_eq!(m.int8_saturation_warning_on(false), None, "a float set");
        m.provenance = serde_json::json!({"quantized": {"graphs": ["image_encoder", "agent"],
            "format": "QDQ: Conv layers with uint8 activations and per-channel int8 weights"}});
        let warning = m.int8_saturation_warning_on(false).expect("8-bit weights without VNNI");
        assert!(warning.contains("image_encoder, agent") && warning.contains("cmr.quantize"), "{warning}");
        assert_eq!(m.int8_saturation_warning_on(true), None, "with VNNI nothing saturates");
        m.provenance["quantized"]["format"] = "QDQ: Conv layers with uint8 activations and per-channel int8 weights within 7 bits (reduce_range)".into();
        assert_eq!(m.int8_saturation_warning_on(false), None, "7-bit weights");
        let shipped = Manifest::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models")).unwrap();
        assert_eq!(shipped.int8_saturation_warning_on(false), None, "the shipped set");
    }

    /// A calibrator section survives load and write unchanged (the Python fitter writes it, the
    /// server reads it), is absent when absent, and a malformed one stops the load.
    #[test]
    fn the_calibrator_round_trips_and_is_checked() {
        let m = Manifest::load(&fixture_dir()).unwrap();
        assert!(m.calibrator.is_none());
        assert!(serde_json::to_value(&m).unwrap().get("calibrator").is_none(), "absent stays absent");
        let section = serde_json::json!({
            "kind": "logistic",
            "target": "registered (protocol A)",
            "features": ["alignment", "agreement", "log2_starts"],
            "mean": [0.41, 0.2, 1.0],
            "std": [0.12, 0.3, 1.0],
            "weights": [1.5, 0.75, -0.25],
            "bias": -0.5,
            "clip": 3.0,
            "threshold": 0.83,
            "provenance": {"command": "python -m cmr.calibrate", "metrics": {"auc": 0.9}},
        });
        let dir = tempfile::tempdir().unwrap();
        copy_fixture(dir.path());
        edit_manifest(dir.path(), |v| v["calibrator"] = section.clone());
        let m = Manifest::load(dir.path()).unwrap();
        let c = m.calibrator.as_ref().unwrap();
        assert_eq!((c.features.len(), c.threshold), (3, 0.83));
        assert_eq!(serde_json::to_value(&m).unwrap()["calibrator"], section);
        edit_manifest(dir.path(), |v| v["calibrator"]["features"][2] = "confidence".into());
        let err = Manifest::load(dir.path()).unwrap_err().to_string();
        assert!(err.contains("unknown signal \"confidence\""), "{err}");
    }

    #[test]
    fn state_2d_defaults_to_the_features_form_and_sizes_the_correlation_form() {
        let mut m = Manifest::load(&fixture_dir()).unwrap();
        assert!(m.state_2d.is_features());
        assert_eq!((m.state_2d.input_name(), m.state_2d_len()), ("state_2d", 2 * 64 * 40 * 128));
        assert!(serde_json::to_value(&m).unwrap().get("state_2d").is_none(), "absent stays absent");
        m.state_2d = State2dSpec { form: "correlation".into(), row_shifts: vec![-1, 0, 1], column_shifts: vec![2] };
        assert_eq!((m.state_2d.input_name(), m.state_2d_len()), ("correlation", 5 * 40 * 128));
        assert_eq!(m.contract("agent").inputs[0], ("correlation", vec![Dim::Any, Dim::Fixed(5), Dim::Fixed(40), Dim::Fixed(128)]));
    }

    fn intensity_fixture_dir() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model-intensity")
    }

    /// `points.channels`: absent and ["x", "y", "z"] read 3 columns, ["x", "y", "z",
    /// "intensity_rank"] 4 (the point encoder's declared input must say so); anything else, or
    /// a declared input that disagrees, stops the load with a message naming it.
    #[test]
    fn point_channels_are_three_or_four_with_the_intensity_rank() {
        let m = Manifest::load(&fixture_dir()).unwrap();
        assert!(m.points.channels.is_none());
        assert_eq!((m.point_channels(), m.reads_intensity()), (3, false));
        assert_eq!(m.contract("point_encoder").inputs[0].1, vec![Dim::Fixed(1), Dim::Any, Dim::Fixed(3)]);
        assert!(serde_json::to_value(&m).unwrap()["points"].get("channels").is_none(), "absent stays absent");

        let m = Manifest::load(&intensity_fixture_dir()).unwrap();
        assert_eq!(m.points.channels.as_deref(), Some(&POINT_CHANNELS_INTENSITY.map(String::from)[..]));
        assert_eq!((m.point_channels(), m.reads_intensity()), (4, true));
        assert_eq!(m.contract("point_encoder").inputs[0].1, vec![Dim::Fixed(1), Dim::Any, Dim::Fixed(4)]);
        assert_eq!(serde_json::to_value(&m).unwrap()["points"]["channels"], serde_json::json!(["x", "y", "z", "intensity_rank"]));

        // Naming the three columns is the same as not naming them.
        let dir = tempfile::tempdir().unwrap();
        copy_fixture(dir.path());
        edit_manifest(dir.path(), |v| v["points"]["channels"] = serde_json::json!(["x", "y", "z"]));
        assert_eq!(Manifest::load(dir.path()).unwrap().point_channels(), 3);

        let copy_intensity = |to: &Path| {
            for entry in std::fs::read_dir(intensity_fixture_dir()).unwrap() {
                let entry = entry.unwrap();
                std::fs::copy(entry.path(), to.join(entry.file_name())).unwrap();
            }
        };
        type Edit = Box<dyn FnOnce(&mut serde_json::Value)>;
        let cases: Vec<(bool, Edit, &str)> = vec![
            // A three-column set that says it reads intensity: its graph declares 3 columns.
            (false, Box::new(|v| v["points"]["channels"] = serde_json::json!(["x", "y", "z", "intensity_rank"])), "is declared [1, ?, 3] but the contract needs [1, ?, 4]"),
            // A four-column graph in a set without `channels`, or with three.
            (true, Box::new(|v| { v["points"].as_object_mut().unwrap().remove("channels"); }), "is declared [1, ?, 4] but the contract needs [1, ?, 3]"),
            (true, Box::new(|v| v["points"]["channels"] = serde_json::json!(["x", "y", "z"])), "contract needs [1, ?, 3]"),
            // Unknown names, orders and counts.
            (true, Box::new(|v| v["points"]["channels"] = serde_json::json!(["x", "y", "z", "reflectance"])), "points.channels must be"),
            (true, Box::new(|v| v["points"]["channels"] = serde_json::json!(["x", "y", "z", "intensity"])), "got [\"x\", \"y\", \"z\", \"intensity\"]"),
            (true, Box::new(|v| v["points"]["channels"] = serde_json::json!(["intensity_rank", "x", "y", "z"])), "points.channels must be"),
            (false, Box::new(|v| v["points"]["channels"] = serde_json::json!(["x", "y"])), "points.channels must be"),
            (false, Box::new(|v| v["points"]["channels"] = serde_json::json!([])), "points.channels must be"),
            (false, Box::new(|v| v["points"]["channels"] = serde_json::json!(4)), "malformed"),
        ];
        for (four, edit, needle) in cases {
            let dir = tempfile::tempdir().unwrap();
            if four { copy_intensity(dir.path()) } else { copy_fixture(dir.path()) }
            edit_manifest(dir.path(), edit);
            let err = Manifest::load(dir.path()).unwrap_err().to_string();
            assert!(err.contains(needle), "{err} should mention {needle}");
        }
    }

    #[test]
    fn action_frame_defaults_to_camera_y_and_reads_map_z() {
        let m = Manifest::load(&fixture_dir()).unwrap();
        assert!(m.actions.frame.is_none());
        assert_eq!(m.action_frame(), ActionFrame::CameraY);
        assert_eq!(m.action_set().frame, ActionFrame::CameraY);
        // Absent stays absent when written back (old readers see the same manifest).
        assert!(serde_json::to_value(&m).unwrap()["actions"].get("frame").is_none());
        for (name, frame) in [("camera_y", ActionFrame::CameraY), ("map_z", ActionFrame::MapZ)] {
            let dir = tempfile::tempdir().unwrap();
            copy_fixture(dir.path());
            edit_manifest(dir.path(), |v| v["actions"]["frame"] = name.into());
            let m = Manifest::load(dir.path()).unwrap();
            assert_eq!((m.action_frame(), m.action_set().frame), (frame, frame));
        }
    }
}
