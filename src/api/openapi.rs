//! The OpenAPI document, generated from the handlers and types; `cmr-agent print-schema` prints
//! it and a test keeps `openapi/openapi.json` in step.

use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi};

use super::error::ErrorBody;
use super::routes;
use super::types::*;
use crate::maps::MapMetadata;

#[derive(OpenApi)]
#[openapi(
    info(title = "cmr-agent", description = "Localize a camera image inside a pre-built LiDAR map (CMR-Agent)."),
    paths(
        routes::health, routes::ready, routes::metrics, routes::info,
        routes::list_maps, routes::get_map, routes::map_points, routes::put_map, routes::put_metadata, routes::delete_map,
        routes::localize, super::overlay::overlay,
    ),
    components(schemas(ErrorBody, crate::serving::LocalizeRequest, crate::serving::Matrix4x4, LocalizeResponse, super::overlay::OverlayRequest, MapList, MapSummary, MapMetadata, RegisterResponse, Info)),
    modifiers(&BearerAuth),
)]
pub struct ApiDoc;

struct BearerAuth;

impl Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme("bearer", SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()));
    }
}

/// The document as pretty JSON with a trailing newline (the committed file's exact bytes).
pub fn schema_json() -> String {
    let mut doc = ApiDoc::openapi();
    // The version comes from Cargo.toml; keep it so clients can tell documents apart.
    doc.info.version = env!("CARGO_PKG_VERSION").to_string();
    let mut text = doc.to_pretty_json().expect("OpenAPI document serialises");
    text.push('\n');
    text
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::{Value, json};

    /// utoipa's bound attributes take literals only; this pins each literal the document states
    /// to the constant the server enforces, so the two cannot drift apart.
    #[test]
    fn stated_bounds_are_the_enforced_ones() {
        let doc: Value = serde_json::from_str(&schema_json()).unwrap();
        let param = |path: &str, method: &str, name: &str| -> Value {
            let params = doc["paths"][path][method]["parameters"].as_array().unwrap_or_else(|| panic!("{method} {path} has parameters"));
            let p = params.iter().find(|p| p["name"] == name).unwrap_or_else(|| panic!("{method} {path} has {name}"));
            assert_eq!(p["in"], if name == "id" { "path" } else if name == "Content-Encoding" { "header" } else { "query" }, "{method} {path} {name}");
            p["schema"].clone()
        };
        let bounds = |s: &Value| (s["minimum"].as_f64(), s["maximum"].as_f64());
        let iterations = (Some(1.0), Some(crate::agent::search::MAX_ITERATIONS as f64));
        let hypotheses = (Some(1.0), Some(crate::agent::search::MAX_HYPOTHESES as f64));
        let radius = (Some(*crate::serving::request::RADIUS_RANGE_M.start()), Some(*crate::serving::request::RADIUS_RANGE_M.end()));
        for path in ["/v1/maps/{id}/localize", "/v1/maps/{id}/overlay"] {
            assert_eq!(bounds(&param(path, "post", "max_iterations")), iterations);
            assert_eq!(bounds(&param(path, "post", "hypotheses")), hypotheses);
            assert_eq!(bounds(&param(path, "post", "radius_m")), radius);
            assert_eq!(param(path, "post", "fx")["exclusiveMinimum"], json!(0));
        }
        for body in ["LocalizeRequest", "OverlayRequest"] {
            let props = &doc["components"]["schemas"][body]["properties"];
            assert_eq!(bounds(&props["max_iterations"]), iterations, "{body}");
            assert_eq!(bounds(&props["hypotheses"]), hypotheses, "{body}");
            assert_eq!(bounds(&props["radius_m"]), radius, "{body}");
        }
        let axis = &doc["components"]["schemas"]["AxisStartsBody"]["properties"];
        assert_eq!(bounds(&axis["each_way"]), (Some(0.0), Some(crate::agent::search::MAX_AXIS_STARTS as f64)));
        let step = &crate::agent::search::AXIS_STEP_RANGE_M;
        assert_eq!(bounds(&axis["step_m"]), (Some(*step.start()), Some(*step.end())));
        assert_eq!(bounds(&axis["margin"]), (Some(0.0), Some(1.0)));
        let voxel = param("/v1/maps/{id}", "put", "voxel_m");
        assert_eq!(bounds(&voxel), (Some(crate::geometry::voxel::MIN_VOXEL_M), Some(crate::geometry::voxel::MAX_VOXEL_M)));
        let max = param("/v1/maps/{id}/points", "get", "max");
        assert_eq!(bounds(&max), (Some(1.0), Some(super::routes::MAX_POINTS_QUERY as f64)));
        let chars = crate::maps::store::MAX_DESCRIPTION_CHARS as u64;
        assert_eq!(param("/v1/maps/{id}", "put", "description")["maxLength"].as_u64(), Some(chars));
        assert_eq!(doc["components"]["schemas"]["MapMetadata"]["properties"]["description"]["maxLength"].as_u64(), Some(chars));
        for name in ["kitti_bin", "kitti", "bin", "pcd", "ply", "las", "laz"] {
            assert!(name.parse::<crate::maps::formats::CloudFormat>().is_ok(), "{name} is a format the pattern admits");
        }
        assert!("xyz".parse::<crate::maps::formats::CloudFormat>().is_err());
    }

    /// The matrix schema's per-entry bounds are `Pose::from_matrix`'s: at each bound accepted,
    /// just past it refused.
    #[test]
    fn matrix_entry_bounds_are_the_pose_checks() {
        use crate::geometry::Pose;
        use crate::geometry::pose::entry_bounds;
        let doc: Value = serde_json::from_str(&schema_json()).unwrap();
        let rows = doc["components"]["schemas"]["Matrix4x4"]["prefixItems"].as_array().unwrap();
        assert_eq!(rows.len(), 4);
        for (r, row) in rows.iter().enumerate() {
            for (c, entry) in row["prefixItems"].as_array().unwrap().iter().enumerate() {
                let (low, high) = entry_bounds(r, c);
                assert_eq!((entry["minimum"].as_f64(), entry["maximum"].as_f64()), (Some(low), Some(high)), "entry ({r}, {c})");
            }
        }
        // Translation and last row alone: the other entries keep the identity rotation valid.
        for (r, c) in [(0, 3), (1, 3), (2, 3), (3, 0), (3, 3)] {
            let (low, high) = entry_bounds(r, c);
            for (v, ok) in [(low, true), (high, true), (f64::from_bits(high.to_bits() + 1), false), (-f64::from_bits(high.abs().to_bits() + 1), false)] {
                let mut m = Pose::identity().to_rows();
                m[r][c] = v;
                if r == 3 && c == 3 && v < 0.0 {
                    continue;
                }
                let accepted = Pose::from_matrix(&m).is_ok() || (c == 3 && r < 3 && Pose::from_matrix(&m).unwrap_err().contains("camera position"));
                assert_eq!(accepted, ok, "entry ({r}, {c}) = {v}");
            }
        }
    }
}
