//! The carrier that comes back by itself, [`Redial`], and what it is made of: a bounded
//! exponential backoff between attempts, and wakers for both directions. A TCP device server
//! reconnects, a serial port that disappeared (a USB adapter pulled, a port server restarted) is
//! opened again; each says only how through its [`Dialer`]. While either is away the line reads
//! as cut, and whichever of the reading or the writing task polls drives the next attempt.

use std::fmt;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, Wake, Waker};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::time::{Instant, Sleep};

use super::{LineError, ModemIn, ModemOut, Transport};

/// One attempt to bring the carrier up.
pub type Dial<D> =
    Pin<Box<dyn Future<Output = Result<<D as Dialer>::Stream, <D as Dialer>::Error>> + Send>>;

/// What one kind of carrier that comes back by itself does its own way: how it is dialled, how
/// a fresh stream is set up, what it logs, and what its modem lines are while it is up. The
/// rest — the backoff, the waking, reads and writes that wait while it is away — is [`Redial`].
pub trait Dialer: Send + Unpin {
    /// What carries the bytes while it is up.
    type Stream: AsyncRead + AsyncWrite + Send + Unpin;
    /// Why an attempt failed.
    type Error: fmt::Display;
    /// Why a read that gave nothing means the carrier is gone.
    const END_OF_INPUT: &'static str;
    /// Why a write that took nothing means the carrier is gone.
    const NO_MORE_BYTES: &'static str;
    /// What [`Transport::reconnect`] says it does, after the caller's reason.
    const REDIAL: &'static str;
    /// See [`Transport::modem_wakes_reader`].
    const MODEM_WAKES_READER: bool = false;

    /// Start one attempt.
    fn dial(&self) -> Dial<Self>;
    /// An attempt succeeded (`ups` so far, this one included, after `failed_before` failed
    /// ones): set the stream up and log it.
    fn up(&mut self, stream: Self::Stream, ups: u64, failed_before: u64) -> Self::Stream;
    /// Log a failed attempt (`attempt` in a row).
    fn dial_failed(&self, error: &Self::Error, attempt: u64, retry_in: Duration);
    /// The stream was lost: log it, forget what belonged to it.
    fn lost(&mut self, why: &dyn fmt::Display, retry_in: Duration);
    /// The owner shut the carrier down.
    fn closed(&self) {}
    /// The carrier, for an error ("serial port /dev/ttyS0").
    fn name(&self) -> String;
    /// Write through the stream while it is up.
    fn poll_write(
        &mut self,
        stream: &mut Self::Stream,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(stream).poll_write(cx, buf)
    }
    /// Drive the output lines; `stream` is `None` while the carrier is away.
    fn set_modem(&mut self, stream: Option<&mut Self::Stream>, out: ModemOut) -> io::Result<()>;
    /// The input lines while the carrier is up.
    fn modem(&mut self, stream: &mut Self::Stream) -> io::Result<ModemIn>;
    /// See [`Transport::take_line_error`].
    fn take_line_error(&mut self, _stream: &mut Self::Stream) -> Option<LineError> {
        None
    }
    /// See [`Transport::describe`].
    fn describe(&self) -> String;
}

/// How often a [`Redial`] came up and was lost.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RedialStats {
    /// Successful attempts, the first one included.
    pub ups: u64,
    /// Times the stream failed (read or write error, end of input).
    pub losses: u64,
    /// Failed attempts.
    pub failures: u64,
}

enum State<D: Dialer> {
    Up(D::Stream),
    Dialing(Dial<D>),
    /// Waiting before the next attempt.
    Away(Pin<Box<Sleep>>),
    /// Shut down by the owner: no more attempts.
    Closed,
}

/// A [`Transport`] that comes back by itself after a fault: redialled with bounded exponential
/// backoff. While it is away the line reads as cut (DR, CS and CD off), so the engine raises
/// its line alarm and the link drops what it had not written; reads and writes wait (nothing is
/// taken and thrown away). A failing stream is not an error to the reader; EOF only after
/// [`AsyncWriteExt::shutdown`](tokio::io::AsyncWriteExt).
pub struct Redial<D: Dialer> {
    dialer: D,
    state: State<D>,
    backoff: Backoff,
    wakers: Arc<Wakers>,
    stats: RedialStats,
}

impl<D: Dialer + fmt::Debug> fmt::Debug for Redial<D> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Redial")
            .field("dialer", &self.dialer)
            .field("up", &self.is_up())
            .field("stats", &self.stats)
            .finish()
    }
}

