//! Texts on the line: start code, text, BCC, end code (FFU120B §4-3 items 14–23, §5-3, §5-6;
//! FFU120B notes 1, 6, 7).
//!
//! [`FrameSettings`] mirrors the module's initial file. A *text* here is the binary fields of
//! a command-set text (or the data of a non-procedure message); [`FrameSettings::encode`]
//! lays it on the line:
//!
//! ```text
//!   range text / start+text:       [start] text' [BCC] end
//!   range text+end / start+text+end: [start] text' end [BCC]
//! ```
//!
//! where `text'` is the text transposed to two upper-case hex characters per byte when code
//! transposition (item 14) is on, and the BCC is computed over the bytes as transmitted.
//!
//! [`FrameDecoder`] is the receiving side: a bounded buffer (the module's is 512 bytes, §5-6)
//! that returns whole decoded texts and classifies what it drops by the receive errors of
//! §5-6: buffer full (1), start code unidentified (2), BCC error (5), text too long (6), text
//! form unidentified (7). It never panics on any input; errors are counted
//! ([`ReceiveCounts`]) and logged once per burst.
//!
//! Where a text ends:
//! - code transposition on: at the first end code after the start code (hex characters cannot
//!   contain it); a new start code inside a text restarts the frame;
//! - code transposition off, command-set modes ([`TextLength::FromHeader`]): the text is
//!   5 + BYTEN bytes (§5-3, FFU120B notes 1), so binary data may contain the end code's byte;
//!   the end code must follow;
//! - non-procedure fixed length ([`TextLength::Fixed`]): every N data bytes, no start code,
//!   end code or BCC (appendix "Difference between fixed length and variable length"): N bytes
//!   on the line, or 2N hex characters with code transposition on (§4-3 items 14–15, FFU120B
//!   notes 9);
//! - start code "none": a text starts with the first byte after the previous frame; the owner
//!   clears the decoder after a silence (the master does so at each reply time-out), which is
//!   how the module tells texts apart too.

use serde::{Deserialize, Serialize};

pub use super::bcc::{Bcc, BccBytes, BccCalc, BccCode, BccKind, BccMismatch, Crc16};
use super::bcc::{hex_value, hex2};
use crate::engine::LineError;

mod receive;
pub use receive::{ReceiveCounts, ReceiveError, ReceiveErrorKind, TextForm};

/// The module's receive buffer (§5-6 receive error 1: "Receiving buffer full (512 bytes)").
pub const RX_BUFFER: usize = 512;
/// Longest command-set text: header (5) + relative address and count (4) + 220 data bytes of
/// a write or transfer (§5-3-2, FFU120B notes 3). §5-6 note 1 speaks of 220 bytes of data.
pub const MAX_COMMAND_TEXT: usize = 5 + 4 + 220;
/// Shortest command-set text: CMND, RSNO/STA, MODE, MOLN, BYTEN (§5-3-1).
pub const MIN_COMMAND_TEXT: usize = 5;
/// Longest non-procedure message (§1-3, §5-5: 1 ≤ N ≤ 216; §5-6 note 1).
pub const MAX_NON_PROCEDURE_TEXT: usize = 216;

/// STX (02h), the start code `stx`.
pub const STX: u8 = 0x02;
/// ETX (03h), the end code `etx`.
pub const ETX: u8 = 0x03;
/// LF (0Ah), the end code `lf`.
pub const LF: u8 = 0x0A;
/// CR (0Dh), the end code `cr`.
pub const CR: u8 = 0x0D;
/// DLE (10h), the first byte of the end code `dle-etx`.
pub const DLE: u8 = 0x10;

/// The transmission code of the characters of a frame (§4-3 item 13): JIS / ASCII, or EBCDIC
/// (code page 037; FFU120B notes 10). It decides how the characters the module itself lays on
/// the line are written: the start codes `:` / `::`, the end codes, and, with code
/// transposition (item 14), the hex characters of the text and of a BCC in transmission code.
/// Codes given as bytes (Set 1 / Set 2) and binary data travel as given.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum TransmissionCode {
    /// JIS / ASCII, the initial value.
    #[default]
    #[serde(alias = "jis")]
    Ascii,
    /// EBCDIC, code page 037. Needs 8 data bits (initial error F6).
    Ebcdic,
}

impl TransmissionCode {
    /// The ASCII character `c` as it travels in this code. Only the characters a frame is
    /// made of differ: the hex digits, `:` and LF (STX, ETX, CR and DLE have the same code
    /// points in both); any other byte is returned as it is.
    pub fn encode_char(self, c: u8) -> u8 {
        match self {
            TransmissionCode::Ascii => c,
            TransmissionCode::Ebcdic => match c {
                b'0'..=b'9' => 0xF0 + (c - b'0'),
                b'A'..=b'I' => 0xC1 + (c - b'A'),
                b':' => 0x7A,
                LF => 0x25,
                other => other,
            },
        }
    }

