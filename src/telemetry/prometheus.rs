//! The Prometheus text endpoint: `GET /metrics` on `[telemetry] prometheus`.
//!
//! The OpenTelemetry project's own reader (`opentelemetry-prometheus`, released in step with
//! the SDK at 0.33) turns the meter provider's data into Prometheus metric families; the
//! `prometheus` crate's encoder writes the text format; axum, the console's HTTP stack,
//! serves the one path.

use opentelemetry_prometheus::PrometheusExporter;
use prometheus::{Encoder as _, TextEncoder};
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;

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

/// `GET /metrics` (and `HEAD`): the current metrics in the text format.
pub fn router(exposition: Exposition) -> axum::Router {
    use axum::http::{StatusCode, header};
    use axum::response::IntoResponse;
    axum::Router::new().route(
        "/metrics",
        axum::routing::get(move || {
            let exposition = exposition.clone();
            async move {
                match exposition.render() {
                    Ok(text) => (
                        [(
                            header::CONTENT_TYPE,
                            "text/plain; version=0.0.4; charset=utf-8",
                        )],
                        text,
                    )
                        .into_response(),
                    Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, format!("{e}\n")).into_response(),
                }
            }
        }),
    )
}

/// Serves [`router`] on `listener` until `stop` is cancelled: the same HTTP stack as the
/// console, on a listener of its own.
pub async fn serve(listener: TcpListener, exposition: Exposition, stop: CancellationToken) {
    let served = axum::serve(listener, router(exposition))
        .with_graceful_shutdown(async move { stop.cancelled().await })
        .await;
    if let Err(e) = served {
        tracing::warn!(error = %e, "Prometheus endpoint stopped");
    }
}

/// Parses `[telemetry] prometheus`: an IP address and port, e.g. `127.0.0.1:9464`.
pub use cellgate_core::config::telemetry::parse_socket_addr as parse_addr;

#[cfg(test)]
mod tests;
