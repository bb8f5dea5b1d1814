//! One G05 stream, sans-IO: batches of blocks in, program chunks out, and the stream's
//! figures — credits, blocks on the line, the CNC's buffer and its underruns as estimated
//! from the line and the unit time (§9.1 (2), §9.2).
//!
//! The stream's program is `before` (NC text ending in the `G05` block), the binary blocks,
//! the end block, and `after`; the engine appends EOR. Blocks are held back until the
//! priming level is reached, because the CNC takes one block every T from the moment it
//! reads `G05`; `before` and those blocks then go to the link as one [`Chunk::Primed`], so
//! that no protocol sends the `G05` block ahead of them. The gateway holds at most `window` blocks not yet on the line: a batch beyond
//! the credits is refused whole, so memory stays bounded whatever the producer does.

use std::fmt;
use std::time::{Duration, Instant};

use bytes::Bytes;

use crate::codes::BusCode;
use crate::engine::LineSettings;
use crate::fanuc::g05::{AuxWord, G05EncodeError, G05Format};
use crate::fanuc::host::Chunk;
use crate::pb;

/// How far behind `now` a status tick judges the CNC's slots (see [`Stream::tick`]): a few
/// of the link's progress steps.
pub const ESTIMATE_LAG: Duration = Duration::from_millis(50);

/// What a stream is set up with.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamSettings {
    /// The CNC's G05 settings the blocks are encoded in.
    pub format: G05Format,
    /// NC text before the blocks, ending with the `G05` block.
    pub before: Bytes,
    /// NC text after the end block.
    pub after: Bytes,
    /// Blocks held at most (the credit window).
    pub window: u32,
    /// Blocks held before the `G05` block goes out.
    pub prime: u32,
    /// A producer silent this long while the CNC is estimated dry is taken as gone.
    pub idle: Duration,
    /// The machine's line: the CNC cannot read the `G05` block before the piece carrying it
    /// has crossed it.
    pub line: LineSettings,
    /// The most characters the link's transport holds that have not left on the line yet
    /// (its in-flight window): what was handed over has crossed the line at the latest this
    /// many character times later.
    pub in_flight: u64,
}

/// One block as the producer gives it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BlockIn {
    /// One travel per axis, in least input increments.
    pub travels: Vec<i32>,
    /// The auxiliary word, when the format has one (`None`: a word of zeros).
    pub aux: Option<AuxWord>,
}

/// A batch of blocks, numbered by the producer from 0.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Batch {
    /// The batch's number; the first batch is 0.
    pub seq: u64,
    /// The batch's blocks, in order.
    pub blocks: Vec<BlockIn>,
    /// The producer's last batch: the end block and `after` follow its blocks.
    pub end: bool,
}

/// Why a batch was refused. Nothing of a refused batch is sent.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum BatchError {
    /// The batch is later than the one due: the blocks between are missing.
    #[error(
        "batch {got} arrived where batch {expected} was due: the blocks between are missing, so \
         the batch is refused (send batch {expected} next)"
    )]
    Gap {
        /// The batch due.
        expected: u64,
        /// The batch that arrived.
        got: u64,
    },
    /// The batch holds more blocks than the stream has credits.
    #[error(
        "batch {seq} holds {blocks} blocks but the stream has {credits} credits (it holds at most \
         {window} blocks not yet on the line): wait for credits"
    )]
    Credits {
        /// The batch's number.
        seq: u64,
        /// Blocks in the batch.
        blocks: usize,
        /// Blocks the producer may send now.
        credits: u32,
        /// Most blocks the stream holds that are not yet on the line.
        window: u32,
    },
    /// A block of the batch cannot be encoded.
    #[error("batch {seq}: {error}")]
    Block {
        /// The batch's number.
        seq: u64,
        /// Why the block cannot be encoded.
        error: G05EncodeError,
    },
    /// The batch arrived after the stream ended.
    #[error("batch {seq} arrived after the stream ended ({state})")]
    Ended {
        /// The batch's number.
        seq: u64,
        /// Where the stream stands.
        state: StreamState,
    },
}

