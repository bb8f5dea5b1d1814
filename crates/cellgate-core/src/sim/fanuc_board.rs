//! A simulated FANUC remote-buffer board with its CNC: the device side of Protocol A,
//! Expansion Protocol A, Protocol B and Expansion Protocol B (§4–§7 of B-63322EN-1), sans-IO.
//!
//! [`FanucBoard`] implements [`Engine`]: bytes from the host, modem lines, commands (the
//! operator's cycle start, reset, a CNC alarm, the DI image, a punch-out) and the time go in;
//! bytes for the host, [`BoardEvent`]s, the ER output and the next deadline come out. The
//! protocol is one variant of the board (`Variant`), beside one CNC model
//! ([`crate::sim::cnc`]).
//!
//! Protocol A / Expansion A, in the manual's terms (details in the `protocol_a` submodule):
//! - power-on: after `first_request_delay` (≈2 s, §4.3 (1)) it sends SYN; the host answers
//!   SYN; the board sends RDY; the host answers RDY (initialised) or SYN (not ready yet: SYN
//!   again after `first_request_delay`);
//! - idle: ALM / RST first when the CNC raised an alarm or was reset; GTD when the CNC is
//!   reading and free space ≥ Nb; otherwise SAT Tp seconds after the last reception;
//! - every transmission waits Tx after the last reception (§4.3 (4)); every answer is awaited
//!   for To (§4.3 (3)); checksum errors get RTY and count against Ne with received RTYs
//!   (§4.6 2 (1)); Expansion A adds data packets and monitor packets (§5).
//!
//! Protocol B / Expansion B (details in the `protocol_b` submodule): no messages, only control
//! codes (§6.2). DC1 when the CNC reads and 4096 bytes are free; DC3 at 512 (2560) bytes free;
//! SR0856 past the overrun allowance after DC3; DC3 when the read ends at EOR; CNC alarm and
//! reset posted as NAK / SYN (after DC3 or DC4) or, with notification off, as DC3 and ER off
//! (§6.4); punch-out on demand as DC2 … DC4 under the host's DC3 / DC1 / DC2 and CS.
//!
//! G05 binary input operation (§9) is the CNC's ([`BoardConfig::g05`]): the board reports
//! its start, underruns and end as [`BoardEvent`]s, and its SR0890 as a CNC alarm.

mod expansion_a;
mod protocol_a;
pub mod protocol_b;

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use crate::engine::Engine;
use crate::engine::{LineError, ModemIn, ModemOut};
use crate::fanuc::Protocol;
use crate::fanuc::alarm::CncAlarm;
use crate::fanuc::g05::{G05Format, InvalidG05Format};
use crate::fanuc::message::{Command, Framing};
use crate::fanuc::packet::Monitor;
use crate::fanuc::sat::{AlarmCause, BufferStatus, ParamRangeError, Params, StatusData};
use crate::sim::cnc::{
    Cnc, DEFAULT_BUFFER_SIZE, DEFAULT_CONSUME_RATE, DEFAULT_KEEP_PROGRAM_BYTES, G05End, G05Notice,
    G05Stats, ReceivedProgram,
};

use protocol_a::ProtocolA;
use protocol_b::ProtocolB;

