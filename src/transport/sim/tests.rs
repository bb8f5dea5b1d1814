use super::*;
use crate::transport::{DataBits, StopBits};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

#[tokio::test(start_paused = true)]
async fn one_byte_takes_one_char_time() {
    let s = LineSettings::with_baud(9600);
    let (mut host, mut dev, _l) = line(s);
    let t0 = Instant::now();
    host.write_all(b"A").await.unwrap();
    let mut b = [0u8; 4];
    let n = dev.read(&mut b).await.unwrap();
    assert_eq!(&b[..n], b"A");
    let el = Instant::now() - t0;
    // The timer wheel has millisecond resolution: arrival is at most 1 ms late.
    assert!(el >= s.char_time(), "{el:?}");
    assert!(el < s.char_time() + Duration::from_millis(2), "{el:?}");
}

#[tokio::test(start_paused = true)]
async fn writer_is_held_to_the_fifo() {
    let s = LineSettings::with_baud(9600);
    let (mut host, _dev, l) = line_with(s, SimOptions { fifo: 4 });
    let n = host.write(&[0u8; 100]).await.unwrap();
    assert_eq!(n, 5, "FIFO of 4 plus the shift register");
    let t0 = Instant::now();
    let n = host.write(&[0u8; 100]).await.unwrap();
    assert!(n >= 1);
    assert!(Instant::now() - t0 >= s.char_time());
    assert_eq!(l.counters(Dir::HostToDevice).written, 5 + n as u64);
}

#[tokio::test(start_paused = true)]
async fn seven_bit_framing_masks_bit_7() {
    let s = LineSettings {
        data_bits: DataBits::Seven,
        parity: Parity::Even,
        stop_bits: StopBits::Two,
        ..LineSettings::with_baud(4800)
    };
    let (mut host, mut dev, _l) = line(s);
    host.write_all(&[0xC1, 0x7F, 0x80]).await.unwrap();
    let mut b = [0u8; 3];
    dev.read_exact(&mut b).await.unwrap();
    assert_eq!(b, [0x41, 0x7F, 0x00]);
}

#[tokio::test(start_paused = true)]
async fn shutdown_gives_eof_after_the_bytes() {
    let (mut host, mut dev, _l) = line(LineSettings::with_baud(19_200));
    host.write_all(b"xyz").await.unwrap();
    host.shutdown().await.unwrap();
    assert!(host.write(b"a").await.is_err());
    let mut v = Vec::new();
    dev.read_to_end(&mut v).await.unwrap();
    assert_eq!(v, b"xyz");
}

#[tokio::test(start_paused = true)]
async fn delay_never_reorders() {
    let s = LineSettings::with_baud(9600);
    let (mut host, mut dev, l) = line(s);
    l.set_delay(Dir::HostToDevice, Duration::from_millis(50));
    host.write_all(b"ab").await.unwrap();
    l.set_delay(Dir::HostToDevice, Duration::ZERO);
    host.write_all(b"cd").await.unwrap();
    let mut b = [0u8; 4];
    dev.read_exact(&mut b).await.unwrap();
    assert_eq!(&b, b"abcd");
}

#[tokio::test(start_paused = true)]
async fn error_next_reports_framing() {
    let (mut host, mut dev, l) = line(LineSettings::with_baud(9600));
    l.error_next(Dir::HostToDevice, LineError::Framing);
    host.write_all(b"XY").await.unwrap();
    let mut b = [0u8; 1];
    dev.read_exact(&mut b).await.unwrap();
    assert_eq!(&b, b"Y");
    assert_eq!(dev.take_line_error(), Some(LineError::Framing));
    assert_eq!(dev.take_line_error(), None);
    assert_eq!(l.counters(Dir::HostToDevice).line_errors, 1);
}

#[tokio::test(start_paused = true)]
async fn errored_last_byte_is_seen_without_a_read() {
    let s = LineSettings {
        parity: Parity::Even,
        stop_bits: StopBits::One,
        ..LineSettings::with_baud(9600)
    };
    let (mut host, mut dev, l) = line(s);
    l.corrupt_next(Dir::HostToDevice, 0x01);
    host.write_all(b"Z").await.unwrap();
    assert_eq!(dev.take_line_error(), None, "not arrived yet");
    tokio::time::sleep(s.char_time()).await;
    assert_eq!(dev.take_line_error(), Some(LineError::Parity));
}

#[tokio::test(start_paused = true)]
async fn describe_names_the_framing() {
    let (host, _dev, _l) = line(LineSettings::with_baud(86_400));
    assert_eq!(host.describe(), "sim 86400 8N2");
}

/// Resolves with the input lines of `port` once they differ from `from`, looking at them only
/// when the port's pending read is woken (as the link pump does for such transports).
async fn lines_change(port: &mut SimPort, from: ModemIn) -> ModemIn {
    std::future::poll_fn(|cx| {
        let mut b = [0u8; 1];
        let mut buf = ReadBuf::new(&mut b);
        assert!(Pin::new(&mut *port).poll_read(cx, &mut buf).is_pending());
        match port.modem() {
            Ok(now) if now != from => Poll::Ready(now),
            _ => Poll::Pending,
        }
    })
    .await
}

#[tokio::test(start_paused = true)]
async fn a_change_of_the_input_lines_wakes_the_reader() {
    let (mut host, mut dev, l) = line(LineSettings::with_baud(19_200));
    assert!(host.modem_wakes_reader());
    let on = host.modem().unwrap();
    let within = Duration::from_secs(3600);

    let watch = tokio::spawn(async move {
        let off = lines_change(&mut host, on).await;
        (host, off)
    });
    tokio::task::yield_now().await;
    dev.set_modem(ModemOut {
        er: false,
        rs: true,
    })
    .unwrap();
    let (mut host, off) = tokio::time::timeout(within, watch).await.unwrap().unwrap();
    assert!(!off.dr && !off.cd && off.cs, "{off:?}");

    dev.set_modem(ModemOut::ALL_ON).unwrap();
    let watch = tokio::spawn(async move {
        let cut = lines_change(&mut host, on).await;
        (host, cut)
    });
    tokio::task::yield_now().await;
    l.cut();
    let (host, cut) = tokio::time::timeout(within, watch).await.unwrap().unwrap();
    assert!(!cut.dr && !cut.cs && !cut.cd, "{cut:?}");
    drop(host);
}

#[tokio::test(start_paused = true)]
async fn lines_change_after_the_characters_written_before() {
    let s = LineSettings::with_baud(19_200);
    let (mut host, mut dev, l) = line(s);
    let on = host.modem().unwrap();
    // A board's DC3, then ER off (§6.4 (1)): the host reads the DC3 before DR goes off.
    dev.write_all(&[0x13]).await.unwrap();
    dev.set_modem(ModemOut {
        er: false,
        rs: true,
    })
    .unwrap();
    assert_eq!(
        host.modem().unwrap(),
        on,
        "DR went off before the DC3 arrived"
    );
    assert!(
        l.modem_out(End::Device).er,
        "ER changed before the DC3 left"
    );
    let t0 = Instant::now();
    let mut b = [0u8; 1];
    host.read_exact(&mut b).await.unwrap();
    assert_eq!(b, [0x13]);
    assert!(Instant::now() - t0 >= s.char_time());
    let off = lines_change(&mut host, on).await;
    assert!(!off.dr && !off.cd, "{off:?}");
    assert!(!l.modem_out(End::Device).er);
}
