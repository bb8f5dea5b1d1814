//! Comparing two NC programs block by block, as a DNC host's compare does: a block is a
//! line of the program text (EOB: LF, CR LF or CR), and options leave out what does not
//! change what the CNC does — sequence numbers, blanks, comments.
//!
//! The line alignment itself is the `similar` crate's (Myers); this module decides what a
//! block is, what the options ignore, and how the edits are counted: a run of removed blocks
//! followed by added ones counts its pairs as changed blocks and the rest as removed or
//! added.

use similar::{Algorithm, DiffOp, capture_diff_slices, group_diff_ops};

use crate::pb;

/// What a comparison leaves out.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DiffOptions {
    /// `N` and its digits at the start of a block (after blanks and a block delete `/`).
    pub sequence: bool,
    /// Spaces and tabs.
    pub blanks: bool,
    /// Comments, `(` to the next `)` (or to the end of the block when it is not closed).
    pub comments: bool,
}

/// An `ignore` list that cannot be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("ignore: unknown option {0:?}; the options are sequence, blanks, comments")]
pub struct UnknownOption(pub String);

impl DiffOptions {
    /// The options of a comma-separated list (`sequence,blanks,comments`; empty: none).
    pub fn parse(list: &str) -> Result<Self, UnknownOption> {
        let mut o = DiffOptions::default();
        for item in list.split(',').map(str::trim).filter(|i| !i.is_empty()) {
            match item {
                "sequence" | "seq" => o.sequence = true,
                "blanks" | "blank" => o.blanks = true,
                "comments" | "comment" => o.comments = true,
                other => return Err(UnknownOption(other.to_string())),
            }
        }
        Ok(o)
    }

    /// The options set, by name, as [`DiffOptions::parse`] reads them.
    pub fn names(&self) -> Vec<String> {
        [
            (self.sequence, "sequence"),
            (self.blanks, "blanks"),
            (self.comments, "comments"),
        ]
        .into_iter()
        .filter(|(on, _)| *on)
        .map(|(_, n)| n.to_string())
        .collect()
    }

    fn any(&self) -> bool {
        self.sequence || self.blanks || self.comments
    }
}

/// A program that is not NC text, so has no blocks to compare.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{which} is not NC program text: byte {offset} is {byte:#04x} (programs are 7-bit text)")]
pub struct NotText {
    /// `a` or `b`.
    pub which: &'static str,
    /// Where the first byte that is not text stands.
    pub offset: usize,
    /// That byte.
    pub byte: u8,
}

/// The counts of a comparison.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DiffCounts {
    /// Blocks only in `b`.
    pub added: u32,
    /// Blocks only in `a`.
    pub removed: u32,
    /// Blocks of `a` that `b` has in another form.
    pub changed: u32,
}

impl DiffCounts {
    /// No block differs.
    pub fn same(&self) -> bool {
        self.added == 0 && self.removed == 0 && self.changed == 0
    }
}

/// A block of a program: its text as it stands, its line number, and the form compared.
#[derive(Debug)]
struct Block<'a> {
    text: &'a str,
    line: u32,
    key: String,
}

/// The blocks of `program` to compare, or where it is not text.
fn blocks<'a>(
    which: &'static str,
    program: &'a [u8],
    o: DiffOptions,
) -> Result<Vec<Block<'a>>, NotText> {
    if let Some(offset) = program
        .iter()
        .position(|&b| b >= 0x80 || (b < 0x20 && !matches!(b, b'\n' | b'\r' | b'\t')))
    {
        return Err(NotText {
            which,
            offset,
            byte: program[offset],
        });
    }
    // Only ASCII is left, so this cannot fail.
    let text = std::str::from_utf8(program).map_err(|e| NotText {
        which,
        offset: e.valid_up_to(),
        byte: program[e.valid_up_to()],
    })?;
    let mut out = Vec::new();
    for (i, raw) in split_blocks(text).into_iter().enumerate() {
        let line = u32::try_from(i + 1).unwrap_or(u32::MAX);
        let key = normalise(raw, o);
        // A block that held only what is ignored (a comment line, a bare `N10`, blanks)
        // leaves nothing to compare; without options every line counts, empty ones too.
        if o.any() && key.is_empty() {
            continue;
        }
        out.push(Block {
            text: raw,
            line,
            key,
        });
    }
    Ok(out)
}

/// Lines of `text`, ended by LF, CR LF or CR; a last line without EOB counts when not empty.
fn split_blocks(text: &str) -> Vec<&str> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find(['\n', '\r']) {
        out.push(&rest[..i]);
        let skip = if rest[i..].starts_with("\r\n") { 2 } else { 1 };
        rest = &rest[i + skip..];
    }
    if !rest.is_empty() {
        out.push(rest);
    }
    out
}

fn normalise(block: &str, o: DiffOptions) -> String {
    let mut s = block.to_string();
    if o.comments {
        let mut kept = String::with_capacity(s.len());
        let mut depth = false;
        for c in s.chars() {
            match c {
                '(' if !depth => depth = true,
                ')' if depth => depth = false,
                _ if !depth => kept.push(c),
                _ => {}
            }
        }
        s = kept;
    }
    if o.blanks {
        s.retain(|c| c != ' ' && c != '\t');
    }
    if o.sequence {
        s = strip_sequence(&s);
    }
    s
}

