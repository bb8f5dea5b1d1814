//! Punch codes of an NC tape: ISO, ASCII and EIA (parameter 0000#2 ISP, #4 EIA, §10), the
//! conversions between them, and recognising the code of punched bytes.
//!
//! - ISO: 7-bit code with even parity in bit 7 (channel 8), as [`CodeSystem::Iso`] sends it
//!   (protocol notes 3). A CNC with 0000#2 ISP = 1 punches ISO without the parity bit, which
//!   is byte for byte ASCII and is recognised as such.
//! - ASCII: the same 7-bit code, bit 7 clear.
//! - EIA: the RS-244 code FANUC punches with 0000#4 EIA = 1: odd parity on channel 5 (bit 4),
//!   end of block CR on channel 8 alone (80h), end of record ER 0Bh. Letters have no case.
//!
//! "Text" here is plain 7-bit ISO/ASCII without parity: what the library keeps and what
//! [`decode`] returns. EOB is LF and EOR is `%` in text.

use std::fmt;

use serde::{Deserialize, Serialize};

use crate::fanuc::CodeSystem;
use crate::fanuc::code::{EOR, LF, has_even_parity};

/// The code a tape is punched in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TapeCode {
    /// ISO with the parity bit (0000#4 EIA = 0, 0000#2 ISP = 0).
    Iso,
    /// 7-bit code without parity: ASCII, or ISO punched with 0000#2 ISP = 1.
    Ascii,
    /// EIA RS-244 (0000#4 EIA = 1).
    Eia,
}

impl fmt::Display for TapeCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            TapeCode::Iso => "ISO",
            TapeCode::Ascii => "ASCII",
            TapeCode::Eia => "EIA",
        })
    }
}

/// Why bytes could not be converted from or to a tape code.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum TapeError {
    /// A byte that is no EIA code.
    #[error(
        "byte {byte:#04x} at offset {offset} is not an EIA code (parameter 0000#4 EIA, RS-244)"
    )]
    NotEia {
        /// The byte's offset in the bytes converted.
        offset: usize,
        /// The byte.
        byte: u8,
    },
    /// A text character that has no EIA code.
    #[error("character {} at offset {offset} has no EIA code", show(*byte))]
    NoEiaCode {
        /// The character's offset in the text.
        offset: usize,
        /// The character.
        byte: u8,
    },
    /// A byte with the wrong parity for its code.
    #[error(
        "byte {byte:#04x} at offset {offset} has the wrong parity for {code} code ({})",
        parity_rule(*code)
    )]
    Parity {
        /// The code.
        code: TapeCode,
        /// The byte's offset in the bytes converted.
        offset: usize,
        /// The byte.
        byte: u8,
    },
    /// A byte with bit 7 set where 7-bit text is due.
    #[error("byte {byte:#04x} at offset {offset} is not 7-bit text")]
    EightBit {
        /// The byte's offset in the bytes converted.
        offset: usize,
        /// The byte.
        byte: u8,
    },
}

fn show(byte: u8) -> String {
    if byte.is_ascii_graphic() {
        format!("'{}' ({byte:#04x})", char::from(byte))
    } else {
        format!("{byte:#04x}")
    }
}

fn parity_rule(code: TapeCode) -> &'static str {
    match code {
        TapeCode::Iso => "even parity over 8 bits, parameter 0000#2 ISP = 0",
        TapeCode::Eia => "odd parity over 8 bits, parameter 0000#4 EIA = 1",
        TapeCode::Ascii => "bit 7 clear",
    }
}

/// EIA end of block: CR, channel 8 alone. Text: LF.
pub const EIA_EOB: u8 = 0x80;
/// EIA end of record ER. Text: `%`.
pub const EIA_ER: u8 = 0x0B;
/// EIA blank tape (feed holes only). No holes, so it is the one code without odd parity.
pub const EIA_BLANK: u8 = 0x00;
/// EIA delete (every channel punched), ignored by readers.
pub const EIA_DELETE: u8 = 0x7F;
/// EIA upper case shift.
pub const EIA_UPPER_CASE: u8 = 0x7C;
/// EIA lower case shift.
pub const EIA_LOWER_CASE: u8 = 0x7A;

/// EIA codes that stand for no character: dropped when converting to text.
pub const EIA_IGNORED: [u8; 4] = [EIA_BLANK, EIA_DELETE, EIA_UPPER_CASE, EIA_LOWER_CASE];

