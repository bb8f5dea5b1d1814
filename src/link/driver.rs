//! The host link task: one per machine. It runs a [`HostEngine`] over a transport with a
//! [`Pump`], keeps the machine's program queue, streams the active program from its source into
//! the engine in bounded pieces (a 500 MB program is never held whole), and turns engine events
//! into [`LinkEvent`]s with job ids and byte offsets.

use std::collections::VecDeque;
use std::time::{Duration, Instant, SystemTime};

use std::sync::Arc;

use bytes::Bytes;
use tokio::io::{AsyncRead, AsyncReadExt};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

use super::JobId;
use super::fanout;
use super::pump::{Pump, PumpError, now};
use crate::telemetry::metrics::{self, LinkMetrics};
use crate::telemetry::span_count;
use crate::transport::Transport;
use cellgate_core::fanuc::alarm::CncAlarm;
use cellgate_core::fanuc::error::{AbortReason, LinkAlarm, ProtocolError};
use cellgate_core::fanuc::host::{
    Confirmation, EngineCommand, EngineEvent, HostEngine, LinkState, PunchDamage,
};
use cellgate_core::fanuc::sat::StatusData;

/// Where a program's bytes come from: a file, a bus download, a test vector.
pub type ProgramSource = Box<dyn AsyncRead + Send + Unpin>;

use cellgate_core::codes::BusCode;
pub use cellgate_core::fanuc::host::Chunk;
use cellgate_core::pb;
use cellgate_core::program::fed::FedBlocks;

/// What a job's program is read from.
pub enum JobSource {
    /// A program that exists whole somewhere (file, download, test vector).
    Program(ProgramSource),
    /// A program made while it is sent; it ends when the sender is dropped.
    Chunks(mpsc::Receiver<Chunk>),
}

impl JobSource {
    pub fn program(source: impl AsyncRead + Send + Unpin + 'static) -> Self {
        JobSource::Program(Box::new(source))
    }
}

/// A program to send to the machine.
pub struct ProgramJob {
    pub id: JobId,
    /// Display name (library name, file name).
    pub name: String,
    /// Size in bytes when known, for progress.
    pub size: Option<u64>,
    pub source: JobSource,
    /// How often progress is reported for a program of unknown size (a stream's status wants
    /// it often); `None`: [`PROGRESS_INTERVAL`].
    pub progress_interval: Option<Duration>,
}

impl std::fmt::Debug for ProgramJob {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ProgramJob")
            .field("id", &self.id)
            .field("name", &self.name)
            .field("size", &self.size)
            .finish_non_exhaustive()
    }
}

/// What the gateway asks of a link.
#[derive(Debug)]
#[non_exhaustive]
pub enum LinkCommand {
    /// Queue a program; it is sent when the ones before it are done.
    Queue(ProgramJob),
    /// Cancel a queued or active job.
    Cancel(JobId),
    /// Set the DO bits selected by `mask` to `value` (SDO, §4.4.1). `asked` is when the
    /// command was given (for the `cellgate.do.delay` histogram).
    SetDo {
        value: u8,
        mask: u8,
        asked: SystemTime,
    },
    /// Read the DI image (RDI → SDI, §4.4.1).
    ReadDi,
    /// Clear the board's buffer (CLB, §4.4.1).
    ClearBuffer,
    /// Report the link's jobs: for an owner that fell behind the link's events and may have
    /// missed a job's end.
    Jobs(tokio::sync::oneshot::Sender<LinkJobs>),
}

/// The link's jobs as it holds them now ([`LinkCommand::Jobs`]).
#[derive(Debug, Clone, Default)]
pub struct LinkJobs {
    /// The job being sent.
    pub active: Option<JobId>,
    /// The jobs waiting behind it, in order.
    pub queued: Vec<JobId>,
    /// The end events of the latest jobs that ended ([`RECENT_ENDS`] at most), oldest first.
    pub recent_ends: Vec<LinkEvent>,
}

