//! A real serial port (RS-232-C, or RS-422 through a converter), via tokio-serial.
//!
//! Rates: FANUC 50–19200 baud on RS-232-C and up to 86400 (76800, 86400) on RS-422; Fuji
//! 300–19200. Any rate is passed to the OS, which accepts non-standard ones where the driver can
//! (Linux: termios2 `BOTHER`); a rate the port refuses is [`TransportError::UnsupportedBaud`].
//! 1.5 stop bits are not offered by the OS interface: they are sent as 2, with a warning (a
//! receiver set to 1.5 accepts 2).
//!
//! Three things a plain tokio-serial stream gets wrong for a link, handled here:
//!
//! - **Line errors.** With parity on, Linux hands a character received with a parity or framing
//!   error to the reader as `0x00` — in program data a NUL that is silently ignored. The port is
//!   put in `PARMRK` mode, so the kernel marks such a character (`FF 00 c`) and doubles a real
//!   `FF`; the reader decodes that, drops the bad character and reports a [`LineError`] through
//!   [`Transport::take_line_error`] (§4.6 line errors).
//! - **Write-ahead.** The kernel's output queue holds kilobytes: a writer that fills it could not
//!   honour a DC3 for seconds. Writes are paced to the line rate through a bounded window
//!   ([`PACER_WINDOW`]), checked against the kernel's own count of unsent bytes where the port
//!   reports it.
//! - **Flush.** tokio-serial's flush calls `tcdrain`, which blocks the executor thread until the
//!   queue has gone out; here flush returns at once (the bytes are queued and will leave).
//!
//! Modem lines that a port cannot set or read (a pseudo-terminal answers ENOTTY, many USB
//! adapters lack DSR or CD) are logged once and read as on, the manual's wiring for unused lines;
//! they never fail the link.

use std::fmt;
use std::io;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::time::{Instant, Sleep};
use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};
use tracing::{debug, info, warn};

use cellgate_core::engine::parmrk::MarkDecoder;

use super::redial::{Dial, Dialer, Redial};
use super::{
    DataBits, FlowControl, LineError, LineSettings, ModemIn, ModemOut, Pacer, Parity, StopBits,
    Transport, TransportError,
};

/// Characters written and not yet sent, at most, by default: at 86400 baud about 16 ms of line
/// time, enough to ride over scheduling delays, and far inside Protocol B's 512-character
/// overrun allowance after a DC3 (§6.3).
pub const PACER_WINDOW: usize = 128;

/// Things logged once per port.
mod once {
    pub(super) const ER: u8 = 1 << 0;
    pub(super) const RS: u8 = 1 << 1;
    pub(super) const DR: u8 = 1 << 2;
    pub(super) const CS: u8 = 1 << 3;
    pub(super) const CD: u8 = 1 << 4;
    pub(super) const OUTQ: u8 = 1 << 5;
    pub(super) const RS_FLOW: u8 = 1 << 6;
}

/// A serial port as a [`Transport`]. See the [module docs](self).
pub struct SerialTransport {
    port: SerialStream,
    path: String,
    line: LineSettings,
    pacer: Pacer,
    write_sleep: Option<Pin<Box<Sleep>>>,
    /// Decoder of the kernel's error marks; `None` if the port could not be put in PARMRK mode.
    marks: Option<MarkDecoder>,
    logged: u8,
}

impl fmt::Debug for SerialTransport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SerialTransport")
            .field("path", &self.path)
            .field("line", &self.line)
            .finish()
    }
}

impl SerialTransport {
    /// Open the serial port at `path` (e.g. `/dev/ttyS0`, `/dev/ttyUSB0`) with `line`'s framing.
    /// The port is opened exclusively.
    pub fn open(path: &str, line: LineSettings) -> Result<SerialTransport, TransportError> {
        // Opened at a standard rate; the configured one is set in `from_stream`, where a rate
        // the port refuses can be told apart from a port that cannot be opened.
        let port = tokio_serial::new(path, 9600)
            .open_native_async()
            .map_err(|source| TransportError::Serial {
                path: path.to_string(),
                source,
            })?;
        Self::from_stream(port, path, line)
    }

