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

/// Overrun allowance after DC3 in Protocol B (§6.3: "less than 512 characters").
pub const OVERRUN_B: usize = 512;
/// Overrun allowance after DC3 in Expansion Protocol B (§7: 1280 characters; protocol notes 12).
pub const OVERRUN_EXPANSION_B: usize = 1280;

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
    pub fn validate(&self) -> Vec<ConfigProblem> {
        let mut problems = Vec::new();
        if self.tx_piece == 0 || self.tx_piece > self.overrun_allowance / 2 {
            problems.push(ConfigProblem::TxPiece {
                piece: self.tx_piece,
                allowance: self.overrun_allowance,
            });
        }
        if self.punch_piece == 0 || self.punch_piece > self.max_buffer {
            problems.push(ConfigProblem::PunchPiece {
                piece: self.punch_piece,
                max: self.max_buffer,
            });
        }
        if self.punch_high_water == 0
            || self.punch_high_water.saturating_add(self.overrun_allowance) > self.max_buffer
        {
            problems.push(ConfigProblem::HighWater {
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
pub enum ConfigProblem {
    #[error(
        "tx_piece = {piece} must be between 1 and half the overrun allowance after DC3 ({allowance} characters, §6.3)"
    )]
    TxPiece { piece: usize, allowance: usize },
    #[error("punch_piece = {piece} must be between 1 and max_buffer = {max}")]
    PunchPiece { piece: usize, max: usize },
    #[error(
        "punch_high_water = {high} must be above zero and leave room for the board's overrun after DC3 ({allowance} characters, §6.3) within max_buffer = {max}"
    )]
    HighWater {
        high: usize,
        allowance: usize,
        max: usize,
    },
}

/// A [`ProtocolBConfig`] that cannot run, with every problem found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid Protocol B settings: {}", join(.problems))]
pub struct InvalidConfig {
    pub problems: Vec<ConfigProblem>,
}