/// How the simulated board and its CNC are set up.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardConfig {
    /// `A`: Protocol A only (SET's n is taken as 0, as on an RS-232-C board);
    /// `ExpansionA`: Protocol A, and Expansion A whenever SET puts n ∈ {1, 2, 4} in force;
    /// `B`, `ExpansionB`: Protocol B / Expansion B (§6, §7).
    pub protocol: Protocol,
    /// Code (5000#2) and end code (5000#3) of the messages. Protocol B uses the code for its
    /// control codes (§6.2) and has no end code.
    pub framing: Framing,
    /// Power-on values of Nb..Tw (§4.5); SET changes them.
    pub params: Params,
    /// Power-on packet length parameter n (§5.2 1); 0 = Protocol A until a SET says otherwise.
    pub packet_n: u8,
    /// The board's buffer (8 KiB on the real board, §12.2). Protocol B needs at least 4096
    /// (its DC1 condition, §6.3); 8 KiB leaves DC3 at 7680 bytes held (B) or 5632 (Expansion B).
    pub buffer_size: usize,
    /// Bytes per second the CNC reads from the buffer while running; 0 = as fast as data
    /// arrives.
    pub consume_rate: u32,
    /// Delay before the first request after power-on or a line error (§4.3 (1): ≈2 s).
    /// Protocol B with `autostart`: how long a CNC in alarm waits before it resets itself.
    pub first_request_delay: Duration,
    /// Parameter 5000#1 ECH: echo SET byte 1 (remote/tape switching) in SAT byte 1; off, the
    /// board always sends 0 there.
    pub echo_remote: bool,
    /// The operator presses cycle start by himself: whenever the link is initialised (and
    /// one SAT exchange has completed since, so that the host can select n with SET first,
    /// protocol notes 5) and the CNC is neither reading nor in alarm, it starts reading; a CNC
    /// in alarm resets itself after the next SAT exchange has shown the alarm to the host.
    /// Protocol B: the CNC reads from power-on and again after every program; a CNC in alarm
    /// resets itself `first_request_delay` after the alarm (with the reset's notice), and
    /// after a reset it starts reading again `first_request_delay` later, as an operator
    /// would: what the host still sent when the reset came reaches a CNC that is not reading
    /// and is ignored (§8.2), not taken as the start of the next program.
    pub autostart: bool,
    /// Bytes of each received program kept in [`ReceivedProgram::data`].
    pub keep_program_bytes: usize,
    /// Protocol B: CNC alarm and reset are posted to the host as NAK / SYN (parameter 5003#3
    /// = 1, §6.1.2); off, the board sends DC3 and turns ER off instead (§6.4 (1)).
    pub notify_alarm_reset: bool,
    /// Protocol B with notification off: how long ER stays off after an alarm or reset. Longer
    /// than the host's modem-line polling (50 ms in cellgate), so that the host sees DR off.
    pub er_off_time: Duration,
    /// G05 binary input operation (§9): the CNC's parameters 7635, 7609, 2034 and 7618.
    /// `None`: the CNC has no binary input operation and reads `G05` as any other block.
    pub g05: Option<G05Format>,
    /// The CNC is already reading when the board comes up, as when the host (re)starts under
    /// a CNC that was started before: the board asks with GTD from the start and polls with
    /// SAT only when it has nothing to ask (protocol notes 19).
    pub reading_at_power_on: bool,
    /// Protocol A: after EOD the board sends no GTD until a SAT exchange has completed
    /// (a board that takes EOD as "nothing to send now"). Off, it asks again as soon as its
    /// CNC wants data, which §4.4.1 allows as well.
    pub eod_holds_gtd: bool,
}

impl Default for BoardConfig {
    fn default() -> Self {
        BoardConfig {
            protocol: Protocol::A,
            framing: Framing::default(),
            params: Params::POWER_ON,
            packet_n: 0,
            buffer_size: DEFAULT_BUFFER_SIZE,
            consume_rate: DEFAULT_CONSUME_RATE,
            first_request_delay: Duration::from_secs(2),
            echo_remote: false,
            autostart: false,
            keep_program_bytes: DEFAULT_KEEP_PROGRAM_BYTES,
            notify_alarm_reset: true,
            er_off_time: DEFAULT_ER_OFF_TIME,
            g05: None,
            reading_at_power_on: false,
            eod_holds_gtd: true,
        }
    }
}

/// Default [`BoardConfig::er_off_time`].
pub const DEFAULT_ER_OFF_TIME: Duration = Duration::from_secs(1);

/// Why a [`BoardConfig`] cannot be simulated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum BoardConfigError {
    /// Power-on parameters outside their §4.5 ranges.
    #[error("simulated board power-on parameters: {}", join(errors))]
    Params {
        /// Every parameter out of range.
        errors: Vec<ParamRangeError>,
    },
    /// A buffer smaller than Nb: the board would never send GTD (§4.5).
    #[error(
        "buffer of {buffer_size} bytes is smaller than Nb = {nb}: the board would never send GTD (§4.5)"
    )]
    BufferTooSmall {
        /// The `buffer_size` given, bytes.
        buffer_size: usize,
        /// The power-on Nb, bytes.
        nb: u16,
    },
    /// Protocol B: a buffer smaller than the free space DC1 asks for (§6.3).
    #[error(
        "buffer of {buffer_size} bytes is smaller than the {dc1_free} bytes of free space Protocol B asks for with DC1: the board would never send DC1 (§6.3)"
    )]
    BufferTooSmallForDc1 {
        /// The `buffer_size` given, bytes.
        buffer_size: usize,
        /// Free space the board needs before it sends DC1, bytes.
        dc1_free: usize,
    },
    /// A packet length parameter n the protocol does not take (§5.2 1).
    #[error(
        "packet length parameter n = {n} with {protocol:?}: n must be 0, except 0, 1, 2 or 4 for Expansion A (§5.2 1)"
    )]
    PacketN {
        /// The `packet_n` given.
        n: u8,
        /// The board's protocol.
        protocol: Protocol,
    },
    /// The CNC's G05 settings cannot be used.
    #[error("simulated CNC's G05 settings: {0}")]
    G05(InvalidG05Format),
}

