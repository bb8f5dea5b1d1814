//! The job manager: one per machine. It keeps the machine's queue of programs, hands the link
//! one job at a time, and reports every step of every job as a [`pb::JobEvent`].
//!
//! - Queue: higher `priority` first, arrival order among equals ([`queue`]); at most
//!   [`MAX_WAITING`] jobs wait. The link gets [`LinkCommand::Queue`] only when it has no
//!   active job, so the order stays the gateway's to decide until the last moment, and a
//!   waiting job is cancelled by dropping it. An active job is cancelled with
//!   [`LinkCommand::Cancel`] and ends when the link confirms.
//! - Journal ([`journal`]): every job is written to the cell's journal before its submit is
//!   answered, with its program in the journal's store (inline and fetched programs written,
//!   library programs linked), and every step after. After a restart the waiting jobs run
//!   with their ids in their order, and the one that was being sent is failed with the offset
//!   the board acknowledged, or resumed where its request asked for that. A waiting job holds
//!   no file open: its program is opened when it starts.
//! - Sources ([`source`]): every program is checked before it is queued; a bad one is refused
//!   with the reason and nothing is queued.
//! - Idempotent submits: a request id seen before (among the jobs kept) answers the first
//!   `JobAccepted` and queues nothing.
//! - Blocks (`blocks`): a job may start at a block (by line or sequence number) with the
//!   program's header first; a failed or cancelled one names the first block the board did
//!   not acknowledge whole, where a resume (`resume_job`) starts.
//! - Punched programs (`punch`): a punch-out split into programs and decoded, library
//!   names for them, and remote requests for a program.
//! - Job ids: `<machine>-<run>-<n>`, where `<run>` is the time the manager started, in
//!   seconds since the Unix epoch written in base 36, and `<n>` counts the machine's jobs
//!   from 1. Unique in the cell as long as the clock does not run backwards across restarts;
//!   a valid key chunk, since machine names are `[A-Za-z0-9_-]+`.
//! - Offsets: every offset a job reports is what the board acknowledged (see
//!   `fanuc::host::Confirmation`); what was handed to the line is reported beside it.
//! - Progress: the link reports progress at every whole percent (or every 250 ms for a
//!   program of unknown size). Events are published at most every
//!   [`PROGRESS_MIN_INTERVAL`], and only once progress has reached a further whole percent
//!   (any further byte when the size is unknown), each with the rate since the previous one.
//!
//! The manager knows nothing of the bus: [`JobsHandle`] takes requests and hands out events,
//! and the bus routes put them on their keys. It runs in tokio time, so it is tested under
//! paused time with a stand-in link.

mod hold;
mod intake;
pub mod journal;
mod link_events;
mod progress;
pub mod queue;
pub mod source;

pub use self::hold::Hold;
pub use self::progress::ProgressShaper;

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use prost::Message;
use tokio::sync::{mpsc, oneshot, watch};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use crate::library::{LibraryError, ProgramLibrary};
use crate::link::driver::{JobSource, LinkCommand, LinkEvent, LinkHandle, ProgramJob};
use crate::link::{JobId, fanout};
use crate::telemetry::metrics::{self, MachineMetrics, Outcome};
use crate::telemetry::span_count;
use cellgate_core::config::Accept;
use cellgate_core::fanuc::alarm::CncAlarm;
use cellgate_core::fanuc::host::Confirmation;
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;
use cellgate_core::program::blocks::{Block, BlockError, StartAt};
use journal::{JobRecord, JobState, Journal, JournalError, StartPoint};
use queue::PriorityQueue;
use source::{ProgramError, ProgramInput, ProgramRules};

/// Most jobs waiting on one machine; one more is refused with `ERROR_CODE_QUEUE_FULL`.
pub const MAX_WAITING: usize = 256;

/// Job events kept for a subscriber that fell behind (the machine's bus task, followers):
/// room for a full queue's `queued` events at once, and more. Paid for only while they wait
/// ([`fanout`]); events travel as `Arc`s, so a waiting one is a pointer.
pub const JOB_EVENTS: usize = 1024;

/// Progress events of one job are at least this far apart.
pub const PROGRESS_MIN_INTERVAL: Duration = Duration::from_millis(250);

/// Ended jobs each machine keeps by default: their latest event, request id and program.
pub const KEEP_ENDED: usize = cellgate_core::config::DEFAULT_KEEP_JOBS;

/// Ended jobs per machine whose program copy stays in the journal's store, so that they can be
/// resumed; older ones keep their events and request ids but not their programs.
pub const RESUMABLE_COPIES: usize = 8;

/// Longest client request id.
pub const REQUEST_ID_MAX: usize = 128;

/// A request to send a program to the machine.
#[derive(Debug, Clone, Default)]
pub struct JobSubmission {
    pub input: ProgramInput,
    /// Display name; empty: derived from the source.
    pub name: String,
    /// Higher runs first.
    pub priority: i32,
    /// Append `%` to a program without EOR instead of refusing it.
    pub append_eor: bool,
    /// The client's request id (idempotency); empty: none.
    pub request_id: String,
    /// Start at a block, with this many header lines (0: up to the first numbered block).
    pub start_at: Option<(StartAt, u32)>,
    /// Resume from the first unacknowledged block if the gateway restarts while sending.
    pub resume_after_restart: bool,
    /// Seconds the job may take from its start; 0: no deadline.
    pub deadline_s: u32,
    /// With a library program: the revision (a number or a SHA-256); empty: the latest.
    pub revision: String,
    /// Who submitted it, as the client said.
    pub submitted_by: pb::RequestOrigin,
}