    /// Wrap an already open port (a pseudo-terminal in tests, a port opened with special
    /// options), applying `line`'s framing. `path` names it in logs and errors.
    pub fn from_stream(
        mut port: SerialStream,
        path: impl Into<String>,
        line: LineSettings,
    ) -> Result<SerialTransport, TransportError> {
        let path = path.into();
        // Before the rate is set: the mode change goes through tcsetattr, and the rate through
        // termios2 afterwards, so a non-standard rate is not disturbed.
        let marks = match enable_error_marks(&port) {
            Ok(()) => Some(MarkDecoder::default()),
            Err(e) => {
                warn!(%path, error = %e, "cannot enable error marking: characters received with a parity error will not be reported");
                None
            }
        };
        configure(&mut port, &path, &line)?;
        Ok(SerialTransport {
            port,
            path,
            line,
            pacer: Pacer::new(line, PACER_WINDOW),
            write_sleep: None,
            marks,
            logged: 0,
        })
    }

    /// Use a different in-flight window (characters written and not yet sent, at most).
    pub fn with_window(mut self, window: usize) -> Self {
        self.pacer = Pacer::new(self.line, window);
        self
    }

    /// The port's path as given.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// Log `what` once for this port.
    fn first_time(&mut self, what: u8) -> bool {
        let first = self.logged & what == 0;
        self.logged |= what;
        first
    }

    /// Read one input line; a port that cannot tell reads as on (logged once).
    fn input(
        &mut self,
        bit: u8,
        name: &str,
        read: fn(&mut SerialStream) -> tokio_serial::Result<bool>,
    ) -> bool {
        match read(&mut self.port) {
            Ok(v) => v,
            Err(e) => {
                if self.first_time(bit) {
                    warn!(path = %self.path, line = name, error = %e, "the port cannot read this modem line; taking it as on");
                }
                true
            }
        }
    }

    /// Characters the kernel still holds for sending, where the port reports it.
    fn kernel_unsent(&mut self) -> Option<u64> {
        match self.port.bytes_to_write() {
            Ok(n) => Some(u64::from(n)),
            Err(e) => {
                if self.first_time(once::OUTQ) {
                    debug!(path = %self.path, error = %e, "the port does not report its output queue; pacing by line rate alone");
                }
                None
            }
        }
    }
}

/// Apply `line` to the port.
fn configure(
    port: &mut SerialStream,
    path: &str,
    line: &LineSettings,
) -> Result<(), TransportError> {
    let serial = |source| TransportError::Serial {
        path: path.to_string(),
        source,
    };
    port.set_baud_rate(line.baud)
        .map_err(|_| TransportError::UnsupportedBaud {
            path: path.to_string(),
            baud: line.baud,
        })?;
    let data_bits = match line.data_bits {
        DataBits::Seven => tokio_serial::DataBits::Seven,
        DataBits::Eight => tokio_serial::DataBits::Eight,
    };
    let parity = match line.parity {
        Parity::None => tokio_serial::Parity::None,
        Parity::Odd => tokio_serial::Parity::Odd,
        Parity::Even => tokio_serial::Parity::Even,
    };
    let stop_bits = match line.stop_bits {
        StopBits::One => tokio_serial::StopBits::One,
        StopBits::OnePointFive => {
            warn!(%path, "1.5 stop bits are not available on a serial port here; sending 2");
            tokio_serial::StopBits::Two
        }
        StopBits::Two => tokio_serial::StopBits::Two,
    };
    let flow = match line.flow_control {
        FlowControl::None => tokio_serial::FlowControl::None,
        FlowControl::RtsCts => tokio_serial::FlowControl::Hardware,
    };
    port.set_data_bits(data_bits).map_err(serial)?;
    port.set_parity(parity).map_err(serial)?;
    port.set_stop_bits(stop_bits).map_err(serial)?;
    port.set_flow_control(flow).map_err(serial)?;
    // Some ports (a pseudo-terminal) accept and ignore framing settings: say so.
    if port.data_bits().is_ok_and(|d| d != data_bits) || port.parity().is_ok_and(|p| p != parity) {
        warn!(%path, framing = %line, "the port ignored the data bits or parity setting");
    }
    Ok(())
}

