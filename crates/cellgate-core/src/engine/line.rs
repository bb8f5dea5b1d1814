//! What a serial line is, as sans-IO code sees it: character framing ([`LineSettings`]), the
//! modem lines of the FANUC remote buffer (§3.2, §3.3) and the Fuji FFU120B (§2-2), and the
//! character errors a receiving UART reports (§4.6 line errors).
//!
//! Plain data: the transports carry these, the engines read them.

use std::fmt;
use std::time::Duration;

use serde::{Deserialize, Serialize};

/// Data bits per character (FANUC §3.1, Fuji §4-3 item 5). Written `8` or `"8"`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(try_from = "NumberOrText")]
pub enum DataBits {
    /// 7 data bits.
    #[serde(rename = "7")]
    Seven,
    /// 8 data bits, the default.
    #[serde(rename = "8")]
    #[default]
    Eight,
}

/// Parity bit (FANUC §3.1: even when present; Fuji §4-3 item 6: none, odd or even).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Parity {
    /// No parity bit, the default.
    #[default]
    None,
    /// Odd parity.
    Odd,
    /// Even parity.
    Even,
}

/// Stop bits (Fuji §4-3 item 7 allows 1.5). Written `2`, `1.5` or `"2"`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(try_from = "NumberOrText")]
pub enum StopBits {
    /// 1 stop bit.
    #[serde(rename = "1")]
    One,
    /// 1.5 stop bits (Fuji §4-3 item 7).
    #[serde(rename = "1.5")]
    OnePointFive,
    /// 2 stop bits, the default.
    #[serde(rename = "2")]
    #[default]
    Two,
}

/// A setting people write either as a number or as text (`data_bits = 8`, `stop_bits = "1.5"`).
#[derive(Deserialize)]
#[serde(untagged)]
enum NumberOrText {
    Int(i64),
    Float(f64),
    Text(String),
}

impl NumberOrText {
    fn text(self) -> String {
        match self {
            NumberOrText::Int(i) => i.to_string(),
            NumberOrText::Float(f) => f.to_string(),
            NumberOrText::Text(t) => t,
        }
    }
}

impl TryFrom<NumberOrText> for DataBits {
    type Error = String;
    fn try_from(v: NumberOrText) -> Result<Self, String> {
        match v.text().as_str() {
            "7" => Ok(DataBits::Seven),
            "8" => Ok(DataBits::Eight),
            other => Err(format!("data bits {other}: must be 7 or 8")),
        }
    }
}

impl TryFrom<NumberOrText> for StopBits {
    type Error = String;
    fn try_from(v: NumberOrText) -> Result<Self, String> {
        match v.text().as_str() {
            "1" => Ok(StopBits::One),
            "1.5" => Ok(StopBits::OnePointFive),
            "2" => Ok(StopBits::Two),
            other => Err(format!("stop bits {other}: must be 1, 1.5 or 2")),
        }
    }
}

/// Hardware flow control on the serial port itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum FlowControl {
    /// The protocol does its own flow control (DC1/DC3, RS/CS read by the driver).
    #[default]
    None,
    /// RTS/CTS handled by the UART.
    RtsCts,
}

/// How characters are framed on the line: the settings both ends must agree on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LineSettings {
    /// Bits per second; 9600 by default.
    pub baud: u32,
    /// Data bits per character; 8 by default.
    pub data_bits: DataBits,
    /// Parity bit; none by default.
    pub parity: Parity,
    /// Stop bits; 2 by default.
    pub stop_bits: StopBits,
    /// Flow control; none (the protocol's own) by default.
    pub flow_control: FlowControl,
}

impl Default for LineSettings {
    /// 9600 baud, 8 data bits, no parity, 2 stop bits: 11 bit times a character, the framing
    /// the FANUC manual counts with (§9.2 "11 bits/byte").
    fn default() -> Self {
        LineSettings {
            baud: 9600,
            data_bits: DataBits::Eight,
            parity: Parity::None,
            stop_bits: StopBits::Two,
            flow_control: FlowControl::None,
        }
    }
}

impl LineSettings {
    /// The default framing (8 data bits, no parity, 2 stop bits) at `baud`.
    pub fn with_baud(baud: u32) -> Self {
        LineSettings {
            baud,
            ..Self::default()
        }
    }

    /// Bit times one character occupies on the line, doubled so that 1.5 stop bits stay
    /// integral: start bit + data bits + parity bit + stop bits.
    pub fn half_bits_per_char(&self) -> u32 {
        let data = match self.data_bits {
            DataBits::Seven => 7,
            DataBits::Eight => 8,
        };
        let parity = u32::from(self.parity != Parity::None);
        let stop2 = match self.stop_bits {
            StopBits::One => 2,
            StopBits::OnePointFive => 3,
            StopBits::Two => 4,
        };
        2 * (1 + data + parity) + stop2
    }

