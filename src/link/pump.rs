//! Runs one sans-IO [`Engine`] over one [`Transport`].
//!
//! The pump owns the I/O plumbing every engine needs and nothing protocol-specific: it reads
//! what arrives and hands it to the engine, writes what the engine asks to send (one piece at
//! a time, so a stop request takes effect after the current piece), reports line errors and
//! modem-line changes, and wakes the engine at its deadline. Its state lives in the struct, so
//! [`Pump::step`] is cancel-safe and can sit in a `select!` beside other work.
//!
//! All time comes from `tokio::time`, so a pump runs under paused time: tests drive hours of
//! line traffic in milliseconds.

use std::future::poll_fn;
use std::io;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::time::{Interval, MissedTickBehavior, Sleep};

use crate::transport::Transport;
use cellgate_core::engine::Engine;
use cellgate_core::engine::{ModemIn, ModemOut};

/// How often the input modem lines are read. DR going off must be noticed quickly (SR0855),
/// but transports cannot signal changes, so they are polled.
pub const MODEM_POLL: Duration = Duration::from_millis(50);

/// The most read at once. A board sends little to the host (answers, SAT, punched programs at
/// 19200 baud at most), and a thousand links each hold this buffer: four reads a step
/// (`poll_read`) take 4 KiB.
const READ_CHUNK: usize = 1024;

/// Why a pump stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PumpError {
    /// The transport reached end of stream: the peer went away for good.
    #[error("the line was closed by the other end")]
    Closed,
    #[error("line I/O failed: {0}")]
    Io(#[from] io::Error),
}

/// The current time as engines see it.
pub fn now() -> Instant {
    tokio::time::Instant::now().into_std()
}

/// One engine, one transport, and the I/O state between them.
pub struct Pump<E, T> {
    engine: E,
    transport: T,
    tx: Vec<u8>,
    tx_pos: usize,
    rx: Box<[u8]>,
    sleep: Pin<Box<Sleep>>,
    sleep_at: Option<Instant>,
    /// Polls the input lines, unless the transport wakes the reader on their changes.
    modem_tick: Option<Interval>,
    modem_in: Option<ModemIn>,
    modem_out: Option<ModemOut>,
    bytes_in: u64,
    bytes_out: u64,
}

impl<E: Engine, T: Transport> Pump<E, T> {
    pub fn new(engine: E, transport: T) -> Self {
        let modem_tick = (!transport.modem_wakes_reader()).then(|| {
            let mut tick = tokio::time::interval(MODEM_POLL);
            tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
            tick
        });
        Pump {
            engine,
            transport,
            tx: Vec::new(),
            tx_pos: 0,
            rx: vec![0; READ_CHUNK].into_boxed_slice(),
            sleep: Box::pin(tokio::time::sleep(Duration::ZERO)),
            sleep_at: None,
            modem_tick,
            modem_in: None,
            modem_out: None,
            bytes_in: 0,
            bytes_out: 0,
        }
    }

    pub fn engine(&self) -> &E {
        &self.engine
    }

    pub fn engine_mut(&mut self) -> &mut E {
        &mut self.engine
    }

    pub fn transport(&self) -> &T {
        &self.transport
    }

    pub fn transport_mut(&mut self) -> &mut T {
        &mut self.transport
    }

    /// Bytes read from and written to the line so far.
    pub fn counters(&self) -> (u64, u64) {
        (self.bytes_in, self.bytes_out)
    }

    /// Takes the engine and transport back.
    pub fn into_parts(self) -> (E, T) {
        (self.engine, self.transport)
    }

    /// Drives I/O until something happened (bytes moved, a deadline passed, a line changed),
    /// so that the caller can collect events and give the engine more work. Cancel-safe.
    pub async fn step(&mut self) -> Result<(), PumpError> {
        poll_fn(|cx| self.poll_step(cx)).await
    }

    /// Drives the pump until it fails, handing every event to `on_event`. For engines that
    /// need nothing but their own line (simulated boards); the host driver uses [`Pump::step`].
    pub async fn run(&mut self, mut on_event: impl FnMut(E::Event)) -> PumpError {
        loop {
            while let Some(ev) = self.engine.poll_event() {
                on_event(ev);
            }
            if let Err(e) = self.step().await {
                return e;
            }
        }
    }

    /// Hands a command to the engine at the current time.
    pub fn command(&mut self, command: E::Command) {
        self.engine.handle_command(now(), command);
    }

    fn poll_step(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), PumpError>> {
        let mut progress = false;
        // Loop until nothing more can be done without waiting: every handle_* may make the
        // engine want to transmit or move its deadline.
        loop {
            let mut moved = false;
            let now = now();
            // Bytes first, then the lines: what arrived before a line went off is the
            // engine's before it hears of the change (a board's DC3 before its ER off).
            moved |= self.poll_read(cx, now)?;
            moved |= self.sync_modem(cx, now);
            moved |= self.poll_write(cx, now)?;
            // After the write: bytes the engine handed out before changing its lines go first
            // (a board's DC3 before its ER goes off, §6.4 (1)).
            self.drive_modem();
            moved |= self.poll_deadline(cx, now);
            if !moved {
                break;
            }
            progress = true;
        }
        if progress {
            Poll::Ready(Ok(()))
        } else {
            Poll::Pending
        }
    }

    fn drive_modem(&mut self) {
        let want = self.engine.modem_out();
        if self.modem_out != Some(want) {
            if let Err(e) = self.transport.set_modem(want) {
                tracing::debug!(error = %e, "cannot drive modem lines");
            }
            self.modem_out = Some(want);
        }
    }

