//! The host computer's side of Protocol B and Expansion Protocol B (§6, §7), sans-IO.
//!
//! [`ProtocolBHost`] is fed received bytes, line errors, modem lines, commands and the time; it
//! hands out bytes to transmit and events. There is no message framing in Protocol B: the board
//! steers the host with single control codes (§6.2) and everything the host sends is the data
//! part (§8.1). Program bytes stream through a bounded buffer ([`ProtocolBConfig::max_buffer`]).
//!
//! # Download: the remote buffer receives data (§6.1.1 1, §6.1.2 2)
//!
//! - Nothing is sent until the board sends DC1 (a read request). Then the program flows.
//! - DC3 stops the host. The board tolerates less than the overrun allowance after DC3 (§6.3:
//!   512 characters in Protocol B; 1280 in Expansion Protocol B, protocol notes 12). The driver
//!   writes what [`Engine::poll_transmit`] returns completely before asking again, so the host
//!   hands out pieces of at most [`ProtocolBConfig::tx_piece`] bytes: after DC3 at most one
//!   piece is still on its way. [`ProtocolBHost::sent_since_dc3`] counts what was handed out
//!   after the last DC3, for tests and diagnostics.
//! - The next DC1 resumes with the data immediately after that sent last (§6.1.1 1 (6)).
//! - The program ends at EOR `%` (protocol notes 8; EOR is appended when the source has none,
//!   as in Protocol A). Once the EOR has been handed out the program is reported done. The host
//!   then waits for the CNC's DC3 that ends the read, and starts the next program only on a
//!   DC1 after it: one program per read request (protocol notes 13), since a flow-control DC1
//!   cannot be told from a new read request and the CNC ignores data after EOR (§8.2).
//!
//! # CNC reset and alarm (§6.1.2, §6.4)
//!
//! With notification on (parameter 5003#3 = 1) the board sends SYN on a CNC reset and NAK on a
//! CNC alarm: alone while idle, after DC3 while it receives, after DC4 while it punches. The
//! host reports [`EngineEvent::CncReset`] / [`EngineEvent::CncAlarm`], stops, and aborts a
//! program that has started and is not completely sent. A program that has not started stays
//! queued for the next read request. The notices are reported even with notification off,
//! since a board that sends them means them. With notification off the board instead ends the
//! read with DC3 and turns ER off (§6.4 (1)), which the host sees as DR off.
//!
//! # Punch-out: the remote buffer sends data (§6.1.1 2, §6.1.2 2)
//!
//! DC2 starts punched data; every byte up to DC4 is the punched program, passed on as it was
//! received (parity bit included) in [`EngineEvent::Punched`] pieces of at most
//! [`ProtocolBConfig::punch_piece`] bytes. A piece also ends at each program's EOR (the `%`
//! after a significant character, protocol notes 8) and at DC4, so a punch-out of several
//! programs comes out program by program. Punched bytes held by the engine (not yet taken with
//! [`Engine::poll_event`]) are bounded: above [`ProtocolBConfig::punch_high_water`] the host
//! sends DC3 (method (b) of §6.1.1 2 (3)) and, with [`ProtocolBConfig::rs_flow`], also turns
//! RS off, which the board sees as CS off (method (a)); once the held data has dropped to half
//! of that it turns RS on and resumes the board with DC1 when notification is on and DC2 when
//! it is off (protocol notes 11). Bytes beyond [`ProtocolBConfig::max_buffer`] (a board that overruns) are dropped with
//! a [`EngineEvent::ProtocolError`].
//!
//! # Control codes (§6.2)
//!
//! The board sends DC3, NAK and SYN with the parity bit in ISO (93h, 95h, 96h) and without it
//! in ASCII (13h, 15h, 16h); DC1, DC2 and DC4 are the same in both. The host recognises each
//! code with or without bit 7, whatever the configured code (protocol notes 10 reads monitor
//! codes the same way), and sends its own DC1, DC2 and DC3 in the configured code. Any other
//! byte outside a punch-out is ignored with a `ProtocolError`.
//!
//! # Not in Protocol B
//!
//! There are no DO/DI signals and no buffer clear: `SetDo`, `ReadDi` and `ClearBuffer` are
//! answered with a `ProtocolError`. There is no time supervision on the host side: the board
//! may keep the host stopped as long as its CNC does not read.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use bytes::Bytes;

use crate::engine::{Engine, FrameCounts, LineError, ModemIn, ModemOut};
use crate::fanuc::code::{DC1, DC2, DC3, DC4, EOR, NAK, SYN, is_significant};
use crate::fanuc::error::{AbortReason, LinkAlarm, ProtocolError};
use crate::fanuc::host::{
    Confirmation, EngineCommand, EngineEvent, HostEngine, LinkState, PunchDamage,
};
use crate::fanuc::program::Program;
use crate::fanuc::{CodeSystem, Protocol};

