//! The web page for people (`GET /`): static HTML, JavaScript and CSS from `web/`, embedded in
//! the binary at build time (no npm, no build step, nothing fetched from outside: the
//! Content-Security-Policy allows this origin only), plus the demo localize request
//! (`examples/localize-demo.json`, for the bundled `demo` region) so the page can run it. The
//! page talks to the public API only (`/v1/maps`, `/v1/maps/{id}/points`, `.../localize`, map
//! upload and delete); nothing here is part of the API contract.

use axum::extract::Path;
use axum::extract::rejection::PathRejection;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};

use super::error::ApiError;

const INDEX_HTML: &str = include_str!("../../web/index.html");
const APP_JS: &str = include_str!("../../web/app.js");
const STYLE_CSS: &str = include_str!("../../web/style.css");
const DEMO_JSON: &str = include_str!("../../examples/localize-demo.json");

/// Only this origin: scripts, styles, fetches; images also from `data:`/`blob:` URLs (the
/// dropped image is shown from one).
const CSP: &str = "default-src 'self'; img-src 'self' data: blob:; script-src 'self'; style-src 'self'; \
connect-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'; form-action 'none'";

fn static_file(content_type: &'static str, body: &'static str) -> Response {
    let mut response = ([(header::CONTENT_TYPE, content_type)], body).into_response();
    let h = response.headers_mut();
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    h.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CSP));
    response
}

/// `GET /`: the page.
pub async fn index() -> Response {
    static_file("text/html; charset=utf-8", INDEX_HTML)
}

/// `GET /ui/{asset}`: the page's script and style sheet, and `demo.json` (the demo localize
/// request: a base64 JPEG, its intrinsics and `max_iterations`, for the `demo` region).
pub async fn asset(name: Result<Path<String>, PathRejection>) -> Response {
    let name = match name {
        Ok(Path(name)) => name,
        Err(e) => return ApiError::BadRequest(format!("asset name: {}", e.body_text())).into_response(),
    };
    match name.as_str() {
        "app.js" => static_file("text/javascript; charset=utf-8", APP_JS),
        "style.css" => static_file("text/css; charset=utf-8", STYLE_CSS),
        "demo.json" => static_file("application/json", DEMO_JSON),
        _ => ApiError::NotFound(format!("no such page asset: {name:?}")).into_response(),
    }
}
