//! G05 binary input operation (§9; protocol notes 14, 15): the settings, the block codec and
//! the `G05` block that switches a CNC into binary mode.
//!
//! After the NC block `G05` (optionally `N…` before it) ended by LF or `;`, the CNC takes one
//! block from the remote buffer every unit time T (parameter 7618) until a block whose travel
//! and auxiliary bytes are all zero. A block is:
//!
//! ```text
//! [axis 1: 2][axis 2: 2] … [axis N: 2] ([auxiliary word: 4]) [check byte: 1]
//! ```
//!
//! - each axis word is the travel for one unit time in least input increments, high byte
//!   first (protocol notes 14);
//! - the auxiliary word (parameter 7609#3 RAX = 1) is one 32-bit word, high byte first by
//!   default; bit 31 says whether the value is significant (§9.1 (8));
//! - special format (7609#2 RDS = 0): the value's bits sit in 15–9 and 7–1 (and 30–25, 23–17
//!   for the auxiliary word); bits 0, 8, 16 and 24 are zero, so every byte is even and no CR
//!   (0Dh) or ETX (03h) can occur: Protocol A requires it (§9.1 NOTE);
//! - general format (RDS = 1): plain two's complement;
//! - check byte: the lower 8 bits of the sum of all the other bytes (§9.1 (9)); a wrong one is
//!   SR0890 CHECK SUM ERROR (G05) on the CNC (§11).
//!
//! Everything here is sans-IO and allocation-free per block: blocks are encoded into a
//! caller's `Vec<u8>` and decoded into a fixed-size [`Block`].

use std::fmt;
use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::Protocol;

/// Most axes a block may carry. Parameter 7635 ranges from 0 to the CNC's number of
/// controlled axes (§10.3), which the manual does not bound; 32 covers every CNC it speaks of
/// ("11 or more controlled axes", §9.3 10). [`G05Format::validate_for`] checks a CNC's own.
pub const MAX_AXES: u8 = 32;

/// Longest block: 2·[`MAX_AXES`] + 4 + 1 bytes.
pub const MAX_BLOCK_LEN: usize = 2 * MAX_AXES as usize + 5;

/// Bytes of the auxiliary word (§9.1 (6)).
pub const AUX_LEN: usize = 4;

/// Bit 31 of the auxiliary word: the value is significant (§9.1 (8)).
pub const AUX_SIGNIFICANT: u32 = 1 << 31;

/// Parameter 7618 TM2..TM0: the unit time T in which the CNC takes one block (§9.1 (2),
/// §10.3). Only the five times the parameter offers can be held. Written as milliseconds
/// (`unit_time_ms = 8`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(try_from = "u32", into = "u32")]
pub enum UnitTime {
    /// TM2..TM0 = 100.
    Ms1,
    /// TM2..TM0 = 001.
    Ms2,
    /// TM2..TM0 = 010.
    Ms4,
    /// TM2..TM0 = 000: the parameter's zero value.
    #[default]
    Ms8,
    /// TM2..TM0 = 011.
    Ms16,
}

/// A unit time parameter 7618 cannot set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("G05 unit time {ms} ms: parameter 7618 sets 1, 2, 4, 8 or 16 ms (§10.3)")]
pub struct UnitTimeError {
    /// The unit time given, ms.
    pub ms: u32,
}

impl UnitTime {
    /// Every unit time parameter 7618 sets, shortest first.
    pub const ALL: [UnitTime; 5] = [
        UnitTime::Ms1,
        UnitTime::Ms2,
        UnitTime::Ms4,
        UnitTime::Ms8,
        UnitTime::Ms16,
    ];

    /// The unit time in milliseconds.
    pub const fn ms(self) -> u32 {
        match self {
            UnitTime::Ms1 => 1,
            UnitTime::Ms2 => 2,
            UnitTime::Ms4 => 4,
            UnitTime::Ms8 => 8,
            UnitTime::Ms16 => 16,
        }
    }

    /// The unit time of `ms` milliseconds, if parameter 7618 can set it.
    pub const fn from_ms(ms: u32) -> Option<UnitTime> {
        match ms {
            1 => Some(UnitTime::Ms1),
            2 => Some(UnitTime::Ms2),
            4 => Some(UnitTime::Ms4),
            8 => Some(UnitTime::Ms8),
            16 => Some(UnitTime::Ms16),
            _ => None,
        }
    }

