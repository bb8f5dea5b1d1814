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

use std::collections::VecDeque;
use std::fmt;
use std::time::{Duration, Instant};

use bytes::Bytes;
use sha2::{Digest, Sha256};

use crate::fanuc::code::{EOR, is_eor, is_significant};
use crate::fanuc::sat::{AlarmCause, BufferStatus};

/// The remote buffer's buffer on the real board: 8 KiB (§12.2).
pub const DEFAULT_BUFFER_SIZE: usize = 8192;

/// Default rate at which a running CNC reads from the buffer, bytes per second.
pub const DEFAULT_CONSUME_RATE: u32 = 2000;

/// Default cap on the bytes of one program kept in memory (its length and SHA-256 always
/// cover all of it).
pub const DEFAULT_KEEP_PROGRAM_BYTES: usize = 16 << 20;

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
    Overflow { len: usize, free: usize },
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
}

/// Where the `%` ending the current program sits in the buffer, found incrementally as data
/// arrives (so that deadlines cost nothing per call).
#[derive(Debug, Clone, Copy, Default)]
struct EndScan {
    /// Buffer bytes looked at.
    scanned: usize,
    /// The tape reader's state after those bytes.
    in_program: bool,
    /// Index of the ending `%`, once seen.
    found: Option<usize>,
}

impl EndScan {
    fn restart(in_program: bool) -> Self {
        EndScan {
            scanned: 0,
            in_program,
            found: None,
        }
    }

    fn extend(&mut self, buffer: &VecDeque<u8>) {
        if self.found.is_some() {
            return;
        }
        for (i, &b) in buffer.iter().enumerate().skip(self.scanned) {
            if !self.in_program {
                self.in_program = is_significant(b);
            } else if is_eor(b) {
                self.found = Some(i);
                self.scanned = i + 1;
                return;
            }
        }
        self.scanned = buffer.len();
    }

    /// `k` bytes left the front of the buffer (without completing a program).
    fn consumed(&mut self, k: usize) {
        self.scanned = self.scanned.saturating_sub(k);
        self.found = self.found.and_then(|i| i.checked_sub(k));
    }
}