/// Job ends a link remembers for [`LinkCommand::Jobs`].
pub const RECENT_ENDS: usize = 8;

/// Why a job on a link failed.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum JobFailure {
    /// The engine abandoned the program.
    #[error("{0}")]
    Aborted(AbortReason),
    /// The program's source could not be read to its end.
    #[error("program source failed: {0}")]
    Source(Arc<std::io::Error>),
    /// The link task ended with its line failed for good.
    #[error("{0}")]
    LinkStopped(Arc<PumpError>),
    /// The link task was stopped (the gateway shuts down).
    #[error("gateway shutting down")]
    Shutdown,
}

impl JobFailure {
    /// The CNC alarm number behind the failure, where one applies.
    pub fn cnc_alarm(&self) -> Option<CncAlarm> {
        match self {
            JobFailure::Aborted(reason) => reason.cnc_alarm(),
            _ => None,
        }
    }
}

/// What a link reports.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub enum LinkEvent {
    State {
        state: LinkState,
    },
    Status {
        status: StatusData,
    },
    Di {
        value: u8,
    },
    Do {
        value: u8,
    },
    CncReset,
    CncAlarm,
    /// A link alarm; [`LinkAlarm::cnc_alarm`] is the CNC alarm number where one applies.
    Alarm(LinkAlarm),
    ProtocolError {
        error: ProtocolError,
        retried: bool,
    },
    JobQueued {
        job: JobId,
        position: usize,
    },
    JobStarted {
        job: JobId,
    },
    /// What the link now waits for from the board (`None`: nothing), since `since_unix_ms`
    /// (see [`HostEngine::waiting_for`]).
    Waiting {
        what: Option<&'static str>,
        since_unix_ms: u64,
    },
    /// `acked`: program bytes the board acknowledged; `sent`: handed to the line; `block`:
    /// the last block acknowledged whole (none yet, or a stream of chunks).
    Progress {
        job: JobId,
        acked: u64,
        sent: u64,
        total: Option<u64>,
        block: Option<Arc<str>>,
    },
    /// The board acknowledged the whole program, `bytes` long, as `confirmation` says;
    /// `block`: its last block.
    JobDone {
        job: JobId,
        bytes: u64,
        confirmation: Confirmation,
        block: Option<Arc<str>>,
    },
    /// `offset`: program bytes the board acknowledged; `sent`: handed to the line.
    JobFailed {
        job: JobId,
        offset: u64,
        sent: u64,
        reason: JobFailure,
    },
    JobCancelled {
        job: JobId,
        offset: u64,
        sent: u64,
    },
    /// Punched data from the CNC (Protocol B punch-out, §6.1.1 2), as received, in order. A
    /// piece ends at latest with each program's EOR, so a whole program is the pieces up to
    /// and including one that ends with its `%`.
    Punched {
        data: Bytes,
    },
    /// The punch-out was damaged after the `Punched` pieces before it: the program being
    /// punched is not good.
    PunchDamaged {
        cause: PunchDamage,
    },
    /// The link task ended (shutdown, or the line closed for good).
    Stopped {
        error: Option<Arc<PumpError>>,
    },
}

/// Why a command could not be given to a link.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LinkError {
    #[error("link {machine} is not running")]
    NotRunning { machine: String },
    #[error("link {machine} has {max} commands waiting already; try again later")]
    Busy { machine: String, max: usize },
}

/// Commands a link holds waiting; [`LinkHandle::try_send`] refuses more.
pub const COMMAND_QUEUE: usize = 64;

/// Progress events come at least at every whole percent and at most every this often
/// otherwise (for programs of unknown size).
pub const PROGRESS_INTERVAL: Duration = Duration::from_millis(250);

/// Link events kept for a subscriber that fell behind ([`fanout`]: paid for only while they
/// wait): 256 is a minute of a busy link's events (progress comes at most every 250 ms,
/// status at each SAT), while the subscribers (the machine's bus task, its job manager) take
/// them within milliseconds.
pub const LINK_EVENTS: usize = 256;

