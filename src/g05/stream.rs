//! One G05 stream, sans-IO: batches of blocks in, program chunks out, and the stream's
//! figures — credits, blocks on the line, the CNC's buffer and its underruns as estimated
//! from the line and the unit time (§9.1 (2), §9.2).
//!
//! The stream's program is `before` (NC text ending in the `G05` block), the binary blocks,
//! the end block, and `after`; the engine appends EOR. Blocks are held back until the
//! priming level is reached, because the CNC takes one block every T from the moment it
//! reads `G05`. The gateway holds at most `window` blocks not yet on the line: a batch beyond
//! the credits is refused whole, so memory stays bounded whatever the producer does.

use std::fmt;
use std::time::{Duration, Instant};

use bytes::Bytes;

use crate::fanuc::g05::{AuxWord, G05EncodeError, G05Format};
use crate::fanuc::host::Chunk;

/// How far behind `now` a status tick judges the CNC's slots (see [`Stream::tick`]): a few
/// of the link's progress steps.
pub const ESTIMATE_LAG: Duration = Duration::from_millis(50);

/// What a stream is set up with.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamSettings {
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
}

/// One block as the producer gives it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BlockIn {
    /// One travel per axis, in least input increments.
    pub travels: Vec<i32>,
    pub aux: Option<AuxWord>,
}

/// A batch of blocks, numbered by the producer from 0.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Batch {
    pub seq: u64,
    pub blocks: Vec<BlockIn>,
    /// The producer's last batch: the end block and `after` follow its blocks.
    pub end: bool,
}

/// Why a batch was refused. Nothing of a refused batch is sent.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum BatchError {
    #[error(
        "batch {got} arrived where batch {expected} was due: the blocks between are missing, so \
         the batch is refused (send batch {expected} next)"
    )]
    Gap { expected: u64, got: u64 },
    #[error(
        "batch {seq} holds {blocks} blocks but the stream has {credits} credits (it holds at most \
         {window} blocks not yet on the line): wait for credits"
    )]
    Credits {
        seq: u64,
        blocks: usize,
        credits: u32,
        window: u32,
    },
    #[error("batch {seq}: {error}")]
    Block { seq: u64, error: G05EncodeError },
    #[error("batch {seq} arrived after the stream ended ({state})")]
    Ended { seq: u64, state: StreamState },
}

/// What became of an accepted batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Offered {
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
    Cancelled,
    /// The producer's liveliness token went away.
    ProducerLost,
    /// No batch for the idle time while the CNC ran dry.
    ProducerIdle,
}

impl fmt::Display for EndReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            EndReason::Producer => "the producer ended the stream",
            EndReason::Cancelled => "the stream was cancelled",
            EndReason::ProducerLost => "the producer went away (its liveliness token is gone)",
            EndReason::ProducerIdle => "the producer sent nothing while the CNC ran out of blocks",
        })
    }
}

/// A stream's figures at one moment.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamFigures {
    pub state: StreamState,
    /// Blocks the producer may send now.
    pub credits: u32,
    /// Blocks accepted.
    pub received: u64,
    /// Blocks handed to the line.
    pub on_line: u64,
    /// Blocks estimated in the CNC's buffer (on the line, not yet taken).
    pub cnc_buffer: u64,
    /// Unit-time slots estimated to have found the CNC without a block.
    pub underruns: u64,
    /// Batches refused for a gap, ignored as repeats, refused otherwise.
    pub gaps: u64,
    pub repeats: u64,
    pub refused: u64,
    /// The batch the stream expects next.
    pub next_seq: u64,
    pub last_error: Option<String>,
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
    /// When the `G05` block had gone out: the CNC's unit times count from about then.
    g05_at: Option<Instant>,
    slots_seen: u64,
    cnc_taken: u64,
    underruns: u64,
    last_batch_at: Instant,
    gaps: u64,
    repeats: u64,
    refused: u64,
    last_error: Option<String>,
}

impl Stream {
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
        self.out.push(Chunk::Text(self.settings.before.clone()));
        if !self.held.is_empty() {
            self.out
                .push(Chunk::Binary(Bytes::from(std::mem::take(&mut self.held))));
        }
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

