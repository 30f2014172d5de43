//! The localize request as it arrives (`LocalizeRequest`, also the OpenAPI schema) and as the
//! rest of the server sees it (`ValidLocalizeRequest`): built once, from the wire request, the
//! server's limits and the map entry, so every rule lives here and nowhere else.

use serde::Deserialize;
use utoipa::ToSchema;

use crate::agent::search::{AXIS_STEP_RANGE_M, AxisStarts, MAX_AXIS_STARTS, MAX_HYPOTHESES, MAX_ITERATIONS, PriorBound, SearchConfig, SearchTuning};
use crate::geometry::pose::Matrix4x4;
use crate::geometry::{Intrinsics, LocalFrame, Pose};
use crate::maps::MapEntry;

use super::error::LocalizeError;

/// Pinhole intrinsics in pixels (OpenCV convention, pixel centres at integers).
#[derive(Debug, Clone, Copy, serde::Serialize, Deserialize, ToSchema)]
pub struct IntrinsicsBody {
    /// Focal length along x, pixels.
    #[schema(exclusive_minimum = 0.0)]
    pub fx: f64,
    /// Focal length along y, pixels.
    #[schema(exclusive_minimum = 0.0)]
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

/// How far the prior can be from the truth, as the client knows it (a fleet's odometry or GNSS).
#[derive(Debug, Clone, Copy, serde::Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PriorBoundBody {
    /// Largest rotation between the prior and the true camera_from_map (geodesic angle),
    /// degrees, in (0, 180].
    #[schema(exclusive_minimum = 0.0, maximum = 180.0)]
    pub rotation_deg: f64,
    /// Largest distance between the prior's and the true camera position in the map, metres,
    /// in (0, 500].
    #[schema(exclusive_minimum = 0.0, maximum = 500.0)]
    pub translation_m: f64,
}

/// Starts along the prior's optical axis: the search runs from the prior and from it moved
/// ±k·`step_m` along the camera's optical axis (k = 1..=`each_way`), each as a request of its own
/// would run, and answers with the best-scoring of their answers, the unmoved prior's winning
/// unless another outscores it by more than `margin` (docs/tracking.md, "Starts along the optical
/// axis"). For a prior whose error lies along the heading: a tracked frame's prediction, a fleet
/// prior at an unknown speed.
#[derive(Debug, Clone, Copy, serde::Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct AxisStartsBody {
    /// Shifted priors each way, 0..=7 (0: the prior alone). `hypotheses` × (2·each_way + 1)
    /// may not exceed 16.
    #[schema(minimum = 0, maximum = 7)]
    pub each_way: u32,
    /// Their spacing, metres, 0.1..=10; default: the server's `--axis-step-m` (1.25).
    #[serde(default)]
    #[schema(minimum = 0.1, maximum = 10.0)]
    pub step_m: Option<f64>,
    /// Alignment-score units, 0..=1; default: the server's `--axis-margin` (0.005).
    #[serde(default)]
    #[schema(minimum = 0.0, maximum = 1.0)]
    pub margin: Option<f64>,
}

/// The range of `prior_bound.rotation_deg` (its lower end excluded), degrees.
pub const PRIOR_BOUND_ROTATION_MAX_DEG: f64 = 180.0;
/// The range of `prior_bound.translation_m` (its lower end excluded), metres.
pub const PRIOR_BOUND_TRANSLATION_MAX_M: f64 = 500.0;

