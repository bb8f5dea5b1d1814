//! The block check character of an FFU120B text (§4-3 items 20–23, appendix "BCC
//! calculation"; protocol notes 7).
//!
//! The BCC is computed over the bytes *as transmitted* (after code transposition) over the
//! range of item 21 ([`super::frame::BccRange`]); where it goes is the frame's business. Here:
//! the four calculations, and the two ways a result travels:
//!
//! - transmission code: two hex characters, high digit first for Set 1, swapped for Set 2
//!   (appendix: AEh → `41 45`, Set 2 → `45 41`). A CRC-16 in transmission code is an initial
//!   error (§4-7 F3); should it be asked for anyway it travels as four characters, the high
//!   byte's pair first for Set 1 and the low byte's first for Set 2;
//! - binary: one byte; a CRC-16 two bytes, high byte first for Set 1, low first for Set 2.

use std::fmt;

use serde::{Deserialize, Serialize};

/// Whether a text carries a BCC, and in which order its two halves travel (§4-3 item 20).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum BccKind {
    #[default]
    None,
    /// High half first: high hex digit (transmission code) or high CRC byte (binary).
    Set1,
    /// Low half first.
    Set2,
}

/// How the BCC is calculated (§4-3 item 22).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub enum BccCalc {
    /// Sum of the bytes, mod 256.
    #[default]
    #[serde(rename = "add")]
    Add,
    /// Sum of the bytes mod 256, XOR FFh.
    #[serde(rename = "add-invert")]
    AddInvert,
    /// XOR of the bytes.
    #[serde(rename = "eor")]
    Eor,
    /// CRC-16, x¹⁶ + x¹⁵ + x² + 1; which of the CRCs on that polynomial is [`Crc16`].
    #[serde(rename = "crc16", alias = "crc-16")]
    Crc16,
}

/// How the BCC travels (§4-3 item 23).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum BccCode {
    /// As hex characters of the transmission code.
    #[default]
    TransmissionCode,
    /// As the raw result byte(s).
    Binary,
}

/// Which CRC on the polynomial x¹⁶ + x¹⁵ + x² + 1 (8005h) item 22 means. The manual names only
/// the polynomial; CRC-16/ARC (reflected, initial value 0) is the reading of protocol notes 7,
/// the others are there for a module that turns out to differ.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Crc16 {
    /// Reflected, initial value 0, no final XOR ("123456789" → BB3Dh).
    #[default]
    Arc,
    /// Not reflected, initial value 0 ("123456789" → FEE8h).
    Buypass,
    /// Reflected, initial value FFFFh ("123456789" → 4B37h).
    Modbus,
}

impl Crc16 {
    pub fn checksum(self, bytes: &[u8]) -> u16 {
        match self {
            Crc16::Arc => crc16_reflected(0, bytes),
            Crc16::Modbus => crc16_reflected(0xFFFF, bytes),
            Crc16::Buypass => crc16_normal(0, bytes),
        }
    }
}

/// Bitwise CRC on 8005h, reflected (A001h). Texts are at most a few hundred bytes: no table.
fn crc16_reflected(init: u16, bytes: &[u8]) -> u16 {
    let mut crc = init;
    for &b in bytes {
        crc ^= u16::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xA001
            } else {
                crc >> 1
            };
        }
    }
    crc
}

fn crc16_normal(init: u16, bytes: &[u8]) -> u16 {
    let mut crc = init;
    for &b in bytes {
        crc ^= u16::from(b) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 {
                (crc << 1) ^ 0x8005
            } else {
                crc << 1
            };
        }
    }
    crc
}

/// Lower 8 bits of the sum of `bytes`.
pub fn sum8(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0u8, |acc, &b| acc.wrapping_add(b))
}

/// XOR of `bytes`.
pub fn xor8(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0u8, |acc, &b| acc ^ b)
}

const HEX: &[u8; 16] = b"0123456789ABCDEF";

/// The two upper-case hex characters of `v`, high digit first.
pub fn hex2(v: u8) -> [u8; 2] {
    [HEX[usize::from(v >> 4)], HEX[usize::from(v & 0xF)]]
}

/// The value of one upper-case hex character (§4-3 item 14: "0 to 9, A to F").
pub fn hex_value(c: u8) -> Option<u8> {
    match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'A'..=b'F' => Some(c - b'A' + 10),
        _ => None,
    }
}

/// The value of two upper-case hex characters, high digit first.
pub fn parse_hex2(hi: u8, lo: u8) -> Option<u8> {
    Some((hex_value(hi)? << 4) | hex_value(lo)?)
}

/// The BCC bytes of one text, as they travel: at most four.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct BccBytes {
    buf: [u8; 4],
    len: u8,
}

