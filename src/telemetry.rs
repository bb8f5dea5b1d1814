//! Logs and traces: a tracing subscriber with env-filter, human or JSON output, and an
//! optional OpenTelemetry OTLP export (off by default).

use std::io::IsTerminal as _;

use serde::{Deserialize, Serialize};
use tracing_subscriber::{
    EnvFilter, Layer as _, fmt, layer::SubscriberExt as _, util::SubscriberInitExt as _,
};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    #[default]
    Human,
    Json,
}

/// `[telemetry]` of the cell file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TelemetryConfig {
    pub log_format: LogFormat,
    /// An env-filter directive such as `info,cellgate=debug`; `RUST_LOG` overrides it.
    pub log_filter: String,
    /// OTLP/gRPC endpoint, e.g. `http://127.0.0.1:4317`. `None` (the default) exports nothing,
    /// unless `OTEL_EXPORTER_OTLP_ENDPOINT` is set.
    pub otlp_endpoint: Option<String>,
    /// `service.name` of exported spans.
    pub service_name: String,
}

impl Default for TelemetryConfig {
    fn default() -> Self {
        TelemetryConfig {
            log_format: LogFormat::Human,
            log_filter: "info".to_string(),
            otlp_endpoint: None,
            service_name: "cellgate".to_string(),
        }
    }
}

/// The environment variable that overrides `log_filter`.
pub const RUST_LOG: &str = "RUST_LOG";
/// The standard OpenTelemetry variable that turns the OTLP export on when
/// `otlp_endpoint` is not set.
pub const OTEL_EXPORTER_OTLP_ENDPOINT: &str = "OTEL_EXPORTER_OTLP_ENDPOINT";