impl<D: Dialer> Redial<D> {
    /// Not dialled yet: the owner makes the first attempt and hands its result to
    /// [`Redial::dialed`].
    pub(super) fn new(dialer: D, backoff_min: Duration, backoff_max: Duration) -> Self {
        Redial {
            dialer,
            state: State::Closed,
            backoff: Backoff::new(backoff_min, backoff_max),
            wakers: Arc::new(Wakers::default()),
            stats: RedialStats::default(),
        }
    }

    /// Whether the carrier is up (as of the last read or write).
    pub fn is_up(&self) -> bool {
        matches!(self.state, State::Up(_))
    }

    /// How often it came up and was lost.
    pub fn stats(&self) -> RedialStats {
        self.stats
    }

    pub(super) fn dialer(&self) -> &D {
        &self.dialer
    }

    /// The dialer, and the stream while it is up.
    pub(super) fn parts_mut(&mut self) -> (&mut D, Option<&mut D::Stream>) {
        match &mut self.state {
            State::Up(stream) => (&mut self.dialer, Some(stream)),
            _ => (&mut self.dialer, None),
        }
    }

    /// An attempt ended.
    pub(super) fn dialed(&mut self, result: Result<D::Stream, D::Error>) {
        match result {
            Ok(stream) => {
                let failed = self.backoff.up();
                self.stats.ups += 1;
                let stream = self.dialer.up(stream, self.stats.ups, failed);
                self.state = State::Up(stream);
                self.wakers.wake_by_ref();
            }
            Err(e) => {
                self.stats.failures += 1;
                let attempt = self.backoff.failed();
                self.dialer.dial_failed(&e, attempt, self.backoff.peek());
                self.wait();
            }
        }
    }

    fn wait(&mut self) {
        let wait = self.backoff.take_wait();
        self.state = State::Away(Box::pin(tokio::time::sleep(wait)));
    }

    fn lost(&mut self, why: &dyn fmt::Display) {
        self.stats.losses += 1;
        self.backoff.lost();
        self.dialer.lost(why, self.backoff.peek());
        self.wait();
        self.wakers.wake_by_ref();
    }

    /// Drive the next attempt as far as it goes without waiting: the stream while it is up,
    /// `None` once shut down for good, `Pending` while it is away (both directions are woken
    /// when it is back).
    fn poll_up(&mut self) -> Poll<Option<(&mut D, &mut D::Stream)>> {
        let waker = self.wakers.waker();
        let mut cx = Context::from_waker(&waker);
        loop {
            match &mut self.state {
                State::Up(_) => break,
                State::Closed => return Poll::Ready(None),
                State::Dialing(f) => match f.as_mut().poll(&mut cx) {
                    Poll::Ready(result) => self.dialed(result),
                    Poll::Pending => return Poll::Pending,
                },
                State::Away(sleep) => match sleep.as_mut().poll(&mut cx) {
                    Poll::Ready(()) => self.state = State::Dialing(self.dialer.dial()),
                    Poll::Pending => return Poll::Pending,
                },
            }
        }
        match self.parts_mut() {
            (dialer, Some(stream)) => Poll::Ready(Some((dialer, stream))),
            (_, None) => Poll::Pending,
        }
    }
}

impl<D: Dialer> AsyncRead for Redial<D> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = &mut *self;
        Wakers::set(&this.wakers.read, cx.waker());
        loop {
            let before = buf.filled().len();
            let read = match this.poll_up() {
                Poll::Ready(Some((_, stream))) => Pin::new(stream).poll_read(cx, buf),
                Poll::Ready(None) => return Poll::Ready(Ok(())),
                Poll::Pending => return Poll::Pending,
            };
            match read {
                Poll::Pending => return Poll::Pending,
                Poll::Ready(Ok(())) if buf.filled().len() > before || buf.remaining() == 0 => {
                    return Poll::Ready(Ok(()));
                }
                Poll::Ready(Ok(())) => this.lost(&D::END_OF_INPUT),
                Poll::Ready(Err(e)) => this.lost(&e),
            }
        }
    }
}