    /// The unit time as a duration.
    pub const fn duration(self) -> Duration {
        Duration::from_millis(self.ms() as u64)
    }

    /// Bits 2..0 (TM2, TM1, TM0) of parameter 7618 (§10.3 table).
    pub const fn param_7618(self) -> u8 {
        match self {
            UnitTime::Ms1 => 0b100,
            UnitTime::Ms2 => 0b001,
            UnitTime::Ms4 => 0b010,
            UnitTime::Ms8 => 0b000,
            UnitTime::Ms16 => 0b011,
        }
    }

    /// The unit time bits 2..0 of parameter 7618 select; the other bits are ignored. `None`
    /// for the three combinations the table leaves out.
    pub const fn from_param_7618(bits: u8) -> Option<UnitTime> {
        match bits & 0b111 {
            0b100 => Some(UnitTime::Ms1),
            0b001 => Some(UnitTime::Ms2),
            0b010 => Some(UnitTime::Ms4),
            0b000 => Some(UnitTime::Ms8),
            0b011 => Some(UnitTime::Ms16),
            _ => None,
        }
    }
}

impl TryFrom<u32> for UnitTime {
    type Error = UnitTimeError;
    fn try_from(ms: u32) -> Result<Self, Self::Error> {
        UnitTime::from_ms(ms).ok_or(UnitTimeError { ms })
    }
}

impl From<UnitTime> for u32 {
    fn from(t: UnitTime) -> u32 {
        t.ms()
    }
}

impl fmt::Display for UnitTime {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ms", self.ms())
    }
}

/// Parameter 7609#2 RDS: how travels and the auxiliary word are written (§9.1 (5), (8)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DataFormat {
    /// RDS = 0: value bits in 15–9 and 7–1 (30–25, 23–17 too for the auxiliary word); every
    /// byte even. Required by Protocol A (§9.1 NOTE).
    #[default]
    Special,
    /// RDS = 1: plain two's complement.
    General,
}

impl DataFormat {
    /// The value of parameter 7609#2 RDS.
    pub const fn rds(self) -> bool {
        matches!(self, DataFormat::General)
    }

    /// Least and greatest travel an axis word holds: 14 value bits in the special format,
    /// 16 in the general one (§9.1 (5)).
    pub const fn travel_range(self) -> (i32, i32) {
        match self {
            DataFormat::Special => (-8192, 8191),
            DataFormat::General => (-32768, 32767),
        }
    }

    /// Greatest auxiliary value: 27 value bits (30–25, 23–17, 15–9, 7–1) in the special
    /// format, 31 (30–0) in the general one (§9.1 (8)).
    pub const fn aux_max(self) -> u32 {
        match self {
            DataFormat::Special => (1 << 27) - 1,
            DataFormat::General => (1 << 31) - 1,
        }
    }

    /// The name the cell file uses (`special`, `general`).
    pub const fn name(self) -> &'static str {
        match self {
            DataFormat::Special => "special",
            DataFormat::General => "general",
        }
    }
}

impl fmt::Display for DataFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} format (7609#2 RDS = {})",
            self.name(),
            u8::from(self.rds())
        )
    }
}

/// Parameters 7609#3 RAX and 2034: whether blocks carry an auxiliary word, and which
/// auxiliary function it commands (§9.1 (6), (7)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AuxFunction {
    /// RAX = 0: no auxiliary word; blocks are 2·N + 1 bytes.
    #[default]
    None,
    /// RAX = 1, 2034 = 0: second auxiliary function (B).
    Second,
    /// RAX = 1, 2034 = 1: miscellaneous function (M).
    M,
    /// RAX = 1, 2034 = 2: spindle speed function (S).
    S,
    /// RAX = 1, 2034 = 3: tool function (T).
    T,
}

impl AuxFunction {
    /// The value of parameter 7609#3 RAX.
    pub const fn rax(self) -> bool {
        !matches!(self, AuxFunction::None)
    }

    /// The value of parameter 2034, when the auxiliary word is used.
    pub const fn param_2034(self) -> Option<u8> {
        match self {
            AuxFunction::None => None,
            AuxFunction::Second => Some(0),
            AuxFunction::M => Some(1),
            AuxFunction::S => Some(2),
            AuxFunction::T => Some(3),
        }
    }

