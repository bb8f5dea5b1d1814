//! The SAT / SET data part (§4.4.2) and the remote-buffer parameters Nb..Tw (§4.5).
//!
//! Numeric fields travel as four upper-case hex digits. A SAT may be shorter than the 72
//! bytes the table allows (56 is common): fields it does not reach decode as `None`
//! (protocol notes 4). Bytes 17–20 hold Ne although the manual's table labels them "No".

use std::fmt;

use serde::{Deserialize, Serialize};

/// The remote-buffer parameters that SET can change (§4.5). Times are in the manual's units.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Minimum free buffer space before the board sends GTD, bytes (1 + No ..= 4000).
    pub nb: u16,
    /// Maximum overrun on reception, bytes (2..=2000).
    pub no: u16,
    /// Retry count on a transmission error (0..=100).
    pub ne: u16,
    /// Polling interval of SAT, seconds (1..=99).
    pub tp: u16,
    /// Response time-out, seconds (1..=999).
    pub to: u16,
    /// Minimum interval between transmitted bytes, ms (0..=10, in 2 ms steps).
    pub ti: u16,
    /// Minimum switch time from reception to transmission, ms (0..=100).
    pub tx: u16,
    /// Wait after WAT before the board asks again, seconds (0..=Tp).
    pub tw: u16,
}

impl Default for Params {
    fn default() -> Self {
        Params::POWER_ON
    }
}

/// One parameter outside its §4.5 range.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{name} = {value}: must be within {min}..={max}{why} (§4.5)")]
pub struct ParamRangeError {
    /// The parameter's name as the cell file writes it (`nb`, `no`, ...).
    pub name: &'static str,
    /// The value given.
    pub value: u16,
    /// The smallest value allowed.
    pub min: u16,
    /// The largest value allowed.
    pub max: u16,
    /// Extra words when the bound comes from another parameter, e.g. " (tp)".
    pub why: String,
}

impl Params {
    /// The values on turning on power (§4.5).
    pub const POWER_ON: Params = Params {
        nb: 2000,
        no: 50,
        ne: 10,
        tp: 5,
        to: 20,
        ti: 10,
        tx: 100,
        tw: 5,
    };

    /// Every parameter outside the §4.5 ranges, each with its bounds.
    pub fn validate(&self) -> Vec<ParamRangeError> {
        let mut errors = Vec::new();
        let mut check = |name, value: u16, min: u16, max: u16, why: &str| {
            if value < min || value > max {
                errors.push(ParamRangeError {
                    name,
                    value,
                    min,
                    max,
                    why: why.to_string(),
                });
            }
        };
        // Note 1 of §4.5: 1 + No <= Nb <= 4000.
        check("nb", self.nb, self.no.saturating_add(1), 4000, " (1 + no)");
        check("no", self.no, 2, 2000, "");
        check("ne", self.ne, 0, 100, "");
        check("tp", self.tp, 1, 99, "");
        check("to", self.to, 1, 999, "");
        check("ti", self.ti, 0, 10, "");
        check("tx", self.tx, 0, 100, "");
        check("tw", self.tw, 0, self.tp, &format!(" (tp = {})", self.tp));
        if self.ti % 2 != 0 && self.ti <= 10 {
            errors.push(ParamRangeError {
                name: "ti",
                value: self.ti,
                min: 0,
                max: 10,
                why: " in 2 ms steps".to_string(),
            });
        }
        errors
    }
}

/// Byte 2 of SAT: the status of the remote buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum BufferStatus {
    /// 0: operation preparation not completed.
    NotReady,
    /// 1: reset.
    Reset,
    /// 2: operating.
    Operating,
    /// 3: alarm.
    Alarm,
    /// 4: open line.
    OpenLine,
    /// A digit the manual does not define.
    Other(u8),
}

impl BufferStatus {
    /// The status that the digit of byte 2 stands for.
    pub fn from_digit(d: u8) -> Self {
        match d {
            0 => Self::NotReady,
            1 => Self::Reset,
            2 => Self::Operating,
            3 => Self::Alarm,
            4 => Self::OpenLine,
            other => Self::Other(other),
        }
    }
    /// The digit that stands for this status in byte 2.
    pub fn digit(self) -> u8 {
        match self {
            Self::NotReady => 0,
            Self::Reset => 1,
            Self::Operating => 2,
            Self::Alarm => 3,
            Self::OpenLine => 4,
            Self::Other(d) => d & 0x0F,
        }
    }
}

