//! Logs, traces and metrics: a tracing subscriber with env-filter, human or JSON output; an
//! optional OpenTelemetry OTLP export of spans and metrics; an optional Prometheus text
//! endpoint. Both exports are off by default: nothing is contacted and no port opened.
//!
//! - [`metrics`]: the gateway's counters (plain atomics the links and job managers count
//!   into) and the instruments that read them;
//! - [`prometheus`]: `GET /metrics` in the Prometheus text format.
//!
//! Spans: every job is a root span `job` from queued to ended (machine, job id, bytes,
//! outcome), every time a link is up a root span `link session`; retries, checksum errors,
//! line faults and alarms are events in the link's session span.

pub mod metrics;
pub mod prometheus;

use std::io::IsTerminal as _;
use std::net::SocketAddr;

pub use cellgate_core::config::telemetry::{LogFormat, TelemetryConfig, redact_credentials};
use tracing_subscriber::{
    EnvFilter, Layer as _, fmt, layer::SubscriberExt as _, util::SubscriberInitExt as _,
};

/// A count as a span field: tracing-opentelemetry exports `u64` fields as strings (they may
/// not fit an OTLP integer), so counts go in as `i64`, which every real one fits.
pub fn span_count(n: u64) -> i64 {
    i64::try_from(n).unwrap_or(i64::MAX)
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
    /// The OTLP span or metric exporter could not be built (e.g. a malformed endpoint).
    #[error("OTLP exporter for {endpoint}: {source}")]
    Exporter {
        endpoint: String,
        #[source]
        source: opentelemetry_otlp::ExporterBuildError,
    },
    /// `telemetry.prometheus` is not an IP address and port.
    #[error(
        "telemetry.prometheus {addr:?} is not an IP address and port like \"127.0.0.1:9464\": {source}"
    )]
    PrometheusAddress {
        addr: String,
        #[source]
        source: std::net::AddrParseError,
    },
    /// The Prometheus endpoint's address could not be bound (in use, not local, ...).
    #[error("Prometheus endpoint on {addr}: {source}")]
    PrometheusBind {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Prometheus(#[from] prometheus::PrometheusError),
    /// An export was asked for outside a Tokio runtime (the gRPC channel and the endpoint
    /// live there).
    #[error("telemetry exports need a Tokio runtime: {0}")]
    NoRuntime(#[source] tokio::runtime::TryCurrentError),
    /// A global subscriber was already installed in this process.
    #[error("a tracing subscriber is already installed: {0}")]
    AlreadyInitialised(#[source] tracing_subscriber::util::TryInitError),
    /// Flushing or shutting down an exporter failed (spans or metrics may be lost).
    #[error("shutting down the OTLP exporter: {0}")]
    Shutdown(#[source] opentelemetry_sdk::error::OTelSdkError),
}

/// Keeps the metrics pipeline alive: the meter provider (OTLP export, Prometheus reader) and
/// the Prometheus endpoint. Dropping it (or [`shutdown`](Self::shutdown)) exports what is
/// left and closes the endpoint.
#[derive(Debug, Default)]
#[must_use = "dropping the guard stops the metrics export at once"]
pub struct MetricsGuard {
    provider: Option<opentelemetry_sdk::metrics::SdkMeterProvider>,
    instruments: Option<metrics::Instruments>,
    prometheus: Option<(SocketAddr, tokio_util::sync::CancellationToken)>,
}

impl MetricsGuard {
    /// Whether metrics are collected for an exporter (OTLP or Prometheus).
    pub fn active(&self) -> bool {
        self.provider.is_some()
    }

    /// The address the Prometheus endpoint listens on (the port bound when 0 was asked).
    pub fn prometheus_addr(&self) -> Option<SocketAddr> {
        self.prometheus.as_ref().map(|(a, _)| *a)
    }

    /// Exports the metrics now (OTLP); the Prometheus endpoint always serves current ones.
    pub fn force_flush(&self) -> Result<(), TelemetryError> {
        match &self.provider {
            Some(p) => p.force_flush().map_err(TelemetryError::Shutdown),
            None => Ok(()),
        }
    }

    /// Exports what is left, stops the exporters and closes the endpoint. Later calls do
    /// nothing.
    pub fn shutdown(&mut self) -> Result<(), TelemetryError> {
        if let Some((_, stop)) = self.prometheus.take() {
            stop.cancel();
        }
        self.instruments = None;
        match self.provider.take() {
            Some(provider) => provider.shutdown().map_err(TelemetryError::Shutdown),
            None => Ok(()),
        }
    }
}

impl Drop for MetricsGuard {
    fn drop(&mut self) {
        if let Err(e) = self.shutdown() {
            eprintln!("cellgate: {e}");
        }
    }
}

/// Builds the metrics pipeline `cfg` asks for: an OTLP/gRPC metric exporter when an
/// endpoint is configured (see [`otlp_endpoint`]; every `OTEL_METRIC_EXPORT_INTERVAL` ms,
/// default 60 s, and at shutdown), and the Prometheus endpoint when `prometheus` is set.
/// Neither: nothing is built, nothing contacted, no port opened. The counters are counted
/// either way ([`metrics`]).
///
/// Call it inside the Tokio runtime when anything is exported. The provider is not made
/// global; [`init`] does that.
pub fn install_metrics(
    cfg: &TelemetryConfig,
    endpoint: Option<&str>,
) -> Result<MetricsGuard, TelemetryError> {
    let prometheus_addr = match &cfg.prometheus {
        Some(text) => Some(prometheus::parse_addr(text).map_err(|source| {
            TelemetryError::PrometheusAddress {
                addr: text.clone(),
                source,
            }
        })?),
        None => None,
    };
    if endpoint.is_none() && prometheus_addr.is_none() {
        return Ok(MetricsGuard::default());
    }
    let runtime = tokio::runtime::Handle::try_current().map_err(TelemetryError::NoRuntime)?;
    let mut builder =
        opentelemetry_sdk::metrics::SdkMeterProvider::builder().with_resource(resource(cfg));
    if let Some(endpoint) = endpoint {
        use opentelemetry_otlp::WithExportConfig as _;
        let exporter = opentelemetry_otlp::MetricExporter::builder()
            .with_tonic()
            .with_endpoint(endpoint)
            .build()
            .map_err(|source| TelemetryError::Exporter {
                endpoint: redact_credentials(endpoint),
                source,
            })?;
        builder = builder.with_periodic_exporter(exporter);
    }
    let mut prometheus = None;
    if let Some(addr) = prometheus_addr {
        let (exposition, reader) = prometheus::Exposition::new()?;
        let bind = |addr| -> std::io::Result<tokio::net::TcpListener> {
            let listener = std::net::TcpListener::bind(addr)?;
            listener.set_nonblocking(true)?;
            let _entered = runtime.enter();
            tokio::net::TcpListener::from_std(listener)
        };
        let listener =
            bind(addr).map_err(|source| TelemetryError::PrometheusBind { addr, source })?;
        let bound = listener
            .local_addr()
            .map_err(|source| TelemetryError::PrometheusBind { addr, source })?;
        let stop = tokio_util::sync::CancellationToken::new();
        runtime.spawn(prometheus::serve(listener, exposition, stop.clone()));
        tracing::info!(addr = %bound, "serving Prometheus metrics on /metrics");
        prometheus = Some((bound, stop));
        builder = builder.with_reader(reader);
    }
    let provider = builder.build();
    let instruments = metrics::register(&provider);
    if let Some(endpoint) = endpoint {
        tracing::info!(endpoint = %redact_credentials(endpoint), "exporting metrics over OTLP/gRPC");
    }
    Ok(MetricsGuard {
        provider: Some(provider),
        instruments: Some(instruments),
        prometheus,
    })
}

fn resource(cfg: &TelemetryConfig) -> opentelemetry_sdk::Resource {
    opentelemetry_sdk::Resource::builder()
        .with_service_name(cfg.service_name.clone())
        .build()
}

/// Keeps the OpenTelemetry pipeline alive. Dropping it (or calling
/// [`shutdown`](Self::shutdown)) flushes pending spans and stops the exporter. Keep it
/// until the end of the async main, inside the Tokio runtime: the gRPC exporter needs it.
#[derive(Debug, Default)]
#[must_use = "dropping the guard shuts the span exporter down at once"]
pub struct TelemetryGuard {
    provider: Option<opentelemetry_sdk::trace::SdkTracerProvider>,
    metrics: MetricsGuard,
}

impl TelemetryGuard {
    /// Whether spans are exported over OTLP.
    pub fn exporting(&self) -> bool {
        self.provider.is_some()
    }

    /// The metrics pipeline (Prometheus address, flush).
    pub fn metrics(&self) -> &MetricsGuard {
        &self.metrics
    }

    /// Flushes pending spans and metrics and shuts the exporters down. Later calls do
    /// nothing.
    pub fn shutdown(&mut self) -> Result<(), TelemetryError> {
        let metrics = self.metrics.shutdown();
        let spans = match self.provider.take() {
            Some(provider) => {
                // A failed flush is reported, but the provider is still shut down.
                let flushed = provider.force_flush();
                let shut = provider.shutdown();
                flushed.and(shut).map_err(TelemetryError::Shutdown)
            }
            None => Ok(()),
        };
        spans.and(metrics)
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
    let filter =
        EnvFilter::builder()
            .parse(directives)
            .map_err(|source| TelemetryError::Filter {
                filter: directives.to_string(),
                origin,
                source,
            })?;
    // The OPC 40501 NodeSets carry old binary schemas as base64 with line breaks: the stack
    // warns of each, at length, on every start; they are of no use to the server.
    Ok(match "opcua_types::xml=error".parse() {
        Ok(quiet) if !directives.contains("opcua_types") => filter.add_directive(quiet),
        _ => filter,
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
/// an OTLP/gRPC span exporter when an endpoint is configured (see [`otlp_endpoint`]); and
/// the metrics pipeline ([`install_metrics`]), whose meter provider becomes the global one.
///
/// With OTLP or Prometheus on, call it from inside the Tokio runtime (the gRPC channel and
/// the endpoint live there). Without either nothing is contacted and no port opened.
pub fn init(cfg: &TelemetryConfig) -> Result<TelemetryGuard, TelemetryError> {
    let env_filter = filter(&cfg.log_filter, std::env::var(RUST_LOG).ok().as_deref())?;
    let endpoint = otlp_endpoint(
        cfg,
        std::env::var(OTEL_EXPORTER_OTLP_ENDPOINT).ok().as_deref(),
    );

    let provider = match &endpoint {
        Some(endpoint) => Some(tracer_provider(endpoint, cfg)?),
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
    if let Some(endpoint) = &endpoint {
        tracing::info!(endpoint = %redact_credentials(endpoint), service = %cfg.service_name, "exporting spans over OTLP/gRPC");
    }
    // Built after the subscriber, so that its own messages are logged.
    let metrics = install_metrics(cfg, endpoint.as_deref())?;
    if let Some(p) = &metrics.provider {
        opentelemetry::global::set_meter_provider(p.clone());
    }
    Ok(TelemetryGuard { provider, metrics })
}

fn tracer_provider(
    endpoint: &str,
    cfg: &TelemetryConfig,
) -> Result<opentelemetry_sdk::trace::SdkTracerProvider, TelemetryError> {
    use opentelemetry_otlp::WithExportConfig as _;
    let exporter = opentelemetry_otlp::SpanExporter::builder()
        .with_tonic()
        .with_endpoint(endpoint)
        .build()
        .map_err(|source| TelemetryError::Exporter {
            endpoint: redact_credentials(endpoint),
            source,
        })?;
    Ok(opentelemetry_sdk::trace::SdkTracerProvider::builder()
        .with_batch_exporter(exporter)
        .with_resource(resource(cfg))
        .build())
}

#[cfg(test)]
mod tests;
