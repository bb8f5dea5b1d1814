//! The program being sent: a bounded window of its bytes, and where it ends (§4.4.2 3, §8.2;
//! protocol notes 8).
//!
//! A program streams through: the engine holds at most its buffer limit of it at a time. The
//! program ends at EOR (`%`): the first `%` before any significant character is the tape-start
//! mark, the next one ends the program, and whatever follows is dropped (the CNC ignores it,
//! §8.2). A program whose source ends without EOR gets one appended (§4.4.2 3: "always add the
//! EOR code to the end of NC program").

use std::collections::VecDeque;

use crate::fanuc::code::{EOR, is_eor, is_significant};

/// Why a program cannot be sent as it is.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ProgramError {
    /// A byte of the program equals the end code of Protocol A messages; a DAT cannot carry it.
    #[error(
        "program byte at offset {offset} is the message end code {end:#04x}; a DAT data part cannot carry it (§4.1) — convert the program's line ends or change the end code (parameter 5000#3)"
    )]
    EndCodeInData { offset: u64, end: u8 },
    /// The source ended before any significant character.
    #[error("the program has no data before its source ended (§8.2)")]
    Empty,
}

/// Where the EOR scan stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scan {
    /// Only leader (feed, blanks, line ends) so far: a `%` here is the tape-start mark.
    Leader,
    /// In the program: the next `%` is EOR.
    Body,
    /// EOR has been taken in; nothing more belongs to the program.
    Ended,
}

#[derive(Debug)]
pub struct Program {
    buf: VecDeque<u8>,
    scan: Scan,
    /// The EOR byte as the program writes it (25h, or A5h with ISO parity), from its tape-start.
    eor: u8,
    /// Bytes taken from the source so far (offsets in errors).
    accepted: u64,
    /// Bytes after EOR that were dropped.
    ignored: u64,
    /// Program bytes handed out for transmission (first transmission only).
    pub sent: u64,
    /// EOR was appended because the source had none.
    pub eor_appended: bool,
}

impl Default for Program {
    fn default() -> Self {
        Self::new()
    }
}

impl Program {
    pub fn new() -> Self {
        Program {
            buf: VecDeque::new(),
            scan: Scan::Leader,
            eor: EOR,
            accepted: 0,
            ignored: 0,
            sent: 0,
            eor_appended: false,
        }
    }

    /// Takes the next bytes from the source. `forbidden` is a byte the program may not contain
    /// (the end code, when the program travels in DATs). Bytes after EOR are dropped.
    pub fn push(&mut self, mut data: &[u8], forbidden: Option<u8>) -> Result<(), ProgramError> {
        while let Some((&b, rest)) = data.split_first() {
            if self.scan == Scan::Ended {
                self.ignored += data.len() as u64;
                break;
            }
            if self.scan == Scan::Body {
                // The body up to the next byte that needs a look (EOR, the forbidden byte) goes
                // in as one piece: most of a program is such runs.
                let run = data
                    .iter()
                    .position(|&x| is_eor(x) || forbidden == Some(x))
                    .unwrap_or(data.len());
                if run > 0 {
                    self.buf.extend(&data[..run]);
                    self.accepted += run as u64;
                    data = &data[run..];
                    continue;
                }
            }
            data = rest;
            if forbidden == Some(b) {
                return Err(ProgramError::EndCodeInData {
                    offset: self.accepted,
                    end: b,
                });
            }
            self.accepted += 1;
            self.buf.push_back(b);
            match self.scan {
                Scan::Leader if is_eor(b) => {
                    self.eor = b;
                    self.scan = Scan::Body;
                }
                Scan::Leader if is_significant(b) => self.scan = Scan::Body,
                Scan::Body if is_eor(b) => self.scan = Scan::Ended,
                _ => {}
            }
        }
        if self.ignored > 0 {
            tracing::trace!(ignored = self.ignored, "bytes after EOR dropped (§8.2)");
        }
        Ok(())
    }

    /// Takes bytes that are passed as they are: G05 binary blocks (§9.1), which may hold any
    /// value, `%` included, and so are not scanned for EOR. They belong to the program's body
    /// (they follow its `G05` block); after EOR they are dropped like any other byte.
    pub fn push_binary(&mut self, data: &[u8]) {
        if self.scan == Scan::Ended {
            self.ignored += data.len() as u64;
            return;
        }
        self.scan = Scan::Body;
        self.accepted += data.len() as u64;
        self.buf.extend(data.iter().copied());
    }