/// Byte 3 of SAT: why the remote buffer went to alarm status.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum AlarmCause {
    /// 0: NC alarm.
    NcAlarm,
    /// 1: checksum error, retry over.
    ChecksumRetryOver,
    /// 6: unexpected response received (command error).
    CommandError,
    /// A: overrun error, retry over.
    OverrunRetryOver,
    /// A digit the manual does not define.
    Other(u8),
}

impl AlarmCause {
    /// The cause that the digit of byte 3 stands for.
    pub fn from_digit(d: u8) -> Self {
        match d {
            0 => Self::NcAlarm,
            1 => Self::ChecksumRetryOver,
            6 => Self::CommandError,
            0xA => Self::OverrunRetryOver,
            other => Self::Other(other),
        }
    }
    /// The digit that stands for this cause in byte 3.
    pub fn digit(self) -> u8 {
        match self {
            Self::NcAlarm => 0,
            Self::ChecksumRetryOver => 1,
            Self::CommandError => 6,
            Self::OverrunRetryOver => 0xA,
            Self::Other(d) => d & 0x0F,
        }
    }
}

/// The data part of SAT (board → host) and SET (host → board); same layout (§4.4.2 1, 2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct StatusData {
    /// Byte 1: remote (1) or tape (0) operation; in SET, the switching request.
    pub remote: Option<bool>,
    /// Byte 2 (SAT only; SET's byte 2 is ignored by the board).
    pub status: Option<BufferStatus>,
    /// Byte 3 (SAT only).
    pub alarm_cause: Option<AlarmCause>,
    /// Bytes 5–8: bytes stored in the buffer (SAT only).
    pub buffered: Option<u16>,
    /// Bytes 9–40: Nb No Ne Tp To Ti Tx Tw.
    pub params: Option<Params>,
    /// Bytes 41–44: unit of the boring time (bit 2 = P2: 0.1 s).
    pub boring_unit: Option<u16>,
    /// Bytes 45–48: code to be converted in NC data, and the code it becomes (0, 0 = none).
    pub conversion: Option<(u8, u8)>,
    /// Bytes 55–56: Expansion Protocol A packet length n (0 = Protocol A; 1, 2, 4).
    pub packet_n: Option<u8>,
}

/// Why a SAT/SET data part could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum StatusDataError {
    /// A byte of a numeric field is not a hex digit.
    #[error("SAT/SET data part byte {position} is {byte:#04x}, not a hex digit (§4.4.2)")]
    NotHex {
        /// The byte's position in the data part, from 1.
        position: usize,
        /// The byte.
        byte: u8,
    },
    /// The data part is longer than the 72 bytes of the table.
    #[error("SAT/SET data part is {len} bytes, longer than 72 (§4.4.2)")]
    TooLong {
        /// The data part's length, bytes.
        len: usize,
    },
}

/// The length of the data part this crate sends: bytes 1–56, the common length.
pub const STATUS_DATA_LEN: usize = 56;

fn hex_value(position: usize, b: u8) -> Result<u8, StatusDataError> {
    match b {
        b'0'..=b'9' => Ok(b - b'0'),
        b'A'..=b'F' => Ok(b - b'A' + 10),
        // The board writes upper case; accept lower case in data parts rather than fail a poll.
        b'a'..=b'f' => Ok(b - b'a' + 10),
        _ => Err(StatusDataError::NotHex { position, byte: b }),
    }
}

/// Reads `len` hex digits starting at 1-based byte `pos`, if the data part reaches that far.
fn field(data: &[u8], pos: usize, len: usize) -> Result<Option<u16>, StatusDataError> {
    let Some(bytes) = data.get(pos - 1..pos - 1 + len) else {
        return Ok(None);
    };
    let mut v: u16 = 0;
    for (i, &b) in bytes.iter().enumerate() {
        v = (v << 4) | u16::from(hex_value(pos + i, b)?);
    }
    Ok(Some(v))
}

