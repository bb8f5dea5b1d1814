//! The host computer's side of Protocol A and Expansion Protocol A (§4, §5), sans-IO.
//!
//! [`ProtocolAHost`] is fed received bytes, line errors, modem lines, commands and the time; it
//! hands out bytes to transmit, events, and its next deadline. It never holds a whole program:
//! program bytes stream through a bounded buffer ([`ProtocolAConfig::max_buffer`]).
//!
//! # The exchange (§4.3, §4.4.1, §4.7)
//!
//! The board speaks first; the host answers every message once, at once (within To), except
//! that a GTD may wait up to [`ProtocolAConfig::wat_grace`] for late program data.
//!
//! - Initialisation: board SYN → host SYN; board RDY → host RDY. Until then every other
//!   message from the board is answered with SYN, the host's "initialization command" that
//!   makes the board initialise again (§4.4.1 SYN, H).
//! - SAT (every Tp) → SET, or CLB (pending `ClearBuffer` or clean-up after a cancel), RDI
//!   (pending `ReadDi`), SDO (pending `SetDo`). The SET carries the configured parameters, code
//!   conversion and packet length n the first time after initialisation and whenever the SAT's
//!   current values differ; otherwise its data part is empty, which changes nothing (protocol
//!   notes 5). Byte 1 (remote/tape switching) and bytes 41–44 echo the SAT, so a SET never
//!   switches the operation mode. n changes only between programs.
//! - GTD → DAT with the next piece of the program, at most min(4096, Nb − No) bytes (§4.4.2 3,
//!   §4.5 note 1), Nb and No being the board's current values; EOD once the DAT carrying EOR
//!   has gone (then `ProgramDone`); WAT when not enough data came within the grace (a partial
//!   DAT goes instead when some data is there), and also when no program is queued at all: the
//!   CNC is waiting for a job, and WAT makes the board ask again after Tw. RDI or SDO may
//!   answer a GTD too.
//! - RDI → SDI → the ordinary answer still owed to the SAT or GTD before it (SET, CLB, DAT,
//!   EOD, WAT); SDO answers SAT or GTD and completes the exchange (the board talks next; a GTD
//!   answered by SDO is asked again). The host never sends SDO right after SDI: boards read it
//!   two ways (protocol notes 6), so a pending SDO waits for the next SAT or GTD.
//! - RST → ARS, ALM → AAL; a program the board has data of is aborted (§8.2: the CNC discards
//!   buffered data on reset). A program not started yet stays queued. A program whose bytes,
//!   EOR included, have all gone out is delivered: the board's valid RST, ALM, CAN or alarm
//!   SAT after it shows that it arrived (a CNC ending with M30 may reset before the EOD). A
//!   line failure at that point still aborts it.
//! - RTY (protocol notes 7): a message with a checksum error is answered with RTY reason '1';
//!   an RTY received makes the host send its last message again. RTYs received plus RTYs sent
//!   in a row above Ne is a line error: SR0945 and re-initialisation. RTY answered by RTY is
//!   counted the same way, so it cannot loop.
//!
//! # Expansion Protocol A (§5)
//!
//! Once a SET carrying n ∈ {1, 2, 4} has gone to the board (and as long as its SATs report n),
//! a GTD is answered with data packets of 256·n bytes, one packet per [`Engine::poll_transmit`]
//! and each only once the one before has (nearly) left the line by
//! [`ProtocolAConfig::char_time`], so that after a DC3 only the packet under way can reach the
//! board however much the transport would buffer (§5.3 3; protocol notes 17). Monitor packets are split off the
//! received stream by their first byte (CAN, NAK, DC3, DC1 with or without parity), which no
//! Protocol A message can start with (its first byte is a hex digit). The last packet is padded
//! with [`PAD`]. While data is late the host sends an invalid packet (20h) every
//! [`ProtocolAConfig::dummy_interval`], which keeps the board's To supervision from expiring
//! (§5.4 7). After the end packet, the first Protocol A message from the board ends the
//! transmission and the program is reported done. CAN ends the packets with the end packet
//! (dummy data) after the packet under way; a CAN between a GTD and the host's answer to it
//! gets the end packet at once, since the board then awaits nothing else (protocol notes 16).
//!
//! # Supervision (host side, §4.3 (3), (4))
//!
//! The board answers or polls within Tp + Tx after each host message, and asks again within
//! Tw ≤ Tp after WAT. The host therefore declares a time-out (SR0944, re-initialisation) when
//! nothing at all arrives for max(2·Tp, To) after its last message went out (plus the message's
//! line time, [`ProtocolAConfig::char_time`]); using To as well avoids calling a time-out
//! before the board itself would. There is no supervision while the host owes an answer, while
//! waiting for the first SYN, or during a packet transmission, when a board paused by DC3 may
//! stay silent as long as its CNC does not read.
//!
//! # Errors (§4.6)
//!
//! Line errors (parity, framing, overrun, a parity error inside a message, DR off, time-out,
//! retry over) re-initialise the link and wait for SYN, with an `Alarm` event. Reception errors
//! (undefined or unexpected command, too long a data part, garbage) are ignored with a
//! `ProtocolError` event: the board polls again with SAT.
//!
//! # Rooms
//!
//! `config` (the settings and their checks), `board` (what the board's SAT, RTY and monitor
//! packets mean to the host), `answer` (what the host answers SAT and GTD with, and the line
//! supervision after each message), `expansion` (Expansion A's packets, §5); the engine's
//! state and its event loop stay here.

