//! Protocol B and Expansion Protocol B from the remote buffer's side (§6, §7).
//!
//! There are no messages: the board steers the host with single control codes (§6.2) and
//! everything the host sends is the data part (§8.1). Codes go out in the configured code:
//! DC3, NAK and SYN with the parity bit in ISO (93h, 95h, 96h), without it in ASCII; DC1, DC2
//! and DC4 are the same in both. Codes from the host are recognised with or without bit 7.
//!
//! # Download (§6.1.1 1, §6.1.2 2, §6.3)
//!
//! - A read request opens when the CNC reads (cycle start, or autostart) and the buffer has
//!   at least [`DC1_FREE`] (4096) bytes free: DC1. Every byte received then goes into the
//!   buffer.
//! - Free space at or below [`dc3_free`] (512 in Protocol B, 2560 in Expansion B): DC3. Bytes
//!   received after the DC3 was handed to the line are counted; more than the overrun
//!   allowance ([`overrun_allowance`]: 512; 2560 in Expansion B, protocol notes 12), or more
//!   than the buffer holds, is SR0856.
//! - Free space back at 4096 or more: DC1 (the continuation, §6.1.1 1 (6)).
//! - Once the program's EOR is in the buffer the board asks for nothing more in this read:
//!   the host cannot tell a flow-control DC1 from a new read request (protocol notes 13), so
//!   a DC1 then would bring the next program's bytes behind the EOR, where the CNC ignores
//!   them (§8.2).
//! - When the CNC has read the EOR (or stops reading) the read ends with DC3 (§6.1.1 1 (7));
//!   data arriving after that is ignored (§8.2). The next read starts with DC1 again.
//!
//! # CNC alarm and reset (§6.1.2, §6.4)
//!
//! With notification on (parameter 5003#3 = 1, [`BoardConfig::notify_alarm_reset`]): NAK
//! (alarm) or SYN (reset), alone while idle, after DC3 while a read is open, after DC4 while
//! punching. With notification off: DC3 (DC4 while punching, since the host would take a DC3
//! for punched data), then ER off for [`BoardConfig::er_off_time`] (§6.4 (1)): the host sees
//! DR off. The manual says ER stays off until the CNC opens the interface again; a fixed time
//! keeps an unattended simulator going. After ER is back on the board sends nothing for
//! [`ER_ON_SETTLE`], so that the host has seen DR on before the next DC1. A reset loses the
//! buffered data (§8.2).
//!
//! With autostart, a CNC in alarm resets itself `first_request_delay` after the alarm (or
//! after DR came back), with the reset's own notice, and reads again.
//!
//! # Punch-out (§6.1.1 2, §6.1.2 2)
//!
//! [`BoardCommand::Punch`](super::BoardCommand::Punch) bytes go out exactly as given (the
//! tape is already encoded), framed as DC2 … DC4, in pieces of [`PUNCH_PIECE`] bytes so that a
//! stop takes effect within a piece. An open read is stopped with DC3 first (the host must not
//! send program data meanwhile, and no DC1/DC3 can travel inside the punched data); it resumes
//! with DC1 after the DC4. The host stops the punch-out with DC3 and resumes it with DC1 or DC2
//! (protocol notes 11); CS off holds every transmission, CS on continues. While a punch-out
//! runs, and until the board's next DC1 after it, DC1 / DC2 / DC3 from the host are flow
//! control, not data (a late DC3 must not land in the program). A CNC reset or alarm ends the
//! punch-out with DC4 and the notice; DR off ends it silently.
//!
//! # Line
//!
//! DR off (the host's ER; and CD in Protocol B, an RS-232-C interface) while the CNC reads or
//! punches: SR0855 (§11), the read and punch-out end, queued codes are dropped. A framing or
//! overrun error on a received character then: SR0946. A parity error loses the character
//! and is reported as a protocol error. Nothing is sent while ER is off or settling.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use crate::engine::{LineError, ModemIn, ModemOut};
use crate::fanuc::CodeSystem;
use crate::fanuc::alarm::CncAlarm;
use crate::fanuc::code::{DC1, DC2, DC3};
use crate::fanuc::protocol_b::{OVERRUN_B, OVERRUN_EXPANSION_B_ALARM};
use crate::fanuc::sat::{AlarmCause, StatusData};
use crate::sim::cnc::{Cnc, Push};

use super::{BoardConfig, BoardEvent, BoardLinkState, ControlCode, FlowCounters, Outbox};

