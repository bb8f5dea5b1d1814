//! Simulated devices, sans-IO: the device side of the protocols the gateway speaks as host,
//! for tests, CI and laptops. The gateway crate runs them over its transports.
//!
//! - [`fanuc_board`]: a FANUC remote-buffer board ([`FanucBoard`] implements
//!   [`crate::engine::Engine`]) for Protocol A, Expansion A, Protocol B and Expansion B;
//! - [`cnc`]: the CNC behind it: buffer, consumption at a rate, programs split at EOR, DI/DO,
//!   G05 binary input operation (one block a unit time, underruns, SR0890);
//! - [`micrex`]: an FFU120B module with a MICREX-F behind it (command set and
//!   non-procedure modes).

pub mod cnc;
pub mod fanuc_board;
pub mod micrex;

pub use cnc::{G05End, G05Stats, ReceivedProgram};
pub use fanuc_board::{
    BoardCommand, BoardConfig, BoardConfigError, BoardEvent, BoardLinkState, ControlCode,
    FanucBoard, FlowCounters,
};
