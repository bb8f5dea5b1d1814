//! The block being fed: of the program bytes a job hands to its link, the last block the
//! remote buffer acknowledged whole. The CNC executes blocks from the buffer as it reads them
//! (remote-buffer operation, §1), so this is the furthest block the CNC can have reached,
//! not the one it executes: it may still be working through the blocks the buffer holds
//! (SAT bytes 5–8, §4.4.2).
//!
//! Only the bytes between the last question and the last byte handed over are kept, with the
//! start of the line that runs across them, so a job's memory does not grow with its program.

use std::collections::VecDeque;
use std::sync::Arc;

/// Characters of a block kept: enough for any block a person reads on a screen.
pub const MAX_BLOCK_TEXT: usize = 128;

/// Follows a job's program bytes and its acknowledged offset.
#[derive(Debug, Default)]
pub struct FedBlocks {
    /// Program bytes from offset `base` on, handed over and not yet asked about.
    window: VecDeque<u8>,
    base: u64,
    /// The first bytes of the line that runs across `base` (its part before `base`).
    head: Vec<u8>,
    last: Option<Arc<str>>,
}

impl FedBlocks {
    /// Nothing handed over yet.
    pub fn new() -> Self {
        FedBlocks::default()
    }

    /// Program bytes handed to the link, in order.
    pub fn push(&mut self, bytes: &[u8]) {
        self.window.extend(bytes);
    }

    /// The last block wholly inside the first `acked` bytes: a line ending with LF whose
    /// text is more than a tape mark (`%`) or blanks. `None` until there is one.
    pub fn acked(&mut self, acked: u64) -> Option<Arc<str>> {
        let k = usize::try_from(acked.saturating_sub(self.base))
            .unwrap_or(usize::MAX)
            .min(self.window.len());
        if k == 0 {
            return self.last.clone();
        }
        let taken: Vec<u8> = self.window.drain(..k).collect();
        self.base += k as u64;
        // The lines that ended within what was taken, last first: the last block of them.
        if let Some(end) = taken.iter().rposition(|b| *b == b'\n') {
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
                    self.last = Some(text);
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
        } else {
            let room = MAX_BLOCK_TEXT.saturating_sub(self.head.len());
            self.head.extend(taken.iter().take(room));
        }
        self.last.clone()
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
