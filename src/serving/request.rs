//! The localize request as it arrives (`LocalizeRequest`, also the OpenAPI schema) and as the
//! rest of the server sees it (`ValidLocalizeRequest`): built once, from the wire request, the
//! server's limits and the map entry, so every rule lives here and nowhere else.

use serde::Deserialize;
use utoipa::ToSchema;

use crate::agent::search::{MAX_HYPOTHESES, MAX_ITERATIONS, SearchConfig, SearchTuning};
use crate::geometry::pose::Matrix4x4;
use crate::geometry::{Intrinsics, Pose};
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

#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct LocalizeRequest {
    /// Base64 (standard alphabet) JPEG or PNG bytes.
    #[schema(min_length = 1, format = Byte)]
    pub image: String,
    /// Pinhole intrinsics of `image` in pixels.
    pub intrinsics: IntrinsicsBody,
    /// Starting pose (camera_from_map); defaults to the map's `initial_camera_from_map`, then to
    /// identity.
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
}

/// What the server fills in when a request leaves it out.
#[derive(Debug, Clone, Copy)]
pub struct RequestDefaults {
    pub max_iterations: u32,
    pub hypotheses: u32,
    pub search: SearchTuning,
}

/// A localize request every later stage can trust.
#[derive(Debug, Clone)]
pub struct ValidLocalizeRequest {
    pub map: MapEntry,
    pub intrinsics: Intrinsics,
    pub prior: Pose,
    pub search: SearchConfig,
}

impl ValidLocalizeRequest {
    /// Checks the request's numbers against the limits (422 `invalid_input` naming the field).
    pub fn new(request: &LocalizeRequest, defaults: &RequestDefaults, map: MapEntry) -> Result<Self, LocalizeError> {
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
        let prior = match &request.prior_camera_from_map {
            Some(m) => m.pose().map_err(|e| invalid("prior_camera_from_map", e))?,
            None => map.metadata.initial_pose().unwrap_or_else(Pose::identity),
        };
        let search = defaults.search.search(hypotheses, max_iterations as usize);
        Ok(Self { map, intrinsics, prior, search })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(json: serde_json::Value) -> LocalizeRequest {
        serde_json::from_value(json).unwrap()
    }

    fn entry() -> MapEntry {
        MapEntry { id: "m".into(), num_points: 1, file_bytes: 16, source_sha256: String::new(), metadata: Default::default() }
    }

    const DEFAULTS: RequestDefaults = RequestDefaults { max_iterations: 10, hypotheses: 4, search: SearchTuning { narrow_after: 0, merge_duplicates: true } };

    #[test]
    fn every_field_is_checked_with_its_name() {
        let k = serde_json::json!({"fx": 700.0, "fy": 700.0, "cx": 600.0, "cy": 180.0});
        let ok = ValidLocalizeRequest::new(&request(serde_json::json!({"image": "", "intrinsics": k})), &DEFAULTS, entry()).unwrap();
        assert_eq!((ok.search.hypotheses, ok.search.max_iterations), (4, 10));
        assert_eq!(ok.prior, Pose::identity());
        let cases = [
            (serde_json::json!({"image": "", "intrinsics": {"fx": -1.0, "fy": 700.0, "cx": 600.0, "cy": 180.0}}), "intrinsics"),
            (serde_json::json!({"image": "", "intrinsics": k, "max_iterations": 0}), "max_iterations"),
            (serde_json::json!({"image": "", "intrinsics": k, "hypotheses": 17}), "hypotheses"),
            (serde_json::json!({"image": "", "intrinsics": k, "prior_camera_from_map": [[1, 0, 0, 0, 9], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}), "row 0 must have 4 numbers"),
            (serde_json::json!({"image": "", "intrinsics": k, "prior_camera_from_map": [[1, 0, 0, 3e38], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}), "beyond"),
        ];
        for (json, needle) in cases {
            let e = ValidLocalizeRequest::new(&request(json), &DEFAULTS, entry()).unwrap_err();
            assert!(matches!(&e, LocalizeError::Invalid(m) if m.contains(needle)), "{e} should name {needle}");
        }
    }
}