/// The largest piece read from a program source at once. A file source holds a buffer of
/// the same size in `tokio::fs::File` besides this one, so it is counted twice per busy link.
const SOURCE_CHUNK: usize = 8 * 1024;

/// Talks to a running link task. Cheap to clone.
#[derive(Clone, Debug)]
pub struct LinkHandle {
    machine: String,
    commands: mpsc::Sender<LinkCommand>,
    events: fanout::Sender<LinkEvent>,
    /// The link's state now, for whoever starts watching after the link started.
    state: watch::Receiver<Option<LinkState>>,
    /// The line counters the link task keeps; none for a link served by something else.
    metrics: Option<Arc<LinkMetrics>>,
}

impl LinkHandle {
    /// A handle on a link served by something other than [`spawn`]: a test double, or a
    /// bridge to a link running elsewhere. Whatever reads `commands` must emit the
    /// [`LinkEvent`]s a link task would on `events`.
    pub fn from_channels(
        machine: impl Into<String>,
        commands: mpsc::Sender<LinkCommand>,
        events: fanout::Sender<LinkEvent>,
    ) -> Self {
        // A link built from bare channels reports its state by events only.
        let (_, state) = watch::channel(None);
        LinkHandle {
            machine: machine.into(),
            commands,
            events,
            state,
            metrics: None,
        }
    }

    /// The line's counters (bytes, frames) as the link task keeps them; `None` for a link
    /// that keeps none (one built with [`LinkHandle::from_channels`]).
    pub fn line_counts(&self) -> Option<metrics::LinkCounts> {
        self.metrics.as_ref().map(|m| m.counts())
    }

    pub fn machine(&self) -> &str {
        &self.machine
    }

    pub async fn send(&self, command: LinkCommand) -> Result<(), LinkError> {
        self.commands
            .send(command)
            .await
            .map_err(|_| LinkError::NotRunning {
                machine: self.machine.clone(),
            })
    }

    /// Gives the link a command without waiting: a flood of commands (DO puts) is refused
    /// once [`COMMAND_QUEUE`] wait, rather than held up behind one another.
    pub fn try_send(&self, command: LinkCommand) -> Result<(), LinkError> {
        self.commands.try_send(command).map_err(|e| match e {
            mpsc::error::TrySendError::Full(_) => LinkError::Busy {
                machine: self.machine.clone(),
                max: COMMAND_QUEUE,
            },
            mpsc::error::TrySendError::Closed(_) => LinkError::NotRunning {
                machine: self.machine.clone(),
            },
        })
    }

    /// Events from now on. A receiver that falls more than the channel's capacity behind
    /// loses the oldest events (and is told so by `RecvError::Lagged`).
    pub fn subscribe(&self) -> fanout::Receiver<LinkEvent> {
        self.events.subscribe()
    }

    /// The link's current state (`None` before the engine reported one). Events sent before a
    /// subscriber subscribed are not replayed; this is what such a subscriber starts from.
    pub fn state(&self) -> Option<LinkState> {
        *self.state.borrow()
    }
}

