//! The cell's PLCs, sans-IO: named tags ([`tags`]: poll plan, decoding, publish on change,
//! writes). What a `[[plcs]]` entry gives the FFU120B master is
//! [`crate::config::PlcConfig::master_settings`], and the simulated module
//! [`crate::sim::micrex::MicrexConfig::for_plc`].

pub mod tags;

pub use tags::{Quality, TagError, TagTable, TagValue};