fn join(errors: &[ParamRangeError]) -> String {
    errors
        .iter()
        .map(ToString::to_string)
        .collect::<Vec<_>>()
        .join("; ")
}

impl BoardConfig {
    /// Whether a board can be simulated with these settings; the first problem found if not.
    pub fn validate(&self) -> Result<(), BoardConfigError> {
        let errors = self.params.validate();
        if !errors.is_empty() {
            return Err(BoardConfigError::Params { errors });
        }
        if !self.protocol.is_a_family() {
            if self.buffer_size < protocol_b::DC1_FREE {
                return Err(BoardConfigError::BufferTooSmallForDc1 {
                    buffer_size: self.buffer_size,
                    dc1_free: protocol_b::DC1_FREE,
                });
            }
        } else if self.buffer_size < usize::from(self.params.nb) {
            return Err(BoardConfigError::BufferTooSmall {
                buffer_size: self.buffer_size,
                nb: self.params.nb,
            });
        }
        let n_ok = match self.protocol {
            Protocol::ExpansionA => matches!(self.packet_n, 0 | 1 | 2 | 4),
            _ => self.packet_n == 0,
        };
        if !n_ok {
            return Err(BoardConfigError::PacketN {
                n: self.packet_n,
                protocol: self.protocol,
            });
        }
        if let Some(g05) = &self.g05 {
            let errors = g05.validate_for(self.protocol, None);
            if !errors.is_empty() {
                return Err(BoardConfigError::G05(InvalidG05Format { errors }));
            }
        }
        Ok(())
    }
}

/// What the operator (or a test) does to the CNC.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum BoardCommand {
    /// Cycle start in remote mode: the CNC reads from the buffer (refused while in alarm).
    StartReading,
    /// Feed hold: the CNC stops reading; the buffer is kept.
    StopReading,
    /// The 8-bit DI image (PMC G152) the board reports in SDI.
    SetDi(u8),
    /// A CNC alarm: the CNC stops; ALM to the host; CAN during Expansion A packets.
    /// Protocol B: NAK (after DC3 / DC4), or DC3 and ER off with notification off (§6.4).
    RaiseAlarm,
    /// CNC reset: buffered data lost (§8.2), alarm cleared; RST to the host; CAN during
    /// Expansion A packets. Protocol B: SYN (after DC3 / DC4), or DC3 and ER off.
    Reset,
    /// Change the rate at which the running CNC reads, bytes per second (0 = unlimited).
    SetConsumeRate(u32),
    /// Whether the operator starts reads and resets alarms by himself (see
    /// [`BoardConfig::autostart`]); off, only [`BoardCommand::StartReading`] and
    /// [`BoardCommand::Reset`] do, so a CNC stays in alarm, and a job waits, until told.
    SetAutostart(bool),
    /// Protocol B: punch these bytes out to the host, exactly as given (the tape is already
    /// encoded: ISO with parity, ASCII or EIA), framed as DC2 … DC4 (§6.1.1 2). Punch-outs
    /// queue up; refused while DR is off or the CNC is in alarm. Ignored by Protocol A.
    Punch(Vec<u8>),
}

/// A Protocol B control code (§6.2), by its manual name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum ControlCode {
    /// Starts host transmission.
    Dc1,
    /// Starts punch-out; from the host: resume the punch-out.
    Dc2,
    /// Stops host transmission; from the host: stop the punch-out.
    Dc3,
    /// Stops punch-out.
    Dc4,
    /// Posts a CNC alarm.
    Nak,
    /// Posts a CNC reset.
    Syn,
}

