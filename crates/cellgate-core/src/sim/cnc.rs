//! The CNC behind a simulated remote buffer: the board's buffer (8 KiB on the real board,
//! §12.2), the CNC reading it while running, the programs it read, its DI/DO images and its
//! alarm and reset state.
//!
//! The CNC reads from the buffer at a fixed rate while it is "reading" (the operator pressed
//! cycle start in remote mode). Consumption is computed lazily from `now`: no per-byte timer
//! ever runs. What the CNC reads goes through a tape reader that splits programs at EOR
//! (§8.2; protocol notes 8): the first `%` before any other significant character is the
//! tape-start mark, the program ends at the next `%`, and the CNC stops reading there; data
//! after EOR is ignored (dropped from the buffer). A reset loses buffered data (§8.2).
//!
//! With G05 settings ([`Cnc::with_g05`]), the CNC enters binary input operation when it reads
//! the `G05` block (protocol notes 15) and from then on takes one whole block from the buffer
//! every unit time T (§9.1, §9.2), also computed lazily from `now`: slot i falls at
//! entry + i·T, counted from the moment the CNC read the end of the `G05` block. A slot that
//! finds no whole block is an underrun, so the slots between `G05` and the first block that
//! arrive too late count as underruns too. A block arriving at the very instant of a slot is
//! too late for it. The all-zero end block leaves binary mode (text is read at the rate again
//! from that slot on); a wrong check byte raises SR0890 (§11) and leaves it too. Binary
//! blocks are part of the program the CNC reads (its length and SHA-256 cover them).

use std::collections::VecDeque;
use std::fmt;
use std::time::{Duration, Instant};

use bytes::Bytes;
use sha2::{Digest, Sha256};

use crate::fanuc::code::{EOR, is_eor, is_significant};
use crate::fanuc::g05::{BlockDecoder, G05DecodeError, G05Entry, G05Format, InvalidG05Format};
use crate::fanuc::sat::{AlarmCause, BufferStatus};

/// The remote buffer's buffer on the real board: 8 KiB (§12.2).
pub const DEFAULT_BUFFER_SIZE: usize = 8192;

/// Default rate at which a running CNC reads from the buffer, bytes per second.
pub const DEFAULT_CONSUME_RATE: u32 = 2000;

/// Default cap on the bytes of one program kept in memory (its length and SHA-256 always
/// cover all of it).
pub const DEFAULT_KEEP_PROGRAM_BYTES: usize = 16 << 20;

/// Significant auxiliary values kept per binary session ([`G05Stats::aux`]); the count goes on.
pub const MAX_AUX_KEPT: usize = 256;

/// Underrun reports come at most this often ([`G05Notice::Underruns`]).
pub const UNDERRUN_REPORT_INTERVAL: Duration = Duration::from_secs(1);

/// G05 notices kept for the board; older ones are dropped beyond this.
const MAX_NOTICES: usize = 1024;

/// How a binary input session ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum G05End {
    /// The all-zero end block (§9.1).
    EndBlock,
    /// A wrong check byte: SR0890 (§9.1 (9), §11).
    CheckSum,
    /// A CNC reset.
    Reset,
    /// A CNC alarm (other than SR0890).
    Alarm,
}

impl G05End {
    /// The end's name in reports: `end-block`, `check-sum`, `reset` or `alarm`.
    pub fn name(self) -> &'static str {
        match self {
            G05End::EndBlock => "end-block",
            G05End::CheckSum => "check-sum",
            G05End::Reset => "reset",
            G05End::Alarm => "alarm",
        }
    }
}