/// Characters a Protocol B board takes after its DC3 (§6.3: "less than 512 characters"):
/// the host's limit, and past it the board's SR0856 (§11).
pub const OVERRUN_B: usize = 512;
/// Characters the host may send after an Expansion Protocol B board's DC3 (§7: 1280).
pub const OVERRUN_EXPANSION_B: usize = 1280;
/// Characters after its DC3 past which an Expansion Protocol B board raises SR0856: the
/// §6.3 table and §11 say 2560, §7 says 1280; the host keeps within §7's
/// [`OVERRUN_EXPANSION_B`], a board alarms only past this (protocol notes 12).
pub const OVERRUN_EXPANSION_B_ALARM: usize = 2560;

/// Settings of a Protocol B / Expansion Protocol B host link.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProtocolBConfig {
    /// ISO or ASCII (parameter 5000#2: 0 = ISO, 1 = ASCII for Protocol B): the code of the
    /// control codes the host sends (§6.2).
    pub code: CodeSystem,
    /// Expansion Protocol B (§7) rather than Protocol B.
    pub expansion: bool,
    /// CNC reset/alarm is posted to the host (§6.1.2; the manual names the parameter bit
    /// 5000#3 "ETX" in §6.1 and 5003#3 in §6.4): selects DC1 rather than DC2 to resume a
    /// punch-out (protocol notes 11).
    pub notify_alarm_reset: bool,
    /// The board's overrun allowance after DC3 (§6.3, §7): [`OVERRUN_B`] or
    /// [`OVERRUN_EXPANSION_B`].
    pub overrun_allowance: usize,
    /// Most bytes handed out per [`Engine::poll_transmit`], and so the most that can still go
    /// out after a DC3. At most half the overrun allowance.
    pub tx_piece: usize,
    /// Most program bytes held at once ([`HostEngine::data_wanted`] is the free space), and
    /// most punched bytes held.
    pub max_buffer: usize,
    /// Largest [`EngineEvent::Punched`] piece.
    pub punch_piece: usize,
    /// Punched bytes held above which the host sends DC3 to the board.
    pub punch_high_water: usize,
    /// Also hold a punch-out with RS off (the board's CS, method (a) of §6.1.1 2 (3)) while
    /// it is stopped by DC3. Where the transport carries no modem lines (a TCP device
    /// server) only the DC3 acts.
    pub rs_flow: bool,
    /// Line time of one character (`LineSettings::char_time`): when a byte handed out has
    /// reached the board, for acknowledged offsets and the end of a program. Zero when unknown.
    pub char_time: Duration,
    /// The line carries the board's ER (our DR): a serial port or the simulated line does, a
    /// TCP device server does not. Without it and without notification, the end of a read
    /// cannot be told from a CNC reset or alarm (§6.4 (1)).
    pub er_visible: bool,
}

impl ProtocolBConfig {
    /// The settings for Protocol B (`expansion` false) or Expansion Protocol B.
    pub fn new(code: CodeSystem, expansion: bool, notify_alarm_reset: bool) -> Self {
        let overrun_allowance = if expansion {
            OVERRUN_EXPANSION_B
        } else {
            OVERRUN_B
        };
        let max_buffer = 64 * 1024;
        ProtocolBConfig {
            code,
            expansion,
            notify_alarm_reset,
            overrun_allowance,
            tx_piece: 64,
            max_buffer,
            punch_piece: 16 * 1024,
            // Room for the board's overrun after DC3, twice over (§6.3).
            punch_high_water: max_buffer - 2 * overrun_allowance,
            rs_flow: true,
            char_time: Duration::ZERO,
            er_visible: true,
        }
    }

    /// The settings for `protocol`, or `None` for the Protocol A family.
    pub fn for_protocol(
        protocol: Protocol,
        code: CodeSystem,
        notify_alarm_reset: bool,
    ) -> Option<Self> {
        match protocol {
            Protocol::B => Some(Self::new(code, false, notify_alarm_reset)),
            Protocol::ExpansionB => Some(Self::new(code, true, notify_alarm_reset)),
            Protocol::A | Protocol::ExpansionA => None,
        }
    }

