//! Protocol A and Expansion Protocol A from the remote buffer's side (§4, §5).
//!
//! One exchange at a time: the board sends a message and awaits the host's answer for To
//! (restarted by every byte received, so that a long DAT at a low baud rate is not cut off).
//!
//! | board sends | host may answer (§4.4.1; protocol notes 6)                             |
//! |-------------|------------------------------------------------------------------------|
//! | SYN         | SYN (then the board sends RDY)                                         |
//! | RDY         | RDY (initialised) or SYN (not ready: SYN again later)                  |
//! | SAT         | SET, CLB, SDO (done), RDI (→ SDI, the answer is still owed), SYN       |
//! | GTD         | DAT, EOD, WAT (GTD again after Tw), SDO (GTD again), RDI, SYN; with n ≠ 0 data packets |
//! | SDI         | SDO (for the SDI), or the answer owed to the SAT / GTD before it       |
//! | RST / ALM   | ARS / AAL                                                              |
//!
//! RTY from the host makes the board resend its last message; a checksum error makes it send
//! RTY '1'. Both count against Ne (§4.6 2 (1)); past Ne: SR0945, alarm cause 1, and back to
//! SAT polling. An undefined command or a format error: SR0948; a defined command that is not
//! an answer to what the board sent: SR0947 (alarm cause 6 for both, §4.6 2 (2)). No answer
//! within To: SR0944 and re-initialisation (§4.6 1 (6)). DR off: SR0855 (§3.2). A framing or
//! overrun error: SR0946; a parity error: re-initialisation (§4.6 1). NC data beyond the free
//! space (the host ignored DC3, or a DAT longer than Nb − No allows): SR0856, alarm cause A,
//! re-initialisation (§4.6 1 (5)). SR alarms put the CNC in alarm: it stops reading until it
//! is reset. During initialisation (SYN / RDY) nothing raises an alarm; the board just sends
//! SYN again every To.
//!
//! After EOD the board sends no GTD until a SAT exchange has completed, so that a host with no
//! data is asked about every Tp rather than in a tight loop ([`BoardConfig::eod_holds_gtd`];
//! off, it asks again as soon as its CNC wants data).
//!
//! Expansion A (§5), when n ∈ {1, 2, 4} is in force at GTD time: the host answers the GTD with
//! data packets of `packet::packet_len(n)` bytes (or with a Protocol A message, recognised when
//! a valid non-DAT message starts where the first packet would; once packets flow the host
//! sends only packets until its end packet). Packets are judged by
//! [`super::expansion_a`]. Flow control: DC3 when free space falls below two packets' data
//! (one packet may still be in flight when the host sees it); DC1 when free space is back to
//! max(Nb, three packets' data), capped at the buffer size. To supervises the time to the
//! first packet after GTD and between packets (§5.4 7), and is suspended while DC3 is in
//! force. A CNC reset or alarm during the packets, or between the GTD and the host's answer,
//! sends CAN; the board then waits for the end packet, ignores its data, and goes back to
//! Protocol A (then RST / ALM). A Protocol A command where it awaits that end packet is an
//! unexpected command, SR0947 (§5.3 1; protocol notes 16). NAKs count against
//! Ne; past Ne: SR0945 and CAN. A packet stream that lost bytes is not realigned: its packets
//! fail until the NAKs exceed Ne.

use std::time::{Duration, Instant};

use crate::engine::{LineError, ModemIn};
use crate::fanuc::Protocol;
use crate::fanuc::alarm::CncAlarm;
use crate::fanuc::message::{
    Command, FrameError, Framing, MAX_FRAME, MAX_OTHER_DATA, Message, RTY_CHECKSUM, hex2,
};
use crate::fanuc::packet::{self, Monitor};
use crate::fanuc::sat::{AlarmCause, Params, StatusData};
use crate::sim::cnc::Cnc;

mod errors;
mod host_data;

use super::expansion_a::{GtdRx, Verdict};
use super::{BoardConfig, BoardEvent, BoardLinkState, Outbox};

/// What the board is doing.
#[derive(Debug)]
enum Phase {
    /// Not talking: power-on or re-initialisation delay until `until`; `None` while DR is off.
    Off { until: Option<Instant> },
    /// Initialised, no exchange outstanding.
    Idle,
    /// A message went out (or is about to, after Tx); the host's answer is awaited.
    Awaiting { exchange: Exchange, after_sdi: bool },
    /// WAT received: GTD again at `until` (§4.4.1 WAT).
    WatWait { until: Instant },
}

