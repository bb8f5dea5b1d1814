//! The PLC link task: a [`Master`] run by a [`Pump`] over any [`Transport`], the tag poll
//! groups on their intervals, and the requests of the bus. Thin: every protocol decision is
//! the master's, every tag decision the [`TagTable`]'s; this file only moves commands, bytes,
//! events and time between them. All time is `tokio::time`, so it runs in paused time.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use tokio::sync::{broadcast, mpsc, oneshot};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use crate::link::pump::{Pump, PumpError};
use crate::transport::Transport;
use cellgate_core::codes::BusCode;
use cellgate_core::engine::Engine;
use cellgate_core::fuji::command::{Reply, Request};
use cellgate_core::fuji::master::{
    Counters, Master, MasterCommand, MasterError, MasterEvent, RequestId,
};
use cellgate_core::pb;
use cellgate_core::plc::tags::{TagError, TagTable, TagValue, TagWrite, WriteOp};

/// Commands a PLC link holds waiting; [`PlcHandle`] refuses more (`Busy`).
pub const COMMAND_QUEUE: usize = 256;

/// The answer to a memory or transfer request.
pub type RequestResult = Result<Reply, MasterError>;

/// What the bus (or a test) asks of a PLC link.
#[derive(Debug)]
#[non_exhaustive]
pub enum PlcCommand {
    /// A command-set request to `station`; the module's reply (or the error) comes back.
    Request {
        station: u8,
        request: Request,
        reply: oneshot::Sender<RequestResult>,
    },
    /// Writes a tag (scale undone, range checked; a read-only tag is refused here).
    WriteTag {
        name: String,
        value: f64,
        reply: oneshot::Sender<Result<TagWrite, TagWriteError>>,
    },
    /// The latest value of a tag.
    GetTag {
        name: String,
        reply: oneshot::Sender<Result<TagValue, TagError>>,
    },
    /// Counters and tag values now.
    Snapshot { reply: oneshot::Sender<PlcSnapshot> },
    /// Modes 4–5: a message to the module (§5-5); done once it is on its way (nothing
    /// answers it).
    Send {
        data: Vec<u8>,
        reply: oneshot::Sender<RequestResult>,
    },
    /// New tags and poll groups (a reload): the rounds under way are dropped and each group
    /// of the new table starts at once; the values are read anew.
    SetTags {
        tags: TagTable,
        reply: oneshot::Sender<()>,
    },
}

/// Why a tag write failed.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum TagWriteError {
    #[error(transparent)]
    Tag(#[from] TagError),
    #[error("{0}")]
    Plc(#[from] MasterError),
}

/// What a PLC link reports.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub enum PlcEvent {
    /// A tag changed (value beyond its deadband, or quality).
    Tag(TagValue),
    /// A transfer the PLC sent (mode 1, §5-4 iv).
    Transfer {
        message: u8,
        data: Vec<u8>,
        time: SystemTime,
    },
    /// Modes 4–5: a message the PLC sent (§5-5 ii).
    Message { data: Vec<u8>, time: SystemTime },
    /// A station was marked down or answers again.
    Station { station: u8, up: bool },
    /// A poll group's reads all ended (`group` index, when its round started).
    PollDone { group: usize, started: Instant },
    /// The link task ended.
    Stopped { error: Option<Arc<PumpError>> },
}

/// How one poll group keeps its interval, as the link measured it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct GroupStats {
    /// The configured interval (the tags' `poll_ms`).
    pub interval: Duration,
    /// Read requests per round.
    pub reads: usize,
    /// Rounds completed.
    pub rounds: u64,
    /// The last round: from its first request to the end of its last read.
    pub last_round: Duration,
    /// The mean round since the link started.
    pub mean_round: Duration,
    /// The longest round since the link started.
    pub max_round: Duration,
    /// Between the starts of the last two rounds: the interval achieved.
    pub achieved_interval: Duration,
    /// Rounds that took longer than the interval (the next one started late).
    pub overruns: u64,
}

