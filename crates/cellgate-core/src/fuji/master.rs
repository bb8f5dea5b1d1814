//! The host ("personal computer") side of an FFU120B link, sans-IO (§5-3 to §5-5; FFU120B
//! notes 2, 5, 6, 8).
//!
//! [`Master`] implements [`Engine`]: requests ([`MasterCommand`]), received bytes, line
//! errors, modem lines and the time go in; texts to send, [`MasterEvent`]s and the next
//! deadline come out.
//!
//! Command-set modes 1–3:
//! - one request at a time on the line; requests wait in a bounded queue
//!   ([`MasterSettings::queue_limit`]) and are sent in the order they came;
//! - the reply time-out starts when the request is on the line (its bytes × the character
//!   time) and allows for the line time of the longest reply the request can get; a silent
//!   station is a time-out, not an error code (FFU120B notes 5), and so is a text the module could not
//!   read, since it answers receive errors with silence (FFU120B notes 6);
//! - a time-out or a corrupted reply (BCC error, text too long, unreadable text) is retried up
//!   to [`MasterSettings::retries`] times; STA errors and malformed replies are not;
//! - after [`MasterSettings::down_after`] time-outs in a row a station is marked down: its
//!   requests then fail at once with [`MasterError::StationDown`], except one every
//!   [`MasterSettings::probe_interval`], which goes out as a single-attempt probe. So a dead
//!   station costs the line one reply time-out per probe interval, and the others keep their
//!   pace. Any reply marks it up again;
//! - every request ends with exactly one [`MasterEvent::Done`] carrying the caller's id;
//! - mode 1: the PLC may send a transfer (`90 00 00 MSGNO BYTEN data`) at any time; it is
//!   reported as [`MasterEvent::Transfer`] and not answered (FFU120B notes 8). Transfers to the PLC
//!   work in mode 1 only (§5-4 iii).
//!
//! Non-procedure modes 4–5 (§5-5): no command set; [`MasterCommand::Send`] puts a message on
//! the line (variable length: framed with start code, BCC and end code; fixed length: exactly
//! N bytes of data alone, as 2N hex characters with code transposition on, §4-3 items 14–15)
//! and received messages come out as [`MasterEvent::Received`]. What
//! differs between the two modes is the line (§1-3, §3-8): mode 4 is RS-232C 1:1, so the host
//! honours CS (the module's RTS/CTS control, §4-3 item 9); mode 5 is RS-485, a line the
//! module shares with other devices and with no modem lines, so the host ignores CS and does
//! not start a message while the module is sending (it waits two character times of silence).
//!
//! Counters per station and per receive-error kind are kept ([`Master::counters`]).

use std::collections::{BTreeMap, VecDeque};
use std::fmt;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use super::command::{
    CMND_TRANSFER, CommandError, CommandText, MAX_READ, Reply, ReplyError, Request, StaError,
    to_bcd, unsolicited_transfer,
};
use super::frame::{
    Decoded, FrameDecoder, FrameProblem, FrameSettings, MAX_NON_PROCEDURE_TEXT, ReceiveCounts,
    ReceiveError, ReceiveErrorKind,
};
use crate::codes::BusCode;
use crate::engine::{Engine, LineError, LineSettings, ModemIn};
use crate::pb;

/// The caller's name for a request; it comes back in [`MasterEvent::Done`].
pub type RequestId = u64;

/// Longest time setting: deadlines are `now` plus settings, and must not overflow.
pub const MAX_DURATION: Duration = Duration::from_secs(24 * 3600);

/// Most stations on one RS-485 line (§2-2 (1)).
pub const MAX_STATIONS: usize = 31;

/// The operation mode set on the module's MODE dial (§1-3, §3-8, §4-2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(try_from = "u8", into = "u8")]
pub enum OperationMode {
    /// Command set, RS-232C, 1:1.
    One,
    /// Command set, RS-232C to the first module and RS-485 1:N beyond it.
    Two,
    /// Command set, RS-485 1:N.
    Three,
    /// Non-procedure, RS-232C, 1:1.
    Four,
    /// Non-procedure, RS-485.
    Five,
}

impl OperationMode {
    /// The mode the MODE dial shows as `n`; `None` outside 1–5.
    pub fn from_dial(n: u8) -> Option<OperationMode> {
        Some(match n {
            1 => OperationMode::One,
            2 => OperationMode::Two,
            3 => OperationMode::Three,
            4 => OperationMode::Four,
            5 => OperationMode::Five,
            _ => return None,
        })
    }

    /// The number on the MODE dial: 1–5.
    pub fn dial(self) -> u8 {
        match self {
            OperationMode::One => 1,
            OperationMode::Two => 2,
            OperationMode::Three => 3,
            OperationMode::Four => 4,
            OperationMode::Five => 5,
        }
    }

    /// Modes 1–3 speak the command set (§5-3); 4–5 are non-procedure (§5-5).
    pub fn is_command_set(self) -> bool {
        matches!(
            self,
            OperationMode::One | OperationMode::Two | OperationMode::Three
        )
    }