    /// The name the cell file uses (`none`, `second`, `m`, `s`, `t`).
    pub const fn name(self) -> &'static str {
        match self {
            AuxFunction::None => "none",
            AuxFunction::Second => "second",
            AuxFunction::M => "m",
            AuxFunction::S => "s",
            AuxFunction::T => "t",
        }
    }
}

/// Order of the two 16-bit halves of the auxiliary word on the line. Each half travels high
/// byte first either way (protocol notes 14).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AuxOrder {
    /// Bits 31–16 first: the word high byte first (protocol notes 14).
    #[default]
    HighFirst,
    /// Bits 15–0 first, for machines that read the manual's figure (bits 15–0 printed above
    /// bits 31–16) that way.
    LowFirst,
}

/// The G05 settings of a CNC: parameters 7635, 7609#2, 7609#3, 2034 and 7618 (§10.3), and
/// the order of the auxiliary word's halves (protocol notes 14). In a cell file they are keys
/// of a machine's `[machines.g05]` table, by these names
/// ([`G05Config`](crate::config::G05Config)); all but `axes` may be left out, for their
/// defaults (as [`G05Format::new`]). Serialized by the same names (the simulator's
/// `listening` line).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub struct G05Format {
    /// Parameter 7635: the axes in a block, the first N controlled axes (1..=[`MAX_AXES`]).
    pub axes: u8,
    /// Parameter 7609#2 RDS: how travels and the auxiliary word are written.
    pub data_format: DataFormat,
    /// Parameters 7609#3 RAX and 2034: the auxiliary word and its function.
    pub aux: AuxFunction,
    /// Parameter 7618: the unit time T, one block per T: 1, 2, 4, 8 or 16 ms.
    pub unit_time_ms: UnitTime,
    /// Order of the auxiliary word's halves on the line (protocol notes 14).
    pub aux_order: AuxOrder,
}

/// One problem of a [`G05Format`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum G05FormatError {
    /// `axes` is 0 or above [`MAX_AXES`] (§9.1 (1), §10.3).
    #[error("G05 axes = {axes}: parameter 7635 must be 1 to {max} (§9.1 (1), §10.3)")]
    Axes {
        /// The axes given.
        axes: u8,
        /// The most axes a block may carry ([`MAX_AXES`]).
        max: u8,
    },
    /// More axes than the CNC controls (parameter 7635, §10.3).
    #[error(
        "G05 axes = {axes}: more than the CNC's {controlled} controlled axes (parameter 7635, §10.3)"
    )]
    MoreThanControlled {
        /// The axes given.
        axes: u8,
        /// The CNC's controlled axes.
        controlled: u8,
    },
    /// The general format on a Protocol A family link, which requires the special one (§9.1 NOTE).
    #[error(
        "G05 general format with {}: Protocol A requires the special format (7609#2 RDS = 0, §9.1 NOTE)",
        .protocol.name()
    )]
    GeneralWithProtocolA {
        /// The link's protocol.
        protocol: Protocol,
    },
}

/// A [`G05Format`] that cannot be used, with every problem it has.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{}", join(.errors))]
pub struct InvalidG05Format {
    /// Every problem found, at least one.
    pub errors: Vec<G05FormatError>,
}

fn join(errors: &[G05FormatError]) -> String {
    errors
        .iter()
        .map(ToString::to_string)
        .collect::<Vec<_>>()
        .join("; ")
}

impl G05Format {
    /// `axes` axes and the defaults: special format, no auxiliary word, 8 ms (the parameters
    /// at zero), the high half first.
    pub fn new(axes: u8) -> Self {
        G05Format {
            axes,
            data_format: DataFormat::default(),
            aux: AuxFunction::default(),
            unit_time_ms: UnitTime::default(),
            aux_order: AuxOrder::default(),
        }
    }

    /// Bytes of a block: 2·N + 1, or 2·N + 5 with the auxiliary word (§9.1 (6)).
    pub const fn block_len(&self) -> usize {
        2 * self.axes as usize + self.aux_len() + 1
    }