/// The link's state at one moment.
#[derive(Debug, Clone)]
pub struct PlcSnapshot {
    pub counters: Counters,
    pub tags: Vec<TagValue>,
    /// Each poll group's round times, in the tag table's group order.
    pub groups: Vec<GroupStats>,
    /// The transport, as it describes itself.
    pub line: String,
    /// Bytes received and sent on the line.
    pub bytes: (u64, u64),
}

/// Why a command could not be given to the link.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum PlcLinkError {
    #[error("PLC link {plc} is not running")]
    NotRunning { plc: String },
    #[error("PLC link {plc} has {max} commands waiting already; try again later")]
    Busy { plc: String, max: usize },
}

/// Talks to a running PLC link. Cheap to clone.
#[derive(Debug, Clone)]
pub struct PlcHandle {
    name: String,
    commands: mpsc::Sender<PlcCommand>,
    events: broadcast::Sender<PlcEvent>,
}

impl PlcHandle {
    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn subscribe(&self) -> broadcast::Receiver<PlcEvent> {
        self.events.subscribe()
    }

    fn send(&self, command: PlcCommand) -> Result<(), PlcLinkError> {
        self.commands.try_send(command).map_err(|e| match e {
            mpsc::error::TrySendError::Full(_) => PlcLinkError::Busy {
                plc: self.name.clone(),
                max: COMMAND_QUEUE,
            },
            mpsc::error::TrySendError::Closed(_) => self.not_running(),
        })
    }

    fn not_running(&self) -> PlcLinkError {
        PlcLinkError::NotRunning {
            plc: self.name.clone(),
        }
    }

    /// Sends a command-set request and waits for its end.
    pub async fn request(
        &self,
        station: u8,
        request: Request,
    ) -> Result<RequestResult, PlcLinkError> {
        let (tx, rx) = oneshot::channel();
        self.send(PlcCommand::Request {
            station,
            request,
            reply: tx,
        })?;
        rx.await.map_err(|_| self.not_running())
    }

    pub async fn write_tag(
        &self,
        name: &str,
        value: f64,
    ) -> Result<Result<TagWrite, TagWriteError>, PlcLinkError> {
        let (tx, rx) = oneshot::channel();
        self.send(PlcCommand::WriteTag {
            name: name.to_string(),
            value,
            reply: tx,
        })?;
        rx.await.map_err(|_| self.not_running())
    }

    pub async fn get_tag(&self, name: &str) -> Result<Result<TagValue, TagError>, PlcLinkError> {
        let (tx, rx) = oneshot::channel();
        self.send(PlcCommand::GetTag {
            name: name.to_string(),
            reply: tx,
        })?;
        rx.await.map_err(|_| self.not_running())
    }

    /// Modes 4–5: sends a message and waits until it is on its way.
    pub async fn send_message(&self, data: Vec<u8>) -> Result<RequestResult, PlcLinkError> {
        let (tx, rx) = oneshot::channel();
        self.send(PlcCommand::Send { data, reply: tx })?;
        rx.await.map_err(|_| self.not_running())
    }

    /// Swaps the link's tags and poll groups for `tags`, without touching its line.
    pub async fn set_tags(&self, tags: TagTable) -> Result<(), PlcLinkError> {
        let (tx, rx) = oneshot::channel();
        self.send(PlcCommand::SetTags { tags, reply: tx })?;
        rx.await.map_err(|_| self.not_running())
    }

    pub async fn snapshot(&self) -> Result<PlcSnapshot, PlcLinkError> {
        let (tx, rx) = oneshot::channel();
        self.send(PlcCommand::Snapshot { reply: tx })?;
        rx.await.map_err(|_| self.not_running())
    }
}

/// Starts the link task of PLC `name`. It ends when `shutdown` is cancelled, when every
/// handle is dropped, or when the transport closes for good.
pub fn spawn<T: Transport + 'static>(
    name: impl Into<String>,
    master: Master,
    tags: TagTable,
    transport: T,
    shutdown: CancellationToken,
) -> (
    PlcHandle,
    tokio::task::JoinHandle<Result<(), Arc<PumpError>>>,
) {
    let name = name.into();
    let (cmd_tx, cmd_rx) = mpsc::channel(COMMAND_QUEUE);
    let (ev_tx, _) = broadcast::channel(4096);
    let handle = PlcHandle {
        name: name.clone(),
        commands: cmd_tx,
        events: ev_tx.clone(),
    };
    let span = tracing::info_span!("plc", plc = %name, line = %transport.describe());
    let groups = group_states(&tags, Instant::now());
    let driver = Driver {
        pump: Pump::new(master, transport),
        commands: cmd_rx,
        events: ev_tx,
        tags,
        groups,
        pending: HashMap::new(),
        next_id: 1,
    };
    let task = tokio::spawn(tracing::Instrument::instrument(driver.run(shutdown), span));
    (handle, task)
}