mod answer;
mod board;
mod config;
mod expansion;

pub use config::{InvalidConfig, ProtocolAConfig, ProtocolAProblem};

/// Shortest DAT a noisy line brings the host down to (see `dat_len_now`).
pub const MIN_NOISY_DAT: usize = 128;
/// DATs taken without an RTY before the DAT length doubles again.
const CLEAN_DATS_TO_GROW: u8 = 8;

pub use expansion::PAD;

use std::collections::VecDeque;
use std::fmt;
use std::time::{Duration, Instant};

use bytes::Bytes;

use crate::engine::{Engine, FrameCounts, LineError, ModemIn};
use crate::fanuc::alarm::CncAlarm;
use crate::fanuc::error::{AbortReason, LinkAlarm, ProtocolError};
use crate::fanuc::host::{EngineCommand, EngineEvent, HostEngine, LinkState};
use crate::fanuc::message::{
    Command, Decoder, FrameError, MAX_DAT_DATA, Message, RTY_CHECKSUM, hex2,
};
use crate::fanuc::packet::{MONITOR_LEN, Monitor};
use crate::fanuc::program::Program;
use crate::fanuc::sat::{Params, StatusData, effective_packet_n};

use expansion::{PacketRun, RunOutcome};

/// How much the engine holds, for metrics and for tests that check it stays bounded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BufferUsage {
    /// Received bytes not yet part of a complete message or monitor packet.
    pub rx: usize,
    /// Bytes queued for transmission.
    pub tx: usize,
    /// Program bytes held.
    pub program: usize,
    /// Expansion A packets kept for retransmission.
    pub packets: usize,
    /// Events not yet taken.
    pub events: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Waiting for SYN (§4.6 1: "SYN wait status").
    SynWait,
    /// SYN answered; waiting for RDY.
    RdyWait,
    Ready,
}

/// A board message the host still has to answer.
#[derive(Debug, Clone, PartialEq)]
enum Request {
    Sat {
        data: Option<StatusData>,
        after_sdi: bool,
    },
    Gtd {
        at: Instant,
        after_sdi: bool,
    },
}

impl Request {
    fn resumed(self, now: Instant) -> Request {
        match self {
            Request::Sat { data, .. } => Request::Sat {
                data,
                after_sdi: true,
            },
            Request::Gtd { .. } => Request::Gtd {
                at: now,
                after_sdi: true,
            },
        }
    }
}

/// Why an EOD is owed to the next GTD.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum EodFor {
    /// The program's last DAT (with EOR) is queued or gone; the program is done once the
    /// board's next exchange acknowledges it, and EOD then ends the transfer.
    Done,
    /// Clean-up after an abandoned program (§4.4.1 EOD).
    Cleanup,
    /// The end of a confirmed program, for a GTD of the read that took it. Stale once that
    /// read is over: a SAT showing the buffer empty (the CNC read through the EOR), a reset,
    /// an alarm; the next read's first GTD then gets data, not an EOD that makes the board
    /// ask again only after Tp.
    Delivered,
}

#[derive(Debug)]
struct Outgoing {
    bytes: Vec<u8>,
    pos: usize,
    /// The program bytes this message carries for the first time (a DAT's data part).
    program: Bytes,
    do_sent: Option<u8>,
    /// The DAT carrying the program's EOR.
    last_of_program: bool,
}

impl Outgoing {
    /// A message that carries program data: it is never dropped, since a lost DAT would leave
    /// a hole in the program.
    fn carries_program(&self) -> bool {
        !self.program.is_empty()
    }
}

/// GTDs answered with EOD to make the board poll with SAT before the host gives up
/// (protocol notes 19).
const SAT_PROBES: u8 = 2;

/// Characters of a data packet that may still be on their way when the next is handed out.
const PACE_SLACK: usize = 16;

/// SetDo requests kept while the link cannot send them; older ones are dropped past this.
const MAX_PENDING_DO: usize = 16;

/// Protocol A messages queued for transmission at most.
const MAX_QUEUED: usize = 4;

