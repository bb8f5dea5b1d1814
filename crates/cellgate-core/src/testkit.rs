//! Two engines on one simulated serial line, in plain time (quinn-proto's `Pair`): what one
//! hands to `poll_transmit` arrives at the other after its line time (bytes × character time,
//! one character after another), and every deadline fires on time. A host engine and the
//! simulated device it speaks to (a FANUC host and [`crate::sim::FanucBoard`], the FFU120B
//! master and [`crate::sim::micrex::Micrex`]) run together without a runtime or a socket, for
//! the core's tests and for anyone who drives an engine in a test of their own.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use crate::engine::{Engine, LineSettings};

/// A one-way channel: bytes in flight with the instant they have fully arrived.
#[derive(Default)]
struct Wire {
    in_flight: VecDeque<(Instant, Vec<u8>)>,
    busy_until: Option<Instant>,
}

impl Wire {
    fn send(&mut self, now: Instant, line: &LineSettings, bytes: Vec<u8>) {
        let start = self.busy_until.map_or(now, |b| b.max(now));
        let done = start + line.time_for_chars(bytes.len() as u64);
        self.busy_until = Some(done);
        self.in_flight.push_back((done, bytes));
    }

    fn next(&self) -> Option<Instant> {
        self.in_flight.front().map(|(t, _)| *t)
    }

    /// Whether fewer than `window` characters are still to go onto the line at `now`; else
    /// the instant at which they are.
    fn room(&self, now: Instant, line: &LineSettings, window: usize) -> Result<(), Instant> {
        let Some(busy) = self.busy_until else {
            return Ok(());
        };
        match busy.checked_sub(line.time_for_chars(window as u64)) {
            Some(free_at) if free_at > now => Err(free_at),
            _ => Ok(()),
        }
    }
}

/// A host engine `a` and a device engine `b` on one line.
pub struct Pair<A: Engine, B: Engine> {
    /// The host engine.
    pub a: A,
    /// The device engine.
    pub b: B,
    /// The pair's clock.
    pub now: Instant,
    /// The line both ends run at.
    pub line: LineSettings,
    a_to_b: Wire,
    b_to_a: Wire,
    /// `a`'s events with the instant each came out, not taken yet.
    pub a_events: Vec<(Instant, A::Event)>,
    /// `b`'s events with the instant each came out, not taken yet.
    pub b_events: Vec<(Instant, B::Event)>,
    /// Everything `a` sent, in order.
    pub a_sent: Vec<u8>,
    /// Everything `b` sent, in order.
    pub b_sent: Vec<u8>,
    /// Drops what `b` sends (a cut line toward `a`).
    pub cut_b_to_a: bool,
    /// Most characters `a` may have handed out that are not yet on the line: a transport's
    /// in-flight window (a device server's buffer, a kernel queue). `a` is asked for its next
    /// piece only while fewer are pending, as the link's pump asks only once the transport
    /// took the last piece. `None`: the line takes everything at once.
    pub a_window: Option<usize>,
}

impl<A: Engine, B: Engine> Pair<A, B> {
    /// The two engines on a line of `line`, at `now`.
    pub fn new(a: A, b: B, line: LineSettings, now: Instant) -> Self {
        let mut pair = Pair {
            a,
            b,
            now,
            line,
            a_to_b: Wire::default(),
            b_to_a: Wire::default(),
            a_events: Vec::new(),
            b_events: Vec::new(),
            a_sent: Vec::new(),
            b_sent: Vec::new(),
            cut_b_to_a: false,
            a_window: None,
        };
        pair.pump();
        pair
    }

    /// Takes what both want to send now, and their events.
    pub fn pump(&mut self) {
        loop {
            let mut moved = false;
            while self.a_room().is_ok()
                && let Some(bytes) = self.a.poll_transmit(self.now)
            {
                self.a_sent.extend(&bytes);
                self.a_to_b.send(self.now, &self.line, bytes);
                moved = true;
            }
            while let Some(bytes) = self.b.poll_transmit(self.now) {
                self.b_sent.extend(&bytes);
                if !self.cut_b_to_a {
                    self.b_to_a.send(self.now, &self.line, bytes);
                }
                moved = true;
            }
            while let Some(e) = self.a.poll_event() {
                self.a_events.push((self.now, e));
            }
            while let Some(e) = self.b.poll_event() {
                self.b_events.push((self.now, e));
            }
            if !moved {
                return;
            }
        }
    }

    /// Whether `a` may hand out a piece now (see [`Pair::a_window`]); else when it may.
    fn a_room(&self) -> Result<(), Instant> {
        match self.a_window {
            Some(window) => self.a_to_b.room(self.now, &self.line, window),
            None => Ok(()),
        }
    }

    /// A command to `a`.
    pub fn command_a(&mut self, c: A::Command) {
        self.a.handle_command(self.now, c);
        self.pump();
    }

    /// A command to `b`.
    pub fn command_b(&mut self, c: B::Command) {
        self.b.handle_command(self.now, c);
        self.pump();
    }

    /// The next instant anything happens, if any.
    pub fn next_instant(&self) -> Option<Instant> {
        [
            self.a.poll_timeout(),
            self.b.poll_timeout(),
            self.a_to_b.next(),
            self.b_to_a.next(),
            self.a_room().err(),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// Runs the next thing due at or before `limit`; false when nothing is.
    pub fn step(&mut self, limit: Instant) -> bool {
        let Some(t) = self.next_instant().filter(|t| *t <= limit) else {
            return false;
        };
        self.now = self.now.max(t);
        while let Some((at, _)) = self.a_to_b.in_flight.front()
            && *at <= self.now
        {
            if let Some((_, bytes)) = self.a_to_b.in_flight.pop_front() {
                self.b.handle_input(self.now, &bytes);
            }
        }
        while let Some((at, _)) = self.b_to_a.in_flight.front()
            && *at <= self.now
        {
            if let Some((_, bytes)) = self.b_to_a.in_flight.pop_front() {
                self.a.handle_input(self.now, &bytes);
            }
        }
        if self.a.poll_timeout().is_some_and(|d| d <= self.now) {
            self.a.handle_timeout(self.now);
        }
        if self.b.poll_timeout().is_some_and(|d| d <= self.now) {
            self.b.handle_timeout(self.now);
        }
        self.pump();
        true
    }

    /// Runs everything due until `t`.
    pub fn run_until(&mut self, t: Instant) {
        let mut guard = 0u64;
        while self.step(t) {
            guard += 1;
            assert!(guard < 10_000_000, "the rig does not settle");
        }
        self.now = self.now.max(t);
    }

    /// Runs everything due for `d`.
    pub fn run_for(&mut self, d: Duration) {
        let t = self.now + d;
        self.run_until(t);
    }

    /// Runs until nothing is left to do (or `limit` has passed).
    pub fn settle(&mut self, limit: Duration) {
        let t = self.now + limit;
        while self.step(t) {}
    }

    /// Bytes straight into `a`, as a scripted peer would send them.
    pub fn inject_to_a(&mut self, bytes: &[u8]) {
        self.a.handle_input(self.now, bytes);
        self.pump();
    }

    /// `a`'s events so far, taken.
    pub fn take_a_events(&mut self) -> Vec<A::Event> {
        std::mem::take(&mut self.a_events)
            .into_iter()
            .map(|(_, e)| e)
            .collect()
    }

    /// `b`'s events so far, taken.
    pub fn take_b_events(&mut self) -> Vec<B::Event> {
        std::mem::take(&mut self.b_events)
            .into_iter()
            .map(|(_, e)| e)
            .collect()
    }
}