/// The message the board sent and awaits an answer to.
#[derive(Debug)]
enum Exchange {
    Syn,
    Rdy,
    Sat,
    Gtd(Box<GtdRx>),
    Rst,
    Alm,
}

impl Exchange {
    fn command(&self) -> Command {
        match self {
            Exchange::Syn => Command::Syn,
            Exchange::Rdy => Command::Rdy,
            Exchange::Sat => Command::Sat,
            Exchange::Gtd(_) => Command::Gtd,
            Exchange::Rst => Command::Rst,
            Exchange::Alm => Command::Alm,
        }
    }

    fn answers(&self, after_sdi: bool) -> &'static str {
        match (self, after_sdi) {
            (Exchange::Syn, _) => "SYN",
            (Exchange::Rdy, _) => "RDY or SYN",
            (Exchange::Sat, false) => "SET, CLB, RDI, SDO or SYN",
            (Exchange::Sat, true) => "SDO, or SET, CLB, RDI or SYN for the SAT",
            (Exchange::Gtd(g), false) if g.n > 0 => "data packets, EOD, WAT, RDI, SDO or SYN",
            (Exchange::Gtd(_), false) => "DAT, EOD, WAT, RDI, SDO or SYN",
            (Exchange::Gtd(_), true) => "SDO, or DAT, EOD, WAT, RDI or SYN for the GTD",
            (Exchange::Rst, _) => "ARS",
            (Exchange::Alm, _) => "AAL",
        }
    }
}

/// One unit of input: a Protocol A message, or an Expansion A data packet.
enum Unit {
    Frame(Result<Message, FrameError>),
    Packet(Vec<u8>),
}

/// Longest message other than DAT, as it travels.
const MAX_SHORT_FRAME: usize = 2 + 3 + MAX_OTHER_DATA + 1;

fn secs(s: u16) -> Duration {
    Duration::from_secs(u64::from(s))
}

fn millis(ms: u16) -> Duration {
    Duration::from_millis(u64::from(ms))
}

fn send_monitor(m: Monitor, out: &mut Outbox) {
    out.send(m.encode().to_vec());
    out.event(BoardEvent::MonitorSent(m));
}

/// Two hex digits (either case) as a byte: the SDO data part (§4.4.2 5).
fn parse_image(data: &[u8]) -> Option<u8> {
    let d = data.get(..2)?;
    if !d.iter().all(u8::is_ascii_hexdigit) {
        return None;
    }
    u8::from_str_radix(std::str::from_utf8(d).ok()?, 16).ok()
}

/// Takes a SET field when it lies in its §4.5 range; otherwise keeps `current` and says so.
fn checked(name: &str, value: u16, range: (u16, u16), current: u16, out: &mut Outbox) -> u16 {
    let (min, max) = range;
    if (min..=max).contains(&value) {
        value
    } else {
        out.event(BoardEvent::ProtocolError {
            detail: format!(
                "SET {name} = {value} ignored: must be within {min}..={max} (§4.5; protocol notes 5)"
            ),
        });
        current
    }
}

/// The device side of Protocol A / Expansion A.
#[derive(Debug)]
pub(super) struct ProtocolA {
    framing: Framing,
    expansion: bool,
    first_request_delay: Duration,
    echo_remote: bool,
    autostart: bool,
    params: Params,
    packet_n: u8,
    conversion: (u8, u8),
    boring_unit: u16,
    remote: bool,
    phase: Phase,
    link: BoardLinkState,
    rx: Vec<u8>,
    /// Dropping input up to the next end code after an oversize run.
    discarding: bool,
    /// The next message, sent once Tx has passed since the last reception (§4.3 (4)).
    queued: Option<Message>,
    /// What an RTY from the host asks for again.
    last_sent: Option<Message>,
    /// RTYs received + RTYs sent in this exchange (§4.6 2 (1)).
    retries: u16,
    earliest_tx: Instant,
    /// Start of the Tp wait before the next SAT.
    idle_since: Instant,
    /// Last message sent or byte received: To runs from here.
    last_activity: Instant,
    dr: bool,
    cs: bool,
    pending_rst: bool,
    pending_alm: bool,
    /// EOD received: no GTD before the next SAT exchange.
    no_data: bool,
    /// Whether EOD holds GTD until a SAT exchange ([`BoardConfig::eod_holds_gtd`]).
    eod_holds_gtd: bool,
    /// A SAT exchange completed since the link was initialised (autostart waits for one, so
    /// that the host can select n with SET before the first GTD; protocol notes 5).
    sat_done: bool,
}