/// Starts the link task for `machine`. It ends when `shutdown` is cancelled, when every
/// handle is dropped, or when the transport closes for good.
pub fn spawn<E, T>(
    machine: impl Into<String>,
    engine: E,
    transport: T,
    shutdown: CancellationToken,
) -> (
    LinkHandle,
    tokio::task::JoinHandle<Result<(), Arc<PumpError>>>,
)
where
    E: HostEngine + 'static,
    T: Transport + 'static,
{
    let machine = machine.into();
    let (cmd_tx, cmd_rx) = mpsc::channel(COMMAND_QUEUE);
    let (ev_tx, _) = fanout::channel(LINK_EVENTS);
    let (state_tx, state_rx) = watch::channel(None);
    let link_metrics = metrics::link(&machine);
    let handle = LinkHandle {
        machine: machine.clone(),
        commands: cmd_tx,
        events: ev_tx.clone(),
        state: state_rx,
        metrics: Some(Arc::clone(&link_metrics)),
    };
    let line = transport.describe();
    let span = tracing::info_span!("link", machine = %machine, line = %line);
    let driver = Driver {
        metrics: link_metrics,
        counted: Counted::default(),
        session: None,
        machine,
        line,
        pump: Pump::new(engine, transport),
        commands: cmd_rx,
        events: ev_tx,
        state: state_tx,
        queue: VecDeque::new(),
        active: None,
        do_image: 0,
        do_wanted: 0,
        buf: Box::default(),
        waiting: None,
        recent_ends: VecDeque::new(),
    };
    let task = tokio::spawn(tracing::Instrument::instrument(driver.run(shutdown), span));
    (handle, task)
}

struct ActiveJob {
    id: JobId,
    size: Option<u64>,
    /// `None` once the source reached its end (or failed).
    source: Option<JobSource>,
    progress_interval: Duration,
    /// Program bytes handed to the line.
    sent: u64,
    /// Program bytes the board acknowledged.
    acked: u64,
    /// When the last progress event went, and the figures it carried (acked, sent).
    last_progress: Option<(Instant, u64, u64)>,
    cancelling: bool,
    /// The program's bytes from the last progress event on, for the block being fed.
    fed: FedBlocks,
}

/// What of the pump's running totals is already in the link's counters.
#[derive(Default)]
struct Counted {
    bytes: (u64, u64),
    frames: (u64, u64),
}

/// The span of the link's current session (from the link up to its next re-initialisation,
/// line down or stop), and the byte totals it started at.
struct Session {
    span: tracing::Span,
    bytes_at_start: (u64, u64),
}

struct Driver<E, T> {
    machine: String,
    /// The transport as described in logs.
    line: String,
    metrics: Arc<LinkMetrics>,
    counted: Counted,
    session: Option<Session>,
    pump: Pump<E, T>,
    commands: mpsc::Receiver<LinkCommand>,
    events: fanout::Sender<LinkEvent>,
    state: watch::Sender<Option<LinkState>>,
    queue: VecDeque<ProgramJob>,
    active: Option<ActiveJob>,
    do_image: u8,
    /// The DO image last asked for (sent or still pending).
    do_wanted: u8,
    buf: Box<[u8]>,
    /// What the engine waits for from the board, as last reported.
    waiting: Option<&'static str>,
    /// The latest job ends, for an owner that missed them.
    recent_ends: VecDeque<LinkEvent>,
}

enum Wake {
    Shutdown,
    Command(Option<LinkCommand>),
    Source(Read),
    Pump(Result<(), PumpError>),
}