/// Binary input operation as the CNC saw it: the current session, or the last one when
/// [`G05Stats::active`] is false.
#[derive(Debug, Clone, PartialEq, Eq, Default, serde::Serialize)]
pub struct G05Stats {
    /// In binary input operation now.
    pub active: bool,
    /// Sessions since power-on (times the CNC read `G05`).
    pub sessions: u64,
    /// Blocks taken, the end block not counted.
    pub blocks: u64,
    /// Travel received per axis, least input increments, summed over the blocks.
    pub travel: Vec<i64>,
    /// Significant auxiliary values received, oldest first, the first [`MAX_AUX_KEPT`].
    pub aux: Vec<u32>,
    /// Significant auxiliary values received.
    pub aux_count: u64,
    /// Unit times that found no whole block in the buffer (§9.2), from the `G05` block on.
    pub underruns: u64,
    /// Fewest whole blocks in the buffer at a unit time (before it took its block; an end
    /// block waiting counts), from the one that took the first block on; `None` before the
    /// first block. 0 once a unit time found none after the first block.
    pub min_buffered_blocks: Option<u64>,
    /// How the session ended; `None` while it runs.
    pub end: Option<G05End>,
}

/// What binary input operation did, for the board to report.
#[derive(Debug, Clone, PartialEq)]
pub enum G05Notice {
    /// The CNC read the `G05` block at `at`.
    Entered {
        /// When the CNC read the `G05` block.
        at: Instant,
    },
    /// `new` underruns since the last report, `total` this session (at most one a second).
    Underruns {
        /// Underruns since the last report.
        new: u64,
        /// Underruns this session.
        total: u64,
    },
    /// A block with a wrong check byte: the CNC raised SR0890 and stopped (a `Left` follows).
    CheckSum(G05DecodeError),
    /// Binary input operation ended, with the session's totals.
    Left {
        /// How the session ended.
        end: G05End,
        /// The session's totals.
        stats: G05Stats,
    },
}

/// A program the CNC read, from its tape-start `%` (or first significant character) through
/// the `%` that ended it, byte-exact as it left the buffer (after any SET code conversion).
#[derive(Clone, PartialEq, Eq)]
pub struct ReceivedProgram {
    /// The program's bytes; only the first `keep_program_bytes` when `truncated`.
    pub data: Bytes,
    /// Length of the whole program.
    pub len: u64,
    /// SHA-256 of the whole program.
    pub sha256: [u8; 32],
    /// The first line of text after the tape-start mark, e.g. `O1234`.
    pub first_line: String,
    /// Whether `data` holds only the start of the program.
    pub truncated: bool,
}

impl ReceivedProgram {
    /// The SHA-256 of the program as lower-case hex.
    pub fn sha256_hex(&self) -> String {
        hex::encode(self.sha256)
    }
}

impl fmt::Debug for ReceivedProgram {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ReceivedProgram")
            .field("len", &self.len)
            .field("sha256", &self.sha256_hex())
            .field("first_line", &self.first_line)
            .field("truncated", &self.truncated)
            .finish()
    }
}

/// Splits what the CNC reads into programs at EOR.
#[derive(Debug)]
struct Tape {
    in_program: bool,
    data: Vec<u8>,
    /// The program's first bytes, for its first line even when `data` keeps fewer.
    head: Vec<u8>,
    len: u64,
    hasher: Sha256,
    keep: usize,
}

/// Bytes kept for the first line.
const HEAD: usize = 256;

impl Tape {
    fn new(keep: usize) -> Self {
        Tape {
            in_program: false,
            data: Vec::new(),
            head: Vec::new(),
            len: 0,
            hasher: Sha256::new(),
            keep,
        }
    }

    fn push(&mut self, b: u8) {
        self.len += 1;
        self.hasher.update([b]);
        if self.data.len() < self.keep {
            self.data.push(b);
        }
        if self.head.len() < HEAD {
            self.head.push(b);
        }
    }

    /// Reads one byte; returns the program it completes.
    fn feed(&mut self, b: u8) -> Option<ReceivedProgram> {
        if !self.in_program {
            if !is_significant(b) {
                return None;
            }
            // The tape-start `%` or the program's first character: neither ends a program.
            self.in_program = true;
            self.push(b);
            return None;
        }
        self.push(b);
        is_eor(b).then(|| self.finish())
    }

    fn finish(&mut self) -> ReceivedProgram {
        let hasher = std::mem::take(&mut self.hasher);
        let data = std::mem::take(&mut self.data);
        let head = std::mem::take(&mut self.head);
        let len = std::mem::take(&mut self.len);
        self.in_program = false;
        ReceivedProgram {
            first_line: first_line(&head),
            truncated: (data.len() as u64) < len,
            data: Bytes::from(data),
            len,
            sha256: hasher.finalize().into(),
        }
    }