/// Each poll group of `tags`, due at `start`.
fn group_states(tags: &TagTable, start: Instant) -> Vec<GroupState> {
    tags.groups()
        .iter()
        .map(|g| GroupState {
            due: start,
            started: start,
            last_start: None,
            after_write: None,
            extra: false,
            outstanding: 0,
            total: Duration::ZERO,
            stats: GroupStats {
                interval: g.interval,
                reads: g.reads.len(),
                ..GroupStats::default()
            },
        })
        .collect()
}

/// Who waits for a request's end.
enum Pending {
    Caller(oneshot::Sender<RequestResult>),
    Poll {
        group: usize,
        read: usize,
    },
    /// The word of a bit tag was read; the bit is changed and the word written back.
    BitRead {
        write: TagWrite,
        reply: oneshot::Sender<Result<TagWrite, TagWriteError>>,
    },
    TagWrite {
        write: TagWrite,
        reply: oneshot::Sender<Result<TagWrite, TagWriteError>>,
    },
}

struct GroupState {
    due: Instant,
    started: Instant,
    /// When the round before the current one started.
    last_start: Option<Instant>,
    /// A write asked for a read of what it wrote now: the round that was due at this time
    /// keeps its time, and that read is no poll.
    after_write: Option<Instant>,
    /// The round in flight reads what a write wrote: not counted as a poll.
    extra: bool,
    /// Reads of the current round not ended yet.
    outstanding: usize,
    /// Every completed round's time, added up (for the mean).
    total: Duration,
    stats: GroupStats,
}

impl GroupState {
    /// The round that started at `started` ended at `now`.
    fn round_done(&mut self, now: Instant) {
        let round = now.saturating_duration_since(self.started);
        let s = &mut self.stats;
        s.rounds += 1;
        s.last_round = round;
        s.max_round = s.max_round.max(round);
        self.total += round;
        s.mean_round = self.total / u32::try_from(s.rounds).unwrap_or(u32::MAX);
        if round > s.interval {
            s.overruns += 1;
        }
    }
}

struct Driver<T> {
    pump: Pump<Master, T>,
    commands: mpsc::Receiver<PlcCommand>,
    events: broadcast::Sender<PlcEvent>,
    tags: TagTable,
    groups: Vec<GroupState>,
    pending: HashMap<RequestId, Pending>,
    next_id: RequestId,
}

enum Wake {
    Shutdown,
    Command(Option<PlcCommand>),
    Poll,
    Pump(Result<(), PumpError>),
}

impl<T: Transport> Driver<T> {
    async fn run(mut self, shutdown: CancellationToken) -> Result<(), Arc<PumpError>> {
        let result = loop {
            self.drain();
            let due = self
                .groups
                .iter()
                .filter(|g| g.outstanding == 0)
                .map(|g| g.due)
                .min();
            let wake = tokio::select! {
                biased;
                () = shutdown.cancelled() => Wake::Shutdown,
                cmd = self.commands.recv() => Wake::Command(cmd),
                () = sleep_until(due) => Wake::Poll,
                r = self.pump.step() => Wake::Pump(r),
            };
            match wake {
                Wake::Shutdown | Wake::Command(None) => break Ok(()),
                Wake::Command(Some(cmd)) => self.command(cmd),
                Wake::Poll => self.poll_due(),
                Wake::Pump(Ok(())) => {}
                Wake::Pump(Err(e)) => break Err(Arc::new(e)),
            }
        };
        self.drain();
        let error = result.as_ref().err().cloned();
        if let Some(e) = &error {
            tracing::error!(error = %e, "PLC link stopped");
        }
        let _ = self.events.send(PlcEvent::Stopped { error });
        result
    }