/// Free space at which the board asks for data with DC1 (§6.3: "vacant space ≥ 4096").
pub const DC1_FREE: usize = 4096;
/// Free space at or below which the board stops the host with DC3 in Protocol B (§6.3).
pub const DC3_FREE_B: usize = 512;
/// The same in Expansion Protocol B (§6.3).
pub const DC3_FREE_EXPANSION_B: usize = 2560;
/// Punched bytes handed to the line at once: a host's DC3 or CS off takes effect after at
/// most this many more (plus the UART FIFO).
pub const PUNCH_PIECE: usize = 32;

/// The free space at or below which the board sends DC3.
pub const fn dc3_free(expansion: bool) -> usize {
    if expansion {
        DC3_FREE_EXPANSION_B
    } else {
        DC3_FREE_B
    }
}

/// Characters after a DC3 beyond which the board raises SR0856 (the manual's sizes are
/// the host engine's: [`OVERRUN_B`], [`OVERRUN_EXPANSION_B_ALARM`]).
pub const fn overrun_allowance(expansion: bool) -> usize {
    if expansion {
        OVERRUN_EXPANSION_B_ALARM
    } else {
        OVERRUN_B
    }
}

/// The board's ER output (§6.4 (1)).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Er {
    On,
    /// Off once the codes queued before it (the DC3 or DC4) have been handed to the line.
    OffAfterSend,
    Off {
        until: Instant,
    },
    /// On again; nothing is sent before `until`, so that a host that polls its modem lines
    /// has seen DR on before the next DC1.
    Settling {
        until: Instant,
    },
}

/// How long the board waits after turning ER back on before it sends anything. A host reads
/// DR by polling (cellgate every 50 ms) and ignores what arrives while it sees DR off.
pub const ER_ON_SETTLE: Duration = Duration::from_millis(200);

/// A punch-out in progress.
#[derive(Debug)]
struct Punch {
    data: Vec<u8>,
    sent: usize,
    /// DC2 has been handed to the line.
    started: bool,
    /// The host stopped it with DC3.
    held: bool,
    /// All data handed out; DC4 queued.
    finishing: bool,
}

/// The device side of Protocol B / Expansion B.
#[derive(Debug)]
pub(super) struct ProtocolB {
    code: CodeSystem,
    expansion: bool,
    notify: bool,
    autostart: bool,
    er_off_time: Duration,
    reset_delay: Duration,
    link: BoardLinkState,
    /// DR (and CD in Protocol B) on: the host is there.
    dr: bool,
    cs: bool,
    er: Er,
    /// Control codes waiting for the line, in order.
    tx: VecDeque<ControlCode>,
    /// A read request is open: DC1 went since the CNC started reading, and the read has not
    /// ended.
    read_open: bool,
    /// The host is stopped in the open read (DC3 queued or sent).
    stopped: bool,
    /// Bytes received since the flow-control DC3 was handed to the line; `None` while the
    /// host may send.
    after_dc3: Option<usize>,
    punch: Option<Punch>,
    punch_queue: VecDeque<Vec<u8>>,
    /// A punch-out ended and the host has not been asked for data since: DC1 / DC2 / DC3
    /// from it are still punch flow control.
    punch_tail: bool,
    /// Since when the CNC has been in alarm with the line up (autostart resets it later).
    alarm_since: Option<Instant>,
    /// Autostart after a reset: when the operator presses cycle start again. Until then the
    /// CNC does not read, so what the host still had on the line when the reset came is
    /// ignored (§8.2) instead of starting the next program.
    cycle_start_at: Option<Instant>,
    counters: FlowCounters,
}

impl ProtocolB {
    pub(super) fn new(config: &BoardConfig, _now: Instant) -> Self {
        ProtocolB {
            code: config.framing.code,
            expansion: config.protocol == crate::fanuc::Protocol::ExpansionB,
            notify: config.notify_alarm_reset,
            autostart: config.autostart,
            er_off_time: config.er_off_time,
            reset_delay: config.first_request_delay,
            link: BoardLinkState::Ready,
            dr: true,
            cs: true,
            er: Er::On,
            tx: VecDeque::new(),
            read_open: false,
            stopped: false,
            after_dc3: None,
            punch: None,
            punch_queue: VecDeque::new(),
            punch_tail: false,
            alarm_since: None,
            cycle_start_at: None,
            counters: FlowCounters::default(),
        }
    }

    pub(super) fn link_state(&self) -> BoardLinkState {
        self.link
    }

