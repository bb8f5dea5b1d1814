//! G05 binary input streams (§9): a producer's blocks, through a machine's link, to the CNC.
//!
//! A stream is a program made while it is sent: `before` (ending with the `G05` block), the
//! binary blocks as the producer sends them, the end block and `after`. It waits its turn in
//! the link's queue like any program and goes out through whichever protocol the machine
//! speaks. [`cellgate_core::fanuc::g05::stream::Stream`] holds the rules (credits, priming, sequence, estimates); the task
//! here runs one over the link, and [`G05Desk`] opens them, one at a time per machine.
//!
//! Who imports whom: this module uses `fanuc::g05` (the block codec), `link` (the link's
//! queue and events) and `config`; the bus routes use it.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::Bytes;
use tokio::sync::{mpsc, oneshot, watch};
use tokio_util::sync::CancellationToken;

use crate::link::driver::{Chunk, JobSource, LinkCommand, LinkEvent, LinkHandle, ProgramJob};
use crate::link::pump::now;
use crate::link::{JobId, fanout};
use crate::transport::sim::SimOptions;
use cellgate_core::codes::BusCode;
use cellgate_core::config::{G05Config, MachineConfig, Refill, TransportConfig};
use cellgate_core::engine::LineSettings;
use cellgate_core::fanuc::g05::stream::{
    Batch, BatchError, EndReason, Offered, Stream, StreamFigures, StreamSettings, StreamState,
};
use cellgate_core::pb;

/// Link job ids of streams start here, far above the job manager's.
pub const STREAM_JOB_BASE: JobId = 1 << 48;

/// A stream's status is brought up to date at least this often while it is open.
pub const STATUS_INTERVAL: Duration = Duration::from_millis(100);

/// How often the link reports a stream's progress (its blocks on the line): at every piece
/// handed over. The underrun estimate counts a block as the CNC's from its hand-over; a
/// piece reported late (the last of a burst, before a pause of the producer) would have made
/// it count underruns the CNC cannot have had.
const PROGRESS_INTERVAL: Duration = Duration::ZERO;

/// Why a stream could not be opened.
#[derive(Debug, Clone, thiserror::Error)]
#[non_exhaustive]
pub enum G05Error {
    #[error(
        "machine {machine} takes no G05 streams: its cell file has no [machines.g05] table (§9)"
    )]
    NotConfigured { machine: String },
    #[error("machine {machine} is busy with G05 stream {stream}; one stream at a time")]
    Busy { machine: String, stream: String },
    #[error(
        "machine {machine}: G05 needs at least {required} baud here and the line runs at \
         {actual} (§9.2)"
    )]
    LineTooSlow {
        machine: String,
        required: u32,
        actual: u32,
    },
    #[error("machine {machine}: its link is not running")]
    LinkStopped { machine: String },
    #[error("machine {machine}: stream id {id:?} must be 1 to 64 letters, digits, '-' or '_'")]
    BadId { machine: String, id: String },
    #[error("machine {machine}: G05 stream {stream} has ended")]
    StreamEnded { machine: String, stream: String },
}

/// What an opened stream offers its producer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Opened {
    pub stream: String,
    pub block_len: u32,
    pub credits: u32,
    pub window: u32,
    pub prime: u32,
    pub unit_time_ms: u32,
    pub required_baud: u32,
    pub actual_baud: u32,
}

/// A stream's status as published.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamStatus {
    pub stream: String,
    pub machine: String,
    pub figures: StreamFigures,
}

impl StreamStatus {
    pub fn is_over(&self) -> bool {
        matches!(
            self.figures.state,
            StreamState::Completed | StreamState::Failed
        )
    }
}

enum Input {
    Batch(Batch, oneshot::Sender<Result<Offered, BatchError>>),
    End(EndReason),
}

/// Talks to one open stream.
#[derive(Clone, Debug)]
pub struct StreamHandle {
    pub id: String,
    machine: String,
    inputs: mpsc::Sender<Input>,
    status: watch::Receiver<StreamStatus>,
}