/// Put the port in PARMRK mode: the kernel marks a character received with an error as
/// `FF 00 c` and doubles a real `FF`, instead of handing over `00` for a bad character.
#[cfg(unix)]
fn enable_error_marks(port: &SerialStream) -> io::Result<()> {
    use std::os::unix::io::AsRawFd;
    let fd = port.as_raw_fd();
    let mut t = std::mem::MaybeUninit::<libc::termios>::uninit();
    // SAFETY: fd is the open descriptor owned by `port`; tcgetattr initialises `t` on success.
    let t = unsafe {
        if libc::tcgetattr(fd, t.as_mut_ptr()) != 0 {
            return Err(io::Error::last_os_error());
        }
        t.assume_init()
    };
    let mut t = t;
    t.c_iflag |= libc::PARMRK;
    t.c_iflag &= !libc::ISTRIP;
    // SAFETY: as above; `t` is a valid termios read from the same descriptor.
    if unsafe { libc::tcsetattr(fd, libc::TCSANOW, &t) } != 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

#[cfg(not(unix))]
fn enable_error_marks(_port: &SerialStream) -> io::Result<()> {
    Err(io::Error::new(
        io::ErrorKind::Unsupported,
        "error marking needs a POSIX terminal",
    ))
}

impl AsyncRead for SerialTransport {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = &mut *self;
        let Some(marks) = &mut this.marks else {
            return Pin::new(&mut this.port).poll_read(cx, buf);
        };
        if buf.remaining() == 0 {
            return Poll::Ready(Ok(()));
        }
        loop {
            let n = marks.decode(buf.initialize_unfilled());
            if n > 0 {
                buf.advance(n);
                return Poll::Ready(Ok(()));
            }
            let mut scratch = [0u8; 512];
            let mut raw = ReadBuf::new(&mut scratch);
            match Pin::new(&mut this.port).poll_read(cx, &mut raw) {
                Poll::Pending => return Poll::Pending,
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                Poll::Ready(Ok(())) if raw.filled().is_empty() => {
                    let n = marks.finish(buf.initialize_unfilled());
                    buf.advance(n);
                    return Poll::Ready(Ok(()));
                }
                Poll::Ready(Ok(())) => marks.feed(raw.filled()),
            }
        }
    }
}

impl AsyncWrite for SerialTransport {
    /// Writes at most the room left in the in-flight window; waits on a timer while it is full.
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        if buf.is_empty() {
            return Poll::Ready(Ok(0));
        }
        let this = &mut *self;
        loop {
            let now = Instant::now();
            let window = this.pacer.window() as u64;
            let paced = this.pacer.unsent(now.into_std());
            let kernel = this.kernel_unsent().unwrap_or(0);
            let unsent = paced.max(kernel);
            // In batches of half a window at line rate (see `Pacer::batch`).
            let need = this.pacer.low_water(buf.len()) as u64;
            if unsent + need > window {
                let at = if paced + need > window {
                    Instant::from_std(this.pacer.batch_at(now.into_std(), buf.len()))
                } else {
                    now + this.line.time_for_chars(kernel + need - window)
                };
                match super::poll_sleep(&mut this.write_sleep, at, cx) {
                    Poll::Ready(()) => continue,
                    Poll::Pending => return Poll::Pending,
                }
            }
            let room = usize::try_from(window - unsent).unwrap_or(usize::MAX);
            let chunk = buf.get(..room.min(buf.len())).unwrap_or(buf);
            return match Pin::new(&mut this.port).poll_write(cx, chunk) {
                Poll::Ready(Ok(k)) => {
                    this.pacer.wrote(k, now.into_std());
                    Poll::Ready(Ok(k))
                }
                other => other,
            };
        }
    }

    /// Returns at once: written bytes are in the kernel's queue and leave at the line rate.
    /// (Waiting for them with `tcdrain` would block the executor thread.)
    fn poll_flush(self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }

    fn poll_shutdown(self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
}

impl Transport for SerialTransport {
    /// Drives DTR (ER) and RTS (RS). Under RTS/CTS flow control the UART owns RTS and only ER is
    /// set. A line the port cannot set is logged once and otherwise ignored.
    fn set_modem(&mut self, out: ModemOut) -> io::Result<()> {
        if let Err(e) = self.port.write_data_terminal_ready(out.er)
            && self.first_time(once::ER)
        {
            warn!(path = %self.path, error = %e, "the port cannot set ER (DTR); ignoring");
        }
        if self.line.flow_control == FlowControl::RtsCts {
            if self.first_time(once::RS_FLOW) {
                debug!(path = %self.path, "RTS/CTS flow control: RS is driven by the UART");
            }
        } else if let Err(e) = self.port.write_request_to_send(out.rs)
            && self.first_time(once::RS)
        {
            warn!(path = %self.path, error = %e, "the port cannot set RS (RTS); ignoring");
        }
        Ok(())
    }

    fn modem(&mut self) -> io::Result<ModemIn> {
        Ok(ModemIn {
            dr: self.input(once::DR, "DR (DSR)", |p| p.read_data_set_ready()),
            cs: self.input(once::CS, "CS (CTS)", |p| p.read_clear_to_send()),
            cd: self.input(once::CD, "CD", |p| p.read_carrier_detect()),
        })
    }