    /// Forgets a partly read program (CNC reset).
    fn reset(&mut self) {
        *self = Tape::new(self.keep);
    }
}

/// The first line of a program's text: after the tape-start `%` and blank lines, up to the
/// end of block (LF, CR or `;`), parity stripped.
fn first_line(data: &[u8]) -> String {
    let text = data
        .iter()
        .map(|&b| b & 0x7F)
        .skip_while(|&c| c == EOR || !is_significant(c))
        .take_while(|&c| !matches!(c, b'\n' | b'\r' | b';') && c != EOR)
        .take(80)
        .map(|c| {
            if c.is_ascii_graphic() || c == b' ' {
                c as char
            } else {
                '?'
            }
        })
        .collect::<String>();
    text.trim().to_string()
}

/// What happened to NC data handed to the CNC's buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Push {
    /// Stored in the buffer.
    Stored(usize),
    /// The CNC is not reading (stopped at EOR, reset, alarm): the data is ignored (§8.2).
    Ignored(usize),
    /// More data than free space: the host ignored the stop request (§4.6 1 (5)).
    Overflow {
        /// Bytes handed over; none were stored.
        len: usize,
        /// Free space in the buffer, bytes.
        free: usize,
    },
}

/// The CNC and its buffer.
#[derive(Debug)]
pub struct Cnc {
    capacity: usize,
    /// Bytes per second; 0 = as fast as data arrives.
    rate: u32,
    buffer: VecDeque<u8>,
    reading: bool,
    /// Consumption is `rate` bytes per second since `anchor`, of which `anchor_consumed`
    /// were already taken. Re-anchored whenever the buffer runs empty, so that a starved CNC
    /// banks no credit.
    anchor: Instant,
    anchor_consumed: u64,
    alarm: Option<AlarmCause>,
    di: u8,
    do_image: u8,
    tape: Tape,
    finished: VecDeque<ReceivedProgram>,
    read_total: u64,
    scan: EndScan,
    /// G05 binary input operation, when the CNC has the settings for it.
    g05: Option<Box<G05Cnc>>,
}

/// The CNC's side of G05 binary input operation (§9).
#[derive(Debug)]
struct G05Cnc {
    format: G05Format,
    unit: Duration,
    len: usize,
    decoder: BlockDecoder,
    /// Finds the `G05` block in what the CNC reads as text.
    entry: G05Entry,
    /// Set while in binary mode.
    slots: Option<Slots>,
    stats: G05Stats,
    notices: VecDeque<G05Notice>,
    /// Underruns not reported yet.
    pending: u64,
    last_report: Option<Instant>,
}

/// The unit-time grid of binary mode and the blocks waiting in the buffer.
#[derive(Debug, Clone, Copy)]
struct Slots {
    /// Slot i (i ≥ 1) falls at `base` + i·T.
    base: Instant,
    /// Slots handled since `base`.
    done: u64,
    /// Whole blocks at the front of the buffer that the CNC will take: through the first end
    /// block or block with a wrong check byte, after which the bytes are no blocks.
    blocks: usize,
    /// Such a last block is among `blocks`.
    stopped: bool,
}

impl Slots {
    fn at(&self, unit: Duration, slot: u64) -> Instant {
        let nanos = unit.as_nanos().saturating_mul(u128::from(slot));
        self.base + Duration::from_nanos(u64::try_from(nanos).unwrap_or(u64::MAX))
    }
}

/// Where the `%` ending the current program sits in the buffer, or the end of a `G05` block
/// before it, found incrementally as data arrives (so that deadlines cost nothing per call).
#[derive(Debug, Clone, Copy, Default)]
struct EndScan {
    /// Buffer bytes looked at.
    scanned: usize,
    /// The tape reader's state after those bytes.
    in_program: bool,
    /// The `G05` block finder's state after those bytes (without G05 settings: none).
    entry: Option<G05Entry>,
    found: Option<Found>,
}

