//! The command line, the cell files and examples, the README's tour, and the layering of the code.
//!
//! One test binary of a few (each links the gateway and zenoh): its modules are the areas.

#[path = "../common/mod.rs"]
mod common;

mod cli;
mod config;
mod doc_commands;
mod examples;
mod help;
mod layering;
mod notes;
mod plc_cli;
mod reload_cli;
mod tour;
mod truth;