impl BccBytes {
    fn new(bytes: &[u8]) -> Self {
        let mut buf = [0u8; 4];
        let len = bytes.len().min(4);
        buf[..len].copy_from_slice(&bytes[..len]);
        BccBytes {
            buf,
            len: len as u8,
        }
    }

    pub fn as_slice(&self) -> &[u8] {
        &self.buf[..usize::from(self.len)]
    }
}

impl fmt::Debug for BccBytes {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for b in self.as_slice() {
            write!(f, "{b:02X}")?;
        }
        Ok(())
    }
}

/// A received BCC that does not match the bytes it covers (§5-6 receive error 5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("BCC error: received {received:?}, computed {expected:?} (FFU120B §4-3 item 22, §5-6)")]
pub struct BccMismatch {
    pub expected: BccBytes,
    pub received: BccBytes,
}

/// One link's BCC: calculation, byte order and code (items 20, 22, 23 and the CRC reading).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Bcc {
    /// `Set1` or `Set2`; `None` means no BCC at all.
    pub kind: BccKind,
    pub calc: BccCalc,
    pub code: BccCode,
    pub crc16: Crc16,
}

impl Bcc {
    /// The raw result over `bytes`: 8 bits for add, add-invert and EOR, 16 for CRC-16.
    pub fn value(&self, bytes: &[u8]) -> u16 {
        match self.calc {
            BccCalc::Add => u16::from(sum8(bytes)),
            BccCalc::AddInvert => u16::from(sum8(bytes) ^ 0xFF),
            BccCalc::Eor => u16::from(xor8(bytes)),
            BccCalc::Crc16 => self.crc16.checksum(bytes),
        }
    }