/// Why a job request or a cancellation was refused.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum JobError {
    #[error("machine {machine}: {error}")]
    Program {
        machine: String,
        #[source]
        error: ProgramError,
    },
    #[error("machine {machine}: {error}")]
    Library {
        machine: String,
        #[source]
        error: LibraryError,
    },
    #[error("machine {machine}: the queue is full ({max} jobs waiting); try again later")]
    QueueFull { machine: String, max: usize },
    #[error("machine {machine} has no job {job:?} waiting or running")]
    UnknownJob { machine: String, job: String },
    #[error("machine {machine}: its link has stopped; no job can be sent")]
    LinkStopped { machine: String },
    /// The machine is leaving the cell (a reload removed it).
    #[error("machine {machine} {why}")]
    Retired { machine: String, why: String },
    #[error("machine {machine}: the job manager has stopped (gateway shutting down)")]
    Stopped { machine: String },
    #[error("machine {machine}: the job could not be journalled, so it was not accepted: {error}")]
    Journal {
        machine: String,
        #[source]
        error: JournalError,
    },
    #[error("machine {machine}: request id of {len} characters; at most {REQUEST_ID_MAX} are kept")]
    RequestId { machine: String, len: usize },
    #[error("machine {machine}: cannot start at that block: {error}")]
    Start {
        machine: String,
        #[source]
        error: BlockError,
    },
    #[error(
        "machine {machine}: JobRequest.revision names a library revision, but the program does \
         not come from the library"
    )]
    RevisionWithoutLibrary { machine: String },
    /// The machine takes only released library revisions, and the program is not one.
    #[error(
        "machine {machine} takes only released library revisions (accept = \"released\"): \
         {what} cannot be sent to it; store it in the library and release it"
    )]
    OnlyReleased { machine: String, what: &'static str },
    #[error("machine {machine}: job {job} cannot be resumed: {why}")]
    NotResumable {
        machine: String,
        job: String,
        why: String,
    },
}

/// What a cancellation did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CancelOutcome {
    /// The job was waiting and is gone; its `cancelled` event is out.
    Dropped,
    /// The job is being sent; the link was asked to stop, and the job ends when it has.
    Cancelling,
}

/// A machine's jobs at a glance, for its status.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct JobsSnapshot {
    /// The job being sent.
    pub active: Option<String>,
    /// Jobs waiting.
    pub waiting: usize,
    /// NC bytes the board acknowledged over every job, as far as published in progress events.
    pub nc_bytes_sent: u64,
    pub jobs_completed: u64,
    pub jobs_failed: u64,
}

/// Talks to a machine's job manager. Cheap to clone.
#[derive(Debug, Clone)]
pub struct JobsHandle {
    machine: Arc<str>,
    rules: ProgramRules,
    accept: Accept,
    library: ProgramLibrary,
    journal: Journal,
    requests: mpsc::Sender<Request>,
    events: fanout::Sender<Arc<pb::JobEvent>>,
    snapshot: watch::Receiver<JobsSnapshot>,
    /// The latest event of each job kept when the manager started, oldest first.
    restored: Arc<Vec<pb::JobEvent>>,
}

enum Request {
    Submit {
        record: Box<JobRecord>,
        reply: oneshot::Sender<Result<pb::JobAccepted, JobError>>,
    },
    Cancel {
        id: String,
        reply: oneshot::Sender<Result<CancelOutcome, JobError>>,
    },
    List {
        reply: oneshot::Sender<pb::JobQueue>,
    },
    /// A reload holds the jobs (`hold`), or lets them go again.
    Hold {
        hold: Hold,
        reply: oneshot::Sender<()>,
    },
    Release {
        reply: oneshot::Sender<()>,
    },
    /// The record of a job kept, for a resume.
    Find {
        id: String,
        reply: oneshot::Sender<Option<JobRecord>>,
    },
}

impl JobsHandle {
    pub fn machine(&self) -> &str {
        &self.machine
    }

    pub fn rules(&self) -> ProgramRules {
        self.rules
    }

    /// Which library revisions the machine takes.
    pub fn accept(&self) -> Accept {
        self.accept
    }

    /// The program library the machine's jobs read from.
    pub fn library(&self) -> &ProgramLibrary {
        &self.library
    }

    /// The cell's journal.
    pub fn journal(&self) -> &Journal {
        &self.journal
    }

    /// The latest event of each job the journal held when the manager started.
    pub fn restored_events(&self) -> &[pb::JobEvent] {
        &self.restored
    }

    fn stopped(&self) -> JobError {
        JobError::Stopped {
            machine: self.machine.to_string(),
        }
    }

    fn program_error(&self, error: ProgramError) -> JobError {
        JobError::Program {
            machine: self.machine.to_string(),
            error,
        }
    }