impl ControlCode {
    /// The 7-bit code; [`crate::fanuc::CodeSystem::control`] gives the byte on the line.
    pub fn byte(self) -> u8 {
        use crate::fanuc::code;
        match self {
            Self::Dc1 => code::DC1,
            Self::Dc2 => code::DC2,
            Self::Dc3 => code::DC3,
            Self::Dc4 => code::DC4,
            Self::Nak => code::NAK,
            Self::Syn => code::SYN,
        }
    }
    /// The manual's name of the code: `DC1` … `DC4`, `NAK` or `SYN`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Dc1 => "DC1",
            Self::Dc2 => "DC2",
            Self::Dc3 => "DC3",
            Self::Dc4 => "DC4",
            Self::Nak => "NAK",
            Self::Syn => "SYN",
        }
    }
}

/// Protocol B flow-control counters of a board since power-on (all zero for Protocol A).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FlowCounters {
    /// DC1 codes sent: read requests and resumptions.
    pub dc1_sent: u64,
    /// DC3 codes sent: stops, ends of reads, and those before notices.
    pub dc3_sent: u64,
    /// Most characters received after one DC3 (the host's overrun, §6.3).
    pub max_overrun: usize,
    /// SR0856 alarms raised (past the allowance or the buffer full).
    pub overruns: u64,
    /// Punched bytes handed to the line.
    pub punched: u64,
}

/// The state of the board's link.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum BoardLinkState {
    /// Powered on, waiting the first-request delay (§4.3 (1)).
    PowerOn,
    /// SYN / RDY exchange in progress (power-on or re-initialisation after a line error).
    Initialising,
    /// Initialised: SAT / GTD traffic (Protocol B: DR on).
    Ready,
    /// DR is off (the host's ER): the board waits for it (§3.2, SR0855).
    LineDown,
}

impl BoardLinkState {
    /// The state's name in reports: `power-on`, `initialising`, `ready` or `line-down`.
    pub fn name(self) -> &'static str {
        match self {
            Self::PowerOn => "power-on",
            Self::Initialising => "initialising",
            Self::Ready => "ready",
            Self::LineDown => "line-down",
        }
    }
}

/// What the board reports.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum BoardEvent {
    /// The board's link state changed.
    LinkState(BoardLinkState),
    /// SAT bytes 2–3 changed: status, and the alarm cause while in alarm.
    Status {
        /// Byte 2 of SAT.
        status: BufferStatus,
        /// Byte 3 of SAT while in alarm; `None` otherwise.
        alarm_cause: Option<AlarmCause>,
    },
    /// A SET changed parameters, n or the code conversion.
    ParamsChanged {
        /// The parameters Nb..Tw now in force.
        params: Params,
        /// The packet length parameter n now in force.
        packet_n: u8,
        /// The code conversion now in force, (from, to); (0, 0) = none.
        conversion: (u8, u8),
    },
    /// A message went to the host.
    MessageSent(Command),
    /// A valid message came from the host.
    MessageReceived(Command),
    /// An Expansion A monitor packet went to the host.
    MonitorSent(Monitor),
    /// NC data (DAT or data packets) went into the buffer.
    DataReceived {
        /// Bytes stored.
        bytes: usize,
        /// Bytes the buffer holds now.
        buffered: usize,
    },
    /// NC data arrived while the CNC was not reading and was ignored (§8.2).
    DataIgnored {
        /// Bytes ignored.
        bytes: usize,
    },
    /// The CNC started reading.
    ReadingStarted,
    /// The CNC stopped reading.
    ReadingStopped,
    /// The CNC read a whole program, up to its EOR.
    ProgramReceived(ReceivedProgram),
    /// An SDO wrote the DO image (for every SDO, even with an unchanged value).
    DoChanged(u8),
    /// The board sent this DI image in SDI.
    DiSent(u8),
    /// CLB cleared the buffer.
    BufferCleared,
    /// Protocol B: a control code went to the line.
    ControlSent(ControlCode),
    /// Protocol B: the host's DC3 / DC1 / DC2 during a punch-out.
    ControlReceived(ControlCode),
    /// Protocol B: DC2 went out; `bytes` to punch.
    PunchStarted {
        /// Bytes to punch.
        bytes: usize,
    },
    /// Protocol B: the whole punch-out and its DC4 went out.
    PunchFinished {
        /// Bytes punched.
        bytes: usize,
    },
    /// Protocol B: a punch-out ended early (CNC reset or alarm, DR off) after `sent` of
    /// `bytes`, or was dropped before it started (`sent` 0).
    PunchInterrupted {
        /// Bytes punched before the punch-out ended.
        sent: usize,
        /// Bytes of the whole punch-out.
        bytes: usize,
    },
    /// Protocol B: the board turned its ER output off or on (§6.4 (1)).
    ErSignal {
        /// Whether ER is now on.
        on: bool,
    },
    /// The CNC read the `G05` block: binary input operation, one block every `unit_ms`
    /// (§9.1; protocol notes 15).
    G05Started {
        /// Axes in a block (parameter 7635).
        axes: u8,
        /// The unit time T, ms (parameter 7618).
        unit_ms: u32,
    },
    /// Unit times that found no whole block in the buffer (§9.2): `new` since the last
    /// report, `total` this session. At most one report a second; the end carries the total.
    G05Underruns {
        /// Underruns since the last report.
        new: u64,
        /// Underruns this session.
        total: u64,
    },
    /// Binary input operation ended (end block, SR0890, reset, alarm), with the session's
    /// totals.
    G05Ended {
        /// How the session ended.
        end: G05End,
        /// The session's totals.
        stats: G05Stats,
    },
    /// The board raised a CNC alarm of §11 (SR0855, SR0944, SR0945, ...; SR0890 is the
    /// CNC's own, followed by [`BoardEvent::CncAlarm`]).
    Alarm {
        /// The CNC alarm (§11).
        alarm: CncAlarm,
        /// The alarm cause SAT byte 3 reports for it.
        cause: AlarmCause,
        /// What happened, in words.
        detail: String,
    },
    /// The CNC went to alarm by [`BoardCommand::RaiseAlarm`] or by SR0890 (ALM follows;
    /// Protocol B: NAK, or DC3 and ER off).
    CncAlarm,
    /// The CNC was reset (RST follows; Protocol B: SYN, or DC3 and ER off).
    CncReset,
    /// A protocol error the board recovered from or ignored (RTY, NAK, garbage, SET field
    /// out of range, ...). For logs.
    ProtocolError {
        /// What happened, in words.
        detail: String,
    },
}

