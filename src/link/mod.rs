//! Links: one async driver task per serial link, running a sans-IO protocol engine
//! ([`cellgate_core::engine::Engine`]) over a [`Transport`](crate::transport::Transport).
//!
//! The engine never awaits. [`pump`] feeds it received bytes, line errors, modem-line changes
//! and the time; it writes what `poll_transmit` returns and sleeps until `poll_timeout`.
//! [`driver`] runs a FANUC host engine ([`cellgate_core::fanuc::host::HostEngine`]) that way, keeps
//! the machine's program queue, and forwards the engine's events as [`driver::LinkEvent`]s.
//! The rest of the gateway (bus routes, job manager) talks to a link only through
//! [`driver::LinkCommand`] and [`driver::LinkEvent`]: that is the seam the bus bridge uses,
//! and the one tests drive in virtual time.

pub mod driver;
pub mod fanout;
pub mod g05;
pub mod pump;

/// Identifies a program job on one link.
pub type JobId = u64;