fn put_hex(out: &mut Vec<u8>, v: u16, digits: usize) {
    for i in (0..digits).rev() {
        out.push(crate::engine::hex::DIGITS[usize::from((v >> (4 * i)) & 0xF)]);
    }
}

impl StatusData {
    /// Decodes a SAT or SET data part (parity already stripped). An empty part is all `None`.
    pub fn decode(data: &[u8]) -> Result<Self, StatusDataError> {
        if data.len() > 72 {
            return Err(StatusDataError::TooLong { len: data.len() });
        }
        let digit = |pos| -> Result<Option<u8>, StatusDataError> {
            Ok(field(data, pos, 1)?.map(|v| v as u8))
        };
        let params = match (
            field(data, 9, 4)?,
            field(data, 13, 4)?,
            field(data, 17, 4)?,
            field(data, 21, 4)?,
            field(data, 25, 4)?,
            field(data, 29, 4)?,
            field(data, 33, 4)?,
            field(data, 37, 4)?,
        ) {
            (Some(nb), Some(no), Some(ne), Some(tp), Some(to), Some(ti), Some(tx), Some(tw)) => {
                Some(Params {
                    nb,
                    no,
                    ne,
                    tp,
                    to,
                    ti,
                    tx,
                    tw,
                })
            }
            _ => None,
        };
        let conversion = match (field(data, 45, 2)?, field(data, 47, 2)?) {
            (Some(from), Some(to)) => Some((from as u8, to as u8)),
            _ => None,
        };
        Ok(StatusData {
            remote: digit(1)?.map(|d| d != 0),
            status: digit(2)?.map(BufferStatus::from_digit),
            alarm_cause: digit(3)?.map(AlarmCause::from_digit),
            buffered: field(data, 5, 4)?,
            params,
            boring_unit: field(data, 41, 4)?,
            conversion,
            packet_n: field(data, 55, 2)?.map(|v| v as u8),
        })
    }

    /// Encodes bytes 1–56. Fields that are `None` are written as zeros; byte 4 and the
    /// reserved bytes 49–54 are zeros.
    pub fn encode(&self, out: &mut Vec<u8>) {
        put_hex(out, u16::from(self.remote.unwrap_or(false)), 1);
        put_hex(
            out,
            u16::from(self.status.map_or(0, BufferStatus::digit)),
            1,
        );
        put_hex(
            out,
            u16::from(self.alarm_cause.map_or(0, AlarmCause::digit)),
            1,
        );
        out.push(b'0');
        put_hex(out, self.buffered.unwrap_or(0), 4);
        match &self.params {
            Some(p) => {
                for v in [p.nb, p.no, p.ne, p.tp, p.to, p.ti, p.tx, p.tw] {
                    put_hex(out, v, 4);
                }
            }
            None => out.extend_from_slice(&[b'0'; 32]),
        }
        put_hex(out, self.boring_unit.unwrap_or(0), 4);
        let (from, to) = self.conversion.unwrap_or((0, 0));
        put_hex(out, u16::from(from), 2);
        put_hex(out, u16::from(to), 2);
        out.extend_from_slice(b"000000");
        put_hex(out, u16::from(self.packet_n.unwrap_or(0)), 2);
    }

    /// The encoded data part, bytes 1–56 (see [`StatusData::encode`]).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut v = Vec::with_capacity(STATUS_DATA_LEN);
        self.encode(&mut v);
        v
    }
}

/// Expansion Protocol A packet length: n = 0 (Protocol A), 1, 2 or 4 (§5.2 1).
/// Any other value means 0, as the board treats it (§5.2 note).
pub fn effective_packet_n(n: u8) -> u8 {
    match n {
        1 | 2 | 4 => n,
        _ => 0,
    }
}

impl fmt::Display for Params {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "Nb={} No={} Ne={} Tp={}s To={}s Ti={}ms Tx={}ms Tw={}s",
            self.nb, self.no, self.ne, self.tp, self.to, self.ti, self.tx, self.tw
        )
    }
}

#[cfg(test)]
mod tests;