    /// Every problem of these settings.
    pub fn validate(&self) -> Vec<ProtocolBProblem> {
        let mut problems = Vec::new();
        if self.tx_piece == 0 || self.tx_piece > self.overrun_allowance / 2 {
            problems.push(ProtocolBProblem::TxPiece {
                piece: self.tx_piece,
                allowance: self.overrun_allowance,
            });
        }
        if self.punch_piece == 0 || self.punch_piece > self.max_buffer {
            problems.push(ProtocolBProblem::PunchPiece {
                piece: self.punch_piece,
                max: self.max_buffer,
            });
        }
        if self.punch_high_water == 0
            || self.punch_high_water.saturating_add(self.overrun_allowance) > self.max_buffer
        {
            problems.push(ProtocolBProblem::HighWater {
                high: self.punch_high_water,
                allowance: self.overrun_allowance,
                max: self.max_buffer,
            });
        }
        problems
    }
}

impl Default for ProtocolBConfig {
    fn default() -> Self {
        ProtocolBConfig::new(CodeSystem::default(), false, true)
    }
}

/// One problem with a [`ProtocolBConfig`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ProtocolBProblem {
    /// `tx_piece` is zero or above half the overrun allowance after DC3 (§6.3).
    #[error(
        "tx_piece = {piece} must be between 1 and half the overrun allowance after DC3 ({allowance} characters, §6.3)"
    )]
    TxPiece {
        /// The `tx_piece` given, bytes.
        piece: usize,
        /// The overrun allowance after DC3, characters.
        allowance: usize,
    },
    /// `punch_piece` is zero or above `max_buffer`.
    #[error("punch_piece = {piece} must be between 1 and max_buffer = {max}")]
    PunchPiece {
        /// The `punch_piece` given, bytes.
        piece: usize,
        /// The `max_buffer` given, bytes.
        max: usize,
    },
    /// `punch_high_water` is zero or leaves no room for the overrun after DC3 within `max_buffer`.
    #[error(
        "punch_high_water = {high} must be above zero and leave room for the board's overrun after DC3 ({allowance} characters, §6.3) within max_buffer = {max}"
    )]
    HighWater {
        /// The `punch_high_water` given, bytes.
        high: usize,
        /// The overrun allowance after DC3, characters.
        allowance: usize,
        /// The `max_buffer` given, bytes.
        max: usize,
    },
}

/// A [`ProtocolBConfig`] that cannot run, with every problem found.
pub type InvalidConfig = crate::engine::InvalidSettings<ProtocolBProblem>;

/// What the board is doing on its side of the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Rx {
    /// Sending control codes only.
    Control,
    /// Punching out: data until DC4 (§6.1.1 2).
    Punch,
}

/// The host side of a Protocol B / Expansion Protocol B link.
pub struct ProtocolBHost {
    /// Control codes received and sent: Protocol B has no frames, its control codes are what
    /// passes for them; punched and NC data are counted as bytes only.
    frames: FrameCounts,
    cfg: ProtocolBConfig,
    events: VecDeque<EngineEvent>,
    state: LinkState,
    line_up: bool,
    cs: bool,
    program: Option<Program>,
    /// The board asked for data (DC1) and has not stopped the host (DC3) since.
    flowing: bool,
    /// A program was completely sent in this read request: the next one waits for the DC3
    /// that ends the read and a DC1 after it (protocol notes 13).
    await_next_read: bool,
    /// Program bytes handed out since the last DC3 arrived.
    sent_since_dc3: u64,
    /// The board stopped the current program with DC3 (its buffer filled) at least once: a
    /// CNC that reads slower than the line, whose DC3 near the EOR may be flow control.
    stopped_this_program: bool,
    /// The punch-out flow-control code the host owes the board (DC3, or DC1 / DC2 to resume);
    /// only the latest instruction matters.
    ctl_out: Option<u8>,
    rx: Rx,
    punch: Vec<u8>,
    /// Punched bytes in queued `Punched` events not yet taken.
    punch_queued: usize,
    /// The host stopped the board's punch-out with DC3.
    punch_paused: bool,
    /// A significant character was punched since the last EOR: the next `%` ends a program.
    punch_body: bool,
    /// When the last byte handed out reaches the board, by the line's character time.
    line_end: Instant,
    /// (when it reaches the board, program bytes up to it) of pieces handed out and not yet
    /// acknowledged; oldest first, at most [`MAX_MARKS`].
    marks: VecDeque<(Instant, u64)>,
    /// Program bytes of the current program the board has acknowledged: those that reached
    /// it before a control code it sent.
    acked: u64,
    /// The current program went out through its EOR and awaits the end of the read.
    finishing: Option<Finishing>,
}

