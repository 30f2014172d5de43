//! Request and response bodies of the HTTP API (their JSON schema is generated from these).

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::agent::{Localization, Step};
use crate::geometry::Pose;
use crate::maps::{Extent, MapEntry, MapMetadata, Maps};
use crate::serving::{Matrix4x4, PriorSource};

use super::error::ApiError;

/// A row-major 4x4 rigid transform (its JSON schema is `serving::Matrix4x4`).
pub type Rows4x4 = [[f64; 4]; 4];

/// A pose and what a person wants to read off it.
#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct PoseBody {
    /// p_cam = R p_map + t, row-major 4x4.
    #[schema(value_type = Matrix4x4)]
    pub camera_from_map: Rows4x4,
    /// The camera centre in the map frame, metres.
    #[schema(value_type = Vec<f64>)]
    pub position_m: [f64; 3],
    /// Optical axis in the map's ground plane, degrees counter-clockwise from the map's +x axis.
    pub heading_deg: f64,
}

impl From<Pose> for PoseBody {
    fn from(p: Pose) -> Self {
        let c = p.camera_position_in_map();
        PoseBody { camera_from_map: p.to_rows(), position_m: [c.x, c.y, c.z], heading_deg: p.camera_heading_in_map_deg() }
    }
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct ActionBody {
    /// Yaw step, degrees: about the camera's y axis (model `actions.frame` = `camera_y`) or about
    /// the map's up axis z (`map_z`), through the map pivot.
    pub yaw_deg: f64,
    /// Step along the camera's x axis (`camera_y`) or its ground-plane right direction (`map_z`),
    /// metres.
    pub tx_m: f64,
    /// Step along the camera's z axis (`camera_y`) or its ground-plane heading (`map_z`), metres.
    pub tz_m: f64,
    /// Chosen step index per DoF (yaw, tx, tz) in the manifest's ascending action lists.
    #[schema(value_type = Vec<usize>)]
    pub indices: [usize; 3],
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct PolicyProbabilities {
    pub yaw_deg: Vec<f32>,
    pub tx_m: Vec<f32>,
    pub tz_m: Vec<f32>,
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct StepBody {
    pub iteration: usize,
    /// The action chosen at the previous pose.
    pub action: ActionBody,
    /// The pose after the action.
    #[schema(value_type = Matrix4x4)]
    pub camera_from_map: Rows4x4,
    /// Softmax of the policy per DoF over the ascending steps.
    pub probabilities: PolicyProbabilities,
    /// Mean over DoF of the chosen step's probability.
    pub policy_certainty: f32,
    /// Alignment score of the pose after the action (see `ConfidenceBody::alignment`).
    pub alignment: f32,
}

impl From<&Step> for StepBody {
    fn from(s: &Step) -> Self {
        StepBody {
            iteration: s.iteration,
            action: ActionBody { yaw_deg: s.action.yaw_deg, tx_m: s.action.tx_m, tz_m: s.action.tz_m, indices: s.action.indices },
            camera_from_map: s.camera_from_map.to_rows(),
            probabilities: PolicyProbabilities {
                yaw_deg: s.probabilities[0].clone(),
                tx_m: s.probabilities[1].clone(),
                tz_m: s.probabilities[2].clone(),
            },
            policy_certainty: s.confidence,
            alignment: s.alignment,
        }
    }
}

/// How sure the answer is: the calibrated verdict (`p_registered`, `localized`), then the raw
/// signals. score = sqrt(frustum_iou · policy_certainty).
#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct ConfidenceBody {
    /// Probability (0..1) that `pose` is within the paper's protocol A of the truth (rotation
    /// error, sum of absolute Euler angles, < 10° and translation error < 5 m), from the model
    /// set's calibrator over `signals` (manifest `calibrator`, fitted on evaluation outputs by
    /// `python -m cmr.calibrate`). Null when the model set has no calibrator (manifests made
    /// before it) or a signal it reads is not finite.
    #[schema(required = true, minimum = 0.0, maximum = 1.0)]
    pub p_registered: Option<f64>,
    /// `p_registered` ≥ the threshold in force (`localized_threshold` of `/v1/info`, or
    /// `localized_threshold_bounded` when the request stated a `prior_bound`: the manifest's,
    /// each chosen on calibration data for a precision of at least 95 %, or `serve
    /// --localized-threshold` for both). False whenever `p_registered` is null. Act on the pose
    /// only when true; otherwise treat it as unknown.
    pub localized: bool,
    /// What the calibrator reads (each field documented in the schema).
    pub signals: crate::model::Signals,
    pub score: f32,
    /// IoU of the points the frustum head predicts in view and the points in view at the final
    /// pose, over the model's state points (a random sample of M = 2,048 of the region's points).
    pub frustum_iou: f32,
    /// The last step's mean (over DoF) probability of the chosen step.
    pub policy_certainty: f32,
    /// Mean agreement (dot product of unit embeddings, −1..1) between the map points in view at
    /// the final pose and the image features where they project: what chose this hypothesis.
    pub alignment: f32,
}

/// One start of the multi-start search.
#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct HypothesisBody {
    /// The turn applied to its base to get this start, degrees: in the first round the prior,
    /// moved by `start_axis_shift_m` along its optical axis (about the map's centroid; within a
    /// `prior_bound`, about the prior's camera centre), in the refinement round the first
    /// round's answer or that answer turned by 180° (about its camera centre).
    pub start_yaw_offset_deg: f64,
    /// Where its base lies along the prior's optical axis, metres, forward positive: 0 without a
    /// request's `axis_starts`; in the refinement round, that of the first round's answer.
    pub start_axis_shift_m: f64,
    /// A start of the refinement round (the server's `--refine`; docs/server.md).
    pub refinement: bool,
    /// Alignment score of the start and of the final pose.
    pub start_alignment: f32,
    pub alignment: f32,
    /// The start: its base turned by `start_yaw_offset_deg` (camera_from_map, row-major).
    #[schema(value_type = Matrix4x4)]
    pub start_camera_from_map: Rows4x4,
    /// The hypothesis's final pose.
    #[schema(value_type = Matrix4x4)]
    pub camera_from_map: Rows4x4,
    pub iterations: usize,
    pub converged: bool,
    /// Stopped early: it came within 4 m / 20° of an earlier hypothesis (`merge_duplicates`), or
    /// another scored better after `narrow_after` steps.
    pub dropped: bool,
}

#[derive(Debug, Default, Clone, Copy, Serialize, Deserialize, ToSchema)]
pub struct TimingsMs {
    pub queue: f64,
    pub decode: f64,
    pub image_encoder: f64,
    pub frustum_head: f64,
    pub agent_steps: f64,
    /// Part of agent_steps: building the observations in Rust.
    pub agent_state_build: f64,
    /// Part of agent_steps: the continuous polish of the answer (0 when it did not run).
    pub agent_polish: f64,
    pub total: f64,
}

impl TimingsMs {
    /// The response's breakdown: the caller's own phases plus the agent's.
    pub fn new(queue: f64, decode: f64, agent: &crate::agent::Timings, total: f64) -> Self {
        TimingsMs {
            queue,
            decode,
            image_encoder: agent.image_encoder_ms,
            frustum_head: agent.frustum_head_ms,
            agent_steps: agent.agent_steps_ms,
            agent_state_build: agent.state_build_ms,
            agent_polish: agent.polish_ms,
            total,
        }
    }