impl<E: HostEngine, T: Transport> Driver<E, T> {
    async fn run(mut self, shutdown: CancellationToken) -> Result<(), Arc<PumpError>> {
        let result = loop {
            self.drain_engine_events();
            self.start_next_job();
            let want = match &self.active {
                Some(ActiveJob {
                    source: Some(_),
                    cancelling: false,
                    ..
                }) => self.pump.engine().data_wanted().min(SOURCE_CHUNK),
                _ => 0,
            };
            // The read buffer exists only while a program is being read: an idle link of a
            // thousand does not hold 16 KiB.
            if want > 0 && self.buf.is_empty() {
                self.buf = vec![0; SOURCE_CHUNK].into_boxed_slice();
            } else if self.active.is_none() && !self.buf.is_empty() {
                self.buf = Box::default();
            }
            let wake = {
                let source = self.active.as_mut().and_then(|a| a.source.as_mut());
                let buf = &mut self.buf[..want];
                tokio::select! {
                    biased;
                    () = shutdown.cancelled() => Wake::Shutdown,
                    cmd = self.commands.recv() => Wake::Command(cmd),
                    r = read_some(source, buf), if want > 0 => Wake::Source(r),
                    r = self.pump.step() => Wake::Pump(r),
                }
            };
            self.count_line();
            match wake {
                Wake::Shutdown | Wake::Command(None) => break Ok(()),
                Wake::Command(Some(cmd)) => self.handle_command(cmd),
                Wake::Source(r) => self.handle_source(r, want),
                Wake::Pump(Ok(())) => {}
                Wake::Pump(Err(e)) => break Err(e),
            }
        };
        self.drain_engine_events();
        self.count_line();
        self.end_session(if result.is_ok() {
            "stopped"
        } else {
            "line failed"
        });
        let (result, error) = match result {
            Ok(()) => (Ok(()), None),
            Err(e) => {
                let shared = Arc::new(e);
                (Err(Arc::clone(&shared)), Some(shared))
            }
        };
        if let Some(active) = self.active.take() {
            let reason = match &error {
                Some(e) => JobFailure::LinkStopped(Arc::clone(e)),
                None => JobFailure::Shutdown,
            };
            // Interrupted at what the board acknowledged; bytes still under way are not
            // claimed.
            self.emit(LinkEvent::JobFailed {
                job: active.id,
                offset: active.acked,
                sent: active.sent,
                reason,
            });
        }
        for job in std::mem::take(&mut self.queue) {
            self.emit(LinkEvent::JobCancelled {
                job: job.id,
                offset: 0,
                sent: 0,
            });
        }
        self.emit(LinkEvent::Stopped { error });
        result
    }

    fn emit(&mut self, event: LinkEvent) {
        if matches!(
            event,
            LinkEvent::JobDone { .. }
                | LinkEvent::JobFailed { .. }
                | LinkEvent::JobCancelled { .. }
        ) {
            if self.recent_ends.len() >= RECENT_ENDS {
                self.recent_ends.pop_front();
            }
            self.recent_ends.push_back(event.clone());
        }
        // No subscriber is not an error: nobody is watching this link right now.
        let _ = self.events.send(event);
    }

    /// Adds what the pump moved since the last call to the link's counters: a subtraction
    /// and at most four atomic adds per wake-up, nothing per byte.
    fn count_line(&mut self) {
        let bytes = self.pump.counters();
        let frames = self.pump.engine().frames();
        let frames = (frames.received, frames.sent);
        let c = &mut self.counted;
        self.metrics.add_bytes(
            bytes.0.saturating_sub(c.bytes.0),
            bytes.1.saturating_sub(c.bytes.1),
        );
        self.metrics.add_frames(
            frames.0.saturating_sub(c.frames.0),
            frames.1.saturating_sub(c.frames.1),
        );
        c.bytes = bytes;
        c.frames = frames;
    }

    /// The span link events belong to: the session's, else the link task's.
    fn event_parent(&self) -> Option<tracing::Id> {
        match &self.session {
            Some(s) => s.span.id(),
            None => tracing::Span::current().id(),
        }
    }

    /// A link session starts when the link is up with its board and ends when it goes back
    /// to initialising or the line goes down. Its own trace: a link runs for months.
    fn on_state(&mut self, state: LinkState) {
        match state {
            LinkState::Ready | LinkState::Sending | LinkState::Receiving => {
                if self.session.is_none() {
                    self.metrics.session();
                    let span = tracing::info_span!(
                        parent: None,
                        "link session",
                        link = %self.machine,
                        line = %self.line,
                        bytes_in = tracing::field::Empty,
                        bytes_out = tracing::field::Empty,
                        ended = tracing::field::Empty,
                    );
                    span.follows_from(tracing::Span::current());
                    tracing::info!(parent: &span, "link up");
                    self.session = Some(Session {
                        span,
                        bytes_at_start: self.pump.counters(),
                    });
                }
            }
            LinkState::Initialising => self.end_session("re-initialised"),
            LinkState::LineDown => self.end_session("line down"),
        }
    }

