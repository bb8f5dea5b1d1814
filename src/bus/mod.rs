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

pub use crate::config::{BusConfig, BusMode};