impl ProtocolA {
    pub(super) fn new(config: &BoardConfig, now: Instant) -> Self {
        ProtocolA {
            framing: config.framing,
            expansion: config.protocol == Protocol::ExpansionA,
            first_request_delay: config.first_request_delay,
            echo_remote: config.echo_remote,
            autostart: config.autostart,
            params: config.params,
            packet_n: config.packet_n,
            conversion: (0, 0),
            boring_unit: 0,
            remote: false,
            phase: Phase::Off {
                until: Some(now + config.first_request_delay),
            },
            link: BoardLinkState::PowerOn,
            rx: Vec::new(),
            discarding: false,
            queued: None,
            last_sent: None,
            retries: 0,
            earliest_tx: now,
            idle_since: now,
            last_activity: now,
            dr: true,
            cs: true,
            pending_rst: false,
            pending_alm: false,
            no_data: false,
            eod_holds_gtd: config.eod_holds_gtd,
            sat_done: false,
        }
    }

    pub(super) fn link_state(&self) -> BoardLinkState {
        self.link
    }
    pub(super) fn params(&self) -> Params {
        self.params
    }
    pub(super) fn packet_n(&self) -> u8 {
        self.packet_n
    }

    /// The SAT data part (§4.4.2 1). Byte 3 is 0 when the board is not in alarm.
    pub(super) fn status_data(&self, cnc: &Cnc) -> StatusData {
        StatusData {
            remote: Some(self.echo_remote && self.remote),
            status: Some(cnc.status()),
            alarm_cause: Some(cnc.alarm().unwrap_or(AlarmCause::NcAlarm)),
            buffered: Some(u16::try_from(cnc.buffered()).unwrap_or(u16::MAX)),
            params: Some(self.params),
            boring_unit: Some(self.boring_unit),
            conversion: Some(self.conversion),
            packet_n: Some(self.packet_n),
        }
    }

    fn initialised(&self) -> bool {
        self.link == BoardLinkState::Ready
    }

    fn can_tx(&self) -> bool {
        self.dr && self.cs
    }

    fn set_link(&mut self, link: BoardLinkState, out: &mut Outbox) {
        if self.link != link {
            self.link = link;
            out.event(BoardEvent::LinkState(link));
        }
    }

    fn queue(&mut self, msg: Message) {
        self.queued = Some(msg);
    }

    fn awaiting(&mut self, exchange: Exchange) {
        self.phase = Phase::Awaiting {
            exchange,
            after_sdi: false,
        };
    }

    fn gtd(&mut self) -> Option<&mut GtdRx> {
        match &mut self.phase {
            Phase::Awaiting {
                exchange: Exchange::Gtd(g),
                ..
            } => Some(g),
            _ => None,
        }
    }

    /// When the next input may be an Expansion A data packet: n, and whether packets have
    /// started (from then on the host sends nothing but packets until its end packet, §5.2 2 b).
    fn packet_mode(&self) -> Option<(u8, bool)> {
        match &self.phase {
            Phase::Awaiting {
                exchange: Exchange::Gtd(g),
                ..
            } if g.n > 0 => Some((g.n, g.started)),
            _ => None,
        }
    }

    /// Whether data packets are flowing (so errors end them with CAN rather than at once).
    fn in_packets(&self) -> bool {
        matches!(&self.phase, Phase::Awaiting { exchange: Exchange::Gtd(g), .. } if g.n > 0 && g.started)
    }

    fn dc1_level(&self, n: u8, cnc: &Cnc) -> usize {
        let p = packet::data_len(n);
        usize::from(self.params.nb).max(3 * p).min(cnc.capacity())
    }

    fn gtd_allowed(&self, cnc: &Cnc) -> bool {
        self.initialised()
            && !self.no_data
            && cnc.reading()
            && cnc.alarm().is_none()
            && cnc.free() >= usize::from(self.params.nb)
    }

    /// When the host's answer is overdue (To, §4.3 (3); §5.4 7 between packets).
    fn to_deadline(&self) -> Option<Instant> {
        match &self.phase {
            Phase::Awaiting { exchange, .. } if self.queued.is_none() => {
                if let Exchange::Gtd(g) = exchange
                    && g.dc3
                    && !g.cancelled
                {
                    return None;
                }
                Some(self.last_activity + secs(self.params.to))
            }
            _ => None,
        }
    }

    // ---- input ----------------------------------------------------------------------------

