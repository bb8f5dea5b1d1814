//! The block being fed: of the program bytes a link has sent (what its engine reports with
//! `EngineEvent::DataSent`), the last block the remote buffer acknowledged whole. The CNC
//! executes blocks from the buffer as it reads them (remote-buffer operation, §1), so this is
//! the furthest block the CNC can have reached, not the one it executes: it may still be
//! working through the blocks the buffer holds (SAT bytes 5–8, §4.4.2).
//!
//! Kept: the bytes sent since the last question, with the start of the line that runs across
//! them, but only the last [`SENT_KEPT`] of them: a board answers for what was sent lately (a
//! DAT, the packets of a run), and an Expansion A board whose CNC reads as fast as the line
//! asks nothing until the program's end (§5.3), which would otherwise keep the whole program.
//! Of the bytes let go, the last block of every [`LET_GO_STEP`] is remembered (at most
//! [`LET_GO_KEPT`] of them, thinned evenly and coarser when more): a Protocol B line acknowledges only
//! what reached the board before its next control code, so what was sent may run far ahead
//! of what is acknowledged, and the block being fed must still move as the acknowledgements
//! come. A job's memory does not grow with its program.

use std::collections::VecDeque;
use std::sync::Arc;

use crate::fanuc::program::take_front;

/// Characters of a block kept: enough for any block a person reads on a screen.
pub const MAX_BLOCK_TEXT: usize = 128;

/// Bytes already sent that are kept for the next question. An answer acknowledging bytes sent
/// earlier than these names the last block of what was let go, if it lies within the answer.
/// 8 KiB: two DATs at their largest (4096 bytes), eight Expansion A packets of n = 4, a second
/// of an 86400-baud line.
pub const SENT_KEPT: usize = 8 * 1024;

/// Of the bytes let go, one block is remembered for each this many.
pub const LET_GO_STEP: usize = 1024;

/// Blocks of the bytes let go remembered at most.
pub const LET_GO_KEPT: usize = 32;

/// Follows a job's program bytes and its acknowledged offset.
#[derive(Debug, Default)]
pub struct FedBlocks {
    /// Program bytes from offset `base` on, sent and not yet asked about.
    window: VecDeque<u8>,
    base: u64,
    /// The first bytes of the line that runs across `base` (its part before `base`).
    head: Vec<u8>,
    last: Option<Arc<str>>,
    /// Blocks of the bytes let go unasked (see [`SENT_KEPT`]), each with where it ends, in
    /// order.
    let_go: VecDeque<(u64, Arc<str>)>,
    /// The least distance between two of `let_go`: [`LET_GO_STEP`], doubled at each
    /// thinning, back to it once all were answered for.
    grain: u64,
}

impl FedBlocks {
    /// Nothing sent yet.
    pub fn new() -> Self {
        FedBlocks {
            grain: LET_GO_STEP as u64,
            ..FedBlocks::default()
        }
    }

    /// Program bytes sent, in order.
    pub fn push(&mut self, bytes: &[u8]) {
        // Grown no further than it is filled ([`SENT_KEPT`] and a piece).
        self.window.reserve_exact(bytes.len());
        self.window.extend(bytes);
    }

    /// The link has put the first `sent` bytes on the line: of those, only the last
    /// [`SENT_KEPT`] are kept.
    pub fn sent(&mut self, sent: u64) {
        let keep_from = sent.saturating_sub(SENT_KEPT as u64);
        let n = usize::try_from(keep_from.saturating_sub(self.base))
            .unwrap_or(usize::MAX)
            .min(self.window.len());
        let mut left = n;
        while left > 0 {
            let step = left.min(LET_GO_STEP);
            left -= step;
            let start = self.base;
            let found = self.last_block_in_front(step);
            self.base += step as u64;
            if let Some((end, text)) = found {
                let end = start + end as u64;
                // The last one moves on while it is within a grain of the one before it;
                // once a grain away, it stays and the next is added.
                let before = (self.let_go.len().checked_sub(2))
                    .and_then(|i| self.let_go.get(i))
                    .map(|e| e.0);
                match (before, self.let_go.back_mut()) {
                    (Some(before), Some(last)) if last.0 < before + self.grain => {
                        *last = (end, text)
                    }
                    _ => self.let_go.push_back((end, text)),
                }
                if self.let_go.len() > LET_GO_KEPT {
                    // Thinned evenly, and coarser from now on: the blocks still span all
                    // that was let go.
                    let mut i = 0;
                    self.let_go.retain(|_| {
                        i += 1;
                        i % 2 == 0
                    });
                    self.grain *= 2;
                }
            }
        }
    }