/// A program sent through its EOR, not confirmed yet.
#[derive(Debug, Clone, Copy)]
struct Finishing {
    /// When the EOR reaches the board at the nominal line rate: a DC3 before it is flow
    /// control (see `ProtocolBHost::end_of_read`).
    eor_on_board: Instant,
    /// A DC3 after the EOR went out was taken as flow control, and no DC1 came since: a
    /// board stops the host once per DC1, so a second DC3 ends the read.
    stopped: bool,
    /// A DC1 came after such a DC3: if no DC3 follows by this time (the EOR has reached the
    /// board even on a line slower than its estimate), that DC3 ended the read and the DC1
    /// asked for the next program (protocol notes 20).
    next_read_at: Option<Instant>,
    /// The DC3 that ends the read came; the program is the board's unless a reset or alarm
    /// notice, or ER off, follows by then (§6.1.2 (7), §6.4).
    confirm_at: Option<Instant>,
}

/// Acknowledgement marks kept at most; past it the oldest go, which only makes acknowledged
/// offsets coarser, never wrong.
const MAX_MARKS: usize = 256;

/// How long after the DC3 that ends a read a SYN or NAK may still come (it follows the DC3
/// at once, §6.1.2 (7)), in characters and at least.
const NOTICE_CHARS: u32 = 20;
const NOTICE_MIN: Duration = Duration::from_millis(10);
/// How long after that DC3 ER may still go off (§6.4 (1)): a few reads of the modem lines.
const ER_OFF_SETTLE: Duration = Duration::from_millis(150);

impl std::fmt::Debug for ProtocolBHost {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ProtocolBHost")
            .field("state", &self.state)
            .field("flowing", &self.flowing)
            .field("await_next_read", &self.await_next_read)
            .field("rx", &self.rx)
            .field("punch_held", &self.punch_held())
            .finish_non_exhaustive()
    }
}

impl ProtocolBHost {
    /// A host engine with these settings, or every problem with them.
    pub fn new(config: ProtocolBConfig, now: Instant) -> Result<Self, InvalidConfig> {
        InvalidConfig::check("Protocol B", config.validate())?;
        Ok(ProtocolBHost {
            frames: FrameCounts::default(),
            cfg: config,
            events: VecDeque::from([EngineEvent::State(LinkState::Ready)]),
            state: LinkState::Ready,
            line_up: true,
            cs: true,
            program: None,
            flowing: false,
            await_next_read: false,
            sent_since_dc3: 0,
            stopped_this_program: false,
            ctl_out: None,
            rx: Rx::Control,
            punch: Vec::new(),
            punch_queued: 0,
            punch_paused: false,
            punch_body: false,
            line_end: now,
            marks: VecDeque::new(),
            acked: 0,
            finishing: None,
        })
    }

    /// The settings the engine runs with.
    pub fn config(&self) -> &ProtocolBConfig {
        &self.cfg
    }

    /// Program bytes handed out for transmission since the last DC3 arrived (all of them when
    /// no DC3 came yet). Right after a DC3 it is zero and stays so until the next DC1.
    pub fn sent_since_dc3(&self) -> u64 {
        self.sent_since_dc3
    }

    /// The board has asked for data (DC1) and not stopped the host since.
    pub fn flowing(&self) -> bool {
        self.flowing
    }

    /// Punched bytes held by the engine: received and not yet taken with `poll_event`.
    pub fn punch_held(&self) -> usize {
        self.punch.len() + self.punch_queued
    }

    /// Program bytes buffered and not yet handed out.
    pub fn program_buffered(&self) -> usize {
        self.program.as_ref().map_or(0, Program::buffered)
    }

    fn emit(&mut self, event: EngineEvent) {
        self.events.push_back(event);
    }

    fn protocol_error(&mut self, error: ProtocolError) {
        tracing::debug!(%error, "Protocol B");
        self.emit(EngineEvent::ProtocolError {
            error,
            retried: false,
        });
    }

    /// The board has (or had) data of the current program: part of it went out, or all of
    /// it and its end is not confirmed yet.
    fn program_started(&self) -> bool {
        self.program.as_ref().is_some_and(|p| p.sent > 0) || self.finishing.is_some()
    }

    /// A control code from the board arrived at `now`: every byte that had reached the board
    /// before it was received (the line carries bytes in order; Protocol B acknowledges
    /// nothing more precisely).
    fn ack_until(&mut self, now: Instant) {
        let mut offset = self.acked;
        while let Some(&(at, upto)) = self.marks.front() {
            if at > now {
                break;
            }
            offset = upto;
            self.marks.pop_front();
        }
        if offset > self.acked {
            self.acked = offset;
            self.emit(EngineEvent::Acked { offset });
        }
    }