    pub(super) fn handle_input(
        &mut self,
        now: Instant,
        bytes: &[u8],
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        if matches!(self.phase, Phase::Off { .. }) {
            return; // not listening yet
        }
        self.last_activity = now;
        self.rx.extend_from_slice(bytes);
        while let Some(unit) = self.next_unit() {
            self.earliest_tx = now + millis(self.params.tx);
            match unit {
                Unit::Frame(res) => self.on_frame(now, res, cnc, out),
                Unit::Packet(raw) => self.on_packet(now, &raw, cnc, out),
            }
            if matches!(self.phase, Phase::Off { .. }) {
                self.rx.clear();
                break;
            }
        }
    }

    fn next_unit(&mut self) -> Option<Unit> {
        if let Some((n, started)) = self.packet_mode() {
            return self.next_packet_unit(n, started);
        }
        let end = self.framing.end_byte();
        loop {
            match self.rx.iter().position(|&b| b == end) {
                Some(i) => {
                    let frame: Vec<u8> = self.rx.drain(..=i).collect();
                    if std::mem::take(&mut self.discarding) {
                        continue;
                    }
                    return Some(Unit::Frame(self.framing.decode(&frame)));
                }
                None if self.rx.len() > MAX_FRAME => {
                    let dropped = self.rx.len();
                    self.rx.clear();
                    if std::mem::replace(&mut self.discarding, true) {
                        return None;
                    }
                    return Some(Unit::Frame(Err(FrameError::Oversize { dropped })));
                }
                None => return None,
            }
        }
    }

    /// After a GTD with n ≠ 0: before the first packet, a valid Protocol A message (the host
    /// may answer the GTD with EOD, WAT, RDI, SDO, RTY or SYN); otherwise a whole packet.
    ///
    /// A first packet whose number and first data bytes happen to form a valid message
    /// (`0` + `7SYN` + CR) would be taken for that message; NC data does not start so.
    fn next_packet_unit(&mut self, n: u8, started: bool) -> Option<Unit> {
        let end = self.framing.end_byte();
        let window = if started {
            0
        } else {
            self.rx.len().min(MAX_SHORT_FRAME)
        };
        if let Some(i) = self.rx[..window].iter().position(|&b| b == end)
            && let Ok(msg) = self.framing.decode(&self.rx[..=i])
            && msg.command != Command::Dat
        {
            self.rx.drain(..=i);
            return Some(Unit::Frame(Ok(msg)));
        }
        let len = packet::packet_len(n);
        (self.rx.len() >= len).then(|| Unit::Packet(self.rx.drain(..len).collect()))
    }

    fn on_frame(
        &mut self,
        now: Instant,
        res: Result<Message, FrameError>,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        match res {
            Ok(msg) => {
                out.event(BoardEvent::MessageReceived(msg.command));
                self.on_message(now, msg, cnc, out);
            }
            Err(e) if e.is_checksum_error() => {
                out.event(BoardEvent::ProtocolError {
                    detail: format!("{e}: RTY"),
                });
                if self.count_retry(now, cnc, out) {
                    self.queue(Message::with_data(Command::Rty, vec![RTY_CHECKSUM]));
                }
            }
            Err(e) if e.is_line_error() => {
                self.line_error(now, None, AlarmCause::NcAlarm, e.to_string(), cnc, out);
            }
            Err(e) => self.command_error(now, CncAlarm::Sr0948BadCommand, e.to_string(), cnc, out),
        }
    }

    /// Counts one retry; past Ne it handles the retry-over and returns false.
    fn count_retry(&mut self, now: Instant, cnc: &mut Cnc, out: &mut Outbox) -> bool {
        self.retries = self.retries.saturating_add(1);
        if self.retries <= self.params.ne {
            return true;
        }
        let detail = format!(
            "retry count over: {} retries > Ne = {} (§4.6 2 (1))",
            self.retries, self.params.ne
        );
        if self.initialised() {
            self.reception_error(
                now,
                CncAlarm::Sr0945RetryOver,
                AlarmCause::ChecksumRetryOver,
                detail,
                cnc,
                out,
            );
        } else {
            out.event(BoardEvent::ProtocolError { detail });
            self.start_init(out);
        }
        false
    }