    fn end_session(&mut self, why: &'static str) {
        let Some(session) = self.session.take() else {
            return;
        };
        let (rx, tx) = self.pump.counters();
        let span = session.span;
        span.record(
            "bytes_in",
            span_count(rx.saturating_sub(session.bytes_at_start.0)),
        );
        span.record(
            "bytes_out",
            span_count(tx.saturating_sub(session.bytes_at_start.1)),
        );
        span.record("ended", why);
        tracing::info!(parent: &span, why, "link session over");
    }

    /// Counts a protocol error and notes it in the session's span.
    fn on_protocol_error(&self, error: &ProtocolError, retried: bool) {
        if retried {
            self.metrics.retry();
        }
        let checksum = error.is_checksum();
        if checksum {
            self.metrics.checksum_error();
        }
        let line = matches!(error, ProtocolError::LineB { .. });
        if line {
            self.metrics.line_error();
        }
        let parent = self.event_parent();
        if line {
            tracing::warn!(parent: parent, %error, "line fault");
        } else if checksum {
            tracing::info!(parent: parent, %error, retried, "checksum error");
        } else if retried {
            tracing::info!(parent: parent, %error, "retry");
        } else {
            tracing::debug!(parent: parent, %error, "protocol error");
        }
    }

    /// Counts a link alarm and notes it in the session's span (before the session ends with
    /// the re-initialisation the alarm brings).
    fn on_alarm(&self, alarm: &LinkAlarm) {
        self.metrics.alarm();
        let line = matches!(alarm, LinkAlarm::Line(_) | LinkAlarm::FrameParity { .. });
        if line {
            self.metrics.line_error();
        }
        let number = alarm.cnc_alarm().map(CncAlarm::number);
        tracing::warn!(parent: self.event_parent(), number, line_fault = line, %alarm, "link alarm");
    }

    fn engine_command(&mut self, command: EngineCommand) {
        self.pump.engine_mut().handle_command(now(), command);
    }

    fn handle_command(&mut self, command: LinkCommand) {
        match command {
            LinkCommand::Queue(job) => {
                let position = self.queue.len() + usize::from(self.active.is_some());
                tracing::info!(job = job.id, name = %job.name, size = ?job.size, position, "program queued");
                self.emit(LinkEvent::JobQueued {
                    job: job.id,
                    position,
                });
                self.queue.push_back(job);
            }
            LinkCommand::Cancel(id) => {
                if let Some(i) = self.queue.iter().position(|j| j.id == id) {
                    self.queue.remove(i);
                    self.emit(LinkEvent::JobCancelled {
                        job: id,
                        offset: 0,
                        sent: 0,
                    });
                } else if let Some(active) = self.active.as_mut().filter(|a| a.id == id) {
                    if !active.cancelling {
                        active.cancelling = true;
                        active.source = None;
                        self.engine_command(EngineCommand::Cancel);
                    }
                }
            }
            LinkCommand::SetDo { value, mask, asked } => {
                self.metrics
                    .do_delay(SystemTime::now().duration_since(asked).unwrap_or_default());
                // Masked writes compose with the last image asked for, not the last one sent:
                // two quick writes of different bits both hold.
                let image = (self.do_wanted & !mask) | (value & mask);
                self.do_wanted = image;
                self.engine_command(EngineCommand::SetDo(image));
            }
            LinkCommand::ReadDi => self.engine_command(EngineCommand::ReadDi),
            LinkCommand::ClearBuffer => self.engine_command(EngineCommand::ClearBuffer),
            LinkCommand::Jobs(reply) => {
                let _ = reply.send(LinkJobs {
                    active: self.active.as_ref().map(|a| a.id),
                    queued: self.queue.iter().map(|j| j.id).collect(),
                    recent_ends: self.recent_ends.iter().cloned().collect(),
                });
            }
        }
    }

