//! Protocol A messages (§4.1, §4.2; protocol notes 1, 3).
//!
//! A message on the line is `[checksum 2][command 3][data 0..n][end code 1]`. The checksum is
//! the lower 8 bits of the sum of every byte from the first command byte through the end code,
//! as transmitted, written as two upper-case hex digits, high digit first: `07SYN<CR>`.
//!
//! With the ISO code the checksum, the command, the data part of every command but DAT and
//! the end code carry even parity in bit 7; DAT's data part (NC data) is passed as it is.

use std::fmt;

use super::code::{CR, ETX};
use super::{CodeSystem, EndCode};

/// The commands of §4.4.1.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
pub enum Command {
    /// R: initialise the host. H: initialise the board / "not initialised yet".
    Syn,
    /// Initialisation end (both directions).
    Rdy,
    /// R: CNC reset notice.
    Rst,
    /// H: answer to RST.
    Ars,
    /// R: CNC alarm notice.
    Alm,
    /// H: answer to ALM.
    Aal,
    /// R: remote-buffer status, sent every Tp when idle.
    Sat,
    /// H: answer to SAT, optionally changing parameters.
    Set,
    /// R: request for NC data.
    Gtd,
    /// H: NC data.
    Dat,
    /// H: NC data not ready within To; the board asks again after Tw.
    Wat,
    /// H: no more NC data.
    Eod,
    /// H: clear the board's buffer (answer to SAT).
    Clb,
    /// H: request the DI image (answer to SAT or GTD).
    Rdi,
    /// R: DI image (answer to RDI).
    Sdi,
    /// H: output a DO image (answer to SAT, GTD or SDI).
    Sdo,
    /// R/H: retransmission request, reason in the data part.
    Rty,
}

impl Command {
    /// Every command of §4.4.1.
    pub const ALL: [Command; 17] = [
        Command::Syn,
        Command::Rdy,
        Command::Rst,
        Command::Ars,
        Command::Alm,
        Command::Aal,
        Command::Sat,
        Command::Set,
        Command::Gtd,
        Command::Dat,
        Command::Wat,
        Command::Eod,
        Command::Clb,
        Command::Rdi,
        Command::Sdi,
        Command::Sdo,
        Command::Rty,
    ];

    /// The three letters on the line.
    pub fn name(self) -> &'static [u8; 3] {
        match self {
            Command::Syn => b"SYN",
            Command::Rdy => b"RDY",
            Command::Rst => b"RST",
            Command::Ars => b"ARS",
            Command::Alm => b"ALM",
            Command::Aal => b"AAL",
            Command::Sat => b"SAT",
            Command::Set => b"SET",
            Command::Gtd => b"GTD",
            Command::Dat => b"DAT",
            Command::Wat => b"WAT",
            Command::Eod => b"EOD",
            Command::Clb => b"CLB",
            Command::Rdi => b"RDI",
            Command::Sdi => b"SDI",
            Command::Sdo => b"SDO",
            Command::Rty => b"RTY",
        }
    }

    /// The command whose three-letter name is `name` (parity stripped), if any.
    pub fn from_name(name: &[u8]) -> Option<Command> {
        Command::ALL.into_iter().find(|c| c.name() == name)
    }

    /// Longest data part the command may carry (§4.4.2: 4096 for DAT, 72 for the others).
    pub fn max_data(self) -> usize {
        match self {
            Command::Dat => MAX_DAT_DATA,
            _ => MAX_OTHER_DATA,
        }
    }
}

impl fmt::Display for Command {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // The names are ASCII letters.
        f.write_str(std::str::from_utf8(self.name()).unwrap_or("???"))
    }
}

/// Longest data part of a DAT, bytes (§4.4.2).
pub const MAX_DAT_DATA: usize = 4096;
/// Longest data part of every command but DAT, bytes (§4.4.2).
pub const MAX_OTHER_DATA: usize = 72;
/// Longest message on the line: checksum, command, a full DAT data part, end code.
pub const MAX_FRAME: usize = 2 + 3 + MAX_DAT_DATA + 1;

