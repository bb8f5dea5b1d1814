//! The simulated serial line: pacing at the baud rate, flow control reach, modem lines and every
//! fault hook, all under paused time.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use cellgate::transport::sim::{self, Dir, End, SimOptions};
use cellgate::transport::{
    DataBits, LineError, LineSettings, ModemIn, ModemOut, Parity, StopBits, Transport,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::time::Instant;

const DC3: u8 = 0x13;

fn line_8n1(baud: u32) -> LineSettings {
    LineSettings {
        stop_bits: StopBits::One,
        ..LineSettings::with_baud(baud)
    }
}

fn line_8e1(baud: u32) -> LineSettings {
    LineSettings {
        parity: Parity::Even,
        stop_bits: StopBits::One,
        ..LineSettings::with_baud(baud)
    }
}

/// Send `n` bytes host → device and check every batch the device reads: never a byte before
/// its line time, and the last one within 1 % of the nominal time for `n` characters.
async fn check_pacing(settings: LineSettings, n: usize) {
    let (mut host, mut dev, l) = sim::line(settings);
    let data: Vec<u8> = (0..n).map(|i| (i % 251) as u8).collect();
    let t0 = Instant::now();
    let writer = tokio::spawn(async move {
        host.write_all(&data).await.unwrap();
        host
    });
    let mut got = Vec::with_capacity(n);
    let mut buf = [0u8; 4096];
    let mut reads = 0u64;
    while got.len() < n {
        let k = dev.read(&mut buf).await.unwrap();
        reads += 1;
        assert!(k > 0, "unexpected EOF");
        got.extend_from_slice(&buf[..k]);
        let elapsed = Instant::now() - t0;
        // Byte j arrives at t0 + time_for_chars(j + 1): having got.len() bytes means the last
        // of them is due by now.
        assert!(
            settings.time_for_chars(got.len() as u64) <= elapsed,
            "{settings}: {} bytes after {elapsed:?}, nominal {:?}",
            got.len(),
            settings.time_for_chars(got.len() as u64)
        );
    }
    let elapsed = Instant::now() - t0;
    let nominal = settings.time_for_chars(n as u64);
    assert!(
        elapsed.as_secs_f64() <= nominal.as_secs_f64() * 1.01,
        "{settings}: {n} bytes took {elapsed:?}, nominal {nominal:?}"
    );
    // The reader is woken per batch (at most once per millisecond of timer resolution), not
    // per character.
    let ms = nominal.as_millis() as u64;
    assert!(reads <= ms + 2, "{reads} reads for {n} bytes in {ms} ms");
    let mask = settings.data_mask();
    assert!(
        got.iter()
            .enumerate()
            .all(|(i, &b)| b == (i % 251) as u8 & mask)
    );
    let _host = writer.await.unwrap();
    let c = l.counters(Dir::HostToDevice);
    assert_eq!(c.written, n as u64);
    assert_eq!(c.delivered, n as u64);
}

#[tokio::test(start_paused = true)]
async fn pacing_86400_8n2_within_one_percent() {
    check_pacing(LineSettings::with_baud(86_400), 50_000).await;
}

#[tokio::test(start_paused = true)]
async fn pacing_19200_8n1_within_one_percent() {
    check_pacing(line_8n1(19_200), 20_000).await;
}

#[tokio::test(start_paused = true)]
async fn pacing_300_7e2() {
    let s = LineSettings {
        data_bits: DataBits::Seven,
        parity: Parity::Even,
        stop_bits: StopBits::Two,
        ..LineSettings::with_baud(300)
    };
    check_pacing(s, 300).await;
}

#[tokio::test(start_paused = true)]
async fn both_directions_at_once() {
    let s = LineSettings::with_baud(19_200);
    let (host, dev, _l) = sim::line(s);
    let (mut hr, mut hw) = tokio::io::split(host);
    let (mut dr, mut dw) = tokio::io::split(dev);
    let t0 = Instant::now();
    let a = tokio::spawn(async move { hw.write_all(&[0x55; 2000]).await.unwrap() });
    let b = tokio::spawn(async move { dw.write_all(&[0xAA; 2000]).await.unwrap() });
    let mut x = vec![0u8; 2000];
    let mut y = vec![0u8; 2000];
    let (r1, r2) = tokio::join!(dr.read_exact(&mut x), hr.read_exact(&mut y));
    r1.unwrap();
    r2.unwrap();
    a.await.unwrap();
    b.await.unwrap();
    assert!(x.iter().all(|&v| v == 0x55));
    assert!(y.iter().all(|&v| v == 0xAA));
    // Full duplex: both directions in the time of one.
    let el = Instant::now() - t0;
    let nominal = s.time_for_chars(2000);
    assert!(
        el >= nominal && el.as_secs_f64() <= nominal.as_secs_f64() * 1.01,
        "{el:?}"
    );
}

/// A mebibyte through the line in paused time. Wall time is printed, not asserted (speed
/// belongs in benchmarks). Wakeups are per batch: the reader and the writer each wake once per
/// millisecond of line time (the timer's resolution), whatever the baud rate.
#[tokio::test(start_paused = true)]
async fn one_mebibyte_in_paused_time() {
    let s = LineSettings::with_baud(86_400);
    let (mut host, mut dev, l) = sim::line(s);
    const N: usize = 1 << 20;
    let wall = std::time::Instant::now();
    let writer = tokio::spawn(async move {
        host.write_all(&vec![0x5A; N]).await.unwrap();
        host.shutdown().await.unwrap();
    });
    let mut v = Vec::with_capacity(N);
    dev.read_to_end(&mut v).await.unwrap();
    writer.await.unwrap();
    assert_eq!(v.len(), N);
    assert_eq!(l.counters(Dir::HostToDevice).delivered, N as u64);
    eprintln!(
        "1 MiB at {s}: {:?} virtual, {:?} wall",
        s.time_for_chars(N as u64),
        wall.elapsed()
    );
}

/// The receiver sends DC3 after 100 characters; a writer that stops on it overruns by no more
/// than the transmit FIFO, the shift register and the DC3's own flight (§4.6).
#[tokio::test(start_paused = true)]
async fn dc3_takes_effect_within_a_fifo() {
    let s = LineSettings::with_baud(9600);
    let fifo = 16;
    let (host, mut dev, _l) = sim::line_with(s, SimOptions { fifo });
    let (mut hr, mut hw) = tokio::io::split(host);
    let stop = Arc::new(AtomicBool::new(false));
    let sent = Arc::new(AtomicU64::new(0));
    let watcher = {
        let stop = stop.clone();
        tokio::spawn(async move {
            let mut b = [0u8; 1];
            hr.read_exact(&mut b).await.unwrap();
            assert_eq!(b[0], DC3);
            stop.store(true, Ordering::SeqCst);
        })
    };
    let writer = {
        let (stop, sent) = (stop.clone(), sent.clone());
        tokio::spawn(async move {
            for i in 0..5000u32 {
                if stop.load(Ordering::SeqCst) {
                    break;
                }
                hw.write_all(&[(i % 200) as u8]).await.unwrap();
                sent.fetch_add(1, Ordering::SeqCst);
            }
        })
    };
    let mut got = 0usize;
    let mut buf = [0u8; 256];
    while got < 100 {
        got += dev.read(&mut buf).await.unwrap();
    }
    let at_dc3 = got;
    dev.write_all(&[DC3]).await.unwrap();
    watcher.await.unwrap();
    writer.await.unwrap();
    // Collect whatever was still on its way; the host end is gone, so EOF follows.
    loop {
        match dev.read(&mut buf).await.unwrap() {
            0 => break,
            k => got += k,
        }
    }
    assert_eq!(got as u64, sent.load(Ordering::SeqCst));
    let overrun = got - at_dc3;
    // FIFO + shift register + the DC3's own character time + timer resolution.
    assert!(overrun <= fifo + 4, "overran DC3 by {overrun} characters");
}

#[tokio::test(start_paused = true)]
async fn modem_lines_cross_like_a_null_modem() {
    let (mut host, mut dev, l) = sim::line(LineSettings::with_baud(9600));
    assert_eq!(host.modem().unwrap(), ModemIn::ALL_ON);
    assert_eq!(dev.modem().unwrap(), ModemIn::ALL_ON);
    host.set_modem(ModemOut {
        er: false,
        rs: true,
    })
    .unwrap();
    assert_eq!(
        dev.modem().unwrap(),
        ModemIn {
            dr: false,
            cs: true,
            cd: false
        }
    );
    host.set_modem(ModemOut {
        er: true,
        rs: false,
    })
    .unwrap();
    assert_eq!(
        dev.modem().unwrap(),
        ModemIn {
            dr: true,
            cs: false,
            cd: true
        }
    );
    assert_eq!(
        host.modem().unwrap(),
        ModemIn::ALL_ON,
        "host reads the device's lines"
    );
    dev.set_modem(ModemOut {
        er: false,
        rs: false,
    })
    .unwrap();
    assert_eq!(
        host.modem().unwrap(),
        ModemIn {
            dr: false,
            cs: false,
            cd: false
        }
    );
    assert_eq!(
        l.modem_out(End::Host),
        ModemOut {
            er: true,
            rs: false
        }
    );
    assert_eq!(l.modem_in(End::Host), host.modem().unwrap());
}

#[tokio::test(start_paused = true)]
async fn corrupt_with_parity_reports_and_withholds_the_byte() {
    let s = line_8e1(9600);
    let (mut host, mut dev, l) = sim::line(s);
    host.write_all(b"AB").await.unwrap();
    l.corrupt_next(Dir::HostToDevice, 0x04);
    host.write_all(b"CDE").await.unwrap();
    let mut b = [0u8; 4];
    dev.read_exact(&mut b).await.unwrap();
    assert_eq!(&b, b"ABDE");
    assert_eq!(dev.take_line_error(), Some(LineError::Parity));
    assert_eq!(dev.take_line_error(), None);
    let c = l.counters(Dir::HostToDevice);
    assert_eq!(
        (c.written, c.delivered, c.corrupted, c.line_errors),
        (5, 4, 1, 1)
    );
    // The other direction is untouched.
    assert_eq!(l.counters(Dir::DeviceToHost).corrupted, 0);
    assert_eq!(host.take_line_error(), None);
}

#[tokio::test(start_paused = true)]
async fn a_read_stops_before_an_errored_character() {
    let (mut host, mut dev, l) = sim::line(line_8e1(9600));
    host.write_all(b"AB").await.unwrap();
    l.corrupt_next(Dir::HostToDevice, 0x01);
    host.write_all(b"CD").await.unwrap();
    tokio::time::sleep(Duration::from_millis(50)).await; // all four have arrived
    let mut b = [0u8; 8];
    let n = dev.read(&mut b).await.unwrap();
    assert_eq!(&b[..n], b"AB");
    // The error lies after these bytes: the next read takes it, and it comes before that
    // read's bytes, so that a reader that takes the errors before the bytes of each read sees
    // them in line order.
    assert_eq!(dev.take_line_error(), None);
    let n = dev.read(&mut b).await.unwrap();
    assert_eq!(&b[..n], b"D");
    assert_eq!(dev.take_line_error(), Some(LineError::Parity));
    assert_eq!(dev.take_line_error(), None);
}

#[tokio::test(start_paused = true)]
async fn corrupt_without_parity_delivers_the_altered_byte() {
    let (mut host, mut dev, l) = sim::line(LineSettings::with_baud(9600));
    l.corrupt_next(Dir::DeviceToHost, 0x20);
    dev.write_all(b"ab").await.unwrap();
    let mut b = [0u8; 2];
    host.read_exact(&mut b).await.unwrap();
    assert_eq!(&b, b"Ab");
    assert_eq!(host.take_line_error(), None);
    let c = l.counters(Dir::DeviceToHost);
    assert_eq!((c.corrupted, c.delivered, c.line_errors), (1, 2, 0));
}

#[tokio::test(start_paused = true)]
async fn drop_next_removes_bytes_and_counts_them() {
    let (mut host, mut dev, l) = sim::line(LineSettings::with_baud(19_200));
    host.write_all(b"12").await.unwrap();
    l.drop_next(Dir::HostToDevice, 3);
    host.write_all(b"34567").await.unwrap();
    host.shutdown().await.unwrap();
    let mut v = Vec::new();
    dev.read_to_end(&mut v).await.unwrap();
    assert_eq!(v, b"1267");
    let c = l.counters(Dir::HostToDevice);
    assert_eq!((c.written, c.delivered, c.dropped), (7, 4, 3));
}

#[tokio::test(start_paused = true)]
async fn delay_postpones_later_deliveries() {
    let s = LineSettings::with_baud(9600);
    let (mut host, mut dev, l) = sim::line(s);
    let delay = Duration::from_millis(200);
    l.set_delay(Dir::HostToDevice, delay);
    let t0 = Instant::now();
    host.write_all(b"Q").await.unwrap();
    let mut b = [0u8; 1];
    dev.read_exact(&mut b).await.unwrap();
    let el = Instant::now() - t0;
    assert!(el >= delay + s.char_time(), "{el:?}");
    assert!(
        el < delay + s.char_time() + Duration::from_millis(5),
        "{el:?}"
    );
    // The other direction is not delayed.
    let t1 = Instant::now();
    dev.write_all(b"R").await.unwrap();
    host.read_exact(&mut b).await.unwrap();
    assert!(Instant::now() - t1 < Duration::from_millis(5));
}

#[tokio::test(start_paused = true)]
async fn cut_drops_modem_lines_and_traffic_until_restored() {
    let s = LineSettings::with_baud(9600);
    let (mut host, mut dev, l) = sim::line(s);
    // Bytes in flight when the cable is cut are lost.
    host.write_all(b"lost").await.unwrap();
    l.cut();
    assert!(l.is_cut());
    let off = ModemIn {
        dr: false,
        cs: false,
        cd: false,
    };
    assert_eq!(host.modem().unwrap(), off);
    assert_eq!(dev.modem().unwrap(), off);
    // Writes are accepted and go nowhere.
    host.write_all(b"into the void").await.unwrap();
    dev.write_all(b"also").await.unwrap();
    let mut b = [0u8; 16];
    let r = tokio::time::timeout(Duration::from_secs(2), dev.read(&mut b)).await;
    assert!(r.is_err(), "nothing may arrive on a cut line");
    let r = tokio::time::timeout(Duration::from_secs(2), host.read(&mut b)).await;
    assert!(r.is_err(), "nothing may arrive on a cut line");
    let c = l.counters(Dir::HostToDevice);
    assert_eq!((c.written, c.delivered, c.lost), (17, 0, 17));
    assert_eq!(l.counters(Dir::DeviceToHost).lost, 4);

    l.restore();
    assert!(!l.is_cut());
    assert_eq!(host.modem().unwrap(), ModemIn::ALL_ON);
    assert_eq!(dev.modem().unwrap(), ModemIn::ALL_ON);
    host.write_all(b"back").await.unwrap();
    let mut b = [0u8; 4];
    dev.read_exact(&mut b).await.unwrap();
    assert_eq!(&b, b"back");
}

#[tokio::test(start_paused = true)]
async fn a_cut_wakes_no_reader_and_restore_resumes_it() {
    let (mut host, mut dev, l) = sim::line(LineSettings::with_baud(9600));
    let reader = tokio::spawn(async move {
        let mut b = [0u8; 2];
        dev.read_exact(&mut b).await.unwrap();
        b
    });
    tokio::task::yield_now().await;
    l.cut();
    host.write_all(b"xx").await.unwrap();
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert!(!reader.is_finished());
    l.restore();
    host.write_all(b"ok").await.unwrap();
    assert_eq!(&reader.await.unwrap(), b"ok");
}

#[tokio::test(start_paused = true)]
async fn dropping_an_end_gives_the_other_eof_after_the_queue() {
    let (mut host, mut dev, l) = sim::line(LineSettings::with_baud(9600));
    dev.write_all(b"bye").await.unwrap();
    drop(dev);
    let mut v = Vec::new();
    host.read_to_end(&mut v).await.unwrap();
    assert_eq!(v, b"bye");
    // The peer is gone: its lines read off, writes are discarded without error.
    assert_eq!(
        host.modem().unwrap(),
        ModemIn {
            dr: false,
            cs: false,
            cd: false
        }
    );
    host.write_all(b"anyone?").await.unwrap();
    let c = l.counters(Dir::HostToDevice);
    assert_eq!((c.written, c.lost), (7, 7));
}

#[tokio::test(start_paused = true)]
async fn a_pending_reader_sees_eof_when_the_peer_drops() {
    let (host, mut dev, _l) = sim::line(LineSettings::with_baud(9600));
    let reader = tokio::spawn(async move {
        let mut b = [0u8; 8];
        dev.read(&mut b).await.unwrap()
    });
    tokio::time::sleep(Duration::from_millis(10)).await;
    drop(host);
    assert_eq!(reader.await.unwrap(), 0);
}

#[tokio::test(start_paused = true)]
async fn binary_bytes_pass_unchanged_on_8_bits() {
    let (mut host, mut dev, _l) = sim::line(LineSettings::with_baud(38_400));
    let all: Vec<u8> = (0..=255).collect();
    host.write_all(&all).await.unwrap();
    let mut b = vec![0u8; 256];
    dev.read_exact(&mut b).await.unwrap();
    assert_eq!(b, all);
}

#[tokio::test(start_paused = true)]
async fn describe_and_boxed_transport() {
    let (host, _dev, _l) = sim::line(line_8e1(4800));
    let mut boxed: Box<dyn Transport> = Box::new(host);
    assert_eq!(boxed.describe(), "sim 4800 8E1");
    assert_eq!(boxed.modem().unwrap(), ModemIn::ALL_ON);
}
