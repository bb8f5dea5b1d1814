//! The host side's contract: what the gateway asks of a remote-buffer host engine
//! ([`EngineCommand`]), what the engine reports ([`EngineEvent`]), and [`HostEngine`], the
//! [`Engine`] both host engines ([`ProtocolAHost`], [`ProtocolBHost`])
//! implement. Plain data and a trait: the async link driver runs any `HostEngine` over any
//! transport.
//!
//! [`ProtocolAHost`]: super::protocol_a::ProtocolAHost
//! [`ProtocolBHost`]: super::protocol_b::ProtocolBHost

use bytes::Bytes;
use serde::Serialize;

use super::error::{AbortReason, LinkAlarm, ProtocolError};
use super::sat::StatusData;
use crate::engine::{Engine, LineError};

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

/// Commands a host engine takes. Program data comes in pieces no larger than
/// [`HostEngine::data_wanted`], so that no program is ever held whole.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum EngineCommand {
    /// A program is ready to be sent when the board asks for data. `total` is its size
    /// when known (for progress).
    StartProgram {
        /// The program's size in bytes, when known.
        total: Option<u64>,
    },
    /// The next bytes of the current program.
    ProgramData(Bytes),
    /// The next bytes of the current program, passed as they are: G05 binary blocks (§9.1),
    /// which are not scanned for EOR or checked against the message end code.
    BinaryData(Bytes),
    /// NC text ending in the `G05` block and the binary blocks of the priming level, taken
    /// in one step: no DAT, packet or piece carries the `G05` block without the blocks
    /// behind it, since the CNC takes a block every unit time from the moment it reads it
    /// (§9.1, §9.2).
    Primed {
        /// NC text up to and including the `G05` block, as `ProgramData`.
        text: Bytes,
        /// Binary blocks, as `BinaryData`.
        blocks: Bytes,
    },
    /// The current program is made while it is sent (a G05 stream): what there is goes out
    /// at once — a short DAT rather than a wait for a full one, since a late block starves the
    /// CNC (§9.2).
    Streaming,
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

/// A piece of a program that is made while it is sent (a G05 stream): what the sans-IO G05
/// stream produces and the link hands to the engine as `ProgramData`, `BinaryData` or
/// `Primed` ([`Chunk::command`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Chunk {
    /// NC text: scanned for EOR like any program.
    Text(Bytes),
    /// Binary blocks (G05, §9.1): passed as they are.
    Binary(Bytes),
    /// The text ending in the `G05` block with the blocks of the priming level: one piece,
    /// so that the `G05` block never reaches the CNC without blocks behind it (§9.2).
    Primed {
        /// NC text up to and including the `G05` block.
        text: Bytes,
        /// Binary blocks.
        blocks: Bytes,
    },
}

impl Chunk {
    /// The engine command that hands this chunk over.
    pub fn command(self) -> EngineCommand {
        match self {
            Chunk::Text(text) => EngineCommand::ProgramData(text),
            Chunk::Binary(blocks) => EngineCommand::BinaryData(blocks),
            Chunk::Primed { text, blocks } => EngineCommand::Primed { text, blocks },
        }
    }
}