    /// Modes 2 and 3 address stations over RS-485 and set MODE's MSB in replies (§5-4).
    pub fn is_multi_drop(self) -> bool {
        matches!(self, OperationMode::Two | OperationMode::Three)
    }
}

impl TryFrom<u8> for OperationMode {
    type Error = String;
    fn try_from(n: u8) -> Result<Self, String> {
        OperationMode::from_dial(n)
            .ok_or_else(|| format!("mode {n}: the MODE dial takes 1 to 5 (FFU120B §4-2)"))
    }
}

impl From<OperationMode> for u8 {
    fn from(m: OperationMode) -> u8 {
        m.dial()
    }
}

impl fmt::Display for OperationMode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "mode {}", self.dial())
    }
}

/// Settings of one host link to FFU120B modules.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MasterSettings {
    /// The operation mode set on the modules' MODE dial.
    pub mode: OperationMode,
    /// The framing items of the modules' initial file (§4-3).
    pub frame: FrameSettings,
    /// Character framing, for the line time of texts.
    pub line: LineSettings,
    /// How long the module may take to start its reply once the request is on the line. The
    /// line time of the longest reply the request can get is added.
    pub reply_timeout: Duration,
    /// Times a request is sent again after a time-out or a corrupted reply.
    pub retries: u32,
    /// Time-outs in a row after which a station is marked down.
    pub down_after: u32,
    /// How often a station marked down is probed (with a request for it, if any waits).
    pub probe_interval: Duration,
    /// Most requests waiting; past it a request is refused with [`MasterError::QueueFull`].
    pub queue_limit: usize,
    /// Quiet time after a reply before the next request (RS-485 line turnaround).
    pub turnaround: Duration,
    /// Modes 4–5: fixed message length N (1–216, §4-3 item 15), or `None` for variable length
    /// with end code.
    pub fixed_length: Option<usize>,
    /// RS-232C modes (1, 4; and 2 toward its first module): send only while CS is on.
    pub honour_cs: bool,
}

impl MasterSettings {
    /// Default of `reply_timeout`: 2 s.
    pub const DEFAULT_REPLY_TIMEOUT: Duration = Duration::from_millis(2000);

    /// Settings for `mode`: the module's initial framing, the default line, a 2 s reply time-out,
    /// 2 retries, down after 3 time-outs, a probe every 10 s, at most 64 requests waiting.
    pub fn new(mode: OperationMode) -> Self {
        MasterSettings {
            mode,
            frame: FrameSettings::default(),
            line: LineSettings::default(),
            reply_timeout: Self::DEFAULT_REPLY_TIMEOUT,
            retries: 2,
            down_after: 3,
            probe_interval: Duration::from_secs(10),
            queue_limit: 64,
            turnaround: Duration::ZERO,
            fixed_length: None,
            honour_cs: true,
        }
    }

    /// Every problem of these settings.
    pub fn validate(&self) -> Vec<MasterProblem> {
        let mut p: Vec<MasterProblem> = self
            .frame
            .validate_with_line(&self.line)
            .into_iter()
            .map(MasterProblem::Frame)
            .collect();
        if self.reply_timeout.is_zero() {
            p.push(MasterProblem::ZeroReplyTimeout);
        }
        let bounds = [
            ("reply_timeout", self.reply_timeout),
            ("probe_interval", self.probe_interval),
            ("turnaround", self.turnaround),
        ];
        for (name, value) in bounds {
            if value > MAX_DURATION {
                p.push(MasterProblem::TooLong { name, value });
            }
        }
        if self.down_after == 0 {
            p.push(MasterProblem::ZeroDownAfter);
        }
        if self.queue_limit == 0 {
            p.push(MasterProblem::ZeroQueue);
        }
        if self.probe_interval < self.reply_timeout {
            p.push(MasterProblem::ProbeInterval {
                probe: self.probe_interval,
                timeout: self.reply_timeout,
            });
        }
        match self.fixed_length {
            Some(n) if self.mode.is_command_set() => {
                p.push(MasterProblem::FixedLengthInCommandSet { n, mode: self.mode });
            }
            Some(n) if !(1..=MAX_NON_PROCEDURE_TEXT).contains(&n) => {
                p.push(MasterProblem::FixedLength { n });
            }
            _ => {}
        }
        p
    }
}