    /// Bytes of the auxiliary word in a block: 4 or 0.
    pub const fn aux_len(&self) -> usize {
        if self.aux.rax() { AUX_LEN } else { 0 }
    }

    /// Parameter 7609 with RDS (#2) and RAX (#3) set as this format says, other bits 0.
    pub const fn param_7609(&self) -> u8 {
        (self.data_format.rds() as u8) << 2 | (self.aux.rax() as u8) << 3
    }

    /// Every problem of the format on its own.
    pub fn validate(&self) -> Vec<G05FormatError> {
        let mut errors = Vec::new();
        if self.axes == 0 || self.axes > MAX_AXES {
            errors.push(G05FormatError::Axes {
                axes: self.axes,
                max: MAX_AXES,
            });
        }
        errors
    }

    /// Every problem of the format on a remote buffer speaking `protocol` in front of a CNC
    /// with `controlled_axes` (when known).
    pub fn validate_for(
        &self,
        protocol: Protocol,
        controlled_axes: Option<u8>,
    ) -> Vec<G05FormatError> {
        let mut errors = self.validate();
        if let Some(controlled) = controlled_axes
            && self.axes > controlled
        {
            errors.push(G05FormatError::MoreThanControlled {
                axes: self.axes,
                controlled,
            });
        }
        if protocol.is_a_family() && self.data_format == DataFormat::General {
            errors.push(G05FormatError::GeneralWithProtocolA { protocol });
        }
        errors
    }

    fn checked(&self) -> Result<(), InvalidG05Format> {
        let errors = self.validate();
        if errors.is_empty() {
            Ok(())
        } else {
            Err(InvalidG05Format { errors })
        }
    }

    /// Appends block number `block` (for errors) to `out`: one travel per axis in least input
    /// increments, and the auxiliary word when the format has one (`None`: a word of zeros,
    /// not significant). On error `out` is left as it was.
    ///
    /// A block whose bytes would all be zero is refused ([`G05EncodeError::ZeroBlock`]): the
    /// CNC would take it for the end block (§9.1). Use [`G05Format::encode_end`] for that.
    pub fn encode_block(
        &self,
        block: u64,
        travels: &[i32],
        aux: Option<AuxWord>,
        out: &mut Vec<u8>,
    ) -> Result<(), G05EncodeError> {
        if travels.len() != usize::from(self.axes) {
            return Err(G05EncodeError::AxisCount {
                block,
                given: travels.len(),
                axes: self.axes,
            });
        }
        let format = self.data_format;
        let (min, max) = format.travel_range();
        if let Some((i, &value)) = travels
            .iter()
            .enumerate()
            .find(|&(_, &v)| v < min || v > max)
        {
            return Err(G05EncodeError::Travel {
                block,
                axis: i + 1,
                value,
                min,
                max,
                format,
            });
        }
        let aux_word = match (self.aux.rax(), aux) {
            (false, Some(_)) => return Err(G05EncodeError::AuxOff { block }),
            (false, None) => None,
            (true, None) => Some(0),
            (true, Some(word)) => Some(aux_word(format, word).ok_or(G05EncodeError::AuxValue {
                block,
                value: word.value,
                max: format.aux_max(),
                format,
            })?),
        };
        if travels.iter().all(|&v| v == 0) && aux_word.unwrap_or(0) == 0 {
            return Err(G05EncodeError::ZeroBlock { block });
        }
        let start = out.len();
        out.reserve(self.block_len());
        for &value in travels {
            // In range: checked above.
            let word = travel_word(format, value).unwrap_or(0);
            out.extend_from_slice(&word.to_be_bytes());
        }
        if let Some(word) = aux_word {
            out.extend_from_slice(&aux_bytes(self.aux_order, word));
        }
        let ck = check_byte(out.get(start..).unwrap_or(&[]));
        out.push(ck);
        Ok(())
    }

    /// Appends the end block: every travel and auxiliary byte zero, and so the check byte
    /// (§9.1: "Binary input operation off").
    pub fn encode_end(&self, out: &mut Vec<u8>) {
        out.resize(out.len() + self.block_len(), 0);
    }
}