    /// The value of one upper-case hex character in this code.
    pub fn hex_value(self, b: u8) -> Option<u8> {
        match self {
            TransmissionCode::Ascii => hex_value(b),
            TransmissionCode::Ebcdic => match b {
                0xF0..=0xF9 => Some(b - 0xF0),
                0xC1..=0xC6 => Some(b - 0xC1 + 10),
                _ => None,
            },
        }
    }

    /// The two hex characters of `v`, high digit first, in this code.
    pub fn hex2(self, v: u8) -> [u8; 2] {
        hex2(v).map(|c| self.encode_char(c))
    }

    /// The value of two hex characters in this code.
    pub fn parse_hex2(self, hi: u8, lo: u8) -> Option<u8> {
        Some((self.hex_value(hi)? << 4) | self.hex_value(lo)?)
    }
}

/// Start code of a text (§4-3 item 16).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub enum StartCode {
    /// No start code.
    #[serde(rename = "none")]
    None,
    /// STX (02h).
    #[serde(rename = "stx")]
    Stx,
    /// `:` — the manual's usual choice.
    #[default]
    #[serde(rename = ":", alias = "colon")]
    Colon,
    /// `::`.
    #[serde(rename = "::", alias = "double-colon")]
    DoubleColon,
    /// One byte given in `start_codes` (item 18).
    #[serde(rename = "set1")]
    Set1,
    /// Two bytes given in `start_codes` (item 18).
    #[serde(rename = "set2")]
    Set2,
}

impl StartCode {
    /// Bytes Set 1 / Set 2 need in `start_codes`.
    pub fn set_bytes(self) -> Option<usize> {
        match self {
            StartCode::Set1 => Some(1),
            StartCode::Set2 => Some(2),
            _ => None,
        }
    }
}

/// End code of a text (§4-3 item 17). There is no "none": no end code is initial error F5.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum EndCode {
    /// ETX (03h).
    Etx,
    /// CR — the manual's usual choice.
    #[default]
    Cr,
    /// LF (0Ah).
    Lf,
    /// CR LF.
    CrLf,
    /// DLE ETX.
    DleEtx,
    /// One byte given in `end_codes` (item 19).
    Set1,
    /// Two bytes given in `end_codes` (item 19).
    Set2,
}

impl EndCode {
    /// Bytes Set 1 / Set 2 need in `end_codes`.
    pub fn set_bytes(self) -> Option<usize> {
        match self {
            EndCode::Set1 => Some(1),
            EndCode::Set2 => Some(2),
            _ => None,
        }
    }
}

/// Location of the BCC and the range it covers (§4-3 item 21). A range that contains the end
/// code puts the BCC after the end code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub enum BccRange {
    /// The text; the BCC goes before the end code.
    #[default]
    #[serde(rename = "text")]
    Text,
    /// The text and the end code; the BCC follows the end code.
    #[serde(rename = "text+end")]
    TextEnd,
    /// The start code and the text; the BCC goes before the end code.
    #[serde(rename = "start+text")]
    StartText,
    /// The start code, the text and the end code; the BCC follows the end code.
    #[serde(rename = "start+text+end")]
    StartTextEnd,
}

impl BccRange {
    /// The range contains the end code, so the BCC follows it.
    pub fn includes_end(self) -> bool {
        matches!(self, BccRange::TextEnd | BccRange::StartTextEnd)
    }
    /// The range contains the start code.
    pub fn includes_start(self) -> bool {
        matches!(self, BccRange::StartText | BccRange::StartTextEnd)
    }
}

/// The framing items of the module's initial file (§4-3 items 14, 16–23), which both ends must
/// agree on. Field names and spellings are those of the cell file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FrameSettings {
    /// Start code (item 16); `:` by default.
    pub start_code: StartCode,
    /// The bytes of `start_code = "set1"` (one) or `"set2"` (two), item 18.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub start_codes: Vec<u8>,
    /// End code (item 17); CR by default.
    pub end_code: EndCode,
    /// The bytes of `end_code = "set1"` (one) or `"set2"` (two), item 19.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub end_codes: Vec<u8>,
    /// Code transposition (item 14, initial value "yes"): every byte of the text travels as
    /// two upper-case hex characters.
    pub transposition: bool,
    /// Transmission code (item 13): `ascii` (JIS, the initial value) or `ebcdic`.
    pub code: TransmissionCode,
    /// Whether texts carry a BCC, and the order of its halves (item 20); none by default.
    pub bcc: BccKind,
    /// Where the BCC goes and what it covers (item 21).
    pub bcc_range: BccRange,
    /// How the BCC is calculated (item 22).
    pub bcc_calc: BccCalc,
    /// How the BCC travels (item 23).
    pub bcc_code: BccCode,
    /// Which CRC-16 `bcc_calc = "crc16"` means (the manual names only the polynomial).
    pub crc16: Crc16,
}

