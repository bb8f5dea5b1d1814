//! What can go wrong on a remote-buffer link, in three categories kept apart (as rustls keeps
//! its error categories): [`ProtocolError`]s the host recovered from, [`LinkAlarm`]s that broke
//! the link, and the [`AbortReason`] a program was abandoned for. Each carries the fields a
//! person needs and cites the manual; a link alarm knows its CNC alarm number as a value
//! ([`LinkAlarm::cnc_alarm`]). They cross the engine seam as they are: nothing downstream
//! reads their text.

use std::time::Duration;

use super::alarm::CncAlarm;
use super::message::{Command, FrameError};
use super::packet::{Monitor, PacketError};
use super::program::ProgramSendError;
use super::sat::{AlarmCause, StatusDataError};
use crate::codes::BusCode;
use crate::engine::LineError;
use crate::pb;

/// A protocol error the host engine recovered from (a retry, a resync, a request it ignored).
/// For logs and counters; the link carries on.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ProtocolError {
    /// A received frame that is not a valid message (ignored, §4.6 2).
    #[error("received message refused: {error}{}", frame_hint(.error))]
    Frame {
        /// Why the frame was refused.
        error: FrameError,
    },
    /// A received frame with a checksum error; RTY was sent.
    #[error(
        "checksum error in a received message, RTY '1' sent (retry {count}, Ne = {ne}): {error}"
    )]
    ChecksumRetry {
        /// The checksum error.
        error: FrameError,
        /// Retries so far, this one included.
        count: u16,
        /// Retry count parameter Ne (§4.5).
        ne: u16,
    },
    /// The board asked for the last message again (RTY, §4.4.1); `reason` is its data byte.
    #[error(
        "the board sent RTY (reason {}): last message sent again (retry {count}, Ne = {ne})",
        rty_reason(*.reason)
    )]
    RtyReceived {
        /// The RTY's first data byte (`1` checksum error, `3` overrun error), if any.
        reason: Option<u8>,
        /// Retries so far, this one included.
        count: u16,
        /// Retry count parameter Ne (§4.5).
        ne: u16,
    },
    /// The board sent RTY before the host had sent any message; ignored.
    #[error("the board sent RTY before the host had sent any message; ignored")]
    RtyNothingSent,
    /// A command that does not fit the state (§4.6 2 (2)).
    #[error(
        "unexpected {command} {context}; ignored (§4.6 2 (2); a remote buffer reports this as SR0947)"
    )]
    Unexpected {
        /// The command received.
        command: Command,
        /// The state it came in, in words (e.g. "during an Expansion A packet transmission").
        context: &'static str,
    },
    /// A SAT whose data part cannot be read; no `Status` event was reported.
    #[error("SAT data part unreadable, no Status reported: {0}")]
    Status(StatusDataError),
    /// An SDI whose data part does not start with two hex digits (§4.4.2 4).
    #[error(
        "SDI data part {:?} does not start with two hex digits (§4.4.2 4)",
        String::from_utf8_lossy(.data)
    )]
    SdiData {
        /// The SDI's data part.
        data: Vec<u8>,
    },
    /// A monitor packet that could not be read (§5.3).
    #[error("monitor packet refused: {0}")]
    Monitor(PacketError),
    /// A monitor packet outside an Expansion A transmission; ignored (§5.3).
    #[error("monitor packet {monitor:?} outside an Expansion A transmission; ignored (§5.3)")]
    StrayMonitor {
        /// The monitor packet.
        monitor: Monitor,
    },
    /// No RDY came after the host's SYN; the host waits for SYN again (§4.7).
    #[error("no RDY within {waited:?} of the host's SYN; waiting for SYN again (§4.7)")]
    NoRdy {
        /// How long the host waited for RDY.
        waited: Duration,
    },
    /// Bytes outside a punch-out that are no Protocol B control code.
    #[error(
        "{count} received byte(s) starting with {first:#04x} are not Protocol B control codes (§6.2); ignored"
    )]
    NotControlCodes {
        /// How many such bytes arrived.
        count: usize,
        /// The first of them.
        first: u8,
    },
    /// Punched bytes beyond what the host holds.
    #[error(
        "punch-out overflow: {dropped} punched byte(s) dropped; the board did not stop within the overrun after DC3 (§6.3) or the punched data is not being taken"
    )]
    PunchOverflow {
        /// Punched bytes dropped.
        dropped: usize,
    },
    /// A UART error on a Protocol B line, which has no retransmission (§6).
    #[error("line error on a Protocol B line: {error}{}", if *.punching { "; a punched character was lost" } else { "" })]
    LineB {
        /// The UART's error.
        error: LineError,
        /// Whether a punch-out was under way, so that a punched character was lost.
        punching: bool,
    },
    /// DR went off in the middle of a punch-out.
    #[error("punch-out cut off by DR off: {lost} punched byte(s) without DC4 discarded")]
    PunchCutOff {
        /// Punched bytes received since DC2 without a DC4, discarded.
        lost: usize,
    },
    /// A command the protocol does not have (SDO, RDI and CLB in Protocol B).
    #[error("{what} is not available in Protocol B (§6)")]
    NotInProtocolB {
        /// What was asked for, in words (e.g. "DO output (SDO)").
        what: &'static str,
    },
}