    /// The `Server-Timing` header value.
    pub fn header(&self) -> String {
        format!(
            "queue;dur={:.2}, decode;dur={:.2}, image_encoder;dur={:.2}, frustum_head;dur={:.2}, agent_steps;dur={:.2}, total;dur={:.2}",
            self.queue, self.decode, self.image_encoder, self.frustum_head, self.agent_steps, self.total
        )
    }
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct LocalizeResponse {
    pub map_id: String,
    pub pose: PoseBody,
    /// The starting pose.
    #[schema(value_type = Matrix4x4)]
    pub prior_camera_from_map: Rows4x4,
    /// Where the starting pose came from: `request` (its `prior_camera_from_map`), `region` (the
    /// region's `initial_camera_from_map`) or `default` (neither: a level camera at the map
    /// frame's origin looking along the map's +x axis; docs/server.md, "The prior").
    pub prior_source: PriorSource,
    /// The chosen hypothesis's steps (none when the prior was kept).
    pub trajectory: Vec<StepBody>,
    pub confidence: ConfidenceBody,
    /// True when the chosen hypothesis's agent chose all-zero steps before running out of
    /// iterations (false when the prior was kept).
    pub converged: bool,
    /// Steps that led to the answer (0 when the prior was kept).
    pub iterations: usize,
    /// Every start of the search, in order; the first one starts at the prior.
    pub hypotheses: Vec<HypothesisBody>,
    /// Index into `hypotheses` of the answer (0 when the prior was kept).
    pub chosen_hypothesis: usize,
    /// The search's answer is the prior, unmoved: its alignment score beat every hypothesis's
    /// final pose (the server's `--keep-prior`, on by default); with `axis_starts`, the chosen
    /// hypothesis's start (the prior moved by its `start_axis_shift_m`); `polish` may still have
    /// moved `pose` from it.
    pub kept_prior: bool,
    /// How the search's answer was polished into `pose` (the server's `--polish`, on by
    /// default); null when the polish did not run.
    pub polish: Option<PolishBody>,
    /// Whether the judge's views chose the answer (docs/server.md, "The judge's views"); null
    /// when the search does not judge (`--judge-zoom 0`, or one start without a `prior_bound`).
    pub judge: Option<JudgeBody>,
    pub timings_ms: TimingsMs,
}

/// The judge's views of one request (the server's `--judge-zoom`, `--judge-gate`).
#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct JudgeBody {
    /// Share of the other starts whose final pose lies within 4 m / 20° of the served search's
    /// own answer, in [0, 1].
    pub agreement: f64,
    /// The views were encoded and judged (`agreement` at most the server's `--judge-gate`); when
    /// false the served crop's score chose among the visited poses alone.
    pub read_views: bool,
}

/// The continuous polish of an answer (docs/server.md, "The continuous polish"): from the
/// search's answer (the chosen hypothesis's pose, or the kept prior) or, when its polish scored
/// higher, another hypothesis's final pose, turns about the camera centre and sideways shifts
/// kept while they raise the alignment score.
#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct PolishBody {
    /// The pose polished (camera_from_map, map frame): the search's answer, or the final pose of
    /// the hypothesis the polished choice took (`chosen_hypothesis`).
    #[schema(value_type = Matrix4x4)]
    pub from_camera_from_map: Rows4x4,
    /// Its alignment score.
    pub from_alignment: f32,
    /// The polished answer's alignment score (`pose` is the polished answer).
    pub alignment: f32,
    /// Heading change from `from_camera_from_map` to `pose`, degrees (geodesic).
    pub rotation_deg: f64,
    /// Camera centre moved from `from_camera_from_map` to `pose`, metres.
    pub translation_m: f64,
    /// Poses scored, every candidate's together.
    pub scores: usize,
    /// Poses polished to choose the answer: the search's answer and up to 6 other hypotheses'
    /// final poses apart from it; `from_camera_from_map` is the one whose polish scored highest
    /// (docs/server.md, "The continuous polish").
    pub candidates: usize,
    /// The highest alignment score another candidate's peak reached; absent with one candidate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub runner_up_alignment: Option<f32>,
}