    pub(super) fn counters(&self) -> FlowCounters {
        self.counters
    }

    pub(super) fn modem_out(&self) -> ModemOut {
        ModemOut {
            er: !matches!(self.er, Er::Off { .. }),
            rs: true,
        }
    }

    /// What a SAT would say, for the snapshot: Protocol B has no SAT.
    pub(super) fn status_data(&self, cnc: &Cnc) -> StatusData {
        StatusData {
            status: Some(cnc.status()),
            alarm_cause: cnc.alarm(),
            buffered: Some(u16::try_from(cnc.buffered()).unwrap_or(u16::MAX)),
            ..StatusData::default()
        }
    }

    fn set_link(&mut self, link: BoardLinkState, out: &mut Outbox) {
        if self.link != link {
            self.link = link;
            out.event(BoardEvent::LinkState(link));
        }
    }

    fn punching(&self) -> bool {
        self.punch.as_ref().is_some_and(|p| p.started)
    }

    /// The EOR of the program being read is in the buffer: this read needs no more data.
    fn eor_buffered(cnc: &Cnc) -> bool {
        cnc.when_program_ends().is_some()
    }

    /// The board may open or continue a read or start a punch-out.
    fn line_usable(&self) -> bool {
        self.dr && self.er == Er::On
    }

    // ---- input ----------------------------------------------------------------------------

    pub(super) fn handle_input(
        &mut self,
        now: Instant,
        bytes: &[u8],
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        if !self.dr {
            // DR off: nothing on the line is trusted.
            return;
        }
        if self.punch.is_some() || self.punch_tail {
            let mut data = Vec::new();
            for &b in bytes {
                match CodeSystem::strip(b) {
                    DC3 => self.host_flow(ControlCode::Dc3, out),
                    DC1 => self.host_flow(ControlCode::Dc1, out),
                    DC2 => self.host_flow(ControlCode::Dc2, out),
                    _ => data.push(b),
                }
            }
            self.receive(now, &data, cnc, out);
        } else {
            self.receive(now, bytes, cnc, out);
        }
    }

    /// DC3 / DC1 / DC2 from the host during a punch-out (§6.1.1 2 (3), protocol notes 11).
    fn host_flow(&mut self, code: ControlCode, out: &mut Outbox) {
        out.event(BoardEvent::ControlReceived(code));
        if let Some(p) = self.punch.as_mut() {
            p.held = code == ControlCode::Dc3;
        }
    }

    /// The data part (§8.1): into the buffer while the CNC reads; counted after a DC3.
    fn receive(&mut self, now: Instant, data: &[u8], cnc: &mut Cnc, out: &mut Outbox) {
        if data.is_empty() {
            return;
        }
        if !cnc.reading() {
            // After EOR, a reset or an alarm: ignored (§8.2), and no overrun either.
            out.event(BoardEvent::DataIgnored { bytes: data.len() });
            return;
        }
        let mut take = data.len();
        let mut overrun = None;
        if let Some(n) = self.after_dc3.as_mut() {
            let allowance = overrun_allowance(self.expansion);
            let before = *n;
            *n = n.saturating_add(data.len());
            self.counters.max_overrun = self.counters.max_overrun.max(*n);
            if *n > allowance {
                take = allowance.saturating_sub(before);
                overrun = Some(*n);
            }
        }
        let mut overflow = None;
        if take > 0 {
            let part = data.get(..take).unwrap_or(data);
            match cnc.push_data(now, part) {
                Push::Stored(bytes) => out.event(BoardEvent::DataReceived {
                    bytes,
                    buffered: cnc.buffered(),
                }),
                Push::Ignored(bytes) => out.event(BoardEvent::DataIgnored { bytes }),
                Push::Overflow { len, free } => {
                    // What fits is kept; the rest is lost with the alarm.
                    if free > 0
                        && let Some(fits) = part.get(..free)
                        && let Push::Stored(bytes) = cnc.push_data(now, fits)
                    {
                        out.event(BoardEvent::DataReceived {
                            bytes,
                            buffered: cnc.buffered(),
                        });
                    }
                    overflow = Some((len, free));
                }
            }
        }
        if let Some(n) = overrun {
            let detail = format!(
                "{n} characters received after DC3, more than the {} the board allows (§6.3, §11)",
                overrun_allowance(self.expansion)
            );
            self.counters.overruns += 1;
            self.raise(now, CncAlarm::Sr0856BufferOverflow, detail, cnc, out);
        } else if let Some((len, free)) = overflow {
            let detail = format!(
                "buffer full: {len} bytes of NC data with {free} bytes free; the host did not stop on DC3 (§6.3, §11)"
            );
            self.counters.overruns += 1;
            self.raise(now, CncAlarm::Sr0856BufferOverflow, detail, cnc, out);
        }
    }

