//! An in-memory serial line between the host and a simulated board, paced at the baud rate.
//!
//! [`line()`] returns the two ends of a null-modem cable, both [`Transport`]s, and a [`SimLine`]
//! handle that injects faults and observes traffic. Everything runs on `tokio::time`, so a test
//! under paused time (`#[tokio::test(start_paused = true)]`) sees the line's real timing while
//! running far faster than the wall clock.
//!
//! # Timing
//!
//! Each direction is a UART transmitter with a transmit FIFO ([`SimOptions::fifo`], 16 by default)
//! feeding a wire that carries one character every [`LineSettings::char_time`]. Byte `k` of a
//! back-to-back run arrives at `run_start + time_for_chars(k + 1)`: computed from the count, so long
//! transfers keep the nominal rate exactly. A write accepts bytes only while the FIFO has room
//! (the character being shifted out plus `fifo` waiting) and otherwise waits until the front has
//! left, so the writer cannot race ahead of the line and a DC3 from the peer stops it within a
//! FIFO's worth of characters (§6.3). A reader is given every character that has arrived by now;
//! with none yet, it sleeps until the next arrival. Wakeups are per batch, not per character.
//!
//! # Modem lines
//!
//! Null-modem crossing (§3.2): an end's DR and CD follow the peer's ER, its CS follows the peer's
//! RS. Both ends start with ER and RS on. A cut line or a dropped peer reads as all lines off.
//! An end's output change takes effect once the characters it wrote before have arrived, as a
//! driver that drains its transmitter before changing its lines; every change wakes the
//! peer's reader, so the lines need no polling ([`Transport::modem_wakes_reader`]).
//!
//! # Faults
//!
//! Per direction ([`Dir`]): corrupt the next byte, give it a receive error, drop the next bytes,
//! delay later deliveries; and for the whole cable: [`SimLine::cut`] / [`SimLine::restore`].
//! [`SimLine::counters`] shows what each hook did.

use std::collections::VecDeque;
use std::fmt;
use std::io;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll, Waker};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::time::{Instant, Sleep};

use super::{LineError, LineSettings, ModemIn, ModemOut, Pacer, Parity, Transport};

/// One end of the simulated cable.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum End {
    /// The host computer's end (cellgate).
    Host,
    /// The device's end (the simulated remote-buffer board or PLC).
    Device,
}

impl End {
    fn index(self) -> usize {
        match self {
            End::Host => 0,
            End::Device => 1,
        }
    }

    fn peer(self) -> End {
        match self {
            End::Host => End::Device,
            End::Device => End::Host,
        }
    }

    /// The direction this end transmits in.
    pub fn tx(self) -> Dir {
        match self {
            End::Host => Dir::HostToDevice,
            End::Device => Dir::DeviceToHost,
        }
    }

    /// The direction this end receives from.
    pub fn rx(self) -> Dir {
        self.peer().tx()
    }
}

/// One direction of the simulated cable.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Dir {
    /// Host transmits (TXD of the host), device receives.
    HostToDevice,
    /// Device transmits, host receives.
    DeviceToHost,
}

impl Dir {
    fn index(self) -> usize {
        match self {
            Dir::HostToDevice => 0,
            Dir::DeviceToHost => 1,
        }
    }
}

/// Options of the simulated line beyond the character framing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SimOptions {
    /// Size of each transmitter's FIFO in characters (a 16550-style UART has 16). The character
    /// in the shift register comes on top of it.
    pub fifo: usize,
}

impl Default for SimOptions {
    fn default() -> Self {
        SimOptions { fifo: 16 }
    }
}

/// What happened to the bytes of one direction so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Counters {
    /// Bytes the transmitting end's writes accepted.
    pub written: u64,
    /// Bytes handed to the receiving end's reads.
    pub delivered: u64,
    /// Bytes removed by [`SimLine::drop_next`].
    pub dropped: u64,
    /// Bytes altered by [`SimLine::corrupt_next`] or given an error by [`SimLine::error_next`]
    /// (delivered altered, or reported as a [`LineError`] and not delivered).
    pub corrupted: u64,
    /// Bytes lost because the line was cut or the receiving end was gone.
    pub lost: u64,
    /// Receive errors reported (through [`Transport::take_line_error`] or still pending).
    pub line_errors: u64,
}

