//! cellgate's sans-IO core: everything the gateway decides without doing I/O, in a crate
//! whose dependencies hold no async runtime, no sockets and no zenoh, so the compiler keeps
//! the rule that the engines, codecs and device models never await (quinn-proto's shape).
//!
//! # Layout
//!
//! - [`engine`]: the contract every protocol engine keeps ([`engine::Engine`]: bytes, line
//!   errors, modem lines, commands and `now` in; bytes, events and the next deadline out),
//!   the line's plain data, the pacing of a buffered line, the kernel's parity marks;
//! - [`fanuc`]: the FANUC remote buffer (B-63322EN-1): codecs, the host engines of Protocol A,
//!   Expansion A, Protocol B and Expansion B, their typed errors, G05 blocks and streams;
//! - [`fuji`]: the Fuji FFU120B (FEH087b): BCC, framing, the command set, the host engine;
//! - [`program`]: NC program text: checks, blocks, tape codes, punched programs;
//! - [`plc`]: named PLC tags (poll plan, decoding, writes) and what a `[[plcs]]` entry gives
//!   the FFU120B master and the simulated module;
//! - [`sim`]: the simulated devices' protocol side: a remote-buffer board with its CNC, an
//!   FFU120B with its MICREX-F;
//! - [`history`]: what a history, audit or utilisation query asks, what a machine is doing
//!   as the remote buffer tells it, and utilisation computed from the records;
//! - [`config`]: the cell file, one file per concern, validated with every error at once;
//! - [`bounds`]: the size of every request message, checked before it is decoded, and of its
//!   fields;
//! - [`mtconnect`]: the cell in MTConnect 2.5: the device model, the mapping from the bus
//!   contract's messages, the sequence buffer, the documents and SHDR lines;
//! - [`opcua`]: the cell in OPC UA (OPC 40501 Machine Tools): what each node of a machine
//!   tool and of a PLC shows, and the alerts, from the bus contract's messages;
//! - [`near`]: the names near a mistyped one, for every "did you mean";
//! - [`testkit`]: two engines on a simulated line in plain time ([`testkit::Pair`]);
//! - the bus contract: [`keys`] (every key expression of a cell, built and parsed), [`pb`]
//!   (its protobuf messages), [`codes`] (how errors become its codes).
//!
//! # Who imports whom
//!
//! `engine` imports nothing of the crate. `fanuc` and `fuji` import `engine`; `program`
//! imports `fanuc`; `plc` imports `fuji`; `sim` imports the protocols it simulates;
//! `config` imports the engines' own settings types and `program`'s rules; `pb` imports
//! nothing and `codes` only `pb`; `near` imports nothing; `opcua` imports `mtconnect`. `tests/cli/layering.rs` checks
//! these arrows.

#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod bounds;
pub mod codes;
pub mod config;
pub mod engine;
pub mod fanuc;
pub mod fuji;
pub mod history;
pub mod keys;
pub mod mtconnect;
pub mod near;
pub mod opcua;
pub mod pb;
pub mod plc;
pub mod program;
pub mod sim;
pub mod testkit;