/// RTY reasons (§4.4.2 6).
pub const RTY_CHECKSUM: u8 = b'1';
/// Overrun error: data received after RS was turned off.
pub const RTY_OVERRUN: u8 = b'3';

/// A Protocol A message. `data` holds 7-bit characters (parity stripped) for every command
/// but DAT, whose NC data is kept exactly as it travels.
#[derive(Clone, PartialEq, Eq)]
pub struct Message {
    /// The command.
    pub command: Command,
    /// The data part; empty when the command carries none.
    pub data: Vec<u8>,
}

impl Message {
    /// A message without a data part.
    pub fn new(command: Command) -> Self {
        Message {
            command,
            data: Vec::new(),
        }
    }

    /// A message with the data part `data`.
    pub fn with_data(command: Command, data: impl Into<Vec<u8>>) -> Self {
        Message {
            command,
            data: data.into(),
        }
    }
}

impl fmt::Debug for Message {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.data.is_empty() {
            write!(f, "<{}>", self.command)
        } else if self.command == Command::Dat {
            write!(f, "<DAT {} bytes>", self.data.len())
        } else {
            write!(
                f,
                "<{} {}>",
                self.command,
                String::from_utf8_lossy(&self.data).escape_debug()
            )
        }
    }
}

/// Why a message could not be encoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum EncodeError {
    /// The data part is longer than the command may carry (§4.4.2).
    #[error("{command} data part of {len} bytes exceeds {max} (§4.4.2)")]
    DataTooLong {
        /// The command.
        command: Command,
        /// Length of the data part, bytes.
        len: usize,
        /// Longest data part the command may carry, bytes.
        max: usize,
    },
    /// A byte of the data part is the end code as transmitted (§4.1).
    #[error(
        "{command} data part carries the end code {end:#04x} at offset {offset}; the end code may not appear in a data part (§4.1)"
    )]
    EndCodeInData {
        /// The command.
        command: Command,
        /// The end code as transmitted.
        end: u8,
        /// Offset of the first such byte in the data part.
        offset: usize,
    },
}

/// Why bytes ending in an end code are not a valid message (§4.6).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FrameError {
    /// A character with wrong parity for the ISO code (or bit 7 set in ASCII): a line error.
    #[error("parity error in character {position} of a message ({byte:#04x}) (§4.6)")]
    Parity {
        /// The character's position in the message, from 0 (the first checksum digit).
        position: usize,
        /// The character as received.
        byte: u8,
    },
    /// Fewer bytes than a checksum and a command before the end code.
    #[error(
        "message of {len} bytes before its end code is too short for checksum and command (§4.1)"
    )]
    TooShort {
        /// Bytes before the end code.
        len: usize,
    },
    /// The checksum field is not two upper-case hex digits.
    #[error("checksum field {field:?} is not two upper-case hex digits (§4.1)")]
    ChecksumDigits {
        /// The checksum field, parity stripped.
        field: [u8; 2],
    },
    /// The checksum does not match the bytes of the message.
    #[error("checksum error: message says {received:02X}, bytes sum to {computed:02X} (§4.1)")]
    Checksum {
        /// The checksum the message carries.
        received: u8,
        /// The checksum of the bytes received.
        computed: u8,
    },
    /// An undefined command, or an end code inside the command name: SR0948's causes.
    #[error("undefined command {name:?} (§4.4.1)")]
    UnknownCommand {
        /// The three command characters, parity stripped.
        name: String,
    },
    /// The data part is longer than the command may carry (§4.4.2).
    #[error("{command} data part of {len} bytes exceeds {max} (§4.4.2)")]
    DataTooLong {
        /// The command.
        command: Command,
        /// Length of the data part, bytes.
        len: usize,
        /// Longest data part the command may carry, bytes.
        max: usize,
    },
    /// More than [`MAX_FRAME`] bytes without an end code; they were dropped.
    #[error("{dropped} bytes without an end code were dropped (longest message is {MAX_FRAME})")]
    Oversize {
        /// Bytes dropped.
        dropped: usize,
    },
}

