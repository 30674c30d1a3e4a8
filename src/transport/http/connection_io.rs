//! The socket under every HTTP connection. It records when bytes last moved and whether a
//! request is being answered (for the idle timeout), holds the connection's slot until the
//! socket closes (also after a WebSocket upgrade, when hyper hands the socket on), and turns
//! hyper's own bodiless answers to requests it cannot parse (400, 414, 431) into the JSON error
//! body every other refusal has.
//!
//! hyper writes those answers itself, before any service sees a request, and offers no hook to
//! give them a body; recognising the exact head it writes (status 400/414/431 and
//! `content-length: 0`, a head our router never produces: its errors all carry JSON) is the one
//! place they can be changed.

use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{ready, Context, Poll};
use std::time::{Duration, Instant};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;

use super::admission::SlotCell;
use crate::api::ErrorKind;
use crate::api::ServiceError;

/// Largest request head (request line and headers) hyper buffers; beyond it, 431. Large enough
/// for hyper's own URI limit (65 534 bytes, then 414) to be reachable.
pub(super) const MAX_HEAD_BYTES: usize = 128 << 10;

/// When bytes last moved on a connection, and how many of its requests are being answered.
pub(super) struct Activity {
    opened: Instant,
    last_moved_ms: AtomicU64,
    answering: AtomicUsize,
}

impl Activity {
    pub(super) fn new() -> Arc<Self> {
        Arc::new(Self {
            opened: Instant::now(),
            last_moved_ms: AtomicU64::new(0),
            answering: AtomicUsize::new(0),
        })
    }

    fn touch(&self) {
        let now = self.opened.elapsed().as_millis() as u64;
        self.last_moved_ms.store(now, Ordering::Relaxed);
    }

    /// How long no byte has moved either way.
    pub(super) fn quiet_for(&self) -> Duration {
        let now = self.opened.elapsed().as_millis() as u64;
        Duration::from_millis(now.saturating_sub(self.last_moved_ms.load(Ordering::Relaxed)))
    }

    /// Whether a handler is working on a request (a long `?wait=true` solve moves no bytes).
    pub(super) fn answering(&self) -> bool {
        self.answering.load(Ordering::Relaxed) > 0
    }

    /// Marks a request as being answered until the returned guard is dropped.
    pub(super) fn begin_answer(self: &Arc<Self>) -> Answering {
        self.answering.fetch_add(1, Ordering::Relaxed);
        Answering(Arc::clone(self))
    }
}

pub(super) struct Answering(Arc<Activity>);

impl Drop for Answering {
    fn drop(&mut self) {
        self.0.answering.fetch_sub(1, Ordering::Relaxed);
    }
}

/// A TCP stream as hyper sees it (see the module documentation).
pub(super) struct ConnectionIo {
    stream: TcpStream,
    activity: Arc<Activity>,
    /// The connection's place under the cap, released when the socket is dropped (or emptied
    /// earlier when a newcomer takes it over).
    _slot: Option<Arc<SlotCell>>,
    /// A JSON answer replacing hyper's bodiless one, and how much of it is written.
    replacement: Option<(Vec<u8>, usize)>,
}

impl ConnectionIo {
    pub(super) fn new(
        stream: TcpStream,
        activity: Arc<Activity>,
        slot: Option<Arc<SlotCell>>,
    ) -> Self {
        Self {
            stream,
            activity,
            _slot: slot,
            replacement: None,
        }
    }

    pub(super) fn activity(&self) -> Arc<Activity> {
        Arc::clone(&self.activity)
    }

    /// Writes what is left of a replacement answer.
    fn poll_replacement(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        while let Some((bytes, written)) = &mut self.replacement {
            if *written == bytes.len() {
                self.replacement = None;
                break;
            }
            let n = ready!(Pin::new(&mut self.stream).poll_write(cx, &bytes[*written..]))?;
            if n == 0 {
                return Poll::Ready(Err(io::ErrorKind::WriteZero.into()));
            }
            *written += n;
            self.activity.touch();
        }
        Poll::Ready(Ok(()))
    }

    /// Takes `buf` in place of hyper's parse-error head when it is one: the JSON answer is
    /// written instead (now or on the next write, flush or shutdown).
    fn replace(&mut self, cx: &mut Context<'_>, buf: &[u8]) -> Option<Poll<io::Result<usize>>> {
        let status = parse_error_status(buf)?;
        self.replacement = Some((parse_error_answer(status), 0));
        Some(match self.poll_replacement(cx) {
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
            // Accepted either way: what is not written yet goes out on the next flush.
            _ => Poll::Ready(Ok(buf.len())),
        })
    }
}

