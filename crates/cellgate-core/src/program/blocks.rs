//! Blocks of a program: where one starts, its line and its sequence number (`N1234`), so
//! that a job can start at a block and a failed one resume at the first block the board did
//! not acknowledge whole (DNC "restart from block N").
//!
//! A block is a line: it ends with LF (the EOB of ISO and ASCII programs as the gateway
//! takes them). Its sequence number is an `N` and digits at its start, after blanks. The
//! header of a program is its lines before the first block with a sequence number (the
//! tape-start `%`, the O-number, comments and modal set-up), or a count of lines the request
//! gives; a job that starts at a block sends the header first.

use crate::fanuc::code::LF;
use crate::pb;

/// A block of a program.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Block {
    /// Counting the first line as 1.
    pub line: u64,
    /// `N1234`, or `None`.
    pub sequence: Option<String>,
    /// Where it starts in the program.
    pub offset: u64,
}

impl Block {
    /// The block as the bus reports it.
    pub fn to_pb(&self) -> pb::BlockPosition {
        pb::BlockPosition {
            line: self.line,
            sequence_number: self.sequence.clone().unwrap_or_default(),
            byte_offset: self.offset,
        }
    }
}

/// Where a job starts, as a request asks for it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StartAt {
    /// The block on this line, counting the first line as 1.
    Line(u64),
    /// The block whose sequence number is `N` and this number.
    Sequence(u64),
}

/// Why a start cannot be found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum BlockError {
    /// No block has this sequence number.
    #[error("the program has no block N{0}")]
    NoSequence(u64),
    /// The program has no such line.
    #[error("the program has {lines} lines: line {line} is not one of its blocks")]
    NoLine {
        /// The line asked for.
        line: u64,
        /// Lines in the program.
        lines: u64,
    },
    /// Line 0 was asked for: lines count from 1.
    #[error("line 0 is not a line: lines count from 1 (the tape-start %)")]
    LineZero,
    /// Reading the program again failed; the text says why.
    #[error("reading the program again failed: {0}")]
    Read(String),
}

/// Reads lines from a program's bytes in pieces (sans-IO).
#[derive(Debug, Default)]
struct Lines {
    /// Bytes seen.
    offset: u64,
    /// The current line: its number, where it starts, its sequence number so far.
    line: u64,
    line_start: u64,
    /// `Some(digits)` while the line's start reads `N` and digits; `None` after anything else.
    seq: SeqScan,
}

#[derive(Debug, Default, Clone, PartialEq, Eq)]
enum SeqScan {
    /// Blanks so far.
    #[default]
    Start,
    /// `N` and these digits so far.
    Digits(String),
    /// The sequence number is complete (or the line has none).
    Done(Option<String>),
}

impl Lines {
    fn new() -> Self {
        Lines {
            line: 1,
            ..Lines::default()
        }
    }

    fn current(&self) -> Block {
        let sequence = match &self.seq {
            SeqScan::Digits(d) if !d.is_empty() => Some(format!("N{d}")),
            SeqScan::Done(s) => s.clone(),
            _ => None,
        };
        Block {
            line: self.line,
            sequence,
            offset: self.line_start,
        }
    }

    /// Takes one byte; returns the block that it completed (with its LF).
    fn byte(&mut self, b: u8) -> Option<Block> {
        let c = b & 0x7F;
        self.seq = match std::mem::take(&mut self.seq) {
            SeqScan::Start if c == b' ' || c == b'\t' => SeqScan::Start,
            SeqScan::Start if c == b'N' => SeqScan::Digits(String::new()),
            SeqScan::Digits(mut d) if c.is_ascii_digit() && d.len() < 9 => {
                d.push(char::from(c));
                SeqScan::Digits(d)
            }
            SeqScan::Digits(d) => SeqScan::Done((!d.is_empty()).then(|| format!("N{d}"))),
            SeqScan::Start => SeqScan::Done(None),
            done => done,
        };
        self.offset += 1;
        if c == LF {
            let block = self.current();
            self.line += 1;
            self.line_start = self.offset;
            self.seq = SeqScan::Start;
            return Some(block);
        }
        None
    }
}

/// The number of a sequence number as written (`N0010` is block 10, §8's leading zeros
/// being optional).
fn sequence_value(sequence: Option<&str>) -> Option<u64> {
    sequence?.strip_prefix('N')?.parse().ok()
}