/// What the scan found first.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Found {
    /// The `%` ending the program, at this index.
    Eor(usize),
    /// The end of a `G05` block at this index: binary data follows (the scan stops there).
    G05(usize),
}

impl Found {
    fn index(self) -> usize {
        match self {
            Found::Eor(i) | Found::G05(i) => i,
        }
    }
    fn shifted(self, k: usize) -> Option<Found> {
        Some(match self {
            Found::Eor(i) => Found::Eor(i.checked_sub(k)?),
            Found::G05(i) => Found::G05(i.checked_sub(k)?),
        })
    }
}

impl EndScan {
    fn restart(in_program: bool, entry: Option<G05Entry>) -> Self {
        EndScan {
            scanned: 0,
            in_program,
            entry,
            found: None,
        }
    }

    fn extend(&mut self, buffer: &VecDeque<u8>) {
        if self.found.is_some() {
            return;
        }
        for (i, &b) in buffer.iter().enumerate().skip(self.scanned) {
            // As the reader does: the G05 finder sees every byte, EOR ends the program.
            let entered = self.entry.as_mut().is_some_and(|e| e.feed(b));
            if !self.in_program {
                self.in_program = is_significant(b);
            } else if is_eor(b) {
                self.found = Some(Found::Eor(i));
                self.scanned = i + 1;
                return;
            }
            if entered {
                self.found = Some(Found::G05(i));
                self.scanned = i + 1;
                return;
            }
        }
        self.scanned = buffer.len();
    }

    /// `k` bytes left the front of the buffer (without completing a program).
    fn consumed(&mut self, k: usize) {
        self.scanned = self.scanned.saturating_sub(k);
        self.found = self.found.and_then(|f| f.shifted(k));
    }
}

/// Where reading text stopped.
enum TextStop {
    /// Budget or buffer exhausted, EOR reached, or not reading.
    Done,
    /// The CNC read the end of the `G05` block at this time.
    G05(Instant),
}

/// Where binary mode stopped.
enum BinaryStop {
    /// Waiting for the next slot, or stopped by SR0890.
    Done,
    /// The end block was taken at this time: text follows.
    Left(Instant),
}

impl Cnc {
    /// A CNC with a buffer of `capacity` bytes that reads `rate` bytes per second (0: as fast as
    /// data arrives) and keeps at most `keep_program_bytes` of each program; not reading yet.
    pub fn new(capacity: usize, rate: u32, keep_program_bytes: usize, now: Instant) -> Self {
        Cnc {
            capacity,
            rate,
            buffer: VecDeque::with_capacity(capacity.min(1 << 16)),
            reading: false,
            anchor: now,
            anchor_consumed: 0,
            alarm: None,
            di: 0,
            do_image: 0,
            tape: Tape::new(keep_program_bytes),
            finished: VecDeque::new(),
            read_total: 0,
            scan: EndScan::default(),
            g05: None,
        }
    }

    /// The CNC with G05 binary input operation set up as `format` says (§9, §10.3).
    pub fn with_g05(mut self, format: G05Format) -> Result<Self, InvalidG05Format> {
        let decoder = BlockDecoder::new(format)?;
        let g = G05Cnc {
            format,
            unit: format.unit_time_ms.duration(),
            len: format.block_len(),
            decoder,
            entry: G05Entry::default(),
            slots: None,
            stats: G05Stats::default(),
            notices: VecDeque::new(),
            pending: 0,
            last_report: None,
        };
        self.scan = EndScan::restart(self.tape.in_program, Some(g.entry));
        self.scan.extend(&self.buffer);
        self.g05 = Some(Box::new(g));
        Ok(self)
    }