/// What became of an accepted batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Offered {
    /// The batch was taken, all its blocks.
    Accepted,
    /// A batch already taken (the producer sent it again): ignored, nothing sent twice.
    Repeat,
}

/// Where a stream stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StreamState {
    /// Waiting for the blocks of the priming level, or for the machine's earlier jobs.
    Priming,
    /// The `G05` block has gone out; blocks flow.
    Streaming,
    /// The end block is queued; the program is finishing.
    Ending,
    /// The program was acknowledged to its EOR.
    Completed,
    /// The program failed or never started.
    Failed,
}

impl fmt::Display for StreamState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            StreamState::Priming => "priming",
            StreamState::Streaming => "streaming",
            StreamState::Ending => "ending",
            StreamState::Completed => "completed",
            StreamState::Failed => "failed",
        })
    }
}

/// Why a stream ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EndReason {
    /// The producer's last batch.
    Producer,
    /// The stream was cancelled.
    Cancelled,
    /// The producer's liveliness token went away.
    ProducerLost,
    /// No batch for the idle time while the CNC ran dry.
    ProducerIdle,
    /// No batch at all within the idle time of the opening: nobody is producing, and the
    /// machine is freed for its jobs.
    NoBatch,
}

impl fmt::Display for EndReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            EndReason::Producer => "the producer ended the stream",
            EndReason::Cancelled => "the stream was cancelled",
            EndReason::ProducerLost => "the producer went away (its liveliness token is gone)",
            EndReason::ProducerIdle => "the producer sent nothing while the CNC ran out of blocks",
            EndReason::NoBatch => "no batch came within the idle time of the opening",
        })
    }
}

/// A stream's figures at one moment.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamFigures {
    /// Where the stream stands.
    pub state: StreamState,
    /// Blocks the producer may send now.
    pub credits: u32,
    /// Blocks accepted.
    pub received: u64,
    /// Blocks handed to the line.
    pub on_line: u64,
    /// Blocks estimated in the CNC's buffer (on the line, not yet taken) while the stream
    /// runs; 0 once it is over.
    pub cnc_buffer: u64,
    /// Unit-time slots estimated to have found the CNC without a block.
    pub underruns: u64,
    /// Batches refused for a gap, ignored as repeats, refused otherwise.
    pub gaps: u64,
    /// Batches ignored as repeats.
    pub repeats: u64,
    /// Batches refused for another reason (credits, a block, the stream ended).
    pub refused: u64,
    /// The batch the stream expects next.
    pub next_seq: u64,
    /// The error of the latest refused batch, or the one the link reported at the end.
    pub last_error: Option<String>,
    /// Why the stream was ended ([`Stream::finish`]); `None` before that.
    pub end_reason: Option<EndReason>,
}

/// One G05 stream.
#[derive(Debug)]
pub struct Stream {
    settings: StreamSettings,
    next_seq: u64,
    received: u64,
    /// Encoded blocks held back until priming.
    held: Vec<u8>,
    primed: bool,
    out: Vec<Chunk>,
    closing: bool,
    state: StreamState,
    end_reason: Option<EndReason>,
    /// Program bytes handed to the line.
    sent: u64,
    /// The latest the CNC can have read the `G05` block (see [`Stream::on_sent`]): the
    /// estimate's unit times count from then.
    g05_at: Option<Instant>,
    slots_seen: u64,
    cnc_taken: u64,
    underruns: u64,
    /// The last batch, or the moment credits came back after there were none: a producer
    /// that had no credits could not send, and is not idle for it.
    last_batch_at: Instant,
    gaps: u64,
    repeats: u64,
    refused: u64,
    last_error: Option<String>,
}

impl Stream {
    /// A stream with these settings, priming, expecting batch 0.
    pub fn new(settings: StreamSettings, now: Instant) -> Self {
        Stream {
            settings,
            next_seq: 0,
            received: 0,
            held: Vec::new(),
            primed: false,
            out: Vec::new(),
            closing: false,
            state: StreamState::Priming,
            end_reason: None,
            sent: 0,
            g05_at: None,
            slots_seen: 0,
            cnc_taken: 0,
            underruns: 0,
            last_batch_at: now,
            gaps: 0,
            repeats: 0,
            refused: 0,
            last_error: None,
        }
    }

