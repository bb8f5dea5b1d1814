use super::*;
use crate::transport::sim::{Dir, line};
use crate::transport::{DataBits, LineSettings, Parity, StopBits};
use cellgate_core::engine::line::Parity as P;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// An 8N1 port carrying a 7E1 line: what the gateway writes arrives with even parity in bit
/// 7; what arrives loses its parity bit, and a byte with the wrong one is a parity error, not
/// delivered, reported between the bytes around it.
#[tokio::test(start_paused = true)]
async fn parity_goes_out_in_bit_7_and_a_wrong_one_is_a_parity_error() {
    let port = LineSettings {
        baud: 9600,
        data_bits: DataBits::Eight,
        parity: Parity::None,
        stop_bits: StopBits::One,
        ..LineSettings::default()
    };
    let (host, mut device, _sim) = line(port);
    let codec = ParityCodec::new(P::Even).unwrap();
    let mut host = GatewayParity::new(host, codec);
    host.write_all(b":1\r").await.unwrap();
    let mut got = [0u8; 3];
    device.read_exact(&mut got).await.unwrap();
    assert_eq!(got, [0x3A, 0xB1, 0x8D]);
    // '4' with its parity bit, '1' without (a parity error), then "2" CR.
    device.write_all(&[0xB4, 0x31, 0xB2, 0x8D]).await.unwrap();
    tokio::time::sleep(port.time_for_chars(4)).await;
    let mut buf = [0u8; 8];
    let n = host.read(&mut buf).await.unwrap();
    assert_eq!(&buf[..n], b"4");
    assert_eq!(host.take_line_error(), None);
    let n = host.read(&mut buf).await.unwrap();
    assert_eq!(&buf[..n], b"2\r");
    assert_eq!(host.take_line_error(), Some(LineError::Parity));
    assert_eq!(host.take_line_error(), None);
}

/// The simulated device's fault: the character asked for goes out with its parity bit wrong,
/// and only that one.
#[tokio::test(start_paused = true)]
async fn a_spoilt_character_goes_out_with_the_wrong_parity() {
    let port = LineSettings::with_baud(9600);
    let (host, mut device, sim) = line(port);
    let codec = ParityCodec::new(P::Odd).unwrap();
    let mut host = GatewayParity::new(host, codec);
    host.spoil_sent(1);
    host.write_all(b"AB").await.unwrap();
    host.write_all(b"C").await.unwrap();
    let mut got = [0u8; 3];
    device.read_exact(&mut got).await.unwrap();
    assert_eq!(got, [0xC1, 0xC2 ^ 0x80, 0x43]);
    assert_eq!(sim.counters(Dir::HostToDevice).written, 3);
}
