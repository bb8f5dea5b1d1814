//! The cell's PLCs: Fuji MICREX-F through FFU120B modules (`[[plcs]]`), each a link task
//! running the core's sans-IO FFU120B master over a transport ([`link::spawn`],
//! [`link::PlcHandle`]). The tag rules (poll plan, decoding, writes) are the core's
//! [`cellgate_core::plc::tags`].

pub mod link;

pub use cellgate_core::plc::tags::{self, Quality, TagError, TagTable, TagValue};
pub use link::{PlcCommand, PlcEvent, PlcHandle, PlcLinkError, PlcSnapshot, TagWriteError};