/// A fault that hits one byte.
#[derive(Debug, Clone, Copy)]
enum ByteFault {
    Corrupt(u8),
    Error(LineError),
}

/// Characters on their way to the receiver: a stretch of one back-to-back run, sent with the
/// same delay. Arrival times are computed from the run index, so a long transfer is one segment
/// growing at the back and drained at the front, and the reader finds how many characters have
/// arrived with one division instead of one comparison per character.
#[derive(Debug)]
struct Segment {
    bytes: VecDeque<u8>,
    /// Start of the run on the wire, plus the delay the characters were sent with.
    origin: Instant,
    /// Index within the run of `bytes[0]`.
    first: u64,
    /// Nothing in the segment arrives before this (a lowered delay never reorders).
    not_before: Instant,
    /// The (single) character of the segment was received with this error: not delivered.
    error: Option<LineError>,
}

impl Segment {
    /// Arrival time of `bytes[j]`.
    fn arrival(&self, line: &LineSettings, j: usize) -> Instant {
        let natural = self.origin + line.time_for_chars(self.first + j as u64 + 1);
        natural.max(self.not_before)
    }

    /// How many of the segment's characters have arrived by `now`.
    fn arrived(&self, line: &LineSettings, now: Instant) -> usize {
        if now < self.not_before || now < self.origin {
            return 0;
        }
        let done = line.chars_in(now - self.origin).saturating_sub(self.first);
        usize::try_from(done)
            .unwrap_or(usize::MAX)
            .min(self.bytes.len())
    }
}

/// Random faults on every byte of one direction, for fault-matrix tests: each byte is dropped
/// with probability `drop_ppm` / 10⁶, else hit in one bit with probability `corrupt_ppm` / 10⁶
/// (reported as a parity error on a line with parity, as for [`SimLine::corrupt_next`]). After
/// a fault the next `guard` bytes are left alone: with a guard longer than a frame, no frame
/// takes two hits, which an 8-bit sum could miss (two flips of one bit in opposite directions
/// cancel). The same `seed` gives the same faults for the same bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Noise {
    pub corrupt_ppm: u32,
    pub drop_ppm: u32,
    pub guard: u32,
    pub seed: u64,
}

impl Noise {
    fn is_quiet(&self) -> bool {
        self.corrupt_ppm == 0 && self.drop_ppm == 0
    }
}

/// A small deterministic generator (xorshift64*): the line's noise needs no crate.
#[derive(Debug, Clone, Copy)]
struct Rng(u64);

impl Rng {
    fn new(seed: u64) -> Self {
        Rng(seed | 1)
    }

    fn next(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
}

#[derive(Debug)]
struct Direction {
    pacer: Pacer,
    queue: VecDeque<Segment>,
    /// Receive errors not yet taken by the receiver.
    errors: VecDeque<LineError>,
    faults: VecDeque<ByteFault>,
    noise: Noise,
    rng: Rng,
    /// Bytes still to pass before the noise may hit again.
    guarded: u32,
    drop_next: u64,
    delay: Duration,
    counters: Counters,
    reader_waker: Option<Waker>,
    /// The transmitting end shut down or was dropped: the receiver reads EOF once drained.
    writer_closed: bool,
    /// The receiving end was dropped: bytes are lost.
    reader_closed: bool,
}

impl Direction {
    fn new(settings: LineSettings, opts: SimOptions) -> Self {
        Direction {
            // The shift register holds one character on top of the FIFO.
            pacer: Pacer::new(settings, opts.fifo.saturating_add(1)),
            queue: VecDeque::new(),
            errors: VecDeque::new(),
            faults: VecDeque::new(),
            noise: Noise::default(),
            rng: Rng::new(0),
            guarded: 0,
            drop_next: 0,
            delay: Duration::ZERO,
            counters: Counters::default(),
            reader_waker: None,
            writer_closed: false,
            reader_closed: false,
        }
    }

