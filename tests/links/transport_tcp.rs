//! The TCP device-server transport against loopback listeners, in real time: bytes both ways,
//! reconnection after the server goes away, and the in-flight window.

use std::time::Duration;

use cellgate::transport::tcp::{TcpOptions, TcpTransport};
use cellgate::transport::{LineSettings, ModemIn, ModemOut, Transport, TransportError};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::{Instant, timeout};

const LONG: Duration = Duration::from_secs(10);

fn quick() -> TcpOptions {
    TcpOptions {
        backoff_min: Duration::from_millis(20),
        backoff_max: Duration::from_millis(200),
        connect_timeout: Duration::from_secs(2),
        ..TcpOptions::default()
    }
}

async fn listener() -> (TcpListener, String) {
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap().to_string();
    (l, addr)
}

/// Read from the transport until `want` bytes came, failing after [`LONG`].
async fn read_n(t: &mut TcpTransport, want: usize) -> Vec<u8> {
    let mut v = vec![0u8; want];
    timeout(LONG, t.read_exact(&mut v)).await.unwrap().unwrap();
    v
}

#[tokio::test]
async fn bytes_flow_both_ways() {
    let (l, addr) = listener().await;
    let mut t = TcpTransport::connect(addr.clone(), LineSettings::with_baud(19_200), quick())
        .await
        .unwrap();
    let (mut server, _) = timeout(LONG, l.accept()).await.unwrap().unwrap();
    assert!(t.is_up());
    assert_eq!(t.modem().unwrap(), ModemIn::ALL_ON);
    t.set_modem(ModemOut {
        er: false,
        rs: false,
    })
    .unwrap();
    assert_eq!(
        t.modem().unwrap(),
        ModemIn::ALL_ON,
        "no modem lines over raw TCP"
    );
    assert_eq!(t.describe(), format!("tcp {addr} (line 19200 8N2)"));

    let special = [0x11, 0x13, 0x0D, 0x0A, 0x00, 0xFF, 0x12, 0x14];
    t.write_all(&special).await.unwrap();
    let mut got = [0u8; 8];
    timeout(LONG, server.read_exact(&mut got))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(got, special);

    server.write_all(&special).await.unwrap();
    assert_eq!(read_n(&mut t, 8).await, special);
    assert_eq!(t.stats().ups, 1);
}

#[tokio::test]
async fn reconnects_after_the_server_goes_away() {
    let (l, addr) = listener().await;
    let mut t = TcpTransport::connect(addr.clone(), LineSettings::with_baud(9600), quick())
        .await
        .unwrap();
    let (mut server, _) = timeout(LONG, l.accept()).await.unwrap().unwrap();
    server.write_all(b"one").await.unwrap();
    assert_eq!(read_n(&mut t, 3).await, b"one");

    // The device server dies: listener and connection gone.
    drop(server);
    drop(l);
    // The read notices the EOF, does not return it, and waits for the reconnection.
    let mut b = [0u8; 1];
    assert!(
        timeout(Duration::from_millis(300), t.read(&mut b))
            .await
            .is_err()
    );
    assert!(!t.is_up());
    let m = t.modem().unwrap();
    assert!(
        !m.dr && !m.cd,
        "a lost device server reads as an open line: {m:?}"
    );
    assert_eq!(t.stats().losses, 1);
    assert!(t.stats().failures >= 1, "{:?}", t.stats());
    // Writes meanwhile are refused: they wait, nothing is taken and thrown away.
    assert!(
        timeout(Duration::from_millis(200), t.write_all(b"lost"))
            .await
            .is_err()
    );

    // It comes back on the same port.
    let l = TcpListener::bind(&addr).await.unwrap();
    let accept = tokio::spawn(async move { l.accept().await.unwrap().0 });
    let mut server = loop {
        // Reads drive the reconnection.
        let _ = timeout(Duration::from_millis(50), t.read(&mut b)).await;
        if accept.is_finished() {
            break accept.await.unwrap();
        }
    };
    server.write_all(b"two").await.unwrap();
    assert_eq!(read_n(&mut t, 3).await, b"two");
    assert!(t.is_up());
    assert_eq!(t.modem().unwrap(), ModemIn::ALL_ON);
    t.write_all(b"three").await.unwrap();
    let mut got = [0u8; 5];
    timeout(LONG, server.read_exact(&mut got))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(&got, b"three");
    assert_eq!(t.stats().ups, 2);
}

#[tokio::test]
async fn starts_without_a_server_and_picks_it_up() {
    // A port that nothing listens on (bound, noted, released).
    let (l, addr) = listener().await;
    drop(l);
    let mut t = TcpTransport::connect(addr.clone(), LineSettings::with_baud(9600), quick())
        .await
        .unwrap();
    assert!(!t.is_up());
    assert!(!t.modem().unwrap().dr);
    let l = TcpListener::bind(&addr).await.unwrap();
    let reader = tokio::spawn(async move {
        let mut b = [0u8; 2];
        t.read_exact(&mut b).await.unwrap();
        (t, b)
    });
    let (mut server, _) = timeout(LONG, l.accept()).await.unwrap().unwrap();
    server.write_all(b"hi").await.unwrap();
    let (t, b) = timeout(LONG, reader).await.unwrap().unwrap();
    assert_eq!(&b, b"hi");
    assert!(t.is_up());
    assert!(t.stats().failures >= 1);
}

#[tokio::test]
async fn a_bad_address_is_an_error() {
    let r = TcpTransport::connect("127.0.0.1", LineSettings::default(), quick()).await;
    assert!(matches!(r, Err(TransportError::BadAddress { .. })), "{r:?}");
}