    fn handle_source(&mut self, read: Read, want: usize) {
        let read = match read {
            Read::Bytes(r) => r,
            Read::Chunk(Some(chunk)) => return self.engine_command(chunk.command()),
            Read::Chunk(None) => Ok(0),
        };
        match read {
            Ok(0) if want > 0 => {
                if let Some(active) = self.active.as_mut() {
                    active.source = None;
                }
                self.engine_command(EngineCommand::ProgramEnd);
            }
            Ok(n) => {
                let data = Bytes::copy_from_slice(&self.buf[..n]);
                self.engine_command(EngineCommand::ProgramData(data));
            }
            Err(e) => {
                tracing::warn!(error = %e, "program source failed");
                if let Some(active) = self.active.as_mut() {
                    active.source = None;
                    active.cancelling = true;
                }
                self.engine_command(EngineCommand::Cancel);
                if let Some(active) = self.active.take() {
                    self.emit(LinkEvent::JobFailed {
                        job: active.id,
                        offset: active.acked,
                        sent: active.sent,
                        reason: JobFailure::Source(Arc::new(e)),
                    });
                }
            }
        }
    }

    fn start_next_job(&mut self) {
        if self.active.is_some() {
            return;
        }
        let Some(job) = self.queue.pop_front() else {
            return;
        };
        tracing::info!(job = job.id, name = %job.name, "program started");
        self.engine_command(EngineCommand::StartProgram { total: job.size });
        if matches!(job.source, JobSource::Chunks(_)) {
            self.engine_command(EngineCommand::Streaming);
        }
        self.emit(LinkEvent::JobStarted { job: job.id });
        self.active = Some(ActiveJob {
            id: job.id,
            size: job.size,
            source: Some(job.source),
            progress_interval: job.progress_interval.unwrap_or(PROGRESS_INTERVAL),
            sent: 0,
            acked: 0,
            last_progress: None,
            cancelling: false,
            fed: FedBlocks::new(),
        });
    }

    fn drain_engine_events(&mut self) {
        while let Some(event) = self.pump.engine_mut().poll_event() {
            self.on_engine_event(event);
        }
        let waiting = self.pump.engine().waiting_for();
        if waiting != self.waiting {
            self.waiting = waiting;
            self.emit(LinkEvent::Waiting {
                what: waiting,
                since_unix_ms: pb::now_ms(),
            });
        }
    }

    fn on_engine_event(&mut self, event: EngineEvent) {
        let event = match event {
            EngineEvent::State(state) => {
                self.state.send_replace(Some(state));
                self.on_state(state);
                LinkEvent::State { state }
            }
            EngineEvent::Status(status) => LinkEvent::Status { status },
            EngineEvent::Di(value) => LinkEvent::Di { value },
            EngineEvent::DoSent(value) => {
                self.do_image = value;
                LinkEvent::Do { value }
            }
            EngineEvent::CncReset => LinkEvent::CncReset,
            EngineEvent::CncAlarm => LinkEvent::CncAlarm,
            EngineEvent::Alarm(alarm) => {
                self.on_alarm(&alarm);
                if let LinkAlarm::TimeOut { waited } = &alarm {
                    // Silence past the protocol's time-out is how a half-open connection (a
                    // device server that lost power or was replaced) shows: make a new one. The
                    // engine has already re-initialised, so nothing in flight is lost by it.
                    let why = format!("no message from the board for {waited:?}");
                    self.pump.transport_mut().reconnect(&why);
                }
                LinkEvent::Alarm(alarm)
            }
            EngineEvent::ProtocolError { error, retried } => {
                self.on_protocol_error(&error, retried);
                LinkEvent::ProtocolError { error, retried }
            }
            EngineEvent::Punched { data } => LinkEvent::Punched { data },
            EngineEvent::PunchDamaged { cause } => LinkEvent::PunchDamaged { cause },
            EngineEvent::DataSent { data } => {
                let Some(active) = self.active.as_mut() else {
                    return;
                };
                active.sent += data.len() as u64;
                // The block finder reads what went out, not what the engine was given: it
                // holds no copy of the engine's unsent program.
                active.fed.push(&data);
                active.fed.sent(active.sent);
                match self.progress() {
                    Some(event) => event,
                    None => return,
                }
            }
            EngineEvent::Acked { offset } => {
                let Some(active) = self.active.as_mut() else {
                    return;
                };
                active.acked = active.acked.max(offset);
                match self.progress() {
                    Some(event) => event,
                    None => return,
                }
            }
            EngineEvent::ProgramDone { confirmation } => match self.active.take() {
                Some(mut active) => {
                    // The whole program is acknowledged: its length is what went out.
                    let bytes = active.sent.max(active.acked);
                    tracing::info!(job = active.id, bytes, ?confirmation, "program delivered");
                    LinkEvent::JobDone {
                        job: active.id,
                        bytes,
                        confirmation,
                        block: active.fed.acked(bytes),
                    }
                }
                None => return,
            },
            EngineEvent::ProgramAborted { reason, cancelled } => match self.active.take() {
                Some(active) if cancelled || active.cancelling => LinkEvent::JobCancelled {
                    job: active.id,
                    offset: active.acked,
                    sent: active.sent,
                },
                Some(active) => {
                    tracing::warn!(job = active.id, offset = active.acked, sent = active.sent, %reason, "program failed");
                    LinkEvent::JobFailed {
                        job: active.id,
                        offset: active.acked,
                        sent: active.sent,
                        reason: JobFailure::Aborted(reason),
                    }
                }
                None => return,
            },
        };
        self.emit(event);
    }

