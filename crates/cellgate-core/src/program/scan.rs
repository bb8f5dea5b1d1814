//! The checks every program passes before anything is queued, streaming through it once
//! ([`Scanner`]), whatever its source (inline bytes, a fetched payload, a library file read in
//! pieces). Sans-IO: the caller feeds the pieces.
//!
//! The checks (each names the byte offset and the manual section):
//! - empty: no significant character at all;
//! - size over `programs.max_size`;
//! - 8-bit bytes: programs are 7-bit text in the machine's code system without parity; the
//!   link adds the ISO parity bit itself (§4.2, §6.2; protocol notes 3);
//! - Protocol A family: the message end code (CR 0Dh or ETX 03h, which travels as 8Dh / 03h
//!   in ISO) ends a DAT message, so NC data cannot contain it (§4.1). Expansion Protocol A
//!   runs as plain Protocol A whenever n = 0 (§5.2 1), so the rule holds for both;
//! - Protocol B family: DC1–DC4 (11h–14h), NAK (15h) and SYN (16h) are the board's control
//!   codes (§6.2) and cannot travel as data;
//! - EOR: a program ends at `%` (§4.4.2 3; protocol notes 8): the first `%` before any other
//!   significant character is the tape-start mark, the next one is EOR. A program without EOR
//!   is refused, or completed with `%` when the request asks for it.

use super::name::O_DIGITS_MAX;
use crate::fanuc::code::{CR, DC1, DC2, DC3, DC4, EOR, ETX, LF, NAK, SYN, is_significant};
use crate::fanuc::{EndCode, Protocol};
/// What a machine's link can carry, from its cell-file settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProgramRules {
    /// The machine's protocol.
    pub protocol: Protocol,
    /// The message end code (Protocol A family).
    pub end_code: EndCode,
    /// `programs.max_size`, bytes.
    pub max_size: u64,
}

impl ProgramRules {
    /// Why the link cannot carry the 7-bit byte `b` as NC data, if it cannot.
    fn forbidden(&self, b: u8) -> Option<ProgramError> {
        if self.protocol.is_a_family() {
            let end = match self.end_code {
                EndCode::Cr => CR,
                EndCode::Etx => ETX,
            };
            if b == end {
                return Some(ProgramError::EndCodeInData {
                    offset: 0,
                    code: control_name(b),
                });
            }
        } else if matches!(b, DC1 | DC2 | DC3 | DC4 | NAK | SYN) {
            return Some(ProgramError::ControlCodeInData {
                offset: 0,
                code: control_name(b),
            });
        }
        None
    }
}

fn control_name(b: u8) -> &'static str {
    match b {
        CR => "CR (0Dh)",
        ETX => "ETX (03h)",
        DC1 => "DC1 (11h)",
        DC2 => "DC2 (12h)",
        DC3 => "DC3 (13h)",
        DC4 => "DC4 (14h)",
        NAK => "NAK (15h)",
        SYN => "SYN (16h)",
        _ => "a control code",
    }
}

/// Why a program cannot be sent to a machine.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ProgramError {
    /// No character other than blanks, line ends and `%`.
    #[error("the program is empty: it has no character other than blanks, line ends and %")]
    Empty,
    /// No EOR `%`, and the request did not ask for one to be appended.
    #[error(
        "the program has no EOR: it must end with % (§4.4.2 3); \
         set append_eor to have the gateway add it"
    )]
    MissingEor,
    /// The program is larger than `programs.max_size`.
    #[error("the program is {size} bytes or more; programs.max_size allows {max}")]
    TooLarge {
        /// Bytes of the program taken so far.
        size: u64,
        /// `programs.max_size`, bytes.
        max: u64,
    },
    /// A byte with bit 7 set.
    #[error(
        "byte {byte:02X}h at offset {offset} has bit 7 set: programs are 7-bit ISO/ASCII text \
         without parity, the link adds the ISO parity bit itself (§4.2, §6.2)"
    )]
    EightBit {
        /// The byte's offset in the program.
        offset: u64,
        /// The byte.
        byte: u8,
    },
    /// Protocol A family: the message end code in the program.
    #[error(
        "{code} at offset {offset}: a Protocol A DAT message ends at its end code, so NC data \
         cannot contain it (§4.1); end blocks with LF only"
    )]
    EndCodeInData {
        /// The byte's offset in the program.
        offset: u64,
        /// The code's name and value, e.g. "CR (0Dh)".
        code: &'static str,
    },
    /// Protocol B family: one of the board's control codes in the program (§6.2).
    #[error(
        "{code} at offset {offset}: it is a Protocol B control code of the remote buffer \
         (§6.2) and cannot travel as NC data"
    )]
    ControlCodeInData {
        /// The byte's offset in the program.
        offset: u64,
        /// The code's name and value, e.g. "DC3 (13h)".
        code: &'static str,
    },
}