    /// Program bytes held.
    pub fn held(&self) -> usize {
        self.window.len() + self.head.len()
    }

    /// The last block wholly inside the first `acked` bytes: a line ending with LF whose
    /// text is more than a tape mark (`%`) or blanks. `None` until there is one.
    pub fn acked(&mut self, acked: u64) -> Option<Arc<str>> {
        while let Some((end, _)) = self.let_go.front()
            && *end <= acked
        {
            self.last = self.let_go.pop_front().map(|(_, text)| text);
            if self.let_go.is_empty() {
                self.grain = LET_GO_STEP as u64;
            }
        }
        let k = usize::try_from(acked.saturating_sub(self.base))
            .unwrap_or(usize::MAX)
            .min(self.window.len());
        if k == 0 {
            return self.last.clone();
        }
        let found = self.last_block_in_front(k);
        self.base += k as u64;
        if let Some((_, text)) = found {
            self.last = Some(text);
        }
        self.last.clone()
    }

    /// [`FedBlocks::last_block_in`] the first `n` bytes of the window, which are let go.
    fn last_block_in_front(&mut self, n: usize) -> Option<(usize, Arc<str>)> {
        let taken = take_front(&mut self.window, n);
        self.last_block_in(&taken)
    }

    /// The last block of the lines that end within `taken` (the bytes after the ones taken
    /// before), and the length of `taken` through its line end; the line left open is kept
    /// as the next one's start.
    fn last_block_in(&mut self, taken: &[u8]) -> Option<(usize, Arc<str>)> {
        let Some(end) = taken.iter().rposition(|b| *b == b'\n') else {
            let room = MAX_BLOCK_TEXT.saturating_sub(self.head.len());
            self.head.extend(taken.iter().take(room));
            return None;
        };
        // The lines that ended within what was taken, last first: the last block of them.
        let mut found = None;
        let mut line_end = end;
        loop {
            let start = taken
                .get(..line_end)
                .and_then(|t| t.iter().rposition(|b| *b == b'\n'));
            let line: Vec<u8> = match start {
                Some(s) => taken.get(s + 1..line_end).unwrap_or_default().to_vec(),
                None => {
                    let mut l = std::mem::take(&mut self.head);
                    l.extend(taken.get(..line_end).unwrap_or_default());
                    l
                }
            };
            if let Some(text) = block_text(&line) {
                found = Some((line_end + 1, text));
                break;
            }
            match start {
                Some(s) => line_end = s,
                None => break,
            }
        }
        self.head.clear();
        let rest = taken.get(end + 1..).unwrap_or_default();
        self.head.extend(rest.iter().take(MAX_BLOCK_TEXT));
        found
    }
}

/// A line's text as a block: CR and blanks trimmed, at most [`MAX_BLOCK_TEXT`] characters;
/// `None` for a tape mark or an empty line.
fn block_text(line: &[u8]) -> Option<Arc<str>> {
    let text = String::from_utf8_lossy(line);
    let text = text.trim_matches(|c: char| c == '\r' || c.is_whitespace());
    if text.is_empty() || text == "%" {
        return None;
    }
    Some(text.chars().take(MAX_BLOCK_TEXT).collect::<String>().into())
}

#[cfg(test)]
mod tests;
