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
pub enum ProgramSendError {
    /// A byte of the program equals the end code of Protocol A messages; a DAT cannot carry it.
    #[error(
        "program byte at offset {offset} is the message end code {end:#04x}; a DAT data part cannot carry it (§4.1) — convert the program's line ends or change the end code (parameter 5000#3)"
    )]
    EndCodeInData {
        /// The program byte's offset from the start of the source.
        offset: u64,
        /// The end code the byte equals.
        end: u8,
    },
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

/// The program being sent: a bounded window of its bytes, scanned for its EOR (§8.2).
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
    /// An empty program, before its tape-start.
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
    pub fn push(&mut self, mut data: &[u8], forbidden: Option<u8>) -> Result<(), ProgramSendError> {
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
                    // Grown no further than it is filled: the engine's limit bounds it, and
                    // a thousand busy links each hold one.
                    self.buf.reserve_exact(run);
                    self.buf.extend(&data[..run]);
                    self.accepted += run as u64;
                    data = &data[run..];
                    continue;
                }
            }
            data = rest;
            if forbidden == Some(b) {
                return Err(ProgramSendError::EndCodeInData {
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
    pub fn end(&mut self) -> Result<(), ProgramSendError> {
        match self.scan {
            Scan::Leader => Err(ProgramSendError::Empty),
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

    /// Bytes taken in and not yet handed out for transmission.
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
        let out = take_front(&mut self.buf, len);
        self.sent += out.len() as u64;
        out
    }

    /// How many more bytes the program takes now, within `limit` bytes of buffer: none while
    /// it holds more than half the limit, so that its source is read in large pieces, not a
    /// packet's worth at a time (each read of a file is a trip to a blocking thread: 8 % of the
    /// gateway's CPU at 1024 busy links, docs/performance.md "A thousand links: the gateway
    /// alone").
    /// None after EOR: what follows it would only be dropped.
    pub fn wanted(&self, limit: usize) -> usize {
        if self.complete() || self.buf.len() > limit / 2 {
            0
        } else {
            limit - self.buf.len()
        }
    }
}

/// Takes the first `n` bytes of `buf` (all of them if fewer), copied a slice at a time:
/// collecting the drained bytes one by one was 7 % of the gateway's CPU at 1024 busy links
/// (docs/performance.md).
pub fn take_front(buf: &mut VecDeque<u8>, n: usize) -> Vec<u8> {
    let n = n.min(buf.len());
    let (front, back) = buf.as_slices();
    let from_front = n.min(front.len());
    let mut out = Vec::with_capacity(n);
    out.extend_from_slice(&front[..from_front]);
    out.extend_from_slice(&back[..n - from_front]);
    buf.drain(..n);
    out
}

#[cfg(test)]
mod tests;