#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct LocalizeRequest {
    /// Base64 (standard alphabet) JPEG or PNG bytes.
    #[schema(min_length = 1, format = Byte)]
    pub image: String,
    /// Pinhole intrinsics of `image` in pixels.
    pub intrinsics: IntrinsicsBody,
    /// Starting pose (camera_from_map). Default: the region's `initial_camera_from_map`; for a
    /// whole region without one, a level camera at the map frame's origin looking along the
    /// map's +x axis, when that origin lies within the region's x-y extent (a scan in its
    /// sensor's frame); otherwise (and in a tiled region without one) the request is a 422 naming
    /// this field. The response's `prior_source` says which.
    #[serde(default)]
    pub prior_camera_from_map: Option<Matrix4x4>,
    /// Policy steps per start, 1..=50; default: the server's `default_max_iterations` (10).
    #[serde(default)]
    #[schema(minimum = 1, maximum = 50)]
    pub max_iterations: Option<u32>,
    /// Starts of the multi-start search, 1..=16: the prior turned by k·360°/H about the map's
    /// centroid; the answer is the hypothesis whose pose best explains the image. 1 runs the
    /// paper's single trajectory (use it when the prior's heading is already good to ±45°).
    /// Default: the server's `default_hypotheses`.
    #[serde(default)]
    #[schema(minimum = 1, maximum = 16)]
    pub hypotheses: Option<u32>,
    /// In a tiled region (more points than one scan): the map points within this ground-plane
    /// distance of the prior's camera position are used, sampled to the model's N; metres,
    /// 1..=500. Default: the server's `default_radius_m` (60). Ignored by whole regions.
    #[serde(default)]
    #[schema(minimum = 1, maximum = 500)]
    pub radius_m: Option<f64>,
    /// The prior is known to be within this of the truth: the starts spread over the bound
    /// (the prior turned about its own camera centre by 0, ±rotation_deg, ±rotation_deg/2, ...)
    /// and the answer is the best-scoring pose the search visited inside it, the prior included,
    /// so it never lies outside. Absent: the whole circle (docs/server.md, "A bounded prior").
    #[serde(default)]
    pub prior_bound: Option<PriorBoundBody>,
    /// Also start from the prior moved forward and back along its optical axis (see the
    /// schema). With `prior_bound`, every start of every shifted prior competes as the bounded
    /// search's do (the best pose visited inside the bound around the prior). Default: the
    /// server's `--axis-starts` (0: none).
    #[serde(default)]
    pub axis_starts: Option<AxisStartsBody>,
}

/// The range of `radius_m`, metres.
pub const RADIUS_RANGE_M: std::ops::RangeInclusive<f64> = 1.0..=500.0;

/// What the server fills in when a request leaves it out.
#[derive(Debug, Clone, Copy)]
pub struct RequestDefaults {
    pub max_iterations: u32,
    pub hypotheses: u32,
    pub search: SearchTuning,
    /// Crop radius in tiled regions, metres.
    pub radius_m: f64,
}

/// Which points of a tiled region a request uses: a virtual scan from `sensor` (the prior
/// camera's position, local frame) of the points within `radius_m` of it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Crop {
    pub sensor: [f64; 3],
    pub radius_m: f64,
}

/// Where a localization's starting pose came from (the response's `prior_source`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum PriorSource {
    /// The request's `prior_camera_from_map`.
    Request,
    /// The region's `initial_camera_from_map`.
    Region,
    /// Neither was given: [`Pose::level_camera_along_x`] at the map frame's origin, which lies
    /// within the region's x-y extent (a whole region only).
    Default,
}

/// A localize request every later stage can trust.
#[derive(Debug, Clone)]
pub struct ValidLocalizeRequest {
    pub map: MapEntry,
    pub intrinsics: Intrinsics,
    /// The region's local frame: `prior` and everything the agent computes are in it.
    pub frame: LocalFrame,
    /// camera_from_local of the starting pose.
    pub prior: Pose,
    /// Where `prior` came from (the response's `prior_source`).
    pub prior_source: PriorSource,
    pub search: SearchConfig,
    /// For a tiled region: the crop around the prior, then (with starts along the optical axis)
    /// one around each shifted prior, in `AxisStarts::priors` order, as a request from it would
    /// get. Empty for a whole region.
    pub crops: Vec<Crop>,
}