    fn take_line_error(&mut self) -> Option<LineError> {
        self.marks.as_mut().and_then(MarkDecoder::take_error)
    }

    fn describe(&self) -> String {
        format!("serial {} {}", self.path, self.line)
    }
}

/// A serial port that comes back by itself: the [`Transport`] a machine's `serial` link runs
/// over.
///
/// A port that cannot be opened at start (a USB adapter not plugged in yet, a port server still
/// booting) or that fails later (the adapter pulled: reads fail with `EIO`) is opened again with
/// bounded exponential backoff; see [`Redial`] for how the line reads meanwhile. When the port is
/// back, the framing and the last modem output lines are applied again. Only a setting the port
/// itself refuses (a baud rate) is an error, at start: retrying would not help.
pub type ReopeningSerial = Redial<PortOpener>;

/// How a [`ReopeningSerial`] opens its port.
#[derive(Debug)]
pub struct PortOpener {
    path: String,
    line: LineSettings,
    window: usize,
    modem_out: Option<ModemOut>,
}

impl ReopeningSerial {
    /// Open the port at `path`, or start without it and keep trying every `backoff_min` (doubling
    /// up to `backoff_max`) while the transport is read or written. Fails only if the port
    /// refuses the line settings ([`TransportError::UnsupportedBaud`]).
    pub fn open(
        path: impl Into<String>,
        line: LineSettings,
        backoff_min: Duration,
        backoff_max: Duration,
    ) -> Result<ReopeningSerial, TransportError> {
        let opener = PortOpener {
            path: path.into(),
            line,
            window: PACER_WINDOW,
            modem_out: None,
        };
        let first = SerialTransport::open(&opener.path, line);
        let mut t = Redial::new(opener, backoff_min, backoff_max);
        match first {
            Err(e @ TransportError::UnsupportedBaud { .. }) => return Err(e),
            first => t.dialed(first),
        }
        Ok(t)
    }

    /// Use a different in-flight window (see [`SerialTransport::with_window`]).
    pub fn with_window(mut self, window: usize) -> Self {
        let (opener, port) = self.parts_mut();
        opener.window = window;
        if let Some(port) = port {
            port.pacer = Pacer::new(port.line, window);
        }
        self
    }
}

impl Dialer for PortOpener {
    type Stream = SerialTransport;
    type Error = TransportError;
    const END_OF_INPUT: &'static str = "end of input";
    const NO_MORE_BYTES: &'static str = "the port accepts no more bytes";
    /// Closing the port and opening it again revives a USB adapter whose driver stopped
    /// delivering, often.
    const REDIAL: &'static str = "opening the port again";

    fn dial(&self) -> Dial<Self> {
        let (path, line) = (self.path.clone(), self.line);
        Box::pin(async move { SerialTransport::open(&path, line) })
    }

    fn up(&mut self, port: SerialTransport, opens: u64, failed_before: u64) -> SerialTransport {
        if opens > 1 || failed_before > 0 {
            info!(path = %self.path, attempts = failed_before + 1, "serial port open again");
        }
        let mut port = port.with_window(self.window);
        if let Some(out) = self.modem_out {
            // Errors are logged by the port once; the line works without them.
            let _ = port.set_modem(out);
        }
        port
    }

    fn dial_failed(&self, error: &TransportError, attempt: u64, retry_in: Duration) {
        if attempt == 1 {
            warn!(path = %self.path, %error, ?retry_in, "cannot open the serial port; the line reads as cut until it opens");
        } else {
            debug!(path = %self.path, %error, attempt, ?retry_in, "serial port still cannot be opened");
        }
    }

    fn lost(&mut self, why: &dyn fmt::Display, retry_in: Duration) {
        warn!(path = %self.path, reason = %why, ?retry_in, "serial port lost; the line reads as cut until it is open again");
    }

    fn name(&self) -> String {
        format!("serial port {}", self.path)
    }

    fn set_modem(&mut self, port: Option<&mut SerialTransport>, out: ModemOut) -> io::Result<()> {
        self.modem_out = Some(out);
        port.map_or(Ok(()), |port| port.set_modem(out))
    }

    fn modem(&mut self, port: &mut SerialTransport) -> io::Result<ModemIn> {
        port.modem()
    }

    fn take_line_error(&mut self, port: &mut SerialTransport) -> Option<LineError> {
        port.take_line_error()
    }

    fn describe(&self) -> String {
        format!("serial {} {}", self.path, self.line)
    }
}

#[cfg(test)]
mod tests;
