//! Transports: what carries a link's bytes, so that no protocol code knows.
//!
//! Every link driver talks to a [`Transport`]: an `AsyncRead + AsyncWrite` byte stream plus the
//! modem lines the FANUC protocols use (§3.2, §3.3 of the remote-buffer manual): the host sets
//! ER (DTR) and RS (RTS) and reads DR (DSR), CS (CTS) and CD. Three carriers exist:
//!
//! - [`serial`]: a real serial port (tokio-serial);
//! - [`tcp`]: a raw TCP connection to a serial device server, reconnecting with backoff and
//!   writing through a bounded in-flight window;
//! - [`sim`]: an in-memory line to a simulated board, paced at the configured baud rate, with
//!   fault injection;
//! - [`parity`]: around either of the first two, the parity bit of a 7-bit line made and
//!   checked by the gateway where the port passes whole 8-bit frames.
//!
//! All three bound how far a writer can run ahead of the line with a [`Pacer`], so that a stop
//! code (DC3) from the peer takes effect within a few characters (§6.3), not after whatever a
//! UART FIFO, the kernel or a device server has already swallowed.
//!
//! Line errors that a UART reports (parity, framing, overrun) surface as [`LineError`]s through
//! [`Transport::take_line_error`]; a cut line or a lost device server shows as DR (and CD) off in
//! [`Transport::modem`] (alarm SR0855). Neither is an I/O error, and nothing panics on line input.

pub mod parity;
pub mod redial;
pub mod serial;
pub mod sim;
pub mod tcp;

pub use cellgate_core::engine::pacer::{self, Pacer};

use tokio::io::{AsyncRead, AsyncWrite};

pub use cellgate_core::engine::line::{
    DataBits, FlowControl, LineError, LineSettings, ModemIn, ModemOut, Parity, StopBits,
};

/// Errors of the carriers themselves, kept apart from protocol and device errors.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TransportError {
    #[error("serial port {path}: {source}")]
    Serial {
        path: String,
        #[source]
        source: tokio_serial::Error,
    },
    #[error("serial port {path}: baud rate {baud} is not supported by this port")]
    UnsupportedBaud { path: String, baud: u32 },
    #[error(
        "device server address {addr:?}: {reason} (expected host:port, e.g. 192.168.0.10:4001)"
    )]
    BadAddress { addr: String, reason: &'static str },
    #[error("device server {addr}: {source}")]
    Tcp {
        addr: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

/// A byte stream with modem lines: what every link driver runs over.
///
/// Implementations never block the executor and never panic on line input. A line that the
/// carrier cannot report (a pseudo-terminal, a TCP device server, many USB adapters) reads as on,
/// which is the manual's own wiring for unused lines; the carrier logs that once.
pub trait Transport: AsyncRead + AsyncWrite + Send + Unpin {
    /// Drive the host's output lines ER (DTR) and RS (RTS).
    fn set_modem(&mut self, out: ModemOut) -> std::io::Result<()>;

    /// Read the input lines DR (DSR), CS (CTS) and CD.
    fn modem(&mut self) -> std::io::Result<ModemIn>;

    /// Take the oldest line error the receiver reported since the last call, if any.
    /// Bytes that arrived with an error are not delivered by `poll_read`.
    fn take_line_error(&mut self) -> Option<LineError> {
        None
    }

    /// A short human description for logs and status ("serial /dev/ttyS0 19200 8N2").
    fn describe(&self) -> String;

    /// Whether the carrier wakes its reader whenever its input lines change (a TCP device
    /// server: they follow the connection, which the reader drives), so that they need not be
    /// polled. The others are read on a timer, which an idle link then pays for.
    fn modem_wakes_reader(&self) -> bool {
        false
    }

    /// The protocol heard nothing from the peer for longer than it allows: a carrier that can
    /// (a TCP device server whose end went away without closing, a serial port that stopped
    /// answering) drops its connection and makes a new one. Others ignore it.
    fn reconnect(&mut self, _why: &str) {}
}

impl<T: Transport + ?Sized> Transport for Box<T> {
    fn set_modem(&mut self, out: ModemOut) -> std::io::Result<()> {
        (**self).set_modem(out)
    }
    fn modem(&mut self) -> std::io::Result<ModemIn> {
        (**self).modem()
    }
    fn take_line_error(&mut self) -> Option<LineError> {
        (**self).take_line_error()
    }
    fn describe(&self) -> String {
        (**self).describe()
    }
    fn modem_wakes_reader(&self) -> bool {
        (**self).modem_wakes_reader()
    }
    fn reconnect(&mut self, why: &str) {
        (**self).reconnect(why)
    }
}

/// Arm `slot` for `deadline` and poll it. Ready means the deadline has passed.
pub(crate) fn poll_sleep(
    slot: &mut Option<std::pin::Pin<Box<tokio::time::Sleep>>>,
    deadline: tokio::time::Instant,
    cx: &mut std::task::Context<'_>,
) -> std::task::Poll<()> {
    let sleep = match slot {
        Some(s) => {
            if s.deadline() != deadline {
                s.as_mut().reset(deadline);
            }
            s
        }
        None => slot.insert(Box::pin(tokio::time::sleep_until(deadline))),
    };
    sleep.as_mut().poll(cx)
}