fn frame_hint(error: &FrameError) -> &'static str {
    match error {
        FrameError::UnknownCommand { .. } => {
            " (a remote buffer reports an undefined command as SR0948)"
        }
        FrameError::DataTooLong { .. } => " (reception error, §4.6 2)",
        _ => "",
    }
}

fn rty_reason(reason: Option<u8>) -> String {
    match reason {
        Some(b'1') => "\"1: checksum error\"".to_string(),
        Some(b'3') => "\"3: overrun error\"".to_string(),
        Some(b) => format!("{:?}", String::from_utf8_lossy(&[b])),
        None => "\"none given\"".to_string(),
    }
}

impl ProtocolError {
    /// A checksum error, in either direction: one the host found in a message or packet, or
    /// one the board reported with RTY reason 1 (§4.4.1, §4.6 2).
    pub fn is_checksum(&self) -> bool {
        match self {
            ProtocolError::Frame { error } => error.is_checksum_error(),
            ProtocolError::ChecksumRetry { .. } => true,
            ProtocolError::RtyReceived { reason, .. } => *reason == Some(b'1'),
            ProtocolError::Monitor(e) => matches!(
                e,
                PacketError::Checksum { .. } | PacketError::MonitorChecksum { .. }
            ),
            _ => false,
        }
    }
}

/// A link alarm: the link failed and was re-initialised (Protocol A, §4.6 1) or lost its line
/// (DR off). [`LinkAlarm::cnc_alarm`] is the alarm the CNC shows for it (§11).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum LinkAlarm {
    /// The UART reported a character error; the link was re-initialised (§4.6 1).
    #[error("line error: {0}; link re-initialised, waiting for SYN (§4.6 1)")]
    Line(LineError),
    /// A received message with a parity error (§4.6 1 (3)).
    #[error("{error}; link re-initialised, waiting for SYN (§4.6 1 (3))")]
    FrameParity {
        /// The parity error.
        error: FrameError,
    },
    /// Protocol A: DR or CD went off (§4.6 1 (4)).
    #[error(
        "data set ready (DR) or carrier detect (CD) off; waiting for the line, then for SYN (§4.6 1 (4))"
    )]
    DataSetReadyOff,
    /// Protocol B: the board turns ER off at a CNC reset or alarm without notification, or
    /// the line is cut (§6.4 (1)).
    #[error("data set ready (DR) went off on a Protocol B line (§6.4 (1))")]
    DataSetReadyOffB,
    /// More retries than Ne (§4.6 1 (7)).
    #[error(
        "retry count exceeded: {count} retries > Ne = {ne} (§4.6 1 (7)); link re-initialised, waiting for SYN"
    )]
    RetryOver {
        /// Retries made.
        count: u16,
        /// Retry count parameter Ne (§4.5).
        ne: u16,
    },
    /// No message from the board within the time-out after the host's last message (§4.6 1 (6)).
    #[error(
        "no message from the board for {waited:?} after the host's last message (§4.3 (3), (4); §4.6 1 (6)); link re-initialised, waiting for SYN"
    )]
    TimeOut {
        /// How long the host waited.
        waited: Duration,
    },
    /// No SAT came since the link initialised, although the host answered GTDs with EOD: the
    /// CNC was reading when the link came up, so the SET with the cell file's parameters and
    /// n has not gone (§4.4.1 SAT, §4.5; protocol notes 19).
    #[error(
        "the cell file's parameters (Nb..Tw, n) are not applied: the board has sent no SAT since the link initialised, its CNC was already reading ({probes} GTDs answered with EOD did not make it poll); reset the CNC (or end its read) so that the board polls with SAT and takes them; meanwhile programs go as Protocol A DATs within the power-on Nb and No, and G05 streams are refused (protocol notes 19)"
    )]
    ParamsNotApplied {
        /// GTDs answered with EOD to make the board poll with SAT.
        probes: u8,
    },
    /// The board's SAT reports alarm status (§4.4.2 1).
    #[error(
        "remote buffer in alarm status: {} (SAT byte 3 = {:X}, §4.4.2 1)",
        board_alarm_text(*.cause),
        .cause.digit()
    )]
    BoardAlarm {
        /// Byte 3 of the SAT: why the board went to alarm status.
        cause: AlarmCause,
    },
}