impl StreamHandle {
    /// Offers a batch; the answer says whether it was taken.
    pub async fn batch(&self, batch: Batch) -> Result<Offered, BatchError> {
        let (reply, answer) = oneshot::channel();
        let seq = batch.seq;
        let ended = || BatchError::Ended {
            seq,
            state: self.status.borrow().figures.state,
        };
        if self.inputs.send(Input::Batch(batch, reply)).await.is_err() {
            return Err(ended());
        }
        answer.await.unwrap_or_else(|_| Err(ended()))
    }

    /// Ends the stream for `reason`: the end block goes out behind what was accepted.
    pub async fn end(&self, reason: EndReason) -> Result<(), G05Error> {
        self.inputs
            .send(Input::End(reason))
            .await
            .map_err(|_| G05Error::StreamEnded {
                machine: self.machine.clone(),
                stream: self.id.clone(),
            })
    }

    pub fn status(&self) -> watch::Receiver<StreamStatus> {
        self.status.clone()
    }
}

/// Opens a machine's G05 streams, one at a time.
#[derive(Debug)]
pub struct G05Desk {
    machine: String,
    link: LinkHandle,
    config: Option<G05Config>,
    line: LineSettings,
    /// How the machine's board is refilled (Protocol A family), for the priming level.
    refill: Option<Refill>,
    /// The most characters the machine's transport holds unsent (for the estimate).
    in_flight: u64,
    current: Mutex<Option<StreamHandle>>,
    next: AtomicU64,
    shutdown: CancellationToken,
    /// Open streams on a line slower than §9.2 asks (to measure what it does).
    allow_slow_line: std::sync::atomic::AtomicBool,
}

impl G05Desk {
    /// The desk of `machine`, whose streams go through `link`: its `g05` table, line and
    /// board decide the streams' encoding, pace and priming.
    pub fn new(
        machine: &MachineConfig,
        link: LinkHandle,
        shutdown: CancellationToken,
    ) -> Arc<Self> {
        Arc::new(G05Desk {
            machine: machine.name.clone(),
            link,
            config: machine.g05.clone(),
            line: *machine.transport.line(),
            refill: machine.g05_refill(),
            in_flight: match &machine.transport {
                TransportConfig::Sim { .. } => SimOptions::default().fifo as u64 + 1,
                TransportConfig::Tcp { .. } => u64::from(machine.tcp_window()),
                TransportConfig::Serial { .. } => crate::transport::serial::PACER_WINDOW as u64,
            },
            current: Mutex::new(None),
            next: AtomicU64::new(0),
            shutdown,
            allow_slow_line: std::sync::atomic::AtomicBool::new(false),
        })
    }

    /// Lets streams open on a line slower than §9.2 asks, for measurements and tests of what
    /// such a line does (underruns); the cell file refuses such a line.
    pub fn allow_slow_line(&self) {
        self.allow_slow_line.store(true, Ordering::Relaxed);
    }

    pub fn config(&self) -> Option<&G05Config> {
        self.config.as_ref()
    }