    /// Size of the buffer, bytes.
    pub fn capacity(&self) -> usize {
        self.capacity
    }
    /// Bytes in the buffer.
    pub fn buffered(&self) -> usize {
        self.buffer.len()
    }
    /// Free space in the buffer, bytes.
    pub fn free(&self) -> usize {
        self.capacity.saturating_sub(self.buffer.len())
    }
    /// Whether the CNC is reading (cycle start in remote mode).
    pub fn reading(&self) -> bool {
        self.reading
    }
    /// The cause of the CNC's alarm; `None` when it is not in alarm.
    pub fn alarm(&self) -> Option<AlarmCause> {
        self.alarm
    }
    /// The DI image, which the board reports in SDI.
    pub fn di(&self) -> u8 {
        self.di
    }
    /// The DO image the host last output (SDO).
    pub fn do_image(&self) -> u8 {
        self.do_image
    }
    /// Bytes per second the CNC reads while running; 0 = as fast as data arrives.
    pub fn consume_rate(&self) -> u32 {
        self.rate
    }
    /// Bytes the CNC has read from the buffer since power-on.
    pub fn read_total(&self) -> u64 {
        self.read_total
    }

    /// The G05 settings, when the CNC has binary input operation.
    pub fn g05_format(&self) -> Option<&G05Format> {
        self.g05.as_ref().map(|g| &g.format)
    }
    /// Binary input operation of the current or last session, when the CNC has it.
    pub fn g05_stats(&self) -> Option<&G05Stats> {
        self.g05.as_ref().map(|g| &g.stats)
    }
    /// Whether the CNC is in binary input operation.
    pub fn in_binary(&self) -> bool {
        self.g05.as_ref().is_some_and(|g| g.slots.is_some())
    }
    /// What binary input operation did since the last call, oldest first.
    pub fn take_g05_notice(&mut self) -> Option<G05Notice> {
        self.g05.as_mut()?.notices.pop_front()
    }

    /// Byte 2 of SAT (§4.4.2): alarm, operating (reading) or reset.
    pub fn status(&self) -> BufferStatus {
        if self.alarm.is_some() {
            BufferStatus::Alarm
        } else if self.reading {
            BufferStatus::Operating
        } else {
            BufferStatus::Reset
        }
    }

    fn allowed(&self, now: Instant) -> u64 {
        if self.rate == 0 {
            return u64::MAX;
        }
        let nanos = now.saturating_duration_since(self.anchor).as_nanos();
        u64::try_from(nanos * u128::from(self.rate) / 1_000_000_000).unwrap_or(u64::MAX)
    }

    /// When the `total`-th byte since the anchor is read.
    fn consumed_at(&self, total: u64) -> Instant {
        if self.rate == 0 {
            return self.anchor;
        }
        let nanos = (u128::from(total) * 1_000_000_000).div_ceil(u128::from(self.rate));
        self.anchor + Duration::from_nanos(u64::try_from(nanos).unwrap_or(u64::MAX))
    }

    fn reanchor(&mut self, now: Instant) {
        self.anchor = now;
        self.anchor_consumed = 0;
    }

    /// Lets the CNC read what it could have read by `now`. Programs it completes are queued
    /// for [`Cnc::take_finished`], what binary input operation did for
    /// [`Cnc::take_g05_notice`].
    pub fn advance(&mut self, now: Instant) {
        if !self.reading {
            self.reanchor(now);
            return;
        }
        // Each turn either ends the call or changes mode at a time not after `now`.
        loop {
            if self.in_binary() {
                match self.advance_binary(now) {
                    BinaryStop::Done => return,
                    BinaryStop::Left(at) => self.reanchor(at),
                }
            }
            match self.advance_text(now) {
                TextStop::Done => return,
                TextStop::G05(at) => self.enter_binary(at),
            }
        }
    }

    /// Text at the consumption rate, up to EOR or the end of a `G05` block.
    fn advance_text(&mut self, now: Instant) -> TextStop {
        let mut budget = self.allowed(now).saturating_sub(self.anchor_consumed);
        let mut taken = 0;
        let mut stop = TextStop::Done;
        while budget > 0 {
            let Some(b) = self.buffer.pop_front() else {
                break;
            };
            budget -= 1;
            taken += 1;
            self.anchor_consumed += 1;
            self.read_total += 1;
            let entered = self.g05.as_mut().is_some_and(|g| g.entry.feed(b));
            if let Some(program) = self.tape.feed(b) {
                // The CNC stops at EOR and ignores everything after it (§8.2).
                self.finished.push_back(program);
                self.reading = false;
                self.buffer.clear();
                self.restart_scan();
                taken = 0;
                break;
            }
            if entered {
                stop = TextStop::G05(self.consumed_at(self.anchor_consumed));
                break;
            }
        }
        self.scan.consumed(taken);
        if matches!(stop, TextStop::Done) && (self.buffer.is_empty() || !self.reading) {
            self.reanchor(now);
        }
        stop
    }

