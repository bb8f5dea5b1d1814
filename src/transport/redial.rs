//! What the carriers that come back by themselves share: a bounded exponential backoff between
//! attempts, and wakers for both directions. A TCP device server reconnects, a serial port that
//! disappeared (a USB adapter pulled, a port server restarted) is opened again; while either is
//! away the line reads as cut, and whichever of the reading or the writing task polls drives
//! the next attempt.

use std::fmt;
use std::io;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, Wake, Waker};
use std::time::Duration;

use tokio::io::{AsyncRead, ReadBuf};
use tokio::time::Instant;

/// A carrier that comes back by itself, as its reads see it.
pub(crate) trait Redialing {
    /// What carries the bytes while it is up.
    type Stream: AsyncRead + Unpin + ?Sized;
    /// Why a read that gave nothing means the carrier is gone.
    const END_OF_INPUT: &'static str;
    /// Drives the next attempt: the stream while it is up, `None` once shut down for good,
    /// `Pending` while it is away (both directions are woken when it is back).
    fn poll_up(&mut self) -> Poll<Option<&mut Self::Stream>>;
    /// The stream failed: drop it and try again after the backoff.
    fn lost(&mut self, why: &dyn fmt::Display);
}

/// A read through a carrier that comes back: a failing carrier is not an error to the reader,
/// who waits for it to be up again; EOF only after shutdown.
pub(crate) fn poll_read<T: Redialing>(
    carrier: &mut T,
    cx: &mut Context<'_>,
    buf: &mut ReadBuf<'_>,
) -> Poll<io::Result<()>> {
    loop {
        let before = buf.filled().len();
        let read = match carrier.poll_up() {
            Poll::Ready(Some(stream)) => Pin::new(stream).poll_read(cx, buf),
            Poll::Ready(None) => return Poll::Ready(Ok(())),
            Poll::Pending => return Poll::Pending,
        };
        match read {
            Poll::Pending => return Poll::Pending,
            Poll::Ready(Ok(())) if buf.filled().len() > before || buf.remaining() == 0 => {
                return Poll::Ready(Ok(()));
            }
            Poll::Ready(Ok(())) => carrier.lost(&T::END_OF_INPUT),
            Poll::Ready(Err(e)) => carrier.lost(&e),
        }
    }
}

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
mod tests;