/// The status of hyper's automatic answer to an unparseable request, if `buf` is one.
fn parse_error_status(buf: &[u8]) -> Option<u16> {
    let rest = buf.strip_prefix(b"HTTP/1.1 ")?;
    let status = match rest.get(..4)? {
        b"400 " => 400,
        b"414 " => 414,
        b"431 " => 431,
        _ => return None,
    };
    let head = std::str::from_utf8(buf).ok()?.to_ascii_lowercase();
    (head.ends_with("\r\n\r\n") && head.contains("\r\ncontent-length: 0\r\n")).then_some(status)
}

/// The whole answer (head and JSON error body) for a request hyper could not parse.
fn parse_error_answer(status: u16) -> Vec<u8> {
    let error = match status {
        414 => ServiceError::new(
            ErrorKind::UriTooLong,
            "uri_too_long",
            "the request target is longer than 65534 bytes",
        )
        .at("uri"),
        431 => ServiceError::new(
            ErrorKind::HeadersTooLarge,
            "headers_too_large",
            format!(
                "the request head (request line and headers) is larger than {MAX_HEAD_BYTES} \
                 bytes or has more than 100 headers"
            ),
        )
        .at("headers"),
        _ => ServiceError::new(
            ErrorKind::BadRequest,
            "malformed_request",
            "the request line or a header is not valid HTTP/1.1",
        ),
    };
    crate::runtime::metrics::count_rejection(&error.body);
    let body = serde_json::json!({ "error": error.body }).to_string();
    let reason = axum::http::StatusCode::from_u16(status)
        .ok()
        .and_then(|s| s.canonical_reason())
        .unwrap_or("Bad Request");
    format!(
        "HTTP/1.1 {status} {reason}\r\ncontent-type: application/json\r\n\
         content-length: {}\r\nconnection: close\r\n\r\n{body}",
        body.len()
    )
    .into_bytes()
}

impl AsyncRead for ConnectionIo {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        ready!(Pin::new(&mut this.stream).poll_read(cx, buf))?;
        if buf.filled().len() > before {
            this.activity.touch();
        }
        Poll::Ready(Ok(()))
    }
}

impl AsyncWrite for ConnectionIo {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        ready!(this.poll_replacement(cx))?;
        if let Some(done) = this.replace(cx, buf) {
            return done;
        }
        let n = ready!(Pin::new(&mut this.stream).poll_write(cx, buf))?;
        if n > 0 {
            this.activity.touch();
        }
        Poll::Ready(Ok(n))
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        ready!(this.poll_replacement(cx))?;
        // hyper's parse-error answer is a head alone, the first slice.
        if let Some(first) = bufs.iter().find(|b| !b.is_empty()) {
            if let Some(done) = this.replace(cx, first) {
                return done;
            }
        }
        let n = ready!(Pin::new(&mut this.stream).poll_write_vectored(cx, bufs))?;
        if n > 0 {
            this.activity.touch();
        }
        Poll::Ready(Ok(n))
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        ready!(this.poll_replacement(cx))?;
        Pin::new(&mut this.stream).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        ready!(this.poll_replacement(cx))?;
        Pin::new(&mut this.stream).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_hypers_bodiless_parse_error_heads_are_replaced() {
        let hyper_431 = b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-length: 0\r\n\
            date: Thu, 01 Jan 2026 00:00:00 GMT\r\n\r\n";
        assert_eq!(parse_error_status(hyper_431), Some(431));
        let ours = b"HTTP/1.1 400 Bad Request\r\ncontent-type: application/json\r\n\
            content-length: 80\r\n\r\n";
        assert_eq!(parse_error_status(ours), None);
        let ok = b"HTTP/1.1 200 OK\r\ncontent-length: 0\r\n\r\n";
        assert_eq!(parse_error_status(ok), None);
        let answer = String::from_utf8(parse_error_answer(414)).unwrap();
        let body: serde_json::Value =
            serde_json::from_str(answer.split_once("\r\n\r\n").unwrap().1).unwrap();
        assert_eq!(body["error"]["code"], "uri_too_long");
        assert_eq!(body["error"]["status"], 414);
    }
}