    /// The stream open now (or the last one, ended), if any.
    pub fn current(&self) -> Option<StreamHandle> {
        self.current
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    /// The stream `id`, if it is the current one.
    pub fn find(&self, id: &str) -> Option<StreamHandle> {
        self.current().filter(|s| s.id == id)
    }

    /// Opens a stream: it is queued on the link at once and primes as blocks come.
    /// `id`: the producer's name for it (a key chunk); `None`: one is made.
    pub async fn open(&self, id: Option<String>) -> Result<(StreamHandle, Opened), G05Error> {
        let machine = self.machine.clone();
        let config = self
            .config
            .as_ref()
            .ok_or_else(|| G05Error::NotConfigured {
                machine: machine.clone(),
            })?;
        let required = config.required_baud(&self.line);
        if self.line.baud < required && !self.allow_slow_line.load(Ordering::Relaxed) {
            return Err(G05Error::LineTooSlow {
                machine,
                required,
                actual: self.line.baud,
            });
        }
        let n = self.next.fetch_add(1, Ordering::Relaxed);
        let id = match id.filter(|s| !s.is_empty()) {
            Some(id) => {
                let ok = id.len() <= 64
                    && id
                        .bytes()
                        .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
                if !ok {
                    return Err(G05Error::BadId { machine, id });
                }
                id
            }
            None => format!("s{}-{n}", cellgate_core::pb::now_ms()),
        };
        let settings = StreamSettings {
            format: config.format(),
            before: Bytes::from(config.before.clone().into_bytes()),
            after: Bytes::from(config.after.clone().into_bytes()),
            window: config.window_blocks(),
            prime: config.prime_blocks_on(self.refill),
            idle: Duration::from_millis(u64::from(config.idle_ms)),
            line: self.line,
            in_flight: self.in_flight,
        };
        let stream = Stream::new(settings.clone(), now());
        let initial = StreamStatus {
            stream: id.clone(),
            machine: machine.clone(),
            figures: stream.figures(),
        };
        let handle = {
            let mut current = self
                .current
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            if let Some(open) = current.as_ref()
                && !open.status.borrow().is_over()
            {
                return Err(G05Error::Busy {
                    machine,
                    stream: open.id.clone(),
                });
            }
            let (inputs, inputs_rx) = mpsc::channel(16);
            let (status_tx, status) = watch::channel(initial);
            let handle = StreamHandle {
                id: id.clone(),
                machine: machine.clone(),
                inputs,
                status,
            };
            *current = Some(handle.clone());
            (handle, inputs_rx, status_tx)
        };
        let (handle, inputs_rx, status_tx) = handle;
        // The link reads chunks as its engine wants data; credits bound how many wait.
        let (chunks, chunks_rx) = mpsc::channel(settings.window as usize + 8);
        let job = STREAM_JOB_BASE + n;
        let events = self.link.subscribe();
        let queued = self
            .link
            .send(LinkCommand::Queue(ProgramJob {
                id: job,
                name: format!("G05 stream {id}"),
                size: None,
                source: JobSource::Chunks(chunks_rx),
                progress_interval: Some(PROGRESS_INTERVAL),
            }))
            .await;
        if queued.is_err() {
            return Err(G05Error::LinkStopped { machine });
        }
        tracing::info!(machine = %self.machine, stream = %id, "G05 stream opened");
        let task = StreamTask {
            metrics: crate::telemetry::metrics::machine(&self.machine),
            underruns_counted: 0,
            stream,
            job,
            chunks: Some(chunks),
            status: status_tx,
        };
        tokio::spawn(task.run(inputs_rx, events, self.shutdown.child_token()));
        let opened = Opened {
            stream: id,
            block_len: settings.format.block_len() as u32,
            credits: settings.window,
            window: settings.window,
            prime: settings.prime,
            unit_time_ms: settings.format.unit_time_ms.ms(),
            required_baud: required,
            actual_baud: self.line.baud,
        };
        Ok((handle, opened))
    }
}

struct StreamTask {
    metrics: std::sync::Arc<crate::telemetry::metrics::MachineMetrics>,
    /// The stream's underruns already in the machine's counter.
    underruns_counted: u64,
    stream: Stream,
    job: JobId,
    /// The link's source; dropped when the stream closes, which ends the program.
    chunks: Option<mpsc::Sender<Chunk>>,
    status: watch::Sender<StreamStatus>,
}

impl StreamTask {
    async fn run(
        mut self,
        mut inputs: mpsc::Receiver<Input>,
        mut events: fanout::Receiver<LinkEvent>,
        shutdown: CancellationToken,
    ) {
        let mut tick = tokio::time::interval(STATUS_INTERVAL);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                () = shutdown.cancelled() => {
                    self.stream.finish(EndReason::Cancelled);
                    self.flush();
                    break;
                }
                input = inputs.recv() => match input {
                    Some(Input::Batch(batch, reply)) => {
                        let r = self.stream.offer(now(), &batch);
                        if let Err(e) = &r {
                            tracing::warn!(stream = %self.id(), error = %e, "G05 batch refused");
                        }
                        self.flush();
                        // The status the answer's reader sees already holds this batch.
                        self.publish();
                        let _ = reply.send(r);
                    }
                    Some(Input::End(reason)) => {
                        tracing::info!(stream = %self.id(), %reason, "G05 stream ending");
                        self.stream.finish(reason);
                        self.flush();
                    }
                    // Every handle is gone (the bus route stopped): end cleanly.
                    None => {
                        self.stream.finish(EndReason::Cancelled);
                        self.flush();
                    }
                },
                event = events.recv() => match event {
                    Ok(event) => {
                        if self.on_link_event(event) {
                            break;
                        }
                    }
                    Err(fanout::RecvError::Lagged(n)) => {
                        tracing::warn!(stream = %self.id(), missed = n, "G05 stream fell behind its link's events");
                    }
                    Err(fanout::RecvError::Closed) => {
                        self.stream.ended(false, Some("the link stopped".to_string()));
                        break;
                    }
                },
                _ = tick.tick() => {
                    if let Some(reason) = self.stream.tick(now()) {
                        tracing::warn!(stream = %self.id(), %reason, "G05 stream ending");
                        self.stream.finish(reason);
                        self.flush();
                    }
                }
            }
            self.publish();
        }
        self.publish();
        let f = self.stream.figures();
        tracing::info!(
            stream = %self.id(),
            state = %f.state,
            blocks = f.received,
            underruns = f.underruns,
            "G05 stream over"
        );
    }

    fn id(&self) -> String {
        self.status.borrow().stream.clone()
    }

    /// Hands the stream's chunks to the link; closes its source once the stream closes.
    fn flush(&mut self) {
        for chunk in self.stream.take_chunks() {
            let Some(tx) = &self.chunks else { break };
            // Credits bound the chunks waiting: the channel holds a window's worth.
            if tx.try_send(chunk).is_err() {
                tracing::error!(stream = %self.id(), "G05 chunk could not be queued on the link");
            }
        }
        if self.stream.is_closing() {
            self.chunks = None;
        }
    }

    /// Returns whether the stream is over.
    fn on_link_event(&mut self, event: LinkEvent) -> bool {
        match event {
            LinkEvent::Progress { job, sent, .. } if job == self.job => {
                self.stream.on_sent(now(), sent);
                false
            }
            LinkEvent::JobDone { job, bytes, .. } if job == self.job => {
                self.stream.on_sent(now(), bytes);
                self.stream.ended(true, None);
                true
            }
            LinkEvent::JobFailed {
                job, sent, reason, ..
            } if job == self.job => {
                self.stream.on_sent(now(), sent);
                self.stream.ended(false, Some(reason.to_string()));
                true
            }
            LinkEvent::JobCancelled { job, .. } if job == self.job => {
                self.stream
                    .ended(false, Some("the program was cancelled".to_string()));
                true
            }
            LinkEvent::Stopped { .. } => {
                self.stream
                    .ended(false, Some("the link stopped".to_string()));
                true
            }
            _ => false,
        }
    }

    fn publish(&mut self) {
        let figures = self.stream.figures();
        self.metrics
            .add_g05_underruns(figures.underruns.saturating_sub(self.underruns_counted));
        self.underruns_counted = self.underruns_counted.max(figures.underruns);
        self.status.send_if_modified(|s| {
            let changed = s.figures != figures;
            s.figures = figures;
            changed
        });
    }
}

impl BusCode for G05Error {
    fn code(&self) -> pb::ErrorCode {
        match self {
            G05Error::NotConfigured { .. } | G05Error::LineTooSlow { .. } => {
                pb::ErrorCode::NotSupported
            }
            G05Error::Busy { .. } => pb::ErrorCode::Busy,
            G05Error::LinkStopped { .. } => pb::ErrorCode::Unavailable,
            G05Error::BadId { .. } => pb::ErrorCode::InvalidRequest,
            G05Error::StreamEnded { .. } => pb::ErrorCode::NotFound,
        }
    }
}
