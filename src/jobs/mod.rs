//! The job manager: one per machine. It keeps the machine's queue of programs, hands the link
//! one job at a time, and reports every step of every job as a [`pb::JobEvent`].
//!
//! - Queue: higher `priority` first, arrival order among equals ([`queue`]); at most
//!   [`MAX_WAITING`] jobs wait. The link gets [`LinkCommand::Queue`] only when it has no
//!   active job, so the order stays the gateway's to decide until the last moment, and a
//!   waiting job is cancelled by dropping it. An active job is cancelled with
//!   [`LinkCommand::Cancel`] and ends when the link confirms.
//! - Sources ([`source`]): inline bytes, a library program ([`library`]) streamed from its
//!   file, or bytes fetched from a bus key. Every program is checked before it is queued;
//!   a bad one is refused with the reason and nothing is queued.
//! - Punched programs ([`punch`]): a punch-out split into programs and decoded, library
//!   names for them, and remote requests for a program.
//! - Job ids: `<machine>-<run>-<n>`, where `<run>` is the time the manager started, in
//!   seconds since the Unix epoch written in base 36, and `<n>` counts the machine's jobs
//!   from 1. Unique in the cell as long as the clock does not run backwards across restarts;
//!   a valid key chunk, since machine names are `[A-Za-z0-9_-]+`.
//! - Progress: the link reports progress at every whole percent (or every 250 ms for a
//!   program of unknown size). Events are published at most every
//!   [`PROGRESS_MIN_INTERVAL`], and only once progress has reached a further whole percent
//!   (any further byte when the size is unknown), each with the rate since the previous one.
//!
//! The manager knows nothing of the bus: [`JobsHandle`] takes requests and hands out events,
//! and the bus routes put them on their keys. It runs in tokio time, so it is tested under
//! paused time with a stand-in link.

pub mod library;
pub mod punch;
pub mod queue;
pub mod source;

use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use tokio::sync::{broadcast, mpsc, oneshot, watch};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use crate::codes::BusCode;
use crate::fanuc::alarm::CncAlarm;
use crate::link::JobId;
use crate::link::driver::{
    JobFailure, LinkCommand, LinkEvent, LinkHandle, ProgramJob, ProgramSource,
};
use crate::pb;
use crate::pb::job_event::Kind;
use library::{LibraryError, ProgramLibrary};
use queue::PriorityQueue;
use source::{PrepareError, ProgramError, ProgramInput, ProgramRules};

/// Most jobs waiting on one machine; one more is refused with `ERROR_CODE_QUEUE_FULL`.
pub const MAX_WAITING: usize = 256;

/// Progress events of one job are at least this far apart.
pub const PROGRESS_MIN_INTERVAL: Duration = Duration::from_millis(250);

/// A request to send a program to the machine.
#[derive(Debug, Clone)]
pub struct JobSubmission {
    pub input: ProgramInput,
    /// Display name; empty: derived from the source.
    pub name: String,
    /// Higher runs first.
    pub priority: i32,
    /// Append `%` to a program without EOR instead of refusing it.
    pub append_eor: bool,
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
    #[error("machine {machine}: the job manager has stopped (gateway shutting down)")]
    Stopped { machine: String },
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
    /// NC bytes the board accepted over every job, as far as published in progress events.
    pub nc_bytes_sent: u64,
    pub jobs_completed: u64,
    pub jobs_failed: u64,
}

/// Talks to a machine's job manager. Cheap to clone.
#[derive(Debug, Clone)]
pub struct JobsHandle {
    machine: Arc<str>,
    rules: ProgramRules,
    library: ProgramLibrary,
    requests: mpsc::Sender<Request>,
    events: broadcast::Sender<pb::JobEvent>,
    snapshot: watch::Receiver<JobsSnapshot>,
}

enum Request {
    Submit {
        job: Waiting,
        reply: oneshot::Sender<Result<pb::JobAccepted, JobError>>,
    },
    Cancel {
        id: String,
        reply: oneshot::Sender<Result<CancelOutcome, JobError>>,
    },
    List {
        reply: oneshot::Sender<pb::JobQueue>,
    },
}

impl JobsHandle {
    pub fn machine(&self) -> &str {
        &self.machine
    }

    pub fn rules(&self) -> ProgramRules {
        self.rules
    }

    /// The program library the machine's jobs read from.
    pub fn library(&self) -> &ProgramLibrary {
        &self.library
    }

    fn stopped(&self) -> JobError {
        JobError::Stopped {
            machine: self.machine.to_string(),
        }
    }

