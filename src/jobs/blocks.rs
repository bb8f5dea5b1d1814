//! Blocks of a program: where one starts, its line and its sequence number (`N1234`), so
//! that a job can start at a block and a failed one resume at the first block the board did
//! not acknowledge whole (DNC "restart from block N").
//!
//! A block is a line: it ends with LF (the EOB of ISO and ASCII programs as the gateway
//! takes them). Its sequence number is an `N` and digits at its start, after blanks. The
//! header of a program is its lines before the first block with a sequence number (the
//! tape-start `%`, the O-number, comments and modal set-up), or a count of lines the request
//! gives; a job that starts at a block sends the header first.

use tokio::io::{AsyncRead, AsyncReadExt};

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
    Line(u64),
    Sequence(u64),
}

/// Why a start cannot be found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum BlockError {
    #[error("the program has no block N{0}")]
    NoSequence(u64),
    #[error("the program has {lines} lines: line {line} is not one of its blocks")]
    NoLine { line: u64, lines: u64 },
    #[error("line 0 is not a line: lines count from 1 (the tape-start %)")]
    LineZero,
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

const CHUNK: usize = 64 * 1024;

async fn read_chunk<R: AsyncRead + Unpin>(r: &mut R, buf: &mut [u8]) -> Result<usize, BlockError> {
    r.read(buf)
        .await
        .map_err(|e| BlockError::Read(e.to_string()))
}

/// The block that holds byte `offset` of the program: the first block the board does not
/// hold whole when it acknowledged `offset` bytes. `None` when `offset` is past the end.
pub async fn block_at<R: AsyncRead + Unpin>(
    mut program: R,
    offset: u64,
) -> Result<Option<Block>, BlockError> {
    let mut lines = Lines::new();
    let mut found = false;
    let mut buf = vec![0u8; CHUNK];
    loop {
        let n = read_chunk(&mut program, &mut buf).await?;
        if n == 0 {
            // The program ended: within its last line, or before `offset`.
            return Ok(found.then(|| lines.current()));
        }
        for &b in buf.iter().take(n) {
            found |= lines.offset == offset;
            let ended = lines.byte(b);
            if found {
                // Read on until the line's sequence number is known.
                if let Some(block) = ended {
                    return Ok(Some(block));
                }
                if matches!(lines.seq, SeqScan::Done(_)) {
                    return Ok(Some(lines.current()));
                }
            }
        }
    }
}

/// Where a job that starts at `at` begins: `(header_end, start block)`, the header being the
/// first `header_lines` lines, or (0) every line before the first block with a sequence
/// number, and never reaching past the start block.
pub async fn find_start<R: AsyncRead + Unpin>(
    mut program: R,
    at: StartAt,
    header_lines: u32,
) -> Result<(u64, Block), BlockError> {
    if at == StartAt::Line(0) {
        return Err(BlockError::LineZero);
    }
    let mut lines = Lines::new();
    let mut buf = vec![0u8; CHUNK];
    let mut header_end: Option<u64> = None;
    let mut last: Option<Block> = None;
    loop {
        let n = read_chunk(&mut program, &mut buf).await?;
        for &b in buf.iter().take(n) {
            let Some(block) = lines.byte(b) else { continue };
            if header_lines > 0 && block.line == u64::from(header_lines) {
                header_end.get_or_insert(lines.offset);
            }
            if header_lines == 0 && block.sequence.is_some() {
                header_end.get_or_insert(block.offset);
            }
            let found = match at {
                StartAt::Line(l) => block.line == l,
                StartAt::Sequence(s) => block.sequence.as_deref() == Some(&format!("N{s}")),
            };
            if found {
                let header = header_end.unwrap_or(block.offset).min(block.offset);
                return Ok((header, block));
            }
            last = Some(block);
        }
        if n == 0 {
            // A last line without LF (the EOR line) is a block too.
            let tail = lines.current();
            if lines.offset > tail.offset {
                let found = match at {
                    StartAt::Line(l) => tail.line == l,
                    StartAt::Sequence(s) => tail.sequence.as_deref() == Some(&format!("N{s}")),
                };
                if found {
                    let header = header_end.unwrap_or(tail.offset).min(tail.offset);
                    return Ok((header, tail));
                }
                last = Some(tail);
            }
            return Err(match at {
                StartAt::Sequence(s) => BlockError::NoSequence(s),
                StartAt::Line(line) => BlockError::NoLine {
                    line,
                    lines: last.map_or(0, |b| b.line),
                },
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PROGRAM: &[u8] = b"%\nO1234 (BRACKET)\nG90 G54\n N10 G01 X1\nN20 X2\nN30X3\nM30\n%";

    #[tokio::test]
    async fn the_block_holding_an_offset() {
        let at = |o| block_at(PROGRAM, o);
        let b = at(0).await.unwrap().unwrap();
        assert_eq!((b.line, b.sequence.as_deref(), b.offset), (1, None, 0));
        // The first byte of line 4, and one in its middle: the same block.
        let start4 = PROGRAM.windows(4).position(|w| w == b" N10").unwrap() as u64;
        for o in [start4, start4 + 5] {
            let b = at(o).await.unwrap().unwrap();
            assert_eq!(
                (b.line, b.sequence.as_deref(), b.offset),
                (4, Some("N10"), start4)
            );
        }
        let start6 = PROGRAM.windows(3).position(|w| w == b"N30").unwrap() as u64;
        let b = at(start6).await.unwrap().unwrap();
        assert_eq!((b.line, b.sequence.as_deref()), (6, Some("N30")));
        let b = at(PROGRAM.len() as u64 - 1).await.unwrap().unwrap();
        assert_eq!((b.line, b.sequence), (8, None));
        assert_eq!(at(PROGRAM.len() as u64).await.unwrap(), None);
    }

    #[tokio::test]
    async fn starts_by_sequence_number_or_line_with_the_header_before() {
        let header = b"%\nO1234 (BRACKET)\nG90 G54\n".len() as u64;
        let (h, b) = find_start(PROGRAM, StartAt::Sequence(20), 0).await.unwrap();
        assert_eq!((h, b.line, b.sequence.as_deref()), (header, 5, Some("N20")));
        let (h, b) = find_start(PROGRAM, StartAt::Line(7), 0).await.unwrap();
        assert_eq!((h, b.line), (header, 7));
        // A header of two lines.
        let (h, _) = find_start(PROGRAM, StartAt::Line(6), 2).await.unwrap();
        assert_eq!(h, b"%\nO1234 (BRACKET)\n".len() as u64);
        // A start inside the header: the header stops before it.
        let (h, b) = find_start(PROGRAM, StartAt::Line(2), 0).await.unwrap();
        assert_eq!((h, b.offset), (2, 2));
        // The EOR line, without LF.
        let (_, b) = find_start(PROGRAM, StartAt::Line(8), 0).await.unwrap();
        assert_eq!(b.offset, PROGRAM.len() as u64 - 1);
        assert_eq!(
            find_start(PROGRAM, StartAt::Sequence(99), 0).await,
            Err(BlockError::NoSequence(99))
        );
        assert_eq!(
            find_start(PROGRAM, StartAt::Line(50), 0).await,
            Err(BlockError::NoLine { line: 50, lines: 8 })
        );
        assert_eq!(
            find_start(PROGRAM, StartAt::Line(0), 0).await,
            Err(BlockError::LineZero)
        );
    }
}