impl Default for FrameSettings {
    /// The module's initial values (§4-3-1): `:`, CR, transposition on, no BCC.
    fn default() -> Self {
        FrameSettings {
            start_code: StartCode::Colon,
            start_codes: Vec::new(),
            end_code: EndCode::Cr,
            end_codes: Vec::new(),
            transposition: true,
            code: TransmissionCode::Ascii,
            bcc: BccKind::None,
            bcc_range: BccRange::Text,
            bcc_calc: BccCalc::Add,
            bcc_code: BccCode::TransmissionCode,
            crc16: Crc16::Arc,
        }
    }
}

/// One thing the module would refuse in these settings, with its initial error (§4-7), or
/// that would make texts ambiguous on the line.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FrameProblem {
    /// Set 1 / Set 2 start code without the right number of bytes in `start_codes`.
    #[error(
        "start code {code:?} needs {want} byte(s) in start_codes, {got} given (initial error F0, FFU120B §4-3 item 18, §4-7)"
    )]
    StartCodeBytes {
        /// The start code.
        code: StartCode,
        /// Bytes it needs.
        want: usize,
        /// Bytes given.
        got: usize,
    },
    /// Set 1 / Set 2 end code without the right number of bytes in `end_codes`.
    #[error(
        "end code {code:?} needs {want} byte(s) in end_codes, {got} given (initial error F0, FFU120B §4-3 item 19, §4-7)"
    )]
    EndCodeBytes {
        /// The end code.
        code: EndCode,
        /// Bytes it needs.
        want: usize,
        /// Bytes given.
        got: usize,
    },
    /// Set 1 / Set 2 end code with no bytes at all: no end code is set.
    #[error(
        "end code {code:?} has no bytes in end_codes: no end code is set (initial error F5, FFU120B §4-7)"
    )]
    NoEndCode {
        /// The end code.
        code: EndCode,
    },
    /// A binary BCC placed before the end code.
    #[error(
        "a binary BCC must follow the end code: bcc_range {range:?} puts it before (initial error F1, FFU120B §4-3 item 23, §4-7)"
    )]
    BinaryBccBeforeEnd {
        /// The BCC range given.
        range: BccRange,
    },
    /// A CRC-16 BCC placed before the end code.
    #[error(
        "a CRC-16 BCC must follow the end code: bcc_range {range:?} puts it before (initial error F2, FFU120B §4-7)"
    )]
    CrcBeforeEnd {
        /// The BCC range given.
        range: BccRange,
    },
    /// A CRC-16 BCC in transmission code.
    #[error(
        "a CRC-16 BCC travels in binary, not in transmission code (initial error F3, FFU120B §4-3 item 23, §4-7)"
    )]
    CrcInTransmissionCode,
    /// EBCDIC with 7 data bits (items 5 and 13).
    #[error(
        "EBCDIC (item 13) is an 8-bit code: data bits must be 8, not 7 (item 5; initial error F6, FFU120B §4-7)"
    )]
    EbcdicSevenBits,
    /// Not an initial error: with code transposition the text is hex characters, and a start
    /// or end code byte that is one could not be told from the text.
    #[error(
        "{which} byte {byte:#04x} is a hex character, which the transposed text is made of (FFU120B §4-3 items 14, 18, 19)"
    )]
    CodeIsTextCharacter {
        /// `"start code"` or `"end code"`.
        which: &'static str,
        /// The byte that is a hex character.
        byte: u8,
    },
}

impl FrameProblem {
    /// The initial error number the module shows for this problem (§4-7), if it has one.
    pub fn initial_error(&self) -> Option<u8> {
        match self {
            FrameProblem::StartCodeBytes { .. } | FrameProblem::EndCodeBytes { .. } => Some(0xF0),
            FrameProblem::BinaryBccBeforeEnd { .. } => Some(0xF1),
            FrameProblem::CrcBeforeEnd { .. } => Some(0xF2),
            FrameProblem::CrcInTransmissionCode => Some(0xF3),
            FrameProblem::NoEndCode { .. } => Some(0xF5),
            FrameProblem::EbcdicSevenBits => Some(0xF6),
            FrameProblem::CodeIsTextCharacter { .. } => None,
        }
    }
}

impl FrameSettings {
    /// The start code's bytes (empty for "none"), in the transmission code.
    pub fn start_bytes(&self) -> &[u8] {
        let ebcdic = self.code == TransmissionCode::Ebcdic;
        match self.start_code {
            StartCode::None => &[],
            StartCode::Stx => &[STX],
            StartCode::Colon if ebcdic => &[0x7A],
            StartCode::Colon => b":",
            StartCode::DoubleColon if ebcdic => &[0x7A, 0x7A],
            StartCode::DoubleColon => b"::",
            StartCode::Set1 => self.start_codes.get(..1).unwrap_or(&self.start_codes),
            StartCode::Set2 => self.start_codes.get(..2).unwrap_or(&self.start_codes),
        }
    }