    pub(super) fn handle_line_error(
        &mut self,
        now: Instant,
        error: LineError,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        if !self.dr {
            return;
        }
        let in_use = cnc.reading() || self.punch.is_some();
        match error {
            LineError::Parity => out.event(BoardEvent::ProtocolError {
                detail: format!("{error}: the character is lost (Protocol B has no retry)"),
            }),
            _ if !in_use => out.event(BoardEvent::ProtocolError {
                detail: format!("{error} while the interface is not in use: ignored"),
            }),
            _ => self.raise(
                now,
                CncAlarm::Sr0946FramingOverrun,
                format!("{error} (§11)"),
                cnc,
                out,
            ),
        }
    }

    pub(super) fn handle_modem(
        &mut self,
        now: Instant,
        modem: ModemIn,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        self.cs = modem.cs;
        // CD counts on the RS-232-C interface only (§11 SR0855); Expansion B is RS-422.
        let up = modem.dr && (self.expansion || modem.cd);
        if up == self.dr {
            return;
        }
        self.dr = up;
        if !up {
            let in_use = cnc.reading() || self.read_open || self.punch.is_some();
            self.tx.clear();
            if self.er == Er::OffAfterSend {
                self.er_off(now, out);
            }
            self.end_read();
            self.drop_punches(out);
            if in_use {
                self.raise(
                    now,
                    CncAlarm::Sr0855DataSetReadyDown,
                    "DR (the host's ER) went off (§11)".to_string(),
                    cnc,
                    out,
                );
            }
            self.set_link(BoardLinkState::LineDown, out);
        } else {
            if cnc.alarm().is_some() {
                self.alarm_since = Some(now);
            }
            self.set_link(BoardLinkState::Ready, out);
        }
    }

    // ---- the CNC's side -------------------------------------------------------------------

    /// An SR alarm of §11 raised by the board: the CNC stops; the host hears of it as of any
    /// CNC alarm (NAK, or DC3 and ER off).
    fn raise(
        &mut self,
        now: Instant,
        alarm: CncAlarm,
        detail: String,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        tracing::warn!(alarm = alarm.number(), %detail, "simulated board alarm");
        let cause = match alarm {
            CncAlarm::Sr0856BufferOverflow => AlarmCause::OverrunRetryOver,
            _ => AlarmCause::NcAlarm,
        };
        out.event(BoardEvent::Alarm {
            alarm,
            cause,
            detail,
        });
        let was_reading = cnc.reading();
        cnc.raise_alarm(now, cause);
        if was_reading {
            out.event(BoardEvent::ReadingStopped);
        }
        self.alarm_since = Some(now);
        if self.dr {
            self.notice(false, out);
        }
    }

    /// [`BoardCommand::RaiseAlarm`](super::BoardCommand::RaiseAlarm).
    pub(super) fn cnc_alarm(&mut self, now: Instant, cnc: &mut Cnc, out: &mut Outbox) {
        let was_reading = cnc.reading();
        cnc.raise_alarm(now, AlarmCause::NcAlarm);
        out.event(BoardEvent::CncAlarm);
        if was_reading {
            out.event(BoardEvent::ReadingStopped);
        }
        self.alarm_since = Some(now);
        if self.dr {
            self.notice(false, out);
        }
    }

    /// [`BoardCommand::Reset`](super::BoardCommand::Reset): buffered data lost (§8.2).
    pub(super) fn cnc_reset(&mut self, now: Instant, cnc: &mut Cnc, out: &mut Outbox) {
        let was_reading = cnc.reading();
        cnc.reset(now);
        out.event(BoardEvent::CncReset);
        if was_reading {
            out.event(BoardEvent::ReadingStopped);
        }
        self.alarm_since = None;
        self.cycle_start_at = Some(now + self.reset_delay);
        if self.dr {
            self.notice(true, out);
        }
    }