    /// Characters queued, arrived or not.
    fn queued(&self) -> usize {
        self.queue.iter().map(|s| s.bytes.len()).sum()
    }

    /// Discard everything in flight (cut cable, receiver gone).
    fn lose_in_flight(&mut self) {
        self.counters.lost += self.queued() as u64;
        self.queue.clear();
    }

    /// Queue characters `first..` of the run starting at `run_start`, already masked.
    fn push(
        &mut self,
        line: &LineSettings,
        bytes: &[u8],
        run_start: Instant,
        first: u64,
        error: Option<LineError>,
    ) {
        let origin = run_start + self.delay;
        if let Some(tail) = self.queue.back_mut()
            && error.is_none()
            && tail.error.is_none()
            && tail.origin == origin
            && tail.first + tail.bytes.len() as u64 == first
        {
            tail.bytes.extend(bytes.iter().copied());
            return;
        }
        let not_before = match self.queue.back() {
            Some(tail) => tail.arrival(line, tail.bytes.len().saturating_sub(1)),
            None => origin,
        };
        self.queue.push_back(Segment {
            bytes: bytes.iter().copied().collect(),
            origin,
            first,
            not_before,
            error,
        });
    }

    /// Move an errored character that has arrived at the front of the queue to `errors`.
    fn take_arrived_error(&mut self, line: &LineSettings, now: Instant) -> bool {
        match self.queue.front() {
            Some(seg) if seg.error.is_some() && seg.arrival(line, 0) <= now => {
                if let Some(e) = seg.error {
                    self.errors.push_back(e);
                    self.counters.line_errors += 1;
                }
                self.queue.pop_front();
                true
            }
            _ => false,
        }
    }

    /// Arrival time of the next queued character.
    fn next_arrival(&self, line: &LineSettings) -> Option<Instant> {
        self.queue.front().map(|seg| seg.arrival(line, 0))
    }

    /// Arrival time of the last queued character.
    fn last_arrival(&self, line: &LineSettings) -> Option<Instant> {
        self.queue
            .back()
            .map(|seg| seg.arrival(line, seg.bytes.len().saturating_sub(1)))
    }
}

#[derive(Debug)]
struct Shared {
    settings: LineSettings,
    dirs: [Direction; 2],
    out: [ModemOut; 2],
    /// Output changes of each end waiting for the characters that end wrote before them to
    /// leave the line, oldest first: (when, lines).
    changes: [VecDeque<(Instant, ModemOut)>; 2],
    open: [bool; 2],
    cut: bool,
}

impl Shared {
    fn dir(&mut self, d: Dir) -> &mut Direction {
        &mut self.dirs[d.index()]
    }

    /// Both ends' readers, to be woken (outside the lock) after the input lines of both changed.
    fn take_reader_wakers(&mut self) -> [Option<Waker>; 2] {
        self.dirs.each_mut().map(|d| d.reader_waker.take())
    }

    /// Applies the output changes due by `now`; whether one of `end`'s inputs changed.
    fn settle(&mut self, now: Instant, end: End) -> bool {
        let mut changed = false;
        for e in [End::Host, End::Device] {
            let i = e.index();
            while let Some(&(at, out)) = self.changes[i].front()
                && at <= now
            {
                changed |= e == end.peer() && self.out[i] != out;
                self.out[i] = out;
                self.changes[i].pop_front();
            }
        }
        changed
    }