    fn on_message(&mut self, now: Instant, msg: Message, cnc: &mut Cnc, out: &mut Outbox) {
        let cmd = msg.command;
        if cmd == Command::Rty {
            if matches!(self.phase, Phase::Awaiting { .. }) {
                if self.count_retry(now, cnc, out)
                    && let Some(last) = self.last_sent.clone()
                {
                    self.queue(last);
                }
            } else {
                self.unexpected(
                    now,
                    cmd,
                    "while no message of the board was outstanding",
                    cnc,
                    out,
                );
            }
            return;
        }
        match std::mem::replace(&mut self.phase, Phase::Idle) {
            phase @ Phase::Off { .. } => self.phase = phase,
            phase @ (Phase::Idle | Phase::WatWait { .. }) => {
                if cmd == Command::Syn {
                    self.host_initialises(out);
                } else {
                    self.phase = phase;
                    self.unexpected(
                        now,
                        cmd,
                        "while no message of the board was outstanding",
                        cnc,
                        out,
                    );
                }
            }
            Phase::Awaiting {
                exchange,
                after_sdi,
            } => self.on_answer(now, exchange, after_sdi, msg, cnc, out),
        }
    }

    /// The host's answer to `exchange`. `self.phase` is Idle on entry; every arm sets it.
    fn on_answer(
        &mut self,
        now: Instant,
        exchange: Exchange,
        after_sdi: bool,
        msg: Message,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        use Command as C;
        let cmd = msg.command;
        match (exchange, cmd) {
            (Exchange::Syn, C::Syn) => {
                self.retries = 0;
                self.queue(Message::new(C::Rdy));
                self.awaiting(Exchange::Rdy);
            }
            (Exchange::Rdy, C::Rdy) => {
                self.complete(now);
                self.no_data = false;
                self.sat_done = false;
                self.set_link(BoardLinkState::Ready, out);
            }
            (Exchange::Rdy, C::Syn) => {
                // The host is not initialised yet (§4.4.1 RDY): SYN again later.
                self.retries = 0;
                self.phase = Phase::Off {
                    until: Some(now + self.first_request_delay),
                };
            }
            (exchange @ (Exchange::Syn | Exchange::Rdy), _) => {
                out.event(BoardEvent::ProtocolError {
                    detail: format!(
                        "{cmd} in answer to {} during initialisation ignored",
                        exchange.command()
                    ),
                });
                self.phase = Phase::Awaiting {
                    exchange,
                    after_sdi,
                };
            }
            (_, C::Syn) => self.host_initialises(out),
            // After CAN only the end packet may come, even before the first data packet
            // (§5.3 1; protocol notes 16): a Protocol A answer to the GTD is unexpected.
            (Exchange::Gtd(g), _) if g.cancelled => {
                let context = "after CAN, where only the end packet may come (§5.3 1)";
                self.phase = Phase::Awaiting {
                    exchange: Exchange::Gtd(g),
                    after_sdi,
                };
                self.unexpected(now, cmd, context, cnc, out);
            }
            (exchange @ (Exchange::Sat | Exchange::Gtd(_)), C::Rdi) => {
                self.retries = 0;
                let di = cnc.di();
                self.queue(Message::with_data(C::Sdi, hex2(di).to_vec()));
                out.event(BoardEvent::DiSent(di));
                self.phase = Phase::Awaiting {
                    exchange,
                    after_sdi: true,
                };
            }
            // After SDI the host owes "the response of the command received immediately before
            // the RDI" (§4.4.1 SDI); SDO is a response of SAT and GTD, so an SDO here answers
            // the SAT or GTD (the arms below), and nothing more is owed.
            (Exchange::Sat, C::Set) => match self.apply_set(&msg.data, out) {
                Ok(()) => self.complete_sat(now, cnc, out),
                Err(e) => self.command_error(
                    now,
                    CncAlarm::Sr0948BadCommand,
                    format!("SET data part: {e}"),
                    cnc,
                    out,
                ),
            },
            (Exchange::Sat, C::Clb) => {
                cnc.clear_buffer(now);
                out.event(BoardEvent::BufferCleared);
                self.complete_sat(now, cnc, out);
            }
            (Exchange::Sat, C::Sdo) => {
                if self.apply_sdo(now, &msg, cnc, out) {
                    self.complete_sat(now, cnc, out);
                }
            }
            (Exchange::Gtd(g), C::Dat) if g.n == 0 => {
                if self.store(now, msg.data, cnc, out) {
                    self.complete(now);
                }
            }
            (Exchange::Gtd(_), C::Eod) => {
                self.no_data = self.eod_holds_gtd;
                self.complete(now);
            }
            (Exchange::Gtd(_), C::Wat) => {
                self.retries = 0;
                self.idle_since = now;
                self.phase = Phase::WatWait {
                    until: now + secs(self.params.tw),
                };
            }
            (Exchange::Gtd(_), C::Sdo) => {
                // SDO completes the GTD exchange; the board asks for data again (notes 6).
                if self.apply_sdo(now, &msg, cnc, out) {
                    self.complete(now);
                }
            }
            (Exchange::Rst, C::Ars) | (Exchange::Alm, C::Aal) => self.complete(now),
            (exchange, _) => {
                let context = format!(
                    "in answer to {} (expected {})",
                    exchange.command(),
                    exchange.answers(after_sdi)
                );
                self.phase = Phase::Awaiting {
                    exchange,
                    after_sdi,
                };
                self.unexpected(now, cmd, &context, cnc, out);
            }
        }
    }