    /// Tells the host of a CNC reset or alarm (§6.1.2, §6.4) and ends the read and any
    /// punch-out.
    fn notice(&mut self, reset: bool, out: &mut Outbox) {
        // Nothing asks the host for data or starts a punch-out any more.
        self.tx
            .retain(|c| !matches!(c, ControlCode::Dc1 | ControlCode::Dc2));
        let punching = self.punching();
        self.drop_punches(out);
        let first = if punching {
            Some(ControlCode::Dc4)
        } else if self.read_open {
            Some(ControlCode::Dc3)
        } else {
            None
        };
        self.end_read();
        if self.notify {
            self.tx.extend(first);
            self.tx.push_back(if reset {
                ControlCode::Syn
            } else {
                ControlCode::Nak
            });
        } else if self.er == Er::On {
            self.tx.push_back(first.unwrap_or(ControlCode::Dc3));
            self.er = Er::OffAfterSend;
        }
        // Otherwise ER is (about to go, or just came back from) off for an earlier notice:
        // the host has seen the interface close already.
    }

    fn end_read(&mut self) {
        self.read_open = false;
        self.stopped = false;
        self.after_dc3 = None;
    }

    /// Ends the current punch-out (if any) and forgets the queued ones.
    fn drop_punches(&mut self, out: &mut Outbox) {
        if let Some(p) = self.punch.take() {
            self.punch_tail = p.started;
            out.event(BoardEvent::PunchInterrupted {
                sent: p.sent,
                bytes: p.data.len(),
            });
        }
        for p in self.punch_queue.drain(..) {
            out.event(BoardEvent::PunchInterrupted {
                sent: 0,
                bytes: p.len(),
            });
        }
    }

    fn er_off(&mut self, now: Instant, out: &mut Outbox) {
        self.er = Er::Off {
            until: now + self.er_off_time,
        };
        out.event(BoardEvent::ErSignal { on: false });
    }

    /// [`BoardCommand::Punch`](super::BoardCommand::Punch).
    pub(super) fn punch(&mut self, data: Vec<u8>, cnc: &Cnc, out: &mut Outbox) {
        let refused = if !self.dr {
            Some("DR is off")
        } else if cnc.alarm().is_some() {
            Some("the CNC is in alarm (reset it first)")
        } else {
            None
        };
        match refused {
            Some(why) => out.event(BoardEvent::ProtocolError {
                detail: format!("punch-out of {} bytes refused: {why}", data.len()),
            }),
            None => self.punch_queue.push_back(data),
        }
    }

    // ---- time -----------------------------------------------------------------------------

    pub(super) fn step(&mut self, now: Instant, cnc: &mut Cnc, out: &mut Outbox) {
        if let Er::Off { until } = self.er
            && now >= until
        {
            self.er = Er::Settling {
                until: now + ER_ON_SETTLE,
            };
            out.event(BoardEvent::ErSignal { on: true });
        }
        if let Er::Settling { until } = self.er
            && now >= until
        {
            self.er = Er::On;
        }
        if self.autostart
            && cnc.alarm().is_some()
            && self.line_usable()
            && self
                .alarm_since
                .is_some_and(|t| now >= t + self.reset_delay)
        {
            // The operator resets the CNC: the reset's own notice follows the alarm's.
            self.cnc_reset(now, cnc, out);
        }
        if self.read_open && !cnc.reading() && !self.punching() {
            // The CNC read the EOR or stopped: the read ends (§6.1.1 1 (7)).
            self.end_read();
            self.queue_code(ControlCode::Dc3);
        }
        if self.autostart
            && self.line_usable()
            && !cnc.reading()
            && cnc.alarm().is_none()
            && self.cycle_start_at.is_none_or(|t| now >= t)
            && cnc.start_reading(now)
        {
            self.cycle_start_at = None;
            out.event(BoardEvent::ReadingStarted);
        }
        self.check_flow(cnc);
        self.start_punch();
    }

    pub(super) fn set_autostart(&mut self, on: bool) {
        self.autostart = on;
    }

    pub(super) fn autostart(&self) -> bool {
        self.autostart
    }

    /// DC1 / DC3 of the download (§6.3).
    fn check_flow(&mut self, cnc: &Cnc) {
        if !self.line_usable() || self.punch.is_some() || !cnc.reading() {
            return;
        }
        let free = cnc.free();
        if !self.read_open {
            if free >= DC1_FREE && !Self::eor_buffered(cnc) {
                self.read_open = true;
                self.stopped = false;
                self.queue_code(ControlCode::Dc1);
            }
        } else if !self.stopped {
            if free <= dc3_free(self.expansion) {
                self.stopped = true;
                self.queue_code(ControlCode::Dc3);
            }
        } else if free >= DC1_FREE && !Self::eor_buffered(cnc) {
            self.stopped = false;
            self.queue_code(ControlCode::Dc1);
        }
    }

