//! Fuji MICREX-F through the FFU120B general interface module (FEH087b): the host side of the
//! command-set modes 1–3 and the non-procedure modes 4–5, sans-IO.
//!
//! Everything here imports [`crate::engine`], std, `serde`, `thiserror`, `tracing` and its own
//! files, and nothing of the async runtime, the link drivers or the transports.
//!
//! - [`bcc`]: the block check character: add, add-invert, EOR, CRC-16; transmission code or
//!   binary, Set 1 / Set 2 (§4-3 items 20–23, appendix). Imports nothing of its siblings.
//! - [`frame`]: the initial-file framing items ([`frame::FrameSettings`], §4-3), their initial
//!   errors (§4-7), the encoder and the bounded, resyncing decoder with the receive errors of
//!   §5-6. Imports `bcc`.
//! - [`command`]: the command-set text of §5-3: requests, replies, the module table, STA
//!   codes, byte order, BCD. Imports `frame` (its limits) only.
//! - [`master`]: the host engine ([`master::Master`]): one request at a time, time-outs,
//!   retries, stations down and probed, transfers, modes 4–5, counters. Imports all of the
//!   above and [`crate::engine`].
//!
//!
//! The simulated module ([`crate::sim::micrex`]) reuses `frame` and `command` for the wire
//! format, and `master` only for [`master::OperationMode`]; none of the logic.

pub mod bcc;
pub mod command;
pub mod frame;
pub mod master;
