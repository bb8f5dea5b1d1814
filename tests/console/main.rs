//! The console: its API as pages and other clients use it, its door, and its pages in a real browser.
//!
//! One test binary of a few (each links the gateway and zenoh): its modules are the areas.

#[path = "../common/mod.rs"]
mod common;

mod api;
mod browser;
mod listeners;
mod mtconnect;
