//! The links: FANUC and FFU120B engines on simulated, TCP and serial lines, the simulated boards and devices, faults, delivery and restarts.
//!
//! One test binary of a few (each links the gateway and zenoh): its modules are the areas.

#[path = "../common/mod.rs"]
mod common;

mod delivery;
mod fanuc_link;
mod fanuc_link_b;
mod faults;
mod g05;
mod plc_link;
mod plc_messages;
mod restart;
mod sim_board;
mod sim_fanuc_boards;
mod sim_fuji;
mod transport_serial;
mod transport_sim;
mod transport_tcp;