    fn restart_scan(&mut self) {
        let entry = self.g05.as_ref().map(|g| g.entry);
        self.scan = EndScan::restart(self.tape.in_program, entry);
        self.scan.extend(&self.buffer);
    }

    /// The CNC read the `G05` block at `at` (protocol notes 15): binary mode, slots from `at`.
    fn enter_binary(&mut self, at: Instant) {
        let Some(g) = self.g05.as_mut() else {
            return;
        };
        g.decoder.clear();
        g.pending = 0;
        g.last_report = None;
        g.stats = G05Stats {
            active: true,
            sessions: g.stats.sessions.saturating_add(1),
            travel: vec![0; usize::from(g.format.axes)],
            ..G05Stats::default()
        };
        g.slots = Some(Slots {
            base: at,
            done: 0,
            blocks: 0,
            stopped: false,
        });
        notify(&mut g.notices, G05Notice::Entered { at });
        self.count_blocks();
    }

    /// Extends the count of whole blocks waiting at the front of the buffer.
    fn count_blocks(&mut self) {
        let Some(g) = self.g05.as_mut() else {
            return;
        };
        let len = g.len;
        let Some(s) = g.slots.as_mut() else {
            return;
        };
        while !s.stopped && len > 0 {
            let start = s.blocks * len;
            let end = start + len;
            if self.buffer.len() < end {
                break;
            }
            let (mut sum, mut ck, mut zero) = (0u8, 0u8, true);
            for (i, &b) in self.buffer.range(start..end).enumerate() {
                if i + 1 < len {
                    sum = sum.wrapping_add(b);
                } else {
                    ck = b;
                }
                zero &= b == 0;
            }
            s.blocks += 1;
            // The end block, or SR0890: the CNC takes nothing after it as a block.
            s.stopped = zero || sum != ck;
        }
    }

    /// Binary mode: one whole block every unit time, up to `now`.
    fn advance_binary(&mut self, now: Instant) -> BinaryStop {
        let Some(g) = self.g05.as_mut() else {
            return BinaryStop::Done;
        };
        let Some(mut s) = g.slots else {
            return BinaryStop::Done;
        };
        let elapsed = now.saturating_duration_since(s.base).as_nanos();
        let due = u64::try_from(elapsed / g.unit.as_nanos().max(1)).unwrap_or(u64::MAX);
        let len = g.len;
        let mut stop = None;
        while s.done < due {
            if s.blocks == 0 {
                // No whole block, and none arrives within this call: every slot up to now
                // is an underrun.
                let n = due - s.done;
                g.stats.underruns = g.stats.underruns.saturating_add(n);
                g.pending = g.pending.saturating_add(n);
                if g.stats.blocks > 0 {
                    g.stats.min_buffered_blocks = Some(0);
                }
                s.done = due;
                break;
            }
            let slot = s.done + 1;
            let at = s.at(g.unit, slot);
            let whole = s.blocks as u64;
            s.done = slot;
            s.blocks -= 1;
            let mut result = None;
            for _ in 0..len {
                let b = self.buffer.pop_front().unwrap_or(0);
                self.tape.push(b);
                result = g.decoder.push(b).or(result);
            }
            self.read_total = self.read_total.saturating_add(len as u64);
            match result {
                Some(Ok(block)) if block.is_end() => {
                    stop = Some(Ok(at));
                    break;
                }
                Some(Ok(block)) => {
                    let st = &mut g.stats;
                    st.blocks = st.blocks.saturating_add(1);
                    for (sum, &t) in st.travel.iter_mut().zip(block.travels()) {
                        *sum = sum.saturating_add(i64::from(t));
                    }
                    if let Some(aux) = block.aux()
                        && aux.significant
                    {
                        st.aux_count = st.aux_count.saturating_add(1);
                        if st.aux.len() < MAX_AUX_KEPT {
                            st.aux.push(aux.value);
                        }
                    }
                    st.min_buffered_blocks =
                        Some(st.min_buffered_blocks.map_or(whole, |m| m.min(whole)));
                }
                Some(Err(e)) => {
                    stop = Some(Err(e));
                    break;
                }
                // A whole block always completes one.
                None => {}
            }
        }
        g.slots = Some(s);
        if g.pending > 0
            && g.last_report
                .is_none_or(|t| now >= t + UNDERRUN_REPORT_INTERVAL)
        {
            let new = std::mem::take(&mut g.pending);
            let total = g.stats.underruns;
            notify(&mut g.notices, G05Notice::Underruns { new, total });
            g.last_report = Some(now);
        }
        match stop {
            None => BinaryStop::Done,
            Some(Ok(at)) => {
                self.leave_binary(G05End::EndBlock);
                BinaryStop::Left(at)
            }
            Some(Err(e)) => {
                // SR0890: the CNC stops in alarm (§11).
                if let Some(g) = self.g05.as_mut() {
                    notify(&mut g.notices, G05Notice::CheckSum(e));
                }
                self.leave_binary(G05End::CheckSum);
                self.reading = false;
                self.alarm = Some(AlarmCause::NcAlarm);
                BinaryStop::Done
            }
        }
    }