/// Baud rate the line must reach at least for the CNC never to wait for a block (§9.2):
/// (2·N + n) bytes × `bits_per_char` / T × 1000, rounded up. The manual counts 11 bits a
/// character (protocol notes 2); pass the line's, e.g.
/// [`LineSettings::bits_per_char`](crate::engine::LineSettings::bits_per_char).
pub fn required_baud(format: &G05Format, bits_per_char: f64) -> u32 {
    let bytes = format.block_len() as f64;
    // T is a power of two: the division is exact.
    let bps = bytes * bits_per_char * 1000.0 / f64::from(format.unit_time_ms.ms());
    // A float-to-int `as` saturates (NaN → 0): never panics.
    bps.ceil() as u32
}

/// The auxiliary word of a block (§9.1 (8)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize)]
pub struct AuxWord {
    /// The value for the auxiliary function, unsigned (M, S, T and B codes): at most
    /// [`DataFormat::aux_max`].
    pub value: u32,
    /// Bit 31: the CNC sends the value to the auxiliary function only when set.
    pub significant: bool,
}

impl AuxWord {
    /// A significant value.
    pub const fn significant(value: u32) -> Self {
        AuxWord {
            value,
            significant: true,
        }
    }
}

/// The 16-bit word for `value` in `format`, or `None` outside [`DataFormat::travel_range`].
/// Special: value bits 13–7 into word bits 15–9, 6–0 into 7–1 (700 → 0A78h); general: two's
/// complement (700 → 02BCh).
pub fn travel_word(format: DataFormat, value: i32) -> Option<u16> {
    let (min, max) = format.travel_range();
    if value < min || value > max {
        return None;
    }
    // Two's complement in 16 bits; the special format keeps its low 14.
    let v = value as u16;
    Some(match format {
        DataFormat::Special => ((v >> 7) & 0x7F) << 9 | (v & 0x7F) << 1,
        DataFormat::General => v,
    })
}

/// The travel a 16-bit word holds. Special format: bits 0 and 8 are ignored (the CNC reads
/// only the marked bits, §9.1 (5)).
pub fn travel_value(format: DataFormat, word: u16) -> i16 {
    match format {
        DataFormat::Special => {
            let v = ((word >> 9) & 0x7F) << 7 | ((word >> 1) & 0x7F);
            // Sign-extend the 14-bit value.
            ((v << 2) as i16) >> 2
        }
        DataFormat::General => word as i16,
    }
}

/// The 32-bit auxiliary word for `aux`, or `None` when its value exceeds
/// [`DataFormat::aux_max`].
pub fn aux_word(format: DataFormat, aux: AuxWord) -> Option<u32> {
    if aux.value > format.aux_max() {
        return None;
    }
    let v = aux.value;
    let bits = match format {
        DataFormat::Special => {
            (v >> 21 & 0x3F) << 25 | (v >> 14 & 0x7F) << 17 | (v >> 7 & 0x7F) << 9 | (v & 0x7F) << 1
        }
        DataFormat::General => v,
    };
    Some(if aux.significant {
        bits | AUX_SIGNIFICANT
    } else {
        bits
    })
}

/// The auxiliary word a 32-bit word holds. Special format: bits 0, 8, 16 and 24 are ignored.
pub fn aux_value(format: DataFormat, word: u32) -> AuxWord {
    let value = match format {
        DataFormat::Special => {
            (word >> 25 & 0x3F) << 21
                | (word >> 17 & 0x7F) << 14
                | (word >> 9 & 0x7F) << 7
                | (word >> 1 & 0x7F)
        }
        DataFormat::General => word & !AUX_SIGNIFICANT,
    };
    AuxWord {
        value,
        significant: word & AUX_SIGNIFICANT != 0,
    }
}

/// The four bytes of the auxiliary word on the line (protocol notes 14).
pub fn aux_bytes(order: AuxOrder, word: u32) -> [u8; 4] {
    let [a, b, c, d] = word.to_be_bytes();
    match order {
        AuxOrder::HighFirst => [a, b, c, d],
        AuxOrder::LowFirst => [c, d, a, b],
    }
}

/// The auxiliary word from its four bytes on the line.
pub fn aux_from_bytes(order: AuxOrder, bytes: [u8; 4]) -> u32 {
    let [a, b, c, d] = bytes;
    match order {
        AuxOrder::HighFirst => u32::from_be_bytes([a, b, c, d]),
        AuxOrder::LowFirst => u32::from_be_bytes([c, d, a, b]),
    }
}