    /// The source has no more bytes: appends EOR if the program has none.
    pub fn end(&mut self) -> Result<(), ProgramError> {
        match self.scan {
            Scan::Leader => Err(ProgramError::Empty),
            Scan::Body => {
                tracing::info!("program source ended without EOR: '%' appended (§4.4.2 3)");
                self.buf.push_back(self.eor);
                self.accepted += 1;
                self.scan = Scan::Ended;
                self.eor_appended = true;
                Ok(())
            }
            Scan::Ended => Ok(()),
        }
    }

    /// Every byte of the program up to and including EOR is in the buffer or already sent.
    pub fn complete(&self) -> bool {
        self.scan == Scan::Ended
    }

    /// Complete, and nothing of it is left to send.
    pub fn all_sent(&self) -> bool {
        self.complete() && self.buf.is_empty()
    }

    pub fn buffered(&self) -> usize {
        self.buf.len()
    }

    /// Whether a data part of `len` bytes can be filled now, or the rest of the program is
    /// shorter and complete.
    pub fn can_fill(&self, len: usize) -> bool {
        self.buf.len() >= len || (self.complete() && !self.buf.is_empty())
    }

    /// The rest of the program fits in `len` bytes (the next piece is its last).
    pub fn ends_within(&self, len: usize) -> bool {
        self.complete() && self.buf.len() <= len
    }

    /// Whether the next `len` bytes contain `b` (the end code check of a DAT).
    pub fn find_in_next(&self, len: usize, b: u8) -> Option<u64> {
        self.buf
            .iter()
            .take(len)
            .position(|&x| x == b)
            .map(|i| self.sent + i as u64)
    }

    /// Takes up to `len` bytes for transmission.
    pub fn take(&mut self, len: usize) -> Vec<u8> {
        let n = len.min(self.buf.len());
        let out: Vec<u8> = self.buf.drain(..n).collect();
        self.sent += n as u64;
        out
    }