    /// The end code's bytes, in the transmission code (LF is 25h in EBCDIC).
    pub fn end_bytes(&self) -> &[u8] {
        let ebcdic = self.code == TransmissionCode::Ebcdic;
        match self.end_code {
            EndCode::Etx => &[ETX],
            EndCode::Cr => &[CR],
            EndCode::Lf if ebcdic => &[0x25],
            EndCode::Lf => &[LF],
            EndCode::CrLf if ebcdic => &[CR, 0x25],
            EndCode::CrLf => &[CR, LF],
            EndCode::DleEtx => &[DLE, ETX],
            EndCode::Set1 => self.end_codes.get(..1).unwrap_or(&self.end_codes),
            EndCode::Set2 => self.end_codes.get(..2).unwrap_or(&self.end_codes),
        }
    }

    /// The link's BCC, from items 20–23 and `crc16`.
    pub fn bcc(&self) -> Bcc {
        Bcc {
            kind: self.bcc,
            calc: self.bcc_calc,
            code: self.bcc_code,
            crc16: self.crc16,
        }
    }

    /// The BCC of `covered` as it travels: in transmission code, its hex characters in the
    /// link's code (item 13; FFU120B notes 10).
    pub fn bcc_bytes(&self, covered: &[u8]) -> BccBytes {
        let b = self.bcc().encode(covered);
        if self.bcc_code == BccCode::TransmissionCode && self.code != TransmissionCode::Ascii {
            let mapped: Vec<u8> = b
                .as_slice()
                .iter()
                .map(|&c| self.code.encode_char(c))
                .collect();
            BccBytes::new(&mapped)
        } else {
            b
        }
    }

    /// Checks a received BCC against the BCC of `covered`.
    pub fn verify_bcc(&self, covered: &[u8], received: &[u8]) -> Result<(), BccMismatch> {
        let expected = self.bcc_bytes(covered);
        if expected.as_slice() == received {
            Ok(())
        } else {
            Err(BccMismatch {
                expected,
                received: BccBytes::new(received),
            })
        }
    }

    /// Every problem of these settings with the line's character framing: those of
    /// [`FrameSettings::validate`], and EBCDIC with 7 data bits (initial error F6).
    pub fn validate_with_line(&self, line: &crate::engine::LineSettings) -> Vec<FrameProblem> {
        let mut problems = self.validate();
        if self.code == TransmissionCode::Ebcdic
            && line.data_bits == crate::engine::line::DataBits::Seven
        {
            problems.push(FrameProblem::EbcdicSevenBits);
        }
        problems
    }

    /// Line bytes per text byte.
    pub fn width(&self) -> usize {
        if self.transposition { 2 } else { 1 }
    }

    /// Bytes on the line of a text of `text_len` bytes.
    pub fn line_len(&self, text_len: usize) -> usize {
        self.start_bytes().len()
            + text_len * self.width()
            + self.bcc().len()
            + self.end_bytes().len()
    }

    /// Every problem of these settings (§4-7), empty when the module would accept them.
    pub fn validate(&self) -> Vec<FrameProblem> {
        let mut problems = Vec::new();
        if let Some(want) = self.start_code.set_bytes()
            && self.start_codes.len() != want
        {
            problems.push(FrameProblem::StartCodeBytes {
                code: self.start_code,
                want,
                got: self.start_codes.len(),
            });
        }
        if let Some(want) = self.end_code.set_bytes() {
            if self.end_codes.is_empty() {
                problems.push(FrameProblem::NoEndCode {
                    code: self.end_code,
                });
            } else if self.end_codes.len() != want {
                problems.push(FrameProblem::EndCodeBytes {
                    code: self.end_code,
                    want,
                    got: self.end_codes.len(),
                });
            }
        }
        if self.bcc != BccKind::None {
            if !self.bcc_range.includes_end() {
                if self.bcc_code == BccCode::Binary {
                    problems.push(FrameProblem::BinaryBccBeforeEnd {
                        range: self.bcc_range,
                    });
                }
                if self.bcc_calc == BccCalc::Crc16 {
                    problems.push(FrameProblem::CrcBeforeEnd {
                        range: self.bcc_range,
                    });
                }
            }
            if self.bcc_calc == BccCalc::Crc16 && self.bcc_code == BccCode::TransmissionCode {
                problems.push(FrameProblem::CrcInTransmissionCode);
            }
        }
        if self.transposition {
            let codes = [
                ("start code", self.start_bytes()),
                ("end code", self.end_bytes()),
            ];
            for (which, bytes) in codes {
                if let Some(&byte) = bytes.iter().find(|b| self.code.hex_value(**b).is_some()) {
                    problems.push(FrameProblem::CodeIsTextCharacter { which, byte });
                }
            }
        }
        problems
    }