    /// A piece of `len` program bytes, up to `upto`, was handed out at `now`.
    fn handed_out(&mut self, now: Instant, len: usize, upto: u64) {
        let line_time = self
            .cfg
            .char_time
            .saturating_mul(u32::try_from(len).unwrap_or(u32::MAX));
        self.line_end = self.line_end.max(now) + line_time;
        if self.marks.len() >= MAX_MARKS {
            self.marks.pop_front();
        }
        self.marks.push_back((self.line_end, upto));
    }

    /// How long the end of a read waits for a reset or alarm that would undo it.
    fn settle_time(&self) -> Duration {
        if self.cfg.notify_alarm_reset {
            self.cfg
                .char_time
                .saturating_mul(NOTICE_CHARS)
                .max(NOTICE_MIN)
        } else {
            ER_OFF_SETTLE
        }
    }

    /// How much earlier than the host's estimate the EOR may reach the board: a device server
    /// whose UART runs a little fast, or one that passes bytes on as they come, empties the
    /// transport's window (at most the overrun allowance) sooner than the nominal line rate
    /// says, and the last piece was handed out with it.
    fn early_arrival(&self) -> Duration {
        let chars = self.cfg.overrun_allowance + self.cfg.tx_piece;
        self.cfg
            .char_time
            .saturating_mul(u32::try_from(chars).unwrap_or(u32::MAX))
    }

    /// A DC3 arrived while the program's end is awaited.
    ///
    /// After the EOR's estimated arrival it ends the read. Before, it is flow control if the
    /// board stopped this program before (a CNC reading slower than the line keeps its buffer
    /// full, and taking its stop for the end would send the next program into a read that
    /// ignores it: protocol notes 13); a board that never stopped it ends the read when its
    /// DC3 comes within [`early_arrival`](Self::early_arrival) of the estimate. Otherwise a
    /// CNC that reads at line speed behind a fast device server would be waited for forever.
    ///
    /// The estimate is at the nominal rate, and a line that runs fast (a device server whose
    /// UART clock is off) delivers the EOR sooner, so a DC3 taken for flow control may have
    /// been the end: a second DC3 with no DC1 between ends the read (no flow control sends
    /// two), and so does a DC1 after it ([`Self::next_read_after_stop`]). The end of a
    /// program does not hang on the line keeping its nominal rate (protocol notes 20).
    fn end_of_read(&mut self, now: Instant) {
        let settle = self.settle_time();
        let early = if self.stopped_this_program {
            Duration::ZERO
        } else {
            self.early_arrival()
        };
        let Some(f) = self.finishing.as_mut() else {
            return;
        };
        if f.confirm_at.is_some() {
            return;
        }
        if now + early >= f.eor_on_board || f.stopped || f.next_read_at.is_some() {
            // After the EOR's arrival; or a second stop; or the DC3 after a DC1 that was a
            // resumption after all: the end of the read.
            f.next_read_at = None;
            f.confirm_at = Some(now + settle);
        } else {
            f.stopped = true;
            self.stopped_this_program = true;
        }
    }

    /// A DC1 while the program's end is awaited, after a DC3 that was taken for flow control.
    /// It resumes a read that still takes the program, or it is the next read's request
    /// after a DC3 that ended the read early (a line faster than its nominal rate): the
    /// board asks for nothing more in a read once it holds the EOR (protocol notes 13), so
    /// a read that goes on ends with a DC3 once the EOR has arrived. If none comes by the
    /// EOR's latest arrival, the read ended and this DC1 asks for the next program.
    fn next_read_after_stop(&mut self, now: Instant) {
        let early = self.early_arrival();
        let Some(f) = self.finishing.as_mut() else {
            return;
        };
        if f.confirm_at.is_none() && f.stopped {
            let at = (f.eor_on_board + early).max(now);
            tracing::debug!(
                ?at,
                "DC1 after a stop with the EOR out: the read may have ended"
            );
            f.next_read_at = Some(at);
        }
        f.stopped = false;
    }

    /// No DC3 came by the time the EOR had surely arrived, after a DC1 that followed a stop:
    /// that stop ended the read, and the DC1 asked for the next program.
    fn next_read_due(&mut self, now: Instant) {
        let Some(f) = self.finishing.as_mut() else {
            return;
        };
        if f.next_read_at.is_some_and(|t| now >= t) {
            f.next_read_at = None;
            f.confirm_at = Some(now);
            self.confirm(now, true);
            self.flowing = true;
            self.update_state();
        }
    }

