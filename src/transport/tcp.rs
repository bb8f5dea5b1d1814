//! Raw TCP to a serial device server (one TCP port per serial port, no Telnet/RFC 2217).
//!
//! The link must survive the device server going away: [`TcpTransport`] never fails after
//! construction. It reconnects with bounded exponential backoff after a failed connect, an EOF or
//! an I/O error, and while disconnected it behaves like an open (cut) line: reads wait, the modem
//! lines read off, and writes wait too — a byte is never taken and thrown away, so what a
//! protocol engine counts as handed to the line did go to a device server. The engine sees
//! exactly what it would see on a broken cable and raises its own timeouts and alarms; the link
//! drops what it had not written yet when the line goes down.
//!
//! Writes go through a bounded in-flight window (a [`Pacer`]): the device server buffers about a
//! kilobyte per port and the sockets more, so without a bound a DC3 from the CNC would be
//! overrun by everything already buffered. The transport estimates the characters written but
//! not yet sent on the serial side (they drain at the line's character rate) and accepts writes
//! only while that estimate is below [`TcpOptions::window`], well inside Protocol B's 512-character
//! overrun allowance (§6.3; 1280 for Expansion B, §7).
//!
//! A raw TCP device server carries no modem lines: [`Transport::set_modem`] does nothing and
//! [`Transport::modem`] reads all lines on while connected.

use std::fmt;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll, Wake};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio::time::{Instant, Sleep};
use tracing::{debug, info, warn};

use super::redial::{self, Backoff, Redialing, Wakers};
use super::{LineSettings, ModemIn, ModemOut, Pacer, Transport, TransportError};

/// Connection and pacing options of a [`TcpTransport`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TcpOptions {
    /// Characters written and not yet sent on the serial side, at most. Bounds how far a DC3
    /// can be overrun; keep it well under the protocol's allowance (512 for Protocol B).
    pub window: usize,
    /// First wait before reconnecting; doubled after each failure.
    pub backoff_min: Duration,
    /// Longest wait between reconnection attempts.
    pub backoff_max: Duration,
    /// Give up one connection attempt after this long.
    pub connect_timeout: Duration,
    /// TCP keepalive: probes start after this long without traffic, every `keepalive / 5`,
    /// and the connection is dropped after 3 unanswered ones, so a device server that lost
    /// power (no FIN, no RST: a half-open connection) is noticed. `None`: no keepalive.
    pub keepalive: Option<Duration>,
    /// A write the connection has not taken for this long (a device server that stops reading)
    /// drops the connection, which is then made again; the write is not lost, it waits.
    pub write_timeout: Duration,
}

impl Default for TcpOptions {
    fn default() -> Self {
        TcpOptions {
            window: 256,
            backoff_min: Duration::from_millis(100),
            backoff_max: Duration::from_secs(5),
            connect_timeout: Duration::from_secs(5),
            keepalive: Some(Duration::from_secs(10)),
            write_timeout: Duration::from_secs(10),
        }
    }
}

/// Connection history of a [`TcpTransport`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TcpStats {
    /// Successful connections, the first one included.
    pub connects: u64,
    /// Connections lost (EOF or I/O error).
    pub disconnects: u64,
    /// Failed connection attempts.
    pub connect_failures: u64,
}

type ConnectFuture = Pin<Box<dyn Future<Output = io::Result<TcpStream>> + Send>>;

enum State {
    Connected(TcpStream),
    Connecting(ConnectFuture),
    /// Waiting before the next connection attempt.
    Backoff(Pin<Box<Sleep>>),
    /// Shut down by the owner: no more reconnecting.
    Closed,
}

/// A serial line reached through a TCP device server. See the [module docs](self).
pub struct TcpTransport {
    addr: String,
    line: LineSettings,
    opts: TcpOptions,
    state: State,
    backoff: Backoff,
    pacer: Pacer,
    write_sleep: Option<Pin<Box<Sleep>>>,
    /// Since when the connection has not taken a write, and the timer of the write time-out.
    write_stuck: Option<(Instant, Pin<Box<Sleep>>)>,
    wakers: Arc<Wakers>,
    stats: TcpStats,
    modem_note_logged: bool,
}

