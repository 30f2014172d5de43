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