    /// Bit times per character (10 for 8N1, 11 for 8N2 or 8E1).
    pub fn bits_per_char(&self) -> f64 {
        f64::from(self.half_bits_per_char()) / 2.0
    }

    /// Characters per second the line carries at most.
    pub fn chars_per_sec(&self) -> f64 {
        f64::from(self.baud) / self.bits_per_char()
    }

    /// Time on the line of `n` characters sent back to back, rounded up to the nanosecond.
    /// Computed from the character count (not by adding per-character durations) so that
    /// long transfers do not accumulate rounding drift.
    pub fn time_for_chars(&self, n: u64) -> Duration {
        let half_bits_per_char = u64::from(self.half_bits_per_char());
        let twice_baud = 2 * u64::from(self.baud.max(1));
        // The simulated line calls this per character: stay in u64 while it cannot overflow
        // (runs of up to ~10^8 characters), u128 beyond.
        if let Some(scaled) = n
            .checked_mul(half_bits_per_char)
            .and_then(|hb| hb.checked_mul(1_000_000_000))
        {
            return Duration::from_nanos(scaled.div_ceil(twice_baud));
        }
        let scaled = u128::from(n) * u128::from(half_bits_per_char) * 1_000_000_000;
        let nanos = scaled.div_ceil(u128::from(twice_baud));
        Duration::from_nanos(u64::try_from(nanos).unwrap_or(u64::MAX))
    }

    /// Characters sent back to back that are fully on the line within `elapsed` of the first
    /// one's start bit: the largest `n` with `time_for_chars(n) <= elapsed`.
    pub fn chars_in(&self, elapsed: Duration) -> u64 {
        // time_for_chars(n) = ceil(n * hb * 1e9 / (2 * baud)) <= e  <=>  n <= e * 2 * baud / (hb * 1e9)
        let half_bits_per_char = u64::from(self.half_bits_per_char().max(1));
        let twice_baud = 2 * u64::from(self.baud.max(1));
        let divisor = half_bits_per_char * 1_000_000_000;
        if let Ok(nanos) = u64::try_from(elapsed.as_nanos())
            && let Some(scaled) = nanos.checked_mul(twice_baud)
        {
            return scaled / divisor;
        }
        let n = elapsed.as_nanos() * u128::from(twice_baud) / u128::from(divisor);
        u64::try_from(n).unwrap_or(u64::MAX)
    }

    /// Time on the line of one character.
    pub fn char_time(&self) -> Duration {
        self.time_for_chars(1)
    }

    /// The mask a receiver applies to a character: 7-bit framing drops bit 7.
    pub fn data_mask(&self) -> u8 {
        match self.data_bits {
            DataBits::Seven => 0x7F,
            DataBits::Eight => 0xFF,
        }
    }
}

impl fmt::Display for LineSettings {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let d = match self.data_bits {
            DataBits::Seven => '7',
            DataBits::Eight => '8',
        };
        let p = match self.parity {
            Parity::None => 'N',
            Parity::Odd => 'O',
            Parity::Even => 'E',
        };
        let s = match self.stop_bits {
            StopBits::One => "1",
            StopBits::OnePointFive => "1.5",
            StopBits::Two => "2",
        };
        write!(f, "{} {d}{p}{s}", self.baud)
    }
}

/// The input modem lines as the host sees them (§3.2 signal table).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ModemIn {
    /// DR / DSR (RS-422: RR): the peer is ready. Off during transmission is an alarm (SR0855).
    pub dr: bool,
    /// CS / CTS: the peer can receive now.
    pub cs: bool,
    /// CD: carrier detect (RS-232-C only; wired to ER on the board side).
    pub cd: bool,
}

impl ModemIn {
    /// All lines on: the manual's wiring for lines that are not used.
    pub const ALL_ON: ModemIn = ModemIn {
        dr: true,
        cs: true,
        cd: true,
    };
}

/// The output modem lines the host drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ModemOut {
    /// ER / DTR (RS-422: TR): the host is ready.
    pub er: bool,
    /// RS / RTS: the host can receive now.
    pub rs: bool,
}

impl ModemOut {
    /// ER and RS both on.
    pub const ALL_ON: ModemOut = ModemOut { er: true, rs: true };
}

/// An error the receiving UART reports about the characters on the line (§4.6 line errors).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error, Serialize)]
#[non_exhaustive]
pub enum LineError {
    /// A parity error in a received character.
    #[error("parity error in a received character")]
    Parity,
    /// A framing error in a received character.
    #[error("framing error in a received character")]
    Framing,
    /// Receiver overrun: characters were lost.
    #[error("receiver overrun: characters were lost")]
    Overrun,
}

#[cfg(test)]
mod tests;
