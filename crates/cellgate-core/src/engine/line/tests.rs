use super::*;

#[test]
fn data_and_stop_bits_read_as_numbers_or_text() {
    #[derive(Deserialize)]
    struct W {
        line: LineSettings,
    }
    let w: W = toml::from_str("line = { data_bits = 7, stop_bits = 1.5 }").unwrap();
    assert_eq!(w.line.data_bits, DataBits::Seven);
    assert_eq!(w.line.stop_bits, StopBits::OnePointFive);
    let w: W = toml::from_str("line = { data_bits = \"8\", stop_bits = \"2\" }").unwrap();
    assert_eq!(
        (w.line.data_bits, w.line.stop_bits),
        (DataBits::Eight, StopBits::Two)
    );
    let e = toml::from_str::<W>("line = { data_bits = 9 }")
        .err()
        .unwrap();
    assert!(e.to_string().contains("data bits 9: must be 7 or 8"), "{e}");
}

#[test]
fn framing_bit_counts() {
    let mut s = LineSettings::with_baud(9600);
    assert_eq!(s.bits_per_char(), 11.0); // 8N2
    s.stop_bits = StopBits::One;
    assert_eq!(s.bits_per_char(), 10.0); // 8N1
    s.parity = Parity::Even;
    assert_eq!(s.bits_per_char(), 11.0); // 8E1
    s.data_bits = DataBits::Seven;
    s.stop_bits = StopBits::OnePointFive;
    assert_eq!(s.bits_per_char(), 10.5); // 7E1.5
}

#[test]
fn time_for_chars_does_not_drift() {
    let s = LineSettings::with_baud(86_400);
    // 86400 baud at 11 bits: 7854.54.. chars/s; one million chars take 127.3148.. s.
    let t = s.time_for_chars(1_000_000);
    assert_eq!(t.as_nanos(), 127_314_814_815);
    assert_eq!(s.char_time().as_nanos(), 127_315);
    // Past the u64 fast path the result is the same formula.
    let huge = 10_000_000_000_u64;
    let expect = (u128::from(huge) * 22 * 1_000_000_000).div_ceil(2 * 86_400);
    assert_eq!(s.time_for_chars(huge).as_nanos(), expect);
}