impl FrameError {
    /// Parity errors are line errors (§4.6 1); the others are reception errors (§4.6 2) or,
    /// for checksum errors, a reason to ask for retransmission.
    pub fn is_line_error(&self) -> bool {
        matches!(self, FrameError::Parity { .. })
    }

    /// Whether the checksum is wrong or unreadable: a reason to ask for retransmission.
    pub fn is_checksum_error(&self) -> bool {
        matches!(
            self,
            FrameError::Checksum { .. } | FrameError::ChecksumDigits { .. }
        )
    }
}

/// Lower 8 bits of the sum of `bytes`.
pub fn sum8(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0u8, |acc, &b| acc.wrapping_add(b))
}

pub use crate::engine::hex::hex2;

/// Value of two upper-case hex digits; lower case is not accepted (protocol notes 1).
pub fn parse_hex2(d: [u8; 2]) -> Option<u8> {
    fn nibble(c: u8) -> Option<u8> {
        match c {
            b'0'..=b'9' => Some(c - b'0'),
            b'A'..=b'F' => Some(c - b'A' + 10),
            _ => None,
        }
    }
    Some((nibble(d[0])? << 4) | nibble(d[1])?)
}

/// The code and end code a link uses for its messages (parameters 5000#2 and 5000#3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Framing {
    /// Code of the control part (parameter 5000#2).
    pub code: CodeSystem,
    /// End code of every message (parameter 5000#3).
    pub end: EndCode,
}

impl Framing {
    /// The framing of `code` and `end`.
    pub fn new(code: CodeSystem, end: EndCode) -> Self {
        Framing { code, end }
    }

    /// The end code as transmitted.
    pub fn end_byte(&self) -> u8 {
        self.code.encode(match self.end {
            EndCode::Cr => CR,
            EndCode::Etx => ETX,
        })
    }

    /// Checks that `data` may travel in a `command` message: its length, and no end code.
    pub fn check_data(&self, command: Command, data: &[u8]) -> Result<(), EncodeError> {
        let max = command.max_data();
        if data.len() > max {
            return Err(EncodeError::DataTooLong {
                command,
                len: data.len(),
                max,
            });
        }
        let end = self.end_byte();
        let on_line = |b: u8| {
            if command == Command::Dat {
                b
            } else {
                self.code.encode(b)
            }
        };
        if let Some(offset) = data.iter().position(|&b| on_line(b) == end) {
            return Err(EncodeError::EndCodeInData {
                command,
                end,
                offset,
            });
        }
        Ok(())
    }

    /// Appends `msg` as transmitted to `out`.
    pub fn encode(&self, msg: &Message, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        self.check_data(msg.command, &msg.data)?;
        let start = out.len();
        out.extend_from_slice(b"00"); // checksum placeholder
        out.extend(msg.command.name().iter().map(|&b| self.code.encode(b)));
        if msg.command == Command::Dat {
            out.extend_from_slice(&msg.data);
        } else {
            out.extend(msg.data.iter().map(|&b| self.code.encode(b)));
        }
        out.push(self.end_byte());
        let digits = hex2(sum8(&out[start + 2..]));
        out[start] = self.code.encode(digits[0]);
        out[start + 1] = self.code.encode(digits[1]);
        Ok(())
    }

    /// `msg` as transmitted, in a new vector.
    pub fn encode_to_vec(&self, msg: &Message) -> Result<Vec<u8>, EncodeError> {
        let mut v = Vec::with_capacity(msg.data.len() + 6);
        self.encode(msg, &mut v)?;
        Ok(v)
    }

