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

pub const MAX_DAT_DATA: usize = 4096;
pub const MAX_OTHER_DATA: usize = 72;
/// Longest message on the line: checksum, command, a full DAT data part, end code.
pub const MAX_FRAME: usize = 2 + 3 + MAX_DAT_DATA + 1;

/// RTY reasons (§4.4.2 6).
pub const RTY_CHECKSUM: u8 = b'1';
pub const RTY_OVERRUN: u8 = b'3';

/// A Protocol A message. `data` holds 7-bit characters (parity stripped) for every command
/// but DAT, whose NC data is kept exactly as it travels.
#[derive(Clone, PartialEq, Eq)]
pub struct Message {
    pub command: Command,
    pub data: Vec<u8>,
}

impl Message {
    pub fn new(command: Command) -> Self {
        Message {
            command,
            data: Vec::new(),
        }
    }

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
    #[error("{command} data part of {len} bytes exceeds {max} (§4.4.2)")]
    DataTooLong {
        command: Command,
        len: usize,
        max: usize,
    },
    #[error(
        "{command} data part carries the end code {end:#04x} at offset {offset}; the end code may not appear in a data part (§4.1)"
    )]
    EndCodeInData {
        command: Command,
        end: u8,
        offset: usize,
    },
}

/// Why bytes ending in an end code are not a valid message (§4.6).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FrameError {
    /// A character with wrong parity for the ISO code (or bit 7 set in ASCII): a line error.
    #[error("parity error in character {position} of a message ({byte:#04x}) (§4.6)")]
    Parity { position: usize, byte: u8 },
    /// Fewer bytes than a checksum and a command before the end code.
    #[error(
        "message of {len} bytes before its end code is too short for checksum and command (§4.1)"
    )]
    TooShort { len: usize },
    #[error("checksum field {field:?} is not two upper-case hex digits (§4.1)")]
    ChecksumDigits { field: [u8; 2] },
    #[error("checksum error: message says {received:02X}, bytes sum to {computed:02X} (§4.1)")]
    Checksum { received: u8, computed: u8 },
    /// An undefined command, or an end code inside the command name: SR0948's causes.
    #[error("undefined command {name:?} (§4.4.1)")]
    UnknownCommand { name: String },
    #[error("{command} data part of {len} bytes exceeds {max} (§4.4.2)")]
    DataTooLong {
        command: Command,
        len: usize,
        max: usize,
    },
    /// More than [`MAX_FRAME`] bytes without an end code; they were dropped.
    #[error("{dropped} bytes without an end code were dropped (longest message is {MAX_FRAME})")]
    Oversize { dropped: usize },
}

impl FrameError {
    /// Parity errors are line errors (§4.6 1); the others are reception errors (§4.6 2) or,
    /// for checksum errors, a reason to ask for retransmission.
    pub fn is_line_error(&self) -> bool {
        matches!(self, FrameError::Parity { .. })
    }

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

const HEX: &[u8; 16] = b"0123456789ABCDEF";

/// The two hex digits of `v`, high first.
pub fn hex2(v: u8) -> [u8; 2] {
    [HEX[usize::from(v >> 4)], HEX[usize::from(v & 0xF)]]
}

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
    pub code: CodeSystem,
    pub end: EndCode,
}

impl Framing {
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
    pub fn new(framing: Framing) -> Self {
        Decoder {
            framing,
            buf: Vec::new(),
            discarding: false,
        }
    }

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
mod tests {
    use super::*;
    use proptest::prelude::*;

    const ASCII_CR: Framing = Framing {
        code: CodeSystem::Ascii,
        end: EndCode::Cr,
    };
    const ISO_CR: Framing = Framing {
        code: CodeSystem::Iso,
        end: EndCode::Cr,
    };

    #[test]
    fn syn_example_of_protocol_notes() {
        // S+Y+N+CR = 0x53+0x59+0x4E+0x0D = 0x107 → "07".
        let bytes = ASCII_CR.encode_to_vec(&Message::new(Command::Syn)).unwrap();
        assert_eq!(bytes, b"07SYN\r");
        assert_eq!(ASCII_CR.decode(&bytes), Ok(Message::new(Command::Syn)));
    }

    #[test]
    fn iso_carries_parity_and_sums_transmitted_bytes() {
        let bytes = ISO_CR.encode_to_vec(&Message::new(Command::Syn)).unwrap();
        // S 53h (4 ones) → 53h, Y 59h (4) → 59h, N 4Eh (4) → 4Eh, CR → 8Dh: 53+59+4E+8D = 187h.
        assert_eq!(&bytes[2..], &[0x53, 0x59, 0x4E, 0x8D]);
        assert_eq!(&bytes[..2], &[with_parity(b'8'), with_parity(b'7')]);
        assert_eq!(ISO_CR.decode(&bytes), Ok(Message::new(Command::Syn)));
    }

    fn with_parity(b: u8) -> u8 {
        CodeSystem::Iso.encode(b)
    }

    #[test]
    fn etx_end_code() {
        let f = Framing::new(CodeSystem::Ascii, EndCode::Etx);
        let bytes = f
            .encode_to_vec(&Message::with_data(Command::Sdo, "A5"))
            .unwrap();
        assert_eq!(*bytes.last().unwrap(), 0x03);
        assert_eq!(f.decode(&bytes).unwrap().data, b"A5");
    }