    fn journal_error(&self, error: JournalError) -> JobError {
        JobError::Journal {
            machine: self.machine.to_string(),
            error,
        }
    }

    /// Cancels a waiting or active job.
    pub async fn cancel(&self, id: &str) -> Result<CancelOutcome, JobError> {
        let (reply, answer) = oneshot::channel();
        self.requests
            .send(Request::Cancel {
                id: id.to_string(),
                reply,
            })
            .await
            .map_err(|_| self.stopped())?;
        answer.await.map_err(|_| self.stopped())?
    }

    /// The active job and the waiting ones, in run order.
    pub async fn queue(&self) -> Result<pb::JobQueue, JobError> {
        let (reply, answer) = oneshot::channel();
        self.requests
            .send(Request::List { reply })
            .await
            .map_err(|_| self.stopped())?;
        answer.await.map_err(|_| self.stopped())
    }

    /// Job events from now on.
    pub fn subscribe(&self) -> fanout::Receiver<Arc<pb::JobEvent>> {
        self.events.subscribe()
    }

    /// The machine's jobs at a glance; changes whenever a job is queued, starts, makes
    /// published progress or ends.
    pub fn snapshot(&self) -> watch::Receiver<JobsSnapshot> {
        self.snapshot.clone()
    }
}

/// How a machine's job manager is set up.
#[derive(Debug, Clone)]
pub struct JobsSettings {
    pub rules: ProgramRules,
    pub library: ProgramLibrary,
    pub journal: Journal,
    /// The jobs of this machine the journal held at start, in arrival order.
    pub restored: Vec<JobRecord>,
    /// Ended jobs kept.
    pub keep: usize,
    /// Which library revisions the machine takes.
    pub accept: Accept,
}

/// Starts the job manager of `machine`, which feeds `link`. It ends when `shutdown` is
/// cancelled or every handle is dropped. Jobs then stay in the journal as they are: the
/// waiting ones run after a restart, and the active one is failed or resumed then. Returns
/// a receiver of the job events subscribed before the manager runs, so that the events of
/// a restart (a job failed or resumed) are not missed.
pub fn spawn(
    machine: &str,
    settings: JobsSettings,
    link: LinkHandle,
    shutdown: CancellationToken,
) -> (
    JobsHandle,
    tokio::task::JoinHandle<()>,
    fanout::Receiver<Arc<pb::JobEvent>>,
) {
    let (req_tx, req_rx) = mpsc::channel(64);
    let (ev_tx, first_rx) = fanout::channel(JOB_EVENTS);
    let (snap_tx, snap_rx) = watch::channel(JobsSnapshot::default());
    let name: Arc<str> = Arc::from(machine);
    let restored_events = settings
        .restored
        .iter()
        .filter_map(|r| pb::JobEvent::decode(r.last_event.as_slice()).ok())
        .filter(|e| e.kind.is_some())
        .collect();
    let handle = JobsHandle {
        machine: name.clone(),
        rules: settings.rules,
        accept: settings.accept,
        library: settings.library.clone(),
        journal: settings.journal.clone(),
        requests: req_tx,
        events: ev_tx.clone(),
        snapshot: snap_rx,
        restored: Arc::new(restored_events),
    };
    // Subscribed before the task runs, so no link event is missed.
    let link_events = link.subscribe();
    let run_stamp = hold::base36(
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_secs()),
    );
    let manager = Manager {
        machine: name.clone(),
        run_stamp,
        next: 1,
        next_link: 1,
        link,
        link_stopped: false,
        waiting: PriorityQueue::new(),
        active: None,
        ended: VecDeque::new(),
        request_ids: HashMap::new(),
        journal: settings.journal,
        keep: settings.keep,
        events: ev_tx,
        snapshot: snap_tx,
        totals: JobsSnapshot::default(),
        link_waiting: None,
        held: false,
        retired: None,
        metrics: metrics::machine(&name),
        traces: HashMap::new(),
    };
    let span = tracing::info_span!("jobs", machine = %name);
    let task = tokio::spawn(tracing::Instrument::instrument(
        manager.run(settings.restored, req_rx, link_events, shutdown),
        span,
    ));
    (handle, task, first_rx)
}

struct Active {
    record: JobRecord,
    link_id: JobId,
    handed_at: Instant,
    started_at: Option<Instant>,
    /// Program bytes the board acknowledged, and handed to the line.
    acked: u64,
    sent: u64,
    /// The last block the board acknowledged whole, as the link last said, and as the last
    /// published progress said.
    block: Option<Arc<str>>,
    published_block: Option<Arc<str>>,
    shaper: ProgressShaper,
    cancel_requested: bool,
    /// The link alarm (with its CNC number) seen while this job ran.
    alarm: Option<CncAlarm>,
    cnc_reset: bool,
    /// When the job's deadline passes (from its start), and whether it has.
    deadline: Option<Instant>,
    deadline_passed: bool,
}

