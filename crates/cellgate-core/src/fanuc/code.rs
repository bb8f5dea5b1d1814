//! Character codes on a remote-buffer line (§4.2, §6.2; protocol notes 3).
//!
//! ISO here means the 7-bit code with even parity carried in bit 7: DC3 13h travels as 93h,
//! CR 0Dh as 8Dh, `%` 25h as A5h. ASCII means the same 7-bit code with bit 7 clear.

use super::CodeSystem;

/// SOH (01h).
pub const SOH: u8 = 0x01;
/// ETX (03h): the Protocol A message end code when parameter 5000#3 is 1 (§4.1, §10.2).
pub const ETX: u8 = 0x03;
/// LF (0Ah).
pub const LF: u8 = 0x0A;
/// CR (0Dh): the Protocol A message end code when parameter 5000#3 is 0 (§4.1, §10.2).
pub const CR: u8 = 0x0D;
/// DC1 (11h): starts host transmission (§6.2).
pub const DC1: u8 = 0x11;
/// DC2 (12h): starts punch-out (§6.2).
pub const DC2: u8 = 0x12;
/// DC3 (13h, 93h in ISO): stops host transmission (§6.2).
pub const DC3: u8 = 0x13;
/// DC4 (14h): stops punch-out (§6.2).
pub const DC4: u8 = 0x14;
/// NAK (15h, 95h in ISO): posts an NC alarm (§6.2).
pub const NAK: u8 = 0x15;
/// SYN (16h, 96h in ISO): posts NC reset (§6.2).
pub const SYN: u8 = 0x16;
/// CAN (18h): the stop request monitor packet's code (§5.3).
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
mod tests;
