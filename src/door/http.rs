//! HTTP/1 on a listener, with the doors' bounds: hyper's own server, given a timer so that its
//! header timeout works (axum's `serve` gives it none, and a connection that never finishes
//! its head stays open for good).
//!
//! The head timeout also closes a kept-alive connection that sends no next request: hyper
//! arms it again whenever the connection goes idle (`proto/h1/conn.rs`, `poll_read_head`).

use std::error::Error as StdError;

use axum::Router;
use axum::extract::ConnectInfo;
use hyper::Request;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use tokio_util::sync::CancellationToken;

use super::{HEAD_TIMEOUT, MAX_HEAD};

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
        let service =
            tower::ServiceExt::map_request(app.clone(), move |mut r: Request<Incoming>| {
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