struct Manager {
    machine: Arc<str>,
    run_stamp: String,
    /// The number of the next job id of this run.
    next: u64,
    /// The next link job id.
    next_link: JobId,
    link: LinkHandle,
    link_stopped: bool,
    waiting: PriorityQueue<JobRecord>,
    active: Option<Active>,
    /// Ended jobs kept, oldest first.
    ended: VecDeque<JobRecord>,
    /// Request ids of the jobs kept, to their job ids.
    request_ids: HashMap<String, String>,
    journal: Journal,
    keep: usize,
    events: fanout::Sender<Arc<pb::JobEvent>>,
    snapshot: watch::Sender<JobsSnapshot>,
    totals: JobsSnapshot,
    /// What the link waits for from the board, and since when (Unix ms).
    link_waiting: Option<(&'static str, u64)>,
    metrics: Arc<MachineMetrics>,
    /// The span of every job not ended yet, by job id.
    traces: HashMap<String, JobTrace>,
    /// A reload holds the jobs: no job is handed to the link ([`hold`]).
    held: bool,
    /// Why new jobs are refused: the machine is leaving the cell.
    retired: Option<String>,
}

/// A job's span, from queued to ended, and when it started on the link.
struct JobTrace {
    span: tracing::Span,
    started_at: Option<Instant>,
}

/// How a job ended, as the manager records it.
enum End {
    Completed {
        bytes: u64,
        duration_ms: u64,
        confirmation: Confirmation,
        /// Bytes of the program past its EOR, which the board was never sent.
        after_eor: u64,
    },
    Failed {
        reason: String,
        alarm: Option<CncAlarm>,
        code: pb::ErrorCode,
    },
    Cancelled {
        by: &'static str,
    },
}

impl Manager {
    async fn run(
        mut self,
        restored: Vec<JobRecord>,
        mut requests: mpsc::Receiver<Request>,
        mut link_events: fanout::Receiver<LinkEvent>,
        shutdown: CancellationToken,
    ) {
        self.restore(restored).await;
        loop {
            self.hand_next().await;
            self.publish_snapshot();
            let deadline = self
                .active
                .as_ref()
                .filter(|a| !a.deadline_passed)
                .and_then(|a| a.deadline);
            tokio::select! {
                biased;
                () = shutdown.cancelled() => break,
                () = sleep_until_some(deadline) => self.deadline_passed().await,
                request = requests.recv() => match request {
                    Some(r) => self.on_request(r).await,
                    None => break,
                },
                event = link_events.recv() => match event {
                    Ok(e) => self.on_link_event(e).await,
                    Err(fanout::RecvError::Lagged(n)) => {
                        // Only a stalled manager lags; a job's end may have been lost.
                        tracing::error!(missed = n, "job manager fell behind the link's events; asking the link where its jobs stand");
                        self.resync().await;
                    }
                    // Cannot happen while this manager holds the link handle.
                    Err(fanout::RecvError::Closed) => break,
                },
            }
        }
        self.shut_down().await;
    }

    /// Takes the machine's jobs from the journal: ended ones are kept, waiting ones queued
    /// in their order, and the one that was being sent when the gateway stopped is failed
    /// ("gateway restarted") at what the board acknowledged, or queued first to resume.
    async fn restore(&mut self, restored: Vec<JobRecord>) {
        let mut resume = Vec::new();
        let mut waiting = Vec::new();
        for mut record in restored {
            match record.state {
                JobState::Ended => {
                    self.remember_request(&record);
                    self.ended.push_back(record);
                }
                JobState::Waiting => waiting.push(record),
                JobState::Active => {
                    let next = self.next_block(&record, record.acked).await;
                    if record.resume_after_restart
                        && let Some(block) = &next
                    {
                        tracing::info!(job = %record.id, line = block.line, "resuming the job that was active at the restart");
                        record.start = Some(StartPoint {
                            header_end: self.header_end(&record, block).await,
                            body_start: block.offset,
                        });
                        record.acked = 0;
                        record.state = JobState::Waiting;
                        resume.push(record);
                    } else {
                        let offset = record.acked;
                        let end = End::Failed {
                            reason: "gateway restarted while the job was being sent".to_string(),
                            alarm: None,
                            code: pb::ErrorCode::Unavailable,
                        };
                        self.totals.jobs_failed += 1;
                        // Its request id still names it: the same request sent again after
                        // the restart answers this job, not a new one.
                        self.remember_request(&record);
                        self.end(record, end, offset, offset, next);
                    }
                }
            }
        }
        for record in resume.into_iter().chain(waiting) {
            self.remember_request(&record);
            self.open_trace(&record, "journal");
            tracing::info!(job = %record.id, "job restored from the journal");
            self.journal_put(&record);
            self.waiting.push(record.priority, record);
        }
        self.trim();
    }

    /// The header of a job resumed at `block`: the program's lines before its first numbered
    /// block, as a new request would have it.
    async fn header_end(&self, record: &JobRecord, block: &Block) -> u64 {
        let Ok(program) = self.open_program(record).await else {
            return 0;
        };
        source::find_start(program, StartAt::Line(block.line), 0)
            .await
            .map_or(0, |(header, _)| header)
    }

    async fn open_program(
        &self,
        record: &JobRecord,
    ) -> std::io::Result<impl tokio::io::AsyncRead + Unpin + use<>> {
        source::open_program(&self.journal.file_path(&record.file), &record.suffix).await
    }