/// At 9600 baud 8N2 (872.7 characters/s) with a 64-character window, writing 64 + 218
/// characters cannot finish before the 218 beyond the window have drained: 250 ms. And the
/// estimate of unsent characters never exceeds the window.
#[tokio::test]
async fn the_window_bounds_what_is_unsent() {
    let (l, addr) = listener().await;
    let line = LineSettings::with_baud(9600);
    let window = 64;
    let opts = TcpOptions { window, ..quick() };
    let mut t = TcpTransport::connect(addr, line, opts).await.unwrap();
    let (mut server, _) = timeout(LONG, l.accept()).await.unwrap().unwrap();
    let sink = tokio::spawn(async move {
        let mut v = Vec::new();
        server.read_to_end(&mut v).await.unwrap();
        v
    });
    let n = window + 218;
    let data: Vec<u8> = (0..n).map(|i| i as u8).collect();
    let t0 = Instant::now();
    let mut off = 0;
    while off < n {
        let k = t.write(&data[off..]).await.unwrap();
        assert!(k > 0);
        off += k;
        assert!(
            t.unsent_estimate() <= window as u64,
            "unsent {} > window {window}",
            t.unsent_estimate()
        );
    }
    let elapsed = t0.elapsed();
    let min = line.time_for_chars((n - window) as u64);
    assert!(
        elapsed >= min,
        "{n} chars written in {elapsed:?}, line needs {min:?}"
    );
    t.shutdown().await.unwrap();
    let got = timeout(LONG, sink).await.unwrap().unwrap();
    assert_eq!(got, data);
}

#[tokio::test]
async fn a_server_that_hangs_up_at_once_is_retried_with_growing_backoff() {
    let (l, addr) = listener().await;
    let hangup = tokio::spawn(async move {
        let mut accepted = 0u32;
        let mut last = Instant::now();
        let mut gaps = Vec::new();
        while accepted < 4 {
            let (s, _): (TcpStream, _) = l.accept().await.unwrap();
            gaps.push(last.elapsed());
            last = Instant::now();
            drop(s);
            accepted += 1;
        }
        gaps
    });
    let mut t = TcpTransport::connect(addr, LineSettings::default(), quick())
        .await
        .unwrap();
    let mut b = [0u8; 1];
    let _ = timeout(Duration::from_millis(600), t.read(&mut b)).await;
    let gaps = timeout(LONG, hangup).await.unwrap().unwrap();
    // 20 ms, then 40 ms, then 80 ms between attempts: each wait at least the backoff.
    assert!(gaps[1] >= Duration::from_millis(20), "{gaps:?}");
    assert!(gaps[2] >= Duration::from_millis(40), "{gaps:?}");
    assert!(gaps[3] >= Duration::from_millis(80), "{gaps:?}");
    assert!(t.stats().losses >= 3);
}

/// A device server that lost power leaves a half-open connection: nothing closes it. When the
/// protocol hears nothing for longer than it allows it asks for a new connection, and the
/// transport drops the old one and connects again at once.
#[tokio::test]
async fn reconnect_replaces_a_silent_connection() {
    let (l, addr) = listener().await;
    let mut t = TcpTransport::connect(addr.clone(), LineSettings::with_baud(9600), quick())
        .await
        .unwrap();
    let (_silent, _) = timeout(LONG, l.accept()).await.unwrap().unwrap();
    assert!(t.is_up());

    t.reconnect("no answer for 30 s");
    assert!(!t.is_up());
    let accept = tokio::spawn(async move { l.accept().await.unwrap().0 });
    let mut b = [0u8; 1];
    let mut server = loop {
        let _ = timeout(Duration::from_millis(50), t.read(&mut b)).await;
        if accept.is_finished() {
            break accept.await.unwrap();
        }
    };
    t.write_all(b"again").await.unwrap();
    let mut got = [0u8; 5];
    timeout(LONG, server.read_exact(&mut got))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(&got, b"again");
    assert_eq!(t.stats().ups, 2);
    assert_eq!(t.stats().losses, 1);
}

/// A device server that stops reading (hung firmware) takes no more bytes once the socket
/// buffers are full. After the write time-out the connection is dropped and made again, and
/// the write goes on over the new one.
#[tokio::test]
async fn a_server_that_stops_reading_is_replaced_after_the_write_timeout() {
    let (l, addr) = listener().await;
    let opts = TcpOptions {
        window: 1 << 20,
        write_timeout: Duration::from_millis(300),
        ..quick()
    };
    // A very fast "line" so the socket buffers fill in moments.
    let mut t = TcpTransport::connect(addr.clone(), LineSettings::with_baud(100_000_000), opts)
        .await
        .unwrap();
    let (_stuck, _) = timeout(LONG, l.accept()).await.unwrap().unwrap();
    let accept = tokio::spawn(async move { l.accept().await.unwrap().0 });
    let chunk = vec![0x55u8; 64 * 1024];
    let started = Instant::now();
    while !accept.is_finished() {
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "no new connection after the write stalled"
        );
        let _ = timeout(Duration::from_millis(50), t.write(&chunk)).await;
    }
    let mut server = accept.await.unwrap();
    assert_eq!(t.stats().losses, 1, "{:?}", t.stats());
    t.write_all(b"fresh").await.unwrap();
    let mut got = vec![0u8; 64 * 1024 + 5];
    // What the new connection carries ends with the fresh bytes.
    let mut seen = Vec::new();
    while !seen.ends_with(b"fresh") {
        let n = timeout(LONG, server.read(&mut got)).await.unwrap().unwrap();
        assert!(n > 0);
        seen.extend_from_slice(&got[..n]);
    }
}