    /// Bytes the BCC occupies on the line (0 without BCC).
    pub fn len(&self) -> usize {
        let wide = self.calc == BccCalc::Crc16;
        match (self.kind, self.code, wide) {
            (BccKind::None, _, _) => 0,
            (_, BccCode::Binary, false) => 1,
            (_, BccCode::Binary, true) | (_, BccCode::TransmissionCode, false) => 2,
            (_, BccCode::TransmissionCode, true) => 4,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The BCC of `bytes` as it travels.
    pub fn encode(&self, bytes: &[u8]) -> BccBytes {
        let v = self.value(bytes);
        let [hi, lo] = v.to_be_bytes();
        let set2 = self.kind == BccKind::Set2;
        let wide = self.calc == BccCalc::Crc16;
        match (self.kind, self.code, wide) {
            (BccKind::None, _, _) => BccBytes::new(&[]),
            (_, BccCode::Binary, false) => BccBytes::new(&[lo]),
            (_, BccCode::Binary, true) => BccBytes::new(&if set2 { [lo, hi] } else { [hi, lo] }),
            (_, BccCode::TransmissionCode, false) => {
                let [h, l] = hex2(lo);
                BccBytes::new(&if set2 { [l, h] } else { [h, l] })
            }
            (_, BccCode::TransmissionCode, true) => {
                let (first, second) = if set2 { (lo, hi) } else { (hi, lo) };
                let [a, b] = hex2(first);
                let [c, d] = hex2(second);
                BccBytes::new(&[a, b, c, d])
            }
        }
    }

    /// Checks `received` (the BCC bytes as they arrived) against the BCC of `bytes`.
    pub fn verify(&self, bytes: &[u8], received: &[u8]) -> Result<(), BccMismatch> {
        let expected = self.encode(bytes);
        if expected.as_slice() == received {
            Ok(())
        } else {
            Err(BccMismatch {
                expected,
                received: BccBytes::new(received),
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bcc(kind: BccKind, calc: BccCalc, code: BccCode) -> Bcc {
        Bcc {
            kind,
            calc,
            code,
            crc16: Crc16::Arc,
        }
    }

    /// The appendix example: `:000000010400000200` CR, add, start+text+end → AEh.
    const APPENDIX: &[u8] = b":000000010400000200\r";

    #[test]
    fn appendix_example_add_set1_set2_binary() {
        let add = |kind, code| bcc(kind, BccCalc::Add, code).encode(APPENDIX);
        assert_eq!(sum8(APPENDIX), 0xAE);
        assert_eq!(
            add(BccKind::Set1, BccCode::TransmissionCode).as_slice(),
            &[0x41, 0x45]
        );
        assert_eq!(
            add(BccKind::Set2, BccCode::TransmissionCode).as_slice(),
            &[0x45, 0x41]
        );
        assert_eq!(add(BccKind::Set1, BccCode::Binary).as_slice(), &[0xAE]);
        assert_eq!(add(BccKind::Set2, BccCode::Binary).as_slice(), &[0xAE]);
    }

    #[test]
    fn calculations_on_known_values() {
        let b = |calc| bcc(BccKind::Set1, calc, BccCode::Binary);
        assert_eq!(b(BccCalc::Add).value(APPENDIX), 0xAE);
        assert_eq!(b(BccCalc::AddInvert).value(APPENDIX), 0x51);
        assert_eq!(
            b(BccCalc::Eor).value(&[0x3A, 0x30, 0x31]),
            0x3A ^ 0x30 ^ 0x31
        );
        // Standard check values of the CRCs on 8005h.
        assert_eq!(Crc16::Arc.checksum(b"123456789"), 0xBB3D);
        assert_eq!(Crc16::Buypass.checksum(b"123456789"), 0xFEE8);
        assert_eq!(Crc16::Modbus.checksum(b"123456789"), 0x4B37);
        assert_eq!(Crc16::Arc.checksum(b""), 0);
    }

    #[test]
    fn crc_byte_order_and_length() {
        let set1 = bcc(BccKind::Set1, BccCalc::Crc16, BccCode::Binary);
        let set2 = bcc(BccKind::Set2, BccCalc::Crc16, BccCode::Binary);
        assert_eq!(set1.encode(b"123456789").as_slice(), &[0xBB, 0x3D]);
        assert_eq!(set2.encode(b"123456789").as_slice(), &[0x3D, 0xBB]);
        assert_eq!((set1.len(), set2.len()), (2, 2));
        // CRC in transmission code is initial error F3; if asked for it is four characters.
        let tc = bcc(BccKind::Set1, BccCalc::Crc16, BccCode::TransmissionCode);
        assert_eq!(tc.encode(b"123456789").as_slice(), b"BB3D");
        let tc2 = bcc(BccKind::Set2, BccCalc::Crc16, BccCode::TransmissionCode);
        assert_eq!(tc2.encode(b"123456789").as_slice(), b"3DBB");
        assert_eq!(tc.len(), 4);
    }

    #[test]
    fn every_kind_encodes_then_verifies_and_catches_a_flip() {
        let kinds = [BccKind::Set1, BccKind::Set2];
        let calcs = [
            BccCalc::Add,
            BccCalc::AddInvert,
            BccCalc::Eor,
            BccCalc::Crc16,
        ];
        let codes = [BccCode::TransmissionCode, BccCode::Binary];
        let crcs = [Crc16::Arc, Crc16::Buypass, Crc16::Modbus];
        for kind in kinds {
            for calc in calcs {
                for code in codes {
                    for crc16 in crcs {
                        let b = Bcc {
                            kind,
                            calc,
                            code,
                            crc16,
                        };
                        let enc = b.encode(APPENDIX);
                        assert_eq!(enc.as_slice().len(), b.len(), "{b:?}");
                        assert_eq!(b.verify(APPENDIX, enc.as_slice()), Ok(()), "{b:?}");
                        let mut bad = enc.as_slice().to_vec();
                        bad[0] ^= 0x01;
                        assert!(b.verify(APPENDIX, &bad).is_err(), "{b:?}");
                        // A changed byte in the range changes every calculation's result.
                        let mut other = APPENDIX.to_vec();
                        other[3] ^= 0x04;
                        assert!(b.verify(&other, enc.as_slice()).is_err(), "{b:?}");
                        if code == BccCode::TransmissionCode {
                            assert!(enc.as_slice().iter().all(|c| hex_value(*c).is_some()));
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn no_bcc_is_empty() {
        let b = bcc(BccKind::None, BccCalc::Crc16, BccCode::Binary);
        assert!(b.is_empty());
        assert_eq!(b.encode(APPENDIX).as_slice(), b"");
        assert_eq!(b.verify(APPENDIX, b""), Ok(()));
    }

    #[test]
    fn hex_helpers_are_upper_case_only() {
        assert_eq!(hex2(0xAE), *b"AE");
        assert_eq!(parse_hex2(b'A', b'E'), Some(0xAE));
        assert_eq!(parse_hex2(b'a', b'e'), None);
        assert_eq!(parse_hex2(b'G', b'0'), None);
    }

    #[test]
    fn serde_spellings() {
        #[derive(Deserialize)]
        struct W {
            calc: BccCalc,
            kind: BccKind,
            code: BccCode,
            crc: Crc16,
        }
        let w: W = toml::from_str(
            "calc = \"crc-16\"\nkind = \"set2\"\ncode = \"binary\"\ncrc = \"modbus\"",
        )
        .unwrap();
        assert_eq!(
            (w.calc, w.kind, w.code, w.crc),
            (
                BccCalc::Crc16,
                BccKind::Set2,
                BccCode::Binary,
                Crc16::Modbus
            )
        );
        let w: W = toml::from_str(
            "calc = \"add-invert\"\nkind = \"none\"\ncode = \"transmission-code\"\ncrc = \"arc\"",
        )
        .unwrap();
        assert_eq!(w.calc, BccCalc::AddInvert);
    }
}