    #[test]
    fn dat_data_is_passed_as_is_in_iso() {
        let data = vec![0x25, 0x0A, 0xB0, 0x31]; // NC data with and without parity bits
        let bytes = ISO_CR
            .encode_to_vec(&Message::with_data(Command::Dat, data.clone()))
            .unwrap();
        assert_eq!(&bytes[5..9], &data[..]);
        assert_eq!(ISO_CR.decode(&bytes).unwrap().data, data);
    }

    #[test]
    fn refuses_end_code_in_data_and_long_parts() {
        let err = ASCII_CR
            .encode_to_vec(&Message::with_data(Command::Dat, b"G01\rX1".to_vec()))
            .unwrap_err();
        assert_eq!(
            err,
            EncodeError::EndCodeInData {
                command: Command::Dat,
                end: 0x0D,
                offset: 3
            }
        );
        assert!(matches!(
            ASCII_CR.encode_to_vec(&Message::with_data(Command::Sat, vec![b'0'; 73])),
            Err(EncodeError::DataTooLong { max: 72, .. })
        ));
        assert!(
            ASCII_CR
                .encode_to_vec(&Message::with_data(Command::Dat, vec![b'X'; 4096]))
                .is_ok()
        );
    }

    #[test]
    fn decode_errors() {
        assert_eq!(ASCII_CR.decode(b""), Err(FrameError::TooShort { len: 0 }));
        assert_eq!(
            ASCII_CR.decode(b"07SY\r"),
            Err(FrameError::TooShort { len: 4 })
        );
        assert_eq!(
            ASCII_CR.decode(b"08SYN\r"),
            Err(FrameError::Checksum {
                received: 0x08,
                computed: 0x07
            })
        );
        assert_eq!(
            ASCII_CR.decode(b"0aSYN\r"),
            Err(FrameError::ChecksumDigits { field: *b"0a" })
        );
        assert!(matches!(
            ASCII_CR.decode(b"00XYZ\r"),
            Err(FrameError::UnknownCommand { .. })
        ));
        // ISO: a CR without parity inside the control part.
        assert!(matches!(
            ISO_CR.decode(&[0x30, 0x30, 0x53, 0x59, 0x4F, 0x8D]),
            Err(FrameError::Parity { position: 4, .. })
        ));
    }

    #[test]
    fn decoder_handles_partial_and_multiple_frames() {
        let mut d = Decoder::new(ASCII_CR);
        assert!(d.next_message().is_none());
        d.push(b"07S");
        assert!(d.next_message().is_none());
        d.push(b"YN\r07SY");
        assert_eq!(d.next_message(), Some(Ok(Message::new(Command::Syn))));
        assert!(d.next_message().is_none());
        d.push(b"N\r");
        assert_eq!(d.next_message(), Some(Ok(Message::new(Command::Syn))));
        assert_eq!(d.buffered(), 0);
    }

    #[test]
    fn decoder_resyncs_after_garbage() {
        let mut d = Decoder::new(ASCII_CR);
        d.push(b"\x00\xffgarbage\r07SYN\r");
        assert!(matches!(d.next_message(), Some(Err(_))));
        assert_eq!(d.next_message(), Some(Ok(Message::new(Command::Syn))));
        // An oversize run: reported once, then dropped up to the next end code.
        d.push(&vec![b'x'; MAX_FRAME + 1]);
        assert_eq!(
            d.next_message(),
            Some(Err(FrameError::Oversize {
                dropped: MAX_FRAME + 1
            }))
        );
        d.push(b"more junk\r07SYN\r");
        assert_eq!(d.next_message(), Some(Ok(Message::new(Command::Syn))));
    }

    fn command() -> impl Strategy<Value = Command> {
        proptest::sample::select(Command::ALL.to_vec())
    }

    proptest! {
        #[test]
        fn round_trip(cmd in command(), data in proptest::collection::vec(0x20u8..0x7f, 0..72),
                      iso in any::<bool>(), etx in any::<bool>()) {
            let f = Framing::new(
                if iso { CodeSystem::Iso } else { CodeSystem::Ascii },
                if etx { EndCode::Etx } else { EndCode::Cr },
            );
            let msg = Message::with_data(cmd, data);
            let bytes = f.encode_to_vec(&msg).unwrap();
            let mut d = Decoder::new(f);
            d.push(&bytes);
            prop_assert_eq!(d.next_message(), Some(Ok(msg)));
        }

        #[test]
        fn decoder_never_panics(chunks in proptest::collection::vec(
            proptest::collection::vec(any::<u8>(), 0..600), 0..20), iso in any::<bool>()) {
            let code = if iso { CodeSystem::Iso } else { CodeSystem::Ascii };
            let mut d = Decoder::new(Framing::new(code, EndCode::Cr));
            for c in chunks {
                d.push(&c);
                while d.next_message().is_some() {}
                prop_assert!(d.buffered() <= MAX_FRAME);
            }
        }

        #[test]
        fn single_byte_corruption_is_detected(data in proptest::collection::vec(0x20u8..0x7f, 0..72),
                                              pos in any::<prop::sample::Index>(), flip in 1u8..=255) {
            let msg = Message::with_data(Command::Sat, data);
            let mut bytes = ASCII_CR.encode_to_vec(&msg).unwrap();
            let i = pos.index(bytes.len() - 1); // keep the end code
            bytes[i] ^= flip;
            if bytes[i] != 0x0D {
                prop_assert!(ASCII_CR.decode(&bytes).is_err());
            }
        }
    }
}