/// Why telemetry could not be set up or shut down.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TelemetryError {
    /// The log filter is not a valid env-filter directive.
    #[error("log filter {filter:?} from {origin} is not valid: {source}")]
    Filter {
        filter: String,
        /// `RUST_LOG` or `telemetry.log_filter`.
        origin: &'static str,
        #[source]
        source: tracing_subscriber::filter::ParseError,
    },
    /// The OTLP span exporter could not be built (e.g. a malformed endpoint).
    #[error("OTLP exporter for {endpoint}: {source}")]
    Exporter {
        endpoint: String,
        #[source]
        source: opentelemetry_otlp::ExporterBuildError,
    },
    /// A global subscriber was already installed in this process.
    #[error("a tracing subscriber is already installed: {0}")]
    AlreadyInitialised(#[source] tracing_subscriber::util::TryInitError),
    /// Flushing or shutting down the span exporter failed (spans may be lost).
    #[error("shutting down the OTLP exporter: {0}")]
    Shutdown(#[source] opentelemetry_sdk::error::OTelSdkError),
}

/// Keeps the OpenTelemetry pipeline alive. Dropping it (or calling
/// [`shutdown`](Self::shutdown)) flushes pending spans and stops the exporter. Keep it
/// until the end of the async main, inside the Tokio runtime: the gRPC exporter needs it.
#[derive(Debug, Default)]
#[must_use = "dropping the guard shuts the span exporter down at once"]
pub struct TelemetryGuard {
    provider: Option<opentelemetry_sdk::trace::SdkTracerProvider>,
}

impl TelemetryGuard {
    /// Whether spans are exported over OTLP.
    pub fn exporting(&self) -> bool {
        self.provider.is_some()
    }

    /// Flushes pending spans and shuts the exporter down. Later calls do nothing.
    pub fn shutdown(&mut self) -> Result<(), TelemetryError> {
        match self.provider.take() {
            Some(provider) => {
                // A failed flush is reported, but the provider is still shut down.
                let flushed = provider.force_flush();
                let shut = provider.shutdown();
                flushed.and(shut).map_err(TelemetryError::Shutdown)
            }
            None => Ok(()),
        }
    }
}

impl Drop for TelemetryGuard {
    fn drop(&mut self) {
        if let Err(e) = self.shutdown() {
            eprintln!("cellgate: {e}");
        }
    }
}

/// The filter to log with: `RUST_LOG` when set (non-empty), else `log_filter`.
pub fn filter(log_filter: &str, rust_log: Option<&str>) -> Result<EnvFilter, TelemetryError> {
    let (directives, origin) = match rust_log {
        Some(s) if !s.trim().is_empty() => (s, RUST_LOG),
        _ => (log_filter, "telemetry.log_filter"),
    };
    EnvFilter::builder()
        .parse(directives)
        .map_err(|source| TelemetryError::Filter {
            filter: directives.to_string(),
            origin,
            source,
        })
}

/// The OTLP endpoint to export to, if any: `otlp_endpoint` from the cell file, else
/// `OTEL_EXPORTER_OTLP_ENDPOINT` (non-empty). `None`: no export.
pub fn otlp_endpoint(cfg: &TelemetryConfig, env_endpoint: Option<&str>) -> Option<String> {
    cfg.otlp_endpoint
        .clone()
        .or_else(|| env_endpoint.map(str::to_string))
        .filter(|e| !e.trim().is_empty())
}

/// Installs the global tracing subscriber: env-filter, human or JSON lines on stderr, and
/// an OTLP/gRPC span exporter when an endpoint is configured (see [`otlp_endpoint`]).
///
/// With OTLP on, call it from inside the Tokio runtime (the gRPC channel lives there).
/// Without an endpoint nothing is contacted.
pub fn init(cfg: &TelemetryConfig) -> Result<TelemetryGuard, TelemetryError> {
    let env_filter = filter(&cfg.log_filter, std::env::var(RUST_LOG).ok().as_deref())?;
    let endpoint = otlp_endpoint(
        cfg,
        std::env::var(OTEL_EXPORTER_OTLP_ENDPOINT).ok().as_deref(),
    );

    let provider = match &endpoint {
        Some(endpoint) => Some(tracer_provider(endpoint, &cfg.service_name)?),
        None => None,
    };
    let otel_layer = provider.as_ref().map(|p| {
        use opentelemetry::trace::TracerProvider as _;
        tracing_opentelemetry::layer().with_tracer(p.tracer("cellgate"))
    });

    let ansi = std::io::stderr().is_terminal();
    let fmt_layer = match cfg.log_format {
        LogFormat::Human => fmt::layer()
            .with_writer(std::io::stderr)
            .with_ansi(ansi)
            .boxed(),
        LogFormat::Json => fmt::layer()
            .json()
            .with_writer(std::io::stderr)
            .with_current_span(true)
            .boxed(),
    };

    tracing_subscriber::registry()
        .with(env_filter)
        .with(fmt_layer)
        .with(otel_layer)
        .try_init()
        .map_err(TelemetryError::AlreadyInitialised)?;

    if let Some(provider) = &provider {
        opentelemetry::global::set_tracer_provider(provider.clone());
    }
    if let Some(endpoint) = endpoint {
        tracing::info!(%endpoint, service = %cfg.service_name, "exporting spans over OTLP/gRPC");
    }
    Ok(TelemetryGuard { provider })
}

fn tracer_provider(
    endpoint: &str,
    service_name: &str,
) -> Result<opentelemetry_sdk::trace::SdkTracerProvider, TelemetryError> {
    use opentelemetry_otlp::WithExportConfig as _;
    let exporter = opentelemetry_otlp::SpanExporter::builder()
        .with_tonic()
        .with_endpoint(endpoint)
        .build()
        .map_err(|source| TelemetryError::Exporter {
            endpoint: endpoint.to_string(),
            source,
        })?;
    let resource = opentelemetry_sdk::Resource::builder()
        .with_service_name(service_name.to_string())
        .build();
    Ok(opentelemetry_sdk::trace::SdkTracerProvider::builder()
        .with_batch_exporter(exporter)
        .with_resource(resource)
        .build())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rust_log_overrides_the_cell_file() {
        let f = filter("info", Some("cellgate=trace")).unwrap();
        assert_eq!(f.to_string(), "cellgate=trace");
        let f = filter("warn,cellgate=debug", None).unwrap();
        assert!(f.to_string().contains("cellgate=debug"), "{f}");
        // An empty RUST_LOG is treated as unset.
        let f = filter("warn", Some("  ")).unwrap();
        assert_eq!(f.to_string(), "warn");
    }

    #[test]
    fn a_bad_filter_names_where_it_came_from() {
        match filter("info", Some("cellgate=loud")) {
            Err(TelemetryError::Filter { origin, .. }) => assert_eq!(origin, RUST_LOG),
            other => panic!("expected a filter error, got {other:?}"),
        }
        match filter("cellgate=loud", None) {
            Err(TelemetryError::Filter { origin, .. }) => {
                assert_eq!(origin, "telemetry.log_filter")
            }
            other => panic!("expected a filter error, got {other:?}"),
        }
    }

    #[test]
    fn otlp_is_off_unless_an_endpoint_is_given() {
        let cfg = TelemetryConfig::default();
        assert_eq!(otlp_endpoint(&cfg, None), None);
        assert_eq!(otlp_endpoint(&cfg, Some("")), None);
        assert_eq!(
            otlp_endpoint(&cfg, Some("http://127.0.0.1:4317")).as_deref(),
            Some("http://127.0.0.1:4317")
        );
        let cfg = TelemetryConfig {
            otlp_endpoint: Some("http://127.0.0.1:14317".to_string()),
            ..TelemetryConfig::default()
        };
        assert_eq!(
            otlp_endpoint(&cfg, Some("http://127.0.0.1:4317")).as_deref(),
            Some("http://127.0.0.1:14317")
        );
    }

    #[test]
    fn a_guard_without_exporter_shuts_down_quietly() {
        let mut guard = TelemetryGuard::default();
        assert!(!guard.exporting());
        guard.shutdown().unwrap();
        guard.shutdown().unwrap();
    }
}