    /// Decodes one complete message: `frame` ends with the end code.
    pub fn decode(&self, frame: &[u8]) -> Result<Message, FrameError> {
        let Some((&_end, body)) = frame.split_last() else {
            return Err(FrameError::TooShort { len: 0 });
        };
        if body.len() < 5 {
            return Err(FrameError::TooShort { len: body.len() });
        }
        // The control part (checksum and command) always carries the link's code.
        let mut control = [0u8; 5];
        for (i, (&b, slot)) in body.iter().zip(control.iter_mut()).enumerate() {
            *slot = self.code.decode(b).ok_or(FrameError::Parity {
                position: i,
                byte: b,
            })?;
        }
        let name = &control[2..5];
        let command = Command::from_name(name).ok_or_else(|| FrameError::UnknownCommand {
            name: String::from_utf8_lossy(name).into_owned(),
        })?;
        let raw_data = &body[5..];
        let data = if command == Command::Dat {
            raw_data.to_vec()
        } else {
            let mut d = Vec::with_capacity(raw_data.len());
            for (i, &b) in raw_data.iter().enumerate() {
                d.push(self.code.decode(b).ok_or(FrameError::Parity {
                    position: 5 + i,
                    byte: b,
                })?);
            }
            d
        };
        let field = [control[0], control[1]];
        let received = parse_hex2(field).ok_or(FrameError::ChecksumDigits { field })?;
        let computed = sum8(&frame[2..]);
        if received != computed {
            return Err(FrameError::Checksum { received, computed });
        }
        if data.len() > command.max_data() {
            return Err(FrameError::DataTooLong {
                command,
                len: data.len(),
                max: command.max_data(),
            });
        }
        Ok(Message { command, data })
    }
}

/// Splits a received byte stream into messages at the end code, with a bounded buffer.
///
/// A run longer than [`MAX_FRAME`] without an end code is dropped (and logged), and the
/// decoder resynchronises at the next end code.
#[derive(Debug, Default)]
pub struct Decoder {
    framing: Framing,
    buf: Vec<u8>,
    /// Bytes after an oversize run are dropped until the next end code.
    discarding: bool,
}

impl Decoder {
    /// A decoder of messages in `framing`, holding nothing yet.
    pub fn new(framing: Framing) -> Self {
        Decoder {
            framing,
            buf: Vec::new(),
            discarding: false,
        }
    }

    /// The code and end code the decoder reads messages in.
    pub fn framing(&self) -> Framing {
        self.framing
    }

    /// Bytes received but not yet part of a complete message.
    pub fn buffered(&self) -> usize {
        self.buf.len()
    }

    /// Forgets any partial message (after a line error or re-initialisation).
    pub fn clear(&mut self) {
        self.buf.clear();
        self.discarding = false;
    }

    /// Takes received bytes; [`Decoder::next_message`] splits them.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// The next complete message (or the error of the next complete frame), if any.
    pub fn next_message(&mut self) -> Option<Result<Message, FrameError>> {
        let end = self.framing.end_byte();
        loop {
            match self.buf.iter().position(|&b| b == end) {
                Some(i) => {
                    let frame: Vec<u8> = self.buf.drain(..=i).collect();
                    if self.discarding {
                        self.discarding = false;
                        tracing::debug!(dropped = frame.len(), "end of an oversize run dropped");
                        continue;
                    }
                    return Some(self.framing.decode(&frame));
                }
                None if self.buf.len() > MAX_FRAME => {
                    let dropped = self.buf.len();
                    tracing::warn!(
                        dropped,
                        head = %hex::encode(&self.buf[..16.min(dropped)]),
                        "no end code within the longest message: bytes dropped"
                    );
                    self.buf.clear();
                    let first = !self.discarding;
                    self.discarding = true;
                    if first {
                        return Some(Err(FrameError::Oversize { dropped }));
                    }
                    return None;
                }
                None => return None,
            }
        }
    }
}

#[cfg(test)]
mod tests;
