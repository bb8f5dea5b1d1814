//! The Zenoh side of the gateway: session settings, the cell's key expressions ([`keys`]),
//! the protobuf payloads ([`payload`]) and the routes that put each machine's link, its job
//! queue and the cell's program library on the bus ([`routes`]).

pub mod keys;
mod machine;
pub mod payload;
mod punch;
pub mod routes;
pub mod session;

pub use routes::{MachineLink, serve};
pub use session::{BusError, open};

use serde::{Deserialize, Serialize};

/// Zenoh session mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum BusMode {
    #[default]
    Peer,
    Client,
    Router,
}

/// `[bus]` of the cell file. The default keeps the gateway on loopback with multicast
/// scouting off: listen on tcp/127.0.0.1:7447, connect nowhere.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BusConfig {
    /// Key prefix `P` of every key the gateway serves (`P/C/...`).
    pub prefix: String,
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