/// Bytes and events the board has produced, waiting for the driver.
#[derive(Debug, Default)]
pub(crate) struct Outbox {
    tx: VecDeque<Vec<u8>>,
    events: VecDeque<BoardEvent>,
}

impl Outbox {
    fn event(&mut self, e: BoardEvent) {
        self.events.push_back(e);
    }
    fn send(&mut self, bytes: Vec<u8>) {
        self.tx.push_back(bytes);
    }
}

/// The protocol a board speaks.
#[derive(Debug)]
enum Variant {
    A(Box<ProtocolA>),
    B(Box<ProtocolB>),
}

/// A simulated remote-buffer board with its CNC (sans-IO).
#[derive(Debug)]
pub struct FanucBoard {
    config: BoardConfig,
    cnc: Cnc,
    variant: Variant,
    out: Outbox,
    reported_status: Option<(BufferStatus, Option<AlarmCause>)>,
}

impl FanucBoard {
    /// A board powered on at `now`.
    pub fn new(config: BoardConfig, now: Instant) -> Result<Self, BoardConfigError> {
        config.validate()?;
        let mut cnc = Cnc::new(
            config.buffer_size,
            config.consume_rate,
            config.keep_program_bytes,
            now,
        );
        if let Some(format) = config.g05 {
            cnc = cnc.with_g05(format).map_err(BoardConfigError::G05)?;
        }
        let reading_at_power_on = config.reading_at_power_on && cnc.start_reading(now);
        let variant = if config.protocol.is_a_family() {
            Variant::A(Box::new(ProtocolA::new(&config, now)))
        } else {
            Variant::B(Box::new(ProtocolB::new(&config, now)))
        };
        let mut board = FanucBoard {
            config,
            cnc,
            variant,
            out: Outbox::default(),
            reported_status: None,
        };
        if reading_at_power_on {
            board.out.event(BoardEvent::ReadingStarted);
        }
        board.step(now);
        Ok(board)
    }

    /// The settings the board was powered on with.
    pub fn config(&self) -> &BoardConfig {
        &self.config
    }

    /// The CNC: buffer, reading state, DI/DO images, alarm.
    pub fn cnc(&self) -> &Cnc {
        &self.cnc
    }