/// The block without its sequence number: `N` and digits after any blanks and a block
/// delete `/`, which stays.
fn strip_sequence(block: &str) -> String {
    let lead = block.len() - block.trim_start_matches([' ', '\t']).len();
    let (head, rest) = block.split_at(lead);
    let (slash, rest) = match rest.strip_prefix('/') {
        Some(r) => ("/", r),
        None => ("", rest),
    };
    let Some(after_n) = rest.strip_prefix(['N', 'n']) else {
        return block.to_string();
    };
    let digits = after_n.len()
        - after_n
            .trim_start_matches(|c: char| c.is_ascii_digit())
            .len();
    if digits == 0 {
        return block.to_string();
    }
    format!("{head}{slash}{}", &after_n[digits..])
}

/// The counts of comparing `a` with `b`.
pub fn counts(a: &[u8], b: &[u8], o: DiffOptions) -> Result<DiffCounts, NotText> {
    let (a, b) = (blocks("a", a, o)?, blocks("b", b, o)?);
    Ok(count_ops(&ops(&a, &b)))
}

fn ops(a: &[Block<'_>], b: &[Block<'_>]) -> Vec<DiffOp> {
    let ak: Vec<&str> = a.iter().map(|x| x.key.as_str()).collect();
    let bk: Vec<&str> = b.iter().map(|x| x.key.as_str()).collect();
    capture_diff_slices(Algorithm::Myers, &ak, &bk)
}

fn count_ops(ops: &[DiffOp]) -> DiffCounts {
    let mut c = DiffCounts::default();
    let n = |x: usize| u32::try_from(x).unwrap_or(u32::MAX);
    for op in ops {
        match *op {
            DiffOp::Equal { .. } => {}
            DiffOp::Delete { old_len, .. } => c.removed = c.removed.saturating_add(n(old_len)),
            DiffOp::Insert { new_len, .. } => c.added = c.added.saturating_add(n(new_len)),
            DiffOp::Replace {
                old_len, new_len, ..
            } => {
                let changed = old_len.min(new_len);
                c.changed = c.changed.saturating_add(n(changed));
                c.removed = c.removed.saturating_add(n(old_len - changed));
                c.added = c.added.saturating_add(n(new_len - changed));
            }
        }
    }
    c
}

/// Compares `a` with `b`: the counts and the hunks with `context` equal blocks around each
/// change, as the bus's `ProgramDiff` carries them (its revisions and name left to the
/// caller).
pub fn diff(
    a: &[u8],
    b: &[u8],
    o: DiffOptions,
    context: usize,
) -> Result<(DiffCounts, Vec<pb::DiffHunk>), NotText> {
    let (a, b) = (blocks("a", a, o)?, blocks("b", b, o)?);
    let ops = ops(&a, &b);
    let counts = count_ops(&ops);
    let line = |op: pb::diff_line::Op, text: &str, al: u32, bl: u32, changed: bool| pb::DiffLine {
        op: op as i32,
        text: text.to_string(),
        a_line: al,
        b_line: bl,
        changed,
    };
    let mut hunks = Vec::new();
    for group in group_diff_ops(ops, context) {
        let mut lines = Vec::new();
        let (mut a_line, mut b_line) = (0, 0);
        for op in &group {
            match *op {
                DiffOp::Equal {
                    old_index,
                    new_index,
                    len,
                } => {
                    for i in 0..len {
                        let (x, y) = (&a[old_index + i], &b[new_index + i]);
                        lines.push(line(
                            pb::diff_line::Op::Equal,
                            y.text,
                            x.line,
                            y.line,
                            false,
                        ));
                    }
                }
                DiffOp::Delete {
                    old_index, old_len, ..
                } => {
                    for x in &a[old_index..old_index + old_len] {
                        lines.push(line(pb::diff_line::Op::Removed, x.text, x.line, 0, false));
                    }
                }
                DiffOp::Insert {
                    new_index, new_len, ..
                } => {
                    for y in &b[new_index..new_index + new_len] {
                        lines.push(line(pb::diff_line::Op::Added, y.text, 0, y.line, false));
                    }
                }
                DiffOp::Replace {
                    old_index,
                    old_len,
                    new_index,
                    new_len,
                } => {
                    let changed = old_len.min(new_len);
                    for (i, x) in a[old_index..old_index + old_len].iter().enumerate() {
                        let c = i < changed;
                        lines.push(line(pb::diff_line::Op::Removed, x.text, x.line, 0, c));
                    }
                    for (i, y) in b[new_index..new_index + new_len].iter().enumerate() {
                        let c = i < changed;
                        lines.push(line(pb::diff_line::Op::Added, y.text, 0, y.line, c));
                    }
                }
            }
        }
        if let Some(first) = group.first() {
            let (ai, bi) = (first.old_range().start, first.new_range().start);
            a_line = a
                .get(ai)
                .map_or(a.last().map_or(0, |x| x.line + 1), |x| x.line);
            b_line = b
                .get(bi)
                .map_or(b.last().map_or(0, |x| x.line + 1), |x| x.line);
        }
        hunks.push(pb::DiffHunk {
            a_line,
            b_line,
            lines,
        });
    }
    Ok((counts, hunks))
}

#[cfg(test)]
mod tests;
