use super::*;
use crate::fanuc::packet::{DUMMY_PACKET, data_len, encode_data_packet};

fn pkt(no: u8, fill: u8) -> Vec<u8> {
    let mut v = Vec::new();
    encode_data_packet(no, &vec![fill; data_len(1)], &mut v);
    v
}

fn spoiled(no: u8) -> Vec<u8> {
    let mut v = pkt(no, b'x');
    v[5] ^= 0x01;
    v
}

fn is_data(v: &Verdict) -> bool {
    matches!(v, Verdict::Data(_))
}

#[test]
fn in_order_dummy_and_end() {
    let mut g = GtdRx::new(1);
    assert!(is_data(&g.judge(&pkt(0x30, b'a'))));
    assert!(matches!(g.judge(&pkt(DUMMY_PACKET, 0)), Verdict::Ignore(_)));
    for no in 0x31..=0x39 {
        assert!(is_data(&g.judge(&pkt(no, b'b'))));
    }
    assert!(is_data(&g.judge(&pkt(0x30, b'c'))), "39h wraps to 30h");
    assert_eq!(
        g.judge(&pkt(0xFF, b'e')),
        Verdict::End(Some(vec![b'e'; 256]))
    );
}

#[test]
fn corrupted_packet_is_nakked_and_in_flight_ones_ignored() {
    let mut g = GtdRx::new(1);
    assert!(is_data(&g.judge(&pkt(0x30, b'a'))));
    assert!(matches!(
        g.judge(&spoiled(0x31)),
        Verdict::Nak { from: 0x31, .. }
    ));
    // Already on the line when the host saw the NAK.
    assert!(matches!(g.judge(&pkt(0x32, b'c')), Verdict::Ignore(_)));
    assert!(matches!(g.judge(&pkt(0xFF, b'd')), Verdict::Ignore(_)));
    // The retransmission.
    assert!(is_data(&g.judge(&pkt(0x31, b'b'))));
    assert!(is_data(&g.judge(&pkt(0x32, b'c'))));
    assert!(matches!(g.judge(&pkt(0xFF, b'd')), Verdict::End(Some(_))));
    assert_eq!(g.naks, 0);
}

#[test]
fn corrupted_end_packet_asks_previous_plus_one() {
    let mut g = GtdRx::new(1);
    assert!(is_data(&g.judge(&pkt(0x30, b'a'))));
    assert!(matches!(
        g.judge(&spoiled(0xFF)),
        Verdict::Nak { from: 0x31, .. }
    ));
    assert!(matches!(g.judge(&pkt(0xFF, b'z')), Verdict::End(Some(_))));
}

#[test]
fn lone_packet_spoiled_asks_packet_zero() {
    let mut g = GtdRx::new(1);
    assert!(matches!(
        g.judge(&spoiled(0xFF)),
        Verdict::Nak { from: 0x30, .. }
    ));
    assert!(matches!(g.judge(&pkt(0xFF, b'z')), Verdict::End(Some(_))));
}

#[test]
fn first_packet_must_be_30h_and_order_is_checked() {
    let mut g = GtdRx::new(1);
    assert!(matches!(
        g.judge(&pkt(0x31, b'a')),
        Verdict::Nak { from: 0x30, .. }
    ));
    assert!(is_data(&g.judge(&pkt(0x30, b'a'))));
    assert!(matches!(
        g.judge(&pkt(0x33, b'a')),
        Verdict::Nak { from: 0x31, .. }
    ));
    assert_eq!(g.naks, 1);
}

#[test]
fn after_can_only_the_end_packet_counts() {
    let mut g = GtdRx::new(1);
    assert!(is_data(&g.judge(&pkt(0x30, b'a'))));
    g.cancelled = true;
    assert!(matches!(g.judge(&pkt(0x31, b'a')), Verdict::Ignore(_)));
    assert!(matches!(g.judge(&spoiled(0x32)), Verdict::Ignore(_)));
    assert!(matches!(g.judge(&spoiled(0xFF)), Verdict::Nak { .. }));
    assert_eq!(g.judge(&pkt(0xFF, b'a')), Verdict::End(None));
}