    /// A fixed-length non-procedure message as it travels (§5-5, appendix): the data alone,
    /// with no start code, end code or BCC, each byte as two hex characters of the
    /// transmission code when code transposition is on (§4-3 items 13–15; FFU120B notes 9).
    pub fn encode_bare(&self, text: &[u8]) -> Vec<u8> {
        if !self.transposition {
            return text.to_vec();
        }
        text.iter().flat_map(|&b| self.code.hex2(b)).collect()
    }

    /// `text` as it travels: start code, text (transposed when item 14 says so), BCC and end
    /// code in the order of item 21.
    pub fn encode(&self, text: &[u8]) -> Vec<u8> {
        let bcc = self.bcc();
        let mut out = Vec::with_capacity(self.line_len(text.len()));
        out.extend_from_slice(self.start_bytes());
        let text_at = out.len();
        if self.transposition {
            for &b in text {
                out.extend_from_slice(&self.code.hex2(b));
            }
        } else {
            out.extend_from_slice(text);
        }
        let from = if self.bcc_range.includes_start() {
            0
        } else {
            text_at
        };
        if !bcc.is_empty() && !self.bcc_range.includes_end() {
            let b = self.bcc_bytes(out.get(from..).unwrap_or_default());
            out.extend_from_slice(b.as_slice());
        }
        out.extend_from_slice(self.end_bytes());
        if !bcc.is_empty() && self.bcc_range.includes_end() {
            let b = self.bcc_bytes(out.get(from..).unwrap_or_default());
            out.extend_from_slice(b.as_slice());
        }
        out
    }
}

/// How the decoder finds where a text ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TextLength {
    /// At the first end code (transposed texts, non-procedure variable length).
    UntilEnd,
    /// 5 + BYTEN bytes, BYTEN being the fifth byte of the text (command-set texts, §5-3).
    FromHeader,
    /// Exactly this many data bytes, without start code, end code or BCC (non-procedure
    /// fixed length, §5-5): as many bytes on the line, or twice as many hex characters with
    /// code transposition (§4-3 items 14–15).
    Fixed(usize),
}

/// What one call to [`FrameDecoder::decode`] found: a text, or what was dropped.
pub type Decoded = Result<Vec<u8>, ReceiveError>;

/// Splits received bytes into texts (see the module documentation).
#[derive(Debug, Clone)]
pub struct FrameDecoder {
    settings: FrameSettings,
    bcc: Bcc,
    length: TextLength,
    min_text: usize,
    max_text: usize,
    buf: Vec<u8>,
    /// After a text too long: drop everything up to the next start code (or, without start
    /// code, through the next end code).
    discarding: bool,
    /// Bytes dropped before a start code, reported as one error when the run ends.
    garbage: usize,
    counts: ReceiveCounts,
    /// Errors since the last good text; the first is logged, the rest summed up.
    burst: u64,
    /// A character of the text under way came with this line error: the text ends as a
    /// receive error (§5-6).
    spoilt: Option<LineError>,
    /// A character came with a line error where a start code was awaited: the bytes dropped
    /// until the next start code are most likely the text whose start code it was, and are
    /// counted as a text ended by that error rather than as line noise.
    spoilt_start: Option<LineError>,
}

impl FrameDecoder {
    /// A decoder with explicit bounds. `max_text` is clamped to what the buffer can hold.
    pub fn new(
        settings: &FrameSettings,
        length: TextLength,
        min_text: usize,
        max_text: usize,
    ) -> Self {
        let length = match length {
            TextLength::Fixed(n) => TextLength::Fixed(n.clamp(1, RX_BUFFER / settings.width())),
            other => other,
        };
        FrameDecoder {
            bcc: settings.bcc(),
            settings: settings.clone(),
            length,
            min_text,
            max_text: max_text.min(RX_BUFFER),
            buf: Vec::new(),
            discarding: false,
            garbage: 0,
            counts: ReceiveCounts::default(),
            burst: 0,
            spoilt: None,
            spoilt_start: None,
        }
    }

    /// The decoder of command-set texts (modes 1–3): 5 to 229 bytes; binary texts end where
    /// BYTEN says.
    pub fn command_set(settings: &FrameSettings) -> Self {
        let length = if settings.transposition {
            TextLength::UntilEnd
        } else {
            TextLength::FromHeader
        };
        Self::new(settings, length, MIN_COMMAND_TEXT, MAX_COMMAND_TEXT)
    }

    /// The decoder of non-procedure messages (modes 4–5): `fixed` bytes each, or up to the
    /// end code (1 to 216 bytes).
    pub fn non_procedure(settings: &FrameSettings, fixed: Option<usize>) -> Self {
        let length = fixed.map_or(TextLength::UntilEnd, TextLength::Fixed);
        Self::new(settings, length, 1, MAX_NON_PROCEDURE_TEXT)
    }