/// What a host engine reports.
#[derive(Debug, Clone, PartialEq)]
pub enum EngineEvent {
    /// The link entered this state (also the engine's first event).
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
    /// Program bytes were handed to the line as NC data (in DAT or data packets;
    /// retransmissions are not counted again). Handed out is not yet received: see `Acked`.
    DataSent {
        /// The program bytes in what was just handed to the line (a DAT's data part, a data
        /// packet's data without its padding, or a piece), in the program's order.
        data: Bytes,
    },
    /// The board has acknowledged the current program's first `offset` bytes (how a protocol
    /// acknowledges is said at [`Confirmation`]). Never decreases within a program.
    Acked {
        /// Bytes of the current program the board has acknowledged, from its start.
        offset: u64,
    },
    /// The board has acknowledged the whole current program, through its EOR.
    ProgramDone {
        /// How the board showed that it holds the program.
        confirmation: Confirmation,
    },
    /// The current program was abandoned: by `Cancel` (`cancelled`), by the CNC (reset or
    /// alarm), or by a link failure.
    ProgramAborted {
        /// Why the program was abandoned.
        reason: AbortReason,
        /// Whether a `Cancel` command abandoned it.
        cancelled: bool,
    },
    /// A link alarm; [`LinkAlarm::cnc_alarm`] is the CNC alarm number the board raises for it.
    Alarm(LinkAlarm),
    /// A protocol error that the engine recovered from (retry, resync). For logs and counters.
    ProtocolError {
        /// The error recovered from.
        error: ProtocolError,
        /// Whether the engine retried because of it (a retransmission or an RTY).
        retried: bool,
    },
    /// Punched data from the board (Protocol B punch-out, DC2 … DC4, §6.1.1 2), in order. A
    /// long punch-out arrives in several pieces; the last piece of a punch-out is followed by
    /// nothing that marks it, the next punch-out starts a new piece.
    Punched {
        /// The punched bytes of this piece.
        data: Bytes,
    },
    /// The punch-out was damaged here, after the `Punched` pieces received before it: the
    /// program being punched has a character wrong or missing and must not be taken as good.
    PunchDamaged {
        /// What damaged the punch-out.
        cause: PunchDamage,
    },
}

/// How a punch-out was damaged.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error, Serialize)]
#[non_exhaustive]
pub enum PunchDamage {
    /// The UART reported a character in error (§4.6 line errors).
    #[error("{0} during the punch-out")]
    Line(LineError),
    /// Characters arrived with the engine's buffer full and were dropped (the board did not
    /// stop at DC3 within its overrun allowance, §6.3).
    #[error("punched characters dropped: the board did not stop at DC3 (§6.3)")]
    Dropped,
}

/// How the board showed that it holds a program (and, for offsets, its first bytes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Confirmation {
    /// The protocol acknowledged every byte: in Protocol A the board's next exchange after
    /// the DAT (not RTY, RST or ALM), in Expansion Protocol A the board back in Protocol A
    /// after the end packet (§4.4, §5.2). Expansion A packets get only negative
    /// acknowledgements (NAK, §5.3), so nothing of a transmission is acknowledged before its
    /// end: a program cut in the middle of one fails at the offset acknowledged before it.
    Acknowledged,
    /// Protocol B: the DC3 that ends the read arrived after the EOR had had its line time,
    /// and no reset or alarm notice (SYN, NAK) or ER off followed it (§6.1.1 (7), §6.4).
    EndOfRead,
    /// Protocol B with reset/alarm notification off over a line that does not carry the
    /// board's ER (a TCP device server): the DC3 that ends a read cannot be told from the one
    /// a CNC reset or alarm sends, so the end of the read is taken as delivery, unverified.
    Unverified,
}

/// A host-side engine (Protocol A family or Protocol B family).
pub trait HostEngine: Engine<Command = EngineCommand, Event = EngineEvent> {
    /// How many more program bytes the engine will take now (bounded buffer). Zero while it
    /// holds more than half its buffer: the source is read in a few large pieces.
    #[must_use]
    fn data_wanted(&self) -> usize;

    /// What the link is waiting for from the board, in the manual's words, when progress
    /// depends on the board (SYN after a re-initialisation, the GTD or DC1 of a CNC that has not
    /// started reading): status shows it, with since when, so that a stuck link says why.
    #[must_use]
    fn waiting_for(&self) -> Option<&'static str> {
        None
    }

    /// Program bytes the line has had time to carry to the board by `now`, where the
    /// protocol acknowledges nothing finer until its next control code (Protocol B, §6.3):
    /// what the block being fed is read from meanwhile. It acknowledges nothing: a job's
    /// offset is `EngineEvent::Acked`'s. `None` where acknowledgements say it all.
    #[must_use]
    fn carried(&self, now: std::time::Instant) -> Option<u64> {
        let _ = now;
        None
    }
}