impl Cnc {
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
        }
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }
    pub fn buffered(&self) -> usize {
        self.buffer.len()
    }
    pub fn free(&self) -> usize {
        self.capacity.saturating_sub(self.buffer.len())
    }
    pub fn reading(&self) -> bool {
        self.reading
    }
    pub fn alarm(&self) -> Option<AlarmCause> {
        self.alarm
    }
    pub fn di(&self) -> u8 {
        self.di
    }
    pub fn do_image(&self) -> u8 {
        self.do_image
    }
    pub fn consume_rate(&self) -> u32 {
        self.rate
    }
    /// Bytes the CNC has read from the buffer since power-on.
    pub fn read_total(&self) -> u64 {
        self.read_total
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

    fn reanchor(&mut self, now: Instant) {
        self.anchor = now;
        self.anchor_consumed = 0;
    }

    /// Lets the CNC read what it could have read by `now`. Programs it completes are queued
    /// for [`Cnc::take_finished`].
    pub fn advance(&mut self, now: Instant) {
        if !self.reading {
            self.reanchor(now);
            return;
        }
        let mut budget = self.allowed(now).saturating_sub(self.anchor_consumed);
        let mut taken = 0;
        while budget > 0 {
            let Some(b) = self.buffer.pop_front() else {
                break;
            };
            budget -= 1;
            taken += 1;
            self.anchor_consumed += 1;
            self.read_total += 1;
            if let Some(program) = self.tape.feed(b) {
                // The CNC stops at EOR and ignores everything after it (§8.2).
                self.finished.push_back(program);
                self.reading = false;
                self.buffer.clear();
                self.scan = EndScan::restart(self.tape.in_program);
                taken = 0;
                break;
            }
        }
        self.scan.consumed(taken);
        if self.buffer.is_empty() || !self.reading {
            self.reanchor(now);
        }
    }

    /// Programs completed since the last call, oldest first.
    pub fn take_finished(&mut self) -> Option<ReceivedProgram> {
        self.finished.pop_front()
    }

    /// Cycle start in remote mode. Refused (false) while the CNC is in alarm.
    pub fn start_reading(&mut self, now: Instant) -> bool {
        self.advance(now);
        if self.alarm.is_some() {
            return false;
        }
        if !self.reading {
            self.reading = true;
            self.reanchor(now);
        }
        true
    }

    pub fn stop_reading(&mut self, now: Instant) {
        self.advance(now);
        self.reading = false;
    }

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
        self.scan.extend(&self.buffer);
        Push::Stored(data.len())
    }

    /// CLB (§4.4.1).
    pub fn clear_buffer(&mut self, now: Instant) {
        self.advance(now);
        self.buffer.clear();
        self.scan = EndScan::restart(self.tape.in_program);
        self.reanchor(now);
    }

    /// CNC reset: stops reading, clears the alarm, and loses the buffered data and any partly
    /// read program (§8.2).
    pub fn reset(&mut self, now: Instant) {
        self.advance(now);
        self.buffer.clear();
        self.reading = false;
        self.alarm = None;
        self.tape.reset();
        self.scan = EndScan::restart(false);
        self.reanchor(now);
    }

    /// The CNC goes to alarm: it stops reading until it is reset.
    pub fn raise_alarm(&mut self, now: Instant, cause: AlarmCause) {
        self.advance(now);
        self.reading = false;
        self.alarm = Some(cause);
    }

    pub fn set_di(&mut self, di: u8) {
        self.di = di;
    }
    pub fn set_do(&mut self, image: u8) {
        self.do_image = image;
    }

    /// When the CNC will have read `k` more bytes, if it is reading.
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

    /// When the CNC will read the EOR now in its buffer.
    pub fn when_program_ends(&self) -> Option<Instant> {
        if !self.reading {
            return None;
        }
        self.when_consumed(self.scan.found? + 1)
    }

    /// When free space will reach `free` bytes, if it is below that now and the CNC reads.
    pub fn when_free_at_least(&self, free: usize) -> Option<Instant> {
        let target = self.capacity.saturating_sub(free);
        let excess = self.buffer.len().checked_sub(target)?;
        self.when_consumed(excess)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn secs(s: f64) -> Duration {
        Duration::from_secs_f64(s)
    }

    #[test]
    fn consumes_at_rate_lazily() {
        let t0 = Instant::now();
        let mut cnc = Cnc::new(8192, 1000, 1 << 20, t0);
        assert!(cnc.start_reading(t0));
        assert_eq!(cnc.push_data(t0, &[b'X'; 3000]), Push::Stored(3000));
        cnc.advance(t0 + secs(1.0));
        assert_eq!(cnc.buffered(), 2000);
        cnc.advance(t0 + secs(1.5));
        assert_eq!(cnc.buffered(), 1500);
        // Free reaches 7692 once 1000 more are read: at 2.5 s.
        assert_eq!(cnc.when_free_at_least(8192 - 500), Some(t0 + secs(2.5)));
        cnc.advance(t0 + secs(10.0));
        assert_eq!(cnc.buffered(), 0);
        // Starved for 7 s: no credit banked; new data is read at the rate again.
        cnc.push_data(t0 + secs(10.0), &[b'Y'; 100]);
        cnc.advance(t0 + secs(10.05));
        assert_eq!(cnc.buffered(), 50);
        assert_eq!(cnc.read_total(), 3050);
    }

    #[test]
    fn splits_programs_at_eor_and_ignores_the_rest() {
        let t0 = Instant::now();
        let mut cnc = Cnc::new(8192, 100, 1 << 20, t0);
        cnc.start_reading(t0);
        let tape = b"\n\n%\nO1234 (TEST)\nG01 X1.\nM30\n%\nIGNORED";
        cnc.push_data(t0, tape);
        let end = cnc.when_program_ends().unwrap();
        // Leader (2) + program through the second % (28): 30 bytes at 100 B/s.
        assert_eq!(end, t0 + secs(0.30));
        cnc.advance(end - Duration::from_nanos(1));
        assert!(cnc.take_finished().is_none());
        cnc.advance(end);
        let p = cnc.take_finished().unwrap();
        assert_eq!(&p.data[..], b"%\nO1234 (TEST)\nG01 X1.\nM30\n%");
        assert_eq!(p.first_line, "O1234 (TEST)");
        assert_eq!(p.len, 28);
        assert_eq!(p.sha256.to_vec(), Sha256::digest(&p.data).to_vec());
        assert!(!cnc.reading());
        assert_eq!(cnc.buffered(), 0, "data after EOR is ignored");
        assert_eq!(cnc.push_data(end, b"more"), Push::Ignored(4));
    }

    #[test]
    fn program_end_found_across_pieces_and_consumption() {
        let t0 = Instant::now();
        let mut cnc = Cnc::new(8192, 10, 1 << 20, t0);
        cnc.start_reading(t0);
        cnc.push_data(t0, b"\n%\nO9\n");
        assert_eq!(
            cnc.when_program_ends(),
            None,
            "the first % is the tape start"
        );
        cnc.advance(t0 + secs(0.5));
        assert_eq!(cnc.buffered(), 1);
        cnc.push_data(t0 + secs(0.5), b"M30\n%\n");
        // 5 bytes read by 0.5 s, then 1 + 5 more through the ending %: at 1.1 s.
        assert_eq!(cnc.when_program_ends(), Some(t0 + secs(1.1)));
        cnc.advance(t0 + secs(1.1));
        assert_eq!(&cnc.take_finished().unwrap().data[..], b"%\nO9\nM30\n%");
        // CLB keeps the tape reader's state: inside a program, the next % ends it.
        cnc.start_reading(t0 + secs(2.0));
        cnc.push_data(t0 + secs(2.0), b"%O1\nG1\n");
        cnc.clear_buffer(t0 + secs(2.5));
        cnc.push_data(t0 + secs(2.5), b"G0%");
        assert_eq!(cnc.when_program_ends(), Some(t0 + secs(2.8)));
        cnc.advance(t0 + secs(2.8));
        assert_eq!(&cnc.take_finished().unwrap().data[..], b"%O1\nGG0%");
    }

    #[test]
    fn program_without_tape_start_and_iso_parity() {
        let t0 = Instant::now();
        let mut cnc = Cnc::new(64, 0, 4, t0);
        cnc.start_reading(t0);
        // ISO: % is A5h, LF 0Ah.
        cnc.push_data(t0, b"O0001\nM30\n\xA5");
        cnc.advance(t0);
        let p = cnc.take_finished().unwrap();
        assert_eq!(p.first_line, "O0001");
        assert_eq!(p.len, 11);
        assert!(p.truncated);
        assert_eq!(&p.data[..], b"O000");
    }

    #[test]
    fn overflow_reset_and_alarm() {
        let t0 = Instant::now();
        let mut cnc = Cnc::new(10, 1, 100, t0);
        cnc.start_reading(t0);
        assert_eq!(
            cnc.push_data(t0, &[b'1'; 11]),
            Push::Overflow { len: 11, free: 10 }
        );
        cnc.push_data(t0, b"%O1\nG0");
        assert_eq!(cnc.status(), BufferStatus::Operating);
        cnc.raise_alarm(t0, AlarmCause::NcAlarm);
        assert_eq!(cnc.status(), BufferStatus::Alarm);
        assert!(!cnc.start_reading(t0));
        assert_eq!(cnc.when_program_ends(), None);
        cnc.reset(t0);
        assert_eq!(cnc.status(), BufferStatus::Reset);
        assert_eq!(cnc.buffered(), 0);
    }
}