/// The check byte of a block's other bytes: the lower 8 bits of their sum (§9.1 (9)).
pub fn check_byte(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0u8, |s, &b| s.wrapping_add(b))
}

/// Whether `block` (a whole block, check byte included) is the end block: every byte zero.
/// Its check byte is zero too; a block of zero travels with another check byte is an SR0890.
pub fn is_end_block(block: &[u8]) -> bool {
    block.iter().all(|&b| b == 0)
}

/// Why a block was not encoded (§9.1).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum G05EncodeError {
    /// Not one travel per axis of the format (§9.1 (1)).
    #[error(
        "G05 block {block}: {given} travel(s) given, the format has {axes} axes (parameter 7635, §9.1 (1))"
    )]
    AxisCount {
        /// The block's number (1 = the first block after `G05`).
        block: u64,
        /// Travels given.
        given: usize,
        /// Axes of the format (parameter 7635).
        axes: u8,
    },
    /// A travel the format cannot hold (§9.1 (5)).
    #[error(
        "G05 block {block}, axis {axis}: travel {value} is outside {min}..={max} of the {format} (§9.1 (5))"
    )]
    Travel {
        /// The block's number (1 = the first block after `G05`).
        block: u64,
        /// 1-based, as the controlled axes are numbered.
        axis: usize,
        /// The travel given, least input increments.
        value: i32,
        /// Least travel the format holds.
        min: i32,
        /// Greatest travel the format holds.
        max: i32,
        /// The data format.
        format: DataFormat,
    },
    /// An auxiliary value the format cannot hold (§9.1 (8)).
    #[error(
        "G05 block {block}: auxiliary value {value} is above {max}, the most the {format} holds (§9.1 (8))"
    )]
    AuxValue {
        /// The block's number (1 = the first block after `G05`).
        block: u64,
        /// The auxiliary value given.
        value: u32,
        /// Greatest auxiliary value the format holds.
        max: u32,
        /// The data format.
        format: DataFormat,
    },
    /// An auxiliary word for a format without one (7609#3 RAX = 0, §9.1 (6)).
    #[error(
        "G05 block {block}: an auxiliary word was given but the format has none (7609#3 RAX = 0, §9.1 (6))"
    )]
    AuxOff {
        /// The block's number (1 = the first block after `G05`).
        block: u64,
    },
    /// Every travel and the auxiliary word zero: the CNC would take it for the end block (§9.1).
    #[error(
        "G05 block {block}: every travel and the auxiliary word are zero; the CNC would take it for the end block and leave binary input operation (§9.1)"
    )]
    ZeroBlock {
        /// The block's number (1 = the first block after `G05`).
        block: u64,
    },
}

/// Numbers blocks as it encodes them, for errors that name the block (1 = the first block
/// after `G05`).
#[derive(Debug, Clone)]
pub struct G05Encoder {
    format: G05Format,
    blocks: u64,
}

impl G05Encoder {
    /// An encoder for `format`, at block 1; fails when the format has a problem of its own.
    pub fn new(format: G05Format) -> Result<Self, InvalidG05Format> {
        format.checked()?;
        Ok(G05Encoder { format, blocks: 0 })
    }

    /// The format blocks are encoded in.
    pub fn format(&self) -> &G05Format {
        &self.format
    }

    /// Blocks encoded so far, the end block included.
    pub fn blocks(&self) -> u64 {
        self.blocks
    }

    /// Appends the next block; see [`G05Format::encode_block`]. A refused block keeps its
    /// number for the next try.
    pub fn block(
        &mut self,
        travels: &[i32],
        aux: Option<AuxWord>,
        out: &mut Vec<u8>,
    ) -> Result<(), G05EncodeError> {
        let no = self.blocks.saturating_add(1);
        self.format.encode_block(no, travels, aux, out)?;
        self.blocks = no;
        Ok(())
    }

    /// Appends the end block, and starts numbering again for the next `G05`.
    pub fn end(&mut self, out: &mut Vec<u8>) {
        self.format.encode_end(out);
        self.blocks = 0;
    }
}

