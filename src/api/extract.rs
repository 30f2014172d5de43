//! Extractors whose rejections speak the API's error shape (`{error, error_type}` JSON) instead
//! of axum's plain text.

use std::sync::Arc;

use axum::extract::{FromRequestParts, Path};
use axum::http::request::Parts;
use utoipa::IntoParams;

use super::AppState;
use super::error::ApiError;

/// The `{id}` path segment of the map routes, percent-decoded. An undecodable segment is a 400
/// `bad_request`; the id's own rules are checked where it is used (`maps::validate_id`).
pub struct MapId(pub String);

impl<S: Send + Sync> FromRequestParts<S> for MapId {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        match Path::<String>::from_request_parts(parts, state).await {
            Ok(Path(id)) => Ok(MapId(id)),
            Err(e) => Err(ApiError::BadRequest(format!("map id: {}", e.body_text()))),
        }
    }
}

/// The bearer-token check of map management, as an extractor: it runs on the request head,
/// before the body extractor, so an unauthenticated upload is refused (401) without reading or
/// buffering its body (and a client that sent `Expect: 100-continue` never sends it).
pub struct Admin;

impl axum::extract::FromRequestParts<Arc<AppState>> for Admin {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut axum::http::request::Parts, st: &Arc<AppState>) -> Result<Self, ApiError> {
        st.authorize(&parts.headers).map(|()| Admin)
    }
}

/// The map id as the OpenAPI document describes it.
#[derive(IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
pub struct MapIdParam {
    /// Map region id: 1-64 characters of a-z, 0-9, '_' or '-', starting with a letter or digit.
    #[param(pattern = r"^[a-z0-9][a-z0-9_-]{0,63}$", min_length = 1, max_length = 64)]
    id: String,
}