    fn modem_in(&mut self, end: End) -> ModemIn {
        self.settle(Instant::now(), end);
        let peer = end.peer().index();
        if self.cut || !self.open[peer] {
            return ModemIn {
                dr: false,
                cs: false,
                cd: false,
            };
        }
        let out = self.out[peer];
        // Null-modem crossing: DR and CD from the peer's ER, CS from the peer's RS.
        ModemIn {
            dr: out.er,
            cs: out.rs,
            cd: out.er,
        }
    }
}

fn lock(shared: &Mutex<Shared>) -> MutexGuard<'_, Shared> {
    // A panic elsewhere while holding the lock leaves consistent data (no await, no partial
    // updates that matter), so keep going rather than spread the panic.
    shared.lock().unwrap_or_else(|e| e.into_inner())
}

/// Build a simulated line with the default [`SimOptions`]: `(host end, device end, control)`.
pub fn line(settings: LineSettings) -> (SimPort, SimPort, SimLine) {
    line_with(settings, SimOptions::default())
}

/// Build a simulated line: `(host end, device end, control)`.
pub fn line_with(settings: LineSettings, opts: SimOptions) -> (SimPort, SimPort, SimLine) {
    let shared = Arc::new(Mutex::new(Shared {
        settings,
        dirs: [
            Direction::new(settings, opts),
            Direction::new(settings, opts),
        ],
        out: [ModemOut::ALL_ON; 2],
        changes: Default::default(),
        open: [true; 2],
        cut: false,
    }));
    let port = |end| SimPort {
        shared: shared.clone(),
        end,
        read_sleep: None,
        write_sleep: None,
        shut_down: false,
        read_stopped_at_error: false,
    };
    (
        port(End::Host),
        port(End::Device),
        SimLine {
            shared: shared.clone(),
        },
    )
}

/// One end of a simulated line. Dropping it closes that end: the peer reads EOF once the bytes
/// already on the wire are delivered, and the peer's writes are discarded.
pub struct SimPort {
    shared: Arc<Mutex<Shared>>,
    end: End,
    read_sleep: Option<Pin<Box<Sleep>>>,
    write_sleep: Option<Pin<Box<Sleep>>>,
    shut_down: bool,
    /// The last read stopped at an errored character: that error lies after the bytes it
    /// returned, so it is for the next read to take, not for [`Transport::take_line_error`].
    read_stopped_at_error: bool,
}

impl fmt::Debug for SimPort {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SimPort").field("end", &self.end).finish()
    }
}

impl SimPort {
    /// Which end of the cable this is.
    pub fn end(&self) -> End {
        self.end
    }

    /// A control handle for the line this end belongs to.
    pub fn control(&self) -> SimLine {
        SimLine {
            shared: self.shared.clone(),
        }
    }
}

fn store_waker(slot: &mut Option<Waker>, cx: &Context<'_>) {
    match slot {
        Some(w) if w.will_wake(cx.waker()) => {}
        _ => *slot = Some(cx.waker().clone()),
    }
}

impl AsyncRead for SimPort {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        if buf.remaining() == 0 {
            return Poll::Ready(Ok(()));
        }
        let this = &mut *self;
        this.read_stopped_at_error = false;
        loop {
            let now = Instant::now();
            let mut guard = lock(&this.shared);
            let line = guard.settings;
            let d = guard.dir(this.end.rx());
            // Errors at the front are taken first, then characters up to the next error: the
            // bytes of one read all follow the errors recorded by that read.
            let mut n = 0;
            while buf.remaining() > 0 {
                let Some(seg) = d.queue.front_mut() else {
                    break;
                };
                if seg.error.is_some() {
                    if n > 0 {
                        this.read_stopped_at_error = true;
                        break;
                    }
                    if !d.take_arrived_error(&line, now) {
                        break;
                    }
                    continue;
                }
                let k = seg.arrived(&line, now).min(buf.remaining());
                if k == 0 {
                    break;
                }
                let (a, b) = seg.bytes.as_slices();
                let from_a = k.min(a.len());
                buf.put_slice(&a[..from_a]);
                buf.put_slice(&b[..k - from_a]);
                seg.bytes.drain(..k);
                seg.first += k as u64;
                if seg.bytes.is_empty() {
                    d.queue.pop_front();
                }
                n += k;
            }
            if n > 0 {
                d.counters.delivered += n as u64;
                return Poll::Ready(Ok(()));
            }
            let arrival = d.next_arrival(&line);
            let closed = d.writer_closed;
            store_waker(&mut d.reader_waker, cx);
            // The peer's output changes are due in line order: this reader wakes for them
            // too, and its owner reads the lines again.
            if guard.settle(now, this.end) {
                cx.waker().wake_by_ref();
            }
            let change = guard.changes[this.end.peer().index()].front().map(|c| c.0);
            let next = match (arrival, change) {
                (Some(a), Some(c)) => a.min(c),
                (Some(at), None) | (None, Some(at)) => at,
                (None, None) if closed => return Poll::Ready(Ok(())), // EOF
                (None, None) => return Poll::Pending,
            };
            drop(guard);
            match super::poll_sleep(&mut this.read_sleep, next, cx) {
                Poll::Ready(()) => continue,
                Poll::Pending => return Poll::Pending,
            }
        }
    }
}