    /// An exchange ended normally: back to idle; SAT in Tp unless there is more to send.
    fn complete(&mut self, now: Instant) {
        self.phase = Phase::Idle;
        self.idle_since = now;
        self.retries = 0;
    }

    pub(super) fn set_autostart(&mut self, on: bool) {
        self.autostart = on;
    }

    pub(super) fn autostart(&self) -> bool {
        self.autostart
    }

    fn complete_sat(&mut self, now: Instant, cnc: &mut Cnc, out: &mut Outbox) {
        self.complete(now);
        self.no_data = false;
        self.sat_done = true;
        if self.autostart && cnc.alarm().is_some() {
            // The host has seen the alarm in this SAT: the operator resets the CNC.
            self.cnc_reset(now, cnc, out);
        }
    }

    /// The host sent SYN outside the power-on handshake: it re-initialises the board.
    fn host_initialises(&mut self, out: &mut Outbox) {
        self.retries = 0;
        self.queue(Message::new(Command::Rdy));
        self.awaiting(Exchange::Rdy);
        self.set_link(BoardLinkState::Initialising, out);
    }

    fn on_packet(&mut self, now: Instant, raw: &[u8], cnc: &mut Cnc, out: &mut Outbox) {
        let ne = self.params.ne;
        let Some(g) = self.gtd() else {
            return;
        };
        if g.dc3 && !g.cancelled {
            // After DC3 the host finishes the packet under way and waits (§5.3 3): a second
            // packet is a stop request it did not accept (§4.6 1 (5), protocol notes 17).
            g.after_dc3 += 1;
            if g.after_dc3 > 1 {
                let detail = format!(
                    "packet {:02X}h is packet {} since DC3: only the packet under way may follow a DC3 (§5.3 3)",
                    raw.first().copied().unwrap_or(0),
                    g.after_dc3
                );
                self.line_error(
                    now,
                    Some(CncAlarm::Sr0856BufferOverflow),
                    AlarmCause::OverrunRetryOver,
                    detail,
                    cnc,
                    out,
                );
                return;
            }
        }
        let verdict = g.judge(raw);
        let naks = g.naks;
        match verdict {
            Verdict::Data(data) => {
                if self.store(now, data, cnc, out) {
                    self.check_flow(now, cnc, out);
                }
            }
            Verdict::End(data) => {
                if data.is_none_or(|d| self.store(now, d, cnc, out)) {
                    // Back to Protocol A (§5.2 2 b).
                    self.complete(now);
                }
            }
            Verdict::Ignore(why) => tracing::debug!(%why, "data packet ignored"),
            Verdict::Nak { from, why } => {
                out.event(BoardEvent::ProtocolError {
                    detail: format!("{why}: NAK {from:02X}h"),
                });
                if naks > ne {
                    let detail =
                        format!("retry count over: {naks} NAKs > Ne = {ne} (§4.6 2 (1), §5.3 2)");
                    self.abort_packets(
                        now,
                        Some((
                            CncAlarm::Sr0945RetryOver,
                            AlarmCause::ChecksumRetryOver,
                            detail,
                        )),
                        cnc,
                        out,
                    );
                } else {
                    // Any monitor packet ends the host's DC3 wait (§5.3 3): it resends at
                    // once, and the board stops it again if it must (`check_flow`).
                    if let Some(g) = self.gtd() {
                        g.dc3 = false;
                    }
                    send_monitor(Monitor::Retransmit(from), out);
                }
            }
        }
    }

    /// DC3 / DC1 during the packets (§5.3 3, 4).
    fn check_flow(&mut self, now: Instant, cnc: &Cnc, out: &mut Outbox) {
        let Some((n, _)) = self.packet_mode() else {
            return;
        };
        let dc3_below = 2 * packet::data_len(n);
        let dc1_at = self.dc1_level(n, cnc);
        let free = cnc.free();
        let Some(g) = self.gtd() else {
            return;
        };
        if g.cancelled || !g.started {
            return;
        }
        if !g.dc3 && free < dc3_below {
            g.dc3 = true;
            g.after_dc3 = 0;
            send_monitor(Monitor::Pause, out);
        } else if g.dc3 && free >= dc1_at {
            g.dc3 = false;
            send_monitor(Monitor::Resume, out);
            self.last_activity = now;
        }
    }