    fn sync_modem(&mut self, cx: &mut Context<'_>, now: Instant) -> bool {
        // Poll until pending, so that the next tick's wake-up is registered: a tick taken
        // without a change and nothing else to do would otherwise leave a silent line (a
        // Protocol B line waiting for DR) unpolled for good.
        // A transport that wakes the reader on changes is read at every step: a cheap
        // look at its state, and no timer for an idle line.
        let mut tick = self.modem_tick.is_none();
        if let Some(modem_tick) = &mut self.modem_tick {
            while modem_tick.poll_tick(cx).is_ready() {
                tick = true;
            }
        }
        if !tick && self.modem_in.is_some() {
            return false;
        }
        let lines = self.read_modem();
        self.apply_modem(now, lines)
    }

    fn read_modem(&mut self) -> ModemIn {
        match self.transport.modem() {
            Ok(m) => m,
            Err(e) => {
                tracing::debug!(error = %e, "cannot read modem lines; treating them as on");
                ModemIn::ALL_ON
            }
        }
    }

    /// Bytes read while the engine holds the line down (or before it heard of the lines at
    /// all): if the line is up now, they came on
    /// it (a device server that reconnected and handed over at once what its serial side
    /// held, a board's DC1), so the engine hears that the line is up before them, not after
    /// them, when it would drop them as noise on a dead line.
    fn line_up_before_input(&mut self, now: Instant) {
        if self.modem_in.is_none_or(|m| !(m.dr && m.cd)) {
            let lines = self.read_modem();
            if lines.dr && lines.cd {
                self.apply_modem(now, lines);
            }
        }
    }

    fn apply_modem(&mut self, now: Instant, lines: ModemIn) -> bool {
        if self.modem_in != Some(lines) {
            self.modem_in = Some(lines);
            if !(lines.dr && lines.cd) && self.tx_pos < self.tx.len() {
                // The line went down: what the engine handed out and the transport has not
                // taken is dropped, so that nothing of it goes out when the line is back (the
                // engine has given it up and counts none of it as acknowledged).
                tracing::debug!(
                    dropped = self.tx.len() - self.tx_pos,
                    "line down: unsent bytes dropped"
                );
                self.tx.clear();
                self.tx_pos = 0;
            }
            self.engine.handle_modem(now, lines);
            return true;
        }
        false
    }

    fn poll_read(&mut self, cx: &mut Context<'_>, now: Instant) -> Result<bool, PumpError> {
        let mut moved = false;
        // A bounded number of reads per step keeps a fast line from starving the writer.
        for _ in 0..4 {
            let mut buf = ReadBuf::new(&mut self.rx);
            match Pin::new(&mut self.transport).poll_read(cx, &mut buf) {
                Poll::Ready(Ok(())) => {
                    let n = buf.filled().len();
                    if n == 0 {
                        return Err(PumpError::Closed);
                    }
                    self.bytes_in += n as u64;
                    // A read never spans a line error, and the errors it met come before its
                    // bytes: the engine must see them in line order, so that it knows which
                    // text the bad character belonged to (FFU120B §5-6, §4.6).
                    while let Some(err) = self.transport.take_line_error() {
                        self.engine.handle_line_error(now, err);
                    }
                    self.line_up_before_input(now);
                    self.engine.handle_input(now, &self.rx[..n]);
                    moved = true;
                }
                Poll::Ready(Err(e)) => return Err(e.into()),
                Poll::Pending => break,
            }
        }
        while let Some(err) = self.transport.take_line_error() {
            self.engine.handle_line_error(now, err);
            moved = true;
        }
        Ok(moved)
    }

    fn poll_write(&mut self, cx: &mut Context<'_>, now: Instant) -> Result<bool, PumpError> {
        let mut moved = false;
        loop {
            if self.tx_pos >= self.tx.len() {
                match self.engine.poll_transmit(now) {
                    Some(bytes) if !bytes.is_empty() => {
                        self.tx = bytes;
                        self.tx_pos = 0;
                    }
                    Some(_) => continue,
                    None => return Ok(moved),
                }
            }
            match Pin::new(&mut self.transport).poll_write(cx, &self.tx[self.tx_pos..]) {
                Poll::Ready(Ok(0)) => return Err(PumpError::Closed),
                Poll::Ready(Ok(n)) => {
                    self.tx_pos += n;
                    self.bytes_out += n as u64;
                    moved = true;
                }
                Poll::Ready(Err(e)) => return Err(e.into()),
                Poll::Pending => return Ok(moved),
            }
        }
    }

    fn poll_deadline(&mut self, cx: &mut Context<'_>, now: Instant) -> bool {
        let Some(deadline) = self.engine.poll_timeout() else {
            self.sleep_at = None;
            return false;
        };
        if deadline <= now {
            self.sleep_at = None;
            self.engine.handle_timeout(now);
            return true;
        }
        if self.sleep_at != Some(deadline) {
            self.sleep
                .as_mut()
                .reset(tokio::time::Instant::from_std(deadline));
            self.sleep_at = Some(deadline);
        }
        if self.sleep.as_mut().poll(cx).is_ready() {
            self.sleep_at = None;
            self.engine.handle_timeout(now.max(deadline));
            return true;
        }
        false
    }
}

impl<E, T: AsyncRead + AsyncWrite> std::fmt::Debug for Pump<E, T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pump")
            .field("bytes_in", &self.bytes_in)
            .field("bytes_out", &self.bytes_out)
            .field(
                "pending_tx",
                &(self.tx.len() - self.tx_pos.min(self.tx.len())),
            )
            .finish()
    }
}

#[cfg(test)]
mod tests;