/// One problem of [`MasterSettings`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum MasterProblem {
    /// A problem of the framing items (§4-7).
    #[error("{0}")]
    Frame(FrameProblem),
    /// `reply_timeout` is zero.
    #[error("reply_timeout must be above zero")]
    ZeroReplyTimeout,
    /// `down_after` is zero.
    #[error("down_after must be at least 1 time-out")]
    ZeroDownAfter,
    /// `queue_limit` is zero.
    #[error("queue_limit must be at least 1")]
    ZeroQueue,
    /// `probe_interval` is shorter than `reply_timeout`.
    #[error(
        "probe_interval {probe:?} is shorter than the reply time-out {timeout:?}: a dead station would cost every other request a time-out"
    )]
    ProbeInterval {
        /// The `probe_interval` given.
        probe: Duration,
        /// The `reply_timeout` given.
        timeout: Duration,
    },
    /// A time setting longer than [`MAX_DURATION`].
    #[error("{name} = {value:?} is longer than a day")]
    TooLong {
        /// The setting's name.
        name: &'static str,
        /// The value given.
        value: Duration,
    },
    /// A fixed message length in a command-set mode (1–3).
    #[error(
        "fixed length {n} in {mode}: fixed length is a non-procedure setting of modes 4 and 5 (FFU120B §4-3 item 15)"
    )]
    FixedLengthInCommandSet {
        /// The fixed length given, bytes.
        n: usize,
        /// The operation mode.
        mode: OperationMode,
    },
    /// A fixed message length outside 1–216 bytes.
    #[error("fixed length {n} must be 1 to 216 bytes (FFU120B §4-3 item 15, §5-5)")]
    FixedLength {
        /// The fixed length given, bytes.
        n: usize,
    },
}

/// [`MasterSettings`] that cannot run, with every problem found.
pub type InvalidSettings = crate::engine::InvalidSettings<MasterProblem>;

/// What the owner asks of the master.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MasterCommand {
    /// A command-set request to `station` (0–99; 0 in mode 1).
    Request {
        /// The caller's name for the request.
        id: RequestId,
        /// The station (0–99; 0 in mode 1).
        station: u8,
        /// The request.
        request: Request,
    },
    /// Modes 4–5: a message to the module (§5-5 i).
    Send {
        /// The caller's name for the message.
        id: RequestId,
        /// The message: framed in variable length, sent alone in fixed length.
        data: Vec<u8>,
    },
}

/// What the master reports.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum MasterEvent {
    /// The end of request `id`: exactly one per request or send.
    Done {
        /// The caller's name for the request.
        id: RequestId,
        /// The station the request went to.
        station: u8,
        /// The reply, or why the request did not complete.
        result: Result<Reply, MasterError>,
    },
    /// Mode 1: a transfer the PLC sent (§5-4 iv); it expects no answer.
    Transfer {
        /// The message number (MOLN).
        message: u8,
        /// The bytes transferred.
        data: Vec<u8>,
    },
    /// Modes 4–5: a message from the module (§5-5 ii).
    Received {
        /// The message.
        data: Vec<u8>,
    },
    /// `station` stopped answering: `timeouts` time-outs in a row.
    StationDown {
        /// The station.
        station: u8,
        /// Time-outs in a row; fewer than `down_after` when the line went down.
        timeouts: u32,
    },
    /// `station` answered again.
    StationUp {
        /// The station.
        station: u8,
    },
}

/// Why a request did not complete.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum MasterError {
    /// The request was refused before it was sent.
    #[error("request refused before sending: {0}")]
    Refused(#[from] CommandError),
    /// [`MasterSettings::queue_limit`] requests are already waiting.
    #[error("request refused: {limit} requests are already waiting")]
    QueueFull {
        /// The queue limit.
        limit: usize,
    },
    /// The request is for a new station beyond the [`MAX_STATIONS`] of a line.
    #[error(
        "request refused: a line carries at most {MAX_STATIONS} stations (FFU120B §2-2); station {station:02} would be one more"
    )]
    TooManyStations {
        /// The station asked for.
        station: u8,
    },
    /// No reply in time to any attempt.
    #[error(
        "no reply from station {station:02} to {request} after {attempts} attempt(s) (a silent station is a time-out: FFU120B §5-3 RSNO, §5-6)"
    )]
    TimeOut {
        /// The station.
        station: u8,
        /// The request's name, or `message` in modes 4–5.
        request: &'static str,
        /// Attempts made.
        attempts: u32,
    },
    /// The replies to every attempt arrived corrupted.
    #[error(
        "the replies of station {station:02} to {request} arrived corrupted {attempts} time(s); last: {last}"
    )]
    Corrupted {
        /// The station.
        station: u8,
        /// The request's name, or `message` in modes 4–5.
        request: &'static str,
        /// Attempts made.
        attempts: u32,
        /// What was wrong with the last reply.
        last: ReceiveError,
    },
    /// The module refused the request with a STA code (§5-3-5).
    #[error("{0}")]
    Sta(StaError),
    /// A reply that does not have the form that answers the request (§5-4).
    #[error("{0}")]
    BadReply(ReplyError),
    /// The station is marked down; the request was not sent.
    #[error(
        "station {station:02} is down (no reply to the last {timeouts} attempts); it is probed every {probe_interval:?}"
    )]
    StationDown {
        /// The station.
        station: u8,
        /// Time-outs in a row.
        timeouts: u32,
        /// How often the station is probed.
        probe_interval: Duration,
    },
}

