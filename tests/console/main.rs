//! The site's clients of the bus contract: the console (its API as pages and other clients use
//! it, its door, its pages in a real browser), the MTConnect agent, and the historian into a
//! real PostgreSQL.
//!
//! One test binary of a few (each links the gateway and zenoh): its modules are the areas.

#[path = "../common/mod.rs"]
mod common;

mod api;
mod browser;
mod gateway;
mod historian;
mod listeners;
mod mtconnect;
mod opcua;