    /// The end of the read stood (its settle time passed, or the board asked for the next
    /// read with DC1, which no reset or alarm does): the board holds the whole program.
    fn confirm(&mut self, now: Instant, next_read: bool) {
        let Some(f) = self.finishing else { return };
        match f.confirm_at {
            Some(t) if next_read || now >= t => {}
            _ => return,
        }
        self.finishing = None;
        // The DC3 came after the EOR's line time: every byte arrived.
        self.ack_until(f.eor_on_board);
        let confirmation = if self.cfg.notify_alarm_reset || self.cfg.er_visible {
            Confirmation::EndOfRead
        } else {
            Confirmation::Unverified
        };
        tracing::info!(
            bytes = self.acked,
            ?confirmation,
            "program delivered (end of read)"
        );
        self.emit(EngineEvent::ProgramDone { confirmation });
        // The next program goes at the next read request's DC1 (protocol notes 13).
        self.await_next_read = false;
        self.flowing = false;
        self.update_state();
    }

    fn update_state(&mut self) {
        let state = if !self.line_up {
            LinkState::LineDown
        } else if self.rx == Rx::Punch {
            LinkState::Receiving
        } else if self.program_started() {
            LinkState::Sending
        } else {
            LinkState::Ready
        };
        if state != self.state {
            self.state = state;
            self.emit(EngineEvent::State(state));
        }
    }

    /// Abandons the current program. One the board has part of ends its read request: the
    /// next program waits for a new one.
    fn abort_program(&mut self, reason: AbortReason, cancelled: bool) {
        let started = match (self.program.take(), self.finishing.take()) {
            (Some(p), _) => p.sent > 0,
            (None, Some(_)) => true,
            (None, None) => return,
        };
        tracing::info!(acked = self.acked, %reason, "program aborted");
        if started {
            self.await_next_read = true;
        }
        self.marks.clear();
        self.emit(EngineEvent::ProgramAborted { reason, cancelled });
    }

    /// A CNC reset (SYN) or alarm (NAK) notice (§6.1.2, §6.4 (2)).
    fn on_notice(&mut self, reset: bool) {
        self.emit(if reset {
            EngineEvent::CncReset
        } else {
            EngineEvent::CncAlarm
        });
        self.flowing = false;
        if self.program_started() {
            let reason = if reset {
                AbortReason::ResetNotice
            } else {
                AbortReason::AlarmNotice
            };
            self.abort_program(reason, false);
        }
        // The read is over; the board asks again with DC1.
        self.await_next_read = false;
    }

    fn on_control(&mut self, now: Instant, b: u8, garbage: &mut usize) {
        if matches!(CodeSystem::strip(b), DC1 | DC2 | DC3 | DC4 | NAK | SYN) {
            self.ack_until(now);
        }
        match CodeSystem::strip(b) {
            DC1 => {
                self.next_read_after_stop(now);
                self.confirm(now, true);
                if self.await_next_read {
                    // Flow control of the read whose program already went (protocol notes 13).
                    tracing::trace!("DC1 before the read ended: no new program yet");
                } else {
                    self.flowing = true;
                }
            }
            DC3 => {
                self.flowing = false;
                self.sent_since_dc3 = 0;
                if self.finishing.is_some() {
                    // The end of the read, once the EOR can have arrived; before, flow control.
                    self.end_of_read(now);
                } else {
                    if self.program.is_some() {
                        self.stopped_this_program = true;
                    }
                    self.await_next_read = false;
                }
            }
            DC2 => {
                self.rx = Rx::Punch;
                self.punch_paused = false;
                self.punch_body = false;
            }
            SYN => self.on_notice(true),
            NAK => self.on_notice(false),
            DC4 => tracing::trace!("DC4 outside a punch-out"),
            _ => *garbage += 1,
        }
    }

    /// Passes the punched bytes held on as an event.
    fn flush_punch(&mut self) {
        if self.punch.is_empty() {
            return;
        }
        let data = Bytes::from(std::mem::take(&mut self.punch));
        self.punch_queued += data.len();
        self.emit(EngineEvent::Punched { data });
    }

    fn on_punch_byte(&mut self, b: u8, dropped: &mut usize) {
        if CodeSystem::strip(b) == DC4 {
            self.flush_punch();
            self.rx = Rx::Control;
            // The board has finished; a pause the host asked for ends with the punch-out.
            self.punch_paused = false;
            return;
        }
        if self.punch_held() >= self.cfg.max_buffer {
            if *dropped == 0 {
                // The program being punched has a hole from here on.
                self.flush_punch();
                self.emit(EngineEvent::PunchDamaged {
                    cause: PunchDamage::Dropped,
                });
            }
            *dropped += 1;
            return;
        }
        self.punch.push(b);
        // A piece ends with each program's EOR (protocol notes 8), so that a punch-out of
        // several programs comes out program by program.
        let c = CodeSystem::strip(b);
        let eor = c == EOR && self.punch_body;
        if c == EOR {
            self.punch_body = false;
        } else if is_significant(c) {
            self.punch_body = true;
        }
        if eor || self.punch.len() >= self.cfg.punch_piece {
            self.flush_punch();
        }
        if !self.punch_paused && self.punch_held() > self.cfg.punch_high_water {
            tracing::debug!(held = self.punch_held(), "punch-out paused with DC3");
            self.punch_paused = true;
            self.ctl_out = Some(self.cfg.code.control(DC3));
        }
    }