/// Counters of one station since the master started.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct StationCounters {
    /// Requests put on the line (a request counts once however often it is retried).
    pub requests: u64,
    /// Replies that answered a request, normal or with an STA error.
    pub replies: u64,
    /// Attempts that got no reply in time.
    pub timeouts: u64,
    /// Requests sent again after a time-out or a corrupted reply.
    pub retries: u64,
    /// Replies with a BCC error (§5-6 error 5).
    pub bcc_errors: u64,
    /// Replies otherwise corrupted: too long, unreadable (§5-6 errors 1, 6, 7).
    pub corrupted_replies: u64,
    /// Error replies by STA code (§5-3-5).
    pub error_replies: BTreeMap<u8, u64>,
    /// Requests failed at once because the station was down.
    pub refused_down: u64,
    /// The last error of a request to this station.
    #[serde(serialize_with = "display_option")]
    pub last_error: Option<MasterError>,
    /// When the last error came: an old one is history, not the station's state.
    #[serde(skip)]
    pub last_error_at: Option<Instant>,
    /// The station answers (not marked down).
    pub up: bool,
    /// Time-outs since the last reply.
    pub consecutive_timeouts: u32,
}

fn display_option<S: serde::Serializer>(v: &Option<MasterError>, s: S) -> Result<S::Ok, S::Error> {
    match v {
        Some(e) => s.serialize_some(&e.to_string()),
        None => s.serialize_none(),
    }
}

/// UART errors the transport reported.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct LineErrorCounts {
    /// Parity errors.
    pub parity: u64,
    /// Framing errors.
    pub framing: u64,
    /// Receiver overruns.
    pub overrun: u64,
}

/// A snapshot of the master's counters.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct Counters {
    /// Counters of each station, by station number.
    pub stations: BTreeMap<u8, StationCounters>,
    /// Everything the decoder dropped, by §5-6 kind (including texts that were no reply).
    pub receive_errors: ReceiveCounts,
    /// UART errors the transport reported.
    pub line_errors: LineErrorCounts,
    /// Mode 1 transfers from the PLC.
    pub transfers_received: u64,
    /// Modes 4–5 messages received.
    pub messages_received: u64,
    /// Modes 4–5 messages handed to the line.
    pub messages_sent: u64,
    /// Modes 4–5, fixed length: partial messages dropped after a silence of the reply
    /// time-out (also counted as receive error "text form").
    pub partial_messages: u64,
    /// Whole texts that answered no request waiting (late replies after a time-out).
    pub unexpected_texts: u64,
}

/// A request waiting or on the line.
#[derive(Debug, Clone)]
struct Job {
    id: RequestId,
    station: u8,
    /// `None` for a non-procedure message.
    request: Option<Request>,
    bytes: Vec<u8>,
    /// Line bytes of the longest reply.
    reply_len: usize,
    attempts: u32,
    max_attempts: u32,
}

#[derive(Debug)]
struct Waiting {
    job: Job,
    deadline: Instant,
}

#[derive(Debug, Default)]
struct Station {
    counters: StationCounters,
    next_probe: Option<Instant>,
}

/// The host side of an FFU120B link.
#[derive(Debug)]
pub struct Master {
    settings: MasterSettings,
    decoder: FrameDecoder,
    queue: VecDeque<Job>,
    waiting: Option<Waiting>,
    tx: VecDeque<Vec<u8>>,
    events: VecDeque<MasterEvent>,
    stations: BTreeMap<u8, Station>,
    /// No request before this instant (turnaround after a reply).
    quiet_until: Option<Instant>,
    cs: bool,
    /// DR and CD on: the line can carry a reply at all (a TCP device server is connected).
    line_up: bool,
    line_errors: LineErrorCounts,
    transfers_received: u64,
    messages_received: u64,
    messages_sent: u64,
    partial_messages: u64,
    /// When the last byte arrived (modes 4–5, fixed length: a silence ends a partial message).
    last_rx: Option<Instant>,
    unexpected_texts: u64,
    /// Receive errors found after the decoder (BYTEN that does not count the body).
    extra_receive: ReceiveCounts,
}

impl Master {
    /// A master with these settings, or every problem with them.
    pub fn new(settings: MasterSettings) -> Result<Master, InvalidSettings> {
        InvalidSettings::check("FFU120B master", settings.validate())?;
        let decoder = if settings.mode.is_command_set() {
            FrameDecoder::command_set(&settings.frame)
        } else {
            FrameDecoder::non_procedure(&settings.frame, settings.fixed_length)
        };
        Ok(Master {
            settings,
            decoder,
            queue: VecDeque::new(),
            waiting: None,
            tx: VecDeque::new(),
            events: VecDeque::new(),
            stations: BTreeMap::new(),
            quiet_until: None,
            cs: true,
            line_up: true,
            line_errors: LineErrorCounts::default(),
            transfers_received: 0,
            messages_received: 0,
            messages_sent: 0,
            partial_messages: 0,
            last_rx: None,
            unexpected_texts: 0,
            extra_receive: ReceiveCounts::default(),
        })
    }

