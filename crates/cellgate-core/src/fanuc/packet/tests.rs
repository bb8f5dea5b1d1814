use super::*;

#[test]
fn data_packet_round_trip() {
    let data = vec![b'X'; data_len(1)];
    let mut out = Vec::new();
    encode_data_packet(0x30, &data, &mut out);
    assert_eq!(out.len(), packet_len(1));
    assert_eq!(out.len(), 260);
    let p = decode_data_packet(&out, 1).unwrap();
    assert_eq!(p.no, 0x30);
    assert_eq!(p.data, &data[..]);
    // 30h + 256·58h = 30h + 5800h → 30h.
    assert_eq!(&out[257..259], b"30");
}

#[test]
fn data_packet_errors() {
    let mut out = Vec::new();
    encode_data_packet(0xFF, &[0u8; 512], &mut out);
    assert!(decode_data_packet(&out, 2).is_ok());
    assert!(matches!(
        decode_data_packet(&out, 1),
        Err(PacketError::Length { .. })
    ));
    out[10] ^= 1;
    assert!(matches!(
        decode_data_packet(&out, 2),
        Err(PacketError::Checksum { no: 0xFF, .. })
    ));
    assert!(matches!(
        decode_data_packet(&[], 1),
        Err(PacketError::Length { len: 0, .. })
    ));
}

#[test]
fn packet_numbers_cycle() {
    assert_eq!(next_packet_no(0x30), 0x31);
    assert_eq!(next_packet_no(0x39), 0x30);
    assert_eq!(packet_kind(0xFF), PacketKind::End);
    assert_eq!(packet_kind(DUMMY_PACKET), PacketKind::Invalid);
}

#[test]
fn monitor_packets() {
    for m in [
        Monitor::Stop,
        Monitor::Retransmit(0x33),
        Monitor::Pause,
        Monitor::Resume,
    ] {
        assert_eq!(Monitor::decode(&m.encode()), Ok(m));
        assert!(Monitor::is_code(m.encode()[0]));
    }
    // CAN 18h + 20h = 38h.
    assert_eq!(Monitor::Stop.encode(), [0x18, 0x20, b'3', b'8', 0x0D]);
    // NAK accepted with parity too (protocol notes 10): 95h + 31h = C6h.
    assert_eq!(
        Monitor::decode(&[0x95, 0x31, b'C', b'6', 0x0D]),
        Ok(Monitor::Retransmit(0x31))
    );
    assert!(Monitor::decode(&[0x18, 0x20, b'0', b'0', 0x0D]).is_err());
    assert!(Monitor::decode(&[0x41, 0x20, b'6', b'1', 0x0D]).is_err());
}