    /// Where the active job resumes, having ended at `acked` with `sent` on the line: none
    /// for a job of which nothing went to the board (the CNC never asked for it), which a
    /// resume would only send whole again.
    async fn resume_point(&self, active: &Active, acked: u64, sent: u64) -> Option<Block> {
        if sent == 0 {
            return None;
        }
        self.next_block(&active.record, acked).await
    }

    /// The first block the board does not hold whole once it acknowledged `acked` bytes of
    /// what the job sent.
    async fn next_block(&self, record: &JobRecord, acked: u64) -> Option<Block> {
        let offset = record.program_offset(acked);
        let program = self.open_program(record).await.ok()?;
        match source::block_at(program, offset).await {
            Ok(block) => block,
            Err(e) => {
                tracing::warn!(job = %record.id, error = %e, "where the job stopped is not known");
                None
            }
        }
    }

    fn remember_request(&mut self, record: &JobRecord) {
        if !record.request_id.is_empty() {
            self.request_ids
                .insert(record.request_id.clone(), record.id.clone());
        }
    }

    /// Writes a record; a journal that fails is logged, the job goes on (it is accepted).
    fn journal_put(&self, record: &JobRecord) {
        if let Err(e) = self.journal.put_job(record) {
            tracing::error!(job = %record.id, error = %e, "job journal write failed");
        }
    }

    /// Forgets the oldest ended jobs past the limit, with their programs.
    /// Keeps the program copies of only the [`RESUMABLE_COPIES`] latest ended jobs: an ended
    /// job's copy serves nothing but a resume (`JobRequest.resume_job`), and the journal's store
    /// must not grow with every failed or cancelled job it keeps.
    fn drop_old_copies(&mut self) {
        let mut kept = 0;
        for r in self.ended.iter().rev() {
            let path = self.journal.file_path(&r.file);
            if !path.exists() {
                continue;
            }
            kept += 1;
            if kept > RESUMABLE_COPIES {
                let _ = std::fs::remove_file(path);
            }
        }
    }

    fn trim(&mut self) {
        let mut gone = Vec::new();
        while self.ended.len() > self.keep {
            if let Some(r) = self.ended.pop_front() {
                if !r.request_id.is_empty() {
                    self.request_ids.remove(&r.request_id);
                }
                gone.push(r);
            }
        }
        if let Err(e) = self.journal.remove_jobs(&gone) {
            tracing::warn!(error = %e, "forgetting old jobs in the journal failed");
        }
    }

    /// The active job stays in the journal as it is (state active, its acknowledged offset),
    /// and so do the waiting ones: a restart fails or resumes the first and runs the others.
    async fn shut_down(&mut self) {
        if let Some(active) = self.active.take() {
            // Best effort: the link may already be stopping with the gateway.
            let cancel = self.link.send(LinkCommand::Cancel(active.link_id));
            let _ = tokio::time::timeout(Duration::from_millis(100), cancel).await;
            let mut record = active.record;
            record.acked = active.acked;
            self.journal_put(&record);
            tracing::info!(job = %record.id, acked = record.acked, "job interrupted by the shutdown; kept in the journal");
        }
        // The spans of jobs not ended close here; the jobs themselves go on after a restart.
        for (_, trace) in self.traces.drain() {
            tracing::info!(parent: &trace.span, "gateway stopped; the job stays in the journal");
        }
        self.publish_snapshot();
    }

    /// Opens a job's span: its own trace, from queued (`how`: a request, the journal) to
    /// ended. Machine, id, name and size now; outcome and bytes when it ends.
    fn open_trace(&mut self, record: &JobRecord, how: &'static str) -> &tracing::Span {
        let span = tracing::info_span!(
            parent: None,
            "job",
            machine = %self.machine,
            job.id = %record.id,
            job.name = %record.name,
            job.bytes = span_count(record.stream_size()),
            job.priority = record.priority,
            job.outcome = tracing::field::Empty,
            job.bytes_acked = tracing::field::Empty,
            job.bytes_on_line = tracing::field::Empty,
            job.error = tracing::field::Empty,
            otel.status_code = tracing::field::Empty,
        );
        tracing::info!(parent: &span, how, "queued");
        let trace = self.traces.entry(record.id.clone()).or_insert(JobTrace {
            span,
            started_at: None,
        });
        &trace.span
    }

    /// The job is on the link now.
    fn trace_started(&mut self, id: &str) {
        if let Some(trace) = self.traces.get_mut(id) {
            trace.started_at = Some(Instant::now());
            tracing::info!(parent: &trace.span, "started");
        }
    }

    /// Closes the job's span with its outcome, and counts the job.
    fn trace_end(&mut self, record: &JobRecord, kind: &Kind, acked: u64, sent: u64) {
        let (outcome, error) = match kind {
            Kind::Completed(_) => (Outcome::Completed, None),
            Kind::Failed(f) => (Outcome::Failed, Some(f.reason.as_str())),
            _ => (Outcome::Cancelled, None),
        };
        // A job ended as the journal is read never had a span: it gets a short one.
        if !self.traces.contains_key(&record.id) {
            self.open_trace(record, "journal");
        }
        let Some(trace) = self.traces.remove(&record.id) else {
            return;
        };
        let span = trace.span;
        span.record("job.outcome", outcome.as_str());
        span.record("job.bytes_acked", span_count(acked));
        span.record("job.bytes_on_line", span_count(sent));
        if let Some(error) = error {
            span.record("job.error", error);
            span.record("otel.status_code", "ERROR");
        }
        tracing::info!(parent: &span, outcome = outcome.as_str(), acked = span_count(acked), "ended");
        let sending = trace
            .started_at
            .map(|at| Instant::now().saturating_duration_since(at));
        self.metrics.job_ended(outcome, sending);
    }