impl<D: Dialer> AsyncWrite for Redial<D> {
    /// Writes through the stream while it is up; waits while it is away.
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        if matches!(this.state, State::Closed) {
            return Poll::Ready(Err(io::Error::new(
                io::ErrorKind::BrokenPipe,
                format!("{}: write after shutdown", this.dialer.name()),
            )));
        }
        if buf.is_empty() {
            return Poll::Ready(Ok(0));
        }
        Wakers::set(&this.wakers.write, cx.waker());
        loop {
            // Refused, not discarded: the writer waits for the carrier (both wakers are woken
            // when it is back).
            let Poll::Ready(Some((dialer, stream))) = this.poll_up() else {
                return Poll::Pending;
            };
            match dialer.poll_write(stream, cx, buf) {
                Poll::Ready(Ok(0)) => this.lost(&D::NO_MORE_BYTES),
                Poll::Ready(Err(e)) => this.lost(&e),
                other => return other,
            }
        }
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        if let State::Up(stream) = &mut this.state
            && let Poll::Ready(Err(e)) = Pin::new(stream).poll_flush(cx)
        {
            this.lost(&e);
        }
        Poll::Ready(Ok(()))
    }

    /// Close the carrier for good: no more attempts; reads return EOF.
    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        if let State::Up(stream) = &mut this.state
            && Pin::new(stream).poll_shutdown(cx).is_pending()
        {
            return Poll::Pending;
        }
        if !matches!(this.state, State::Closed) {
            this.dialer.closed();
        }
        this.state = State::Closed;
        this.wakers.wake_by_ref();
        Poll::Ready(Ok(()))
    }
}

impl<D: Dialer> Transport for Redial<D> {
    fn set_modem(&mut self, out: ModemOut) -> io::Result<()> {
        let (dialer, stream) = self.parts_mut();
        dialer.set_modem(stream, out)
    }

    /// The stream's lines while it is up; all off while it is away, like a cut line.
    fn modem(&mut self) -> io::Result<ModemIn> {
        match self.parts_mut() {
            (dialer, Some(stream)) => dialer.modem(stream),
            (_, None) => Ok(ModemIn {
                dr: false,
                cs: false,
                cd: false,
            }),
        }
    }

    fn take_line_error(&mut self) -> Option<LineError> {
        match self.parts_mut() {
            (dialer, Some(stream)) => dialer.take_line_error(stream),
            (_, None) => None,
        }
    }

    fn describe(&self) -> String {
        self.dialer.describe()
    }

    fn modem_wakes_reader(&self) -> bool {
        D::MODEM_WAKES_READER
    }

    /// Drops the stream and dials again at once.
    fn reconnect(&mut self, why: &str) {
        if self.is_up() {
            self.lost(&format!("{why}; {}", D::REDIAL));
            self.state = State::Dialing(self.dialer.dial());
            self.wakers.wake_by_ref();
        }
    }
}

/// The wakers of the reading and the writing task. Either one may drive reconnection (poll the
/// attempt or the backoff timer); whichever does, both are woken on progress, so that a reader
/// is not left asleep because a writer happened to poll last.
#[derive(Default)]
struct Wakers {
    read: Mutex<Option<Waker>>,
    write: Mutex<Option<Waker>>,
}

impl Wakers {
    fn set(slot: &Mutex<Option<Waker>>, w: &Waker) {
        let mut g = slot.lock().unwrap_or_else(|e| e.into_inner());
        match &*g {
            Some(old) if old.will_wake(w) => {}
            _ => *g = Some(w.clone()),
        }
    }

    /// A waker that wakes both tasks.
    fn waker(self: &Arc<Self>) -> Waker {
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
struct Backoff {
    min: Duration,
    max: Duration,
    next: Duration,
    up_since: Option<Instant>,
    /// Failed attempts since the last success, for quieter logs.
    failures_in_a_row: u64,
}

impl Backoff {
    fn new(min: Duration, max: Duration) -> Self {
        Backoff {
            min,
            max: max.max(min),
            next: min,
            up_since: None,
            failures_in_a_row: 0,
        }
    }

    /// The wait before the next attempt, growing the one after it.
    fn take_wait(&mut self) -> Duration {
        let wait = self.next;
        self.next = (self.next * 2).min(self.max);
        wait
    }

    /// The wait the next [`Backoff::take_wait`] returns.
    fn peek(&self) -> Duration {
        self.next
    }

    /// An attempt succeeded. Returns how many failed before it.
    fn up(&mut self) -> u64 {
        self.up_since = Some(Instant::now());
        std::mem::take(&mut self.failures_in_a_row)
    }

    /// An attempt failed. Returns how many failed in a row, this one included.
    fn failed(&mut self) -> u64 {
        self.failures_in_a_row += 1;
        self.failures_in_a_row
    }

    /// The connection was lost.
    fn lost(&mut self) {
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