impl LocalizeResponse {
    pub fn new(map_id: &str, loc: &Localization, prior_source: PriorSource, timings_ms: TimingsMs) -> Self {
        LocalizeResponse {
            map_id: map_id.to_string(),
            pose: loc.camera_from_map().into(),
            prior_camera_from_map: loc.prior.to_rows(),
            prior_source,
            trajectory: loc.answer_steps().iter().map(StepBody::from).collect(),
            confidence: ConfidenceBody {
                p_registered: loc.verdict.p_registered,
                localized: loc.verdict.localized,
                signals: loc.signals(),
                score: loc.confidence.score,
                frustum_iou: loc.confidence.frustum_iou,
                policy_certainty: loc.confidence.policy_certainty,
                alignment: loc.confidence.alignment,
            },
            converged: loc.converged(),
            iterations: loc.answer_steps().len(),
            hypotheses: loc
                .hypotheses
                .iter()
                .map(|h| HypothesisBody {
                    start_yaw_offset_deg: h.start_yaw_offset_deg,
                    start_axis_shift_m: h.start_axis_shift_m,
                    refinement: h.refinement,
                    start_alignment: h.start_alignment,
                    alignment: h.alignment(),
                    start_camera_from_map: h.start.to_rows(),
                    camera_from_map: h.camera_from_map().to_rows(),
                    iterations: h.steps.len(),
                    converged: h.converged,
                    dropped: h.dropped,
                })
                .collect(),
            chosen_hypothesis: loc.chosen,
            kept_prior: loc.kept_prior,
            polish: loc.polish.map(|p| {
                let (rotation_deg, translation_m) = crate::agent::search::offset_between(&p.from, &p.camera_from_map);
                PolishBody { from_camera_from_map: p.from.to_rows(), from_alignment: p.from_alignment, alignment: p.alignment, rotation_deg, translation_m, scores: p.scores, candidates: p.candidates, runner_up_alignment: p.runner_up_alignment }
            }),
            judge: loc.judge.map(|j| JudgeBody { agreement: j.agreement, read_views: j.read_views }),
            timings_ms,
        }
    }
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct MapList {
    pub maps: Vec<MapSummary>,
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct MapSummary {
    pub id: String,
    /// Points stored (after any voxel downsampling at upload).
    pub num_points: usize,
    /// Bytes of the stored cloud (`<id>.bin`).
    pub file_bytes: u64,
    pub source_sha256: String,
    /// Whether the prepared embeddings are in memory now.
    pub cached: bool,
    pub metadata: MapMetadata,
    /// Map-frame coordinates (metres, float64) of the region's local frame: stored points are
    /// relative to it; requests and responses use the map frame.
    pub origin: [f64; 3],
    /// The box of the stored points, map frame, metres.
    pub extent: Extent,
    /// Whether the region is tiled (more points than one scan: a localize crops `radius_m`
    /// around its prior, and needs one).
    pub tiled: bool,
    /// Ground cells stored in `<id>.emb` (1 for a whole region; 0 when it is not written yet).
    pub tiles: usize,
    pub memory: MapMemory,
}

/// Where a region's bytes are.
#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct MapMemory {
    /// Heap held by the prepared-map cache for it now (a tiled region's embeddings are
    /// memory-mapped, not heap: only its cell table counts).
    pub cache_bytes: u64,
    /// Bytes of `<id>.emb` (a whole region's sample with float32 embeddings; a tiled one's cell
    /// table and points, with float16 embeddings per point only for `--crop-embeddings stored`);
    /// 0 when absent.
    pub embeddings_file_bytes: u64,
}

impl MapSummary {
    /// Blocking: reads the embeddings file's header.
    pub fn new(e: MapEntry, maps: &Maps) -> Self {
        let cached = maps.cache.peek(&e.id);
        let file = maps.store.embeddings_file(&e.id);
        let tiles = match (&cached, file) {
            (Some(p), _) => p.tiles(),
            (None, Some((_, Some(cells)))) => cells,
            (None, Some((_, None))) => 1,
            (None, None) => 0,
        };
        MapSummary {
            tiled: maps.is_tiled(e.num_points),
            tiles,
            memory: MapMemory { cache_bytes: cached.as_ref().map_or(0, |p| p.size_bytes() as u64), embeddings_file_bytes: file.map_or(0, |f| f.0) },
            id: e.id,
            num_points: e.num_points,
            file_bytes: e.file_bytes,
            source_sha256: e.source_sha256,
            cached: cached.is_some(),
            metadata: e.metadata,
            origin: e.origin,
            extent: e.extent,
        }
    }
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct RegisterResponse {
    pub map: MapSummary,
    /// Whether an existing region was replaced.
    pub replaced: bool,
    pub timings_ms: RegisterTimingsMs,
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct RegisterTimingsMs {
    pub parse: f64,
    /// A whole region's point-encoder pass; for a tiled region, grouping its points into cells
    /// (and, with `--crop-embeddings stored`, encoding them).
    pub point_encoder: f64,
    pub store: f64,
    pub total: f64,
}

#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct UploadParams {
    /// `kitti_bin` (or `kitti`, `bin`), `pcd`, `ply` or `las` (or `laz`); sniffed from the bytes
    /// when absent or empty (a body whose own header names another format is refused with 422).
    #[param(pattern = r"^(kitti_bin|kitti|bin|pcd|ply|las|laz)?$")]
    pub format: Option<String>,
    /// Optional description stored in the sidecar (metadata can also be set with PUT .../metadata),
    /// at most 4096 characters.
    #[param(max_length = 4096)]
    pub description: Option<String>,
    /// The region's local-frame origin, map frame, metres: `x,y,z` (e.g. `500000,5400000,0`).
    /// Points are stored relative to it (float32); default: the cloud's box centre rounded to a
    /// multiple of 1 km (so a region near the map frame's origin keeps origin 0,0,0).
    pub origin: Option<String>,
    /// Voxel downsampling before storing: one point (the centroid) per cube of this side,
    /// metres, 0.01..=100 (`geometry::voxel::MIN_VOXEL_M`, `MAX_VOXEL_M`). Default: none.
    #[param(minimum = 0.01, maximum = 100.0)]
    pub voxel_m: Option<f64>,
}

impl UploadParams {
    /// `origin` as three numbers. Errors: 422 naming the parameter.
    pub fn origin(&self) -> Result<Option<[f64; 3]>, ApiError> {
        let Some(text) = self.origin.as_deref().filter(|t| !t.is_empty()) else { return Ok(None) };
        let values: Vec<f64> = text.split(',').map(|v| v.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|e| ApiError::Invalid(format!("origin: {e} in {text:?}; give x,y,z in metres")))?;
        match values.as_slice() {
            [x, y, z] => Ok(Some([*x, *y, *z])),
            _ => Err(ApiError::Invalid(format!("origin: {text:?} has {} numbers; give x,y,z in metres", values.len()))),
        }
    }
}

/// Query of the raw-image variant of localize (body = the JPEG/PNG bytes, `content-type:
/// image/jpeg` or `image/png`): fx, fy, cx and cy are required with it, and unused with a JSON
/// body (a rule OpenAPI cannot state: a parameter cannot be required for one media type only).
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct RawLocalizeParams {
    /// Focal length along x, pixels (> 0). Required with a raw image body.
    #[param(exclusive_minimum = 0.0)]
    pub fx: Option<f64>,
    /// Focal length along y, pixels (> 0). Required with a raw image body.
    #[param(exclusive_minimum = 0.0)]
    pub fy: Option<f64>,
    /// Principal point x, pixels. Required with a raw image body.
    pub cx: Option<f64>,
    /// Principal point y, pixels. Required with a raw image body.
    pub cy: Option<f64>,
    /// 1..=50; default 10. The prior is the map's `initial_camera_from_map`.
    #[param(minimum = 1, maximum = 50)]
    pub max_iterations: Option<u32>,
    /// Starts of the multi-start search, 1..=16; default: the server's `default_hypotheses`.
    #[param(minimum = 1, maximum = 16)]
    pub hypotheses: Option<u32>,
    /// Crop radius in a tiled region, metres, 1..=500; default: the server's `default_radius_m`.
    #[param(minimum = 1, maximum = 500)]
    pub radius_m: Option<f64>,
}

impl RawLocalizeParams {
    /// The localize request a raw image body with these parameters stands for (the image is the
    /// body; the prior is the map's `initial_camera_from_map`). Errors: an intrinsic is missing.
    pub fn request(&self) -> Result<crate::serving::LocalizeRequest, ApiError> {
        let need = |v: Option<f64>, name: &str| v.ok_or_else(|| ApiError::Invalid(format!("query parameter {name} is required with a raw image body")));
        Ok(crate::serving::LocalizeRequest {
            image: String::new(),
            intrinsics: crate::serving::IntrinsicsBody { fx: need(self.fx, "fx")?, fy: need(self.fy, "fy")?, cx: need(self.cx, "cx")?, cy: need(self.cy, "cy")? },
            prior_camera_from_map: None,
            max_iterations: self.max_iterations,
            hypotheses: self.hypotheses,
            radius_m: self.radius_m,
            prior_bound: None,
            axis_starts: None,
        })
    }
}

/// Query of `GET /v1/maps/{id}/points`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct PointsParams {
    /// At most this many points, 1..=100000; default 20000. The answer holds
    /// min(max, the region's sample size N) points.
    #[param(minimum = 1, maximum = 100000)]
    pub max: Option<u32>,
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct Health {
    pub status: String,
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct Readiness {
    pub ready: bool,
    pub draining: bool,
    pub workers: usize,
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct Limits {
    pub max_body_bytes: usize,
    pub max_map_bytes: usize,
    pub max_image_side: u32,
    pub max_iterations: u32,
    pub default_max_iterations: u32,
    pub max_hypotheses: u32,
    pub default_hypotheses: u32,
    /// Steps after which a search keeps only its best-scoring hypothesis (0 = never).
    pub narrow_after: u32,
    /// Whether a hypothesis stops once it comes within 4 m / 20° of an earlier one.
    pub merge_duplicates: bool,
    /// Whether the prior competes with the answers (`--keep-prior`).
    pub keep_prior: bool,
    /// Whether unbounded searches run the refinement round (`--refine`).
    pub refine: bool,
    /// Whether the answer is polished on the alignment score (`--polish`).
    pub polish: bool,
    /// What a pose within 40° / 10 m of a stated prior adds to its alignment score when an
    /// unbounded search chooses its answer (`--prior-margin`; 0 = off).
    pub prior_margin: f32,
    /// The zoom of the judge's views (`--judge-zoom`; 0 = the served crop alone): multi-start and
    /// bounded searches choose their answer by the alignment score averaged over the served crop
    /// and three crops of the image resized this many times more.
    pub judge_zoom: f64,
    /// When those views are read (`--judge-gate`): only when at most this share of the other
    /// starts ended where the served search answers (1 = always).
    pub judge_gate: f64,
    pub queue_capacity: usize,
    pub max_batch: usize,
    pub request_timeout_ms: u64,
    /// How long a client may take to send a whole request body.
    pub body_timeout_ms: u64,
    pub cache_budget_bytes: u64,
    /// Most points an uploaded map file may hold.
    pub max_map_points: usize,
    /// Regions with more points are tiled.
    pub tile_above_points: usize,
    /// Default crop radius in tiled regions, metres.
    pub default_radius_m: f64,
}

#[derive(Debug, Serialize, Deserialize, ToSchema)]
pub struct Info {
    pub name: String,
    pub version: String,
    /// The model manifest as loaded.
    #[schema(value_type = Object)]
    pub manifest: serde_json::Value,
    pub limits: Limits,
    /// An answer is `localized` when its `confidence.p_registered` is at least this; null when
    /// the model set has no calibrator (then no answer is localized).
    #[schema(required = true, minimum = 0.0)]
    pub localized_threshold: Option<f64>,
    /// The same for a request that states a `prior_bound` (its answers are right more often at
    /// the same probability, so the model set may set a lower bar for them); null without a
    /// calibrator.
    #[schema(required = true, minimum = 0.0)]
    pub localized_threshold_bounded: Option<f64>,
    pub workers: usize,
    pub onnxruntime_library: Option<String>,
}

/// A request or response body of raw bytes (a point-cloud file, a JPEG/PNG image, float32
/// points): `{"type": "string", "format": "binary"}` in the OpenAPI document.
pub struct BinaryBody;

impl utoipa::PartialSchema for BinaryBody {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        use utoipa::openapi::schema::{KnownFormat, ObjectBuilder, SchemaFormat, Type};
        ObjectBuilder::new().schema_type(Type::String).format(Some(SchemaFormat::KnownFormat(KnownFormat::Binary))).into()
    }
}

impl utoipa::ToSchema for BinaryBody {}