    /// Ends binary mode (no-op outside it); the CNC reads text again.
    fn leave_binary(&mut self, end: G05End) {
        let Some(g) = self.g05.as_mut() else {
            return;
        };
        if g.slots.take().is_none() {
            return;
        }
        g.pending = 0;
        g.entry.reset();
        g.decoder.clear();
        g.stats.active = false;
        g.stats.end = Some(end);
        let stats = g.stats.clone();
        notify(&mut g.notices, G05Notice::Left { end, stats });
        self.restart_scan();
    }

    /// Programs completed since the last call, oldest first.
    pub fn take_finished(&mut self) -> Option<ReceivedProgram> {
        self.finished.pop_front()
    }

    /// Cycle start in remote mode. Refused (false) while the CNC is in alarm. In binary mode
    /// the unit times start again from now (feed hold stops them, §9.3 4).
    pub fn start_reading(&mut self, now: Instant) -> bool {
        self.advance(now);
        if self.alarm.is_some() {
            return false;
        }
        if !self.reading {
            self.reading = true;
            self.reanchor(now);
            if let Some(s) = self.g05.as_mut().and_then(|g| g.slots.as_mut()) {
                s.base = now;
                s.done = 0;
            }
        }
        true
    }

    /// The CNC stops reading at `now`; the buffer keeps what it holds.
    pub fn stop_reading(&mut self, now: Instant) {
        self.advance(now);
        self.reading = false;
    }

    /// From `now` on the CNC reads `rate` bytes per second (0: as fast as data arrives).
    pub fn set_rate(&mut self, now: Instant, rate: u32) {
        self.advance(now);
        self.rate = rate;
        self.reanchor(now);
    }

    /// NC data from the host, appended to the buffer while the CNC is reading.
    pub fn push_data(&mut self, now: Instant, data: &[u8]) -> Push {
        self.advance(now);
        if !self.reading {
            return Push::Ignored(data.len());
        }
        let free = self.free();
        if data.len() > free {
            return Push::Overflow {
                len: data.len(),
                free,
            };
        }
        if self.buffer.is_empty() {
            self.reanchor(now);
        }
        self.buffer.extend(data.iter().copied());
        if self.in_binary() {
            self.count_blocks();
        } else {
            self.scan.extend(&self.buffer);
        }
        Push::Stored(data.len())
    }

    /// CLB (§4.4.1).
    pub fn clear_buffer(&mut self, now: Instant) {
        self.advance(now);
        self.buffer.clear();
        if let Some(s) = self.g05.as_mut().and_then(|g| g.slots.as_mut()) {
            s.blocks = 0;
            s.stopped = false;
        }
        self.restart_scan();
        self.reanchor(now);
    }