    /// The link's state as the board sees it.
    pub fn link_state(&self) -> BoardLinkState {
        match &self.variant {
            Variant::A(a) => a.link_state(),
            Variant::B(b) => b.link_state(),
        }
    }

    /// Whether the operator starts reads and resets alarms by himself (see
    /// [`BoardConfig::autostart`] and [`BoardCommand::SetAutostart`]).
    pub fn autostart(&self) -> bool {
        match &self.variant {
            Variant::A(a) => a.autostart(),
            Variant::B(b) => b.autostart(),
        }
    }

    /// The parameters in force (§4.5; Protocol B: the configured ones, unused).
    pub fn params(&self) -> Params {
        match &self.variant {
            Variant::A(a) => a.params(),
            Variant::B(_) => self.config.params,
        }
    }

    /// The Expansion A packet length parameter n in force (0 = Protocol A).
    pub fn packet_n(&self) -> u8 {
        match &self.variant {
            Variant::A(a) => a.packet_n(),
            Variant::B(_) => 0,
        }
    }

    /// The data part the board's next SAT would carry (§4.4.2 1). Protocol B has no SAT:
    /// status, alarm cause and bytes buffered only.
    pub fn status_data(&self) -> StatusData {
        match &self.variant {
            Variant::A(a) => a.status_data(&self.cnc),
            Variant::B(b) => b.status_data(&self.cnc),
        }
    }

    /// Protocol B flow-control counters (zero for Protocol A).
    pub fn flow_counters(&self) -> FlowCounters {
        match &self.variant {
            Variant::A(_) => FlowCounters::default(),
            Variant::B(b) => b.counters(),
        }
    }

    /// Runs everything due at `now`, then reports a status change.
    fn step(&mut self, now: Instant) {
        self.cnc.advance(now);
        self.collect_cnc(now);
        match &mut self.variant {
            Variant::A(a) => a.step(now, &mut self.cnc, &mut self.out),
            Variant::B(b) => b.step(now, &mut self.cnc, &mut self.out),
        }
        self.collect_cnc(now);
        let status = (self.cnc.status(), self.cnc.alarm());
        if self.reported_status != Some(status) {
            self.reported_status = Some(status);
            self.out.event(BoardEvent::Status {
                status: status.0,
                alarm_cause: status.1,
            });
        }
    }

    /// Reports what the CNC did: binary input operation and its SR0890, programs read. In
    /// that order: a program read ends the CNC's reading, so nothing it did before can follow.
    fn collect_cnc(&mut self, now: Instant) {
        while let Some(notice) = self.cnc.take_g05_notice() {
            match notice {
                G05Notice::Entered { .. } => {
                    let (axes, unit_ms) = self
                        .cnc
                        .g05_format()
                        .map_or((0, 0), |f| (f.axes, f.unit_time_ms.ms()));
                    self.out.event(BoardEvent::G05Started { axes, unit_ms });
                }
                G05Notice::Underruns { new, total } => {
                    self.out.event(BoardEvent::G05Underruns { new, total });
                }
                G05Notice::CheckSum(error) => {
                    let alarm = CncAlarm::Sr0890G05CheckSum;
                    let detail = error.to_string();
                    tracing::warn!(alarm = alarm.number(), %detail, "simulated CNC alarm");
                    self.out.event(BoardEvent::Alarm {
                        alarm,
                        cause: AlarmCause::NcAlarm,
                        detail,
                    });
                    // The CNC stopped reading when it found the error.
                    self.out.event(BoardEvent::ReadingStopped);
                    // The host hears of it as of any CNC alarm: ALM (CAN during packets);
                    // Protocol B: NAK, or DC3 and ER off.
                    match &mut self.variant {
                        Variant::A(a) => a.cnc_alarm(now, &mut self.cnc, &mut self.out),
                        Variant::B(b) => b.cnc_alarm(now, &mut self.cnc, &mut self.out),
                    }
                }
                G05Notice::Left { end, stats } => {
                    self.out.event(BoardEvent::G05Ended { end, stats });
                }
            }
        }
        while let Some(p) = self.cnc.take_finished() {
            self.out.event(BoardEvent::ProgramReceived(p));
            self.out.event(BoardEvent::ReadingStopped);
        }
    }
}

impl Engine for FanucBoard {
    type Command = BoardCommand;
    type Event = BoardEvent;

