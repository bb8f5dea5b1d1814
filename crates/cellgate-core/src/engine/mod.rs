//! The sans-IO contract every protocol engine keeps, host or device, FANUC or Fuji.
//!
//! An engine does no I/O and has no clock of its own (quinn-proto's promise): bytes, line
//! errors, modem lines, commands and `now` go in; bytes to send, events and the next deadline
//! come out. This module and everything that implements [`Engine`] import no async runtime,
//! no sockets, nothing of the link drivers or the transports, so an engine can be read,
//! tested with a scripted peer in plain time, fuzzed, and reused by the simulated devices.
//! The async side (the link pump) runs any engine over any transport.
//!
//! - [`Engine`]: the contract itself;
//! - `line`: the plain data it speaks of: character framing, modem lines, line errors;
//! - [`pacer`]: what a line may still take at its rate, for transports whose peer buffers
//!   (a TCP device server), so a stop code is never overrun by more than a window;
//! - [`parmrk`]: the kernel's parity marks of a serial port, decoded into line errors;
//! - [`parity`]: the parity bit made and checked by the gateway, where a device server passes
//!   whole 8-bit frames of a 7-bit line.

pub mod hex;
pub mod line;
pub mod pacer;
pub mod parity;
pub mod parmrk;

use std::time::Instant;

pub use line::{LineError, LineSettings, ModemIn, ModemOut};

/// Protocol frames an engine has received and sent so far, for the link's counters. What a
/// frame is depends on the protocol (a message, a packet, a control code); running totals, so
/// that reading them costs the engine nothing.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FrameCounts {
    /// Frames received so far.
    pub received: u64,
    /// Frames sent so far.
    pub sent: u64,
}

/// A sans-IO protocol engine: the host side of a link, or the device side of a simulated board.
///
/// Every method is synchronous and cheap; `now` is the only clock. Inputs may arrive in any
/// split; garbage never panics the engine.
pub trait Engine: Send {
    /// What the owner of the engine asks of it (see [`Engine::handle_command`]).
    type Command: Send;
    /// What the engine reports (see [`Engine::poll_event`]).
    type Event: Send;

    /// Bytes received from the line.
    fn handle_input(&mut self, now: Instant, bytes: &[u8]);
    /// A character error the transport reported (parity, framing, overrun): §4.6 line errors.
    fn handle_line_error(&mut self, now: Instant, error: LineError);
    /// The input modem lines, whenever the driver reads them (after every change at least).
    fn handle_modem(&mut self, now: Instant, modem: ModemIn);
    /// A command from the owner of the engine.
    fn handle_command(&mut self, now: Instant, command: Self::Command);
    /// Time passed: act on any deadline at or before `now`.
    fn handle_timeout(&mut self, now: Instant);
    /// The next bytes to write. The driver writes them completely before asking again, so an
    /// engine that must be able to stop quickly (DC3, monitor packets) hands out small pieces.
    #[must_use]
    fn poll_transmit(&mut self, now: Instant) -> Option<Vec<u8>>;
    /// The next event, if any.
    #[must_use]
    fn poll_event(&mut self) -> Option<Self::Event>;
    /// The earliest deadline the engine wants to be woken at.
    #[must_use]
    fn poll_timeout(&self) -> Option<Instant>;
    /// The modem output lines (ER, RS) the engine wants driven.
    #[must_use]
    fn modem_out(&self) -> ModemOut {
        ModemOut::ALL_ON
    }
    /// Frames received and sent so far; an engine that does not count them reports none.
    #[must_use]
    fn frames(&self) -> FrameCounts {
        FrameCounts::default()
    }
}

/// Settings an engine cannot run with, and every problem found in them (`P`: the engine's own
/// problem type, whose `Display` names the setting and the manual section).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct InvalidSettings<P> {
    /// The engine, as its errors name it ("Protocol A").
    pub engine: &'static str,
    /// Every problem found, at least one.
    pub problems: Vec<P>,
}

impl<P> InvalidSettings<P> {
    /// `Ok` when `problems` is empty, else every problem as one error.
    pub fn check(engine: &'static str, problems: Vec<P>) -> Result<(), Self> {
        if problems.is_empty() {
            Ok(())
        } else {
            Err(InvalidSettings { engine, problems })
        }
    }
}

impl<P: std::fmt::Display> std::fmt::Display for InvalidSettings<P> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "invalid {} settings: ", self.engine)?;
        for (i, p) in self.problems.iter().enumerate() {
            if i > 0 {
                f.write_str("; ")?;
            }
            write!(f, "{p}")?;
        }
        Ok(())
    }
}

impl<P: std::fmt::Debug + std::fmt::Display> std::error::Error for InvalidSettings<P> {}