    /// CNC reset: stops reading, clears the alarm, and loses the buffered data and any partly
    /// read program (§8.2); ends binary mode.
    pub fn reset(&mut self, now: Instant) {
        self.advance(now);
        self.buffer.clear();
        self.reading = false;
        self.alarm = None;
        self.tape.reset();
        self.leave_binary(G05End::Reset);
        if let Some(g) = self.g05.as_mut() {
            g.entry.reset();
        }
        self.restart_scan();
        self.reanchor(now);
    }

    /// The CNC goes to alarm: it stops reading until it is reset, and leaves binary mode.
    pub fn raise_alarm(&mut self, now: Instant, cause: AlarmCause) {
        self.advance(now);
        self.reading = false;
        self.alarm = Some(cause);
        self.leave_binary(G05End::Alarm);
    }

    /// Sets the DI image.
    pub fn set_di(&mut self, di: u8) {
        self.di = di;
    }
    /// Sets the DO image (an SDO from the host).
    pub fn set_do(&mut self, image: u8) {
        self.do_image = image;
    }

    /// When the CNC will have read `k` more bytes of text, if it is reading.
    fn when_consumed(&self, k: usize) -> Option<Instant> {
        if !self.reading || k == 0 {
            return None;
        }
        if self.rate == 0 {
            return Some(self.anchor);
        }
        let need = u128::from(self.anchor_consumed) + k as u128;
        let nanos = (need * 1_000_000_000).div_ceil(u128::from(self.rate));
        Some(self.anchor + Duration::from_nanos(u64::try_from(nanos).ok()?))
    }

    /// When the CNC will read the EOR now in its buffer. `None` in binary mode, or when a
    /// `G05` block comes first: the time is known once the binary data has been read.
    pub fn when_program_ends(&self) -> Option<Instant> {
        if !self.reading || self.in_binary() {
            return None;
        }
        match self.scan.found? {
            Found::Eor(i) => self.when_consumed(i + 1),
            Found::G05(_) => None,
        }
    }

    /// When free space will reach `free` bytes, if it is below that now and the CNC reads.
    /// Past the end of a `G05` block or of the blocks buffered in binary mode, the time the
    /// CNC gets there: the owner asks again then.
    pub fn when_free_at_least(&self, free: usize) -> Option<Instant> {
        let target = self.capacity.saturating_sub(free);
        let excess = self.buffer.len().checked_sub(target)?;
        if let Some(g) = self.g05.as_ref()
            && let Some(s) = g.slots
        {
            if !self.reading || excess == 0 || g.len == 0 {
                return None;
            }
            let blocks = excess.div_ceil(g.len).min(s.blocks);
            if blocks == 0 {
                return None;
            }
            return Some(s.at(g.unit, s.done + blocks as u64));
        }
        match self.scan.found {
            Some(found @ Found::G05(_)) if excess > found.index() + 1 => {
                self.when_consumed(found.index() + 1)
            }
            _ => self.when_consumed(excess),
        }
    }

    /// When binary input operation next needs the CNC's time: the end of a `G05` block in
    /// the buffer, the next unit time with a whole block waiting, or (while no block waits)
    /// the next underrun report, at most one a second.
    pub fn next_g05_deadline(&self) -> Option<Instant> {
        let g = self.g05.as_ref()?;
        if !self.reading {
            return None;
        }
        let Some(s) = g.slots else {
            return match self.scan.found? {
                Found::G05(i) => self.when_consumed(i + 1),
                Found::Eor(_) => None,
            };
        };
        let next = s.at(g.unit, s.done.saturating_add(1));
        if s.blocks > 0 {
            return Some(next);
        }
        Some(match g.last_report {
            None => next,
            Some(t) => next.max(t + UNDERRUN_REPORT_INTERVAL),
        })
    }
}

/// Queues a notice for the board, dropping the oldest beyond [`MAX_NOTICES`].
fn notify(notices: &mut VecDeque<G05Notice>, notice: G05Notice) {
    if notices.len() >= MAX_NOTICES {
        notices.pop_front();
    }
    notices.push_back(notice);
}

#[cfg(test)]
mod tests;