    fn emit(&self, event: PlcEvent) {
        // No subscriber is not an error: nobody is watching this link right now.
        let _ = self.events.send(event);
    }

    fn submit(&mut self, station: u8, request: Request, pending: Pending) {
        let id = self.next_id;
        self.next_id += 1;
        self.pending.insert(id, pending);
        self.pump.command(MasterCommand::Request {
            id,
            station,
            request,
        });
    }

    fn command(&mut self, command: PlcCommand) {
        match command {
            PlcCommand::Request {
                station,
                request,
                reply,
            } => self.submit(station, request, Pending::Caller(reply)),
            PlcCommand::Send { data, reply } => {
                let id = self.next_id;
                self.next_id += 1;
                self.pending.insert(id, Pending::Caller(reply));
                self.pump.command(MasterCommand::Send { id, data });
            }
            PlcCommand::SetTags { tags, reply } => {
                // A read of the old table answers nothing now: its group numbers are gone.
                self.pending
                    .retain(|_, p| !matches!(p, Pending::Poll { .. }));
                self.groups = group_states(&tags, Instant::now());
                self.tags = tags;
                let _ = reply.send(());
            }
            PlcCommand::GetTag { name, reply } => {
                let _ = reply.send(self.tags.value(&name).cloned());
            }
            PlcCommand::Snapshot { reply } => {
                let _ = reply.send(PlcSnapshot {
                    counters: self.pump.engine().counters(),
                    tags: self.tags.values(),
                    groups: self.groups.iter().map(|g| g.stats.clone()).collect(),
                    line: self.pump.transport().describe(),
                    bytes: self.pump.counters(),
                });
            }
            PlcCommand::WriteTag { name, value, reply } => {
                let write = match self.tags.plan_write(&name, value) {
                    Ok(w) => w,
                    Err(e) => {
                        let _ = reply.send(Err(e.into()));
                        return;
                    }
                };
                match &write.op {
                    WriteOp::Words(words) => {
                        match Request::write_words(write.module, write.address, words) {
                            Ok(req) => {
                                let station = write.station;
                                self.submit(station, req, Pending::TagWrite { write, reply });
                            }
                            Err(e) => {
                                let _ = reply.send(Err(MasterError::from(e).into()));
                            }
                        }
                    }
                    WriteOp::Bit { .. } => {
                        match Request::read_words(write.module, write.address, 1) {
                            Ok(req) => {
                                let station = write.station;
                                self.submit(station, req, Pending::BitRead { write, reply });
                            }
                            Err(e) => {
                                let _ = reply.send(Err(MasterError::from(e).into()));
                            }
                        }
                    }
                }
            }
        }
    }

    /// Starts the round of every poll group that is due and not still reading.
    fn poll_due(&mut self) {
        let now = Instant::now();
        for g in 0..self.groups.len() {
            let state = &self.groups[g];
            if state.outstanding > 0 || state.due > now {
                continue;
            }
            let group = &self.tags.groups()[g];
            let interval = group.interval;
            let reads: Vec<_> = group
                .reads
                .iter()
                .map(|r| (r.station, r.module, r.address, r.words))
                .collect();
            let state = &mut self.groups[g];
            match state.after_write.take() {
                // The read a write asked for: the polls' times and schedule are untouched.
                Some(scheduled) => {
                    state.extra = true;
                    state.due = scheduled;
                }
                None => {
                    state.extra = false;
                    if let Some(prev) = state.last_start {
                        state.stats.achieved_interval = now.saturating_duration_since(prev);
                    }
                    state.last_start = Some(now);
                    // Fixed rate; a round that overran starts the next one at once, never in
                    // a burst.
                    state.due = (state.due + interval).max(now);
                }
            }
            state.started = now;
            state.outstanding = reads.len();
            for (read, (station, module, address, words)) in reads.into_iter().enumerate() {
                match Request::read_words(module, address, usize::from(words)) {
                    Ok(req) => self.submit(station, req, Pending::Poll { group: g, read }),
                    Err(e) => {
                        tracing::warn!(error = %e, "tag read cannot be sent");
                        self.read_done(g, read, None);
                    }
                }
            }
        }
    }

