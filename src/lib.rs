//! cellgate: one gateway per manufacturing cell, putting the cell's FANUC remote-buffer links
//! and its Fuji MICREX-F PLC on the Zenoh bus.
//!
//! # Layout
//!
//! Bytes flow bottom-up; commands top-down.
//!
//! - [`transport`]: what carries a link's bytes: serial port, TCP device server, simulated line.
//! - [`fanuc`]: FANUC remote-buffer protocols (A, Expansion A, B, Expansion B), sans-IO: bytes
//!   and `now` go in; bytes to send, events and the next deadline come out.
//! - [`link`]: the async driver that runs one engine over one transport, and the typed
//!   commands and events through which the rest of the gateway talks to a link.
//! - [`sim`]: simulated devices (a remote-buffer board with a CNC behind it) that speak the
//!   device side of the same protocols, for tests, CI and laptops.
//! - [`config`]: the cell file: serde types, defaults, and validation that reports every error.
//! - [`bus`]: the Zenoh session and the cell's key expressions.
//! - [`telemetry`]: tracing subscriber and the optional OpenTelemetry export.
//! - [`pb`]: the protobuf messages of `proto/cellgate/v1`, the bus's public contract.

pub mod bus;
pub mod config;
pub mod fanuc;
pub mod link;
pub mod sim;
pub mod telemetry;
pub mod transport;

/// Protobuf messages generated from `proto/cellgate/v1/*.proto`.
pub mod pb {}
