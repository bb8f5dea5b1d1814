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
//!
//! [`Transport::set_modem`]: super::Transport::set_modem
//! [`Transport::modem`]: super::Transport::modem

use std::fmt;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::AsyncWrite;
use tokio::net::TcpStream;
use tokio::time::{Instant, Sleep};
use tracing::{debug, info, warn};

use super::redial::{Dial, Dialer, Redial};
use super::{LineSettings, ModemIn, ModemOut, Pacer, TransportError};

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

/// A serial line reached through a TCP device server. See the [module docs](self).
pub type TcpTransport = Redial<DeviceServer>;

/// How a [`TcpTransport`] reaches its device server, and paces its writes.
pub struct DeviceServer {
    addr: String,
    line: LineSettings,
    opts: TcpOptions,
    pacer: Pacer,
    write_sleep: Option<Pin<Box<Sleep>>>,
    /// Since when the connection has not taken a write, and the timer of the write time-out.
    write_stuck: Option<(Instant, Pin<Box<Sleep>>)>,
    modem_note_logged: bool,
}

impl fmt::Debug for DeviceServer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("DeviceServer")
            .field("addr", &self.addr)
            .field("line", &self.line)
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
        let server = DeviceServer {
            addr,
            line,
            pacer: Pacer::new(line, opts.window),
            write_sleep: None,
            write_stuck: None,
            modem_note_logged: false,
            opts,
        };
        let first = server.dial().await;
        let mut t = Redial::new(server, opts.backoff_min, opts.backoff_max);
        t.dialed(first);
        Ok(t)
    }

    /// The device server's address as configured.
    pub fn addr(&self) -> &str {
        &self.dialer().addr
    }

    /// Estimated characters written and not yet sent on the serial side: never above
    /// [`TcpOptions::window`] except by the last write's remainder.
    pub fn unsent_estimate(&self) -> u64 {
        self.dialer().pacer.unsent(Instant::now().into_std())
    }
}

impl Dialer for DeviceServer {
    type Stream = TcpStream;
    type Error = io::Error;
    const END_OF_INPUT: &'static str = "closed by the device server";
    const NO_MORE_BYTES: &'static str = "the connection accepts no more bytes";
    /// The protocol heard nothing for longer than it allows: the connection is likely
    /// half-open (the device server lost power or was replaced) even if TCP has not noticed.
    const REDIAL: &'static str = "reconnecting";
    /// The lines follow the connection, and every connect and disconnect wakes the reader.
    const MODEM_WAKES_READER: bool = true;

    fn dial(&self) -> Dial<Self> {
        let (addr, timeout) = (self.addr.clone(), self.opts.connect_timeout);
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

    fn up(&mut self, stream: TcpStream, _connects: u64, failed_before: u64) -> TcpStream {
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
        // Bytes the device server does not acknowledge within the write time-out drop the
        // connection (a powered-off server never answers, and TCP alone would retransmit for
        // about 15 minutes).
        #[cfg(target_os = "linux")]
        if let Err(e) =
            socket2::SockRef::from(&stream).set_tcp_user_timeout(Some(self.opts.write_timeout))
        {
            debug!(addr = %self.addr, error = %e, "could not set TCP_USER_TIMEOUT");
        }
        info!(
            addr = %self.addr,
            attempts = failed_before + 1,
            "connected to the device server"
        );
        // The device server's buffer starts empty.
        self.pacer.reset();
        stream
    }

    fn dial_failed(&self, error: &io::Error, attempt: u64, retry_in: Duration) {
        if attempt == 1 {
            warn!(
                addr = %self.addr,
                %error,
                ?retry_in,
                "cannot connect to the device server; the line reads as open until it answers"
            );
        } else {
            debug!(
                addr = %self.addr,
                %error,
                attempt,
                ?retry_in,
                "device server still unreachable"
            );
        }
    }

    fn lost(&mut self, why: &dyn fmt::Display, retry_in: Duration) {
        self.write_stuck = None;
        warn!(
            addr = %self.addr,
            reason = %why,
            ?retry_in,
            "device server connection lost; the line reads as open until it is back"
        );
    }

    fn closed(&self) {
        info!(addr = %self.addr, "device server connection closed");
    }

    fn name(&self) -> String {
        format!("device server {}", self.addr)
    }

    /// Writes at most the room left in the in-flight window; waits (a timer, not a busy loop)
    /// while the window is full.
    fn poll_write(
        &mut self,
        stream: &mut TcpStream,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        loop {
            let now = Instant::now();
            // In batches of half a window at line rate, not the few characters freed since
            // the last write: a system call and a timer each cost more than the line's time.
            let room = self.pacer.batch(now.into_std(), buf.len());
            if room == 0 {
                let at = Instant::from_std(self.pacer.batch_at(now.into_std(), buf.len()));
                match super::poll_sleep(&mut self.write_sleep, at, cx) {
                    Poll::Ready(()) => continue,
                    Poll::Pending => return Poll::Pending,
                }
            }
            let chunk = buf.get(..room.min(buf.len())).unwrap_or(buf);
            return match Pin::new(&mut *stream).poll_write(cx, chunk) {
                Poll::Pending => {
                    // The device server takes nothing: past the write time-out, it is
                    // dropped and made again (a server that stopped reading never recovers).
                    let timeout = self.opts.write_timeout;
                    let (since, sleep) = self.write_stuck.get_or_insert_with(|| {
                        (now, Box::pin(tokio::time::sleep_until(now + timeout)))
                    });
                    if sleep.as_mut().poll(cx).is_pending() {
                        return Poll::Pending;
                    }
                    let waited = since.elapsed();
                    Poll::Ready(Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        format!("write time-out: the device server took nothing for {waited:?}"),
                    )))
                }
                Poll::Ready(Ok(k)) if k > 0 => {
                    self.write_stuck = None;
                    self.pacer.wrote(k, now.into_std());
                    Poll::Ready(Ok(k))
                }
                other => other,
            };
        }
    }

    /// A raw TCP device server carries no modem lines: nothing to drive.
    fn set_modem(&mut self, _stream: Option<&mut TcpStream>, out: ModemOut) -> io::Result<()> {
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

    /// All lines on while connected (the manual's wiring for unused lines).
    fn modem(&mut self, _stream: &mut TcpStream) -> io::Result<ModemIn> {
        Ok(ModemIn::ALL_ON)
    }

    fn describe(&self) -> String {
        format!("tcp {} (line {})", self.addr, self.line)
    }
}

#[cfg(test)]
mod tests;