/// The host side of a Protocol A / Expansion Protocol A link. See the [module](self) docs.
pub struct ProtocolAHost {
    cfg: ProtocolAConfig,
    phase: Phase,
    /// DR and CD on.
    line_up: bool,
    /// CS on: the board can receive.
    cs: bool,
    decoder: Decoder,
    monitor_buf: Vec<u8>,
    tx: VecDeque<Outgoing>,
    /// The last Protocol A message sent, as transmitted, for RTY.
    last_sent: Option<Vec<u8>>,
    /// RTYs received plus RTYs sent since the last good exchange.
    retries: u16,
    owed: Option<Request>,
    /// The SAT or GTD answered with RDI: answered after the SDI.
    rdi_for: Option<Request>,
    /// The last readable SAT.
    sat: Option<StatusData>,
    /// The packet length n the board uses (0: Protocol A).
    board_n: u8,
    board_in_alarm: bool,
    /// The last program's EOR is in the board's buffer and the CNC may still be reading it:
    /// every byte behind an EOR is ignored (§8.2), so the next program waits — GTDs get EOD,
    /// "the transmission of NC data has been completed" (§4.4.1) — until a SAT shows the
    /// buffer empty (bytes 5–8), or a CLB has cleared it.
    drain_wait: bool,
    /// The current program is a stream: a GTD gets what there is at once.
    streaming: bool,
    /// Longest DAT for now (see [`Self::dat_len_now`]), and DATs taken since it last shrank.
    dat_limit: usize,
    clean_dats: u8,
    /// The next SET carries the parameters whatever the SAT says (first after initialisation).
    set_needed: bool,
    /// A SAT came since the link initialised, so the SET answering it put the cell file's
    /// parameters and n in force (or found them so). A CNC already reading when the link
    /// comes up asks with GTD only (protocol notes 19).
    sat_seen: bool,
    /// GTDs answered with EOD to make the board poll with SAT, since initialisation.
    sat_probes: u8,
    /// The parameters-not-applied alarm was raised since initialisation.
    params_alarmed: bool,
    read_di: bool,
    set_do: VecDeque<u8>,
    clb_owed: bool,
    eod_owed: Option<EodFor>,
    program: Option<Program>,
    /// Program bytes of the current program the board has acknowledged (§4.4: a DAT is
    /// received once the board's next exchange is not RTY; Expansion A: packets past the
    /// NAK window, and the rest when the board is back in Protocol A).
    acked: u64,
    /// Program bytes in DATs handed out and not acknowledged yet.
    dat_unacked: u64,
    /// The DAT carrying the program's EOR has been handed out.
    final_sent: bool,
    run: Option<PacketRun>,
    /// When the last data packet handed out has left the line (by `char_time`): the next
    /// waits for it, so that only the packet under way can follow a DC3 whatever the
    /// transport buffers (§5.3 3; protocol notes 17).
    packet_pace: Option<Instant>,
    /// When the last data packet handed out is done on the line, by `char_time`.
    packet_done: Instant,
    /// Last message received or sent (sent: plus its line time).
    last_activity: Instant,
    events: VecDeque<EngineEvent>,
    state: LinkState,
    /// Messages and packets received (good or not) and sent whole.
    frames: FrameCounts,
}

impl fmt::Debug for ProtocolAHost {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ProtocolAHost")
            .field("phase", &self.phase)
            .field("state", &self.state)
            .field("board_n", &self.board_n)
            .field("owed", &self.owed)
            .field("buffers", &self.buffer_usage())
            .finish_non_exhaustive()
    }
}

impl ProtocolAHost {
    /// A host engine waiting for the board's SYN.
    pub fn new(config: ProtocolAConfig, now: Instant) -> Result<Self, InvalidConfig> {
        InvalidConfig::check("Protocol A", config.validate())?;
        Ok(ProtocolAHost {
            decoder: Decoder::new(config.framing),
            cfg: config,
            phase: Phase::SynWait,
            line_up: true,
            cs: true,
            monitor_buf: Vec::with_capacity(MONITOR_LEN),
            tx: VecDeque::new(),
            last_sent: None,
            retries: 0,
            owed: None,
            rdi_for: None,
            sat: None,
            board_n: 0,
            board_in_alarm: false,
            drain_wait: false,
            streaming: false,
            dat_limit: MAX_DAT_DATA,
            clean_dats: 0,
            set_needed: true,
            sat_seen: false,
            sat_probes: 0,
            params_alarmed: false,
            read_di: false,
            set_do: VecDeque::new(),
            clb_owed: false,
            eod_owed: None,
            program: None,
            acked: 0,
            dat_unacked: 0,
            final_sent: false,
            run: None,
            packet_pace: None,
            packet_done: now,
            last_activity: now,
            events: VecDeque::from([EngineEvent::State(LinkState::Initialising)]),
            state: LinkState::Initialising,
            frames: FrameCounts::default(),
        })
    }

    /// The settings the engine runs with.
    pub fn config(&self) -> &ProtocolAConfig {
        &self.cfg
    }

    /// The packet length n the board is taken to use (0: Protocol A).
    pub fn board_packet_n(&self) -> u8 {
        self.board_n
    }

    /// The last readable SAT data part.
    pub fn last_status(&self) -> Option<&StatusData> {
        self.sat.as_ref()
    }