    /// The framing settings the decoder reads texts in.
    pub fn settings(&self) -> &FrameSettings {
        &self.settings
    }

    /// Receive errors so far, by kind.
    pub fn counts(&self) -> ReceiveCounts {
        self.counts
    }

    /// Bytes held: received and not yet part of a whole text. Never above [`RX_BUFFER`].
    pub fn buffered(&self) -> usize {
        self.buf.len()
    }

    /// Whether a text has begun and not ended.
    pub fn in_text(&self) -> bool {
        !self.buf.is_empty()
    }

    /// Forgets a partial text: after a silence (reply time-out), a line error, a mode change.
    /// Garbage dropped so far is counted.
    pub fn clear(&mut self) {
        self.buf.clear();
        self.discarding = false;
        self.spoilt = None;
        if let Some(e) = self.take_garbage() {
            self.note(&e);
        }
        self.spoilt_start = None;
    }

    /// A character arrived with a line error (parity, framing, overrun; the transport did not
    /// deliver it) after the bytes already taken and before any taken later. The text it
    /// belongs to ends as a receive error ("receiving ends to error", §5-6), and the next text
    /// is read as usual: a fixed-length message keeps the lost character's place, so that the
    /// next one stays on its boundary. A character outside any text (before a start code)
    /// spoils nothing. Returns what the lost character's place completes (a fixed-length
    /// message that ended on it), as [`FrameDecoder::decode`] does.
    pub fn spoil(&mut self, error: LineError) -> Vec<Decoded> {
        let lost = usize::from(!matches!(error, LineError::Overrun));
        match self.length {
            TextLength::Fixed(_) => {
                // Not a hex digit either: the placeholder is never taken as data.
                self.buf.extend(std::iter::repeat_n(0xFF, lost));
            }
            _ if self.buf.is_empty() && !self.settings.start_bytes().is_empty() => {
                self.spoilt_start = Some(error);
                return Vec::new();
            }
            _ => {}
        }
        self.spoilt = Some(error);
        self.decode(&[])
    }

    /// A finished text, or the receive error it is when a character of it was spoilt.
    fn judge(&mut self, d: Decoded) -> Decoded {
        match d {
            Ok(text) => match self.spoilt.take() {
                Some(e) => Err(ReceiveError::Character(e)),
                None => Ok(text),
            },
            // Bytes dropped before a start code are not the spoilt text.
            Err(e @ ReceiveError::StartCode { .. }) => Err(e),
            // Whatever else is wrong with the text, the character error came first.
            Err(e) => match self.spoilt.take() {
                Some(line) => Err(ReceiveError::Character(line)),
                None => Err(e),
            },
        }
    }

    /// Takes received bytes; returns the texts they complete and what was dropped, in order.
    pub fn decode(&mut self, bytes: &[u8]) -> Vec<Decoded> {
        let mut out = Vec::new();
        let mut rest = bytes;
        // At least one pass, so that a place taken by a lost character ([`Self::spoil`]) is
        // looked at too.
        loop {
            // Never hold more than the module's buffer: take what fits, split it, go on.
            let room = RX_BUFFER.saturating_sub(self.buf.len()).max(1);
            let (now, later) = rest.split_at(room.min(rest.len()));
            rest = later;
            self.buf.extend_from_slice(now);
            while let Some(d) = self.next() {
                let d = self.judge(d);
                match &d {
                    Ok(_) => self.good(),
                    Err(e) => self.note(e),
                }
                out.push(d);
            }
            if self.buf.len() >= RX_BUFFER {
                let dropped = self.buf.len();
                self.buf.clear();
                self.discarding = true;
                let e = ReceiveError::BufferFull { dropped };
                self.note(&e);
                out.push(Err(e));
            }
            if rest.is_empty() {
                break;
            }
        }
        out
    }

    fn good(&mut self) {
        if self.burst > 1 {
            tracing::info!(errors = self.burst, "FFU120B receive errors ended");
        }
        self.burst = 0;
    }

    fn note(&mut self, e: &ReceiveError) {
        self.counts.add(e.kind());
        self.burst = self.burst.saturating_add(1);
        if self.burst == 1 {
            tracing::warn!(error = %e, "FFU120B text dropped; further errors of this burst at debug level");
        } else {
            tracing::debug!(error = %e, "FFU120B text dropped");
        }
    }