    fn emit(&self, id: &str, kind: Kind, origin: Option<pb::JobOrigin>) -> pb::JobEvent {
        let event = pb::JobEvent {
            job_id: id.to_string(),
            machine: self.machine.to_string(),
            unix_ms: pb::now_ms(),
            origin,
            kind: Some(kind),
        };
        // No subscriber is not an error: nobody is watching this machine's jobs right now.
        let _ = self.events.send(Arc::new(event.clone()));
        event
    }

    /// Ends a job: its last event out, the record ended in the journal with it.
    fn end(&mut self, mut record: JobRecord, end: End, acked: u64, sent: u64, next: Option<Block>) {
        let next_block = next.as_ref().map(Block::to_pb);
        let kind = match end {
            End::Completed {
                bytes,
                duration_ms,
                confirmation,
                after_eor,
            } => Kind::Completed(pb::job_event::Completed {
                bytes_sent: bytes,
                bytes_after_eor: after_eor,
                duration_ms,
                confirmation: confirmation_pb(confirmation) as i32,
            }),
            End::Failed {
                reason,
                alarm,
                code,
            } => Kind::Failed(pb::job_event::Failed {
                reason,
                byte_offset: acked,
                alarm_number: alarm.map(|a| a.number().to_string()).unwrap_or_default(),
                code: code as i32,
                bytes_on_line: sent,
                next_block,
            }),
            End::Cancelled { by } => Kind::Cancelled(pb::job_event::Cancelled {
                byte_offset: acked,
                by: by.to_string(),
                bytes_on_line: sent,
                next_block,
            }),
        };
        self.trace_end(&record, &kind, acked, sent);
        let event = self.emit(&record.id, kind, Some(record.origin_pb()));
        record.state = JobState::Ended;
        record.acked = acked;
        record.last_event = event.encode_to_vec();
        self.journal_put(&record);
        if matches!(event.kind, Some(Kind::Completed(_))) {
            // A completed job is never resumed: its program copy can go now.
            let _ = std::fs::remove_file(self.journal.file_path(&record.file));
        }
        self.ended.push_back(record);
        self.drop_old_copies();
        self.trim();
    }

    fn publish_snapshot(&mut self) {
        self.metrics.set_queue_depth(self.waiting.len());
        let active = self.active.as_ref().map(|a| a.record.id.as_str());
        let waiting = self.waiting.len();
        // Compared before anything is built (the manager asks after every event it takes);
        // the counters with the other fields blanked, so nothing is allocated to compare them.
        self.snapshot.send_if_modified(|old| {
            let counters = |s: &JobsSnapshot| JobsSnapshot {
                active: None,
                waiting: 0,
                ..*s
            };
            let same = old.active.as_deref() == active
                && old.waiting == waiting
                && counters(old) == counters(&self.totals);
            if !same {
                *old = JobsSnapshot {
                    active: active.map(str::to_owned),
                    waiting,
                    ..self.totals.clone()
                };
            }
            !same
        });
    }

    async fn on_request(&mut self, request: Request) {
        match request {
            Request::Submit { record, reply } => {
                let _ = reply.send(match self.retired_error() {
                    Some(e) => Err(e),
                    None => self.accept(*record),
                });
            }
            Request::Hold { hold, reply } => {
                self.on_hold(hold).await;
                let _ = reply.send(());
            }
            Request::Release { reply } => {
                self.on_release();
                let _ = reply.send(());
            }
            Request::Cancel { id, reply } => {
                let outcome = self.cancel(&id).await;
                let _ = reply.send(outcome);
            }
            Request::List { reply } => {
                let _ = reply.send(self.list());
            }
            Request::Find { id, reply } => {
                let found = self
                    .ended
                    .iter()
                    .chain(self.waiting.iter())
                    .chain(self.active.as_ref().map(|a| &a.record))
                    .find(|r| r.id == id)
                    .cloned();
                let _ = reply.send(found);
            }
        }
    }

