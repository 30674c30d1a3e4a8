//! How a request body must arrive, so that a client that announces a body and then stalls or
//! drips it cannot hold a connection for ever, and one without a valid credential cannot make
//! the server buffer a large one (issue 52, items 3 and 6).
//!
//! - Every body must keep up `http.body_min_bytes_per_s` on average once a grace period (the
//!   header timeout) has passed: `t` after the head, at least `rate × (t − grace)` bytes must
//!   have arrived (408 `body_timeout`). Before this, a handler waiting for a body counted as
//!   work, which the idle timeout never interrupts.
//! - A request without a valid credential (the open routes: login, the pages) may send at most
//!   [`ANONYMOUS_BODY_BYTES`]: refused before reading by its `Content-Length` (413
//!   `body_too_large`, field `content-length`), or, chunked, as soon as it has sent more (413,
//!   field `body`); and the whole body must arrive within the header timeout (408).

use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::Request;
use axum::http::{header, HeaderValue};
use axum::response::{IntoResponse, Response};
use axum::BoxError;
use hyper::body::{Frame, SizeHint};
use tokio::time::{Instant, Sleep};

use super::admission::ConnectionContext;
use crate::api::{ErrorKind, ServiceError};

/// The largest body a request without a valid credential may send: a login is
/// `{"token": "…"}`.
pub const ANONYMOUS_BODY_BYTES: u64 = 4096;
/// An unauthenticated request's body deadline when the listener left no context (unit tests).
const ANONYMOUS_DEADLINE: Duration = Duration::from_secs(10);

/// Why a body was cut off.
#[derive(Debug, thiserror::Error)]
pub enum BodyRefusal {
    #[error(
        "the request body arrived slower than {rate} bytes/s ({received} bytes in {:.1} s)",
        elapsed.as_secs_f64()
    )]
    TooSlow {
        rate: u64,
        received: u64,
        elapsed: Duration,
    },
    #[error(
        "the request body did not arrive within {} ms: a request without a valid token must \
         send its body with its head",
        .0.as_millis()
    )]
    Late(Duration),
    #[error("the request body is larger than {0} bytes, the most a request without a valid token may send")]
    TooLarge(u64),
}

impl BodyRefusal {
    pub(super) fn to_service_error(&self) -> ServiceError {
        let (kind, code) = match self {
            Self::TooSlow { .. } | Self::Late(_) => (ErrorKind::RequestTimeout, "body_timeout"),
            Self::TooLarge(_) => (ErrorKind::TooLarge, "body_too_large"),
        };
        ServiceError::new(kind, code, self.to_string()).at("body")
    }

    /// The refusal somewhere in the chain of `error`'s sources (axum wraps body errors).
    pub(super) fn find<'a>(error: &'a (dyn std::error::Error + 'static)) -> Option<&'a Self> {
        let mut next = Some(error);
        while let Some(error) = next {
            if let Some(refusal) = error.downcast_ref::<Self>() {
                return Some(refusal);
            }
            next = error.source();
        }
        None
    }
}

/// The rules one body is held to.
#[derive(Clone, Copy, Debug)]
pub(super) struct Pace {
    /// Bytes per second on average after `grace` (0: no minimum).
    pub min_rate: u64,
    pub grace: Duration,
    /// The whole body must have arrived within this.
    pub deadline: Option<Duration>,
    pub max_bytes: Option<u64>,
}

/// A request body held to a [`Pace`]: an error frame once it falls behind.
pub(super) struct PacedBody<B> {
    inner: B,
    pace: Pace,
    started: Instant,
    received: u64,
    timer: Pin<Box<Sleep>>,
}

impl<B> PacedBody<B> {
    pub(super) fn new(inner: B, pace: Pace) -> Self {
        let started = Instant::now();
        Self {
            inner,
            pace,
            started,
            received: 0,
            timer: Box::pin(tokio::time::sleep_until(started)),
        }
    }

    /// When the body falls behind unless more arrives, and what it is refused with then.
    fn due(&self) -> Option<(Instant, BodyRefusal)> {
        let late = self
            .pace
            .deadline
            .map(|d| (self.started + d, BodyRefusal::Late(d)));
        let slow = (self.pace.min_rate > 0).then(|| {
            let allowed = Duration::from_secs_f64(self.received as f64 / self.pace.min_rate as f64);
            let at = self.started + self.pace.grace + allowed;
            let refusal = BodyRefusal::TooSlow {
                rate: self.pace.min_rate,
                received: self.received,
                elapsed: at - self.started,
            };
            (at, refusal)
        });
        match (late, slow) {
            (Some(l), Some(s)) => Some(if l.0 <= s.0 { l } else { s }),
            (l, s) => l.or(s),
        }
    }

