//! The serial transport on a pseudo-terminal pair: raw bytes both ways (flow-control and
//! control characters included) and modem lines that a pty cannot report reading as on.
//! A pty ignores parity and data bits and has no modem lines; the simulated line covers those.
#![cfg(unix)]

use std::time::Duration;

use cellgate::transport::serial::SerialTransport;
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