impl AsyncWrite for SimPort {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        if self.shut_down {
            return Poll::Ready(Err(io::Error::new(
                io::ErrorKind::BrokenPipe,
                "simulated line: write after shutdown",
            )));
        }
        if buf.is_empty() {
            return Poll::Ready(Ok(0));
        }
        let this = &mut *self;
        loop {
            let now = Instant::now();
            let mut guard = lock(&this.shared);
            let settings = guard.settings;
            let cut = guard.cut;
            let d = guard.dir(this.end.tx());
            // In batches of half the FIFO, as a driver refills a UART (see `Pacer::batch`).
            let room = d.pacer.batch(now.into_std(), buf.len());
            if room == 0 {
                let at = Instant::from_std(d.pacer.batch_at(now.into_std(), buf.len()));
                drop(guard);
                match super::poll_sleep(&mut this.write_sleep, at, cx) {
                    Poll::Ready(()) => continue,
                    Poll::Pending => return Poll::Pending,
                }
            }
            let n = room.min(buf.len());
            let placement = d.pacer.wrote(n, now.into_std());
            let run_start = Instant::from_std(placement.run_start());
            d.counters.written += n as u64;
            let was_empty = d.queue.is_empty();
            let mask = settings.data_mask();
            let accepted = buf.get(..n).unwrap_or(buf);
            if cut || d.reader_closed {
                d.counters.lost += n as u64;
            } else if d.drop_next == 0 && d.faults.is_empty() && d.noise.is_quiet() {
                if mask == 0xFF {
                    d.push(&settings, accepted, run_start, placement.first(), None);
                } else {
                    let masked: Vec<u8> = accepted.iter().map(|b| b & mask).collect();
                    d.push(&settings, &masked, run_start, placement.first(), None);
                }
            } else {
                for (i, &byte) in accepted.iter().enumerate() {
                    if d.drop_next > 0 {
                        d.drop_next -= 1;
                        d.counters.dropped += 1;
                        continue;
                    }
                    let mut byte = byte;
                    let mut error = None;
                    let mut fault = d.faults.pop_front();
                    if fault.is_none() && !d.noise.is_quiet() {
                        let draw = d.rng.next();
                        let roll = (draw % 1_000_000) as u32;
                        if d.guarded > 0 {
                            d.guarded -= 1;
                        } else if roll < d.noise.drop_ppm {
                            d.counters.dropped += 1;
                            d.guarded = d.noise.guard;
                            continue;
                        } else if roll - d.noise.drop_ppm < d.noise.corrupt_ppm {
                            let bit = 1u8 << ((draw >> 32) % 8);
                            // A hit outside the data bits would change nothing.
                            let bit = if bit & mask == 0 { 1 } else { bit };
                            fault = Some(ByteFault::Corrupt(bit));
                            d.guarded = d.noise.guard;
                        }
                    }
                    match fault {
                        None => {}
                        Some(ByteFault::Corrupt(m)) => {
                            d.counters.corrupted += 1;
                            if settings.parity == Parity::None {
                                byte ^= m;
                            } else {
                                error = Some(LineError::Parity);
                            }
                        }
                        Some(ByteFault::Error(e)) => {
                            d.counters.corrupted += 1;
                            error = Some(e);
                        }
                    }
                    let index = placement.first() + i as u64;
                    d.push(&settings, &[byte & mask], run_start, index, error);
                }
            }
            // A pending reader has armed its sleep for the front; it only needs a wake when
            // the queue was empty.
            let waker = if was_empty && !d.queue.is_empty() {
                d.reader_waker.take()
            } else {
                None
            };
            drop(guard);
            if let Some(w) = waker {
                w.wake();
            }
            return Poll::Ready(Ok(n));
        }
    }

    /// Bytes accepted are in the transmitter's FIFO: nothing to flush.
    fn poll_flush(self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }

    /// Stop transmitting: the peer reads EOF once the bytes on the wire are delivered.
    fn poll_shutdown(mut self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        self.shut_down = true;
        let waker = {
            let mut guard = lock(&self.shared);
            let d = guard.dir(self.end.tx());
            d.writer_closed = true;
            d.reader_waker.take()
        };
        if let Some(w) = waker {
            w.wake();
        }
        Poll::Ready(Ok(()))
    }
}

