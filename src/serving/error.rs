//! Why a localization was refused or failed, in words a client can act on. The HTTP API maps each
//! variant to one status code and `error_type` (`api::error`); the CLI prints the message.

use crate::agent::StepError;
use crate::maps::MapError;

use super::scheduler::{JobError, SubmitError};

#[derive(Debug, Clone, thiserror::Error)]
pub enum LocalizeError {
    /// Undecodable input (base64, query string).
    #[error("{0}")]
    BadRequest(String),
    #[error("{0}")]
    CorruptImage(String),
    #[error("{0}")]
    PayloadTooLarge(String),
    #[error("{0}")]
    UnsupportedMediaType(String),
    /// Well-formed but unacceptable values (intrinsics, prior, limits, aspect ratio).
    #[error("{0}")]
    Invalid(String),
    /// The request's numbers went out of range inside the agent (its own prior or image).
    #[error("the agent cannot localize this request: {0}")]
    Numerical(String),
    #[error(transparent)]
    Map(#[from] MapError),
    #[error("the localization queue is full; retry later")]
    QueueFull,
    #[error("{0}")]
    NotReady(String),
    #[error("the server is shutting down")]
    Draining,
    #[error("the request's deadline passed before the agent finished")]
    DeadlineExceeded,
    #[error("{0}")]
    Internal(String),
}

impl From<SubmitError> for LocalizeError {
    fn from(e: SubmitError) -> Self {
        match e {
            SubmitError::QueueFull => LocalizeError::QueueFull,
            SubmitError::Draining => LocalizeError::Draining,
        }
    }
}

impl From<JobError> for LocalizeError {
    fn from(e: JobError) -> Self {
        match e {
            JobError::DeadlineExceeded => LocalizeError::DeadlineExceeded,
            JobError::Step(StepError::NonFinite(m)) => LocalizeError::Numerical(m),
            JobError::Step(StepError::Inference(m)) => LocalizeError::Internal(format!("inference failed: {m}")),
        }
    }
}