    /// Checks the program and queues the job. On success the job's `queued` event is out
    /// before this returns. The check reads a library program once through; it runs in the
    /// caller's task.
    pub async fn submit(&self, submission: JobSubmission) -> Result<pb::JobAccepted, JobError> {
        let prepared = source::prepare(
            submission.input,
            &submission.name,
            submission.append_eor,
            self.rules,
            &self.library,
        )
        .await
        .map_err(|e| match e {
            PrepareError::Program(error) => JobError::Program {
                machine: self.machine.to_string(),
                error,
            },
            PrepareError::Library(error) => JobError::Library {
                machine: self.machine.to_string(),
                error,
            },
        })?;
        let job = Waiting {
            id: String::new(),
            link_id: 0,
            name: prepared.name.clone(),
            priority: submission.priority,
            size: prepared.size,
            accepted_unix_ms: unix_ms(),
            source: prepared.into_source(),
        };
        let (reply, answer) = oneshot::channel();
        self.requests
            .send(Request::Submit { job, reply })
            .await
            .map_err(|_| self.stopped())?;
        answer.await.map_err(|_| self.stopped())?
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
    pub fn subscribe(&self) -> broadcast::Receiver<pb::JobEvent> {
        self.events.subscribe()
    }

    /// The machine's jobs at a glance; changes whenever a job is queued, starts, makes
    /// published progress or ends.
    pub fn snapshot(&self) -> watch::Receiver<JobsSnapshot> {
        self.snapshot.clone()
    }
}

/// Starts the job manager of `machine`, which feeds `link`. It ends when `shutdown` is
/// cancelled or every handle is dropped; jobs still waiting are then reported cancelled, and
/// the active one failed (the link is asked to cancel it).
pub fn spawn(
    machine: &str,
    rules: ProgramRules,
    library: ProgramLibrary,
    link: LinkHandle,
    shutdown: CancellationToken,
) -> (JobsHandle, tokio::task::JoinHandle<()>) {
    let (req_tx, req_rx) = mpsc::channel(64);
    let (ev_tx, _) = broadcast::channel(1024);
    let (snap_tx, snap_rx) = watch::channel(JobsSnapshot::default());
    let name: Arc<str> = Arc::from(machine);
    let handle = JobsHandle {
        machine: name.clone(),
        rules,
        library,
        requests: req_tx,
        events: ev_tx.clone(),
        snapshot: snap_rx,
    };
    // Subscribed before the task runs, so no link event is missed.
    let link_events = link.subscribe();
    let run_stamp = base36(
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_secs()),
    );
    let manager = Manager {
        machine: name.clone(),
        run_stamp,
        next: 1,
        link,
        link_stopped: false,
        waiting: PriorityQueue::new(),
        active: None,
        events: ev_tx,
        snapshot: snap_tx,
        totals: JobsSnapshot::default(),
    };
    let span = tracing::info_span!("jobs", machine = %name);
    let task = tokio::spawn(tracing::Instrument::instrument(
        manager.run(req_rx, link_events, shutdown),
        span,
    ));
    (handle, task)
}

/// Milliseconds since the Unix epoch, now.
pub fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

fn base36(mut n: u64) -> String {
    const DIGITS: &[u8; 36] = b"0123456789abcdefghijklmnopqrstuvwxyz";
    let mut out = Vec::new();
    loop {
        out.push(DIGITS[(n % 36) as usize]);
        n /= 36;
        if n == 0 {
            break;
        }
    }
    out.reverse();
    String::from_utf8(out).unwrap_or_default()
}

/// Shapes the link's progress reports into the published stream (see the module
/// documentation).
#[derive(Debug, Clone)]
pub struct ProgressShaper {
    total: Option<u64>,
    last_at: Instant,
    last_sent: u64,
}

impl ProgressShaper {
    /// A transfer of `total` bytes (if known) that started at `now`.
    pub fn new(now: Instant, total: Option<u64>) -> Self {
        ProgressShaper {
            total,
            last_at: now,
            last_sent: 0,
        }
    }

    /// The link reports `sent` bytes at `now`; returns the rate in bytes/s since the last
    /// published event when this one is to be published.
    pub fn offer(&mut self, now: Instant, sent: u64) -> Option<u64> {
        let elapsed = now.saturating_duration_since(self.last_at);
        if elapsed < PROGRESS_MIN_INTERVAL || sent <= self.last_sent {
            return None;
        }
        if let Some(total) = self.total.filter(|&t| t > 0) {
            let percent = |b: u64| u128::from(b) * 100 / u128::from(total);
            if percent(sent) <= percent(self.last_sent) {
                return None;
            }
        }
        let bytes = sent - self.last_sent;
        let ms = elapsed.as_millis().max(1);
        let rate = u64::try_from(u128::from(bytes) * 1000 / ms).unwrap_or(u64::MAX);
        self.last_at = now;
        self.last_sent = sent;
        Some(rate)
    }
}