/// What a board in alarm status says of its cause (§4.4.2 1, byte 3).
pub fn board_alarm_text(cause: AlarmCause) -> &'static str {
    match cause {
        AlarmCause::NcAlarm => "NC alarm",
        AlarmCause::ChecksumRetryOver => "checksum error, retry over (SR0945)",
        AlarmCause::OverrunRetryOver => "overrun error, retry over (SR0945)",
        AlarmCause::CommandError => "unexpected response received, command error (SR0947/SR0948)",
        AlarmCause::Other(_) => "unknown cause",
    }
}

impl LinkAlarm {
    /// Whether the CNC's side reports it: a SAT showing the remote buffer in alarm status
    /// (§4.4.2 1) is the board's and its CNC's state, shown as a CNC alarm; every other
    /// link alarm is the link's own.
    pub fn is_cnc_side(&self) -> bool {
        matches!(self, LinkAlarm::BoardAlarm { .. })
    }

    /// Its code as every surface shows it: the manual's number (§11) where it has one, else
    /// cellgate's own ([`crate::codes::alarm`]).
    pub fn code(&self) -> &'static str {
        use crate::codes::alarm;
        match (self.cnc_alarm(), self) {
            (Some(a), _) => a.number(),
            (None, LinkAlarm::BoardAlarm { cause }) if *cause == AlarmCause::NcAlarm => {
                alarm::SAT_NC
            }
            (None, LinkAlarm::BoardAlarm { .. }) => alarm::SAT_OTHER,
            (None, _) => alarm::LINK,
        }
    }

    /// The CNC alarm the board raises for this failure, where the manual names one (§11).
    pub fn cnc_alarm(&self) -> Option<CncAlarm> {
        match self {
            LinkAlarm::Line(LineError::Framing | LineError::Overrun) => {
                Some(CncAlarm::Sr0946FramingOverrun)
            }
            LinkAlarm::Line(_) | LinkAlarm::FrameParity { .. } => None,
            LinkAlarm::DataSetReadyOff | LinkAlarm::DataSetReadyOffB => {
                Some(CncAlarm::Sr0855DataSetReadyDown)
            }
            LinkAlarm::RetryOver { .. } => Some(CncAlarm::Sr0945RetryOver),
            LinkAlarm::ParamsNotApplied { .. } => None,
            LinkAlarm::TimeOut { .. } => Some(CncAlarm::Sr0944TimeOut),
            LinkAlarm::BoardAlarm { cause } => match cause {
                AlarmCause::ChecksumRetryOver | AlarmCause::OverrunRetryOver => {
                    Some(CncAlarm::Sr0945RetryOver)
                }
                AlarmCause::CommandError => Some(CncAlarm::Sr0947InvalidResponse),
                AlarmCause::NcAlarm | AlarmCause::Other(_) => None,
            },
        }
    }
}