impl fmt::Debug for TcpTransport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("TcpTransport")
            .field("addr", &self.addr)
            .field("line", &self.line)
            .field("connected", &self.is_connected())
            .field("stats", &self.stats)
            .finish()
    }
}

/// Check that `addr` has the form `host:port` (IPv6 hosts in brackets).
fn check_addr(addr: &str) -> Result<(), TransportError> {
    let bad = |reason| TransportError::BadAddress {
        addr: addr.to_string(),
        reason,
    };
    let (host, port) = addr.rsplit_once(':').ok_or_else(|| bad("no port"))?;
    if host.is_empty() {
        return Err(bad("no host"));
    }
    if host.contains(':') && !(host.starts_with('[') && host.ends_with(']')) {
        return Err(bad("an IPv6 host must be written in brackets"));
    }
    match port.parse::<u16>() {
        Ok(0) => Err(bad("port 0")),
        Ok(_) => Ok(()),
        Err(_) => Err(bad("the port is not a number from 1 to 65535")),
    }
}

impl TcpTransport {
    /// Connect to the device server at `addr` (`host:port`) carrying a line framed as `line`.
    ///
    /// Makes one connection attempt (up to [`TcpOptions::connect_timeout`]) before returning.
    /// If it fails, the transport is returned anyway, disconnected, and keeps trying with
    /// backoff while it is read or written: a device server switched on after cellgate is picked
    /// up without a restart. Only an address that is not `host:port` is an error
    /// ([`TransportError::BadAddress`]); an unresolvable host name is retried like a refused
    /// connection.
    pub async fn connect(
        addr: impl Into<String>,
        line: LineSettings,
        opts: TcpOptions,
    ) -> Result<TcpTransport, TransportError> {
        let addr = addr.into();
        check_addr(&addr)?;
        let mut t = TcpTransport {
            state: State::Connecting(connect_future(addr.clone(), opts.connect_timeout)),
            addr,
            line,
            backoff: Backoff::new(opts.backoff_min, opts.backoff_max),
            pacer: Pacer::new(line, opts.window),
            write_sleep: None,
            write_stuck: None,
            wakers: Arc::new(Wakers::default()),
            stats: TcpStats::default(),
            modem_note_logged: false,
            opts,
        };
        if let State::Connecting(f) = &mut t.state {
            let result = f.as_mut().await;
            t.connect_done(result);
        }
        Ok(t)
    }

    /// The device server's address as configured.
    pub fn addr(&self) -> &str {
        &self.addr
    }

    /// Whether a connection to the device server is up (as of the last read or write).
    pub fn is_connected(&self) -> bool {
        matches!(self.state, State::Connected(_))
    }

    /// Connection history.
    pub fn stats(&self) -> TcpStats {
        self.stats
    }

    /// Estimated characters written and not yet sent on the serial side: never above
    /// [`TcpOptions::window`] except by the last write's remainder.
    pub fn unsent_estimate(&self) -> u64 {
        self.pacer.unsent(Instant::now().into_std())
    }

    fn connect_done(&mut self, result: io::Result<TcpStream>) {
        match result {
            Ok(stream) => {
                // Small writes (a DC3, an ACK) must leave at once.
                if let Err(e) = stream.set_nodelay(true) {
                    debug!(addr = %self.addr, error = %e, "could not set TCP_NODELAY");
                }
                if let Some(idle) = self.opts.keepalive {
                    let keepalive = socket2::TcpKeepalive::new()
                        .with_time(idle)
                        .with_interval((idle / 5).max(Duration::from_secs(1)))
                        .with_retries(3);
                    if let Err(e) = socket2::SockRef::from(&stream).set_tcp_keepalive(&keepalive) {
                        debug!(addr = %self.addr, error = %e, "could not set TCP keepalive");
                    }
                }
                // Bytes the device server does not acknowledge within the write time-out drop
                // the connection (a powered-off server never answers, and TCP alone would
                // retransmit for about 15 minutes).
                #[cfg(target_os = "linux")]
                if let Err(e) = socket2::SockRef::from(&stream)
                    .set_tcp_user_timeout(Some(self.opts.write_timeout))
                {
                    debug!(addr = %self.addr, error = %e, "could not set TCP_USER_TIMEOUT");
                }
                self.stats.connects += 1;
                let failed = self.backoff.up();
                info!(
                    addr = %self.addr,
                    attempts = failed + 1,
                    "connected to the device server"
                );
                // The device server's buffer starts empty.
                self.pacer.reset();
                self.state = State::Connected(stream);
            }
            Err(e) => {
                self.stats.connect_failures += 1;
                let attempt = self.backoff.failed();
                if attempt == 1 {
                    warn!(
                        addr = %self.addr,
                        error = %e,
                        retry_in = ?self.backoff.peek(),
                        "cannot connect to the device server; the line reads as open until it answers"
                    );
                } else {
                    debug!(
                        addr = %self.addr,
                        error = %e,
                        attempt,
                        retry_in = ?self.backoff.peek(),
                        "device server still unreachable"
                    );
                }
                self.wait_backoff();
            }
        }
    }