    /// The settings the master runs with.
    pub fn settings(&self) -> &MasterSettings {
        &self.settings
    }

    /// A snapshot of every counter.
    pub fn counters(&self) -> Counters {
        Counters {
            stations: self
                .stations
                .iter()
                .map(|(n, s)| (*n, s.counters.clone()))
                .collect(),
            receive_errors: self.decoder.counts().merged(&self.extra_receive),
            line_errors: self.line_errors,
            transfers_received: self.transfers_received,
            messages_received: self.messages_received,
            messages_sent: self.messages_sent,
            partial_messages: self.partial_messages,
            unexpected_texts: self.unexpected_texts,
        }
    }

    /// Requests waiting to be sent (not the one on the line).
    pub fn queued(&self) -> usize {
        self.queue.len()
    }

    /// Whether a request is on the line, waiting for its reply.
    pub fn busy(&self) -> bool {
        self.waiting.is_some()
    }

    /// Whether `station` is marked down.
    pub fn is_down(&self, station: u8) -> bool {
        self.stations.get(&station).is_some_and(|s| !s.counters.up)
    }

    fn done(
        &mut self,
        now: Instant,
        id: RequestId,
        station: u8,
        result: Result<Reply, MasterError>,
    ) {
        if let Err(e) = &result
            && let Some(s) = self.stations.get_mut(&station)
        {
            s.counters.last_error = Some(e.clone());
            s.counters.last_error_at = Some(now);
        }
        self.events.push_back(MasterEvent::Done {
            id,
            station,
            result,
        });
    }

    fn refuse(&mut self, id: RequestId, station: u8, error: MasterError) {
        tracing::debug!(id, station, %error, "FFU120B request refused");
        self.events.push_back(MasterEvent::Done {
            id,
            station,
            result: Err(error),
        });
    }

    fn mode_refusal(&self, what: &'static str, section: &'static str) -> MasterError {
        MasterError::Refused(CommandError::NotInMode {
            what,
            mode: self.settings.mode.dial(),
            section,
        })
    }

    /// Checks and encodes a command-set request.
    fn prepare_request(&mut self, station: u8, request: &Request) -> Result<Job, MasterError> {
        let mode = self.settings.mode;
        if !mode.is_command_set() {
            return Err(self.mode_refusal("the command set", "§1-3, §5-5"));
        }
        if matches!(request, Request::Transfer { .. }) && mode != OperationMode::One {
            return Err(self.mode_refusal("the transfer command", "§5-3, §5-4 iii"));
        }
        if to_bcd(station).is_none() {
            return Err(CommandError::Station { station }.into());
        }
        if mode == OperationMode::One && station != 0 {
            return Err(self.mode_refusal("a station other than 00", "§5-3 RSNO"));
        }
        if !self.stations.contains_key(&station) && self.stations.len() >= MAX_STATIONS {
            return Err(MasterError::TooManyStations { station });
        }
        let text = request.encode(station)?;
        let bytes = self.settings.frame.encode(&text);
        // The longest reply: a read returns address, count, ATTR and the data (FFU120B notes 2).
        let reply_text = match request {
            Request::Read { bytes, .. } => 10 + usize::from(*bytes).min(MAX_READ),
            _ => 9,
        };
        Ok(Job {
            id: 0,
            station,
            request: Some(request.clone()),
            bytes,
            reply_len: self.settings.frame.line_len(reply_text),
            attempts: 0,
            max_attempts: self.settings.retries.saturating_add(1),
        })
    }

    fn prepare_send(&self, data: &[u8]) -> Result<Job, MasterError> {
        if self.settings.mode.is_command_set() {
            return Err(self.mode_refusal("a non-procedure message", "§5-5"));
        }
        let bytes = match self.settings.fixed_length {
            Some(n) => {
                if data.len() != n {
                    return Err(CommandError::MessageLength {
                        bytes: data.len(),
                        want: format!("exactly {n} (fixed length)"),
                    }
                    .into());
                }
                // Fixed length: the data alone, no start code, end code or BCC (appendix),
                // transposed to 2N hex characters when item 14 says so (FFU120B notes 9).
                self.settings.frame.encode_bare(data)
            }
            None => {
                if data.is_empty() || data.len() > MAX_NON_PROCEDURE_TEXT {
                    return Err(CommandError::MessageLength {
                        bytes: data.len(),
                        want: format!("1 to {MAX_NON_PROCEDURE_TEXT}"),
                    }
                    .into());
                }
                let end = self.settings.frame.end_bytes();
                if !self.settings.frame.transposition
                    && let Some(offset) = data.windows(end.len().max(1)).position(|w| w == end)
                {
                    return Err(CommandError::EndCodeInMessage {
                        offset,
                        end: end.to_vec(),
                    }
                    .into());
                }
                self.settings.frame.encode(data)
            }
        };
        Ok(Job {
            id: 0,
            station: 0,
            request: None,
            bytes,
            reply_len: 0,
            attempts: 0,
            max_attempts: 1,
        })
    }