/// Every EIA character code with its 7-bit ISO character (upper-case letters, LF for EOB,
/// `%` for ER). `(` is control out and `)` control in.
pub const EIA_CHARACTERS: [(u8, u8); 49] = [
    (0x20, b'0'),
    (0x01, b'1'),
    (0x02, b'2'),
    (0x13, b'3'),
    (0x04, b'4'),
    (0x15, b'5'),
    (0x16, b'6'),
    (0x07, b'7'),
    (0x08, b'8'),
    (0x19, b'9'),
    (0x61, b'A'),
    (0x62, b'B'),
    (0x73, b'C'),
    (0x64, b'D'),
    (0x75, b'E'),
    (0x76, b'F'),
    (0x67, b'G'),
    (0x68, b'H'),
    (0x79, b'I'),
    (0x51, b'J'),
    (0x52, b'K'),
    (0x43, b'L'),
    (0x54, b'M'),
    (0x45, b'N'),
    (0x46, b'O'),
    (0x57, b'P'),
    (0x58, b'Q'),
    (0x49, b'R'),
    (0x32, b'S'),
    (0x23, b'T'),
    (0x34, b'U'),
    (0x25, b'V'),
    (0x26, b'W'),
    (0x37, b'X'),
    (0x38, b'Y'),
    (0x29, b'Z'),
    (0x10, b' '),
    (0x70, b'+'),
    (0x40, b'-'),
    (0x31, b'/'),
    (0x3B, b','),
    (0x6B, b'.'),
    (0x1A, b'('),
    (0x4A, b')'),
    (0x0E, b'&'),
    (0x3E, b'\t'),
    (0x2A, 0x08),
    (EIA_EOB, LF),
    (EIA_ER, EOR),
];

/// 7-bit text character → EIA code (0xFF: none). NUL (feed) and DEL are codes of both
/// tapes: EIA blank and delete.
const TEXT_TO_EIA: [u8; 128] = {
    let mut t = [0xFF_u8; 128];
    let mut i = 0;
    while i < EIA_CHARACTERS.len() {
        let (eia, text) = EIA_CHARACTERS[i];
        t[text as usize] = eia;
        i += 1;
    }
    t[0x00] = EIA_BLANK;
    t[0x7F] = EIA_DELETE;
    t
};

/// EIA code → 7-bit text character (0xFF: not an EIA code; 0xFE: a code dropped in text).
const EIA_TO_TEXT: [u8; 256] = {
    let mut t = [0xFF_u8; 256];
    let mut i = 0;
    while i < EIA_CHARACTERS.len() {
        let (eia, text) = EIA_CHARACTERS[i];
        t[eia as usize] = text;
        i += 1;
    }
    let mut j = 0;
    while j < EIA_IGNORED.len() {
        t[EIA_IGNORED[j] as usize] = 0xFE;
        j += 1;
    }
    t
};

/// The EIA code of the 7-bit text character `c` (letters of either case), if it has one.
pub fn eia_code(c: u8) -> Option<u8> {
    let c = c.to_ascii_uppercase();
    TEXT_TO_EIA
        .get(usize::from(c))
        .copied()
        .filter(|&e| e != 0xFF)
}

/// The text character of the EIA code `b`: `Ok(Some(c))`, `Ok(None)` for a code that stands
/// for no character ([`EIA_IGNORED`]), `Err(())` when `b` is not an EIA code.
fn eia_text(b: u8) -> Result<Option<u8>, ()> {
    match EIA_TO_TEXT[usize::from(b)] {
        0xFF => Err(()),
        0xFE => Ok(None),
        c => Ok(Some(c)),
    }
}

/// Whether `b` has odd parity over all 8 bits, as every EIA code but blank must.
pub const fn has_odd_parity(b: u8) -> bool {
    !has_even_parity(b)
}

/// EIA tape → text. EOB (CR 80h) becomes LF and ER becomes `%`; blank (00h), delete (7Fh)
/// and the case shifts UC (7Ch) and LC (7Ah) stand for no character and are dropped.
/// A byte with even parity is a parity error, any other byte outside the table not EIA.
pub fn eia_to_iso(eia: &[u8]) -> Result<Vec<u8>, TapeError> {
    let mut text = Vec::with_capacity(eia.len());
    for (offset, &byte) in eia.iter().enumerate() {
        match eia_text(byte) {
            Ok(Some(c)) => text.push(c),
            Ok(None) => {}
            Err(()) if has_even_parity(byte) => {
                return Err(TapeError::Parity {
                    code: TapeCode::Eia,
                    offset,
                    byte,
                });
            }
            Err(()) => return Err(TapeError::NotEia { offset, byte }),
        }
    }
    Ok(text)
}

/// ISO or ASCII text → EIA tape. Bit 7 (the ISO parity bit) is ignored; lower-case letters
/// are punched as letters (EIA has no case); LF becomes EOB (80h) and `%` ER (0Bh). CR is
/// dropped: in ISO it only pads the EOB (LF CR CR, parameter 0000#3 NCR), and the EIA EOB is
/// itself the CR code. NUL (feed) and DEL map to EIA blank and delete. Any other character
/// without an EIA code (`#`, `[`, `=`, `:`, `*`, `;`...) is an error naming it.
pub fn iso_to_eia(iso: &[u8]) -> Result<Vec<u8>, TapeError> {
    let mut eia = Vec::with_capacity(iso.len());
    for (offset, &byte) in iso.iter().enumerate() {
        let c = CodeSystem::strip(byte);
        if c == crate::fanuc::code::CR {
            continue;
        }
        match eia_code(c) {
            Some(e) => eia.push(e),
            None => return Err(TapeError::NoEiaCode { offset, byte: c }),
        }
    }
    Ok(eia)
}

