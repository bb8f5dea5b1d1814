use super::*;
use cellgate_core::engine::{LineError, LineSettings};
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
    fn poll_write(self: Pin<&mut Self>, _: &mut Context<'_>, b: &[u8]) -> Poll<io::Result<usize>> {
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

/// Records what reaches it, in order.
#[derive(Default)]
struct Recorder(Vec<String>);

impl Engine for Recorder {
    type Command = ();
    type Event = ();
    fn handle_input(&mut self, _: Instant, bytes: &[u8]) {
        self.0.push(String::from_utf8_lossy(bytes).into_owned());
    }
    fn handle_line_error(&mut self, _: Instant, e: LineError) {
        self.0.push(format!("<{e}>"));
    }
    fn handle_modem(&mut self, _: Instant, _: ModemIn) {}
    fn handle_command(&mut self, _: Instant, _: ()) {}
    fn handle_timeout(&mut self, _: Instant) {}
    fn poll_transmit(&mut self, _: Instant) -> Option<Vec<u8>> {
        None
    }
    fn poll_event(&mut self) -> Option<()> {
        None
    }
    fn poll_timeout(&self) -> Option<Instant> {
        None
    }
}

/// Bytes, a character received with a parity error, more bytes, all arrived before the pump
/// reads: the engine sees the error between the bytes around it, as they were on the line,
/// not after them (a read never spans an error; the ones it met come before its bytes).
#[tokio::test(start_paused = true)]
async fn a_line_error_reaches_the_engine_between_the_bytes_around_it() {
    use tokio::io::AsyncWriteExt;
    let settings = LineSettings::with_baud(9600);
    let (host, mut device, sim) = crate::transport::sim::line(settings);
    device.write_all(b"ab").await.unwrap();
    sim.error_next(crate::transport::sim::Dir::DeviceToHost, LineError::Parity);
    device.write_all(b"Xcd").await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    let mut pump = Pump::new(Recorder::default(), host);
    while pump.engine().0.concat().len() < "ab<>cd".len() + LineError::Parity.to_string().len() {
        tokio::time::timeout(Duration::from_secs(1), pump.step())
            .await
            .expect("the pump reads what arrived")
            .unwrap();
    }
    let seen = pump.engine().0.concat();
    assert_eq!(seen, format!("ab<{}>cd", LineError::Parity));
}

/// A carrier that is down until it is read, and then hands over what arrived at once, as a
/// device server does when it reconnects with a character its serial side held.
struct Reconnecting {
    lines: ModemIn,
    waiting: Option<&'static [u8]>,
    /// Reads answered Pending before the carrier comes back.
    down_for: u32,
}

impl AsyncRead for Reconnecting {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        if self.down_for > 0 {
            self.down_for -= 1;
            cx.waker().wake_by_ref();
            return Poll::Pending;
        }
        match self.waiting.take() {
            Some(bytes) => {
                self.lines = ModemIn::ALL_ON;
                buf.put_slice(bytes);
                Poll::Ready(Ok(()))
            }
            None => Poll::Pending,
        }
    }
}
impl AsyncWrite for Reconnecting {
    fn poll_write(self: Pin<&mut Self>, _: &mut Context<'_>, b: &[u8]) -> Poll<io::Result<usize>> {
        Poll::Ready(Ok(b.len()))
    }
    fn poll_flush(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
    fn poll_shutdown(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
}
impl Transport for Reconnecting {
    fn set_modem(&mut self, _: ModemOut) -> io::Result<()> {
        Ok(())
    }
    fn modem(&mut self) -> io::Result<ModemIn> {
        Ok(self.lines)
    }
    fn describe(&self) -> String {
        "reconnecting".into()
    }
    fn modem_wakes_reader(&self) -> bool {
        true
    }
}

/// Records the line's state and the input, in order; drops input while the line is down,
/// as a Protocol B host does.
#[derive(Default)]
struct LineOrder {
    up: bool,
    seen: Vec<String>,
}

impl Engine for LineOrder {
    type Command = ();
    type Event = ();
    fn handle_input(&mut self, _: Instant, bytes: &[u8]) {
        if self.up {
            self.seen.push(String::from_utf8_lossy(bytes).into_owned());
        }
    }
    fn handle_line_error(&mut self, _: Instant, _: LineError) {}
    fn handle_modem(&mut self, _: Instant, m: ModemIn) {
        self.up = m.dr && m.cd;
        self.seen
            .push(if self.up { "up" } else { "down" }.to_string());
    }
    fn handle_command(&mut self, _: Instant, _: ()) {}
    fn handle_timeout(&mut self, _: Instant) {}
    fn poll_transmit(&mut self, _: Instant) -> Option<Vec<u8>> {
        None
    }
    fn poll_event(&mut self) -> Option<()> {
        None
    }
    fn poll_timeout(&self) -> Option<Instant> {
        None
    }
}

/// The first bytes of a connection that came back reach the engine after it heard that the
/// line is up: a Protocol B board's DC1 sent as the device server reconnected was dropped as
/// noise on a dead line, and the job waited for good for a DC1 that had come.
#[tokio::test(start_paused = true)]
async fn the_first_bytes_on_a_line_that_came_back_follow_its_coming_up() {
    let down = ModemIn {
        dr: false,
        cs: false,
        cd: false,
    };
    let transport = |down_for| Reconnecting {
        lines: down,
        waiting: Some(b"\x11"),
        down_for,
    };
    // The line seen down first, then back with a byte; and a byte in the very first read.
    for (down_for, expected) in [(1, &["down", "up", "\u{11}"][..]), (0, &["up", "\u{11}"])] {
        let mut pump = Pump::new(LineOrder::default(), transport(down_for));
        for _ in 0..3 {
            let _ = tokio::time::timeout(Duration::from_millis(100), pump.step()).await;
        }
        assert_eq!(pump.engine().seen, expected);
    }
}