impl ProgramError {
    fn at(self, at: u64) -> Self {
        match self {
            ProgramError::EndCodeInData { code, .. } => {
                ProgramError::EndCodeInData { offset: at, code }
            }
            ProgramError::ControlCodeInData { code, .. } => {
                ProgramError::ControlCodeInData { offset: at, code }
            }
            other => other,
        }
    }
}

/// Where the EOR scan stands (protocol notes 8).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Eor {
    /// Nothing significant yet.
    Leader,
    /// The tape-start `%` was seen, nothing significant after it yet.
    TapeStart,
    /// Program text.
    Body,
    /// EOR seen: the CNC ignores the rest.
    Ended,
}

/// What a scan found in a program that passed it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ScanReport {
    /// Bytes in the program as given.
    pub size: u64,
    /// Whether it has its EOR `%`.
    pub has_eor: bool,
    /// The first program number at the start of a block, e.g. "O1234".
    pub o_number: Option<String>,
    /// The last byte, if any.
    pub last_byte: Option<u8>,
}

/// Checks a program piece by piece. Feed every piece, then [`Scanner::finish`].
#[derive(Debug, Clone)]
pub struct Scanner {
    rules: ProgramRules,
    offset: u64,
    eor: Eor,
    significant: bool,
    block_start: bool,
    o_digits: Option<String>,
    o_number: Option<String>,
    last_byte: Option<u8>,
}

impl Scanner {
    /// A scanner for a machine with these rules, at the program's first byte.
    pub fn new(rules: ProgramRules) -> Self {
        Scanner {
            rules,
            offset: 0,
            eor: Eor::Leader,
            significant: false,
            block_start: true,
            o_digits: None,
            o_number: None,
            last_byte: None,
        }
    }

    /// Checks the next piece of the program.
    pub fn feed(&mut self, piece: &[u8]) -> Result<(), ProgramError> {
        let size = self.offset + piece.len() as u64;
        if size > self.rules.max_size {
            return Err(ProgramError::TooLarge {
                size,
                max: self.rules.max_size,
            });
        }
        for &b in piece {
            if b & 0x80 != 0 {
                return Err(ProgramError::EightBit {
                    offset: self.offset,
                    byte: b,
                });
            }
            if let Some(e) = self.rules.forbidden(b) {
                return Err(e.at(self.offset));
            }
            self.track(b);
            self.offset += 1;
        }
        if let Some(&b) = piece.last() {
            self.last_byte = Some(b);
        }
        Ok(())
    }

    fn track(&mut self, b: u8) {
        let blank = !is_significant(b);
        if let Some(digits) = self.o_digits.as_mut() {
            if b.is_ascii_digit() && digits.len() < O_DIGITS_MAX {
                digits.push(char::from(b));
            } else {
                if !digits.is_empty() && self.o_number.is_none() {
                    self.o_number = Some(format!("O{digits}"));
                }
                self.o_digits = None;
            }
        }
        match self.eor {
            Eor::Ended => return,
            _ if b == EOR => {
                self.eor = match self.eor {
                    Eor::Leader => Eor::TapeStart,
                    _ => Eor::Ended,
                };
                self.block_start = true;
                return;
            }
            _ if !blank => {
                self.eor = Eor::Body;
                self.significant = true;
            }
            _ => {}
        }
        if b == LF {
            self.block_start = true;
        } else if !blank {
            if self.block_start && b == b'O' && self.o_number.is_none() {
                self.o_digits = Some(String::new());
            }
            self.block_start = false;
        }
    }

    /// Ends the scan.
    pub fn finish(mut self) -> Result<ScanReport, ProgramError> {
        if let Some(digits) = self.o_digits.take()
            && !digits.is_empty()
            && self.o_number.is_none()
        {
            self.o_number = Some(format!("O{digits}"));
        }
        if !self.significant {
            return Err(ProgramError::Empty);
        }
        Ok(ScanReport {
            size: self.offset,
            has_eor: self.eor == Eor::Ended,
            o_number: self.o_number,
            last_byte: self.last_byte,
        })
    }
}

/// Checks a whole program held in memory.
pub fn scan(rules: ProgramRules, program: &[u8]) -> Result<ScanReport, ProgramError> {
    let mut scanner = Scanner::new(rules);
    scanner.feed(program)?;
    scanner.finish()
}

/// The bytes to append so that a program without EOR ends with one: the last block is closed
/// with LF first if it is open.
pub fn eor_suffix(report: &ScanReport) -> &'static [u8] {
    if report.has_eor {
        b""
    } else if report.last_byte == Some(LF) {
        b"%"
    } else {
        b"\n%"
    }
}

#[cfg(test)]
mod tests;