    fn enqueue(&mut self, id: RequestId, station: u8, job: Result<Job, MasterError>) {
        match job {
            Err(e) => self.refuse(id, station, e),
            Ok(_) if self.queue.len() >= self.settings.queue_limit => self.refuse(
                id,
                station,
                MasterError::QueueFull {
                    limit: self.settings.queue_limit,
                },
            ),
            Ok(mut job) => {
                job.id = id;
                if job.request.is_some() && !self.stations.contains_key(&station) {
                    // Over a line that is down no station answers: it starts down.
                    let up = self.line_up;
                    self.stations.insert(
                        station,
                        Station {
                            counters: StationCounters {
                                up,
                                ..StationCounters::default()
                            },
                            next_probe: None,
                        },
                    );
                    if !up {
                        self.events.push_back(MasterEvent::StationDown {
                            station,
                            timeouts: 0,
                        });
                    }
                }
                self.queue.push_back(job);
            }
        }
    }

    /// May a text start now?
    fn line_free(&self, now: Instant) -> bool {
        if self.waiting.is_some() || !self.tx.is_empty() {
            return false;
        }
        if self.quiet_until.is_some_and(|t| now < t) {
            return false;
        }
        let rs232 = matches!(
            self.settings.mode,
            OperationMode::One | OperationMode::Two | OperationMode::Four
        );
        !(rs232 && self.settings.honour_cs && !self.cs)
    }

    /// Sends the next request if the line is free; fails requests to stations that are down.
    fn drive(&mut self, now: Instant) {
        if self.quiet_until.is_some_and(|t| now >= t) {
            self.quiet_until = None;
        }
        while self.line_free(now) {
            let Some(mut job) = self.queue.pop_front() else {
                return;
            };
            if job.request.is_none() {
                // Non-procedure: nothing answers (§5-5); done once handed to the line.
                let bytes = job.bytes.len();
                self.messages_sent += 1;
                self.tx.push_back(job.bytes);
                self.done(now, job.id, 0, Ok(Reply::Sent { bytes }));
                continue;
            }
            let probe_interval = self.settings.probe_interval;
            let Some(st) = self.stations.get_mut(&job.station) else {
                continue;
            };
            if job.attempts == 0 {
                if !st.counters.up {
                    if st.next_probe.is_some_and(|t| now < t) {
                        st.counters.refused_down += 1;
                        let timeouts = st.counters.consecutive_timeouts;
                        self.done(
                            now,
                            job.id,
                            job.station,
                            Err(MasterError::StationDown {
                                station: job.station,
                                timeouts,
                                probe_interval,
                            }),
                        );
                        continue;
                    }
                    // A probe: one attempt; the next one a probe interval later.
                    st.next_probe = Some(now + probe_interval);
                    job.max_attempts = 1;
                    tracing::debug!(station = job.station, "probing a station marked down");
                }
                st.counters.requests += 1;
            }
            self.transmit(now, job);
        }
    }

    /// Puts an attempt of `job` on the line and starts its time-out: the request's line time,
    /// the module's allowance, and the line time of the longest reply.
    fn transmit(&mut self, now: Instant, mut job: Job) {
        job.attempts += 1;
        let line = &self.settings.line;
        let deadline = now
            + line.time_for_chars(job.bytes.len() as u64)
            + self.settings.reply_timeout
            + line.time_for_chars(job.reply_len as u64);
        self.tx.push_back(job.bytes.clone());
        self.waiting = Some(Waiting { job, deadline });
    }

    /// The attempt on the line failed: send it again, or end the request with `error`.
    fn attempt_failed(&mut self, now: Instant, error: MasterError) {
        let Some(Waiting { job, .. }) = self.waiting.take() else {
            return;
        };
        self.quiet_until = Some(now + self.settings.turnaround);
        let up = self
            .stations
            .get(&job.station)
            .is_some_and(|s| s.counters.up);
        if job.attempts < job.max_attempts && up {
            if let Some(st) = self.stations.get_mut(&job.station) {
                st.counters.retries += 1;
            }
            tracing::debug!(station = job.station, attempt = job.attempts + 1, %error, "FFU120B request sent again");
            // The retry goes ahead of the queue.
            self.queue.push_front(job);
            return;
        }
        self.done(now, job.id, job.station, Err(error));
    }

    fn on_timeout(&mut self, now: Instant) {
        let Some(w) = &self.waiting else {
            return;
        };
        let (station, attempts) = (w.job.station, w.job.attempts);
        let request = w.job.request.as_ref().map_or("message", Request::name);
        // The silence ends any partial text: with no start code, the next byte starts one.
        self.decoder.clear();
        let down_after = self.settings.down_after;
        let probe_interval = self.settings.probe_interval;
        if let Some(st) = self.stations.get_mut(&station) {
            st.counters.timeouts += 1;
            st.counters.consecutive_timeouts = st.counters.consecutive_timeouts.saturating_add(1);
            if st.counters.up && st.counters.consecutive_timeouts >= down_after {
                st.counters.up = false;
                st.next_probe = Some(now + probe_interval);
                let timeouts = st.counters.consecutive_timeouts;
                tracing::warn!(station, timeouts, "FFU120B station marked down");
                self.events
                    .push_back(MasterEvent::StationDown { station, timeouts });
            }
        }
        let error = MasterError::TimeOut {
            station,
            request,
            attempts,
        };
        self.attempt_failed(now, error);
    }