impl Drop for SimPort {
    fn drop(&mut self) {
        let waker = {
            let mut guard = lock(&self.shared);
            guard.open[self.end.index()] = false;
            let rx = guard.dir(self.end.rx());
            rx.reader_closed = true;
            rx.lose_in_flight();
            let tx = guard.dir(self.end.tx());
            tx.writer_closed = true;
            tx.reader_waker.take()
        };
        if let Some(w) = waker {
            w.wake();
        }
    }
}

impl Transport for SimPort {
    fn set_modem(&mut self, out: ModemOut) -> io::Result<()> {
        let waker = {
            let now = Instant::now();
            let mut guard = lock(&self.shared);
            guard.settle(now, self.end);
            let i = self.end.index();
            let line = guard.settings;
            let last = guard.changes[i].back().map_or(guard.out[i], |c| c.1);
            if last == out {
                None
            } else {
                // As a UART's driver drains its transmitter first: the lines change once the
                // characters written before have left, so a DC3 sent before ER goes off
                // reaches the peer before it sees ER off (§6.4 (1)).
                match guard.dir(self.end.tx()).last_arrival(&line) {
                    Some(at) if at > now => guard.changes[i].push_back((at, out)),
                    _ if guard.changes[i].is_empty() => guard.out[i] = out,
                    _ => guard.changes[i].push_back((now, out)),
                }
                // The peer's input lines follow these: its reader looks at them again.
                guard.dir(self.end.tx()).reader_waker.take()
            }
        };
        if let Some(w) = waker {
            w.wake();
        }
        Ok(())
    }

    /// Every change of an end's input lines (the peer's outputs, the peer dropped, the cable
    /// cut or restored) wakes that end's reader, so an idle simulated link needs no timer.
    fn modem_wakes_reader(&self) -> bool {
        true
    }

    fn modem(&mut self) -> io::Result<ModemIn> {
        Ok(lock(&self.shared).modem_in(self.end))
    }

    /// Errors come in line order: after a read, an error taken here lies before that read's
    /// bytes (a read never returns bytes from both sides of an errored character). An errored
    /// character that has arrived is also found here while no read is pending.
    fn take_line_error(&mut self) -> Option<LineError> {
        let now = Instant::now();
        let mut guard = lock(&self.shared);
        let line = guard.settings;
        let d = guard.dir(self.end.rx());
        if d.errors.is_empty() && !self.read_stopped_at_error {
            d.take_arrived_error(&line, now);
        }
        d.errors.pop_front()
    }

    fn describe(&self) -> String {
        format!("sim {}", lock(&self.shared).settings)
    }
}

/// Control handle of a simulated line: fault injection and observation. Cheap to clone.
#[derive(Clone)]
pub struct SimLine {
    shared: Arc<Mutex<Shared>>,
}