    /// The settings the stream was set up with.
    pub fn settings(&self) -> &StreamSettings {
        &self.settings
    }

    fn block_len(&self) -> u64 {
        self.settings.format.block_len() as u64
    }

    /// Blocks whose bytes have gone to the line (the end block not counted).
    fn on_line(&self) -> u64 {
        let before = self.settings.before.len() as u64;
        (self.sent.saturating_sub(before) / self.block_len()).min(self.received)
    }

    /// Blocks the producer may send now.
    pub fn credits(&self) -> u32 {
        if self.closing {
            return 0;
        }
        let held = self.received - self.on_line();
        u32::try_from(u64::from(self.settings.window).saturating_sub(held)).unwrap_or(0)
    }

    /// Takes a batch: all its blocks, or none.
    pub fn offer(&mut self, now: Instant, batch: &Batch) -> Result<Offered, BatchError> {
        let result = self.try_offer(now, batch);
        if let Err(e) = &result {
            match e {
                BatchError::Gap { .. } => self.gaps += 1,
                _ => self.refused += 1,
            }
            self.last_error = Some(e.to_string());
        }
        result
    }

    fn try_offer(&mut self, now: Instant, batch: &Batch) -> Result<Offered, BatchError> {
        let seq = batch.seq;
        if self.closing {
            return Err(BatchError::Ended {
                seq,
                state: self.state,
            });
        }
        if seq < self.next_seq {
            self.repeats += 1;
            return Ok(Offered::Repeat);
        }
        if seq > self.next_seq {
            return Err(BatchError::Gap {
                expected: self.next_seq,
                got: seq,
            });
        }
        let credits = self.credits();
        if batch.blocks.len() > credits as usize {
            return Err(BatchError::Credits {
                seq,
                blocks: batch.blocks.len(),
                credits,
                window: self.settings.window,
            });
        }
        let mut bytes = Vec::with_capacity(batch.blocks.len() * self.block_len() as usize);
        for (i, b) in batch.blocks.iter().enumerate() {
            let no = self.received + i as u64 + 1;
            self.settings
                .format
                .encode_block(no, &b.travels, b.aux, &mut bytes)
                .map_err(|error| BatchError::Block { seq, error })?;
        }
        self.next_seq += 1;
        self.received += batch.blocks.len() as u64;
        self.last_batch_at = now;
        if self.primed {
            if !bytes.is_empty() {
                self.out.push(Chunk::Binary(Bytes::from(bytes)));
            }
        } else {
            self.held.extend_from_slice(&bytes);
            if self.received >= u64::from(self.settings.prime) {
                self.prime();
            }
        }
        if batch.end {
            self.finish(EndReason::Producer);
        }
        Ok(Offered::Accepted)
    }

    fn prime(&mut self) {
        self.primed = true;
        self.state = StreamState::Streaming;
        // One chunk: the engine takes both in one step (§9.2).
        self.out.push(Chunk::Primed {
            text: self.settings.before.clone(),
            blocks: Bytes::from(std::mem::take(&mut self.held)),
        });
    }

    /// Ends the stream: the end block and `after` go out behind what was accepted. A stream
    /// that never reached its `G05` block sends nothing when it was not the producer that
    /// ended it (the CNC never entered binary mode); a producer's short stream is sent whole.
    pub fn finish(&mut self, reason: EndReason) {
        if self.closing {
            return;
        }
        self.closing = true;
        self.end_reason = Some(reason);
        if !self.primed {
            if reason == EndReason::Producer && self.received > 0 {
                self.prime();
            } else {
                self.held.clear();
                self.state = StreamState::Failed;
                return;
            }
        }
        self.state = StreamState::Ending;
        let mut end = Vec::with_capacity(self.block_len() as usize);
        self.settings.format.encode_end(&mut end);
        self.out.push(Chunk::Binary(Bytes::from(end)));
        if !self.settings.after.is_empty() {
            self.out.push(Chunk::Text(self.settings.after.clone()));
        }
    }

