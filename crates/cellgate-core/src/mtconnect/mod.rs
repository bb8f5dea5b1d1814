//! The cell in MTConnect (ANSI/MTC1.4, version 2.5), sans-IO: the device model of a cell's
//! machines and PLCs, the mapping from the bus contract's messages to observations, the
//! sequence buffer, the documents (XML and JSON) and the SHDR lines. The HTTP and TCP
//! serving, and the subscriptions that feed it, are the gateway's (`cellgate::mtconnect`).
//!
//! - [`desc`]: what a cell has, from its cell file, its `@admin` document or its statuses;
//! - [`model`]: the devices, components and data items, with stable ids and UUIDs;
//! - [`mapping`]: what each message says of each data item (docs/mtconnect.md);
//! - [`buffer`]: observations numbered without gaps, bounded in memory;
//! - [`agent`]: all of it together, answering `/probe`, `/current`, `/sample`;
//! - [`assets`]: punched programs kept as File assets;
//! - [`request`]: query parameters, `path` filters, errors and their codes;
//! - [`types`]: the data item types and units a PLC tag may be given (the configuration's);
//! - [`xml`], [`json`]: the documents, [`pretty`] laid out for reading; [`shdr`]: the
//!   adapter's line format.

pub mod agent;
pub mod assets;
pub mod buffer;
pub mod desc;
pub mod json;
pub mod mapping;
pub mod model;
pub mod pretty;
pub mod request;
pub mod shdr;
pub use crate::config::mtconnect_types as types;
pub mod xml;

pub use agent::{Agent, Update};
pub use desc::CellDesc;
pub use request::{ErrorCode, Format, MtError, Query, Request};

#[cfg(test)]
mod tests;