    fn wait_backoff(&mut self) {
        let wait = self.backoff.take_wait();
        self.state = State::Backoff(Box::pin(tokio::time::sleep(wait)));
    }

    fn disconnected(&mut self, why: &dyn fmt::Display) {
        self.stats.disconnects += 1;
        self.backoff.lost();
        self.write_stuck = None;
        warn!(
            addr = %self.addr,
            reason = %why,
            retry_in = ?self.backoff.peek(),
            "device server connection lost; the line reads as open until it is back"
        );
        self.wait_backoff();
        self.wakers.wake_by_ref();
    }

    /// Drive reconnection as far as it goes without waiting. Returns whether connected.
    fn poll_connection(&mut self) -> bool {
        let waker = self.wakers.waker();
        let mut cx = Context::from_waker(&waker);
        loop {
            match &mut self.state {
                State::Connected(_) => return true,
                State::Closed => return false,
                State::Connecting(f) => match f.as_mut().poll(&mut cx) {
                    Poll::Ready(result) => {
                        self.connect_done(result);
                        if self.is_connected() {
                            self.wakers.wake_by_ref();
                        }
                    }
                    Poll::Pending => return false,
                },
                State::Backoff(sleep) => match sleep.as_mut().poll(&mut cx) {
                    Poll::Ready(()) => {
                        self.state = State::Connecting(connect_future(
                            self.addr.clone(),
                            self.opts.connect_timeout,
                        ));
                    }
                    Poll::Pending => return false,
                },
            }
        }
    }
}

fn connect_future(addr: String, timeout: Duration) -> ConnectFuture {
    Box::pin(async move {
        match tokio::time::timeout(timeout, TcpStream::connect(addr.as_str())).await {
            Ok(r) => r,
            Err(_) => Err(io::Error::new(
                io::ErrorKind::TimedOut,
                format!("no answer within {timeout:?}"),
            )),
        }
    })
}

impl Redialing for TcpTransport {
    type Stream = TcpStream;
    const END_OF_INPUT: &'static str = "closed by the device server";

    fn poll_up(&mut self) -> Poll<Option<&mut TcpStream>> {
        if !self.poll_connection() {
            return match self.state {
                State::Closed => Poll::Ready(None),
                _ => Poll::Pending,
            };
        }
        match &mut self.state {
            State::Connected(stream) => Poll::Ready(Some(stream)),
            _ => Poll::Pending,
        }
    }

    fn lost(&mut self, why: &dyn fmt::Display) {
        self.disconnected(why);
    }
}

impl AsyncRead for TcpTransport {
    /// Bytes from the device server. Never returns EOF or an error while the transport is in
    /// use: a lost connection is reported in the log and by the modem lines, and the read waits
    /// for the reconnection. EOF only after [`AsyncWriteExt::shutdown`](tokio::io::AsyncWriteExt).
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = &mut *self;
        Wakers::set(&this.wakers.read, cx.waker());
        redial::poll_read(this, cx, buf)
    }
}