struct Waiting {
    id: String,
    link_id: JobId,
    name: String,
    priority: i32,
    size: u64,
    accepted_unix_ms: u64,
    source: ProgramSource,
}

struct Active {
    id: String,
    link_id: JobId,
    name: String,
    priority: i32,
    size: u64,
    accepted_unix_ms: u64,
    handed_at: Instant,
    started_at: Option<Instant>,
    sent: u64,
    shaper: ProgressShaper,
    cancel_requested: bool,
    /// The link alarm (with its CNC number) seen while this job ran.
    alarm: Option<CncAlarm>,
    cnc_reset: bool,
}

struct Manager {
    machine: Arc<str>,
    run_stamp: String,
    next: JobId,
    link: LinkHandle,
    link_stopped: bool,
    waiting: PriorityQueue<Waiting>,
    active: Option<Active>,
    events: broadcast::Sender<pb::JobEvent>,
    snapshot: watch::Sender<JobsSnapshot>,
    totals: JobsSnapshot,
}

impl Manager {
    async fn run(
        mut self,
        mut requests: mpsc::Receiver<Request>,
        mut link_events: broadcast::Receiver<LinkEvent>,
        shutdown: CancellationToken,
    ) {
        loop {
            self.hand_next().await;
            self.publish_snapshot();
            tokio::select! {
                biased;
                () = shutdown.cancelled() => break,
                request = requests.recv() => match request {
                    Some(r) => self.on_request(r).await,
                    None => break,
                },
                event = link_events.recv() => match event {
                    Ok(e) => self.on_link_event(e),
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        // Only a stalled manager lags; job ends may have been lost.
                        tracing::error!(missed = n, "job manager fell behind the link's events");
                    }
                    // Cannot happen while this manager holds the link handle.
                    Err(broadcast::error::RecvError::Closed) => break,
                },
            }
        }
        self.shut_down().await;
    }

    async fn shut_down(&mut self) {
        if let Some(active) = self.active.take() {
            // Best effort: the link may already be stopping with the gateway.
            let cancel = self.link.send(LinkCommand::Cancel(active.link_id));
            let _ = tokio::time::timeout(Duration::from_millis(100), cancel).await;
            let failed = Kind::Failed(pb::job_event::Failed {
                reason: "the gateway is shutting down".to_string(),
                byte_offset: active.sent,
                alarm_number: String::new(),
                code: pb::ErrorCode::Unavailable as i32,
            });
            self.emit(&active.id, failed);
        }
        for job in self.waiting.drain() {
            self.emit(
                &job.id,
                Kind::Cancelled(pb::job_event::Cancelled {
                    byte_offset: 0,
                    by: "gateway shutdown".to_string(),
                }),
            );
        }
        self.publish_snapshot();
    }

    fn emit(&self, id: &str, kind: Kind) {
        // No subscriber is not an error: nobody is watching this machine's jobs right now.
        let _ = self.events.send(pb::JobEvent {
            job_id: id.to_string(),
            machine: self.machine.to_string(),
            unix_ms: unix_ms(),
            kind: Some(kind),
        });
    }

    fn publish_snapshot(&mut self) {
        let snapshot = JobsSnapshot {
            active: self.active.as_ref().map(|a| a.id.clone()),
            waiting: self.waiting.len(),
            ..self.totals.clone()
        };
        self.snapshot.send_if_modified(|old| {
            if *old == snapshot {
                false
            } else {
                *old = snapshot;
                true
            }
        });
    }

    async fn on_request(&mut self, request: Request) {
        match request {
            Request::Submit { mut job, reply } => {
                if self.link_stopped {
                    let _ = reply.send(Err(JobError::LinkStopped {
                        machine: self.machine.to_string(),
                    }));
                    return;
                }
                if self.waiting.len() >= MAX_WAITING {
                    let _ = reply.send(Err(JobError::QueueFull {
                        machine: self.machine.to_string(),
                        max: MAX_WAITING,
                    }));
                    return;
                }
                job.link_id = self.next;
                job.id = format!("{}-{}-{}", self.machine, self.run_stamp, self.next);
                self.next += 1;
                let id = job.id.clone();
                tracing::info!(job = %id, name = %job.name, size = job.size, priority = job.priority, "job queued");
                let position =
                    u32::try_from(self.waiting.push(job.priority, job)).unwrap_or(u32::MAX);
                self.emit(
                    &id,
                    Kind::Queued(pb::job_event::Queued {
                        queue_position: position,
                    }),
                );
                let _ = reply.send(Ok(pb::JobAccepted {
                    job_id: id,
                    queue_position: position,
                }));
            }
            Request::Cancel { id, reply } => {
                let outcome = self.cancel(&id).await;
                let _ = reply.send(outcome);
            }
            Request::List { reply } => {
                let _ = reply.send(self.list());
            }
        }
    }

    async fn cancel(&mut self, id: &str) -> Result<CancelOutcome, JobError> {
        if let Some(job) = self.waiting.remove_first(|j| j.id == id) {
            tracing::info!(job = %id, "waiting job cancelled");
            self.emit(
                &job.id,
                Kind::Cancelled(pb::job_event::Cancelled {
                    byte_offset: 0,
                    by: "request".to_string(),
                }),
            );
            return Ok(CancelOutcome::Dropped);
        }
        let Some(active) = self.active.as_mut().filter(|a| a.id == id) else {
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
                self.link_gone("the link is not running");
            }
        }
        Ok(CancelOutcome::Cancelling)
    }

    fn list(&self) -> pb::JobQueue {
        let active = self.active.as_ref().map(|a| pb::QueuedJob {
            job_id: a.id.clone(),
            name: a.name.clone(),
            priority: a.priority,
            bytes_total: a.size,
            bytes_sent: a.sent,
            accepted_unix_ms: a.accepted_unix_ms,
        });
        let waiting = self
            .waiting
            .iter()
            .map(|w| pb::QueuedJob {
                job_id: w.id.clone(),
                name: w.name.clone(),
                priority: w.priority,
                bytes_total: w.size,
                bytes_sent: 0,
                accepted_unix_ms: w.accepted_unix_ms,
            })
            .collect();
        pb::JobQueue {
            machine: self.machine.to_string(),
            active,
            waiting,
        }
    }

    /// Gives the link the next job when it has none.
    async fn hand_next(&mut self) {
        if self.active.is_some() || self.link_stopped {
            return;
        }
        let Some(job) = self.waiting.pop() else {
            return;
        };
        let now = Instant::now();
        let active = Active {
            id: job.id,
            link_id: job.link_id,
            name: job.name.clone(),
            priority: job.priority,
            size: job.size,
            accepted_unix_ms: job.accepted_unix_ms,
            handed_at: now,
            started_at: None,
            sent: 0,
            shaper: ProgressShaper::new(now, Some(job.size)),
            cancel_requested: false,
            alarm: None,
            cnc_reset: false,
        };
        let command = LinkCommand::Queue(ProgramJob {
            id: job.link_id,
            name: job.name,
            size: Some(job.size),
            source: job.source,
        });
        self.active = Some(active);
        if self.link.send(command).await.is_err() {
            self.link_gone("the link is not running");
        }
    }

    /// The link stopped for good: the active job fails, the waiting ones cannot run.
    fn link_gone(&mut self, why: &str) {
        self.link_stopped = true;
        tracing::warn!(reason = why, "link stopped; failing its jobs");
        let ended = self.active.take().map(|a| (a.id, a.sent));
        for (id, offset) in ended
            .into_iter()
            .chain(self.waiting.drain().into_iter().map(|w| (w.id, 0)))
        {
            self.totals.jobs_failed += 1;
            self.emit(
                &id,
                Kind::Failed(pb::job_event::Failed {
                    reason: format!("{why}; the job cannot continue"),
                    byte_offset: offset,
                    alarm_number: String::new(),
                    code: pb::ErrorCode::Unavailable as i32,
                }),
            );
        }
    }

    fn on_link_event(&mut self, event: LinkEvent) {
        match event {
            LinkEvent::Stopped { error } => {
                let why = match error {
                    Some(e) => format!("the link stopped: {e}"),
                    None => "the link stopped".to_string(),
                };
                self.link_gone(&why);
            }
            LinkEvent::Alarm(alarm) => {
                if let Some(active) = self.active.as_mut() {
                    active.alarm = alarm.cnc_alarm().or(active.alarm);
                }
            }
            LinkEvent::CncReset => {
                if let Some(active) = self.active.as_mut() {
                    active.cnc_reset = true;
                }
            }
            LinkEvent::JobStarted { job } => {
                let Some(active) = self.active_for(job) else {
                    return;
                };
                let now = Instant::now();
                active.started_at = Some(now);
                active.shaper = ProgressShaper::new(now, Some(active.size));
                let (id, size) = (active.id.clone(), active.size);
                tracing::info!(job = %id, "job started");
                self.emit(
                    &id,
                    Kind::Started(pb::job_event::Started {
                        bytes_total: Some(size),
                    }),
                );
            }
            LinkEvent::Progress { job, sent, .. } => {
                let Some(active) = self.active_for(job) else {
                    return;
                };
                let published = published_bytes(active);
                active.sent = sent.max(active.sent);
                let Some(rate) = active.shaper.offer(Instant::now(), active.sent) else {
                    return;
                };
                let (id, sent, size) = (active.id.clone(), active.sent, active.size);
                self.totals.nc_bytes_sent += sent.saturating_sub(published);
                self.emit(
                    &id,
                    Kind::Progress(pb::job_event::Progress {
                        bytes_sent: sent,
                        bytes_total: Some(size),
                        rate_bps: rate,
                    }),
                );
            }
            LinkEvent::JobDone { job, bytes } => {
                if self.active_for(job).is_none() {
                    return;
                }
                let Some(active) = self.active.take() else {
                    return;
                };
                let since = active.started_at.unwrap_or(active.handed_at);
                let duration = Instant::now().saturating_duration_since(since);
                self.totals.jobs_completed += 1;
                self.totals.nc_bytes_sent += bytes.saturating_sub(published_bytes(&active));
                tracing::info!(job = %active.id, bytes, "job completed");
                self.emit(
                    &active.id,
                    Kind::Completed(pb::job_event::Completed {
                        bytes_sent: bytes,
                        duration_ms: u64::try_from(duration.as_millis()).unwrap_or(u64::MAX),
                    }),
                );
            }
            LinkEvent::JobFailed {
                job,
                offset,
                reason,
            } => {
                if self.active_for(job).is_none() {
                    return;
                }
                let Some(active) = self.active.take() else {
                    return;
                };
                self.totals.nc_bytes_sent += offset.saturating_sub(published_bytes(&active));
                let reset = matches!(&reason, JobFailure::Aborted(r) if r.is_reset());
                if active.cnc_reset || reset || active.cancel_requested {
                    // A CNC reset abandons the program: the proto counts that as a
                    // cancellation, as it does one the request asked for.
                    let by = if active.cancel_requested {
                        "request"
                    } else {
                        "cnc reset"
                    };
                    self.emit(
                        &active.id,
                        Kind::Cancelled(pb::job_event::Cancelled {
                            byte_offset: offset,
                            by: by.to_string(),
                        }),
                    );
                    return;
                }
                self.totals.jobs_failed += 1;
                tracing::warn!(job = %active.id, offset, %reason, "job failed");
                let alarm = active.alarm.or(reason.cnc_alarm());
                self.emit(
                    &active.id,
                    Kind::Failed(pb::job_event::Failed {
                        reason: reason.to_string(),
                        byte_offset: offset,
                        alarm_number: alarm.map(|a| a.number().to_string()).unwrap_or_default(),
                        code: reason.code() as i32,
                    }),
                );
            }
            LinkEvent::JobCancelled { job, offset } => {
                if self.active_for(job).is_none() {
                    // A waiting job is never on the link, so this is one the link dropped
                    // by itself; nothing of ours.
                    return;
                }
                let Some(active) = self.active.take() else {
                    return;
                };
                self.totals.nc_bytes_sent += offset.saturating_sub(published_bytes(&active));
                let by = if active.cancel_requested {
                    "request"
                } else if active.cnc_reset {
                    "cnc reset"
                } else {
                    "link"
                };
                tracing::info!(job = %active.id, offset, by, "job cancelled");
                self.emit(
                    &active.id,
                    Kind::Cancelled(pb::job_event::Cancelled {
                        byte_offset: offset,
                        by: by.to_string(),
                    }),
                );
            }
            _ => {}
        }
    }

    fn active_for(&mut self, link_id: JobId) -> Option<&mut Active> {
        self.active.as_mut().filter(|a| a.link_id == link_id)
    }
}

/// Bytes of `active` already counted in the totals (through published progress).
fn published_bytes(active: &Active) -> u64 {
    active.shaper.last_sent
}

#[cfg(test)]
mod tests;