    /// A progress event when the acknowledged or the sent figure crossed a whole percent or,
    /// for programs of unknown size, when [`PROGRESS_INTERVAL`] has passed.
    fn progress(&mut self) -> Option<LinkEvent> {
        let active = self.active.as_mut()?;
        let t = now();
        let due = match (active.last_progress, active.size) {
            (None, _) => true,
            (Some((_, acked, sent)), Some(total)) if total > 0 => {
                let percent = |b: u64| u128::from(b) * 100 / u128::from(total);
                percent(active.acked) > percent(acked) || percent(active.sent) > percent(sent)
            }
            (Some((at, _, _)), _) => t.duration_since(at) >= active.progress_interval,
        };
        if !due {
            return None;
        }
        active.last_progress = Some((t, active.acked, active.sent));
        // Protocol B acknowledges only at its next control code: meanwhile the block is
        // read from what the line has carried (`HostEngine::carried`).
        let through = self
            .pump
            .engine()
            .carried(t)
            .map_or(active.acked, |c| c.max(active.acked));
        Some(LinkEvent::Progress {
            job: active.id,
            acked: active.acked,
            sent: active.sent,
            total: active.size,
            block: active.fed.acked(through),
        })
    }
}

/// What a job's source gave.
enum Read {
    /// Program text read into the buffer (0: the end).
    Bytes(std::io::Result<usize>),
    /// A chunk of a stream, or its end.
    Chunk(Option<Chunk>),
}

/// Reads into `buf` from `source` (which is present whenever `buf` is not empty).
async fn read_some(source: Option<&mut JobSource>, buf: &mut [u8]) -> Read {
    match source {
        Some(JobSource::Program(s)) => Read::Bytes(s.read(buf).await),
        Some(JobSource::Chunks(rx)) => Read::Chunk(rx.recv().await),
        None => std::future::pending().await,
    }
}

impl BusCode for LinkError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            LinkError::NotRunning { .. } => pb::ErrorCode::Unavailable,
            LinkError::Busy { .. } => pb::ErrorCode::Busy,
        }
    }
}

impl BusCode for JobFailure {
    fn code(&self) -> pb::ErrorCode {
        match self {
            JobFailure::Aborted(reason) => reason.code(),
            JobFailure::Source(_) | JobFailure::LinkStopped(_) => pb::ErrorCode::LinkFailed,
            JobFailure::Shutdown => pb::ErrorCode::Unavailable,
        }
    }
}
