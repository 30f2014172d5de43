//! A deadline on receiving the whole request body.
//!
//! Without one, a client that sends a map upload one byte at a time holds a connection and a
//! buffer for as long as it likes. tower-http's `RequestBodyTimeoutLayer` only bounds the gap
//! between two chunks, which such a client never exceeds, so this layer bounds the total: the
//! clock starts when the handler first reads the body. Reading fails with [`BodyDeadlineExceeded`],
//! which `ApiError::from_body` turns into 408.

use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::Request;
use axum::middleware::Next;
use axum::response::Response;
use http_body::Frame;
use tokio::time::{Instant, Sleep};

/// The error a body yields once its deadline has passed.
#[derive(Debug, thiserror::Error)]
#[error("the request body was not received within {0:?}")]
pub struct BodyDeadlineExceeded(pub Duration);

pin_project_lite::pin_project! {
    struct DeadlineBody {
        #[pin]
        inner: Body,
        #[pin]
        sleep: Option<Sleep>,
        limit: Duration,
    }
}

impl http_body::Body for DeadlineBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        let mut this = self.project();
        if this.sleep.is_none() {
            this.sleep.set(Some(tokio::time::sleep_until(Instant::now() + *this.limit)));
        }
        if let Some(sleep) = this.sleep.as_mut().as_pin_mut() {
            if sleep.poll(cx).is_ready() {
                return Poll::Ready(Some(Err(axum::Error::new(BodyDeadlineExceeded(*this.limit)))));
            }
        }
        this.inner.poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// Middleware (`axum::middleware::from_fn_with_state`) that puts `limit` on every request body.
pub async fn limit_body_time(
    axum::extract::State(limit): axum::extract::State<Duration>,
    request: Request,
    next: Next,
) -> Response {
    let (parts, body) = request.into_parts();
    let body = Body::new(DeadlineBody { inner: body, sleep: None, limit });
    next.run(Request::from_parts(parts, body)).await
}

/// Whether an error (or anything in its source chain) is a passed body deadline.
pub fn is_body_deadline(error: &(dyn std::error::Error + 'static)) -> bool {
    has_source::<BodyDeadlineExceeded>(error)
}

/// Whether `error` or anything in its source chain is an `E`.
pub fn has_source<E: std::error::Error + 'static>(error: &(dyn std::error::Error + 'static)) -> bool {
    let mut current = Some(error);
    while let Some(e) = current {
        if e.is::<E>() {
            return true;
        }
        current = e.source();
    }
    false
}
