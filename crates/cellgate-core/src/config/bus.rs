//! `[bus]` and `[telemetry]`: the zenoh session the gateway opens and where its logs and
//! traces go.

use serde::{Deserialize, Serialize};

use super::error::{Checker, q};
use super::telemetry::{TelemetryConfig, parse_socket_addr};

/// Zenoh session mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum BusMode {
    /// Peer mode, the default.
    #[default]
    Peer,
    /// Client mode.
    Client,
    /// Router mode.
    Router,
}

/// `[bus]` of the cell file. The default keeps the gateway on loopback with multicast
/// scouting off: listen on tcp/127.0.0.1:7447, connect nowhere.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BusConfig {
    /// Key prefix `P` of every key the gateway serves (`P/C/...`).
    pub prefix: String,
    /// Zenoh session mode; peer by default.
    pub mode: BusMode,
    /// Zenoh endpoints to listen on, e.g. `tcp/127.0.0.1:7447`.
    pub listen: Vec<String>,
    /// Zenoh endpoints to connect to.
    pub connect: Vec<String>,
    /// Zenoh multicast scouting. Off unless asked for.
    pub multicast_scouting: bool,
    /// Optional zenoh json5 configuration file; the keys above override it.
    pub zenoh_config: Option<std::path::PathBuf>,
}

impl Default for BusConfig {
    fn default() -> Self {
        BusConfig {
            prefix: "cellgate".to_string(),
            mode: BusMode::Peer,
            listen: vec!["tcp/127.0.0.1:7447".to_string()],
            connect: Vec::new(),
            multicast_scouting: false,
            zenoh_config: None,
        }
    }
}

/// Whether a zenoh endpoint listens on this host only: a loopback address (`127.0.0.0/8`,
/// `::1`, `localhost`) or a unix socket.
pub fn is_loopback_endpoint(endpoint: &str) -> bool {
    let Some((proto, rest)) = endpoint.split_once('/') else {
        return false;
    };
    if proto.starts_with("unixsock") {
        return true;
    }
    // Options after '#' (zenoh's endpoint metadata) are not part of the address.
    let addr = rest.split(['#', '?']).next().unwrap_or(rest);
    let host = match addr.rsplit_once(':') {
        Some((h, _)) => h,
        None => addr,
    };
    let host = host.trim_start_matches('[').trim_end_matches(']');
    if host.eq_ignore_ascii_case("localhost") {
        return true;
    }
    host.parse::<std::net::IpAddr>()
        .is_ok_and(|ip| ip.is_loopback())
}

pub(super) fn check_bus(c: &mut Checker, bus: &BusConfig) {
    let prefix = &bus.prefix;
    if prefix.is_empty()
        || prefix.split('/').any(|chunk| {
            chunk.is_empty() || chunk.contains(['*', '$', '?', '#']) || chunk.trim() != chunk
        })
    {
        c.invalid(
            "bus.prefix".to_string(),
            q(prefix),
            "must be one or more '/'-separated key chunks, none empty, without wildcards \
             ('*', '$', '?', '#') or surrounding spaces"
                .to_string(),
            "",
        );
    }
    for (key, list) in [("listen", &bus.listen), ("connect", &bus.connect)] {
        for (i, ep) in list.iter().enumerate() {
            let ok = ep
                .split_once('/')
                .is_some_and(|(proto, addr)| !proto.is_empty() && !addr.is_empty());
            if !ok {
                c.invalid(
                    format!("bus.{key}[{}]", i + 1),
                    q(ep),
                    "a Zenoh endpoint is PROTOCOL/ADDRESS, e.g. \"tcp/127.0.0.1:7447\"".to_string(),
                    "",
                );
            }
        }
    }
}

pub(super) fn check_telemetry(c: &mut Checker, t: &TelemetryConfig) {
    if let Err(e) = tracing_subscriber::EnvFilter::try_new(&t.log_filter) {
        c.invalid(
            "telemetry.log_filter".to_string(),
            q(&t.log_filter),
            format!("not a log filter directive like \"info,cellgate=debug\": {e}"),
            "",
        );
    }
    if let Some(ep) = &t.otlp_endpoint
        && !(ep.starts_with("http://") || ep.starts_with("https://"))
    {
        c.invalid(
            "telemetry.otlp_endpoint".to_string(),
            q(ep),
            "an OTLP/gRPC endpoint is an http:// or https:// URL, e.g. \"http://127.0.0.1:4317\""
                .to_string(),
            "",
        );
    }
    if let Some(addr) = &t.prometheus
        && parse_socket_addr(addr).is_err()
    {
        c.invalid(
            "telemetry.prometheus".to_string(),
            q(addr),
            "the Prometheus endpoint is an IP address and port, e.g. \"127.0.0.1:9464\" \
             (a host name is not resolved)"
                .to_string(),
            "",
        );
    }
    if t.service_name.trim().is_empty() {
        c.invalid(
            "telemetry.service_name".to_string(),
            q(&t.service_name),
            "must not be empty".to_string(),
            "",
        );
    }
}

impl BusMode {
    /// The name zenoh uses for this mode in its configuration.
    pub fn as_str(self) -> &'static str {
        match self {
            BusMode::Peer => "peer",
            BusMode::Client => "client",
            BusMode::Router => "router",
        }
    }
}