    /// The chunks to hand to the link, in order.
    pub fn take_chunks(&mut self) -> Vec<Chunk> {
        std::mem::take(&mut self.out)
    }

    /// Nothing more will be handed out: the link's source can be closed (after the chunks
    /// still to take).
    pub fn is_closing(&self) -> bool {
        self.closing
    }

    /// The program's bytes handed to the line so far (the link's progress, reported as each
    /// piece is handed over).
    ///
    /// The estimate must never count an underrun the CNC cannot have had, so its unit times
    /// start no earlier than the CNC's: the stream starts on an idle line (the protocol ended
    /// the program before it), so the piece carrying the `G05` block, all handed over by
    /// `now`, is whole at the board at the latest when the line has carried what the
    /// transport may still hold of it (a board uses a DAT or packet only once it has arrived
    /// whole, §4.4.2, §5.2), and the CNC's first unit time ends at most one T after it read
    /// the block (§9.2). Starting
    /// earlier, at the hand-over, made the estimate run ahead of the CNC by the first piece's
    /// line time for the whole stream: 197 underruns estimated, and alarms, where the CNC
    /// counted none.
    pub fn on_sent(&mut self, now: Instant, sent: u64) {
        let had_credits = self.credits() > 0;
        self.sent = self.sent.max(sent);
        if !had_credits && self.credits() > 0 {
            self.last_batch_at = self.last_batch_at.max(now);
        }
        if self.g05_at.is_none() && self.primed && self.sent >= self.settings.before.len() as u64 {
            let held = self.sent.min(self.settings.in_flight);
            let crossed = self.settings.line.time_for_chars(held);
            self.g05_at = Some(now + crossed + self.settings.format.unit_time_ms.duration());
        }
        self.account(now);
    }

    /// Brings the CNC estimate up to `now`, less [`ESTIMATE_LAG`]: the line's progress comes
    /// in steps, and slots after the last step are judged when the next one comes. Returns
    /// why the stream should end, if its producer has been silent past the idle time while
    /// the CNC ran dry.
    pub fn tick(&mut self, now: Instant) -> Option<EndReason> {
        if let Some(until) = now.checked_sub(ESTIMATE_LAG) {
            self.account(until);
        }
        // Before the G05 block is on the line the CNC waits for nothing yet; it has run dry
        // once a unit time found no block (not merely when the last one was taken).
        let dry = self.g05_at.is_some()
            && self.on_line() <= self.cnc_taken
            && self.slots_seen > self.cnc_taken;
        // Without credits the producer may not send: that is the line's doing, not silence.
        let silent = self.credits() > 0
            && now.saturating_duration_since(self.last_batch_at) >= self.settings.idle;
        if self.closing || !silent {
            return None;
        }
        if self.received == 0 {
            return Some(EndReason::NoBatch);
        }
        dry.then_some(EndReason::ProducerIdle)
    }

    /// Takes the CNC's unit-time slots up to `until`: each takes a block on the line if there
    /// is one, else it is an underrun (§9.2). A block counts from when it was handed to the
    /// line, before it can have arrived, so a slot the estimate finds empty found the CNC
    /// empty too.
    fn account(&mut self, until: Instant) {
        if let Some(at) = self.g05_at {
            let t = self.settings.format.unit_time_ms.duration();
            let slots = (until.saturating_duration_since(at).as_nanos() / t.as_nanos().max(1))
                .try_into()
                .unwrap_or(u64::MAX);
            let new = slots.saturating_sub(self.slots_seen);
            self.slots_seen = self.slots_seen.max(slots);
            let available = self.on_line().saturating_sub(self.cnc_taken);
            let taken = available.min(new);
            self.cnc_taken += taken;
            // After the producer's last block the CNC leaves binary mode: no more slots.
            let done = self.closing && self.cnc_taken >= self.received;
            if !done {
                self.underruns += new - taken;
            }
        }
    }