    fn read_done(&mut self, group: usize, read: usize, words: Option<&[u32]>) {
        for v in self.tags.apply_read(group, read, words, SystemTime::now()) {
            self.emit(PlcEvent::Tag(v));
        }
        if let Some(state) = self.groups.get_mut(group) {
            state.outstanding = state.outstanding.saturating_sub(1);
            if state.outstanding == 0 && !state.extra {
                state.round_done(Instant::now());
                let started = state.started;
                self.emit(PlcEvent::PollDone { group, started });
            }
        }
    }

    /// Hands on everything the master reported.
    fn drain(&mut self) {
        while let Some(event) = self.pump.engine_mut().poll_event() {
            match event {
                MasterEvent::Done { id, result, .. } => self.done(id, result),
                MasterEvent::Transfer { message, data } => self.emit(PlcEvent::Transfer {
                    message,
                    data,
                    time: SystemTime::now(),
                }),
                MasterEvent::Received { data } => self.emit(PlcEvent::Message {
                    data,
                    time: SystemTime::now(),
                }),
                MasterEvent::StationDown { station, .. } => {
                    for v in self.tags.station_down(station) {
                        self.emit(PlcEvent::Tag(v));
                    }
                    self.emit(PlcEvent::Station { station, up: false });
                }
                MasterEvent::StationUp { station } => {
                    self.emit(PlcEvent::Station { station, up: true })
                }
                other => tracing::debug!(?other, "PLC link event ignored"),
            }
        }
    }

    fn done(&mut self, id: RequestId, result: RequestResult) {
        let Some(pending) = self.pending.remove(&id) else {
            return;
        };
        match pending {
            Pending::Caller(reply) => {
                let _ = reply.send(result);
            }
            Pending::Poll { group, read } => match &result {
                Ok(Reply::Read { words, .. }) => self.read_done(group, read, Some(words)),
                _ => self.read_done(group, read, None),
            },
            Pending::BitRead { write, reply } => {
                let word = match result {
                    Ok(Reply::Read { words, .. }) => words.first().copied().unwrap_or(0),
                    Ok(_) => 0,
                    Err(e) => {
                        let _ = reply.send(Err(e.into()));
                        return;
                    }
                };
                let WriteOp::Bit { bit, on } = write.op else {
                    return;
                };
                let word = if on {
                    word | (1 << bit)
                } else {
                    word & !(1 << bit)
                };
                match Request::write_words(write.module, write.address, &[word]) {
                    Ok(req) => {
                        let station = write.station;
                        self.submit(station, req, Pending::TagWrite { write, reply });
                    }
                    Err(e) => {
                        let _ = reply.send(Err(MasterError::from(e).into()));
                    }
                }
            }
            Pending::TagWrite { write, reply } => {
                let ok = result.is_ok();
                if ok {
                    // Before the reply: a get that follows the confirmed write answers it.
                    if let Some(v) = self.tags.apply_written(&write, SystemTime::now()) {
                        self.emit(PlcEvent::Tag(v));
                    }
                }
                let _ = reply.send(result.map(|_| write).map_err(TagWriteError::from));
                if ok {
                    // Read the groups of what was written at once, so its new value is
                    // published without waiting for the next round; that read is no poll
                    // (the status reports polls only).
                    let now = Instant::now();
                    for g in &mut self.groups {
                        if g.due > now {
                            g.after_write.get_or_insert(g.due);
                            g.due = now;
                        }
                    }
                }
            }
        }
    }
}

async fn sleep_until(due: Option<Instant>) {
    match due {
        Some(t) => tokio::time::sleep_until(t).await,
        None => std::future::pending().await,
    }
}

impl BusCode for TagWriteError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            TagWriteError::Tag(e) => e.code(),
            TagWriteError::Plc(e) => e.code(),
        }
    }
    fn sta(&self) -> Option<u8> {
        match self {
            TagWriteError::Plc(e) => e.sta(),
            TagWriteError::Tag(_) => None,
        }
    }
}

impl BusCode for PlcLinkError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            PlcLinkError::NotRunning { .. } => pb::ErrorCode::Unavailable,
            PlcLinkError::Busy { .. } => pb::ErrorCode::Busy,
        }
    }
}