    fn on_text(&mut self, now: Instant, text: Vec<u8>) {
        if !self.settings.mode.is_command_set() {
            self.messages_received += 1;
            self.events.push_back(MasterEvent::Received { data: text });
            return;
        }
        let parsed = match CommandText::parse(&text) {
            Ok(t) => t,
            Err(form) => {
                // BYTEN that does not count the body: the module's receive error 7.
                self.extra_receive.add(ReceiveErrorKind::TextForm);
                self.on_receive_error(now, ReceiveError::TextForm(form));
                return;
            }
        };
        let waiting_request = self.waiting.as_ref().and_then(|w| w.job.request.as_ref());
        if self.settings.mode == OperationMode::One
            && let Some((message, data)) = unsolicited_transfer(&parsed)
        {
            // The answer to our own transfer has the same header with BYTEN 00; a text with
            // data, or with no transfer of ours waiting, is the PLC's (FFU120B notes 8).
            let our_ack = data.is_empty()
                && waiting_request
                    .is_some_and(|r| r.cmnd() == CMND_TRANSFER && r.answered_by(&parsed));
            if !our_ack {
                // The reply we wait for queues behind the transfer on the line.
                let delay = self
                    .settings
                    .line
                    .time_for_chars(self.settings.frame.line_len(text.len()) as u64);
                if let Some(w) = &mut self.waiting {
                    w.deadline += delay;
                }
                self.transfers_received += 1;
                self.events
                    .push_back(MasterEvent::Transfer { message, data });
                return;
            }
        }
        // Over a two-wire RS-485 line the host may hear its own request; the module's reply
        // differs from it (STA for RSNO, MODE with its MSB, §5-4), so an exact echo is ignored.
        let echo = self.settings.mode.is_multi_drop()
            && self.waiting.as_ref().is_some_and(|w| {
                w.job
                    .request
                    .as_ref()
                    .and_then(|r| r.encode(w.job.station).ok())
                    .is_some_and(|t| t == text)
            });
        if echo || !waiting_request.is_some_and(|r| r.answered_by(&parsed)) {
            self.unexpected_texts += 1;
            tracing::debug!(
                cmnd = parsed.cmnd,
                moln = parsed.moln,
                "FFU120B text that answers no request waiting; ignored"
            );
            return;
        }
        let Some(Waiting { job, .. }) = self.waiting.take() else {
            return;
        };
        let result = request_result(&job, &parsed);
        if let Some(st) = self.stations.get_mut(&job.station) {
            st.counters.replies += 1;
            st.counters.consecutive_timeouts = 0;
            if let Err(MasterError::Sta(e)) = &result {
                *st.counters.error_replies.entry(e.sta.code()).or_default() += 1;
            }
            if !st.counters.up {
                st.counters.up = true;
                st.next_probe = None;
                tracing::info!(station = job.station, "FFU120B station answers again");
                self.events.push_back(MasterEvent::StationUp {
                    station: job.station,
                });
            }
        }
        self.done(now, job.id, job.station, result);
        self.quiet_until = Some(now + self.settings.turnaround);
    }

    /// A dropped text. While a reply is awaited, one that got as far as its end (BCC error,
    /// too long, unreadable) was the reply, corrupted: send the request again.
    fn on_receive_error(&mut self, now: Instant, error: ReceiveError) {
        let kind = error.kind();
        if kind == ReceiveErrorKind::StartCode {
            return;
        }
        let Some(w) = &mut self.waiting else {
            return;
        };
        let (station, attempts) = (w.job.station, w.job.attempts);
        let request = w.job.request.as_ref().map_or("message", Request::name);
        if let Some(st) = self.stations.get_mut(&station) {
            if kind == ReceiveErrorKind::Bcc {
                st.counters.bcc_errors += 1;
            } else {
                st.counters.corrupted_replies += 1;
            }
            // Something came back: the station is alive.
            st.counters.consecutive_timeouts = 0;
        }
        self.attempt_failed(
            now,
            MasterError::Corrupted {
                station,
                request,
                attempts,
                last: error,
            },
        );
    }

    fn on_decoded(&mut self, now: Instant, decoded: Decoded) {
        match decoded {
            Ok(text) => self.on_text(now, text),
            Err(e) => self.on_receive_error(now, e),
        }
    }
}

