//! What the carriers that come back by themselves share: a bounded exponential backoff between
//! attempts, and wakers for both directions. A TCP device server reconnects, a serial port that
//! disappeared (a USB adapter pulled, a port server restarted) is opened again; while either is
//! away the line reads as cut, and whichever of the reading or the writing task polls drives
//! the next attempt.

use std::sync::{Arc, Mutex};
use std::task::{Wake, Waker};
use std::time::Duration;

use tokio::time::Instant;

/// The wakers of the reading and the writing task. Either one may drive reconnection (poll the
/// attempt or the backoff timer); whichever does, both are woken on progress, so that a reader
/// is not left asleep because a writer happened to poll last.
#[derive(Default)]
pub(crate) struct Wakers {
    pub(crate) read: Mutex<Option<Waker>>,
    pub(crate) write: Mutex<Option<Waker>>,
}

impl Wakers {
    pub(crate) fn set(slot: &Mutex<Option<Waker>>, w: &Waker) {
        let mut g = slot.lock().unwrap_or_else(|e| e.into_inner());
        match &*g {
            Some(old) if old.will_wake(w) => {}
            _ => *g = Some(w.clone()),
        }
    }

    /// A waker that wakes both tasks.
    pub(crate) fn waker(self: &Arc<Self>) -> Waker {
        Waker::from(self.clone())
    }
}

impl Wake for Wakers {
    fn wake(self: Arc<Self>) {
        self.wake_by_ref();
    }

    fn wake_by_ref(self: &Arc<Self>) {
        for slot in [&self.read, &self.write] {
            let w = slot.lock().unwrap_or_else(|e| e.into_inner()).take();
            if let Some(w) = w {
                w.wake();
            }
        }
    }
}

/// Waits between attempts: `min`, doubled after each failure up to `max`. A connection that
/// lasted at least `max` starts the next round at `min` again; one dropped at once (a device
/// server that accepts and closes, a port that opens and fails) keeps it growing.
#[derive(Debug, Clone)]
pub(crate) struct Backoff {
    min: Duration,
    max: Duration,
    next: Duration,
    up_since: Option<Instant>,
    /// Failed attempts since the last success, for quieter logs.
    failures_in_a_row: u64,
}

impl Backoff {
    pub(crate) fn new(min: Duration, max: Duration) -> Self {
        Backoff {
            min,
            max: max.max(min),
            next: min,
            up_since: None,
            failures_in_a_row: 0,
        }
    }

    /// The wait before the next attempt, growing the one after it.
    pub(crate) fn take_wait(&mut self) -> Duration {
        let wait = self.next;
        self.next = (self.next * 2).min(self.max);
        wait
    }

    /// The wait the next [`Backoff::take_wait`] returns.
    pub(crate) fn peek(&self) -> Duration {
        self.next
    }

    /// An attempt succeeded. Returns how many failed before it.
    pub(crate) fn up(&mut self) -> u64 {
        self.up_since = Some(Instant::now());
        std::mem::take(&mut self.failures_in_a_row)
    }

    /// An attempt failed. Returns how many failed in a row, this one included.
    pub(crate) fn failed(&mut self) -> u64 {
        self.failures_in_a_row += 1;
        self.failures_in_a_row
    }

    /// The connection was lost.
    pub(crate) fn lost(&mut self) {
        if self
            .up_since
            .take()
            .is_some_and(|t| t.elapsed() >= self.max)
        {
            self.next = self.min;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn doubles_to_the_bound_and_restarts_after_a_lasting_connection() {
        let ms = Duration::from_millis;
        let mut b = Backoff::new(ms(100), ms(500));
        let waits: Vec<_> = (0..5).map(|_| b.take_wait()).collect();
        assert_eq!(waits, [ms(100), ms(200), ms(400), ms(500), ms(500)]);
        assert_eq!(b.failed(), 1);
        assert_eq!(b.failed(), 2);
        assert_eq!(b.up(), 2);
        // Dropped at once: the backoff keeps its size.
        b.lost();
        assert_eq!(b.peek(), ms(500));
        b.up();
        tokio::time::advance(ms(600)).await;
        b.lost();
        assert_eq!(b.peek(), ms(100));
    }
}