    /// One step over the buffer: a text, an error, or `None` when more bytes are needed.
    fn next(&mut self) -> Option<Decoded> {
        if let TextLength::Fixed(n) = self.length {
            // N data bytes are 2N characters with transposition on; every character counts
            // towards the message, so one that is not a hex digit spoils only its own message
            // (text form, §5-6) and the next starts on its boundary.
            let chars = n * self.settings.width();
            if self.buf.len() < chars {
                return None;
            }
            let line: Vec<u8> = self.buf.drain(..chars).collect();
            if !self.settings.transposition {
                return Some(Ok(line));
            }
            return Some(untranspose_in(self.settings.code, &line));
        }
        let start_len = self.settings.start_bytes().len();
        if start_len > 0 {
            if let Some(e) = self.find_start() {
                return Some(Err(e));
            }
            if self.buf.len() < start_len {
                return None;
            }
        } else if self.discarding {
            // No start code: resynchronise after the next end code.
            let end = self.settings.end_bytes();
            let at = find(&self.buf, end)?;
            self.buf.drain(..at + end.len());
            self.discarding = false;
            return self.next();
        }
        match self.length {
            TextLength::FromHeader => self.next_by_header(start_len),
            _ => self.next_until_end(start_len),
        }
    }

    /// Drops bytes before the start code; the run is reported once it ends. Leaves the buffer
    /// starting with the start code (or a prefix of it).
    fn find_start(&mut self) -> Option<ReceiveError> {
        let start = self.settings.start_bytes();
        match find(&self.buf, start) {
            Some(0) => {
                self.discarding = false;
                self.take_garbage()
            }
            Some(p) => {
                self.drop_front(p);
                self.discarding = false;
                self.take_garbage()
            }
            None => {
                // Keep a trailing byte that may begin a two-byte start code.
                let keep = usize::from(
                    start.len() == 2 && self.buf.last() == start.first() && !self.buf.is_empty(),
                );
                let p = self.buf.len() - keep;
                self.drop_front(p);
                None
            }
        }
    }

    fn drop_front(&mut self, n: usize) {
        if n == 0 {
            return;
        }
        self.buf.drain(..n);
        if !self.discarding {
            self.garbage = self.garbage.saturating_add(n);
        }
    }

    fn take_garbage(&mut self) -> Option<ReceiveError> {
        let spoilt = self.spoilt_start.take();
        if self.garbage == 0 {
            return None;
        }
        let dropped = std::mem::take(&mut self.garbage);
        Some(match spoilt {
            Some(line) => ReceiveError::Character(line),
            None => ReceiveError::StartCode { dropped },
        })
    }

    /// Longest body (text and a BCC before the end code) on the line.
    fn max_body(&self) -> usize {
        let before = if self.settings.bcc_range.includes_end() {
            0
        } else {
            self.bcc.len()
        };
        self.max_text * self.settings.width() + before
    }

    fn too_long(&mut self) -> Decoded {
        let len = self.buf.len();
        self.buf.clear();
        self.discarding = true;
        Err(ReceiveError::TooLong {
            len: len / self.settings.width(),
            max: self.max_text,
        })
    }

    fn next_until_end(&mut self, start_len: usize) -> Option<Decoded> {
        let end = self.settings.end_bytes();
        let end_len = end.len();
        let body = self.buf.get(start_len..).unwrap_or_default();
        let end_at = find(body, end).map(|i| i + start_len);
        // A start code inside a transposed text: the text was cut short; restart there.
        if self.settings.transposition && start_len > 0 {
            let first = self.settings.start_bytes().first().copied();
            let scan_to = end_at.unwrap_or(self.buf.len());
            let scan = self.buf.get(start_len..scan_to).unwrap_or_default();
            if let Some(first) = first
                && self.settings.code.hex_value(first).is_none()
                && let Some(q) = scan.iter().position(|&b| b == first)
            {
                if q == 0 {
                    // Start code after start code: no text had begun, nothing was lost; the
                    // later one starts the text.
                    self.buf.drain(..start_len);
                    return self.next();
                }
                self.buf.drain(..start_len + q);
                return Some(Err(ReceiveError::TextForm(TextForm::Truncated {
                    after: q,
                })));
            }
        }
        let Some(end_at) = end_at else {
            if body.len() > self.max_body() + end_len {
                return Some(self.too_long());
            }
            return None;
        };
        if end_at - start_len > self.max_body() {
            self.buf.drain(..end_at + end_len);
            return Some(Err(ReceiveError::TooLong {
                len: (end_at - start_len) / self.settings.width(),
                max: self.max_text,
            }));
        }
        let after = if self.settings.bcc_range.includes_end() {
            self.bcc.len()
        } else {
            0
        };
        let frame_len = end_at + end_len + after;
        if self.buf.len() < frame_len {
            return None;
        }
        let frame: Vec<u8> = self.buf.drain(..frame_len).collect();
        Some(self.finish(&frame, start_len, end_at))
    }