    /// Resumes a paused punch-out once the held data has been taken (protocol notes 11).
    fn maybe_resume_punch(&mut self) {
        if self.punch_paused && self.punch_held() <= self.cfg.punch_high_water / 2 {
            self.punch_paused = false;
            let resume = if self.cfg.notify_alarm_reset {
                DC1
            } else {
                DC2
            };
            tracing::debug!(held = self.punch_held(), "punch-out resumed");
            // A DC3 not sent yet never stopped the board: drop it instead of resuming.
            self.ctl_out = match self.ctl_out {
                Some(_) => None,
                None => Some(self.cfg.code.control(resume)),
            };
        }
    }
}

impl Engine for ProtocolBHost {
    type Command = EngineCommand;
    type Event = EngineEvent;

    fn handle_input(&mut self, now: Instant, bytes: &[u8]) {
        if !self.line_up {
            // DR off: nothing on the line is trusted.
            return;
        }
        let mut garbage = 0usize;
        let mut first_garbage = 0u8;
        let mut dropped = 0usize;
        for &b in bytes {
            match self.rx {
                Rx::Punch => self.on_punch_byte(b, &mut dropped),
                Rx::Control => {
                    let before = garbage;
                    self.on_control(now, b, &mut garbage);
                    if garbage == before {
                        self.frames.received += 1;
                    }
                    if before == 0 && garbage == 1 {
                        first_garbage = b;
                    }
                }
            }
        }
        if garbage > 0 {
            self.protocol_error(ProtocolError::NotControlCodes {
                count: garbage,
                first: first_garbage,
            });
        }
        if dropped > 0 {
            self.protocol_error(ProtocolError::PunchOverflow { dropped });
        }
        self.update_state();
    }

    fn handle_line_error(&mut self, _now: Instant, error: LineError) {
        if !self.line_up {
            return;
        }
        let punching = self.rx == Rx::Punch;
        if punching {
            // What came before the bad character is intact; the program it belongs to is not.
            self.flush_punch();
            self.emit(EngineEvent::PunchDamaged {
                cause: PunchDamage::Line(error),
            });
        }
        self.protocol_error(ProtocolError::LineB { error, punching });
    }

    fn handle_modem(&mut self, _now: Instant, modem: ModemIn) {
        self.cs = modem.cs;
        let up = modem.dr && modem.cd;
        if !up && self.line_up {
            self.line_up = false;
            self.emit(EngineEvent::Alarm(LinkAlarm::DataSetReadyOffB));
            if self.program_started() {
                self.abort_program(AbortReason::Link(LinkAlarm::DataSetReadyOffB), false);
            }
            self.flowing = false;
            self.await_next_read = false;
            self.ctl_out = None;
            if self.rx == Rx::Punch && !self.punch.is_empty() {
                let lost = self.punch.len();
                self.punch.clear();
                self.protocol_error(ProtocolError::PunchCutOff { lost });
            }
            self.rx = Rx::Control;
            self.punch_paused = false;
        } else if up && !self.line_up {
            tracing::info!("Protocol B line up again: waiting for DC1 or DC2");
            self.line_up = true;
        }
        self.update_state();
    }