impl AsyncWrite for TcpTransport {
    /// Writes at most the room left in the in-flight window; waits (a timer, not a busy loop)
    /// while the window is full, and while the device server is unreachable.
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        if matches!(this.state, State::Closed) {
            return Poll::Ready(Err(io::Error::new(
                io::ErrorKind::BrokenPipe,
                format!("device server {}: write after shutdown", this.addr),
            )));
        }
        if buf.is_empty() {
            return Poll::Ready(Ok(0));
        }
        Wakers::set(&this.wakers.write, cx.waker());
        loop {
            let now = Instant::now();
            // In batches of half a window at line rate, not the few characters freed since
            // the last write: a system call and a timer each cost more than the line's time.
            let room = this.pacer.batch(now.into_std(), buf.len());
            if room == 0 {
                let at = Instant::from_std(this.pacer.batch_at(now.into_std(), buf.len()));
                match super::poll_sleep(&mut this.write_sleep, at, cx) {
                    Poll::Ready(()) => continue,
                    Poll::Pending => return Poll::Pending,
                }
            }
            let n = room.min(buf.len());
            let chunk = buf.get(..n).unwrap_or(buf);
            if !this.poll_connection() {
                // Refused, not discarded: the writer waits for the reconnection (both wakers
                // are woken then).
                return Poll::Pending;
            }
            let State::Connected(stream) = &mut this.state else {
                continue;
            };
            match Pin::new(stream).poll_write(cx, chunk) {
                Poll::Pending => {
                    // The device server takes nothing: past the write time-out, it is
                    // dropped and made again (a server that stopped reading never recovers).
                    let timeout = this.opts.write_timeout;
                    let (since, sleep) = this.write_stuck.get_or_insert_with(|| {
                        (now, Box::pin(tokio::time::sleep_until(now + timeout)))
                    });
                    if sleep.as_mut().poll(cx).is_pending() {
                        return Poll::Pending;
                    }
                    let waited = since.elapsed();
                    this.disconnected(&format!(
                        "write time-out: the device server took nothing for {waited:?}"
                    ));
                }
                Poll::Ready(Ok(0)) => this.disconnected(&"the connection accepts no more bytes"),
                Poll::Ready(Ok(k)) => {
                    this.write_stuck = None;
                    this.pacer.wrote(k, now.into_std());
                    return Poll::Ready(Ok(k));
                }
                Poll::Ready(Err(e)) => this.disconnected(&e),
            }
            // Disconnected: loop to wait for the reconnection.
        }
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        if let State::Connected(stream) = &mut this.state
            && let Poll::Ready(Err(e)) = Pin::new(stream).poll_flush(cx)
        {
            this.disconnected(&e);
        }
        Poll::Ready(Ok(()))
    }

    /// Close the connection for good: no more reconnecting; reads return EOF.
    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        if let State::Connected(stream) = &mut this.state
            && Pin::new(stream).poll_shutdown(cx).is_pending()
        {
            return Poll::Pending;
        }
        if !matches!(this.state, State::Closed) {
            info!(addr = %this.addr, "device server connection closed");
        }
        this.state = State::Closed;
        this.wakers.wake_by_ref();
        Poll::Ready(Ok(()))
    }
}

impl Transport for TcpTransport {
    /// A raw TCP device server carries no modem lines: nothing to drive.
    fn set_modem(&mut self, out: ModemOut) -> io::Result<()> {
        if !self.modem_note_logged {
            self.modem_note_logged = true;
            debug!(
                addr = %self.addr,
                ?out,
                "the device server carries no modem lines; ER and RS are not sent"
            );
        }
        Ok(())
    }

    /// All lines on while connected (the manual's wiring for unused lines); all off while the
    /// device server is unreachable, like an open line.
    fn modem(&mut self) -> io::Result<ModemIn> {
        Ok(if self.is_connected() {
            ModemIn::ALL_ON
        } else {
            ModemIn {
                dr: false,
                cs: false,
                cd: false,
            }
        })
    }

    fn describe(&self) -> String {
        format!("tcp {} (line {})", self.addr, self.line)
    }

    /// The lines follow the connection, and every connect and disconnect wakes the reader.
    fn modem_wakes_reader(&self) -> bool {
        true
    }

    /// Drops the connection and connects again at once: the protocol heard nothing for longer
    /// than it allows, so the connection is likely half-open (the device server lost power or
    /// was replaced) even if TCP has not noticed yet.
    fn reconnect(&mut self, why: &str) {
        if self.is_connected() {
            self.disconnected(&format!("{why}; reconnecting"));
            self.state =
                State::Connecting(connect_future(self.addr.clone(), self.opts.connect_timeout));
            self.wakers.wake_by_ref();
        }
    }
}

#[cfg(test)]
mod tests;