    /// Queues a staged job, journalled first; or, for a request id seen before, answers the
    /// first job's acceptance and queues nothing.
    fn accept(&mut self, mut record: JobRecord) -> Result<pb::JobAccepted, JobError> {
        if let Some(id) = self.request_ids.get(&record.request_id) {
            tracing::info!(job = %id, request_id = %record.request_id, "request id seen before: nothing queued");
            let position = self.position_of(id).unwrap_or(0);
            // Only the first request's program is kept.
            let _ = std::fs::remove_file(self.journal.file_path(&record.file));
            let program = self
                .ended
                .iter()
                .chain(self.waiting.iter())
                .chain(self.active.as_ref().map(|a| &a.record))
                .find(|r| &r.id == id)
                .and_then(|r| r.origin_pb().program);
            return Ok(pb::JobAccepted {
                job_id: id.clone(),
                queue_position: position,
                program,
            });
        }
        if self.link_stopped {
            return Err(JobError::LinkStopped {
                machine: self.machine.to_string(),
            });
        }
        if self.waiting.len() >= MAX_WAITING {
            return Err(JobError::QueueFull {
                machine: self.machine.to_string(),
                max: MAX_WAITING,
            });
        }
        // A restart within the same second gives the same run stamp: skip the ids the journal
        // brought back, so an id never names two jobs.
        loop {
            record.id = format!("{}-{}-{}", self.machine, self.run_stamp, self.next);
            self.next += 1;
            if !self.id_known(&record.id) {
                break;
            }
        }
        let position = u32::try_from(self.waiting.len() + usize::from(self.active.is_some()))
            .unwrap_or(u32::MAX);
        let queued = pb::JobEvent {
            job_id: record.id.clone(),
            machine: self.machine.to_string(),
            unix_ms: pb::now_ms(),
            origin: Some(record.origin_pb()),
            kind: Some(Kind::Queued(pb::job_event::Queued {
                queue_position: position,
                bytes_total: Some(record.stream_size()),
            })),
        };
        record.last_event = queued.encode_to_vec();
        // Journalled before it is answered: an accepted job survives a crash.
        self.journal
            .put_job(&record)
            .map_err(|error| JobError::Journal {
                machine: self.machine.to_string(),
                error,
            })?;
        let id = record.id.clone();
        let program = record.origin_pb().program;
        self.remember_request(&record);
        self.open_trace(&record, "request");
        tracing::info!(job = %id, name = %record.name, size = record.stream_size(), priority = record.priority, "job queued");
        let size = record.stream_size();
        let position =
            u32::try_from(self.waiting.push(record.priority, record)).unwrap_or(u32::MAX);
        let _ = self.events.send(Arc::new(pb::JobEvent {
            kind: Some(Kind::Queued(pb::job_event::Queued {
                queue_position: position,
                bytes_total: Some(size),
            })),
            ..queued
        }));
        Ok(pb::JobAccepted {
            job_id: id,
            queue_position: position,
            program,
        })
    }

    /// Whether `id` names a job this machine holds: waiting, active or ended.
    fn id_known(&self, id: &str) -> bool {
        self.position_of(id).is_some() || self.ended.iter().any(|r| r.id == id)
    }

    /// Where job `id` stands: 0 for the active one, else its place among the waiting.
    fn position_of(&self, id: &str) -> Option<u32> {
        if self.active.as_ref().is_some_and(|a| a.record.id == id) {
            return Some(0);
        }
        self.waiting
            .iter()
            .position(|r| r.id == id)
            .map(|i| u32::try_from(i + usize::from(self.active.is_some())).unwrap_or(u32::MAX))
    }

    async fn cancel(&mut self, id: &str) -> Result<CancelOutcome, JobError> {
        if let Some(job) = self.waiting.remove_first(|j| j.id == id) {
            tracing::info!(job = %id, "waiting job cancelled");
            self.end(job, End::Cancelled { by: "request" }, 0, 0, None);
            return Ok(CancelOutcome::Dropped);
        }
        let Some(active) = self.active.as_mut().filter(|a| a.record.id == id) else {
            return Err(JobError::UnknownJob {
                machine: self.machine.to_string(),
                job: id.to_string(),
            });
        };
        if !active.cancel_requested {
            active.cancel_requested = true;
            let link_id = active.link_id;
            tracing::info!(job = %id, "cancelling the active job");
            if self.link.send(LinkCommand::Cancel(link_id)).await.is_err() {
                self.link_gone("the link is not running").await;
            }
        }
        Ok(CancelOutcome::Cancelling)
    }

    fn list(&self) -> pb::JobQueue {
        let queued = |r: &JobRecord, sent: u64| pb::QueuedJob {
            job_id: r.id.clone(),
            name: r.name.clone(),
            priority: r.priority,
            bytes_total: r.stream_size(),
            bytes_sent: sent,
            accepted_unix_ms: r.accepted_unix_ms,
        };
        pb::JobQueue {
            machine: self.machine.to_string(),
            active: self.active.as_ref().map(|a| queued(&a.record, a.acked)),
            waiting: self.waiting.iter().map(|r| queued(r, 0)).collect(),
        }
    }