    /// The program's bytes handed to the line so far (the link's progress).
    pub fn on_sent(&mut self, now: Instant, sent: u64) {
        self.sent = self.sent.max(sent);
        if self.g05_at.is_none() && self.primed && self.sent >= self.settings.before.len() as u64 {
            self.g05_at = Some(now);
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
        // Before the G05 block is on the line the CNC waits for nothing yet.
        let dry = self.g05_at.is_some() && self.on_line() <= self.cnc_taken;
        let silent = now.saturating_duration_since(self.last_batch_at) >= self.settings.idle;
        (!self.closing && silent && dry).then_some(EndReason::ProducerIdle)
    }

    /// Takes the CNC's unit-time slots up to `until`: each takes a block on the line if there
    /// is one, else it is an underrun (§9.2).
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

    pub fn state(&self) -> StreamState {
        self.state
    }

    pub fn figures(&self) -> StreamFigures {
        let on_line = self.on_line();
        StreamFigures {
            state: self.state,
            credits: self.credits(),
            received: self.received,
            on_line,
            cnc_buffer: on_line.saturating_sub(self.cnc_taken),
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fanuc::g05::UnitTime;

    fn settings() -> StreamSettings {
        let mut format = G05Format::new(2);
        format.unit_time_ms = UnitTime::Ms8;
        StreamSettings {
            format,
            before: Bytes::from_static(b"G05\n"),
            after: Bytes::from_static(b"M30\n"),
            window: 10,
            prime: 4,
            idle: Duration::from_secs(2),
        }
    }

    fn blocks(n: usize) -> Vec<BlockIn> {
        (0..n)
            .map(|i| BlockIn {
                travels: vec![i as i32 + 1, -1],
                aux: None,
            })
            .collect()
    }

    fn batch(seq: u64, n: usize) -> Batch {
        Batch {
            seq,
            blocks: blocks(n),
            end: false,
        }
    }

    fn binary_len(chunks: &[Chunk]) -> usize {
        chunks
            .iter()
            .map(|c| match c {
                Chunk::Binary(b) => b.len(),
                Chunk::Text(_) => 0,
            })
            .sum()
    }

    #[test]
    fn blocks_wait_for_the_priming_level_then_flow() {
        let t0 = Instant::now();
        let mut s = Stream::new(settings(), t0);
        assert_eq!(s.offer(t0, &batch(0, 3)), Ok(Offered::Accepted));
        assert!(s.take_chunks().is_empty(), "below the priming level");
        assert_eq!(s.credits(), 7);
        assert_eq!(s.offer(t0, &batch(1, 1)), Ok(Offered::Accepted));
        let c = s.take_chunks();
        assert_eq!(c[0], Chunk::Text(Bytes::from_static(b"G05\n")));
        assert_eq!(binary_len(&c), 4 * 5);
        assert_eq!(s.state(), StreamState::Streaming);
        s.offer(t0, &batch(2, 2)).unwrap();
        assert_eq!(binary_len(&s.take_chunks()), 2 * 5);
        // Credits come back as blocks go on the line: "G05\n" and two blocks.
        s.on_sent(t0, 4 + 10);
        assert_eq!(s.figures().on_line, 2);
        assert_eq!(s.credits(), 10 - 4);
    }

    #[test]
    fn gaps_repeats_credits_and_bad_blocks_refuse_the_whole_batch() {
        let t0 = Instant::now();
        let mut s = Stream::new(settings(), t0);
        s.offer(t0, &batch(0, 2)).unwrap();
        assert_eq!(s.offer(t0, &batch(0, 2)), Ok(Offered::Repeat));
        assert!(matches!(
            s.offer(t0, &batch(2, 1)),
            Err(BatchError::Gap {
                expected: 1,
                got: 2
            })
        ));
        assert!(matches!(
            s.offer(t0, &batch(1, 9)),
            Err(BatchError::Credits { credits: 8, .. })
        ));
        let mut bad = batch(1, 3);
        bad.blocks[1].travels = vec![1, 9000];
        let e = s.offer(t0, &bad).unwrap_err();
        assert!(e.to_string().contains("9000"), "{e}");
        let mut short = batch(1, 1);
        short.blocks[0].travels = vec![1];
        assert!(s.offer(t0, &short).is_err());
        let f = s.figures();
        assert_eq!(
            (f.received, f.gaps, f.repeats, f.refused, f.next_seq),
            (2, 1, 1, 3, 1)
        );
        // Nothing of the refused batches was taken: the next good one is block 3.
        s.offer(t0, &batch(1, 2)).unwrap();
        assert_eq!(s.figures().received, 4);
    }

    #[test]
    fn the_end_sends_the_end_block_and_the_closing_text() {
        let t0 = Instant::now();
        let mut s = Stream::new(settings(), t0);
        s.offer(
            t0,
            &Batch {
                seq: 0,
                blocks: blocks(2),
                end: true,
            },
        )
        .unwrap();
        // A short stream ended by its producer is sent whole, priming or not.
        let c = s.take_chunks();
        assert_eq!(c.first(), Some(&Chunk::Text(Bytes::from_static(b"G05\n"))));
        assert_eq!(c.get(2), Some(&Chunk::Binary(Bytes::from(vec![0u8; 5]))));
        assert_eq!(c.last(), Some(&Chunk::Text(Bytes::from_static(b"M30\n"))));
        assert!(s.is_closing());
        assert_eq!(s.credits(), 0);
        assert!(matches!(
            s.offer(t0, &batch(1, 1)),
            Err(BatchError::Ended { .. })
        ));
    }

    #[test]
    fn a_stream_lost_before_its_g05_block_sends_nothing() {
        let t0 = Instant::now();
        let mut s = Stream::new(settings(), t0);
        s.offer(t0, &batch(0, 2)).unwrap();
        s.finish(EndReason::ProducerLost);
        assert!(s.take_chunks().is_empty());
        assert_eq!(s.state(), StreamState::Failed);
    }

    #[test]
    fn underruns_are_estimated_from_the_line_and_the_unit_time() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut s = Stream::new(settings(), t0);
        s.offer(t0, &batch(0, 4)).unwrap();
        s.take_chunks();
        // The G05 block and four blocks on the line at t0.
        s.on_sent(t0, 4 + 20);
        // 8 ms slots: at 40 ms five slots have passed, four found a block (judged with the
        // estimate's lag).
        s.tick(t0 + ms(40) + ESTIMATE_LAG);
        let f = s.figures();
        assert_eq!((f.cnc_buffer, f.underruns), (0, 1));
        // A producer silent for the idle time with the CNC dry is taken as gone.
        assert_eq!(s.tick(t0 + ms(1000)), None);
        assert_eq!(s.tick(t0 + ms(2000)), Some(EndReason::ProducerIdle));
    }
}
