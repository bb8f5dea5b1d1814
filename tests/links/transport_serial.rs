//! The serial transport on a pseudo-terminal pair: raw bytes both ways (flow-control and
//! control characters included) and modem lines that a pty cannot report reading as on.
//! A pty ignores parity and data bits and has no modem lines; the simulated line covers those.
#![cfg(unix)]

use std::time::Duration;

use cellgate::transport::serial::{ReopeningSerial, SerialTransport};
use cellgate::transport::{LineSettings, ModemIn, ModemOut, Parity, StopBits, Transport};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::time::timeout;
use tokio_serial::SerialStream;

const LONG: Duration = Duration::from_secs(10);
const SPECIAL: [u8; 9] = [0x11, 0x13, 0x0D, 0x0A, 0x00, 0xFF, 0xFF, 0x12, 0x7F];

fn pair(line: LineSettings) -> (SerialTransport, SerialStream) {
    let (master, slave) = SerialStream::pair().expect("a pseudo-terminal pair");
    let t = SerialTransport::from_stream(slave, "pty", line).unwrap();
    (t, master)
}

#[tokio::test]
async fn raw_bytes_flow_both_ways() {
    let (mut t, mut master) = pair(LineSettings::with_baud(19_200));
    assert_eq!(t.describe(), "serial pty 19200 8N2");

    t.write_all(&SPECIAL).await.unwrap();
    let mut got = [0u8; SPECIAL.len()];
    timeout(LONG, master.read_exact(&mut got))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(got, SPECIAL);

    master.write_all(&SPECIAL).await.unwrap();
    let mut got = [0u8; SPECIAL.len()];
    timeout(LONG, t.read_exact(&mut got))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(
        got, SPECIAL,
        "0xFF must come through the error-mark decoding unchanged"
    );
    assert_eq!(t.take_line_error(), None);
}

#[tokio::test]
async fn every_byte_value_arrives_once() {
    let (mut t, mut master) = pair(LineSettings::with_baud(38_400));
    let all: Vec<u8> = (0..=255u8).chain((0..=255u8).rev()).collect();
    let writer = tokio::spawn(async move {
        master.write_all(&all).await.unwrap();
        (master, all)
    });
    let mut got = vec![0u8; 512];
    timeout(LONG, t.read_exact(&mut got))
        .await
        .unwrap()
        .unwrap();
    let (_master, all) = writer.await.unwrap();
    assert_eq!(got, all);
}

#[tokio::test]
async fn modem_lines_read_as_on_where_the_port_cannot_tell() {
    let (mut t, _master) = pair(LineSettings::with_baud(9600));
    // Every modem ioctl fails with ENOTTY on a pty: no error, lines on.
    t.set_modem(ModemOut { er: true, rs: true }).unwrap();
    t.set_modem(ModemOut {
        er: false,
        rs: false,
    })
    .unwrap();
    assert_eq!(t.modem().unwrap(), ModemIn::ALL_ON);
    assert_eq!(t.modem().unwrap(), ModemIn::ALL_ON);
}

#[tokio::test]
async fn framing_settings_are_accepted() {
    // The pty keeps 8N but must accept the settings FANUC and Fuji use, and odd rates.
    for line in [
        LineSettings {
            parity: Parity::Even,
            stop_bits: StopBits::One,
            ..LineSettings::with_baud(86_400)
        },
        LineSettings {
            stop_bits: StopBits::OnePointFive,
            ..LineSettings::with_baud(76_800)
        },
        LineSettings::with_baud(50),
    ] {
        let (mut t, mut master) = pair(line);
        t.write_all(b"%\n").await.unwrap();
        let mut got = [0u8; 2];
        timeout(LONG, master.read_exact(&mut got))
            .await
            .unwrap()
            .unwrap();
        assert_eq!(&got, b"%\n", "{line}");
    }
}

#[tokio::test]
async fn writes_are_paced_through_the_window() {
    let line = LineSettings::with_baud(9600);
    let (t, mut master) = pair(line);
    let mut t = t.with_window(16);
    let reader = tokio::spawn(async move {
        let mut v = vec![0u8; 16 + 88];
        master.read_exact(&mut v).await.unwrap();
        v
    });
    let data: Vec<u8> = (0..104u8).collect();
    let t0 = std::time::Instant::now();
    t.write_all(&data).await.unwrap();
    // 88 characters beyond the window must have left at 9600 baud 8N2 first.
    let min = line.time_for_chars(88);
    assert!(t0.elapsed() >= min, "{:?} < {min:?}", t0.elapsed());
    assert_eq!(timeout(LONG, reader).await.unwrap().unwrap(), data);
}

/// A pseudo-terminal whose slave end is reached through `link` (a stable path, as udev gives a
/// USB adapter): the master end stands for the device.
fn device_at(link: &std::path::Path) -> SerialStream {
    use tokio_serial::SerialPort;
    let (master, slave) = SerialStream::pair().expect("a pseudo-terminal pair");
    let pts = slave.name().expect("the slave's path");
    drop(slave);
    let _ = std::fs::remove_file(link);
    std::os::unix::fs::symlink(pts, link).unwrap();
    master
}

/// Reads from the transport until `want` bytes came, reading in short slices so that the test
/// fails on time.
async fn read_exactly(t: &mut ReopeningSerial, want: usize) -> Vec<u8> {
    let mut v = vec![0u8; want];
    timeout(LONG, t.read_exact(&mut v)).await.unwrap().unwrap();
    v
}

/// The adapter is pulled (the device end closes: reads fail), the line reads as cut, and when
/// a port appears at the same path again the transport opens it and bytes flow; a port missing
/// at start is picked up the same way.
#[tokio::test]
async fn a_port_that_goes_away_is_opened_again() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyCNC");
    let ms = Duration::from_millis;

    // Missing at start: not an error.
    let mut t = ReopeningSerial::open(
        link.to_str().unwrap(),
        LineSettings::with_baud(19_200),
        ms(20),
        ms(100),
    )
    .unwrap();
    assert!(!t.is_up());
    let cut = ModemIn {
        dr: false,
        cs: false,
        cd: false,
    };
    assert_eq!(t.modem().unwrap(), cut);
    assert_eq!(t.stats().failures, 1);

    let mut device = device_at(&link);
    device.write_all(b"one").await.unwrap();
    assert_eq!(read_exactly(&mut t, 3).await, b"one");
    assert!(t.is_up());
    assert_eq!(t.modem().unwrap(), ModemIn::ALL_ON);

    // Pulled: the device closes and its node goes (as udev removes /dev/ttyUSB0).
    drop(device);
    std::fs::remove_file(&link).unwrap();
    let mut b = [0u8; 1];
    assert!(
        timeout(ms(300), t.read(&mut b)).await.is_err(),
        "a lost port is not end of input"
    );
    assert!(!t.is_up());
    assert_eq!(t.modem().unwrap(), cut);
    assert_eq!(t.stats().losses, 1);
    assert!(
        timeout(ms(200), t.write_all(b"lost")).await.is_err(),
        "writes wait while the port is away"
    );

    // Plugged in again (a new pseudo-terminal behind the same path).
    let mut device = device_at(&link);
    device.write_all(b"two").await.unwrap();
    assert_eq!(read_exactly(&mut t, 3).await, b"two");
    t.write_all(b"three").await.unwrap();
    let mut got = [0u8; 5];
    timeout(LONG, device.read_exact(&mut got))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(&got, b"three");
    assert_eq!(t.stats().ups, 2);
}