impl ValidLocalizeRequest {
    /// Checks the request's numbers against the limits (422 `invalid_input` naming the field).
    /// `tiled`: the region is larger than one scan (`Maps::is_tiled`), so the request needs a
    /// prior (its own or the region's `initial_camera_from_map`) whose camera position lies within
    /// the region's x-y extent. A whole region without either starts from the default prior
    /// ([`PriorSource::Default`]) when the map frame's origin lies within its x-y extent, and is
    /// a 422 naming `prior_camera_from_map` otherwise: never a start that looks at nothing.
    pub fn new(request: &LocalizeRequest, defaults: &RequestDefaults, map: MapEntry, tiled: bool) -> Result<Self, LocalizeError> {
        let invalid = |field: &str, e: String| LocalizeError::Invalid(format!("{field}: {e}"));
        let k = request.intrinsics;
        let intrinsics = Intrinsics { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy };
        intrinsics.validate().map_err(|e| invalid("intrinsics", e.to_string()))?;
        let max_iterations = request.max_iterations.unwrap_or(defaults.max_iterations);
        if !(1..=MAX_ITERATIONS).contains(&max_iterations) {
            return Err(invalid("max_iterations", format!("must be in 1..={MAX_ITERATIONS}, got {max_iterations}")));
        }
        let hypotheses = request.hypotheses.unwrap_or(defaults.hypotheses) as usize;
        if !(1..=MAX_HYPOTHESES).contains(&hypotheses) {
            return Err(invalid("hypotheses", format!("must be in 1..={MAX_HYPOTHESES}, got {hypotheses}")));
        }
        let radius_m = request.radius_m.unwrap_or(defaults.radius_m);
        if !(radius_m.is_finite() && RADIUS_RANGE_M.contains(&radius_m)) {
            return Err(invalid("radius_m", format!("must be within {}..={} m, got {radius_m}", RADIUS_RANGE_M.start(), RADIUS_RANGE_M.end())));
        }
        let (prior, prior_source) = match (&request.prior_camera_from_map, map.metadata.initial_pose()) {
            (Some(m), _) => (m.pose().map_err(|e| invalid("prior_camera_from_map", e))?, PriorSource::Request),
            (None, Some(initial)) => (initial, PriorSource::Region),
            (None, None) if tiled => {
                return Err(invalid(
                    "prior_camera_from_map",
                    format!(
                        "map {:?} is larger than one scan ({} points): a localize in it needs a prior to choose the points around it; send prior_camera_from_map, or set the region's initial_camera_from_map",
                        map.id, map.num_points
                    ),
                ));
            }
            (None, None) if map.extent.contains_xy(0.0, 0.0) => (Pose::level_camera_along_x(nalgebra::Vector3::zeros()), PriorSource::Default),
            (None, None) => {
                return Err(invalid(
                    "prior_camera_from_map",
                    format!(
                        "map {:?} has no initial_camera_from_map and the map frame's origin lies outside its extent ({}), so there is no default start: send prior_camera_from_map, or set the region's initial_camera_from_map (PUT /v1/maps/{}/metadata)",
                        map.id, map.extent, map.id
                    ),
                ));
            }
        };
        let frame = map.frame();
        if tiled {
            let c = prior.camera_position_in_map();
            if !map.extent.contains_xy(c.x, c.y) {
                return Err(invalid(
                    "prior_camera_from_map",
                    format!("the prior camera position ({:.2}, {:.2}) m lies outside map {:?}'s extent ({})", c.x, c.y, map.id, map.extent),
                ));
            }
        }
        let crop_around = |p: &Pose| {
            let c = p.camera_position_in_map();
            Crop { sensor: [c.x - frame.origin.x, c.y - frame.origin.y, c.z - frame.origin.z], radius_m }
        };
        let prior_bound = match request.prior_bound {
            None => None,
            Some(b) => {
                if !(b.rotation_deg > 0.0 && b.rotation_deg <= PRIOR_BOUND_ROTATION_MAX_DEG) {
                    return Err(invalid("prior_bound.rotation_deg", format!("must be in (0, {PRIOR_BOUND_ROTATION_MAX_DEG}], got {}", b.rotation_deg)));
                }
                if !(b.translation_m > 0.0 && b.translation_m <= PRIOR_BOUND_TRANSLATION_MAX_M) {
                    return Err(invalid("prior_bound.translation_m", format!("must be in (0, {PRIOR_BOUND_TRANSLATION_MAX_M}], got {}", b.translation_m)));
                }
                Some(PriorBound { rotation_deg: b.rotation_deg, translation_m: b.translation_m })
            }
        };
        // The prior's margin favours poses near a prior the client stated, not a start the server
        // chose for it (the region's initial pose, the map origin).
        let stated = prior_source == PriorSource::Request;
        let tuned = defaults.search.search(hypotheses, max_iterations as usize);
        let axis = match request.axis_starts {
            None => tuned.axis,
            Some(a) => {
                if a.each_way as usize > MAX_AXIS_STARTS {
                    return Err(invalid("axis_starts.each_way", format!("must be in 0..={MAX_AXIS_STARTS}, got {}", a.each_way)));
                }
                let step_m = a.step_m.unwrap_or(tuned.axis.step_m);
                if !(step_m.is_finite() && AXIS_STEP_RANGE_M.contains(&step_m)) {
                    return Err(invalid("axis_starts.step_m", format!("must be within {}..={} m, got {step_m}", AXIS_STEP_RANGE_M.start(), AXIS_STEP_RANGE_M.end())));
                }
                // Checked before it becomes an f32, which would round 1 + 1e-9 to 1.
                let margin = a.margin.unwrap_or(tuned.axis.margin as f64);
                if !(margin.is_finite() && (0.0..=1.0).contains(&margin)) {
                    return Err(invalid("axis_starts.margin", format!("must be within 0..=1, got {margin}")));
                }
                let margin = margin as f32;
                AxisStarts { each_way: a.each_way as usize, step_m, margin }
            }
        };
        let search = SearchConfig { prior_bound, prior_margin: if stated { tuned.prior_margin } else { 0.0 }, axis, ..tuned };
        if search.starts() > MAX_HYPOTHESES {
            let each_way = search.axis.each_way;
            return Err(invalid("axis_starts", format!("hypotheses × (2·each_way + 1) must be at most {MAX_HYPOTHESES}, got {hypotheses} × {} (each_way {each_way})", search.axis.groups())));
        }
        let crops = if tiled { search.axis.priors(&prior).iter().map(|(_, p)| crop_around(p)).collect() } else { Vec::new() };
        Ok(Self { map, intrinsics, frame, prior: frame.camera_from_local(&prior), prior_source, search, crops })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(json: serde_json::Value) -> LocalizeRequest {
        serde_json::from_value(json).unwrap()
    }

    fn entry() -> MapEntry {
        let extent = crate::maps::Extent { min: [-50.0, -50.0, -3.0], max: [50.0, 50.0, 10.0] };
        MapEntry { id: "m".into(), num_points: 1, file_bytes: 16, source_sha256: String::new(), metadata: Default::default(), origin: [0.0; 3], extent }
    }

    fn defaults() -> RequestDefaults {
        RequestDefaults { max_iterations: 10, hypotheses: 4, search: SearchTuning::default(), radius_m: 40.0 }
    }

    #[test]
    fn every_field_is_checked_with_its_name() {
        let k = serde_json::json!({"fx": 700.0, "fy": 700.0, "cx": 600.0, "cy": 180.0});
        let ok = ValidLocalizeRequest::new(&request(serde_json::json!({"image": "", "intrinsics": k})), &defaults(), entry(), false).unwrap();
        assert_eq!((ok.search.hypotheses, ok.search.max_iterations, ok.search.prior_bound), (4, 10, None));
        let bounded = serde_json::json!({"image": "", "intrinsics": k, "prior_bound": {"rotation_deg": 30.0, "translation_m": 5.0}});
        let bounded = ValidLocalizeRequest::new(&request(bounded), &defaults(), entry(), false).unwrap();
        assert_eq!(bounded.search.prior_bound, Some(PriorBound { rotation_deg: 30.0, translation_m: 5.0 }));
        // Starts along the axis: the server's spacing and margin unless the request states them.
        assert_eq!(ok.search.axis.each_way, 0);
        let axis = serde_json::json!({"image": "", "intrinsics": k, "hypotheses": 1, "axis_starts": {"each_way": 2}});
        let axis = ValidLocalizeRequest::new(&request(axis), &defaults(), entry(), false).unwrap();
        assert_eq!((axis.search.axis, axis.search.starts()), (AxisStarts { each_way: 2, step_m: 1.25, margin: 0.005 }, 5));
        let stated = serde_json::json!({"image": "", "intrinsics": k, "hypotheses": 3, "axis_starts": {"each_way": 2, "step_m": 2.0, "margin": 0.0}});
        let stated = ValidLocalizeRequest::new(&request(stated), &defaults(), entry(), false).unwrap();
        assert_eq!((stated.search.axis, stated.search.starts()), (AxisStarts { each_way: 2, step_m: 2.0, margin: 0.0 }, 15));
        let both = serde_json::json!({"image": "", "intrinsics": k, "hypotheses": 2, "axis_starts": {"each_way": 1}, "prior_bound": {"rotation_deg": 30.0, "translation_m": 5.0}});
        let both = ValidLocalizeRequest::new(&request(both), &defaults(), entry(), false).unwrap();
        assert_eq!((both.search.starts(), both.search.prior_bound.is_some()), (6, true), "a bound and starts along the axis together");
        // No prior anywhere: the level camera at the map's origin, looking along +x.
        assert_eq!((ok.prior, ok.prior_source, ok.search.prior_margin), (Pose::level_camera_along_x(nalgebra::Vector3::zeros()), PriorSource::Default, 0.0));
        let mut far = entry();
        far.extent = crate::maps::Extent { min: [400_000.0, 5_000_000.0, 0.0], max: [400_100.0, 5_000_100.0, 10.0] };
        let e = ValidLocalizeRequest::new(&request(serde_json::json!({"image": "", "intrinsics": k})), &defaults(), far.clone(), false).unwrap_err();
        assert!(matches!(&e, LocalizeError::Invalid(m) if m.starts_with("prior_camera_from_map: map \"m\" has no initial_camera_from_map")), "{e}");
        let rig = Pose::level_camera_along_x(nalgebra::Vector3::new(400_050.0, 5_000_050.0, 2.0));
        far.metadata.initial_camera_from_map = Some(rig.to_rows());
        let ok = ValidLocalizeRequest::new(&request(serde_json::json!({"image": "", "intrinsics": k})), &defaults(), far, false).unwrap();
        assert_eq!((ok.prior_source, ok.search.prior_margin), (PriorSource::Region, 0.0), "a start the client did not state has no margin");
        let json = serde_json::json!({"image": "", "intrinsics": k, "prior_camera_from_map": rig.to_rows()});
        let stated = ValidLocalizeRequest::new(&request(json), &defaults(), entry(), false).unwrap();
        assert_eq!((stated.prior_source, stated.search.prior_margin), (PriorSource::Request, defaults().search.prior_margin));
        assert!(stated.search.prior_margin > 0.0);
        let cases = [
            (serde_json::json!({"image": "", "intrinsics": {"fx": -1.0, "fy": 700.0, "cx": 600.0, "cy": 180.0}}), "intrinsics"),
            (serde_json::json!({"image": "", "intrinsics": k, "max_iterations": 0}), "max_iterations"),
            (serde_json::json!({"image": "", "intrinsics": k, "hypotheses": 17}), "hypotheses"),
            (serde_json::json!({"image": "", "intrinsics": k, "prior_camera_from_map": [[1, 0, 0, 0, 9], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}), "row 0 must have 4 numbers"),
            (serde_json::json!({"image": "", "intrinsics": k, "prior_camera_from_map": [[1, 0, 0, 3e38], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}), "beyond"),
            (serde_json::json!({"image": "", "intrinsics": k, "radius_m": 0.5}), "radius_m"),
            (serde_json::json!({"image": "", "intrinsics": k, "prior_bound": {"rotation_deg": 0.0, "translation_m": 5.0}}), "prior_bound.rotation_deg"),
            (serde_json::json!({"image": "", "intrinsics": k, "prior_bound": {"rotation_deg": 181.0, "translation_m": 5.0}}), "prior_bound.rotation_deg"),
            (serde_json::json!({"image": "", "intrinsics": k, "prior_bound": {"rotation_deg": 30.0, "translation_m": 501.0}}), "prior_bound.translation_m"),
            (serde_json::json!({"image": "", "intrinsics": k, "axis_starts": {"each_way": 8}}), "axis_starts.each_way"),
            (serde_json::json!({"image": "", "intrinsics": k, "axis_starts": {"each_way": 1, "step_m": 0.05}}), "axis_starts.step_m"),
            (serde_json::json!({"image": "", "intrinsics": k, "axis_starts": {"each_way": 1, "margin": 1.000000001}}), "axis_starts.margin"),
            (serde_json::json!({"image": "", "intrinsics": k, "axis_starts": {"each_way": 2}}), "hypotheses × (2·each_way + 1) must be at most 16, got 4 × 5"),
        ];
        for (json, needle) in cases {
            let e = ValidLocalizeRequest::new(&request(json), &defaults(), entry(), false).unwrap_err();
            assert!(matches!(&e, LocalizeError::Invalid(m) if m.contains(needle)), "{e} should name {needle}");
        }
    }
}

#[cfg(test)]
mod tiled_tests {
    use super::*;
    use crate::maps::Extent;

    fn request(json: serde_json::Value) -> LocalizeRequest {
        serde_json::from_value(json).unwrap()
    }

    #[test]
    fn a_tiled_region_needs_a_prior_inside_its_extent_and_works_in_its_local_frame() {
        let origin = [500_000.0, 5_400_000.0, 0.0];
        let extent = Extent { min: [499_900.0, 5_399_950.0, 90.0], max: [500_200.0, 5_400_050.0, 120.0] };
        let entry = MapEntry { id: "big".into(), num_points: 5_000_000, file_bytes: 0, source_sha256: String::new(), metadata: Default::default(), origin, extent };
        let defaults = RequestDefaults { max_iterations: 10, hypotheses: 4, search: SearchTuning::default(), radius_m: 40.0 };
        let k = serde_json::json!({"fx": 700.0, "fy": 700.0, "cx": 600.0, "cy": 180.0});
        let e = ValidLocalizeRequest::new(&request(serde_json::json!({"image": "", "intrinsics": k})), &defaults, entry.clone(), true).unwrap_err();
        assert!(e.to_string().contains("needs a prior"), "{e}");
        // Camera at (500010, 5400020, 100) looking along +x (KITTI-like rig rotation).
        let c = nalgebra::Vector3::new(500_010.0, 5_400_020.0, 100.0);
        let r = nalgebra::Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0);
        let prior = Pose::from_rt(r, -(r * c));
        let json = serde_json::json!({"image": "", "intrinsics": k, "prior_camera_from_map": prior.to_rows(), "radius_m": 30.0});
        let ok = ValidLocalizeRequest::new(&request(json), &defaults, entry.clone(), true).unwrap();
        let crop = ok.crops[0];
        assert_eq!(ok.crops.len(), 1);
        assert!((crop.sensor[0] - 10.0).abs() < 1e-6 && (crop.sensor[1] - 20.0).abs() < 1e-6 && (crop.sensor[2] - 100.0).abs() < 1e-6 && crop.radius_m == 30.0, "{crop:?}");
        let local = ok.prior.camera_position_in_map();
        assert!((local - nalgebra::Vector3::new(10.0, 20.0, 100.0)).norm() < 1e-6, "{local}");
        let outside = Pose::from_rt(r, -(r * nalgebra::Vector3::new(400_000.0, 5_400_020.0, 100.0)));
        let json = serde_json::json!({"image": "", "intrinsics": k, "prior_camera_from_map": outside.to_rows()});
        let e = ValidLocalizeRequest::new(&request(json.clone()), &defaults, entry.clone(), true).unwrap_err();
        assert!(e.to_string().contains("outside map \"big\"'s extent (x 499900.00..500200.00"), "{e}");
        assert!(ValidLocalizeRequest::new(&request(json), &defaults, entry, false).is_ok(), "a whole region keeps today's rules");
    }
}