    fn handle_command(&mut self, _now: Instant, command: EngineCommand) {
        match command {
            EngineCommand::StartProgram { total } => {
                self.abort_program(AbortReason::Replaced, false);
                tracing::debug!(?total, "program queued");
                self.program = Some(Program::new());
                self.acked = 0;
                self.marks.clear();
                self.stopped_this_program = false;
            }
            EngineCommand::ProgramData(data) => match self.program.as_mut() {
                Some(p) => {
                    // Every byte can travel in Protocol B (§8.1): nothing is forbidden.
                    if let Err(e) = p.push(&data, None) {
                        self.abort_program(AbortReason::Program(e), false);
                    }
                }
                None => tracing::trace!(len = data.len(), "program data without a program"),
            },
            // Protocol B sends whatever it has while DC1 is in force: nothing waits anyway.
            EngineCommand::Streaming => {}
            EngineCommand::BinaryData(data) => match self.program.as_mut() {
                Some(p) => p.push_binary(&data),
                None => tracing::trace!(len = data.len(), "binary data without a program"),
            },
            EngineCommand::Primed { text, blocks } => {
                if let Some(p) = self.program.as_mut() {
                    match p.push(&text, None) {
                        Ok(()) => p.push_binary(&blocks),
                        Err(e) => self.abort_program(AbortReason::Program(e), false),
                    }
                }
            }
            EngineCommand::ProgramEnd => {
                if let Some(Err(e)) = self.program.as_mut().map(Program::end) {
                    self.abort_program(AbortReason::Program(e), false);
                }
            }
            EngineCommand::Cancel => self.abort_program(AbortReason::Cancelled, true),
            EngineCommand::SetDo(_) => self.protocol_error(ProtocolError::NotInProtocolB {
                what: "DO output (SDO)",
            }),
            EngineCommand::ReadDi => self.protocol_error(ProtocolError::NotInProtocolB {
                what: "DI input (RDI)",
            }),
            EngineCommand::ClearBuffer => self.protocol_error(ProtocolError::NotInProtocolB {
                what: "clearing the board's buffer (CLB)",
            }),
        }
        self.update_state();
    }

    fn handle_timeout(&mut self, now: Instant) {
        self.confirm(now, false);
        self.next_read_due(now);
    }

    fn poll_transmit(&mut self, now: Instant) -> Option<Vec<u8>> {
        if !self.line_up || !self.cs {
            return None;
        }
        if let Some(code) = self.ctl_out.take() {
            self.frames.sent += 1;
            return Some(vec![code]);
        }
        if !self.flowing || self.await_next_read {
            return None;
        }
        let program = self.program.as_mut()?;
        let piece = program.take(self.cfg.tx_piece);
        if piece.is_empty() {
            return None;
        }
        let done = program.all_sent();
        let upto = program.sent;
        self.sent_since_dc3 += piece.len() as u64;
        self.handed_out(now, piece.len(), upto);
        self.emit(EngineEvent::DataSent {
            data: Bytes::copy_from_slice(&piece),
        });
        if done {
            tracing::debug!("program sent through EOR: waiting for the read to end");
            self.program = None;
            self.await_next_read = true;
            self.finishing = Some(Finishing {
                eor_on_board: self.line_end,
                stopped: false,
                next_read_at: None,
                confirm_at: None,
            });
        }
        self.update_state();
        Some(piece)
    }

    fn poll_event(&mut self) -> Option<EngineEvent> {
        let event = self.events.pop_front()?;
        if let EngineEvent::Punched { data } = &event {
            self.punch_queued = self.punch_queued.saturating_sub(data.len());
            self.maybe_resume_punch();
        }
        Some(event)
    }

    fn poll_timeout(&self) -> Option<Instant> {
        self.finishing
            .and_then(|f| [f.confirm_at, f.next_read_at].into_iter().flatten().min())
    }

    fn modem_out(&self) -> ModemOut {
        ModemOut {
            er: true,
            // CS off stops the board within two characters (§6.1.1 2 (3) (a)); the DC3 sent
            // with it covers boards that ignore CS.
            rs: !(self.cfg.rs_flow && self.punch_paused),
        }
    }

    fn frames(&self) -> FrameCounts {
        self.frames
    }
}

impl HostEngine for ProtocolBHost {
    fn carried(&self, now: Instant) -> Option<u64> {
        let through = self
            .marks
            .iter()
            .take_while(|(at, _)| *at <= now)
            .last()
            .map_or(0, |(_, upto)| *upto);
        Some(through.max(self.acked))
    }

    fn data_wanted(&self) -> usize {
        self.program
            .as_ref()
            .map_or(0, |p| p.wanted(self.cfg.max_buffer))
    }

    fn waiting_for(&self) -> Option<&'static str> {
        if !self.line_up {
            return Some("DR: the board's ER is off or the line is down (§6.4)");
        }
        if self.finishing.is_some() {
            return Some("the DC3 that ends the read (§6.1.1 (7))");
        }
        if self.program.is_none() || self.rx == Rx::Punch {
            return None;
        }
        if self.await_next_read {
            Some("DC3 then DC1: the CNC is ending the last read (protocol notes 13)")
        } else if self.flowing {
            None
        } else if self.program.as_ref().is_some_and(|p| p.sent > 0) {
            Some("DC1 after DC3: the board's buffer is full (§6.3)")
        } else {
            Some("DC1: the CNC has not asked for data (§6.1.1)")
        }
    }
}

#[cfg(test)]
mod tests;