/// Why the host abandoned a program.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum AbortReason {
    /// Cancelled by the owner of the engine (`Cancel`).
    #[error("cancelled")]
    Cancelled,
    /// Protocol A: the CNC was reset (RST, §4.4.1).
    #[error("CNC reset (RST, §4.4.1): the CNC discards the data it had (§8.2)")]
    CncReset,
    /// Protocol A: the CNC raised an alarm (ALM, §4.4.1).
    #[error("CNC alarm (ALM, §4.4.1)")]
    CncAlarm,
    /// Expansion Protocol A: the board sent CAN during the packet transmission (§5.3 1).
    #[error("CNC reset or alarm: the board sent CAN during the packet transmission (§5.3 1)")]
    CncStop,
    /// Protocol B: the board sent SYN, a CNC reset (§6.1.2).
    #[error("CNC reset (SYN, §6.1.2)")]
    ResetNotice,
    /// Protocol B: the board sent NAK, a CNC alarm (§6.1.2).
    #[error("CNC alarm (NAK, §6.1.2)")]
    AlarmNotice,
    /// The program cannot be sent as it is.
    #[error("{0}")]
    Program(#[from] ProgramSendError),
    /// The link failed.
    #[error("link lost: {0}")]
    Link(LinkAlarm),
    /// The board re-initialised the link (SYN, §4.7).
    #[error("the board re-initialised the link (SYN, §4.7)")]
    BoardReinit,
    /// The remote buffer went to alarm status; SAT byte 3 gives the cause.
    #[error("the remote buffer went to alarm status: {}", board_alarm_text(*.0))]
    BoardAlarm(AlarmCause),
    /// The board asked to resend a packet that is not among the last packets kept (§5.3 2).
    #[error(
        "the board asked to resend packet {no:02X}h, which is not among the last packets kept (§5.3 2)"
    )]
    UnknownPacket {
        /// The packet number the board asked for.
        no: u8,
    },
    /// A new program replaced it before it was finished.
    #[error("replaced by a new program before it was finished")]
    Replaced,
    /// A G05 stream on a link whose board took none of the cell file's parameters (no SAT
    /// since the link initialised): refused rather than sent at a packet length and timing
    /// nobody set (§9.2; protocol notes 19).
    #[error(
        "refused: the board's parameters are not applied (no SAT since the link initialised, its CNC was reading), so a G05 stream could starve the CNC; reset the CNC and open the stream again (protocol notes 19)"
    )]
    ParamsNotApplied,
}

impl AbortReason {
    /// The CNC itself stopped the program (reset or alarm), rather than the link or the host.
    pub fn by_cnc(&self) -> bool {
        matches!(
            self,
            AbortReason::CncReset
                | AbortReason::CncAlarm
                | AbortReason::CncStop
                | AbortReason::ResetNotice
                | AbortReason::AlarmNotice
        )
    }

    /// The CNC was reset (not an alarm): the program is abandoned, as a cancellation is.
    pub fn is_reset(&self) -> bool {
        matches!(self, AbortReason::CncReset | AbortReason::ResetNotice)
    }

    /// The CNC alarm number behind the abort, where one applies.
    pub fn cnc_alarm(&self) -> Option<CncAlarm> {
        match self {
            AbortReason::Link(alarm) => alarm.cnc_alarm(),
            AbortReason::BoardAlarm(cause) => LinkAlarm::BoardAlarm { cause: *cause }.cnc_alarm(),
            _ => None,
        }
    }
}

impl BusCode for AbortReason {
    fn code(&self) -> pb::ErrorCode {
        match self {
            // A reset abandons the program as a cancellation does; it is reported cancelled.
            // CAN: "CNC reset or alarm" (§5.3 1); a reset ends as a cancellation anyway.
            AbortReason::CncAlarm | AbortReason::AlarmNotice | AbortReason::CncStop => {
                pb::ErrorCode::CncAlarm
            }
            _ => pb::ErrorCode::LinkFailed,
        }
    }
}

#[cfg(test)]
mod tests;
