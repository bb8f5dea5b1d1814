//! The Prometheus text endpoint: `GET /metrics` on `[telemetry] prometheus`.
//!
//! The OpenTelemetry project's own reader (`opentelemetry-prometheus`, released in step with
//! the SDK at 0.33) turns the meter provider's data into Prometheus metric families; the
//! `prometheus` crate's encoder writes the text format. What is left, serving one path, is
//! a few lines over a tokio listener: an HTTP framework would add a dependency tree for a
//! request line and a response header.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use opentelemetry_prometheus::PrometheusExporter;
use prometheus::{Encoder as _, TextEncoder};
use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;

/// Largest request head read; a scrape's is a few hundred bytes.
const MAX_REQUEST: usize = 8 * 1024;
/// A client that has not sent its request head by then is dropped.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);
/// Scrapes served at once; more wait for their turn.
const MAX_CONNECTIONS: usize = 8;

/// Why the Prometheus exposition could not be set up or rendered.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PrometheusError {
    #[error("building the Prometheus reader: {0}")]
    Reader(#[source] opentelemetry_sdk::error::OTelSdkError),
    #[error("encoding the Prometheus text: {0}")]
    Encode(#[source] prometheus::Error),
}

/// A Prometheus registry fed by an OpenTelemetry reader.
#[derive(Clone)]
pub struct Exposition {
    registry: prometheus::Registry,
}

impl std::fmt::Debug for Exposition {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Exposition").finish_non_exhaustive()
    }
}

impl Exposition {
    /// The exposition, and the reader to give the meter provider that feeds it.
    pub fn new() -> Result<(Self, PrometheusExporter), PrometheusError> {
        let registry = prometheus::Registry::new();
        let reader = opentelemetry_prometheus::exporter()
            .with_registry(registry.clone())
            // The scope is always `cellgate`: a label on every sample would say nothing.
            .scope_info_enabled(false)
            .build()
            .map_err(PrometheusError::Reader)?;
        Ok((Exposition { registry }, reader))
    }

    /// The current metrics in the Prometheus text format (version 0.0.4).
    pub fn render(&self) -> Result<String, PrometheusError> {
        let families = self.registry.gather();
        let mut out = Vec::new();
        TextEncoder::new()
            .encode(&families, &mut out)
            .map_err(PrometheusError::Encode)?;
        Ok(String::from_utf8_lossy(&out).into_owned())
    }
}

/// Serves `GET /metrics` on `listener` until `stop` is cancelled.
pub async fn serve(listener: TcpListener, exposition: Exposition, stop: CancellationToken) {
    let permits = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    loop {
        let accepted = tokio::select! {
            () = stop.cancelled() => return,
            a = listener.accept() => a,
        };
        let (stream, peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                // Out of file descriptors and the like: wait a little rather than spin.
                tracing::warn!(error = %e, "Prometheus endpoint: accept failed");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let Ok(permit) = Arc::clone(&permits).acquire_owned().await else {
            return;
        };
        let exposition = exposition.clone();
        let stop = stop.clone();
        tokio::spawn(async move {
            let _permit = permit;
            tokio::select! {
                () = stop.cancelled() => {}
                r = answer(stream, &exposition) => if let Err(e) = r {
                    tracing::debug!(%peer, error = %e, "Prometheus endpoint: request failed");
                }
            }
        });
    }
}

/// What a request asks for, from its request line.
#[derive(Debug, PartialEq, Eq)]
enum Route {
    Metrics,
    NotFound,
    MethodNotAllowed,
    BadRequest,
}

fn route(head: &[u8]) -> Route {
    let line = head.split(|&b| b == b'\n').next().unwrap_or_default();
    let line = String::from_utf8_lossy(line);
    let mut parts = line.split_whitespace();
    let (Some(method), Some(target), Some(version)) = (parts.next(), parts.next(), parts.next())
    else {
        return Route::BadRequest;
    };
    if !version.starts_with("HTTP/1.") {
        return Route::BadRequest;
    }
    let path = target.split('?').next().unwrap_or_default();
    match (method, path) {
        ("GET" | "HEAD", "/metrics") => Route::Metrics,
        (_, "/metrics") => Route::MethodNotAllowed,
        _ => Route::NotFound,
    }
}

async fn answer(mut stream: TcpStream, exposition: &Exposition) -> std::io::Result<()> {
    let mut head = Vec::with_capacity(512);
    let mut buf = [0u8; 1024];
    let complete = tokio::time::timeout(REQUEST_TIMEOUT, async {
        loop {
            if head.windows(4).any(|w| w == b"\r\n\r\n") || head.windows(2).any(|w| w == b"\n\n") {
                return true;
            }
            if head.len() >= MAX_REQUEST {
                return false;
            }
            match stream.read(&mut buf).await {
                Ok(0) | Err(_) => return false,
                Ok(n) => head.extend_from_slice(&buf[..n]),
            }
        }
    })
    .await
    .unwrap_or(false);
    let head_only = head.starts_with(b"HEAD ");
    let (status, content_type, body) = if !complete {
        ("400 Bad Request", "text/plain", "bad request\n".to_string())
    } else {
        match route(&head) {
            Route::Metrics => match exposition.render() {
                Ok(text) => ("200 OK", "text/plain; version=0.0.4; charset=utf-8", text),
                Err(e) => ("500 Internal Server Error", "text/plain", format!("{e}\n")),
            },
            Route::NotFound => ("404 Not Found", "text/plain", "try /metrics\n".to_string()),
            Route::MethodNotAllowed => (
                "405 Method Not Allowed",
                "text/plain",
                "GET /metrics\n".to_string(),
            ),
            Route::BadRequest => ("400 Bad Request", "text/plain", "bad request\n".to_string()),
        }
    };
    let header = format!(
        "HTTP/1.1 {status}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(header.as_bytes()).await?;
    if !head_only {
        stream.write_all(body.as_bytes()).await?;
    }
    stream.shutdown().await
}

/// Parses `[telemetry] prometheus`: an IP address and port, e.g. `127.0.0.1:9464`.
pub fn parse_addr(text: &str) -> Result<SocketAddr, std::net::AddrParseError> {
    text.trim().parse()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn routes_by_request_line() {
        assert_eq!(route(b"GET /metrics HTTP/1.1\r\n\r\n"), Route::Metrics);
        assert_eq!(route(b"GET /metrics?x=1 HTTP/1.0\r\n\r\n"), Route::Metrics);
        assert_eq!(route(b"HEAD /metrics HTTP/1.1\r\n\r\n"), Route::Metrics);
        assert_eq!(
            route(b"POST /metrics HTTP/1.1\r\n\r\n"),
            Route::MethodNotAllowed
        );
        assert_eq!(route(b"GET / HTTP/1.1\r\n\r\n"), Route::NotFound);
        assert_eq!(route(b"GET /metrics\r\n\r\n"), Route::BadRequest);
        assert_eq!(route(b"\xff\xfe garbage"), Route::BadRequest);
        assert_eq!(route(b""), Route::BadRequest);
    }

    #[test]
    fn addresses_are_ip_and_port() {
        assert!(parse_addr("127.0.0.1:9464").is_ok());
        assert!(parse_addr("[::1]:9464").is_ok());
        assert!(parse_addr("localhost:9464").is_err());
        assert!(parse_addr("127.0.0.1").is_err());
        assert!(parse_addr("").is_err());
    }
}
