use super::*;

#[test]
fn iso_table_of_section_6_2() {
    let iso = CodeSystem::Iso;
    assert_eq!(iso.control(DC1), 0x11);
    assert_eq!(iso.control(DC2), 0x12);
    assert_eq!(iso.control(DC3), 0x93);
    assert_eq!(iso.control(DC4), 0x14);
    assert_eq!(iso.control(NAK), 0x95);
    assert_eq!(iso.control(SYN), 0x96);
    assert_eq!(iso.encode(CR), 0x8D);
    assert_eq!(iso.encode(EOR), 0xA5);
    assert_eq!(CodeSystem::Ascii.control(DC3), 0x13);
}

#[test]
fn decode_checks_parity() {
    assert_eq!(CodeSystem::Iso.decode(0x8D), Some(CR));
    assert_eq!(CodeSystem::Iso.decode(0x0D), None);
    assert_eq!(CodeSystem::Ascii.decode(0x0D), Some(CR));
    assert_eq!(CodeSystem::Ascii.decode(0x8D), None);
    for b in 0..=0x7F_u8 {
        assert_eq!(CodeSystem::Iso.decode(CodeSystem::Iso.encode(b)), Some(b));
    }
}