/// A decoded block.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct Block {
    number: u64,
    axes: u8,
    travels: [i16; MAX_AXES as usize],
    aux: Option<AuxWord>,
    end: bool,
}

impl Block {
    /// 1 for the first block the decoder read (after `G05`, or after [`BlockDecoder::clear`]).
    pub fn number(&self) -> u64 {
        self.number
    }

    /// The travel of each axis for one unit time, least input increments.
    pub fn travels(&self) -> &[i16] {
        self.travels
            .get(..usize::from(self.axes))
            .unwrap_or(&self.travels)
    }

    /// The auxiliary word, when the format has one.
    pub fn aux(&self) -> Option<AuxWord> {
        self.aux
    }

    /// Whether this is the end block: binary input operation ends (§9.1).
    pub fn is_end(&self) -> bool {
        self.end
    }
}

impl fmt::Debug for Block {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut d = f.debug_struct("Block");
        d.field("number", &self.number)
            .field("travels", &self.travels());
        if let Some(aux) = self.aux {
            d.field("aux", &aux);
        }
        d.field("end", &self.end).finish()
    }
}

/// A block the CNC refuses.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum G05DecodeError {
    /// The check byte is not the sum of the other bytes (§9.1 (9)): SR0890 on the CNC.
    #[error(
        "G05 block {block}: check byte {received:02X}h, but the other bytes sum to {computed:02X}h (§9.1 (9)): SR0890 CHECK SUM ERROR (G05) (§11)"
    )]
    CheckByte {
        /// The block's number (1 = the first block the decoder read).
        block: u64,
        /// The check byte received.
        received: u8,
        /// The lower 8 bits of the sum of the other bytes.
        computed: u8,
    },
}

/// Splits a byte stream in binary mode into blocks, whatever pieces the bytes come in. Holds
/// at most one block ([`MAX_BLOCK_LEN`] bytes) and allocates nothing.
///
/// After a check-byte error it goes on with the next block: the CNC stops there with SR0890,
/// but a decoder is also used to read logs and fuzz input.
#[derive(Debug, Clone)]
pub struct BlockDecoder {
    format: G05Format,
    len: usize,
    buf: [u8; MAX_BLOCK_LEN],
    filled: usize,
    blocks: u64,
}

impl BlockDecoder {
    /// A decoder for `format`, at block 1; fails when the format has a problem of its own.
    pub fn new(format: G05Format) -> Result<Self, InvalidG05Format> {
        format.checked()?;
        Ok(BlockDecoder {
            format,
            len: format.block_len().min(MAX_BLOCK_LEN),
            buf: [0; MAX_BLOCK_LEN],
            filled: 0,
            blocks: 0,
        })
    }

    /// The format blocks are decoded in.
    pub fn format(&self) -> &G05Format {
        &self.format
    }

    /// Bytes of a block.
    pub fn block_len(&self) -> usize {
        self.len
    }

    /// Bytes of a partial block held.
    pub fn buffered(&self) -> usize {
        self.filled
    }

    /// Blocks read so far (end block and refused blocks included).
    pub fn blocks(&self) -> u64 {
        self.blocks
    }

    /// Forgets a partial block and numbers blocks from 1 again (a new `G05`).
    pub fn clear(&mut self) {
        self.filled = 0;
        self.blocks = 0;
    }

    /// Takes one byte; returns the block it completes.
    pub fn push(&mut self, b: u8) -> Option<Result<Block, G05DecodeError>> {
        if let Some(slot) = self.buf.get_mut(self.filled) {
            *slot = b;
        }
        self.filled += 1;
        if self.filled < self.len {
            return None;
        }
        self.filled = 0;
        self.blocks = self.blocks.saturating_add(1);
        Some(self.block())
    }

    /// Takes `bytes`; the iterator yields the blocks they complete, in order. Bytes the
    /// iterator was not driven over are not taken.
    pub fn decode<'a>(&'a mut self, bytes: &'a [u8]) -> Decode<'a> {
        Decode {
            decoder: self,
            bytes: bytes.iter(),
        }
    }

