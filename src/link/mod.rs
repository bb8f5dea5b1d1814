//! Links: one async driver task per serial link, running a sans-IO protocol engine over a
//! [`Transport`](crate::transport::Transport).
//!
//! The engine never awaits. The driver feeds it received bytes, line errors, modem-line
//! changes, commands and the time; it writes what [`HostEngine::poll_transmit`] returns, sleeps
//! until [`HostEngine::poll_timeout`], and forwards [`EngineEvent`]s as [`LinkEvent`]s. The rest
//! of the gateway (bus routes, job manager) talks to a link only through [`LinkCommand`] and
//! [`LinkEvent`]: that is the seam the bus bridge uses, and the one tests drive in virtual time.

pub mod driver;
pub mod pump;

use std::time::Instant;

use bytes::Bytes;
use serde::Serialize;

use crate::fanuc::alarm::CncAlarm;
use crate::fanuc::sat::StatusData;
use crate::transport::{LineError, ModemIn, ModemOut};

/// The state of a link as users see it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum LinkState {
    /// Waiting for the board to initialise the link (Protocol A: SYN wait, §4.6 1).
    Initialising,
    /// Initialised and idle (Protocol A: RDY exchanged; Protocol B: ER/DR on).
    Ready,
    /// Sending NC data to the board.
    Sending,
    /// Receiving punched data from the board (Protocol B).
    Receiving,
    /// The line is down (DR off, device server unreachable); the engine waits for it.
    LineDown,
}

/// Commands an engine takes (sans-IO). Program data comes in pieces no larger than
/// [`HostEngine::data_wanted`], so that no program is ever held whole.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum EngineCommand {
    /// A program is ready to be sent when the board asks for data. `total` is its size
    /// when known (for progress).
    StartProgram { total: Option<u64> },
    /// The next bytes of the current program.
    ProgramData(Bytes),
    /// The current program's source has no more bytes.
    ProgramEnd,
    /// Abandon the current program: Protocol A answers the next GTD with EOD and clears the
    /// board's buffer with CLB at the next SAT; Expansion A ends the packets with an end packet.
    Cancel,
    /// Output this 8-bit DO image (SDO) at the protocol's next chance.
    SetDo(u8),
    /// Read the 8-bit DI image (RDI → SDI) at the protocol's next chance.
    ReadDi,
    /// Clear the board's buffer (CLB) at the next SAT.
    ClearBuffer,
}

/// What an engine reports.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[non_exhaustive]
pub enum EngineEvent {
    State(LinkState),
    /// A SAT arrived, decoded (§4.4.2).
    Status(StatusData),
    /// An SDI arrived with this DI image.
    Di(u8),
    /// An SDO carrying this DO image was sent.
    DoSent(u8),
    /// The CNC was reset (ALM/RST in Protocol A; SYN in Protocol B).
    CncReset,
    /// The CNC raised an alarm (ALM in Protocol A; NAK in Protocol B).
    CncAlarm,
    /// `bytes` more program bytes went onto the line as NC data (in DAT or data packets;
    /// retransmissions are not counted again).
    DataSent {
        bytes: u64,
    },
    /// The whole current program was delivered and the board was told (EOD / end packet).
    ProgramDone,
    /// The current program was abandoned: by `Cancel` (`cancelled`), by the CNC (reset or
    /// alarm), or by a link failure.
    ProgramAborted {
        reason: String,
        cancelled: bool,
    },
    /// A link alarm, with the CNC alarm number the board raises for it where one applies.
    Alarm {
        alarm: Option<CncAlarm>,
        error: String,
    },
    /// A protocol error that the engine recovered from (retry, resync). For logs and counters.
    ProtocolError {
        error: String,
        retried: bool,
    },
    /// Punched data from the board (Protocol B punch-out, DC2 … DC4, §6.1.1 2), in order. A
    /// long punch-out arrives in several pieces; the last piece of a punch-out is followed by
    /// nothing that marks it, the next punch-out starts a new piece.
    #[serde(skip)]
    Punched {
        data: Bytes,
    },
}

/// A sans-IO protocol engine: the host side of a link, or the device side of a simulated board.
///
/// Every method is synchronous and cheap; `now` is the only clock. Inputs may arrive in any
/// split; garbage never panics the engine. One async pump ([`pump`]) runs any engine over any
/// transport.
pub trait Engine: Send {
    type Command: Send;
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
}

/// A host-side engine (Protocol A family or Protocol B family).
pub trait HostEngine: Engine<Command = EngineCommand, Event = EngineEvent> {
    /// How many more program bytes the engine will take now (bounded buffer).
    #[must_use]
    fn data_wanted(&self) -> usize;
}

/// Identifies a program job on one link.
pub type JobId = u64;
