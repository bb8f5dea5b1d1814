//! HTTP/1 on a listener, with the doors' bounds: hyper's own server, given a timer so that its
//! header timeout works (axum's `serve` gives it none, and a connection that never finishes
//! its head stays open for good).
//!
//! The head timeout also closes a kept-alive connection that sends no next request: hyper
//! arms it again whenever the connection goes idle (`proto/h1/conn.rs`, `poll_read_head`).
//!
//! A request's body has its own bounds ([`TimedBody`]): hyper gives it none, so a client that
//! sent a head and then trickles its body, or stops, held its connection and the handler
//! reading it for good.

use std::error::Error as StdError;
use std::future::Future as _;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::Router;
use axum::extract::ConnectInfo;
use hyper::Request;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use tokio_util::sync::CancellationToken;

use super::{HEAD_TIMEOUT, MAX_HEAD};

/// How long a request body may pause between two of its pieces.
pub const BODY_IDLE: Duration = HEAD_TIMEOUT;
/// How long a whole request body may take, however steadily it comes: a program of the
/// largest size a cell takes (16 MiB) at 1 Mbit/s.
pub const BODY_TIMEOUT: Duration = Duration::from_secs(180);

/// A request body that fails (and so ends its request with an error, and its connection)
/// when it pauses longer than [`BODY_IDLE`] or takes longer than [`BODY_TIMEOUT`].
pub struct TimedBody {
    inner: Incoming,
    idle: Pin<Box<tokio::time::Sleep>>,
    whole: Pin<Box<tokio::time::Sleep>>,
}

impl TimedBody {
    /// `inner`, timed from now.
    pub fn new(inner: Incoming) -> TimedBody {
        TimedBody {
            inner,
            idle: Box::pin(tokio::time::sleep(BODY_IDLE)),
            whole: Box::pin(tokio::time::sleep(BODY_TIMEOUT)),
        }
    }
}

/// Why a request body was cut short.
#[derive(Debug, thiserror::Error)]
pub enum BodyError {
    #[error("the request body paused longer than {} s", BODY_IDLE.as_secs())]
    Idle,
    #[error("the request body took longer than {} s", BODY_TIMEOUT.as_secs())]
    Slow,
    #[error(transparent)]
    Hyper(#[from] hyper::Error),
}

impl hyper::body::Body for TimedBody {
    type Data = bytes::Bytes;
    type Error = BodyError;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<hyper::body::Frame<Self::Data>, Self::Error>>> {
        let this = &mut *self;
        if this.whole.as_mut().poll(cx).is_ready() {
            return Poll::Ready(Some(Err(BodyError::Slow)));
        }
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(frame) => {
                let next = tokio::time::Instant::now() + BODY_IDLE;
                this.idle.as_mut().reset(next);
                Poll::Ready(frame.map(|f| f.map_err(BodyError::from)))
            }
            Poll::Pending if this.idle.as_mut().poll(cx).is_ready() => {
                Poll::Ready(Some(Err(BodyError::Idle)))
            }
            Poll::Pending => Poll::Pending,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> hyper::body::SizeHint {
        self.inner.size_hint()
    }
}

/// What a connection buffers at most, both ways (hyper's floor is 8 KiB).
const MAX_BUF: usize = 64 * 1024;

/// The HTTP/1 server every listener uses: the head timeout, the head size, the buffer size.
fn builder() -> hyper::server::conn::http1::Builder {
    let mut b = hyper::server::conn::http1::Builder::new();
    b.timer(TokioTimer::new())
        .header_read_timeout(HEAD_TIMEOUT)
        .max_header_size(MAX_HEAD)
        .max_buf_size(MAX_BUF.max(MAX_HEAD));
    b
}

/// Serves `app` on the connections `listener` lets in until `stop`, then lets those under way
/// finish (the caller bounds how long it waits). Each request carries its connection's
/// address as `ConnectInfo<L::Addr>`, as axum's `into_make_service_with_connect_info` gives.
pub async fn serve<L>(mut listener: L, app: Router, stop: CancellationToken)
where
    L: axum::serve::Listener,
    L::Addr: Clone + Send + Sync + std::fmt::Debug + 'static,
{
    let builder = builder();
    let graceful = GracefulShutdown::new();
    loop {
        let (io, addr) = tokio::select! {
            () = stop.cancelled() => break,
            accepted = listener.accept() => accepted,
        };
        let peer = addr.clone();
        let service = tower::ServiceExt::map_request(app.clone(), move |r: Request<Incoming>| {
            let mut r = r.map(TimedBody::new);
            r.extensions_mut().insert(ConnectInfo(peer.clone()));
            r
        });
        let conn = builder.serve_connection(TokioIo::new(io), TowerToHyperService::new(service));
        let conn = graceful.watch(conn);
        tokio::spawn(async move {
            if let Err(e) = conn.await {
                // A client gone, too slow with its head or not reading: theirs to mind.
                tracing::debug!(?addr, error = %e, cause = ?e.source(), "HTTP connection ended");
            }
        });
    }
    drop(listener);
    graceful.shutdown().await;
}