/// The outcome of a reply that answers `job`'s request.
fn request_result(job: &Job, reply: &CommandText) -> Result<Reply, MasterError> {
    let Some(request) = &job.request else {
        return Err(MasterError::Refused(CommandError::Empty {
            what: "message",
        }));
    };
    request
        .parse_reply(job.station, reply)
        .map_err(|e| match e {
            ReplyError::Sta(sta) => MasterError::Sta(sta),
            other => MasterError::BadReply(other),
        })
}

impl Engine for Master {
    type Command = MasterCommand;
    type Event = MasterEvent;

    fn handle_input(&mut self, now: Instant, bytes: &[u8]) {
        if self.settings.fixed_length.is_some()
            && self.decoder.in_text()
            && self
                .last_rx
                .is_some_and(|t| now.saturating_duration_since(t) >= self.settings.reply_timeout)
        {
            // Fixed length has no start code to find a message by (§5-5): a partial message
            // followed by a silence of the reply time-out lost bytes on the line; dropping it
            // puts the next message back on its boundary (FFU120B notes 9).
            tracing::debug!(
                held = self.decoder.buffered(),
                "partial fixed-length message dropped after a silence"
            );
            self.decoder.clear();
            self.partial_messages += 1;
            self.extra_receive.add(ReceiveErrorKind::TextForm);
        }
        if !bytes.is_empty() {
            self.last_rx = Some(now);
        }
        if self.settings.mode == OperationMode::Five && !bytes.is_empty() {
            // RS-485 shared with the module: no message of ours while it talks.
            let quiet = now + self.settings.line.time_for_chars(2);
            self.quiet_until = Some(self.quiet_until.map_or(quiet, |q| q.max(quiet)));
        }
        for decoded in self.decoder.decode(bytes) {
            self.on_decoded(now, decoded);
        }
        self.drive(now);
    }

    fn handle_line_error(&mut self, now: Instant, error: LineError) {
        // Counted (§5-6 keeps them too), and the text the character belonged to ends as a
        // receive error whatever the rest of it holds: a reply is sent again, a message is
        // dropped and the next one read as usual (§5-6 "receiving error").
        match error {
            LineError::Parity => self.line_errors.parity += 1,
            LineError::Framing => self.line_errors.framing += 1,
            LineError::Overrun => self.line_errors.overrun += 1,
        }
        tracing::debug!(%error, "FFU120B line error");
        for decoded in self.decoder.spoil(error) {
            self.on_decoded(now, decoded);
        }
        self.drive(now);
    }

    fn handle_modem(&mut self, now: Instant, modem: ModemIn) {
        self.cs = modem.cs;
        let up = modem.dr && modem.cd;
        if !up && self.line_up {
            // With the line down (DR or CD off: a device server unreachable) no station can
            // answer. Say so now: held back by CS, its requests would never time out. Each
            // station comes up again with its next reply (a probe once the line is back).
            tracing::warn!("FFU120B line down: every station marked down");
            for (&station, st) in &mut self.stations {
                if st.counters.up {
                    st.counters.up = false;
                    st.next_probe = None;
                    self.events.push_back(MasterEvent::StationDown {
                        station,
                        timeouts: st.counters.consecutive_timeouts,
                    });
                }
            }
        }
        self.line_up = up;
        self.drive(now);
    }

    fn handle_command(&mut self, now: Instant, command: MasterCommand) {
        match command {
            MasterCommand::Request {
                id,
                station,
                request,
            } => {
                let job = self.prepare_request(station, &request);
                self.enqueue(id, station, job);
            }
            MasterCommand::Send { id, data } => {
                let job = self.prepare_send(&data);
                self.enqueue(id, 0, job);
            }
        }
        self.drive(now);
    }

    fn handle_timeout(&mut self, now: Instant) {
        if self.waiting.as_ref().is_some_and(|w| now >= w.deadline) {
            self.on_timeout(now);
        }
        self.drive(now);
    }

    fn poll_transmit(&mut self, now: Instant) -> Option<Vec<u8>> {
        self.drive(now);
        self.tx.pop_front()
    }

    fn poll_event(&mut self) -> Option<MasterEvent> {
        self.events.pop_front()
    }

    fn poll_timeout(&self) -> Option<Instant> {
        if let Some(w) = &self.waiting {
            return Some(w.deadline);
        }
        if self.queue.is_empty() {
            return None;
        }
        // A request waits only for the turnaround (or CS, which a modem change ends).
        self.quiet_until
    }
}

impl BusCode for MasterError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            MasterError::Refused(_) | MasterError::TooManyStations { .. } => {
                pb::ErrorCode::InvalidRequest
            }
            MasterError::QueueFull { .. } => pb::ErrorCode::Busy,
            MasterError::TimeOut { .. }
            | MasterError::Corrupted { .. }
            | MasterError::BadReply(_) => pb::ErrorCode::LinkFailed,
            MasterError::Sta(e) => BusCode::code(&e.sta),
            MasterError::StationDown { .. } => pb::ErrorCode::Unavailable,
        }
    }
    fn sta(&self) -> Option<u8> {
        match self {
            MasterError::Sta(e) => Some(e.sta.code()),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests;