    /// The link reported the program's end.
    pub fn ended(&mut self, completed: bool, error: Option<String>) {
        self.closing = true;
        self.state = if completed {
            StreamState::Completed
        } else {
            StreamState::Failed
        };
        if error.is_some() {
            self.last_error = error;
        }
    }

    /// Where the stream stands.
    pub fn state(&self) -> StreamState {
        self.state
    }

    /// The stream's figures now.
    pub fn figures(&self) -> StreamFigures {
        let on_line = self.on_line();
        StreamFigures {
            state: self.state,
            credits: self.credits(),
            received: self.received,
            on_line,
            // Followed while the stream runs only: once it is over, the estimate would stand
            // still at what it was, which the CNC no longer holds.
            cnc_buffer: if matches!(self.state, StreamState::Completed | StreamState::Failed) {
                0
            } else {
                on_line.saturating_sub(self.cnc_taken)
            },
            underruns: self.underruns,
            gaps: self.gaps,
            repeats: self.repeats,
            refused: self.refused,
            next_seq: self.next_seq,
            last_error: self.last_error.clone(),
            end_reason: self.end_reason,
        }
    }
}

/// How long the estimated underruns must stay still before a new rise is a new episode of
/// starvation (and a new alarm).
pub const STARVATION_QUIET: Duration = Duration::from_secs(2);

/// What about a stream an operator must hear of as an alarm, not only read in its status.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum G05Alarm {
    /// Unit times found the CNC without a block, as estimated (§9.2): motion stopped. One
    /// alarm per episode (rises closer than [`STARVATION_QUIET`] belong to one).
    Starving {
        /// Estimated underruns this stream so far.
        underruns: u64,
        /// Blocks accepted from the producer so far.
        received: u64,
        /// Blocks handed to the line so far.
        on_line: u64,
    },
    /// The stream ended because nobody fed it: the producer fell silent while the CNC ran
    /// dry, or no batch came after the opening.
    Idle {
        /// [`EndReason::ProducerIdle`] or [`EndReason::NoBatch`].
        reason: EndReason,
    },
}

impl fmt::Display for G05Alarm {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            G05Alarm::Starving {
                underruns,
                received,
                on_line,
            } => write!(
                f,
                "G05 stream starving the CNC: about {underruns} unit times found no block (§9.2; an estimate from the line, see docs/g05.md), {on_line} of {received} blocks on the line: the producer or the line is slower than the CNC"
            ),
            G05Alarm::Idle { reason } => write!(f, "G05 stream ended: {reason}"),
        }
    }
}

/// Watches a stream's figures for what must raise an alarm (see [`G05Alarm`]).
#[derive(Debug, Default)]
pub struct G05Watch {
    underruns: u64,
    last_rise: Option<Instant>,
    ended: bool,
}

impl G05Watch {
    /// A watch that has seen nothing yet.
    pub fn new() -> Self {
        G05Watch::default()
    }

    /// The alarms `figures`, seen at `now`, raise.
    pub fn observe(&mut self, now: Instant, figures: &StreamFigures) -> Vec<G05Alarm> {
        let mut alarms = Vec::new();
        if figures.underruns > self.underruns {
            let new_episode = self
                .last_rise
                .is_none_or(|t| now.saturating_duration_since(t) >= STARVATION_QUIET);
            if new_episode {
                alarms.push(G05Alarm::Starving {
                    underruns: figures.underruns,
                    received: figures.received,
                    on_line: figures.on_line,
                });
            }
            self.underruns = figures.underruns;
            self.last_rise = Some(now);
        }
        if !self.ended
            && let Some(reason @ (EndReason::ProducerIdle | EndReason::NoBatch)) =
                figures.end_reason
        {
            self.ended = true;
            alarms.push(G05Alarm::Idle { reason });
        }
        alarms
    }
}

impl BusCode for BatchError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            BatchError::Credits { .. } => pb::ErrorCode::Busy,
            BatchError::Ended { .. } => pb::ErrorCode::NotFound,
            _ => pb::ErrorCode::InvalidRequest,
        }
    }
}

#[cfg(test)]
mod tests;
