//! Logs and traces: a tracing subscriber with env-filter, human or JSON output, and an
//! optional OpenTelemetry OTLP export (off by default).

use serde::{Deserialize, Serialize};

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
