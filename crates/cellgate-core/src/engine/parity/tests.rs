use super::*;

#[test]
fn even_and_odd_parity_in_bit_7() {
    let even = ParityCodec::new(Parity::Even).unwrap();
    let odd = ParityCodec::new(Parity::Odd).unwrap();
    assert!(ParityCodec::new(Parity::None).is_none());
    // ':' 3Ah has four ones, '1' 31h three, CR 0Dh three, 'A' 41h two.
    let mut out = Vec::new();
    even.encode(b":1\rA", &mut out);
    assert_eq!(out, [0x3A, 0xB1, 0x8D, 0x41]);
    out.clear();
    odd.encode(b":1\rA", &mut out);
    assert_eq!(out, [0xBA, 0x31, 0x0D, 0xC1]);
    // Bit 7 of the character given is not data on a 7-bit line.
    assert_eq!(even.with_parity(0xB1), 0xB1);
    for c in 0..=0x7Fu8 {
        let e = even.with_parity(c);
        let o = odd.with_parity(c);
        assert_eq!(e.count_ones() % 2, 0);
        assert_eq!(o.count_ones() % 2, 1);
        assert_eq!((even.check(e), odd.check(o)), (Ok(c), Ok(c)));
        assert_eq!(even.check(o), Err(LineError::Parity));
        assert_eq!(odd.check(e), Err(LineError::Parity));
    }
}

#[test]
fn a_bad_character_is_not_delivered_and_its_error_comes_in_line_order() {
    let mut d = ParityDecoder::new(ParityCodec::new(Parity::Even).unwrap());
    // ":4" good, '1' without its parity bit (31h), "2" good, CR good.
    d.feed(&[0x3A, 0xB4, 0x31, 0xB2, 0x8D]);
    let mut out = [0u8; 16];
    let n = d.decode(&mut out);
    assert_eq!(&out[..n], b":4", "a read stops before the bad character");
    assert_eq!(d.take_error(), None, "no error before these bytes");
    let n = d.decode(&mut out);
    assert_eq!(&out[..n], b"2\r");
    assert_eq!(
        d.take_error(),
        Some(LineError::Parity),
        "it came before them"
    );
    assert_eq!(d.take_error(), None);
    // A bad character last: its error is there without more bytes.
    d.feed(&[0x31]);
    assert_eq!(d.decode(&mut out), 0);
    assert_eq!(d.take_error(), Some(LineError::Parity));
    assert_eq!(d.buffered(), 0);
}