    /// How much the engine holds now.
    pub fn buffer_usage(&self) -> BufferUsage {
        BufferUsage {
            rx: self.decoder.buffered() + self.monitor_buf.len(),
            tx: self
                .tx
                .iter()
                .map(|o| o.bytes.len().saturating_sub(o.pos))
                .sum(),
            program: self.program.as_ref().map_or(0, Program::buffered),
            packets: self.run.as_ref().map_or(0, PacketRun::held_bytes),
            events: self.events.len(),
        }
    }

    /// The board's current parameters: from its last SAT, else the ones the host sets.
    fn board_params(&self) -> Params {
        self.sat.and_then(|s| s.params).unwrap_or(self.cfg.params)
    }

    fn ne(&self) -> u16 {
        self.board_params().ne
    }

    /// Longest DAT data part: min(4096, Nb − No) (§4.4.2 3, §4.5 note 1). Without a SAT since
    /// the link initialised the board's Nb and No are unknown: the DAT also fits a board at
    /// its power-on values and one at the cell file's (protocol notes 19).
    fn dat_len(&self) -> usize {
        let room = |p: Params| usize::from(p.nb.saturating_sub(p.no));
        let mut len = room(self.board_params());
        if !self.sat_seen {
            len = len.min(room(self.cfg.params)).min(room(Params::POWER_ON));
        }
        len.clamp(1, MAX_DAT_DATA)
    }

    /// The DAT length to use now: [`Self::dat_len`], shortened on a noisy line. Each RTY for a
    /// DAT halves it (down to [`MIN_NOISY_DAT`]); every [`CLEAN_DATS_TO_GROW`] DATs taken
    /// without one double it again. At an error rate of 1e-3 per byte a 1950-byte DAT gets
    /// through one time in seven, and the RTYs it costs run into Ne (§4.6 2 (1)); a 240-byte
    /// one four times in five.
    fn dat_len_now(&self) -> usize {
        self.dat_len().min(self.dat_limit)
    }

    fn supervision_interval(&self) -> Duration {
        let p = self.board_params();
        let secs = (2 * u64::from(p.tp)).max(u64::from(p.to)).max(1);
        Duration::from_secs(secs)
    }

    /// Pieces of Protocol A messages handed to the driver: at most the board's overrun
    /// allowance No, so that CS off stops the host within No bytes (§4.3 (5)); whole
    /// messages where CS is not seen ([`ProtocolAConfig::cs_visible`]).
    fn tx_chunk(&self) -> usize {
        if self.cfg.cs_visible {
            usize::from(self.board_params().no).max(16)
        } else {
            usize::MAX
        }
    }

    fn emit(&mut self, event: EngineEvent) {
        self.events.push_back(event);
    }

    fn protocol_error(&mut self, error: ProtocolError, retried: bool) {
        tracing::debug!(%error, retried, "Protocol A error");
        self.emit(EngineEvent::ProtocolError { error, retried });
    }

    fn alarm(&mut self, error: LinkAlarm) {
        tracing::warn!(alarm = error.cnc_alarm().map(CncAlarm::number), %error, "Protocol A link alarm");
        self.emit(EngineEvent::Alarm(error));
    }

    fn queue(&mut self, bytes: Vec<u8>, program: Bytes, do_sent: Option<u8>) {
        // The board talks only after the host's answer left; a queue this long means the line
        // is blocked (CS off) while something keeps talking: keep the newest answers, but
        // never drop a DAT (the program would have a hole) nor one partly on the line.
        if self.tx.len() >= MAX_QUEUED {
            let droppable = self
                .tx
                .iter()
                .enumerate()
                .position(|(i, o)| !o.carries_program() && (i > 0 || o.pos == 0));
            if let Some(i) = droppable {
                tracing::warn!(
                    queued = self.tx.len(),
                    "transmit queue full: oldest answer without program data dropped"
                );
                self.tx.remove(i);
            }
        }
        self.tx.push_back(Outgoing {
            bytes,
            pos: 0,
            program,
            do_sent,
            last_of_program: false,
        });
    }

    fn send_with(&mut self, msg: &Message, program: Bytes, do_sent: Option<u8>) {
        match self.cfg.framing.encode_to_vec(msg) {
            Ok(bytes) => {
                tracing::trace!(?msg, "Protocol A message out");
                self.last_sent = Some(bytes.clone());
                self.queue(bytes, program, do_sent);
            }
            // Only a DAT could fail, and its data part is checked before.
            Err(error) => tracing::error!(%error, ?msg, "message not sent"),
        }
    }

    fn send(&mut self, command: Command) {
        self.send_with(&Message::new(command), Bytes::new(), None);
    }

    fn send_sdo(&mut self, v: u8) {
        self.send_with(
            &Message::with_data(Command::Sdo, hex2(v)),
            Bytes::new(),
            Some(v),
        );
    }

    /// Whether the board has (or had) data of the current program.
    fn program_started(&self) -> bool {
        self.program.as_ref().is_some_and(|p| p.sent > 0)
            || self.run.is_some()
            || self.eod_owed == Some(EodFor::Done)
    }

