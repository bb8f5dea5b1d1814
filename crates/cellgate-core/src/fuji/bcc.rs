//! The block check character of an FFU120B text (§4-3 items 20–23, appendix "BCC
//! calculation"; FFU120B notes 7).
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
    /// No BCC, the default.
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
/// the polynomial; CRC-16/ARC (reflected, initial value 0) is the reading of FFU120B notes 7,
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
    /// This CRC of `bytes`.
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

pub use crate::engine::hex::hex2;

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
    pub(crate) fn new(bytes: &[u8]) -> Self {
        let mut buf = [0u8; 4];
        let len = bytes.len().min(4);
        buf[..len].copy_from_slice(&bytes[..len]);
        BccBytes {
            buf,
            len: len as u8,
        }
    }

    /// The BCC bytes, in the order they travel.
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
    /// The BCC computed over the bytes it covers, as it would travel.
    pub expected: BccBytes,
    /// The BCC received.
    pub received: BccBytes,
}

/// One link's BCC: calculation, byte order and code (items 20, 22, 23 and the CRC reading).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Bcc {
    /// `Set1` or `Set2`; `None` means no BCC at all.
    pub kind: BccKind,
    /// How the BCC is calculated (item 22).
    pub calc: BccCalc,
    /// How the BCC travels: hex characters or binary (item 23).
    pub code: BccCode,
    /// Which CRC-16, when `calc` is CRC-16.
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

    /// Whether the text carries no BCC.
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
mod tests;
