//! The cell on the bus: routes, the client library, records, security and hostile clients, as a client meets them.
//!
//! One test binary of a few (each links the gateway and zenoh): its modules are the areas.

#[path = "../common/mod.rs"]
mod common;

mod bus_routes;
mod cell_on_bus;
mod client;
mod client_events;
mod folder;
mod folder_doors;
mod g05_bus;
mod gateway;
mod hostile;
mod plc_bus;
mod punch_on_bus;
mod records;
mod reload;
mod security;