/// Text punched as a tape in `code`: ISO adds the even parity bit (as the link does,
/// [`CodeSystem::Iso`]), ASCII is the text itself, EIA is [`iso_to_eia`]. Text is 7-bit:
/// a byte with bit 7 set is refused in every code.
pub fn encode(text: &[u8], code: TapeCode) -> Result<Vec<u8>, TapeError> {
    if let Some(offset) = text.iter().position(|&b| b & 0x80 != 0) {
        return Err(TapeError::EightBit {
            offset,
            byte: text[offset],
        });
    }
    match code {
        TapeCode::Iso => Ok(text.iter().map(|&b| CodeSystem::Iso.encode(b)).collect()),
        TapeCode::Ascii => Ok(text.to_vec()),
        TapeCode::Eia => iso_to_eia(text),
    }
}

/// The code of punched bytes, from the bytes alone.
///
/// - EIA: every byte but blank (00h) has odd parity, and ER (0Bh) or EOB (80h) occurs. Odd
///   parity alone is not enough: a short ASCII text can be all odd (`O1`, `%`), but never
///   holds 80h (not 7-bit) or 0Bh (VT, no NC character). Neither byte is valid ISO (both
///   have odd parity). A punched EIA program always holds them: it starts with ER and its
///   blocks end with EOB. A fragment without them is not recognised as EIA.
/// - ISO: every byte has even parity and at least one has bit 7 set. A text none of whose
///   characters needs the parity bit reads as ASCII, and gives the same text either way.
/// - ASCII otherwise (including empty input and ISO punched without parity, 0000#2 ISP = 1).
pub fn detect(bytes: &[u8]) -> TapeCode {
    let mut all_odd = true;
    let mut all_even = true;
    let mut high = false;
    let mut eia_mark = false;
    for &b in bytes {
        let even = has_even_parity(b);
        all_even &= even;
        all_odd &= !even || b == EIA_BLANK;
        high |= b & 0x80 != 0;
        eia_mark |= b == EIA_ER || b == EIA_EOB;
    }
    if all_odd && eia_mark {
        TapeCode::Eia
    } else if all_even && high {
        TapeCode::Iso
    } else {
        TapeCode::Ascii
    }
}

/// Punched bytes → their code and their text (see [`detect`] and [`decode_as`]).
///
/// Bytes that are not 7-bit yet fit neither ISO nor EIA are reported as a parity error of
/// the code most of them fit: EIA when most non-blank bytes have odd parity, else ISO.
pub fn decode(bytes: &[u8]) -> Result<(TapeCode, Vec<u8>), TapeError> {
    let code = detect(bytes);
    if code == TapeCode::Ascii && bytes.iter().any(|&b| b & 0x80 != 0) {
        return Err(misfit(bytes));
    }
    Ok((code, decode_as(bytes, code)?))
}

/// Bytes punched in `code` → text. NUL (feed) and DEL are dropped in every code, as readers
/// skip them; nothing else is changed (ISO CRs stay). ISO bytes must have even parity, ASCII
/// bytes bit 7 clear; EIA is [`eia_to_iso`].
pub fn decode_as(bytes: &[u8], code: TapeCode) -> Result<Vec<u8>, TapeError> {
    if code == TapeCode::Eia {
        return eia_to_iso(bytes);
    }
    let mut text = Vec::with_capacity(bytes.len());
    for (offset, &byte) in bytes.iter().enumerate() {
        let c = match code {
            TapeCode::Eia => return eia_to_iso(bytes),
            TapeCode::Iso if has_even_parity(byte) => CodeSystem::strip(byte),
            TapeCode::Ascii if byte & 0x80 == 0 => byte,
            TapeCode::Iso => return Err(TapeError::Parity { code, offset, byte }),
            TapeCode::Ascii => return Err(TapeError::EightBit { offset, byte }),
        };
        if c != 0x00 && c != 0x7F {
            text.push(c);
        }
    }
    Ok(text)
}

/// The parity error that keeps 8-bit `bytes` from being ISO or EIA.
fn misfit(bytes: &[u8]) -> TapeError {
    let odd = bytes.iter().filter(|&&b| has_odd_parity(b)).count();
    let even = bytes
        .iter()
        .filter(|&&b| b != EIA_BLANK && has_even_parity(b))
        .count();
    let (code, bad): (TapeCode, fn(u8) -> bool) = if odd > even {
        (TapeCode::Eia, |b| b != EIA_BLANK && has_even_parity(b))
    } else {
        (TapeCode::Iso, has_odd_parity)
    };
    match bytes.iter().position(|&b| bad(b)) {
        Some(offset) => TapeError::Parity {
            code,
            offset,
            byte: bytes[offset],
        },
        // Unreachable for 8-bit input that detect() called ASCII, but say something true.
        None => {
            let offset = bytes.iter().position(|&b| b & 0x80 != 0).unwrap_or(0);
            TapeError::EightBit {
                offset,
                byte: bytes.get(offset).copied().unwrap_or(0),
            }
        }
    }
}

#[cfg(test)]
mod tests;
