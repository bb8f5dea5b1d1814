//! cellgate: one gateway per manufacturing cell, putting the cell's FANUC remote-buffer links
//! and its Fuji MICREX-F PLC on the Zenoh bus.
//!
//! This crate does the I/O: transports, link tasks, job queues and their journal, the bus,
//! the command line's client. Everything it decides without I/O (protocol engines and codecs,
//! program text, tag rules, the simulated devices' protocol side, the cell file, the bus
//! contract's keys and messages) is the core crate, [`cellgate_core`], which has no tokio and
//! no zenoh.
//!
//! # Layout
//!
//! Bytes flow bottom-up; commands top-down. Lowest layer first:
//!
//! - [`telemetry`]: tracing subscriber, the counters links and jobs keep
//!   ([`telemetry::metrics`]), the optional OTLP export and Prometheus endpoint. [`storage`]:
//!   what the embedded stores share (a database opened without a panic, a full disk told).
//! - [`transport`]: what carries a link's bytes: serial port, TCP device server, simulated
//!   line; carriers that come back by themselves share `redial`. [`door`]: what every
//!   listener shares (its cap on connections, the head's time and size, the write timeout).
//! - [`link`]: the async side of a link: [`link::pump`] runs any core engine over any
//!   transport in tokio time; [`link::driver`] is a FANUC link's task (program queue, streamed
//!   sources, typed commands and events); [`link::g05`] runs G05 streams through it.
//!   [`library`]: the program library, its revisions, and the folder it follows
//!   ([`library::folder`]).
//! - [`jobs`]: per-machine job queues, program sources, the job journal.
//! - [`plc`]: the PLC link task running the FFU120B master over a transport, with its tags.
//! - [`sim`]: the core's simulated devices run over transports, and as TCP device servers.
//! - [`history`]: the cell's history and audit trail in an embedded store, written in
//!   batches, read by time, machine, kind and tag, trimmed by retention.
//! - [`bus`]: the zenoh session, the roles as access control, one route per kind of key
//!   ([`bus::serve`], [`bus::serve_plcs`]); the key grammar is the core's.
//! - [`cell`]: the cell's links, built from the cell file; [`client`]: a client of the bus
//!   contract, the library side of the command line.
//! - [`console`]: the web console, a client of the bus like [`client`], served over HTTP(S);
//!   [`mtconnect`]: the MTConnect agent, a client of the bus as well, over HTTP and SHDR (its
//!   model and documents are the core's `mtconnect`); [`opcua`]: the OPC UA server (OPC 40501
//!   Machine Tools), a client of the bus as well (what its nodes show is the core's
//!   `opcua`); [`historian`]: the site's history in PostgreSQL, a client of the bus too. The
//!   agent and the server follow the cells through [`client::follow`].
//! - [`gateway`]: the running gateway: opens the bus, announces the cell, serves it, and stops
//!   cleanly when the shutdown future completes. [`soak`]: `cellgate sim soak`, a whole
//!   simulated cell run as processes of its own under load and faults, checked as a client of
//!   the bus sees it.
//!
//! # Who imports whom
//!
//! A module imports only the modules of lower layers in the list above (and the core):
//! `tests/cli/layering.rs` checks it, for this crate and the core. Only the bus side (`bus`,
//! `client`, `console`, `mtconnect`, `opcua`, `historian`, `gateway`, `soak`) speaks zenoh, so
//! links, jobs and transports run without a bus (and in paused time).

// What is `pub` is the crate's interface (tests, benches, the binary use it); anything else
// says how far it reaches.
#![warn(unreachable_pub)]

pub mod bus;
pub mod cell;
pub mod client;
pub mod console;
pub mod door;
pub mod gateway;
pub mod historian;
pub mod history;
pub mod jobs;
pub mod library;
pub mod link;
pub mod mtconnect;
pub mod opcua;
pub mod plc;
pub mod sim;
pub mod soak;
pub mod storage;
pub mod telemetry;
pub mod transport;
