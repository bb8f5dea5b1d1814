//! Character codes on a remote-buffer line (§4.2, §6.2; protocol notes 3).
//!
//! ISO here means the 7-bit code with even parity carried in bit 7: DC3 13h travels as 93h,
//! CR 0Dh as 8Dh, `%` 25h as A5h. ASCII means the same 7-bit code with bit 7 clear.

use super::CodeSystem;

pub const SOH: u8 = 0x01;
pub const ETX: u8 = 0x03;
pub const LF: u8 = 0x0A;
pub const CR: u8 = 0x0D;
pub const DC1: u8 = 0x11;
pub const DC2: u8 = 0x12;
pub const DC3: u8 = 0x13;
pub const DC4: u8 = 0x14;
pub const NAK: u8 = 0x15;
pub const SYN: u8 = 0x16;
pub const CAN: u8 = 0x18;
/// End of record: an NC program ends at `%` (§4.4.2 3, §8.2; protocol notes 8).
pub const EOR: u8 = b'%';

/// Whether `b` is a significant character of a tape (protocol notes 8): anything but feed
/// (NUL), delete, blank, tab and line ends, with or without the ISO parity bit. The first `%`
/// before any significant character is the tape-start mark; the next one is EOR.
pub const fn is_significant(b: u8) -> bool {
    !matches!(b & 0x7F, 0x00 | 0x7F | b' ' | b'\t' | LF | CR)
}

/// Whether `b` is EOR `%`, with or without the ISO parity bit (A5h).
pub const fn is_eor(b: u8) -> bool {
    b & 0x7F == EOR
}

/// `b` (7-bit) with bit 7 set where needed for even parity over all 8 bits.
pub const fn with_even_parity(b: u8) -> u8 {
    let b = b & 0x7F;
    if b.count_ones() % 2 == 1 { b | 0x80 } else { b }
}

/// Whether `b` has even parity over all 8 bits, as every ISO character must.
pub const fn has_even_parity(b: u8) -> bool {
    b.count_ones() % 2 == 0
}

impl CodeSystem {
    /// The byte transmitted for the 7-bit character `b`.
    pub const fn encode(self, b: u8) -> u8 {
        match self {
            CodeSystem::Ascii => b & 0x7F,
            CodeSystem::Iso => with_even_parity(b),
        }
    }

    /// The 7-bit character a received byte carries, or `None` when its parity is wrong for
    /// this code (ISO: odd parity; ASCII: bit 7 set). §4.6 counts that as a parity error.
    pub const fn decode(self, b: u8) -> Option<u8> {
        match self {
            CodeSystem::Ascii if b & 0x80 == 0 => Some(b),
            CodeSystem::Iso if has_even_parity(b) => Some(b & 0x7F),
            _ => None,
        }
    }

    /// The 7-bit character of `b` whatever its bit 7: for control codes that boards send
    /// with or without parity (protocol notes 10).
    pub const fn strip(b: u8) -> u8 {
        b & 0x7F
    }

    /// Protocol B / Expansion B control code as transmitted (§6.2 table): DC3, NAK and SYN
    /// carry the parity bit in ISO; DC1, DC2 and DC4 already have even parity.
    pub const fn control(self, code: u8) -> u8 {
        self.encode(code)
    }
}

#[cfg(test)]
mod tests {
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
}