    /// CAN (§5.3 1): the host finishes its packet and sends the end packet, whose data is
    /// ignored. Raises `alarm` first, if any.
    fn abort_packets(
        &mut self,
        now: Instant,
        alarm: Option<(CncAlarm, AlarmCause, String)>,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        if let Some((alarm, cause, detail)) = alarm {
            self.raise(now, alarm, cause, detail, cnc, out);
        }
        if let Some(g) = self.gtd()
            && g.n > 0
            && !g.cancelled
        {
            g.cancelled = true;
            g.dc3 = false;
            send_monitor(Monitor::Stop, out);
            self.last_activity = now;
        }
    }

    fn start_init(&mut self, out: &mut Outbox) {
        self.rx.clear();
        self.discarding = false;
        self.retries = 0;
        self.queue(Message::new(Command::Syn));
        self.awaiting(Exchange::Syn);
        self.set_link(BoardLinkState::Initialising, out);
    }

    fn time_out(&mut self, now: Instant, cnc: &mut Cnc, out: &mut Outbox) {
        let Phase::Awaiting { exchange, .. } = &self.phase else {
            return;
        };
        let what = match exchange {
            Exchange::Syn | Exchange::Rdy => {
                out.event(BoardEvent::ProtocolError {
                    detail: format!(
                        "no answer to {} within To = {} s: SYN again",
                        exchange.command(),
                        self.params.to
                    ),
                });
                self.start_init(out);
                return;
            }
            Exchange::Gtd(g) if g.started => "the next data packet".to_string(),
            exchange => format!("an answer to {}", exchange.command()),
        };
        let detail = format!(
            "time-out: no {what} within To = {} s (§4.3 (3), §4.6 1 (6), §5.4 7)",
            self.params.to
        );
        self.line_error(
            now,
            Some(CncAlarm::Sr0944TimeOut),
            AlarmCause::NcAlarm,
            detail,
            cnc,
            out,
        );
    }

    pub(super) fn handle_line_error(
        &mut self,
        now: Instant,
        error: LineError,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        if matches!(self.phase, Phase::Off { .. }) {
            return;
        }
        let alarm = match error {
            LineError::Parity => None,
            _ => Some(CncAlarm::Sr0946FramingOverrun),
        };
        self.line_error(
            now,
            alarm,
            AlarmCause::NcAlarm,
            format!("{error} (§4.6 1)"),
            cnc,
            out,
        );
    }

    pub(super) fn handle_modem(
        &mut self,
        now: Instant,
        modem: ModemIn,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        self.cs = modem.cs;
        if modem.dr == self.dr {
            return;
        }
        self.dr = modem.dr;
        if !modem.dr {
            if self.initialised() {
                self.raise(
                    now,
                    CncAlarm::Sr0855DataSetReadyDown,
                    AlarmCause::NcAlarm,
                    "DR (the host's ER) went off (§3.2, §4.6 1 (4))".to_string(),
                    cnc,
                    out,
                );
            }
            self.rx.clear();
            self.discarding = false;
            self.queued = None;
            self.phase = Phase::Off { until: None };
            self.set_link(BoardLinkState::LineDown, out);
        } else if matches!(self.phase, Phase::Off { until: None }) {
            self.phase = Phase::Off {
                until: Some(now + self.first_request_delay),
            };
            self.set_link(BoardLinkState::Initialising, out);
        }
    }

    // ---- the CNC's side -------------------------------------------------------------------

    /// A CNC alarm: ALM at the next chance (§4.4.1), CAN during data packets (§5.3 1).
    pub(super) fn cnc_alarm(&mut self, now: Instant, cnc: &mut Cnc, out: &mut Outbox) {
        let was_reading = cnc.reading();
        cnc.raise_alarm(now, AlarmCause::NcAlarm);
        out.event(BoardEvent::CncAlarm);
        if was_reading {
            out.event(BoardEvent::ReadingStopped);
        }
        self.pending_alm = true;
        self.abort_packets(now, None, cnc, out);
    }

    /// A CNC reset: buffered data lost (§8.2); RST at the next chance; CAN during packets.
    pub(super) fn cnc_reset(&mut self, now: Instant, cnc: &mut Cnc, out: &mut Outbox) {
        let was_reading = cnc.reading();
        cnc.reset(now);
        out.event(BoardEvent::CncReset);
        if was_reading {
            out.event(BoardEvent::ReadingStopped);
        }
        self.pending_rst = true;
        self.pending_alm = false;
        self.abort_packets(now, None, cnc, out);
    }

