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

use crate::engine::Engine;
use crate::engine::{ModemIn, ModemOut};
use crate::transport::Transport;

/// How often the input modem lines are read. DR going off must be noticed quickly (SR0855),
/// but transports cannot signal changes, so they are polled.
pub const MODEM_POLL: Duration = Duration::from_millis(50);

const READ_CHUNK: usize = 4096;

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
            moved |= self.sync_modem(cx, now);
            moved |= self.poll_read(cx, now)?;
            moved |= self.poll_write(cx, now)?;
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

    fn sync_modem(&mut self, cx: &mut Context<'_>, now: Instant) -> bool {
        let want = self.engine.modem_out();
        if self.modem_out != Some(want) {
            if let Err(e) = self.transport.set_modem(want) {
                tracing::debug!(error = %e, "cannot drive modem lines");
            }
            self.modem_out = Some(want);
        }
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
        let lines = match self.transport.modem() {
            Ok(m) => m,
            Err(e) => {
                tracing::debug!(error = %e, "cannot read modem lines; treating them as on");
                ModemIn::ALL_ON
            }
        };
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
mod tests {
    use super::*;
    use crate::engine::LineError;
    use std::collections::VecDeque;
    use tokio::io::DuplexStream;

    /// A transport over an in-memory duplex pipe, for testing the pump alone.
    struct Pipe(DuplexStream);

    impl AsyncRead for Pipe {
        fn poll_read(
            mut self: Pin<&mut Self>,
            cx: &mut Context<'_>,
            buf: &mut ReadBuf<'_>,
        ) -> Poll<io::Result<()>> {
            Pin::new(&mut self.0).poll_read(cx, buf)
        }
    }
    impl AsyncWrite for Pipe {
        fn poll_write(
            mut self: Pin<&mut Self>,
            cx: &mut Context<'_>,
            buf: &[u8],
        ) -> Poll<io::Result<usize>> {
            Pin::new(&mut self.0).poll_write(cx, buf)
        }
        fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
            Pin::new(&mut self.0).poll_flush(cx)
        }
        fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
            Pin::new(&mut self.0).poll_shutdown(cx)
        }
    }
    impl Transport for Pipe {
        fn set_modem(&mut self, _: ModemOut) -> io::Result<()> {
            Ok(())
        }
        fn modem(&mut self) -> io::Result<ModemIn> {
            Ok(ModemIn::ALL_ON)
        }
        fn describe(&self) -> String {
            "pipe".into()
        }
    }

    /// Echoes every input upper-cased, and says "tick" at each deadline one second apart.
    #[derive(Default)]
    struct Echo {
        out: VecDeque<Vec<u8>>,
        events: VecDeque<String>,
        next_tick: Option<Instant>,
        ticks: u32,
    }

    impl Engine for Echo {
        type Command = &'static str;
        type Event = String;
        fn handle_input(&mut self, _: Instant, bytes: &[u8]) {
            self.out.push_back(bytes.to_ascii_uppercase());
            self.events.push_back(format!("in {}", bytes.len()));
        }
        fn handle_line_error(&mut self, _: Instant, _: LineError) {}
        fn handle_modem(&mut self, now: Instant, _: ModemIn) {
            self.next_tick.get_or_insert(now + Duration::from_secs(1));
        }
        fn handle_command(&mut self, _: Instant, c: &'static str) {
            self.out.push_back(c.as_bytes().to_vec());
        }
        fn handle_timeout(&mut self, now: Instant) {
            if self.next_tick.is_some_and(|t| t <= now) {
                self.ticks += 1;
                self.events.push_back(format!("tick {}", self.ticks));
                self.next_tick = Some(now + Duration::from_secs(1));
            }
        }
        fn poll_transmit(&mut self, _: Instant) -> Option<Vec<u8>> {
            self.out.pop_front()
        }
        fn poll_event(&mut self) -> Option<String> {
            self.events.pop_front()
        }
        fn poll_timeout(&self) -> Option<Instant> {
            self.next_tick
        }
    }

    #[tokio::test(start_paused = true)]
    async fn moves_bytes_and_fires_deadlines_in_virtual_time() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let (a, mut b) = tokio::io::duplex(64);
        let mut pump = Pump::new(Echo::default(), Pipe(a));
        pump.command("hello");
        let started = tokio::time::Instant::now();
        let mut events = Vec::new();
        let peer = async {
            let mut buf = [0u8; 5];
            b.read_exact(&mut buf).await.unwrap();
            assert_eq!(&buf, b"hello");
            b.write_all(b"abc").await.unwrap();
            let mut buf = [0u8; 3];
            b.read_exact(&mut buf).await.unwrap();
            assert_eq!(&buf, b"ABC");
            b
        };
        let drive = async {
            loop {
                while let Some(ev) = pump.engine_mut().poll_event() {
                    events.push(ev);
                }
                if events.iter().filter(|e| e.starts_with("tick")).count() >= 3 {
                    break;
                }
                pump.step().await.unwrap();
            }
        };
        let (_b, ()) = tokio::join!(peer, drive);
        assert!(events.contains(&"in 3".to_string()));
        // Three one-second ticks took three virtual seconds (and no wall time to speak of).
        let elapsed = started.elapsed();
        assert!(
            elapsed >= Duration::from_secs(3) && elapsed < Duration::from_millis(3100),
            "{elapsed:?}"
        );
    }

    /// A transport whose input lines the test sets, and that carries nothing.
    struct Lines(std::sync::Arc<std::sync::Mutex<ModemIn>>);

    impl AsyncRead for Lines {
        fn poll_read(
            self: Pin<&mut Self>,
            _: &mut Context<'_>,
            _: &mut ReadBuf<'_>,
        ) -> Poll<io::Result<()>> {
            Poll::Pending
        }
    }
    impl AsyncWrite for Lines {
        fn poll_write(
            self: Pin<&mut Self>,
            _: &mut Context<'_>,
            b: &[u8],
        ) -> Poll<io::Result<usize>> {
            Poll::Ready(Ok(b.len()))
        }
        fn poll_flush(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<io::Result<()>> {
            Poll::Ready(Ok(()))
        }
        fn poll_shutdown(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<io::Result<()>> {
            Poll::Ready(Ok(()))
        }
    }
    impl Transport for Lines {
        fn set_modem(&mut self, _: ModemOut) -> io::Result<()> {
            Ok(())
        }
        fn modem(&mut self) -> io::Result<ModemIn> {
            Ok(*self.0.lock().unwrap())
        }
        fn describe(&self) -> String {
            "lines".into()
        }
    }

    /// Records the input lines it is given; no deadlines, nothing to send.
    #[derive(Default)]
    struct Watcher(VecDeque<ModemIn>);

    impl Engine for Watcher {
        type Command = ();
        type Event = ModemIn;
        fn handle_input(&mut self, _: Instant, _: &[u8]) {}
        fn handle_line_error(&mut self, _: Instant, _: LineError) {}
        fn handle_modem(&mut self, _: Instant, modem: ModemIn) {
            self.0.push_back(modem);
        }
        fn handle_command(&mut self, _: Instant, _: ()) {}
        fn handle_timeout(&mut self, _: Instant) {}
        fn poll_transmit(&mut self, _: Instant) -> Option<Vec<u8>> {
            None
        }
        fn poll_event(&mut self) -> Option<ModemIn> {
            self.0.pop_front()
        }
        fn poll_timeout(&self) -> Option<Instant> {
            None
        }
    }

    /// An engine with no deadline on a silent line still hears every change of the input
    /// lines: the modem polling keeps itself going (it once stopped after a tick that saw no
    /// change, leaving a Protocol B link down for good after its line came back).
    #[tokio::test(start_paused = true)]
    async fn a_silent_line_is_still_polled_for_its_modem_lines() {
        let lines = std::sync::Arc::new(std::sync::Mutex::new(ModemIn::ALL_ON));
        let mut pump = Pump::new(Watcher::default(), Lines(lines.clone()));
        let down = ModemIn {
            dr: false,
            cs: false,
            cd: false,
        };
        // The pump runs in a task of its own, so that nothing else's wake-ups poll it.
        let drive = tokio::spawn(async move {
            let mut seen = Vec::new();
            let _ = tokio::time::timeout(Duration::from_secs(10), async {
                loop {
                    while let Some(m) = pump.engine_mut().poll_event() {
                        seen.push(m);
                    }
                    pump.step().await.unwrap();
                }
            })
            .await;
            seen
        });
        tokio::time::sleep(Duration::from_secs(1)).await;
        *lines.lock().unwrap() = down;
        tokio::time::sleep(Duration::from_secs(5)).await;
        *lines.lock().unwrap() = ModemIn::ALL_ON;
        let seen = drive.await.unwrap();
        assert_eq!(seen, [ModemIn::ALL_ON, down, ModemIn::ALL_ON]);
    }

    #[tokio::test(start_paused = true)]
    async fn reports_closed_line() {
        let (a, b) = tokio::io::duplex(64);
        drop(b);
        let mut pump = Pump::new(Echo::default(), Pipe(a));
        // End of stream from the peer is `Closed`, not an I/O error; a pump that missed it
        // would wait forever, which the time-out turns into a failure.
        let err = tokio::time::timeout(Duration::from_secs(60), pump.run(|_| {}))
            .await
            .expect("the pump did not notice the closed line");
        assert!(matches!(err, PumpError::Closed), "{err}");
    }
}