/// Whether `block` is the start `at` asks for.
fn is_start(block: &Block, at: StartAt) -> bool {
    match at {
        StartAt::Line(l) => block.line == l,
        StartAt::Sequence(s) => sequence_value(block.sequence.as_deref()) == Some(s),
    }
}

/// Finds the block that holds byte `offset` of a program fed in pieces: the first block the
/// board does not hold whole when it acknowledged `offset` bytes.
#[derive(Debug)]
pub struct BlockAt {
    lines: Lines,
    offset: u64,
    found: bool,
}

impl BlockAt {
    /// A search for the block holding byte `offset`.
    pub fn new(offset: u64) -> Self {
        BlockAt {
            lines: Lines::new(),
            offset,
            found: false,
        }
    }

    /// The next piece of the program; the block once it is known.
    pub fn feed(&mut self, piece: &[u8]) -> Option<Block> {
        for &b in piece {
            self.found |= self.lines.offset == self.offset;
            let ended = self.lines.byte(b);
            if self.found {
                // Read on until the line's sequence number is known.
                if let Some(block) = ended {
                    return Some(block);
                }
                if matches!(self.lines.seq, SeqScan::Done(_)) {
                    return Some(self.lines.current());
                }
            }
        }
        None
    }

    /// The program ended: the block within its last line, or `None` when `offset` is past
    /// the end.
    pub fn finish(self) -> Option<Block> {
        self.found.then(|| self.lines.current())
    }
}

/// Finds where a job that starts at `at` begins, fed the program in pieces:
/// `(header_end, start block)`, the header being the first `header_lines` lines, or (0)
/// every line before the first block with a sequence number, and never reaching past the
/// start block.
#[derive(Debug)]
pub struct StartSearch {
    at: StartAt,
    header_lines: u32,
    lines: Lines,
    header_end: Option<u64>,
    last: Option<Block>,
}

impl StartSearch {
    /// A search for `at`; line 0 is no line.
    pub fn new(at: StartAt, header_lines: u32) -> Result<Self, BlockError> {
        if at == StartAt::Line(0) {
            return Err(BlockError::LineZero);
        }
        Ok(StartSearch {
            at,
            header_lines,
            lines: Lines::new(),
            header_end: None,
            last: None,
        })
    }

    /// The next piece of the program; the start once it is found.
    pub fn feed(&mut self, piece: &[u8]) -> Option<(u64, Block)> {
        for &b in piece {
            let Some(block) = self.lines.byte(b) else {
                continue;
            };
            if self.header_lines > 0 && block.line == u64::from(self.header_lines) {
                self.header_end.get_or_insert(self.lines.offset);
            }
            if self.header_lines == 0 && block.sequence.is_some() {
                self.header_end.get_or_insert(block.offset);
            }
            if is_start(&block, self.at) {
                let header = self.header_end.unwrap_or(block.offset).min(block.offset);
                return Some((header, block));
            }
            self.last = Some(block);
        }
        None
    }

    /// The program ended without the start found so far: a last line without LF (the EOR
    /// line) is a block too.
    pub fn finish(mut self) -> Result<(u64, Block), BlockError> {
        let tail = self.lines.current();
        if self.lines.offset > tail.offset {
            if is_start(&tail, self.at) {
                let header = self.header_end.unwrap_or(tail.offset).min(tail.offset);
                return Ok((header, tail));
            }
            self.last = Some(tail);
        }
        Err(match self.at {
            StartAt::Sequence(s) => BlockError::NoSequence(s),
            StartAt::Line(line) => BlockError::NoLine {
                line,
                lines: self.last.map_or(0, |b| b.line),
            },
        })
    }
}

/// [`BlockAt`] over a program held whole.
pub fn block_at(program: &[u8], offset: u64) -> Option<Block> {
    let mut search = BlockAt::new(offset);
    search.feed(program).or_else(|| search.finish())
}

/// [`StartSearch`] over a program held whole.
pub fn find_start(
    program: &[u8],
    at: StartAt,
    header_lines: u32,
) -> Result<(u64, Block), BlockError> {
    let mut search = StartSearch::new(at, header_lines)?;
    match search.feed(program) {
        Some(found) => Ok(found),
        None => search.finish(),
    }
}

#[cfg(test)]
mod tests;