    /// The refusal, when the body is behind now; otherwise the timer is set to wake the reader
    /// when it would be.
    fn behind(&mut self, cx: &mut Context<'_>) -> Option<BodyRefusal> {
        let (at, refusal) = self.due()?;
        if Instant::now() >= at {
            return Some(refusal);
        }
        self.timer.as_mut().reset(at);
        self.timer.as_mut().poll(cx).is_ready().then_some(refusal)
    }
}

impl<B> hyper::body::Body for PacedBody<B>
where
    B: hyper::body::Body<Data = Bytes> + Unpin,
    B::Error: Into<BoxError>,
{
    type Data = Bytes;
    type Error = BoxError;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, BoxError>>> {
        let this = self.get_mut();
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref() {
                    this.received += data.len() as u64;
                }
                if let Some(max) = this.pace.max_bytes.filter(|max| this.received > *max) {
                    return Poll::Ready(Some(Err(BodyRefusal::TooLarge(max).into())));
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Ready(Some(Err(e))) => Poll::Ready(Some(Err(e.into()))),
            Poll::Ready(None) => Poll::Ready(None),
            Poll::Pending => match this.behind(cx) {
                Some(refusal) => Poll::Ready(Some(Err(refusal.into()))),
                None => Poll::Pending,
            },
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// Holds the body of a request without a valid credential to the limits above; a response
/// instead when its `Content-Length` already exceeds them.
// A Response is large, but the refusal is the rare path and is sent as it is.
#[allow(clippy::result_large_err)]
pub(super) fn limit_anonymous(request: Request) -> Result<Request, Response> {
    let length = request
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok());
    if let Some(length) = length.filter(|l| *l > ANONYMOUS_BODY_BYTES) {
        let error = ServiceError::new(
            ErrorKind::TooLarge,
            "body_too_large",
            format!(
                "Content-Length {length} is more than the {ANONYMOUS_BODY_BYTES} bytes a request \
                 without a valid token may send"
            ),
        )
        .at("content-length");
        let mut response = super::HttpError::from(error).into_response();
        // The body is never read: the connection cannot carry another request.
        response
            .headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
        return Err(response);
    }
    let deadline = request
        .extensions()
        .get::<ConnectionContext>()
        .map_or(ANONYMOUS_DEADLINE, |c| c.header_timeout);
    let pace = Pace {
        min_rate: 0,
        grace: Duration::ZERO,
        deadline: Some(deadline),
        max_bytes: Some(ANONYMOUS_BODY_BYTES),
    };
    Ok(request.map(|body| Body::new(PacedBody::new(body, pace))))
}

#[cfg(test)]
mod tests {
    use futures_util::StreamExt;
    use hyper::body::Body as _;

    use super::*;

    /// Reads a body to its end, as axum's `Bytes` extractor does; the bytes read.
    async fn collect(mut body: Body) -> Result<u64, BoxError> {
        let mut total = 0;
        while let Some(frame) = std::future::poll_fn(|cx| Pin::new(&mut body).poll_frame(cx)).await
        {
            total += frame?.data_ref().map_or(0, |d| d.len() as u64);
        }
        Ok(total)
    }

    /// A body that sends `bytes` and then nothing, never ending.
    fn stalled_after(bytes: &'static [u8]) -> Body {
        let first = futures_util::stream::iter([Ok::<_, std::io::Error>(Bytes::from(bytes))]);
        Body::from_stream(first.chain(futures_util::stream::pending()))
    }

    #[tokio::test]
    async fn a_stalled_body_is_cut_off_after_the_grace_at_the_rate() {
        let pace = Pace {
            min_rate: 1000,
            grace: Duration::from_millis(200),
            deadline: None,
            max_bytes: None,
        };
        let body = Body::new(PacedBody::new(stalled_after(&[0; 300]), pace));
        let started = Instant::now();
        let error = collect(body).await.unwrap_err();
        // 300 bytes at 1000 bytes/s buy 0.3 s beyond the 0.2 s grace.
        let took = started.elapsed();
        assert!(
            took >= Duration::from_millis(500) && took < Duration::from_secs(2),
            "{took:?}"
        );
        let refusal = BodyRefusal::find(&*error).unwrap();
        assert_eq!(refusal.to_service_error().body.code, "body_timeout");
    }

    #[tokio::test]
    async fn an_anonymous_body_has_a_deadline_and_a_size() {
        let pace = Pace {
            min_rate: 0,
            grace: Duration::ZERO,
            deadline: Some(Duration::from_millis(100)),
            max_bytes: Some(10),
        };
        let late = Body::new(PacedBody::new(stalled_after(b"{}"), pace));
        let error = collect(late).await.unwrap_err();
        assert!(matches!(
            BodyRefusal::find(&*error),
            Some(BodyRefusal::Late(_))
        ));
        let large = Body::new(PacedBody::new(stalled_after(&[b' '; 11]), pace));
        let error = collect(large).await.unwrap_err();
        let refusal = BodyRefusal::find(&*error).unwrap();
        assert_eq!(refusal.to_service_error().body.status, 413);
    }
}