    /// How many more bytes the program takes now, within `limit` bytes of buffer: none while
    /// it holds more than half the limit, so that its source is read in large pieces, not a
    /// packet's worth at a time (each read of a file is a trip to a blocking thread: 8 % of the
    /// gateway's CPU at 1024 busy links, README "A thousand links").
    /// None after EOR: what follows it would only be dropped.
    pub fn wanted(&self, limit: usize) -> usize {
        if self.complete() || self.buf.len() > limit / 2 {
            0
        } else {
            limit - self.buf.len()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all(p: &mut Program) -> Vec<u8> {
        p.take(usize::MAX)
    }

    /// The byte-at-a-time scan `push` replaced with runs: what it accepts, drops and fails on.
    fn reference(data: &[u8], forbidden: Option<u8>) -> (Vec<u8>, u64, Result<(), u64>, bool) {
        let (mut buf, mut ignored, mut scan) = (Vec::new(), 0, Scan::Leader);
        for &b in data {
            if scan == Scan::Ended {
                ignored += 1;
                continue;
            }
            if forbidden == Some(b) {
                let offset = buf.len() as u64;
                return (buf, ignored, Err(offset), false);
            }
            buf.push(b);
            scan = match scan {
                Scan::Leader if is_eor(b) || is_significant(b) => Scan::Body,
                Scan::Body if is_eor(b) => Scan::Ended,
                s => s,
            };
        }
        (buf, ignored, Ok(()), scan == Scan::Ended)
    }

    #[test]
    fn runs_take_in_what_the_byte_scan_would() {
        let alphabet = [b'%', 0xA5, b'X', b'\n', b' ', 0x0D, 0x03];
        let mut seed = 0x9E37_79B9_7F4A_7C15u64;
        for case in 0..2000 {
            let len = case % 40;
            let data: Vec<u8> = (0..len)
                .map(|_| {
                    seed ^= seed << 13;
                    seed ^= seed >> 7;
                    seed ^= seed << 17;
                    alphabet[(seed % alphabet.len() as u64) as usize]
                })
                .collect();
            let forbidden = [None, Some(0x0D), Some(0x03)][case % 3];
            let (buf, ignored, result, ended) = reference(&data, forbidden);
            // Whole, and split in two at each of the first eight places.
            for split in [data.len()].into_iter().chain(0..data.len().min(8)) {
                let mut p = Program::new();
                let got = p
                    .push(&data[..split], forbidden)
                    .and_then(|()| p.push(&data[split..], forbidden));
                let got = got.map_err(|e| match e {
                    ProgramError::EndCodeInData { offset, .. } => offset,
                    other => panic!("{other:?}"),
                });
                assert_eq!(got, result, "{data:02x?} split at {split}");
                assert_eq!(p.complete(), ended, "{data:02x?}");
                if result.is_ok() {
                    assert_eq!(p.ignored, ignored, "{data:02x?}");
                }
                assert_eq!(all(&mut p), buf, "{data:02x?} split at {split}");
            }
        }
    }

    #[test]
    fn binary_bytes_are_not_scanned_for_eor() {
        let mut p = Program::new();
        p.push(b"%\nG05\n", None).unwrap();
        p.push_binary(b"\x25\x25\xA5\x00");
        assert!(!p.complete(), "a % inside binary data is no EOR");
        p.push(b"M30\n", None).unwrap();
        p.end().unwrap();
        assert_eq!(all(&mut p), b"%\nG05\n\x25\x25\xA5\x00M30\n%");
        // After EOR, binary bytes are dropped too.
        p.push_binary(b"\x01");
        assert_eq!(p.buffered(), 0);
    }

    #[test]
    fn tape_start_mark_and_eor() {
        let mut p = Program::new();
        p.push(b"\0\0 \n%\nO0001\nG01X1;\n%\nM30 after EOR\n", None)
            .unwrap();
        assert!(p.complete());
        assert_eq!(all(&mut p), b"\0\0 \n%\nO0001\nG01X1;\n%");
        assert!(p.all_sent());
        assert_eq!(p.wanted(100), 0);
    }

    #[test]
    fn program_without_tape_start_ends_at_first_percent() {
        let mut p = Program::new();
        p.push(b"O1\nX1%junk", None).unwrap();
        assert_eq!(all(&mut p), b"O1\nX1%");
    }

    #[test]
    fn eor_appended_when_missing_with_the_tape_start_code() {
        let mut p = Program::new();
        p.push(&[0xA5, b'\n', b'O', b'1'], None).unwrap();
        assert!(!p.complete());
        p.end().unwrap();
        assert!(p.eor_appended);
        assert_eq!(all(&mut p), [0xA5, b'\n', b'O', b'1', 0xA5]);
        let mut empty = Program::new();
        empty.push(b"\n\n", None).unwrap();
        assert_eq!(empty.end(), Err(ProgramError::Empty));
    }

    #[test]
    fn end_code_is_refused_with_its_offset() {
        let mut p = Program::new();
        assert_eq!(
            p.push(b"%\nO1\r\n", Some(0x0D)),
            Err(ProgramError::EndCodeInData {
                offset: 4,
                end: 0x0D
            })
        );
    }

    #[test]
    fn split_input_and_bounded_wants() {
        let mut p = Program::new();
        p.push(b"%\nG0", None).unwrap();
        p.push(b"1\n", None).unwrap();
        assert_eq!(p.wanted(12), 6);
        assert_eq!(
            p.wanted(8),
            0,
            "more than half the limit is held: refilled later"
        );
        assert_eq!(p.take(2), b"%\n");
        assert_eq!(p.wanted(8), 4);
        assert!(p.can_fill(4));
        assert!(!p.can_fill(5));
        assert_eq!(p.take(3), b"G01");
        assert_eq!(p.sent, 5);
    }

    #[test]
    fn split_input_is_buffered_whole() {
        let mut p = Program::new();
        p.push(b"%\nG0", None).unwrap();
        p.push(b"1\n", None).unwrap();
        assert!(p.can_fill(6));
        assert!(!p.can_fill(7));
        assert_eq!(p.take(3), b"%\nG");
        assert_eq!(p.sent, 3);
        p.push(b"%", None).unwrap();
        assert!(p.ends_within(4));
        assert!(p.can_fill(100));
        assert_eq!(p.find_in_next(10, b'%'), Some(6));
    }
}