fn join(problems: &[ConfigProblem]) -> String {
    problems
        .iter()
        .map(ToString::to_string)
        .collect::<Vec<_>>()
        .join("; ")
}

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
    /// When the EOR reaches the board: a DC3 before it is flow control.
    eor_on_board: Instant,
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
    pub fn new(config: ProtocolBConfig, now: Instant) -> Result<Self, InvalidConfig> {
        let problems = config.validate();
        if !problems.is_empty() {
            return Err(InvalidConfig { problems });
        }
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
        if now + early >= f.eor_on_board {
            f.confirm_at = Some(now + settle);
        } else {
            self.stopped_this_program = true;
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
            bytes: piece.len() as u64,
        });
        if done {
            tracing::debug!("program sent through EOR: waiting for the read to end");
            self.program = None;
            self.await_next_read = true;
            self.finishing = Some(Finishing {
                eor_on_board: self.line_end,
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
        self.finishing.and_then(|f| f.confirm_at)
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
mod tests {
    use super::*;
    use crate::fanuc::alarm::CncAlarm;
    use proptest::prelude::*;

    fn host(code: CodeSystem, expansion: bool, notify: bool) -> (ProtocolBHost, Instant) {
        let now = Instant::now();
        let mut h = ProtocolBHost::new(ProtocolBConfig::new(code, expansion, notify), now).unwrap();
        assert_eq!(h.poll_event(), Some(EngineEvent::State(LinkState::Ready)));
        (h, now)
    }

    fn events(h: &mut ProtocolBHost) -> Vec<EngineEvent> {
        std::iter::from_fn(|| h.poll_event()).collect()
    }

    /// Everything the host hands out now.
    /// The board ends the read with DC3, and no notice follows within the settle time.
    fn end_read(h: &mut ProtocolBHost, now: Instant) -> Vec<EngineEvent> {
        h.handle_input(now, &[h.config().code.control(DC3)]);
        let settle = h.poll_timeout().expect("the end of the read settles");
        h.handle_timeout(settle);
        events(h)
    }

    fn done(evs: &[EngineEvent]) -> bool {
        evs.iter()
            .any(|e| matches!(e, EngineEvent::ProgramDone { .. }))
    }

    fn drain_tx(h: &mut ProtocolBHost, now: Instant) -> Vec<u8> {
        let mut out = Vec::new();
        while let Some(piece) = h.poll_transmit(now) {
            assert!(!piece.is_empty());
            assert!(piece.len() <= h.config().tx_piece);
            out.extend(piece);
        }
        out
    }

    fn program(body_len: usize) -> Vec<u8> {
        let mut p = b"%\nO0001\n".to_vec();
        p.extend((0..body_len).map(|i| b"G01X1.;\n"[i % 8]));
        p.push(EOR);
        p
    }

    fn load(h: &mut ProtocolBHost, now: Instant, prog: &[u8]) {
        h.handle_command(now, EngineCommand::StartProgram { total: None });
        h.handle_command(
            now,
            EngineCommand::ProgramData(Bytes::copy_from_slice(prog)),
        );
        h.handle_command(now, EngineCommand::ProgramEnd);
    }

    fn punched(evs: &[EngineEvent]) -> Vec<u8> {
        evs.iter()
            .filter_map(|e| match e {
                EngineEvent::Punched { data } => Some(data.to_vec()),
                _ => None,
            })
            .flatten()
            .collect()
    }

    /// A queued program waits for the CNC's DC1, a paused one for the DC1 after DC3, a
    /// finished one for the DC3 that ends the read: status says which.
    #[test]
    fn says_what_it_waits_for() {
        let (mut h, now) = host(CodeSystem::Ascii, false, true);
        assert_eq!(h.waiting_for(), None);
        h.handle_command(now, EngineCommand::StartProgram { total: None });
        h.handle_command(now, EngineCommand::ProgramData(Bytes::from(program(600))));
        h.handle_command(now, EngineCommand::ProgramEnd);
        assert!(
            h.waiting_for()
                .is_some_and(|w| w.starts_with("DC1: the CNC"))
        );
        h.handle_input(now, &[DC1]);
        assert_eq!(h.waiting_for(), None);
        let _ = h.poll_transmit(now);
        h.handle_input(now, &[DC3]);
        assert!(
            h.waiting_for()
                .is_some_and(|w| w.starts_with("DC1 after DC3"))
        );
        h.handle_input(now, &[DC1]);
        drain_tx(&mut h, now);
        assert!(h.waiting_for().is_some_and(|w| w.contains("ends the read")));
        h.handle_modem(
            now,
            ModemIn {
                dr: false,
                cs: false,
                cd: false,
            },
        );
        assert!(h.waiting_for().is_some_and(|w| w.starts_with("DR")));
    }

    /// A host at 19200 baud (11 bits a character), notices on.
    fn timed_host() -> (ProtocolBHost, Instant, Duration) {
        let ct = Duration::from_nanos(11 * 1_000_000_000 / 19_200);
        let cfg = ProtocolBConfig {
            char_time: ct,
            ..ProtocolBConfig::new(CodeSystem::Ascii, false, true)
        };
        let now = Instant::now();
        let mut h = ProtocolBHost::new(cfg, now).unwrap();
        events(&mut h);
        (h, now, ct)
    }

    /// A CNC that reads at line speed behind a device server that delivered sooner than the
    /// nominal rate ends the read before the host's estimate of the EOR's arrival: that DC3
    /// ends the read all the same, and the program is done.
    #[test]
    fn an_end_of_read_a_little_before_the_estimate_ends_the_read() {
        let (mut h, t0, ct) = timed_host();
        let prog = program(4000);
        load(&mut h, t0, &prog);
        h.handle_input(t0, &[DC1]);
        assert_eq!(drain_tx(&mut h, t0), prog);
        let estimate = t0 + ct * prog.len() as u32;
        let early = estimate - ct * 300;
        assert!(done(&end_read(&mut h, early)));
        assert_eq!(h.poll_transmit(early), None);
        // Far before the estimate, a DC3 cannot end the read: the EOR is not there yet.
        let (mut h, t0, ct) = timed_host();
        load(&mut h, t0, &prog);
        h.handle_input(t0, &[DC1]);
        drain_tx(&mut h, t0);
        let too_early = t0 + ct * (prog.len() as u32 / 2);
        h.handle_input(too_early, &[DC3]);
        h.handle_timeout(too_early + Duration::from_secs(1));
        assert!(!done(&events(&mut h)));
    }

    /// A board that stopped the program with DC3 before (a CNC slower than the line) may stop
    /// it again just before the EOR arrives: that DC3 stays flow control, the DC1 after it
    /// sends nothing, and only the DC3 after the EOR's arrival ends the read.
    #[test]
    fn a_board_that_stopped_the_program_is_not_taken_early() {
        let (mut h, t0, ct) = timed_host();
        let prog = program(4000);
        load(&mut h, t0, &prog);
        h.handle_input(t0, &[DC1]);
        let first = h.poll_transmit(t0).unwrap();
        h.handle_input(t0, &[DC3]);
        h.handle_input(t0, &[DC1]);
        let mut sent = first;
        sent.extend(drain_tx(&mut h, t0));
        assert_eq!(sent, prog);
        let estimate = t0 + ct * prog.len() as u32;
        let near = estimate - ct * 300;
        h.handle_input(near, &[DC3]);
        assert_eq!(h.poll_timeout(), None, "no end of read to settle");
        h.handle_input(near, &[DC1]);
        assert!(!done(&events(&mut h)));
        assert!(h.waiting_for().is_some_and(|w| w.contains("ends the read")));
        assert!(done(&end_read(&mut h, estimate + ct)));
    }

    #[test]
    fn default_settings_are_valid_and_overrun_per_protocol() {
        assert!(ProtocolBConfig::default().validate().is_empty());
        let b = ProtocolBConfig::new(CodeSystem::Iso, false, true);
        assert_eq!(b.overrun_allowance, 512);
        let eb = ProtocolBConfig::new(CodeSystem::Iso, true, false);
        assert_eq!(eb.overrun_allowance, 1280);
        assert!(eb.validate().is_empty());
        assert_eq!(
            ProtocolBConfig::for_protocol(Protocol::ExpansionB, CodeSystem::Iso, false),
            Some(eb.clone())
        );
        assert_eq!(
            ProtocolBConfig::for_protocol(Protocol::A, CodeSystem::Iso, false),
            None
        );
        let bad = ProtocolBConfig { tx_piece: 300, ..b };
        assert!(matches!(
            bad.validate().as_slice(),
            [ConfigProblem::TxPiece { piece: 300, .. }]
        ));
        assert!(ProtocolBHost::new(bad, Instant::now()).is_err());
    }

    #[test]
    fn nothing_is_sent_before_dc1() {
        let (mut h, now) = host(CodeSystem::Ascii, false, true);
        load(&mut h, now, &program(100));
        assert_eq!(h.poll_transmit(now), None);
        assert!(h.data_wanted() == 0, "EOR is in: the program takes no more");
    }

    #[test]
    fn dc1_dc3_flow_stops_within_a_piece_and_resumes_with_the_continuation() {
        for (code, dc3) in [(CodeSystem::Iso, 0x93), (CodeSystem::Ascii, 0x13)] {
            let (mut h, now) = host(code, false, true);
            let prog = program(2000);
            load(&mut h, now, &prog);
            h.handle_input(now, &[0x11]);
            let mut sent = Vec::new();
            // The board stops the host after a few pieces.
            for _ in 0..5 {
                sent.extend(h.poll_transmit(now).unwrap());
            }
            // A piece is on the line when the DC3 arrives: at most that piece overruns.
            let in_flight = h.poll_transmit(now).unwrap();
            sent.extend(&in_flight);
            h.handle_input(now, &[dc3]);
            assert_eq!(h.sent_since_dc3(), 0);
            assert_eq!(h.poll_transmit(now), None);
            let overrun = in_flight.len() as u64 + h.sent_since_dc3();
            let cfg = h.config();
            assert!(overrun <= cfg.tx_piece as u64, "overrun {overrun}");
            assert!(
                overrun < cfg.overrun_allowance as u64 / 4,
                "overrun {overrun}"
            );
            assert!(!h.flowing());
            // DC1: the data immediately after that sent last.
            h.handle_input(now, &[0x11]);
            sent.extend(drain_tx(&mut h, now));
            assert_eq!(sent, prog);
            let mut evs = events(&mut h);
            evs.extend(end_read(&mut h, now));
            let total: u64 = evs
                .iter()
                .filter_map(|e| match e {
                    EngineEvent::DataSent { bytes } => Some(*bytes),
                    _ => None,
                })
                .sum();
            assert_eq!(total, prog.len() as u64);
            assert_eq!(
                evs.iter()
                    .filter(|e| matches!(e, EngineEvent::ProgramDone { .. }))
                    .count(),
                1
            );
            assert!(evs.contains(&EngineEvent::State(LinkState::Sending)));
            assert_eq!(evs.last(), Some(&EngineEvent::State(LinkState::Ready)));
        }
    }

    #[test]
    fn next_program_waits_for_dc3_and_a_following_dc1() {
        let (mut h, now) = host(CodeSystem::Iso, false, true);
        let first = program(10);
        load(&mut h, now, &first);
        h.handle_input(now, &[0x11]);
        assert_eq!(drain_tx(&mut h, now), first);
        assert!(!done(&events(&mut h)));
        // Flow-control DC1 of the same read: nothing, and the program is not done.
        h.handle_input(now, &[0x11]);
        assert_eq!(h.poll_transmit(now), None);
        assert!(!done(&events(&mut h)));
        // The CNC ends the read with DC3; nothing until a new DC1, which also shows that no
        // reset or alarm followed: the first program is the board's.
        h.handle_input(now, &[0x93]);
        assert_eq!(h.poll_transmit(now), None);
        assert!(!done(&events(&mut h)));
        h.handle_input(now, &[0x11]);
        assert!(done(&events(&mut h)));
        // That DC1 asked for the next program: it goes at once.
        let second = program(20);
        load(&mut h, now, &second);
        assert_eq!(drain_tx(&mut h, now), second);
    }

    #[test]
    fn program_without_eor_gets_one() {
        let (mut h, now) = host(CodeSystem::Ascii, false, true);
        load(&mut h, now, b"%\nO1\nX1\n");
        h.handle_input(now, &[0x11]);
        assert_eq!(drain_tx(&mut h, now), b"%\nO1\nX1\n%");
        assert!(done(&end_read(&mut h, now)));
    }

    #[test]
    fn data_comes_in_bounded_pieces() {
        let (mut h, now) = host(CodeSystem::Ascii, false, true);
        h.handle_command(now, EngineCommand::StartProgram { total: None });
        assert_eq!(h.data_wanted(), 64 * 1024);
        h.handle_command(
            now,
            EngineCommand::ProgramData(Bytes::from(vec![b'X'; 1000])),
        );
        assert_eq!(h.data_wanted(), 64 * 1024 - 1000);
        h.handle_input(now, &[0x11]);
        let sent = drain_tx(&mut h, now);
        assert_eq!(sent.len(), 1000);
        // Late data: the host waits, the board keeps the read open.
        h.handle_command(now, EngineCommand::ProgramData(Bytes::from_static(b"Y%")));
        assert_eq!(drain_tx(&mut h, now), b"Y%");
        assert!(done(&end_read(&mut h, now)));
    }

    #[test]
    fn dc3_syn_is_a_cnc_reset_that_aborts_the_program() {
        for (code, dc3, syn) in [
            (CodeSystem::Iso, 0x93, 0x96),
            (CodeSystem::Ascii, 0x13, 0x16),
        ] {
            let (mut h, now) = host(code, false, true);
            load(&mut h, now, &program(500));
            h.handle_input(now, &[0x11]);
            let _ = h.poll_transmit(now).unwrap();
            events(&mut h);
            h.handle_input(now, &[dc3, syn]);
            assert_eq!(h.poll_transmit(now), None);
            assert_eq!(
                events(&mut h),
                vec![
                    // The piece sent reached the board before its DC3.
                    EngineEvent::Acked { offset: 64 },
                    EngineEvent::CncReset,
                    EngineEvent::ProgramAborted {
                        reason: AbortReason::ResetNotice,
                        cancelled: false
                    },
                    EngineEvent::State(LinkState::Ready),
                ]
            );
            // The next program goes on the next read request.
            let next = program(5);
            load(&mut h, now, &next);
            h.handle_input(now, &[0x11]);
            assert_eq!(drain_tx(&mut h, now), next);
        }
    }

    #[test]
    fn dc3_nak_is_a_cnc_alarm_and_a_queued_program_stays() {
        let (mut h, now) = host(CodeSystem::Iso, true, true);
        load(&mut h, now, &program(500));
        h.handle_input(now, &[0x11]);
        let _ = h.poll_transmit(now).unwrap();
        events(&mut h);
        // Parity-less form accepted defensively with ISO.
        h.handle_input(now, &[0x13, 0x15]);
        let evs = events(&mut h);
        assert_eq!(evs.first(), Some(&EngineEvent::Acked { offset: 64 }));
        assert_eq!(evs.get(1), Some(&EngineEvent::CncAlarm));
        assert!(evs.contains(&EngineEvent::ProgramAborted {
            reason: AbortReason::AlarmNotice,
            cancelled: false
        }));
        // Idle notice (§6.1.2 1): a queued, unstarted program stays queued.
        let next = program(5);
        load(&mut h, now, &next);
        h.handle_input(now, &[0x95]);
        assert_eq!(events(&mut h), vec![EngineEvent::CncAlarm]);
        h.handle_input(now, &[0x11]);
        assert_eq!(drain_tx(&mut h, now), next);
    }

    #[test]
    fn punch_out_produces_exactly_the_punched_bytes() {
        let (mut h, now) = host(CodeSystem::Iso, false, true);
        let data: Vec<u8> = b"%\nO0002\nG00X0\n%"
            .iter()
            .map(|&b| CodeSystem::Iso.encode(b))
            .collect();
        // Split anywhere; DC4 with or without bit 7.
        h.handle_input(now, &[0x12]);
        h.handle_input(now, &data[..5]);
        assert_eq!(
            events(&mut h),
            vec![EngineEvent::State(LinkState::Receiving)]
        );
        h.handle_input(now, &data[5..]);
        h.handle_input(now, &[0x14]);
        let evs = events(&mut h);
        assert_eq!(punched(&evs), data);
        assert_eq!(evs.last(), Some(&EngineEvent::State(LinkState::Ready)));
        assert_eq!(h.punch_held(), 0);
        // A punch-out cut by a reset: DC4 then SYN (§6.1.2 2 (5)).
        h.handle_input(now, &[0x12, b'O', b'1', 0x94, 0x96]);
        let evs = events(&mut h);
        assert_eq!(punched(&evs), b"O1");
        assert!(evs.contains(&EngineEvent::CncReset));
        assert_eq!(h.poll_transmit(now), None);
    }

    #[test]
    fn punch_out_flow_control_sends_dc3_then_dc1_or_dc2() {
        for (notify, resume) in [(true, 0x11), (false, 0x12)] {
            let (mut h, now) = host(CodeSystem::Iso, false, notify);
            let high = h.config().punch_high_water;
            h.handle_input(now, &[0x12]);
            h.handle_input(now, &vec![b'A'; high]);
            assert_eq!(h.poll_transmit(now), None);
            assert!(h.modem_out().rs);
            // One more byte not taken: DC3 in the configured code, and RS off (CS of the
            // board).
            h.handle_input(now, b"B");
            assert_eq!(h.poll_transmit(now), Some(vec![0x93]));
            assert!(!h.modem_out().rs);
            // Overrun within the allowance is kept.
            h.handle_input(now, &vec![b'C'; 400]);
            assert_eq!(h.punch_held(), high + 401);
            // Taking the pieces resumes the board.
            let mut got = punched(&events(&mut h));
            assert_eq!(got.len() + h.punch_held(), high + 401);
            assert_eq!(h.poll_transmit(now), Some(vec![resume]));
            assert!(h.modem_out().rs);
            h.handle_input(now, &[0x14]);
            got.extend(punched(&events(&mut h)));
            let mut expected = vec![b'A'; high];
            expected.push(b'B');
            expected.extend([b'C'; 400]);
            assert!(got == expected, "punched data differs");
            assert_eq!(h.poll_transmit(now), None);
        }
    }

    #[test]
    fn rs_stays_on_without_rs_flow() {
        let cfg = ProtocolBConfig {
            rs_flow: false,
            ..ProtocolBConfig::new(CodeSystem::Ascii, false, true)
        };
        let now = Instant::now();
        let mut h = ProtocolBHost::new(cfg, now).unwrap();
        let high = h.config().punch_high_water;
        h.handle_input(now, &[0x12]);
        h.handle_input(now, &vec![b'A'; high + 1]);
        assert_eq!(h.poll_transmit(now), Some(vec![0x13]));
        assert!(h.modem_out().rs);
    }

    #[test]
    fn punch_overflow_is_dropped_and_reported() {
        let (mut h, now) = host(CodeSystem::Ascii, false, true);
        let max = h.config().max_buffer;
        h.handle_input(now, &[0x12]);
        h.handle_input(now, &vec![b'A'; max + 10]);
        assert_eq!(h.punch_held(), max);
        let evs = events(&mut h);
        assert!(evs.iter().any(|e| matches!(
            e,
            EngineEvent::ProtocolError {
                error: ProtocolError::PunchOverflow { dropped: 10 },
                ..
            }
        )));
    }

    #[test]
    fn cancel_aborts_and_the_next_program_waits_for_a_new_read() {
        let (mut h, now) = host(CodeSystem::Ascii, false, true);
        load(&mut h, now, &program(500));
        h.handle_input(now, &[0x11]);
        let _ = h.poll_transmit(now).unwrap();
        events(&mut h);
        h.handle_command(now, EngineCommand::Cancel);
        assert_eq!(h.poll_transmit(now), None);
        assert!(events(&mut h).contains(&EngineEvent::ProgramAborted {
            reason: AbortReason::Cancelled,
            cancelled: true
        }));
        load(&mut h, now, &program(5));
        assert_eq!(h.poll_transmit(now), None);
        h.handle_input(now, &[0x13, 0x11]);
        assert_eq!(drain_tx(&mut h, now), program(5));
    }

    #[test]
    fn do_di_and_clb_do_not_exist_in_protocol_b() {
        let (mut h, now) = host(CodeSystem::Ascii, false, true);
        for c in [
            EngineCommand::SetDo(1),
            EngineCommand::ReadDi,
            EngineCommand::ClearBuffer,
        ] {
            h.handle_command(now, c);
            let evs = events(&mut h);
            assert!(matches!(
                evs.as_slice(),
                [EngineEvent::ProtocolError {
                    error: ProtocolError::NotInProtocolB { .. },
                    retried: false
                }]
            ));
        }
        assert_eq!(h.poll_transmit(now), None);
    }

    #[test]
    fn dr_off_raises_sr0855_and_aborts() {
        let (mut h, now) = host(CodeSystem::Iso, false, true);
        load(&mut h, now, &program(500));
        h.handle_input(now, &[0x11]);
        let _ = h.poll_transmit(now).unwrap();
        events(&mut h);
        let down = ModemIn {
            dr: false,
            ..ModemIn::ALL_ON
        };
        h.handle_modem(now, down);
        let evs = events(&mut h);
        assert!(matches!(
            evs.first(),
            Some(EngineEvent::Alarm(a)) if a.cnc_alarm() == Some(CncAlarm::Sr0855DataSetReadyDown)
        ));
        assert!(evs.contains(&EngineEvent::ProgramAborted {
            reason: AbortReason::Link(LinkAlarm::DataSetReadyOffB),
            cancelled: false
        }));
        assert_eq!(evs.last(), Some(&EngineEvent::State(LinkState::LineDown)));
        h.handle_input(now, &[0x11]);
        assert_eq!(h.poll_transmit(now), None);
        h.handle_modem(now, ModemIn::ALL_ON);
        assert_eq!(events(&mut h), vec![EngineEvent::State(LinkState::Ready)]);
    }

    #[test]
    fn cs_off_pauses_sending() {
        let (mut h, now) = host(CodeSystem::Ascii, false, true);
        let prog = program(100);
        load(&mut h, now, &prog);
        h.handle_input(now, &[0x11]);
        let mut sent = h.poll_transmit(now).unwrap();
        h.handle_modem(
            now,
            ModemIn {
                cs: false,
                ..ModemIn::ALL_ON
            },
        );
        assert_eq!(h.poll_transmit(now), None);
        h.handle_modem(now, ModemIn::ALL_ON);
        sent.extend(drain_tx(&mut h, now));
        assert_eq!(sent, prog);
    }

    #[test]
    fn garbage_is_reported_and_ignored() {
        let (mut h, now) = host(CodeSystem::Iso, false, true);
        h.handle_input(now, b"hello");
        let evs = events(&mut h);
        assert!(matches!(
            evs.as_slice(),
            [EngineEvent::ProtocolError {
                error: ProtocolError::NotControlCodes {
                    count: 5,
                    first: 0x68
                },
                ..
            }]
        ));
        h.handle_line_error(now, LineError::Parity);
        assert_eq!(events(&mut h).len(), 1);
    }

    #[test]
    fn punched_pieces_end_at_each_programs_eor() {
        let (mut h, now) = host(CodeSystem::Ascii, false, true);
        h.handle_input(now, b"\x12\n%\nO1\nX1\n%\nO2\nX2\n%\x14");
        let pieces: Vec<Vec<u8>> = events(&mut h)
            .into_iter()
            .filter_map(|e| match e {
                EngineEvent::Punched { data } => Some(data.to_vec()),
                _ => None,
            })
            .collect();
        assert_eq!(
            pieces,
            vec![b"\n%\nO1\nX1\n%".to_vec(), b"\nO2\nX2\n%".to_vec()]
        );
    }

    #[test]
    fn a_line_error_while_punching_marks_the_punch_out_damaged_where_it_fell() {
        let (mut h, now) = host(CodeSystem::Ascii, false, true);
        h.handle_input(now, b"\x12\n%\nO1\nX1");
        h.handle_line_error(now, LineError::Parity);
        h.handle_input(now, b"\n%\x14");
        let evs: Vec<EngineEvent> = events(&mut h)
            .into_iter()
            .filter(|e| !matches!(e, EngineEvent::State(_)))
            .collect();
        assert!(
            matches!(
                evs.as_slice(),
                [
                    EngineEvent::Punched { data: before },
                    EngineEvent::PunchDamaged {
                        cause: PunchDamage::Line(LineError::Parity)
                    },
                    EngineEvent::ProtocolError { .. },
                    EngineEvent::Punched { data: after },
                ] if before.as_ref() == b"\n%\nO1\nX1" && after.as_ref() == b"\n%"
            ),
            "{evs:?}"
        );
        // Outside a punch-out a line error damages nothing.
        h.handle_line_error(now, LineError::Framing);
        assert!(
            !events(&mut h)
                .iter()
                .any(|e| matches!(e, EngineEvent::PunchDamaged { .. }))
        );
    }

    #[test]
    fn notices_are_reported_with_notification_off_too() {
        let (mut h, now) = host(CodeSystem::Ascii, false, false);
        h.handle_input(now, &[0x13, 0x16, 0x15]);
        assert_eq!(
            events(&mut h),
            vec![EngineEvent::CncReset, EngineEvent::CncAlarm]
        );
    }

    #[test]
    fn a_dc3_not_sent_yet_is_dropped_rather_than_resumed() {
        let (mut h, now) = host(CodeSystem::Ascii, false, false);
        let high = h.config().punch_high_water;
        h.handle_modem(
            now,
            ModemIn {
                cs: false,
                ..ModemIn::ALL_ON
            },
        );
        h.handle_input(now, &[0x12]);
        h.handle_input(now, &vec![b'A'; high + 1]);
        // CS off: the DC3 waits; the data is taken meanwhile.
        assert_eq!(h.poll_transmit(now), None);
        events(&mut h);
        h.handle_modem(now, ModemIn::ALL_ON);
        assert_eq!(h.poll_transmit(now), None);
        assert!(h.punch_held() <= high / 2);
    }

    proptest! {
        /// A board that stops and resumes the host at random: nothing goes out while stopped,
        /// at most one piece is on its way when DC3 arrives, and the board gets exactly the
        /// program.
        #[test]
        fn random_dc1_dc3_flow_delivers_the_program_exactly(
            steps in proptest::collection::vec((any::<bool>(), 0usize..4), 1..200),
            iso in any::<bool>(),
        ) {
            let code = if iso { CodeSystem::Iso } else { CodeSystem::Ascii };
            let (mut h, now) = host(code, false, true);
            let prog = program(3000);
            load(&mut h, now, &prog);
            let mut sent = Vec::new();
            let mut stopped = true;
            for (dc1, polls) in steps {
                h.handle_input(now, &[code.control(if dc1 { DC1 } else { DC3 })]);
                stopped = !dc1;
                for _ in 0..polls {
                    match h.poll_transmit(now) {
                        Some(out) => {
                            prop_assert!(!stopped, "data after DC3");
                            prop_assert!(out.len() <= 64);
                            sent.extend(out);
                        }
                        None => break,
                    }
                }
                prop_assert!(prog.starts_with(&sent));
            }
            if stopped {
                h.handle_input(now, &[0x11]);
            }
            sent.extend(drain_tx(&mut h, now));
            prop_assert!(sent == prog, "the board got other bytes than the program");
        }

        #[test]
        fn arbitrary_input_never_panics_and_stays_bounded(
            chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..200), 0..60),
            take_events in any::<bool>(),
            expansion in any::<bool>(),
        ) {
            let now = Instant::now();
            let cfg = ProtocolBConfig {
                max_buffer: 4096,
                punch_piece: 512,
                punch_high_water: 4096 - 2 * 1280,
                ..ProtocolBConfig::new(CodeSystem::Iso, expansion, true)
            };
            let mut h = ProtocolBHost::new(cfg, now).unwrap();
            let mut sent = Vec::new();
            let prog = program(3000);
            for (i, chunk) in chunks.iter().enumerate() {
                if i % 7 == 0 {
                    load(&mut h, now, &prog);
                }
                h.handle_input(now, chunk);
                if let Some(out) = h.poll_transmit(now) {
                    prop_assert!(out.len() <= 64);
                    sent.extend(out);
                }
                if take_events {
                    events(&mut h);
                }
                prop_assert!(h.punch_held() <= 4096);
                prop_assert!(h.program_buffered() <= prog.len());
            }
        }
    }
}