    /// Gives the link the next job when it has none. Its program is opened now.
    async fn hand_next(&mut self) {
        while self.active.is_none() && !self.link_stopped && !self.held {
            let Some(mut record) = self.waiting.pop() else {
                return;
            };
            let source = source::open_stream(
                &self.journal.file_path(&record.file),
                &record.suffix,
                record.start,
            )
            .await;
            let source = match source {
                Ok(s) => s,
                Err(e) => {
                    tracing::error!(job = %record.id, error = %e, "the job's program cannot be read");
                    self.totals.jobs_failed += 1;
                    let end = End::Failed {
                        reason: format!("the job's program in the journal cannot be read: {e}"),
                        alarm: None,
                        code: pb::ErrorCode::Internal,
                    };
                    self.end(record, end, 0, 0, None);
                    continue;
                }
            };
            let now = Instant::now();
            let size = record.stream_size();
            record.state = JobState::Active;
            record.acked = 0;
            self.journal_put(&record);
            let link_id = self.next_link;
            self.next_link += 1;
            let command = LinkCommand::Queue(ProgramJob {
                id: link_id,
                name: record.name.clone(),
                size: Some(size),
                source: JobSource::Program(source),
                progress_interval: None,
            });
            self.active = Some(Active {
                record,
                link_id,
                handed_at: now,
                started_at: None,
                acked: 0,
                sent: 0,
                block: None,
                published_block: None,
                shaper: ProgressShaper::new(now, Some(size)),
                cancel_requested: false,
                alarm: None,
                cnc_reset: false,
                deadline: None,
                deadline_passed: false,
            });
            if self.link.send(command).await.is_err() {
                self.link_gone("the link is not running").await;
            }
        }
    }

    /// The active job's deadline passed: it is stopped on the link, and fails when the link
    /// reports it stopped, at what the board acknowledged.
    async fn deadline_passed(&mut self) {
        let Some(active) = self.active.as_mut() else {
            return;
        };
        active.deadline_passed = true;
        tracing::warn!(
            job = %active.record.id,
            deadline_s = active.record.deadline_s,
            waiting_for = self.link_waiting.map(|(w, _)| w),
            "job deadline passed; stopping it"
        );
        let link_id = active.link_id;
        if self.link.send(LinkCommand::Cancel(link_id)).await.is_err() {
            self.link_gone("the link is not running").await;
        }
    }

    /// Why a job whose deadline passed failed: the deadline, and what the link waited for.
    fn deadline_reason(&self, deadline_s: u32) -> String {
        let mut why = format!("the job did not complete within its deadline of {deadline_s} s");
        if let Some((what, since)) = self.link_waiting {
            let secs = pb::now_ms().saturating_sub(since) / 1000;
            why.push_str(&format!("; the link was waiting {secs} s for {what}"));
        }
        why
    }

    /// The link stopped for good: the active job fails, the waiting ones cannot run.
    async fn link_gone(&mut self, why: &str) {
        self.link_stopped = true;
        tracing::warn!(reason = why, "link stopped; failing its jobs");
        let failed = |why: &str| End::Failed {
            reason: format!("{why}; the job cannot continue"),
            alarm: None,
            code: pb::ErrorCode::Unavailable,
        };
        if let Some(active) = self.active.take() {
            let next = self.next_block(&active.record, active.acked).await;
            self.totals.jobs_failed += 1;
            self.end(active.record, failed(why), active.acked, active.sent, next);
        }
        for record in self.waiting.drain() {
            self.totals.jobs_failed += 1;
            self.end(record, failed(why), 0, 0, None);
        }
    }

    /// After missed link events: the active job's end, if the link has one for it, is taken
    /// as if it had come; a job the link no longer holds and has no end for is failed (its end
    /// was lost with the events), never left active forever.
    async fn resync(&mut self) {
        let Some(link_id) = self.active.as_ref().map(|a| a.link_id) else {
            return;
        };
        let (reply, answer) = oneshot::channel();
        if self.link.send(LinkCommand::Jobs(reply)).await.is_err() {
            return self.link_gone("the link stopped").await;
        }
        let Ok(jobs) = answer.await else {
            return self.link_gone("the link stopped").await;
        };
        let end = jobs.recent_ends.into_iter().find(|e| {
            matches!(e,
                LinkEvent::JobDone { job, .. }
                | LinkEvent::JobFailed { job, .. }
                | LinkEvent::JobCancelled { job, .. } if *job == link_id)
        });
        if let Some(end) = end {
            return Box::pin(self.on_link_event(end)).await;
        }
        if jobs.active == Some(link_id) || jobs.queued.contains(&link_id) {
            return;
        }
        if let Some(active) = self.active.take() {
            let next = self.next_block(&active.record, active.acked).await;
            self.totals.jobs_failed += 1;
            let reason = "the link's report of the job's end was lost (the gateway fell behind \
                          its events): what the board acknowledged is all that is known"
                .to_string();
            self.end(
                active.record,
                End::Failed {
                    reason,
                    alarm: None,
                    code: pb::ErrorCode::LinkFailed,
                },
                active.acked,
                active.sent,
                next,
            );
        }
    }

    fn active_for(&mut self, link_id: JobId) -> Option<&mut Active> {
        self.active.as_mut().filter(|a| a.link_id == link_id)
    }
}

/// Completes at `deadline`, never without one.
async fn sleep_until_some(deadline: Option<Instant>) {
    match deadline {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}

/// Bytes of `active` already counted in the totals (through published progress).
fn published_bytes(active: &Active) -> u64 {
    active.shaper.last_acked
}

fn confirmation_pb(c: Confirmation) -> pb::Confirmation {
    match c {
        Confirmation::Acknowledged => pb::Confirmation::Acknowledged,
        Confirmation::EndOfRead => pb::Confirmation::EndOfRead,
        Confirmation::Unverified => pb::Confirmation::Unverified,
    }
}

#[cfg(test)]
mod tests;
