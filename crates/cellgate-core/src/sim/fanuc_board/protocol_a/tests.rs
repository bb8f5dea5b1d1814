use super::*;
use crate::fanuc::CodeSystem;
use crate::fanuc::code::with_even_parity;
use crate::fanuc::packet::encode_data_packet;

fn parts(config: BoardConfig) -> (ProtocolA, Cnc, Outbox) {
    let now = Instant::now();
    let cnc = Cnc::new(config.buffer_size, 0, 1 << 20, now);
    (ProtocolA::new(&config, now), cnc, Outbox::default())
}

fn errors(out: &Outbox) -> Vec<String> {
    out.events
        .iter()
        .filter_map(|e| match e {
            BoardEvent::ProtocolError { detail } => Some(detail.clone()),
            _ => None,
        })
        .collect()
}

#[test]
fn sdo_image_is_two_hex_digits() {
    assert_eq!(parse_image(b"A5"), Some(0xA5));
    assert_eq!(parse_image(b"0f and more"), Some(0x0F));
    assert_eq!(parse_image(b"+F"), None);
    assert_eq!(parse_image(b"G1"), None);
    assert_eq!(parse_image(b"1"), None);
}

#[test]
fn set_fields_are_range_checked_one_by_one() {
    let (mut a, _, mut out) = parts(BoardConfig::default());
    let set = StatusData {
        params: Some(Params {
            no: 100,
            nb: 100, // below 1 + No = 101: ignored
            tp: 4,
            tw: 6, // above Tp = 4: ignored
            ti: 3, // not a 2 ms step: ignored
            ..Params::POWER_ON
        }),
        packet_n: Some(2), // Protocol A board: stays 0
        ..StatusData::default()
    };
    a.apply_set(&set.to_bytes(), &mut out).unwrap();
    let p = a.params();
    assert_eq!((p.no, p.nb, p.tp, p.tw, p.ti), (100, 2000, 4, 4, 10));
    assert_eq!(a.packet_n(), 0);
    let errs = errors(&out);
    assert_eq!(errs.len(), 4, "{errs:?}");
    assert!(errs[0].contains("Nb = 100"), "{errs:?}");
    // An empty SET changes nothing; garbage is a format error.
    a.apply_set(b"", &mut out).unwrap();
    assert_eq!(a.params(), p);
    assert!(a.apply_set(b"1Z", &mut out).is_err());
}

#[test]
fn iso_conversion_ignores_the_parity_bit() {
    let (mut a, _, _) = parts(BoardConfig {
        framing: Framing::new(CodeSystem::Iso, crate::fanuc::EndCode::Cr),
        ..BoardConfig::default()
    });
    a.conversion = (b';', b'\n');
    let mut data = vec![with_even_parity(b';'), b';', b'X'];
    a.convert(&mut data);
    assert_eq!(data, vec![b'\n', b'\n', b'X']);
}

#[test]
fn a_message_is_recognised_where_a_packet_would_start() {
    let (mut a, _, _) = parts(BoardConfig {
        protocol: Protocol::ExpansionA,
        ..BoardConfig::default()
    });
    a.link = BoardLinkState::Ready;
    a.awaiting(Exchange::Gtd(Box::new(GtdRx::new(1))));
    let framing = Framing::default();
    a.rx = framing.encode_to_vec(&Message::new(Command::Wat)).unwrap();
    assert!(matches!(a.next_unit(), Some(Unit::Frame(Ok(m))) if m.command == Command::Wat));
    // A packet whose data holds a CR early on is still a packet.
    let mut data = b"G1\rX".to_vec();
    data.resize(256, b' ');
    encode_data_packet(0x30, &data, &mut a.rx);
    assert!(matches!(a.next_unit(), Some(Unit::Packet(p)) if p.len() == 260));
    // Once packets flow, only packets: even one that reads like a message.
    if let Some(g) = a.gtd() {
        g.started = true;
    }
    let mut data = b"7SYN\r".to_vec();
    data.resize(256, b' ');
    encode_data_packet(0x30, &data, &mut a.rx);
    a.rx.extend_from_slice(b"0");
    assert!(matches!(a.next_unit(), Some(Unit::Packet(p)) if p.len() == 260));
    assert!(a.next_unit().is_none(), "a partial packet waits");
    assert_eq!(a.rx, b"0");
}

#[test]
fn oversize_garbage_is_reported_once_and_dropped() {
    let (mut a, _, _) = parts(BoardConfig::default());
    a.phase = Phase::Idle;
    a.rx = vec![b'x'; MAX_FRAME + 1];
    assert!(matches!(
        a.next_unit(),
        Some(Unit::Frame(Err(FrameError::Oversize { .. })))
    ));
    a.rx = b"junk\r07SYN\r".to_vec();
    assert!(matches!(a.next_unit(), Some(Unit::Frame(Ok(m))) if m.command == Command::Syn));
}
