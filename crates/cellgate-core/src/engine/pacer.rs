//! Line-rate pacing of a writer, sans-IO.
//!
//! A [`Pacer`] models the serial transmitter at the far end of whatever buffers sit between the
//! host and the line: characters written to it leave at the line's character rate, back to back,
//! and the writer may keep at most `window` characters written but not yet fully sent. That bound
//! is what makes a stop code (DC3, §6.3 of the remote-buffer manual) take effect within a few
//! characters instead of after everything the OS, a device server or a UART FIFO has swallowed:
//! Protocol B allows the sender to overrun a DC3 by at most 512 characters.
//!
//! Times are computed from character counts within a run (`run_start + time_for_chars(k)`), never
//! by adding per-character durations, so a long transfer does not drift from the nominal rate.
//! A run ends when the line falls idle; the next write starts a new run at its own time.
//!
//! Used by the simulated line (the UART's transmit FIFO), the TCP device-server transport (the
//! device server's buffer) and the serial transport (the kernel's output queue).

use std::time::Instant;

use super::LineSettings;

/// Tracks characters written and not yet drained onto the line. See the [module docs](self).
#[derive(Debug, Clone)]
pub struct Pacer {
    line: LineSettings,
    window: u64,
    /// Start of the current back-to-back run, if any character was ever written.
    run_start: Option<Instant>,
    /// Characters written in the current run.
    run_len: u64,
}

/// Where a batch of characters accepted by [`Pacer::wrote`] sits on the line.
#[derive(Debug, Clone, Copy)]
pub struct Placement {
    line: LineSettings,
    run_start: Instant,
    first: u64,
}

impl Placement {
    /// Start of the run the batch belongs to.
    pub fn run_start(&self) -> Instant {
        self.run_start
    }

    /// Index within the run of the batch's first character.
    pub fn first(&self) -> u64 {
        self.first
    }

    /// The moment the `i`-th character of the batch (0-based) has fully left the transmitter:
    /// its stop bits are on the line.
    pub fn done_at(&self, i: u64) -> Instant {
        self.run_start + self.line.time_for_chars(self.first + i + 1)
    }
}

impl Pacer {
    /// A pacer for `line` that lets at most `window` characters be in flight (at least 1).
    pub fn new(line: LineSettings, window: usize) -> Self {
        Pacer {
            line,
            window: u64::try_from(window.max(1)).unwrap_or(u64::MAX),
            run_start: None,
            run_len: 0,
        }
    }

    /// The line settings the pacer drains at.
    pub fn line(&self) -> LineSettings {
        self.line
    }

    /// The in-flight bound.
    pub fn window(&self) -> usize {
        usize::try_from(self.window).unwrap_or(usize::MAX)
    }

    /// Characters of the current run fully on the line by `now`.
    fn drained(&self, now: Instant) -> u64 {
        let Some(start) = self.run_start else {
            return 0;
        };
        let elapsed = now.saturating_duration_since(start);
        self.line.chars_in(elapsed).min(self.run_len)
    }

    /// Characters written and not yet fully sent at `now` (the one being shifted out included).
    pub fn unsent(&self, now: Instant) -> u64 {
        self.run_len - self.drained(now)
    }

    /// How many characters may be written at `now` without exceeding the window.
    pub fn writable(&self, now: Instant) -> usize {
        usize::try_from(self.window.saturating_sub(self.unsent(now))).unwrap_or(usize::MAX)
    }

    /// Record that `n` characters were written at `now`. Starts a new run if the line was idle.
    /// Writing more than [`writable`](Self::writable) is allowed; it only delays later writes.
    pub fn wrote(&mut self, n: usize, now: Instant) -> Placement {
        if self.run_start.is_none() || self.unsent(now) == 0 {
            self.run_start = Some(now);
            self.run_len = 0;
        }
        let first = self.run_len;
        self.run_len = self
            .run_len
            .saturating_add(u64::try_from(n).unwrap_or(u64::MAX));
        Placement {
            line: self.line,
            run_start: self.run_start.unwrap_or(now),
            first,
        }
    }

    /// The earliest time at which at least one character may be written: `now` if that is
    /// already the case, else the moment the front of the window has left the line.
    pub fn next_writable_at(&self, now: Instant) -> Instant {
        if self.writable(now) > 0 {
            return now;
        }
        let Some(start) = self.run_start else {
            return now;
        };
        // unsent < window  <=>  drained >= run_len - window + 1
        let needed = self.run_len - self.window + 1;
        start + self.line.time_for_chars(needed)
    }

    /// The fewest characters worth a write for a writer holding `want`: all of them, or half
    /// the window if they are more.
    pub fn low_water(&self, want: usize) -> usize {
        want.clamp(1, (self.window() / 2).max(1))
    }

    /// How many of `want` characters to write at `now`: all that fit once the window has room
    /// for [`low_water`](Self::low_water) of them, else none. A writer at line rate then
    /// writes a few large pieces a window instead of the characters freed since its last
    /// write (a system call and a timer each), and the line never starves: half a window is
    /// still queued when it refills.
    pub fn batch(&self, now: Instant, want: usize) -> usize {
        let room = self.writable(now);
        if room >= self.low_water(want) {
            room.min(want)
        } else {
            0
        }
    }

    /// The earliest time at which [`batch`](Self::batch) is not 0.
    pub fn batch_at(&self, now: Instant, want: usize) -> Instant {
        let need = u64::try_from(self.low_water(want)).unwrap_or(u64::MAX);
        if self.window.saturating_sub(self.unsent(now)) >= need {
            return now;
        }
        let Some(start) = self.run_start else {
            return now;
        };
        // writable >= need  <=>  unsent <= window - need  <=>  drained >= run_len - window + need
        let drained = self
            .run_len
            .saturating_add(need)
            .saturating_sub(self.window);
        start + self.line.time_for_chars(drained)
    }

    /// The moment the last written character has fully left the line (`None` if never written).
    pub fn idle_at(&self) -> Option<Instant> {
        self.run_start
            .map(|s| s + self.line.time_for_chars(self.run_len))
    }

    /// Forget everything in flight (the buffers downstream were lost, e.g. on reconnection).
    pub fn reset(&mut self) {
        self.run_start = None;
        self.run_len = 0;
    }
}

#[cfg(test)]
mod tests;