    // ---- time -----------------------------------------------------------------------------

    pub(super) fn step(&mut self, now: Instant, cnc: &mut Cnc, out: &mut Outbox) {
        self.check_timers(now, cnc, out);
        self.check_flow(now, cnc, out);
        if self.autostart
            && self.initialised()
            && self.sat_done
            && !cnc.reading()
            && cnc.alarm().is_none()
            && !self.pending_rst
            && !self.pending_alm
            && cnc.start_reading(now)
        {
            out.event(BoardEvent::ReadingStarted);
        }
        self.decide(now, cnc);
        self.flush(now, out);
    }

    fn check_timers(&mut self, now: Instant, cnc: &mut Cnc, out: &mut Outbox) {
        match &self.phase {
            Phase::Off { until: Some(until) } if now >= *until && self.dr => self.start_init(out),
            Phase::WatWait { until } if now >= *until => self.phase = Phase::Idle,
            Phase::Awaiting { .. } if self.to_deadline().is_some_and(|d| now >= d) => {
                self.time_out(now, cnc, out);
            }
            _ => {}
        }
    }

    /// When idle: RST, ALM, GTD, or SAT once Tp has passed (§4.4.1).
    fn decide(&mut self, now: Instant, cnc: &Cnc) {
        if !matches!(self.phase, Phase::Idle)
            || self.queued.is_some()
            || !self.can_tx()
            || now < self.earliest_tx
        {
            return;
        }
        let (msg, exchange) = if self.pending_rst {
            self.pending_rst = false;
            (Message::new(Command::Rst), Exchange::Rst)
        } else if self.pending_alm {
            self.pending_alm = false;
            (Message::new(Command::Alm), Exchange::Alm)
        } else if self.gtd_allowed(cnc) {
            (
                Message::new(Command::Gtd),
                Exchange::Gtd(Box::new(GtdRx::new(self.packet_n))),
            )
        } else if now >= self.idle_since + secs(self.params.tp) {
            (
                Message::with_data(Command::Sat, self.status_data(cnc).to_bytes()),
                Exchange::Sat,
            )
        } else {
            return;
        };
        self.queue(msg);
        self.awaiting(exchange);
    }

    /// Sends the queued message once Tx has passed since the last reception (§4.3 (4)).
    fn flush(&mut self, now: Instant, out: &mut Outbox) {
        if !self.can_tx() || now < self.earliest_tx {
            return;
        }
        let Some(msg) = self.queued.take() else {
            return;
        };
        match self.framing.encode_to_vec(&msg) {
            Ok(bytes) => {
                out.send(bytes);
                out.event(BoardEvent::MessageSent(msg.command));
                self.last_sent = Some(msg);
                self.last_activity = now;
            }
            Err(e) => out.event(BoardEvent::ProtocolError {
                detail: format!("cannot encode {msg:?}: {e}"),
            }),
        }
    }

    pub(super) fn poll_timeout(&self, cnc: &Cnc) -> Option<Instant> {
        let mut best: Option<Instant> = None;
        let mut at = |t: Instant| best = Some(best.map_or(t, |b| b.min(t)));
        if self.queued.is_some() && self.can_tx() {
            at(self.earliest_tx);
        }
        match &self.phase {
            Phase::Off { until: Some(until) } if self.dr => at(*until),
            Phase::WatWait { until } => at(*until),
            Phase::Awaiting { exchange, .. } => {
                if let Some(d) = self.to_deadline() {
                    at(d);
                }
                if let Exchange::Gtd(g) = exchange
                    && g.dc3
                    && !g.cancelled
                    && let Some(t) = cnc.when_free_at_least(self.dc1_level(g.n, cnc))
                {
                    at(t);
                }
            }
            Phase::Idle if self.can_tx() && self.queued.is_none() => {
                if self.pending_rst || self.pending_alm || self.gtd_allowed(cnc) {
                    at(self.earliest_tx);
                } else {
                    at((self.idle_since + secs(self.params.tp)).max(self.earliest_tx));
                    if self.initialised()
                        && !self.no_data
                        && let Some(t) = cnc.when_free_at_least(usize::from(self.params.nb))
                    {
                        at(t.max(self.earliest_tx));
                    }
                }
            }
            _ => {}
        }
        best
    }
}

#[cfg(test)]
mod tests;