    /// The whole block in `buf`.
    fn block(&self) -> Result<Block, G05DecodeError> {
        let bytes = self.buf.get(..self.len).unwrap_or(&self.buf);
        let (body, ck) = match bytes.split_last() {
            Some((&ck, body)) => (body, ck),
            None => (bytes, 0),
        };
        let computed = check_byte(body);
        if computed != ck {
            return Err(G05DecodeError::CheckByte {
                block: self.blocks,
                received: ck,
                computed,
            });
        }
        let n = usize::from(self.format.axes).min(usize::from(MAX_AXES));
        let (words, rest) = body.split_at(body.len().min(2 * n));
        let mut travels = [0i16; MAX_AXES as usize];
        for (t, w) in travels.iter_mut().zip(words.chunks_exact(2)) {
            if let [hi, lo] = *w {
                *t = travel_value(self.format.data_format, u16::from_be_bytes([hi, lo]));
            }
        }
        let aux = match (self.format.aux.rax(), rest) {
            (true, &[a, b, c, d]) => Some(aux_value(
                self.format.data_format,
                aux_from_bytes(self.format.aux_order, [a, b, c, d]),
            )),
            _ => None,
        };
        Ok(Block {
            number: self.blocks,
            axes: n as u8,
            travels,
            aux,
            end: is_end_block(bytes),
        })
    }
}

/// The blocks completed by bytes given to [`BlockDecoder::decode`].
#[derive(Debug)]
pub struct Decode<'a> {
    decoder: &'a mut BlockDecoder,
    bytes: std::slice::Iter<'a, u8>,
}

impl Iterator for Decode<'_> {
    type Item = Result<Block, G05DecodeError>;
    fn next(&mut self) -> Option<Self::Item> {
        for &b in self.bytes.by_ref() {
            if let Some(block) = self.decoder.push(b) {
                return Some(block);
            }
        }
        None
    }
}

/// Finds the NC block that starts binary input operation in the text a CNC reads: `G05`,
/// optionally after a sequence number `N…`, ended by LF or `;` (protocol notes 15). The binary
/// data starts with the byte after that end of block.
///
/// Parity bits are stripped (ISO); CR, blanks, tabs and comments `( … )` are ignored, as the
/// CNC ignores them; leading zeros of the G code are optional (`G5`). Any other word in the
/// block (`G05 P10000` is another function) makes it an ordinary block. `%` starts afresh.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct G05Entry {
    state: EntryState,
    /// Inside `( … )`.
    comment: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
enum EntryState {
    /// At the start of a block.
    #[default]
    Start,
    /// `N` and digits read.
    Seq { digits: bool },
    /// `G` read, then digits worth `value` (saturating).
    G { value: u8, digits: bool },
    /// Anything else: not the G05 block.
    Other,
}

impl G05Entry {
    /// Reads one byte of NC text; true when it ends the `G05` block.
    pub fn feed(&mut self, b: u8) -> bool {
        self.feed_char(b & 0x7F)
    }

    fn feed_char(&mut self, c: u8) -> bool {
        // A comment ends at `)`, or with its block.
        if self.comment && !matches!(c, b'\n' | b';' | b'%') {
            if c == b')' {
                self.comment = false;
            }
            return false;
        }
        match c {
            b'\n' | b';' => {
                let found = matches!(
                    self.state,
                    EntryState::G {
                        value: 5,
                        digits: true
                    }
                );
                *self = G05Entry::default();
                found
            }
            b'%' => {
                *self = G05Entry::default();
                false
            }
            0x00 | 0x7F | b'\r' | b' ' | b'\t' => false,
            b'(' => {
                self.comment = true;
                false
            }
            _ => {
                self.state = match (self.state, c) {
                    (EntryState::Start, b'N') => EntryState::Seq { digits: false },
                    (EntryState::Seq { .. }, b'0'..=b'9') => EntryState::Seq { digits: true },
                    (EntryState::Start | EntryState::Seq { digits: true }, b'G') => EntryState::G {
                        value: 0,
                        digits: false,
                    },
                    (EntryState::G { value, .. }, b'0'..=b'9') => EntryState::G {
                        value: value.saturating_mul(10).saturating_add(c - b'0'),
                        digits: true,
                    },
                    _ => EntryState::Other,
                };
                false
            }
        }
    }

    /// Starts afresh, at the start of a block.
    pub fn reset(&mut self) {
        *self = G05Entry::default();
    }
}

pub mod stream;

#[cfg(test)]
mod tests;