impl fmt::Debug for SimLine {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let g = lock(&self.shared);
        f.debug_struct("SimLine")
            .field("settings", &g.settings)
            .field("cut", &g.cut)
            .finish()
    }
}

impl SimLine {
    /// The line's character framing.
    pub fn settings(&self) -> LineSettings {
        lock(&self.shared).settings
    }

    /// Corrupt the next byte written in `dir` (after any dropped ones) by XOR with `mask`.
    /// On a line with a parity bit the receiver reports [`LineError::Parity`] and does not
    /// deliver the byte (the hit is taken to be one parity detects); without parity the altered
    /// byte is delivered. Calls queue up: two calls corrupt the next two bytes.
    pub fn corrupt_next(&self, dir: Dir, mask: u8) {
        lock(&self.shared)
            .dir(dir)
            .faults
            .push_back(ByteFault::Corrupt(mask));
    }

    /// The next byte written in `dir` arrives with the receive error `error` (framing, overrun,
    /// parity) and is not delivered. Queues up with [`corrupt_next`](Self::corrupt_next).
    pub fn error_next(&self, dir: Dir, error: LineError) {
        lock(&self.shared)
            .dir(dir)
            .faults
            .push_back(ByteFault::Error(error));
    }

    /// Random faults on every byte written in `dir` from now on; [`Noise::default`] stops them.
    pub fn set_noise(&self, dir: Dir, noise: Noise) {
        let mut g = lock(&self.shared);
        let d = g.dir(dir);
        d.noise = noise;
        d.rng = Rng::new(noise.seed);
        d.guarded = 0;
    }

    /// Silently drop the next `n` bytes written in `dir` (adds to any drop still pending).
    pub fn drop_next(&self, dir: Dir, n: u64) {
        let mut g = lock(&self.shared);
        let d = g.dir(dir);
        d.drop_next = d.drop_next.saturating_add(n);
    }

    /// Delay the delivery of bytes written in `dir` from now on by `delay` beyond their line
    /// time. Deliveries stay in order: lowering the delay never lets a byte overtake another.
    pub fn set_delay(&self, dir: Dir, delay: Duration) {
        lock(&self.shared).dir(dir).delay = delay;
    }

    /// Cut the cable: bytes in flight are lost, nothing written is delivered, and both ends read
    /// DR, CS and CD off (the "DR down" of alarm SR0855). Writes are still accepted, at line
    /// pace, and discarded.
    pub fn cut(&self) {
        let wakers = {
            let mut g = lock(&self.shared);
            g.cut = true;
            for d in &mut g.dirs {
                d.lose_in_flight();
            }
            g.take_reader_wakers()
        };
        wakers.into_iter().flatten().for_each(Waker::wake);
    }

    /// Reconnect a cut cable: bytes written from now on are delivered again.
    pub fn restore(&self) {
        let wakers = {
            let mut g = lock(&self.shared);
            g.cut = false;
            g.take_reader_wakers()
        };
        wakers.into_iter().flatten().for_each(Waker::wake);
    }

    /// Whether the cable is cut.
    pub fn is_cut(&self) -> bool {
        lock(&self.shared).cut
    }

    /// What happened to the bytes of `dir` so far.
    pub fn counters(&self, dir: Dir) -> Counters {
        lock(&self.shared).dir(dir).counters
    }

    /// Bytes on their way in `dir`: written, not yet read (including ones not yet arrived).
    pub fn in_flight(&self, dir: Dir) -> usize {
        lock(&self.shared).dir(dir).queued()
    }

    /// The output lines `end` drives.
    pub fn modem_out(&self, end: End) -> ModemOut {
        let mut guard = lock(&self.shared);
        guard.settle(Instant::now(), end.peer());
        guard.out[end.index()]
    }

    /// The input lines `end` reads.
    pub fn modem_in(&self, end: End) -> ModemIn {
        lock(&self.shared).modem_in(end)
    }
}

#[cfg(test)]
mod tests;