    fn next_by_header(&mut self, start_len: usize) -> Option<Decoded> {
        let w = self.settings.width();
        let header_end = start_len + MIN_COMMAND_TEXT * w;
        if self.buf.len() < header_end {
            return None;
        }
        let byten = if w == 2 {
            let hi = self.buf.get(header_end - 2).copied().unwrap_or(0);
            let lo = self.buf.get(header_end - 1).copied().unwrap_or(0);
            match self.settings.code.parse_hex2(hi, lo) {
                Some(v) => v,
                None => {
                    return Some(self.resync(TextForm::NotHex {
                        offset: 8,
                        byte: hi,
                    }));
                }
            }
        } else {
            self.buf.get(header_end - 1).copied().unwrap_or(0)
        };
        let text_len = MIN_COMMAND_TEXT + usize::from(byten);
        if text_len > self.max_text {
            return Some(self.resync_too_long(text_len));
        }
        let before = if self.settings.bcc_range.includes_end() {
            0
        } else {
            self.bcc.len()
        };
        let after = self.bcc.len() - before;
        let end_at = start_len + text_len * w + before;
        let end = self.settings.end_bytes();
        if self.buf.len() < end_at + end.len() + after {
            return None;
        }
        if self.buf.get(end_at..end_at + end.len()) != Some(end) {
            return Some(self.resync(TextForm::NoEndCode));
        }
        let frame: Vec<u8> = self.buf.drain(..end_at + end.len() + after).collect();
        Some(self.finish(&frame, start_len, end_at))
    }

    /// Drops a frame whose header cannot be right, and looks for the next start.
    fn resync(&mut self, why: TextForm) -> Decoded {
        let start_len = self.settings.start_bytes().len();
        if start_len > 0 {
            // Past this start code; the next one begins the next frame.
            self.buf.drain(..start_len.min(self.buf.len()));
        } else {
            self.discarding = true;
        }
        Err(ReceiveError::TextForm(why))
    }

    fn resync_too_long(&mut self, len: usize) -> Decoded {
        let _ = self.resync(TextForm::NoEndCode);
        Err(ReceiveError::TooLong {
            len,
            max: self.max_text,
        })
    }

    /// Checks the BCC of a whole frame and decodes its text. `end_at` is where the end code
    /// begins.
    fn finish(&self, frame: &[u8], start_len: usize, end_at: usize) -> Decoded {
        let end_len = self.settings.end_bytes().len();
        let range = self.settings.bcc_range;
        let (text_end, bcc_rx) = if self.bcc.is_empty() {
            (end_at, &[][..])
        } else if range.includes_end() {
            (end_at, frame.get(end_at + end_len..).unwrap_or_default())
        } else {
            let Some(t) = end_at
                .checked_sub(self.bcc.len())
                .filter(|t| *t >= start_len)
            else {
                return Err(ReceiveError::TextForm(TextForm::TooShort {
                    len: 0,
                    min: self.min_text,
                }));
            };
            (t, frame.get(t..end_at).unwrap_or_default())
        };
        if !self.bcc.is_empty() {
            let from = if range.includes_start() { 0 } else { start_len };
            let to = if range.includes_end() {
                end_at + end_len
            } else {
                text_end
            };
            let covered = frame.get(from..to).unwrap_or_default();
            self.settings
                .verify_bcc(covered, bcc_rx)
                .map_err(ReceiveError::Bcc)?;
        }
        let line = frame.get(start_len..text_end).unwrap_or_default();
        let text = if self.settings.transposition {
            untranspose_in(self.settings.code, line)?
        } else {
            line.to_vec()
        };
        if text.len() > self.max_text {
            return Err(ReceiveError::TooLong {
                len: text.len(),
                max: self.max_text,
            });
        }
        if text.len() < self.min_text {
            return Err(ReceiveError::TextForm(TextForm::TooShort {
                len: text.len(),
                min: self.min_text,
            }));
        }
        Ok(text)
    }
}

/// Two upper-case hex characters per byte back to bytes (§4-3 item 14).
pub fn untranspose(line: &[u8]) -> Result<Vec<u8>, ReceiveError> {
    untranspose_in(TransmissionCode::Ascii, line)
}

/// Two upper-case hex characters of `code` per byte back to bytes (§4-3 items 13, 14).
pub fn untranspose_in(code: TransmissionCode, line: &[u8]) -> Result<Vec<u8>, ReceiveError> {
    if line.len() % 2 != 0 {
        return Err(ReceiveError::TextForm(TextForm::OddLength {
            len: line.len(),
        }));
    }
    let mut text = Vec::with_capacity(line.len() / 2);
    for (i, pair) in line.chunks_exact(2).enumerate() {
        let &[hi, lo] = pair else {
            continue;
        };
        match code.parse_hex2(hi, lo) {
            Some(b) => text.push(b),
            None => {
                let (offset, byte) = if code.hex_value(hi).is_none() {
                    (2 * i, hi)
                } else {
                    (2 * i + 1, lo)
                };
                return Err(ReceiveError::TextForm(TextForm::NotHex { offset, byte }));
            }
        }
    }
    Ok(text)
}

/// Position of `needle` in `hay` (an empty needle is never found).
fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    if needle.is_empty() || hay.len() < needle.len() {
        return None;
    }
    hay.windows(needle.len()).position(|w| w == needle)
}

#[cfg(test)]
pub(crate) mod tests;
