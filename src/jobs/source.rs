//! Where a job's program comes from, and the checks it passes before anything is queued.
//!
//! A program is checked by streaming through it once ([`Scanner`]), whatever its source:
//! inline bytes and bytes fetched from a bus key are already in memory; a library file is
//! read in pieces, then rewound and kept open for sending, so a 500 MB program is never
//! held whole. The library replaces files by rename, so the open file keeps the bytes that
//! were checked even if the program is stored again meanwhile.
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

use std::io::Cursor;
use std::path::Path;

use bytes::Bytes;
use tokio::io::{AsyncReadExt, AsyncSeekExt};

use super::journal::StartPoint;
use crate::fanuc::code::{CR, DC1, DC2, DC3, DC4, EOR, ETX, LF, NAK, SYN, is_significant};
use crate::fanuc::{EndCode, Protocol};
use crate::link::driver::ProgramSource;

/// What a machine's link can carry, from its cell-file settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProgramRules {
    pub protocol: Protocol,
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
    #[error("the program is empty: it has no character other than blanks, line ends and %")]
    Empty,
    #[error(
        "the program has no EOR: it must end with % (§4.4.2 3); \
         set append_eor to have the gateway add it"
    )]
    MissingEor,
    #[error("the program is {size} bytes or more; programs.max_size allows {max}")]
    TooLarge { size: u64, max: u64 },
    #[error(
        "byte {byte:02X}h at offset {offset} has bit 7 set: programs are 7-bit ISO/ASCII text \
         without parity, the link adds the ISO parity bit itself (§4.2, §6.2)"
    )]
    EightBit { offset: u64, byte: u8 },
    #[error(
        "{code} at offset {offset}: a Protocol A DAT message ends at its end code, so NC data \
         cannot contain it (§4.1); end blocks with LF only"
    )]
    EndCodeInData { offset: u64, code: &'static str },
    #[error(
        "{code} at offset {offset}: it is a Protocol B control code of the remote buffer \
         (§6.2) and cannot travel as NC data"
    )]
    ControlCodeInData { offset: u64, code: &'static str },
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

/// Longest program number kept (O followed by up to 8 digits).
const O_DIGITS_MAX: usize = 8;

impl Scanner {
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

/// A program as a job request names it.
#[derive(Debug, Clone)]
pub enum ProgramInput {
    /// The program itself.
    Inline(Bytes),
    /// A program of the cell's library, by name.
    Library(String),
    /// The payload fetched from a bus key.
    Fetched { key: String, bytes: Bytes },
    /// The program of an earlier job, by its id, from where that job stopped.
    Resume(String),
}

impl Default for ProgramInput {
    fn default() -> Self {
        ProgramInput::Inline(Bytes::new())
    }
}

/// Why a program file could not be checked.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ScanFileError {
    #[error(transparent)]
    Program(#[from] ProgramError),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

/// Checks the program file at `path` against `rules`, streaming through it once.
pub async fn scan_file(rules: ProgramRules, path: &Path) -> Result<ScanReport, ScanFileError> {
    let mut file = tokio::fs::File::open(path).await?;
    let mut scanner = Scanner::new(rules);
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        let n = file.read(&mut buf).await?;
        if n == 0 {
            break;
        }
        scanner.feed(buf.get(..n).unwrap_or_default())?;
    }
    Ok(scanner.finish()?)
}

/// A program as the journal keeps it: its file, then `suffix` (an appended EOR).
pub async fn open_program(path: &Path, suffix: &[u8]) -> std::io::Result<ProgramSource> {
    let file = tokio::fs::File::open(path).await?;
    Ok(Box::new(file.chain(Cursor::new(suffix.to_vec()))))
}

/// What a job sends of its program: all of it, or its header and the rest from its start
/// block (`start`), streamed in pieces from the file. The file is opened here, when the job
/// starts, not while it waits.
pub async fn open_stream(
    path: &Path,
    suffix: &[u8],
    start: Option<StartPoint>,
) -> std::io::Result<ProgramSource> {
    let file_len = tokio::fs::metadata(path).await?.len();
    let size = file_len + suffix.len() as u64;
    let ranges = match start {
        None => vec![(0, size)],
        Some(s) => vec![(0, s.header_end.min(size)), (s.body_start.min(size), size)],
    };
    let mut stream: ProgramSource = Box::new(tokio::io::empty());
    for (from, to) in ranges {
        let (f_from, f_to) = (from.min(file_len), to.min(file_len));
        if f_to > f_from {
            let mut file = tokio::fs::File::open(path).await?;
            file.seek(std::io::SeekFrom::Start(f_from)).await?;
            stream = Box::new(stream.chain(file.take(f_to - f_from)));
        }
        let (s_from, s_to) = (from.max(file_len) - file_len, to.max(file_len) - file_len);
        let tail = suffix
            .get(usize::try_from(s_from).unwrap_or(usize::MAX)..usize::try_from(s_to).unwrap_or(0))
            .unwrap_or_default();
        if !tail.is_empty() {
            stream = Box::new(stream.chain(Cursor::new(tail.to_vec())));
        }
    }
    Ok(stream)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rules(protocol: Protocol) -> ProgramRules {
        ProgramRules {
            protocol,
            end_code: EndCode::Cr,
            max_size: 1 << 20,
        }
    }

    #[test]
    fn a_plain_program_passes_and_reports_its_number() {
        let r = scan(rules(Protocol::A), b"%\nO1234\nG00X0\nM30\n%\n").unwrap();
        assert!(r.has_eor);
        assert_eq!(r.size, 20);
        assert_eq!(r.o_number.as_deref(), Some("O1234"));
    }

    #[test]
    fn the_tape_start_mark_is_not_eor() {
        let r = scan(rules(Protocol::A), b"%\nO1\nG00X0\n").unwrap();
        assert!(!r.has_eor);
        assert_eq!(eor_suffix(&r), b"%");
        let r = scan(rules(Protocol::A), b"O1\nG00X0").unwrap();
        assert!(!r.has_eor);
        assert_eq!(eor_suffix(&r), b"\n%");
        // Without a tape-start mark, the first % after text is EOR.
        assert!(scan(rules(Protocol::A), b"O1\nG00X0\n%").unwrap().has_eor);
    }

    #[test]
    fn empty_programs_are_refused() {
        for p in [&b""[..], b"\n\n", b"%\n%\n", b"  %"] {
            assert_eq!(
                scan(rules(Protocol::A), p),
                Err(ProgramError::Empty),
                "{p:?}"
            );
        }
    }

    #[test]
    fn eight_bit_bytes_are_refused_with_their_offset() {
        assert_eq!(
            scan(rules(Protocol::B), b"%\nG00\xA5X0\n%"),
            Err(ProgramError::EightBit {
                offset: 5,
                byte: 0xA5
            })
        );
    }

    #[test]
    fn protocol_a_refuses_its_end_code_only() {
        let cr = scan(rules(Protocol::A), b"%\r\nO1\n%");
        assert_eq!(
            cr,
            Err(ProgramError::EndCodeInData {
                offset: 1,
                code: "CR (0Dh)"
            })
        );
        assert!(
            scan(rules(Protocol::ExpansionA), b"%\nO1\r\n%").is_err(),
            "expansion A keeps the rule"
        );
        let etx = ProgramRules {
            end_code: EndCode::Etx,
            ..rules(Protocol::A)
        };
        assert!(
            scan(etx, b"%\r\nO1\n%").is_ok(),
            "CR is data when ETX ends messages"
        );
        assert!(matches!(
            scan(etx, b"%\nO1\x03\n%"),
            Err(ProgramError::EndCodeInData { offset: 4, .. })
        ));
        // DC3 is no control code in Protocol A.
        assert!(scan(rules(Protocol::A), b"%\nO1\x13\n%").is_ok());
    }

    #[test]
    fn protocol_b_refuses_its_control_codes() {
        for (c, name) in [(0x11, "DC1"), (0x13, "DC3"), (0x15, "NAK"), (0x16, "SYN")] {
            let p = [b'%', b'\n', b'G', c, b'\n', b'%'];
            match scan(rules(Protocol::ExpansionB), &p) {
                Err(ProgramError::ControlCodeInData { offset: 3, code }) => {
                    assert!(code.starts_with(name))
                }
                other => panic!("{name}: {other:?}"),
            }
        }
        // CR is plain data in Protocol B.
        assert!(scan(rules(Protocol::B), b"%\r\nO1\r\n%").is_ok());
    }

    #[test]
    fn size_is_checked_while_streaming() {
        let small = ProgramRules {
            max_size: 10,
            ..rules(Protocol::A)
        };
        let mut s = Scanner::new(small);
        s.feed(b"%\nO1\n").unwrap();
        assert_eq!(
            s.feed(b"G00X0\n%"),
            Err(ProgramError::TooLarge { size: 12, max: 10 })
        );
    }

    #[test]
    fn pieces_give_the_same_answer_as_the_whole() {
        let program = b"%\nO0042 (PART)\nG01X1\nM30\n%\n";
        let whole = scan(rules(Protocol::A), program).unwrap();
        for split in 0..program.len() {
            let mut s = Scanner::new(rules(Protocol::A));
            s.feed(&program[..split]).unwrap();
            s.feed(&program[split..]).unwrap();
            assert_eq!(s.finish().unwrap(), whole, "split at {split}");
        }
        assert_eq!(whole.o_number.as_deref(), Some("O0042"));
    }

    #[tokio::test]
    async fn program_files_are_scanned_and_streamed_whole_or_from_a_block() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p");
        let program: Vec<u8> = b"%\nO1\n"
            .iter()
            .copied()
            .chain(std::iter::repeat_n(b"G01X1\n".iter().copied(), 30_000).flatten())
            .collect();
        std::fs::write(&path, &program).unwrap();
        let report = scan_file(rules(Protocol::A), &path).await.unwrap();
        assert_eq!(report.size, program.len() as u64);
        assert!(!report.has_eor);
        assert_eq!(report.o_number.as_deref(), Some("O1"));

        let read = |start| {
            let path = path.clone();
            async move {
                let mut out = Vec::new();
                open_stream(&path, b"%", start)
                    .await
                    .unwrap()
                    .read_to_end(&mut out)
                    .await
                    .unwrap();
                out
            }
        };
        let mut whole = program.clone();
        whole.push(b'%');
        assert_eq!(read(None).await, whole);
        // The header (first two lines), then from the last block on: the suffix follows.
        let body_start = program.len() as u64 - 6;
        let out = read(Some(StartPoint {
            header_end: 5,
            body_start,
        }))
        .await;
        assert_eq!(out, b"%\nO1\nG01X1\n%");
        // A start inside the appended suffix itself.
        let out = read(Some(StartPoint {
            header_end: 2,
            body_start: program.len() as u64,
        }))
        .await;
        assert_eq!(out, b"%\n%");

        std::fs::write(&path, b"%\nO1\n\x0d\n%").unwrap();
        assert!(matches!(
            scan_file(rules(Protocol::A), &path).await,
            Err(ScanFileError::Program(ProgramError::EndCodeInData {
                offset: 5,
                ..
            }))
        ));
        assert!(matches!(
            scan_file(rules(Protocol::A), &dir.path().join("nope")).await,
            Err(ScanFileError::Io(_))
        ));
    }
}
