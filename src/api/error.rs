//! The one error type of the HTTP API: every failure becomes `{"error", "error_type"}` JSON with
//! a status code that tells the client whether retrying can help.

use axum::Json;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Serialize;

use crate::maps::MapError;
use crate::serving::LocalizeError;

#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    #[error("{0}")]
    BadRequest(String),
    #[error("malformed JSON: {0}")]
    MalformedJson(String),
    #[error("{0}")]
    CorruptImage(String),
    #[error("missing or wrong bearer token")]
    Unauthorized,
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    PayloadTooLarge(String),
    #[error("{0}")]
    UnsupportedMediaType(String),
    #[error("{0}")]
    Invalid(String),
    #[error("the localization queue is full; retry later")]
    QueueFull,
    #[error("{0}")]
    NotReady(String),
    #[error("the server is shutting down")]
    Draining,
    #[error("{0}")]
    BodyTimeout(String),
    #[error("the request's deadline passed before the agent finished")]
    DeadlineExceeded,
    /// The request's own numbers went out of range inside the agent.
    #[error("{0}")]
    Numerical(String),
    #[error("{0}")]
    Internal(String),
}

/// The JSON body of every error response.
#[derive(Debug, Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct ErrorBody {
    /// Human-readable explanation.
    pub error: String,
    /// Stable machine-readable kind, e.g. `not_found`, `queue_full`, `invalid_input`.
    pub error_type: String,
}

impl ApiError {
    pub fn status(&self) -> StatusCode {
        match self {
            ApiError::BadRequest(_) | ApiError::MalformedJson(_) | ApiError::CorruptImage(_) => StatusCode::BAD_REQUEST,
            ApiError::Unauthorized => StatusCode::UNAUTHORIZED,
            ApiError::BodyTimeout(_) => StatusCode::REQUEST_TIMEOUT,
            ApiError::NotFound(_) => StatusCode::NOT_FOUND,
            ApiError::PayloadTooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
            ApiError::UnsupportedMediaType(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            ApiError::Invalid(_) | ApiError::Numerical(_) => StatusCode::UNPROCESSABLE_ENTITY,
            ApiError::QueueFull => StatusCode::TOO_MANY_REQUESTS,
            ApiError::NotReady(_) | ApiError::Draining | ApiError::DeadlineExceeded => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    pub fn error_type(&self) -> &'static str {
        match self {
            ApiError::BadRequest(_) => "bad_request",
            ApiError::MalformedJson(_) => "malformed_json",
            ApiError::CorruptImage(_) => "corrupt_image",
            ApiError::Unauthorized => "unauthorized",
            ApiError::NotFound(_) => "not_found",
            ApiError::PayloadTooLarge(_) => "payload_too_large",
            ApiError::UnsupportedMediaType(_) => "unsupported_media_type",
            ApiError::Invalid(_) => "invalid_input",
            ApiError::Numerical(_) => "numerical_failure",
            ApiError::QueueFull => "queue_full",
            ApiError::NotReady(_) => "not_ready",
            ApiError::Draining => "draining",
            ApiError::BodyTimeout(_) => "body_timeout",
            ApiError::DeadlineExceeded => "deadline_exceeded",
            ApiError::Internal(_) => "internal",
        }
    }

    /// Maps a body-extraction failure (size limit, too slow, broken stream) to our error shape.
    pub fn from_body(rejection: axum::extract::rejection::BytesRejection) -> Self {
        if super::body_deadline::is_body_deadline(&rejection) {
            let cause = std::error::Error::source(&rejection).map(|e| e.to_string()).unwrap_or_default();
            ApiError::BodyTimeout(format!("request body too slow: {cause}"))
        } else if rejection.status() == StatusCode::PAYLOAD_TOO_LARGE {
            ApiError::PayloadTooLarge(format!("request body is too large: {}", rejection.body_text()))
        } else {
            ApiError::BadRequest(format!("cannot read the request body: {}", rejection.body_text()))
        }
    }
}

impl From<MapError> for ApiError {
    fn from(e: MapError) -> Self {
        match &e {
            MapError::InvalidId(_) => ApiError::BadRequest(e.to_string()),
            MapError::NotFound(_) => ApiError::NotFound(e.to_string()),
            MapError::BadCloud(_) | MapError::BadMetadata(_) | MapError::BadOption(_) => ApiError::Invalid(e.to_string()),
            MapError::Unsupported(_) => ApiError::UnsupportedMediaType(e.to_string()),
            MapError::TooLarge(_) => ApiError::PayloadTooLarge(e.to_string()),
            MapError::Io(_) | MapError::Inference(_) => ApiError::Internal(e.to_string()),
        }
    }
}

impl From<LocalizeError> for ApiError {
    fn from(e: LocalizeError) -> Self {
        match e {
            LocalizeError::BadRequest(m) => ApiError::BadRequest(m),
            LocalizeError::CorruptImage(m) => ApiError::CorruptImage(m),
            LocalizeError::PayloadTooLarge(m) => ApiError::PayloadTooLarge(m),
            LocalizeError::UnsupportedMediaType(m) => ApiError::UnsupportedMediaType(m),
            LocalizeError::Invalid(m) => ApiError::Invalid(m),
            LocalizeError::Numerical(_) => ApiError::Numerical(e.to_string()),
            LocalizeError::Map(m) => m.into(),
            LocalizeError::QueueFull => ApiError::QueueFull,
            LocalizeError::NotReady(m) => ApiError::NotReady(m),
            LocalizeError::Draining => ApiError::Draining,
            LocalizeError::DeadlineExceeded => ApiError::DeadlineExceeded,
            LocalizeError::Internal(m) => ApiError::Internal(m),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        if status.is_server_error() && !matches!(self, ApiError::NotReady(_) | ApiError::Draining) {
            tracing::warn!(error_type = self.error_type(), "{self}");
        }
        let body = ErrorBody { error: self.to_string(), error_type: self.error_type().to_string() };
        let mut response = (status, Json(body)).into_response();
        if matches!(self, ApiError::QueueFull | ApiError::NotReady(_) | ApiError::Draining) {
            response.headers_mut().insert(axum::http::header::RETRY_AFTER, axum::http::HeaderValue::from_static("1"));
        }
        // These refusals come before the request body is read: the connection cannot carry
        // another request after an unread body, so the client is told not to reuse it.
        if matches!(self, ApiError::QueueFull | ApiError::NotReady(_) | ApiError::Draining | ApiError::Unauthorized) {
            response.headers_mut().insert(axum::http::header::CONNECTION, axum::http::HeaderValue::from_static("close"));
        }
        response
    }
}
