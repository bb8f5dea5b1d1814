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

use super::CodeSystem;
use super::code::{EOR, LF, has_even_parity};

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
    #[error(
        "byte {byte:#04x} at offset {offset} is not an EIA code (parameter 0000#4 EIA, RS-244)"
    )]
    NotEia { offset: usize, byte: u8 },
    #[error("character {} at offset {offset} has no EIA code", show(*byte))]
    NoEiaCode { offset: usize, byte: u8 },
    #[error(
        "byte {byte:#04x} at offset {offset} has the wrong parity for {code} code ({})",
        parity_rule(*code)
    )]
    Parity {
        code: TapeCode,
        offset: usize,
        byte: u8,
    },
    #[error("byte {byte:#04x} at offset {offset} is not 7-bit text")]
    EightBit { offset: usize, byte: u8 },
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
        if c == super::code::CR {
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
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Every character with an EIA code, as text.
    fn eia_text_chars() -> Vec<u8> {
        EIA_CHARACTERS.iter().map(|&(_, c)| c).collect()
    }

    #[test]
    fn every_eia_code_but_blank_has_odd_parity() {
        for &(eia, text) in &EIA_CHARACTERS {
            if eia == EIA_BLANK {
                continue;
            }
            assert!(
                has_odd_parity(eia),
                "{eia:#04x} ({text:#04x}) has even parity"
            );
        }
        for b in [EIA_DELETE, EIA_UPPER_CASE, EIA_LOWER_CASE] {
            assert!(has_odd_parity(b), "{b:#04x}");
        }
        assert!(has_even_parity(EIA_BLANK));
    }

    #[test]
    fn eia_codes_are_distinct() {
        let mut seen = std::collections::HashSet::new();
        for eia in EIA_CHARACTERS.iter().map(|&(e, _)| e).chain(EIA_IGNORED) {
            assert!(seen.insert(eia), "{eia:#04x} twice");
        }
        let mut text = std::collections::HashSet::new();
        for &(_, c) in &EIA_CHARACTERS {
            assert!(c < 0x80 && !c.is_ascii_lowercase());
            assert!(text.insert(c), "{c:#04x} twice");
        }
    }

    #[test]
    fn eia_table_round_trips_both_ways() {
        for c in eia_text_chars() {
            let eia = iso_to_eia(&[c]).unwrap();
            assert_eq!(eia.len(), 1, "{c:#04x}");
            assert_eq!(eia_to_iso(&eia).unwrap(), vec![c], "{c:#04x}");
            // With the ISO parity bit as punched.
            assert_eq!(iso_to_eia(&[CodeSystem::Iso.encode(c)]).unwrap(), eia);
        }
        for &(eia, text) in &EIA_CHARACTERS {
            assert_eq!(eia_to_iso(&[eia]).unwrap(), vec![text]);
            assert_eq!(iso_to_eia(&[text]).unwrap(), vec![eia]);
        }
        for eia in EIA_IGNORED {
            assert_eq!(eia_to_iso(&[eia]).unwrap(), Vec::<u8>::new());
        }
        assert_eq!(iso_to_eia(&[0x00, 0x7F]).unwrap(), [EIA_BLANK, EIA_DELETE]);
    }

    #[test]
    fn eia_codes_of_the_table() {
        assert_eq!(iso_to_eia(b"%").unwrap(), [0x0B]);
        assert_eq!(iso_to_eia(b"\n").unwrap(), [0x80]);
        assert_eq!(
            iso_to_eia(b"0123456789").unwrap(),
            [0x20, 0x01, 0x02, 0x13, 0x04, 0x15, 0x16, 0x07, 0x08, 0x19]
        );
        assert_eq!(
            iso_to_eia(b"gxz.(").unwrap(),
            [0x67, 0x37, 0x29, 0x6B, 0x1A]
        );
        assert_eq!(
            iso_to_eia(b"GXZ.)").unwrap(),
            [0x67, 0x37, 0x29, 0x6B, 0x4A]
        );
        // The ISO EOB of 0000#3 NCR = 0 (LF CR CR) is one EIA EOB.
        assert_eq!(iso_to_eia(b"M30\n\r\r").unwrap(), [0x54, 0x13, 0x20, 0x80]);
        assert_eq!(
            eia_to_iso(&[0x00, 0x0B, 0x80, 0x7C, 0x46, 0x7A, 0x01, 0x7F, 0x80]).unwrap(),
            b"%\nO1\n"
        );
    }

    #[test]
    fn characters_without_eia_code_are_named() {
        for (i, &c) in b"#[]=:*;<>?@!\"$'^_|~{}".iter().enumerate() {
            let text = [b'G', b'1', c];
            assert_eq!(
                iso_to_eia(&text),
                Err(TapeError::NoEiaCode { offset: 2, byte: c }),
                "#{i}"
            );
        }
        let e = iso_to_eia(b"G1#5").unwrap_err();
        assert_eq!(
            e.to_string(),
            "character '#' (0x23) at offset 2 has no EIA code"
        );
        assert_eq!(encode(b"X=1", TapeCode::Eia), iso_to_eia(b"X=1"));
    }

    #[test]
    fn eia_errors() {
        // 0x03 has even parity; 0x0D odd but unassigned.
        assert_eq!(
            eia_to_iso(&[0x0B, 0x03]),
            Err(TapeError::Parity {
                code: TapeCode::Eia,
                offset: 1,
                byte: 0x03
            })
        );
        assert_eq!(
            eia_to_iso(&[0x0B, 0x0D]),
            Err(TapeError::NotEia {
                offset: 1,
                byte: 0x0D
            })
        );
    }

    #[test]
    fn encode_in_each_code() {
        assert_eq!(
            encode(b"%\nO1\n%", TapeCode::Iso).unwrap(),
            [0xA5, 0x0A, 0xCF, 0xB1, 0x0A, 0xA5]
        );
        assert_eq!(encode(b"%\nO1\n%", TapeCode::Ascii).unwrap(), b"%\nO1\n%");
        assert_eq!(
            encode(b"%\nO1\n%", TapeCode::Eia).unwrap(),
            [0x0B, 0x80, 0x46, 0x01, 0x80, 0x0B]
        );
        assert_eq!(
            encode(b"O1\xB1", TapeCode::Ascii),
            Err(TapeError::EightBit {
                offset: 2,
                byte: 0xB1
            })
        );
    }

    const PROGRAM: &[u8] = b"%\nO1234(PART)\nG00X1.Y2.\nM30\n%";
    const PROGRAM_NCR0: &[u8] = b"%\n\r\rO1234(PART)\n\r\rG00X1.Y2.\n\r\rM30\n\r\r%";

    #[test]
    fn detects_realistic_programs() {
        for text in [PROGRAM, PROGRAM_NCR0] {
            for code in [TapeCode::Iso, TapeCode::Ascii, TapeCode::Eia] {
                let tape = encode(text, code).unwrap();
                assert_eq!(detect(&tape), code, "{code} {text:?}");
                let (got, decoded) = decode(&tape).unwrap();
                assert_eq!(got, code);
                if code == TapeCode::Eia {
                    assert_eq!(decoded, PROGRAM);
                } else {
                    assert_eq!(decoded, text);
                }
            }
        }
        // With feed before and after, as spec. no. 1 and 2 punch it (§10).
        let mut eia = vec![0; 10];
        eia.extend(encode(PROGRAM, TapeCode::Eia).unwrap());
        eia.extend([0; 10]);
        assert_eq!(decode(&eia).unwrap(), (TapeCode::Eia, PROGRAM.to_vec()));
        let mut iso = vec![0; 10];
        iso.extend(encode(PROGRAM, TapeCode::Iso).unwrap());
        assert_eq!(decode(&iso).unwrap(), (TapeCode::Iso, PROGRAM.to_vec()));
    }

    #[test]
    fn detects_short_programs() {
        for text in [&b"%"[..], b"%\n%", b"%O1%", b"%\nM30\n%", b"%\nO1\n%"] {
            for code in [TapeCode::Iso, TapeCode::Ascii, TapeCode::Eia] {
                let tape = encode(text, code).unwrap();
                assert_eq!(detect(&tape), code, "{code} {text:?}");
            }
        }
        assert_eq!(detect(b""), TapeCode::Ascii);
        assert_eq!(detect(&[0, 0]), TapeCode::Ascii);
        // All odd parity but no EIA mark: ASCII.
        assert_eq!(detect(b"O1"), TapeCode::Ascii);
        // A text that needs no parity bit: ISO and ASCII give the same bytes.
        assert_eq!(
            detect(&encode(b"G0\n", TapeCode::Iso).unwrap()),
            TapeCode::Ascii
        );
    }

    #[test]
    fn decode_as_a_known_code() {
        let iso = encode(PROGRAM, TapeCode::Iso).unwrap();
        assert_eq!(decode_as(&iso, TapeCode::Iso).unwrap(), PROGRAM);
        assert_eq!(
            decode_as(&iso, TapeCode::Ascii),
            Err(TapeError::EightBit {
                offset: 0,
                byte: 0xA5
            })
        );
        assert_eq!(
            decode_as(b"%\nO1", TapeCode::Iso),
            Err(TapeError::Parity {
                code: TapeCode::Iso,
                offset: 0,
                byte: b'%'
            })
        );
        // Feed and delete are dropped in every code.
        assert_eq!(decode_as(b"\0%\x7f\n", TapeCode::Ascii).unwrap(), b"%\n");
        assert_eq!(decode_as(&[0x00, 0xA5, 0xFF], TapeCode::Iso).unwrap(), b"%");
    }

    #[test]
    fn misfits_are_parity_errors() {
        let mut iso = encode(PROGRAM, TapeCode::Iso).unwrap();
        iso[5] ^= 0x80;
        match decode(&iso) {
            Err(TapeError::Parity {
                code: TapeCode::Iso,
                offset: 5,
                ..
            }) => {}
            other => panic!("{other:?}"),
        }
        let mut eia = encode(PROGRAM, TapeCode::Eia).unwrap();
        eia[4] ^= 0x10;
        match decode(&eia) {
            Err(TapeError::Parity {
                code: TapeCode::Eia,
                offset: 4,
                ..
            }) => {}
            other => panic!("{other:?}"),
        }
    }

    fn eia_text() -> impl Strategy<Value = Vec<u8>> {
        proptest::collection::vec(proptest::sample::select(eia_text_chars()), 0..200)
    }

    proptest! {
        #[test]
        fn text_survives_eia(text in eia_text()) {
            let eia = encode(&text, TapeCode::Eia).unwrap();
            prop_assert!(eia.iter().all(|&b| has_odd_parity(b)));
            prop_assert_eq!(eia_to_iso(&eia).unwrap(), text);
        }

        #[test]
        fn text_survives_iso(text in eia_text()) {
            let iso = encode(&text, TapeCode::Iso).unwrap();
            prop_assert!(iso.iter().all(|&b| has_even_parity(b)));
            let (_, back) = decode(&iso).unwrap();
            prop_assert_eq!(back, text);
        }

        #[test]
        fn tapes_with_marks_are_recognised(text in eia_text()) {
            let mut program = b"%\n".to_vec();
            program.extend(&text);
            program.extend(b"\n%");
            for code in [TapeCode::Iso, TapeCode::Eia] {
                let tape = encode(&program, code).unwrap();
                prop_assert_eq!(detect(&tape), code);
            }
        }

        #[test]
        fn garbage_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
            let code = detect(&bytes);
            if let Ok((got, text)) = decode(&bytes) {
                prop_assert_eq!(got, code);
                prop_assert!(text.iter().all(|&b| b < 0x80));
            }
            let _ = eia_to_iso(&bytes);
            let _ = iso_to_eia(&bytes);
        }
    }
}