    fn handle_input(&mut self, now: Instant, bytes: &[u8]) {
        self.cnc.advance(now);
        self.collect_cnc(now);
        match &mut self.variant {
            Variant::A(a) => a.handle_input(now, bytes, &mut self.cnc, &mut self.out),
            Variant::B(b) => b.handle_input(now, bytes, &mut self.cnc, &mut self.out),
        }
        self.step(now);
    }

    fn handle_line_error(&mut self, now: Instant, error: LineError) {
        match &mut self.variant {
            Variant::A(a) => a.handle_line_error(now, error, &mut self.cnc, &mut self.out),
            Variant::B(b) => b.handle_line_error(now, error, &mut self.cnc, &mut self.out),
        }
        self.step(now);
    }

    fn handle_modem(&mut self, now: Instant, modem: ModemIn) {
        match &mut self.variant {
            Variant::A(a) => a.handle_modem(now, modem, &mut self.cnc, &mut self.out),
            Variant::B(b) => b.handle_modem(now, modem, &mut self.cnc, &mut self.out),
        }
        self.step(now);
    }

    fn handle_command(&mut self, now: Instant, command: BoardCommand) {
        self.cnc.advance(now);
        self.collect_cnc(now);
        match command {
            BoardCommand::StartReading => {
                let was = self.cnc.reading();
                if self.cnc.start_reading(now) {
                    if !was {
                        self.out.event(BoardEvent::ReadingStarted);
                    }
                } else {
                    self.out.event(BoardEvent::ProtocolError {
                        detail: "cycle start refused: the CNC is in alarm (reset it first)"
                            .to_string(),
                    });
                }
            }
            BoardCommand::StopReading => {
                if self.cnc.reading() {
                    self.cnc.stop_reading(now);
                    self.out.event(BoardEvent::ReadingStopped);
                }
            }
            BoardCommand::SetDi(di) => self.cnc.set_di(di),
            BoardCommand::SetConsumeRate(rate) => self.cnc.set_rate(now, rate),
            BoardCommand::SetAutostart(on) => match &mut self.variant {
                Variant::A(a) => a.set_autostart(on),
                Variant::B(b) => b.set_autostart(on),
            },
            BoardCommand::RaiseAlarm => match &mut self.variant {
                Variant::A(a) => a.cnc_alarm(now, &mut self.cnc, &mut self.out),
                Variant::B(b) => b.cnc_alarm(now, &mut self.cnc, &mut self.out),
            },
            BoardCommand::Reset => match &mut self.variant {
                Variant::A(a) => a.cnc_reset(now, &mut self.cnc, &mut self.out),
                Variant::B(b) => b.cnc_reset(now, &mut self.cnc, &mut self.out),
            },
            BoardCommand::Punch(data) => match &mut self.variant {
                Variant::A(_) => self.out.event(BoardEvent::ProtocolError {
                    detail: "punch-out is a Protocol B function (§6.1.1 2); ignored".to_string(),
                }),
                Variant::B(b) => b.punch(data, &self.cnc, &mut self.out),
            },
        }
        self.step(now);
    }

    fn handle_timeout(&mut self, now: Instant) {
        self.step(now);
    }

    fn poll_transmit(&mut self, now: Instant) -> Option<Vec<u8>> {
        if let Some(bytes) = self.out.tx.pop_front() {
            return Some(bytes);
        }
        match &mut self.variant {
            Variant::A(_) => None,
            Variant::B(b) => {
                // Protocol B hands out codes and punch pieces as the line takes them; what it
                // handed out (a DC4, a DC3) may let it queue more.
                let bytes = b.poll_transmit(now, &mut self.out)?;
                self.step(now);
                Some(bytes)
            }
        }
    }

    fn poll_event(&mut self) -> Option<BoardEvent> {
        self.out.events.pop_front()
    }

    fn poll_timeout(&self) -> Option<Instant> {
        let protocol = match &self.variant {
            Variant::A(a) => a.poll_timeout(&self.cnc),
            Variant::B(b) => b.poll_timeout(&self.cnc),
        };
        // The CNC reaching EOR is an event of its own (and may restart an autostart CNC), and
        // so is every unit time of binary input operation with a block waiting.
        [
            protocol,
            self.cnc.when_program_ends(),
            self.cnc.next_g05_deadline(),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    fn modem_out(&self) -> ModemOut {
        match &self.variant {
            Variant::A(_) => ModemOut::ALL_ON,
            Variant::B(b) => b.modem_out(),
        }
    }
}
