//! Serving: everything between a transport (HTTP, the CLI) and the agent's maths. The
//! [`Localizer`] owns the localize path (admission, validation, decode, map preparation,
//! submission, deadline); the [`Scheduler`] runs the agent's step loop on worker threads with
//! requests batched at step boundaries; [`Lifecycle`] says whether the server is ready or
//! draining.
//!
//! Layering: `api` → `serving` → `agent` → `maps` → `model` → `geometry`; nothing here knows
//! about HTTP.

pub mod decode;
pub mod error;
pub mod lifecycle;
pub mod localizer;
pub mod request;
pub mod scheduler;

pub use decode::{ImageLimits, ImagePayload};
pub use error::LocalizeError;
pub use lifecycle::Lifecycle;
pub use localizer::{Admission, Localized, Localizer, LocalizerConfig, PictureInput};
pub use crate::geometry::pose::Matrix4x4;
pub use request::{IntrinsicsBody, LocalizeRequest, PriorSource, RequestDefaults, ValidLocalizeRequest};
pub use scheduler::{Scheduler, SchedulerConfig};