    fn update_state(&mut self) {
        let state = if !self.line_up {
            LinkState::LineDown
        } else if self.phase != Phase::Ready {
            LinkState::Initialising
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

    fn after_step(&mut self, now: Instant) {
        self.try_answer(now);
        self.update_state();
    }

    /// Abandons the current program, and one whose bytes have all gone out but whose end is
    /// not confirmed yet. `only_started`: a program the board has no data of stays queued.
    /// `cleanup`: when the board has data of it, the next GTD gets EOD and the next SAT CLB.
    fn abort_program(
        &mut self,
        reason: AbortReason,
        cancelled: bool,
        cleanup: bool,
        only_started: bool,
    ) {
        // A program whose every byte, EOR included, went out (EOD or the board's return to
        // Protocol A still to come).
        let finishing = self.eod_owed == Some(EodFor::Done)
            || self
                .run
                .as_ref()
                .is_some_and(|r| r.outcome == RunOutcome::Delivered);
        if finishing {
            if self.eod_owed == Some(EodFor::Done) {
                self.eod_owed = None;
            }
            if let Some(run) = self.run.as_mut() {
                run.outcome = RunOutcome::Stopped;
            }
            // Not acknowledged by the board's next exchange: a reset, an alarm, a CAN or a
            // link failure before it leaves the end unconfirmed, so the program failed at
            // what was acknowledged.
            self.program_aborted(&reason, cancelled, cleanup);
        }
        let Some(program) = &self.program else {
            return;
        };
        let started = program.sent > 0
            || self
                .run
                .as_ref()
                .is_some_and(|r| r.outcome == RunOutcome::Sending);
        if only_started && !started {
            return;
        }
        if let Some(run) = self.run.as_mut()
            && run.outcome == RunOutcome::Sending
        {
            run.outcome = RunOutcome::Stopped;
            if !run.end_sent {
                run.stop = true;
            }
        }
        self.program = None;
        self.program_aborted(&reason, cancelled, cleanup && started);
    }

    fn program_aborted(&mut self, reason: &AbortReason, cancelled: bool, cleanup: bool) {
        tracing::info!(%reason, cancelled, acked = self.acked, "program aborted");
        // What the board had not acknowledged by now is not counted for this program.
        self.dat_unacked = 0;
        self.final_sent = false;
        self.emit(EngineEvent::ProgramAborted {
            reason: reason.clone(),
            cancelled,
        });
        if cleanup {
            self.eod_owed = Some(EodFor::Cleanup);
            self.clb_owed = true;
        }
    }

    /// Back to SYN wait (§4.6 1): whatever was in progress is dropped.
    fn reinit(&mut self, now: Instant, reason: AbortReason) {
        self.abort_program(reason, false, false, true);
        self.run = None;
        self.packet_pace = None;
        self.phase = Phase::SynWait;
        self.decoder.clear();
        self.monitor_buf.clear();
        self.tx.clear();
        self.last_sent = None;
        self.retries = 0;
        self.owed = None;
        if self.rdi_for.take().is_some() {
            self.read_di = true;
        }
        self.set_needed = true;
        self.sat_seen = false;
        self.sat_probes = 0;
        self.params_alarmed = false;
        self.last_activity = now;
    }

    fn line_failure(&mut self, now: Instant, error: LinkAlarm) {
        self.alarm(error.clone());
        self.reinit(now, AbortReason::Link(error));
    }

    fn retry_over(&mut self, now: Instant) {
        let error = LinkAlarm::RetryOver {
            count: self.retries,
            ne: self.ne(),
        };
        self.line_failure(now, error);
    }

    // ---- reception ----

    fn on_frame(&mut self, now: Instant, frame: Result<Message, FrameError>) {
        match frame {
            Ok(msg) => self.on_message(now, msg),
            Err(error) if error.is_line_error() => {
                self.line_failure(now, LinkAlarm::FrameParity { error });
            }
            Err(error) if error.is_checksum_error() => {
                if self.run.as_ref().is_some_and(|r| !r.end_sent) {
                    self.protocol_error(ProtocolError::Frame { error }, false);
                    return;
                }
                self.last_activity = now;
                self.retries = self.retries.saturating_add(1);
                let ne = self.ne();
                if self.retries > ne {
                    self.retry_over(now);
                    return;
                }
                self.protocol_error(
                    ProtocolError::ChecksumRetry {
                        error,
                        count: self.retries,
                        ne,
                    },
                    true,
                );
                self.send_with(
                    &Message::with_data(Command::Rty, [RTY_CHECKSUM]),
                    Bytes::new(),
                    None,
                );
            }
            // Reception errors: ignore the data and wait for the next SAT (§4.6 2).
            Err(error) => self.protocol_error(ProtocolError::Frame { error }, false),
        }
    }

    fn on_message(&mut self, now: Instant, msg: Message) {
        tracing::trace!(?msg, "Protocol A message in");
        self.last_activity = now;
        let command = msg.command;
        if command != Command::Rty {
            self.retries = 0;
        }
        if let Some(run) = &self.run {
            let notice = matches!(command, Command::Syn | Command::Rst | Command::Alm);
            if run.end_sent && !notice {
                // The board is back in Protocol A (§5.2 2 b).
                self.finish_run();
            } else if notice {
                // The board left the transmission without CAN; its handler aborts the program.
                tracing::debug!(%command, "packet transmission ended by a Protocol A message");
                self.run = None;
            } else {
                self.protocol_error(
                    ProtocolError::Unexpected {
                        command,
                        context: "during an Expansion A packet transmission (§5.1)",
                    },
                    false,
                );
                return;
            }
        }
        if command != Command::Rty {
            if let Some(req) = self.owed.take() {
                tracing::debug!(?req, %command, "the board spoke again before the host answered");
            }
            if command != Command::Sdi && self.rdi_for.take().is_some() {
                // The RDI went unanswered: ask again at the next chance.
                self.read_di = true;
            }
        }
        match self.phase {
            Phase::SynWait => match command {
                Command::Syn => {
                    self.send(Command::Syn);
                    self.phase = Phase::RdyWait;
                }
                Command::Rty => self.on_rty(now, &msg),
                // Not initialised: SYN asks the board to initialise (§4.4.1 SYN, H).
                _ => self.send(Command::Syn),
            },
            Phase::RdyWait => match command {
                Command::Rdy => {
                    self.send(Command::Rdy);
                    self.phase = Phase::Ready;
                    self.set_needed = true;
                    tracing::info!("Protocol A link initialised");
                }
                Command::Rty => self.on_rty(now, &msg),
                _ => self.send(Command::Syn),
            },
            Phase::Ready => self.on_message_ready(now, msg),
        }
    }

    fn on_message_ready(&mut self, now: Instant, msg: Message) {
        match msg.command {
            Command::Syn => {
                // The board initialises again (after an error it detected).
                self.reinit(now, AbortReason::BoardReinit);
                self.send(Command::Syn);
                self.phase = Phase::RdyWait;
            }
            Command::Rdy => self.send(Command::Rdy),
            Command::Rst => {
                self.send(Command::Ars);
                // A reset ends the CNC's read: an EOD owed to it would meet the next read.
                self.drop_stale_eod();
                self.emit(EngineEvent::CncReset);
                self.abort_program(AbortReason::CncReset, false, false, true);
                self.run = None;
            }
            Command::Alm => {
                self.send(Command::Aal);
                self.drop_stale_eod();
                self.emit(EngineEvent::CncAlarm);
                self.abort_program(AbortReason::CncAlarm, false, false, true);
                self.run = None;
            }
            Command::Sat => {
                // A SAT that reports a new alarm status aborts the program first: what it
                // acknowledges then belongs to no program.
                let data = self.on_sat(&msg.data);
                if !self.sat_seen && self.params_alarmed {
                    tracing::info!("SAT at last: the cell file's parameters go with the SET");
                }
                self.sat_seen = true;
                self.on_exchange();
                self.owed = Some(Request::Sat {
                    data,
                    after_sdi: false,
                });
            }
            Command::Gtd => {
                self.on_exchange();
                self.owed = Some(Request::Gtd {
                    at: now,
                    after_sdi: false,
                });
            }
            Command::Sdi => match self.rdi_for.take() {
                Some(req) => {
                    self.on_exchange();
                    match parse_di(&msg.data) {
                        Some(v) => self.emit(EngineEvent::Di(v)),
                        None => self.protocol_error(
                            ProtocolError::SdiData {
                                data: msg.data.to_vec(),
                            },
                            false,
                        ),
                    }
                    // The SAT or GTD before the RDI gets its ordinary answer now; a pending SDO
                    // waits for the next SAT or GTD. An SDO here would be read by some boards as
                    // that answer and by others as one owed besides it (protocol notes 6): the
                    // ordinary answer means the same to every board.
                    self.owed = Some(req.resumed(now));
                }
                None => self.protocol_error(
                    ProtocolError::Unexpected {
                        command: Command::Sdi,
                        context: "without an RDI before it",
                    },
                    false,
                ),
            },
            Command::Rty => self.on_rty(now, &msg),
            command => self.protocol_error(
                ProtocolError::Unexpected {
                    command,
                    context: "from the remote buffer (a host command, §4.4.1)",
                },
                false,
            ),
        }
    }
}

/// The DI image of an SDI: two hex digits (either case).
fn parse_di(data: &[u8]) -> Option<u8> {
    let digit = |c: u8| char::from(c).to_digit(16);
    match data {
        [h, l, ..] => u8::try_from(digit(*h)? * 16 + digit(*l)?).ok(),
        _ => None,
    }
}

impl Engine for ProtocolAHost {
    type Command = EngineCommand;
    type Event = EngineEvent;

    fn handle_input(&mut self, now: Instant, bytes: &[u8]) {
        if !self.line_up {
            // DR off: nothing on the line is trusted.
            return;
        }
        let end = self.cfg.framing.end_byte();
        let mut rest = bytes;
        while let Some(&first) = rest.first() {
            if !self.monitor_buf.is_empty()
                || (self.decoder.buffered() == 0 && Monitor::is_code(first))
            {
                let take = (MONITOR_LEN - self.monitor_buf.len()).min(rest.len());
                let (head, tail) = rest.split_at(take);
                self.monitor_buf.extend_from_slice(head);
                rest = tail;
                if let Ok(packet) = <[u8; MONITOR_LEN]>::try_from(self.monitor_buf.as_slice()) {
                    self.monitor_buf.clear();
                    self.frames.received += 1;
                    self.on_monitor(now, packet);
                    self.try_answer(now);
                }
                continue;
            }
            let cut = rest
                .iter()
                .position(|&b| b == end)
                .map_or(rest.len(), |i| i + 1);
            let (head, tail) = rest.split_at(cut);
            self.decoder.push(head);
            rest = tail;
            while let Some(frame) = self.decoder.next_message() {
                self.frames.received += 1;
                self.on_frame(now, frame);
                // Answer before the next message: a GTD may start packets that a monitor
                // packet right behind it acts on.
                self.try_answer(now);
            }
        }
        self.after_step(now);
    }

    fn handle_line_error(&mut self, now: Instant, error: LineError) {
        if !self.line_up {
            return;
        }
        self.line_failure(now, LinkAlarm::Line(error));
        self.after_step(now);
    }

    fn handle_modem(&mut self, now: Instant, modem: ModemIn) {
        self.cs = modem.cs;
        let up = modem.dr && modem.cd;
        if !up && self.line_up {
            self.line_up = false;
            self.alarm(LinkAlarm::DataSetReadyOff);
            self.reinit(now, AbortReason::Link(LinkAlarm::DataSetReadyOff));
        } else if up && !self.line_up {
            tracing::info!("line up again: waiting for SYN");
            self.line_up = true;
            self.last_activity = now;
        }
        self.after_step(now);
    }

    fn handle_command(&mut self, now: Instant, command: EngineCommand) {
        match command {
            EngineCommand::StartProgram { total } => {
                if self.program.is_some() {
                    self.abort_program(AbortReason::Replaced, false, true, false);
                }
                tracing::debug!(?total, "program queued");
                self.program = Some(Program::new());
                self.acked = 0;
                self.dat_unacked = 0;
                self.final_sent = false;
                self.streaming = false;
            }
            EngineCommand::Streaming => self.streaming = true,
            EngineCommand::ProgramData(data) => {
                // In Protocol A the program travels in DATs, which cannot carry the end code.
                let forbidden = (effective_packet_n(self.cfg.packet_n) == 0)
                    .then(|| self.cfg.framing.end_byte());
                match self.program.as_mut() {
                    Some(p) => {
                        if let Err(e) = p.push(&data, forbidden) {
                            self.abort_program(AbortReason::Program(e), false, true, false);
                        }
                    }
                    None => tracing::trace!(len = data.len(), "program data without a program"),
                }
            }
            // G05 blocks in the special format are all even bytes: neither CR nor ETX, nor
            // EOR, can occur in them (protocol notes 14), so they need no check here.
            EngineCommand::BinaryData(data) => match self.program.as_mut() {
                Some(p) => p.push_binary(&data),
                None => tracing::trace!(len = data.len(), "binary data without a program"),
            },
            // Both before any answer (`after_step` below): a GTD waiting now gets the `G05`
            // block with the blocks behind it (§9.2).
            EngineCommand::Primed { text, blocks } => {
                let forbidden = (effective_packet_n(self.cfg.packet_n) == 0)
                    .then(|| self.cfg.framing.end_byte());
                if let Some(p) = self.program.as_mut() {
                    match p.push(&text, forbidden) {
                        Ok(()) => p.push_binary(&blocks),
                        Err(e) => self.abort_program(AbortReason::Program(e), false, true, false),
                    }
                }
            }
            EngineCommand::ProgramEnd => {
                if let Some(Err(e)) = self.program.as_mut().map(Program::end) {
                    self.abort_program(AbortReason::Program(e), false, true, false);
                }
            }
            EngineCommand::Cancel => {
                self.abort_program(AbortReason::Cancelled, true, true, false);
            }
            EngineCommand::SetDo(v) => {
                if self.set_do.len() >= MAX_PENDING_DO {
                    self.set_do.pop_front();
                }
                self.set_do.push_back(v);
            }
            EngineCommand::ReadDi => self.read_di = true,
            EngineCommand::ClearBuffer => self.clb_owed = true,
        }
        self.after_step(now);
    }

    fn handle_timeout(&mut self, now: Instant) {
        if let Some(deadline) = self.supervision_deadline()
            && now >= deadline
        {
            let waited = self.supervision_interval();
            if self.phase == Phase::RdyWait {
                self.protocol_error(ProtocolError::NoRdy { waited }, false);
                self.phase = Phase::SynWait;
            } else {
                self.line_failure(now, LinkAlarm::TimeOut { waited });
            }
        }
        if self.packet_pace.is_some_and(|t| now >= t) {
            self.packet_pace = None;
        }
        let interval = self.cfg.dummy_interval;
        if let Some(run) = self.run.as_mut()
            && run.waiting_for_data(self.program.as_ref())
            && now >= run.dummy_deadline(interval)
        {
            run.dummy_due = true;
        }
        self.after_step(now);
    }

    fn poll_transmit(&mut self, now: Instant) -> Option<Vec<u8>> {
        if !self.line_up || !self.cs {
            return None;
        }
        let chunk = self.tx_chunk();
        if let Some(out) = self.tx.front_mut() {
            let end = out.pos.saturating_add(chunk).min(out.bytes.len());
            let piece = out.bytes.get(out.pos..end).map(<[u8]>::to_vec);
            out.pos = end;
            if out.pos >= out.bytes.len()
                && let Some(done) = self.tx.pop_front()
            {
                self.frames.sent += 1;
                self.sent_at(now, done.bytes.len());
                if !done.program.is_empty() {
                    self.dat_unacked += done.program.len() as u64;
                    self.emit(EngineEvent::DataSent { data: done.program });
                }
                if done.last_of_program {
                    self.final_sent = true;
                }
                if let Some(v) = done.do_sent {
                    self.emit(EngineEvent::DoSent(v));
                }
            }
            return piece;
        }
        if self.packet_pace.is_some_and(|t| now < t) {
            return None;
        }
        self.packet_pace = None;
        let run = self.run.as_mut()?;
        let out = run.next(now, self.program.as_mut(), self.cfg.dummy_interval)?;
        let delivered = run.outcome == RunOutcome::Delivered;
        tracing::trace!(no = out.no, "data packet out");
        // The next packet may be handed over while the last few characters of this one
        // are still in the UART, so that the line does not idle for a timer's latency: a
        // DC3 sent when this packet has arrived still comes back well before the next one
        // is done.
        let line_time = self.line_time(out.bytes.len());
        if !line_time.is_zero() {
            // Back to back on the line: this packet starts when the last one is done.
            let done = self.packet_done.max(now) + line_time;
            self.packet_done = done;
            self.packet_pace = Some(done - self.line_time(PACE_SLACK).min(line_time));
        }
        if delivered && self.program.as_ref().is_some_and(Program::all_sent) {
            self.program = None;
        }
        self.sent_at(now, out.bytes.len());
        if !out.program.is_empty() {
            self.emit(EngineEvent::DataSent {
                data: Bytes::from(out.program),
            });
        }
        self.update_state();
        Some(out.bytes)
    }

    fn poll_event(&mut self) -> Option<EngineEvent> {
        self.events.pop_front()
    }

    fn frames(&self) -> FrameCounts {
        self.frames
    }

    fn poll_timeout(&self) -> Option<Instant> {
        if !self.line_up {
            return None;
        }
        let mut deadline: Option<Instant> = None;
        let mut consider = |t: Instant| {
            deadline = Some(deadline.map_or(t, |d| d.min(t)));
        };
        if self.phase == Phase::Ready
            && let Some(Request::Gtd { at, .. }) = &self.owed
        {
            consider(*at + self.cfg.wat_grace);
        }
        if self.cs
            && let Some(run) = &self.run
            && !run.dummy_due
            && run.waiting_for_data(self.program.as_ref())
        {
            consider(run.dummy_deadline(self.cfg.dummy_interval));
        }
        if self.cs
            && self.run.is_some()
            && let Some(t) = self.packet_pace
        {
            consider(t);
        }
        if let Some(t) = self.supervision_deadline() {
            consider(t);
        }
        deadline
    }
}

impl HostEngine for ProtocolAHost {
    fn data_wanted(&self) -> usize {
        self.program
            .as_ref()
            .map_or(0, |p| p.wanted(self.cfg.max_buffer))
    }

    fn waiting_for(&self) -> Option<&'static str> {
        if !self.line_up {
            return Some("DR and CD: the line is down (§3.2)");
        }
        match self.phase {
            Phase::SynWait => {
                return Some("SYN from the board: the link re-initialises (§4.6 1)");
            }
            Phase::RdyWait => return Some("RDY from the board (§4.3 (1))"),
            Phase::Ready => {}
        }
        if self.params_alarmed && !self.sat_seen {
            return Some(
                "a SAT: the cell file's parameters are not applied, the CNC was reading when the link came up; reset the CNC so that the board polls with SAT (protocol notes 19)",
            );
        }
        let queued = self
            .program
            .as_ref()
            .is_some_and(|p| p.sent == 0 && self.run.is_none());
        if queued && self.drain_wait {
            Some("a SAT with the buffer empty: the CNC still reads the last program (§8.2)")
        } else if queued {
            Some("GTD: the CNC has not asked for the program (§4.4.1)")
        } else {
            None
        }
    }
}

#[cfg(test)]
mod tests;
