//! `[telemetry]` of the cell file: logs, the OTLP export and the Prometheus endpoint. The
//! gateway's telemetry module sets them up; here they are only read and checked.

use std::net::SocketAddr;

use serde::{Deserialize, Serialize};

/// Format of the gateway's log lines.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    /// Plain text, the default.
    #[default]
    Human,
    /// One JSON object a line.
    Json,
}

/// `[telemetry]` of the cell file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TelemetryConfig {
    /// Format of log lines; `human` by default.
    pub log_format: LogFormat,
    /// An env-filter directive such as `info,cellgate=debug`; `RUST_LOG` overrides it.
    pub log_filter: String,
    /// OTLP/gRPC endpoint, e.g. `http://127.0.0.1:4317`. `None` (the default) exports nothing,
    /// unless `OTEL_EXPORTER_OTLP_ENDPOINT` is set.
    pub otlp_endpoint: Option<String>,
    /// `service.name` of exported spans and metrics.
    pub service_name: String,
    /// Address (IP and port) of the Prometheus text endpoint, e.g. `127.0.0.1:9464`. `None`
    /// (the default) opens no port.
    pub prometheus: Option<String>,
}

impl Default for TelemetryConfig {
    fn default() -> Self {
        TelemetryConfig {
            log_format: LogFormat::Human,
            log_filter: "info".to_string(),
            otlp_endpoint: None,
            service_name: "cellgate".to_string(),
            prometheus: None,
        }
    }
}

/// A Prometheus listen address: an IP address and a port (host names are not resolved).
pub fn parse_socket_addr(text: &str) -> Result<SocketAddr, std::net::AddrParseError> {
    text.trim().parse()
}

/// `url` without the credentials of its authority (`http://user:secret@host:4317` reads
/// `http://***@host:4317`), for logs and the `@admin` document: an endpoint's password must
/// not leave the cell file.
pub fn redact_credentials(url: &str) -> String {
    let (scheme, rest) = match url.split_once("://") {
        Some((s, r)) => (Some(s), r),
        None => (None, url),
    };
    let end = rest.find(['/', '?', '#']).unwrap_or(rest.len());
    let (authority, tail) = rest.split_at(end);
    let authority = match authority.rsplit_once('@') {
        Some((_, host)) => format!("***@{host}"),
        None => authority.to_string(),
    };
    match scheme {
        Some(s) => format!("{s}://{authority}{tail}"),
        None => format!("{authority}{tail}"),
    }
}

impl TelemetryConfig {
    /// The settings with the credentials of `otlp_endpoint` redacted.
    pub fn redacted(&self) -> TelemetryConfig {
        TelemetryConfig {
            otlp_endpoint: self.otlp_endpoint.as_deref().map(redact_credentials),
            ..self.clone()
        }
    }
}

#[cfg(test)]
mod tests;