    fn start_punch(&mut self) {
        if self.punch.is_some() || !self.line_usable() {
            return;
        }
        let Some(data) = self.punch_queue.pop_front() else {
            return;
        };
        if self.read_open && !self.stopped {
            // No program data while the board punches, and no DC3 inside the punched data.
            self.stopped = true;
            self.queue_code(ControlCode::Dc3);
        }
        self.queue_code(ControlCode::Dc2);
        self.punch = Some(Punch {
            data,
            sent: 0,
            started: false,
            held: false,
            finishing: false,
        });
    }

    fn queue_code(&mut self, code: ControlCode) {
        self.tx.push_back(code);
    }

    /// The next bytes for the line: queued control codes first, then a piece of the
    /// punch-out. Nothing while CS or DR is off.
    pub(super) fn poll_transmit(&mut self, now: Instant, out: &mut Outbox) -> Option<Vec<u8>> {
        if !self.dr || !self.cs || matches!(self.er, Er::Off { .. } | Er::Settling { .. }) {
            return None;
        }
        if !self.tx.is_empty() {
            let mut bytes = Vec::with_capacity(self.tx.len());
            while let Some(code) = self.tx.pop_front() {
                bytes.push(self.code.control(code.byte()));
                self.handed(code, out);
            }
            if self.er == Er::OffAfterSend {
                self.er_off(now, out);
            }
            return Some(bytes);
        }
        if self.er != Er::On {
            return None;
        }
        let p = self.punch.as_mut()?;
        if !p.started || p.held || p.finishing {
            return None;
        }
        let end = p.sent.saturating_add(PUNCH_PIECE).min(p.data.len());
        let piece = p
            .data
            .get(p.sent..end)
            .map(<[u8]>::to_vec)
            .unwrap_or_default();
        p.sent = end;
        self.counters.punched += piece.len() as u64;
        if p.sent >= p.data.len() {
            p.finishing = true;
            self.tx.push_back(ControlCode::Dc4);
        }
        if piece.is_empty() {
            // An empty punch-out: DC2 DC4.
            return self.poll_transmit(now, out);
        }
        Some(piece)
    }

    /// A control code went to the line.
    fn handed(&mut self, code: ControlCode, out: &mut Outbox) {
        out.event(BoardEvent::ControlSent(code));
        match code {
            ControlCode::Dc1 => {
                self.counters.dc1_sent += 1;
                self.after_dc3 = None;
                self.punch_tail = false;
            }
            ControlCode::Dc3 => {
                self.counters.dc3_sent += 1;
                if self.read_open && self.stopped {
                    self.after_dc3 = Some(0);
                }
            }
            ControlCode::Dc2 => {
                if let Some(p) = self.punch.as_mut() {
                    p.started = true;
                    out.event(BoardEvent::PunchStarted {
                        bytes: p.data.len(),
                    });
                }
            }
            ControlCode::Dc4 => {
                if self.punch.as_ref().is_some_and(|p| p.finishing)
                    && let Some(p) = self.punch.take()
                {
                    self.punch_tail = true;
                    out.event(BoardEvent::PunchFinished {
                        bytes: p.data.len(),
                    });
                }
            }
            ControlCode::Nak | ControlCode::Syn => {}
        }
    }

    pub(super) fn poll_timeout(&self, cnc: &Cnc) -> Option<Instant> {
        let mut best: Option<Instant> = None;
        let mut at = |t: Instant| best = Some(best.map_or(t, |b| b.min(t)));
        if let Er::Off { until } | Er::Settling { until } = self.er {
            at(until);
        }
        if self.autostart
            && cnc.alarm().is_some()
            && self.line_usable()
            && let Some(t) = self.alarm_since
        {
            at(t + self.reset_delay);
        }
        if self.autostart
            && !cnc.reading()
            && let Some(t) = self.cycle_start_at
        {
            at(t);
        }
        // The CNC's reading makes room: DC1 once 4096 bytes are free.
        if self.line_usable()
            && self.punch.is_none()
            && (!self.read_open || self.stopped)
            && !Self::eor_buffered(cnc)
            && let Some(t) = cnc.when_free_at_least(DC1_FREE)
        {
            at(t);
        }
        best
    }
}

#[cfg(test)]
mod tests;
