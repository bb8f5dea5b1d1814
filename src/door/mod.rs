//! The doors every listener of the process shares: the console's, the MTConnect agent's HTTP
//! interface and SHDR port, the OPC UA server's (docs/security.md, "Listeners").
//!
//! Whoever reaches a port can open connections and then do nothing with them. A door bounds
//! what that costs:
//!
//! - **Connections**: each listener holds at most its share of the open-file budget
//!   ([`connection_cap`]): the process's limit less what the bus, the journal, the history,
//!   the library and the serial ports need, split between listeners. A connection over the cap
//!   is accepted and closed at once (an HTTP one answered 503), counted
//!   (`cellgate.listen.refused`), never left in the backlog.
//! - **Writes**: a connection's kernel send buffer is [`SEND_BUFFER`], and one whose peer
//!   does not read fails its write after [`WRITE_TIMEOUT`] ([`Admitted`]), freeing its slot.
//! - **Heads and lines**: an HTTP request head must come within [`HEAD_TIMEOUT`] and
//!   [`MAX_HEAD`] bytes ([`http::serve`]); a line protocol bounds its own lines (SHDR).

pub mod admitted;
pub mod http;

use std::net::SocketAddr;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;

pub use self::admitted::Admitted;

/// How long a client has to send a whole request head (and, on a kept-alive connection, the
/// next one) before its connection is closed.
pub const HEAD_TIMEOUT: Duration = Duration::from_secs(10);
/// How long a write may wait for a client that does not read before its connection is closed.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(30);
/// A request head's size at most: its request line and headers (a browser's cookies fit
/// many times over).
pub const MAX_HEAD: usize = 32 * 1024;
/// Open files kept for everything but the listeners: the bus's sockets, the journal, the
/// history, the library and its watch, serial ports, logs.
pub const RESERVE: u64 = 256;
/// The listeners the budget is split between: the console, the MTConnect agent's HTTP
/// interface, its SHDR port, and the OPC UA server.
pub const SHARES: u64 = 4;
/// A listener's connections at most, however high the limit on open files.
pub const MAX_CONNECTIONS: usize = 1024;
/// A listener's connections at least, however low the limit (then the reserve is cut into).
pub const MIN_CONNECTIONS: usize = 4;
/// A connection's kernel send buffer: fixed (the kernel would let it grow to megabytes), so
/// that what a client leaves unread is bounded and a write waits, and times out, soon.
pub const SEND_BUFFER: usize = 64 * 1024;
/// How often a listener logs the connections it refused, at most.
const REFUSED_LOG_EVERY: Duration = Duration::from_secs(10);

/// The process's soft limit on open files, read once (after the binary raised it).
pub fn open_file_limit() -> u64 {
    static LIMIT: OnceLock<u64> = OnceLock::new();
    *LIMIT.get_or_init(|| {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit only writes the struct it is given.
        if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
            // Unknown: the limit every Linux process starts with.
            return 1024;
        }
        limit.rlim_cur
    })
}

/// Connections one listener may hold, for a limit of `open_files`.
pub fn cap_for(open_files: u64) -> usize {
    let share = open_files.saturating_sub(RESERVE) / SHARES;
    usize::try_from(share)
        .unwrap_or(MAX_CONNECTIONS)
        .clamp(MIN_CONNECTIONS, MAX_CONNECTIONS)
}

/// Connections one listener may hold in this process.
pub fn connection_cap() -> usize {
    cap_for(open_file_limit())
}

/// A listening socket with its cap on connections.
pub struct Door {
    /// Names the listener in logs and in the refusals' counter.
    name: &'static str,
    tcp: TcpListener,
    slots: Arc<Semaphore>,
    cap: usize,
    /// Written to a connection over the cap before it is closed (an HTTP 503); may be empty.
    full: &'static [u8],
    /// Refused since the last log line, and when that was.
    refused: Mutex<(u64, Option<Instant>)>,
}

/// What a plain HTTP listener answers a connection over its cap.
pub const HTTP_FULL: &[u8] = b"HTTP/1.1 503 Service Unavailable\r\nRetry-After: 10\r\n\
Content-Length: 0\r\nConnection: close\r\n\r\n";

impl Door {
    /// A door on `tcp` holding at most `cap` connections (at most [`connection_cap`]).
    pub fn new(name: &'static str, tcp: TcpListener, cap: usize, full: &'static [u8]) -> Door {
        let cap = cap.min(connection_cap()).max(1);
        Door {
            name,
            tcp,
            slots: Arc::new(Semaphore::new(cap)),
            cap,
            full,
            refused: Mutex::new((0, None)),
        }
    }

    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.tcp.local_addr()
    }

    /// Connections this door holds at most.
    pub fn cap(&self) -> usize {
        self.cap
    }

    /// The next connection within the cap. Those over it are closed as they come.
    pub async fn accept(&self) -> (Admitted<TcpStream>, SocketAddr) {
        loop {
            let (stream, peer) = match self.tcp.accept().await {
                Ok(a) => a,
                // Out of file descriptors and the like: wait, rather than spin.
                Err(e) => {
                    tracing::warn!(listener = self.name, error = %e, "accept failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            };
            match Arc::clone(&self.slots).try_acquire_owned() {
                Ok(permit) => {
                    if let Err(e) =
                        socket2::SockRef::from(&stream).set_send_buffer_size(SEND_BUFFER)
                    {
                        tracing::debug!(listener = self.name, error = %e, "send buffer not set");
                    }
                    return (Admitted::new(stream, Some(permit)), peer);
                }
                Err(_) => self.refuse(stream, peer),
            }
        }
    }

    /// Closes a connection over the cap at once, with the door's `full` answer if the socket
    /// takes it now, and counts it.
    fn refuse(&self, stream: TcpStream, peer: SocketAddr) {
        // What the client sent already is read first, so that closing sends a FIN its answer
        // can be read before, not a reset.
        let mut sink = [0u8; 4096];
        let _ = stream.try_read(&mut sink);
        if !self.full.is_empty() {
            let _ = stream.try_write(self.full);
        }
        drop(stream);
        crate::telemetry::metrics::event("cellgate.listen.refused", &[("listener", self.name)], 1);
        let mut refused = self.refused.lock().unwrap_or_else(|e| e.into_inner());
        refused.0 += 1;
        if refused.1.is_none_or(|t| t.elapsed() >= REFUSED_LOG_EVERY) {
            tracing::warn!(
                listener = self.name,
                %peer,
                refused = refused.0,
                cap = self.cap,
                "{} connections held already; connections refused",
                self.cap
            );
            *refused = (0, Some(Instant::now()));
        }
    }
}

impl axum::serve::Listener for Door {
    type Io = Admitted<TcpStream>;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        Door::accept(self).await
    }

    fn local_addr(&self) -> std::io::Result<Self::Addr> {
        self.tcp.local_addr()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_budget_leaves_the_reserve_and_splits_the_rest() {
        assert_eq!(cap_for(1024), 192);
        assert_eq!(cap_for(512), 64);
        assert_eq!(cap_for(100), MIN_CONNECTIONS);
        assert_eq!(cap_for(1 << 20), MAX_CONNECTIONS);
        assert_eq!(cap_for(u64::MAX), MAX_CONNECTIONS);
    }
}
