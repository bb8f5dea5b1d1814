//! Programs a CNC punches out to the host (Protocol B punch-out, DC2 … DC4, §6.1.1 2):
//! split into programs and decoded to text ([`PunchAssembler`]), named for the library
//! ([`library_name`]), and recognised as remote requests for a program ([`RequestPatterns`]).
//!
//! Sans-IO: bytes in, programs out; no clock (the caller passes the time for names).
//!
//! # Splitting (protocol notes 8)
//!
//! A program starts at a tape-start mark and runs through its EOR: the first mark before any
//! significant character is the tape start (marks repeated before the text are tape starts
//! too), the next mark is EOR. The mark is `%` in ISO (A5h) and ASCII (25h), ER (0Bh) in
//! EIA. Significant bytes before a tape-start mark (after the previous EOR, or at the start
//! of the punch-out) belong to no program: they are skipped and reported once as
//! [`PunchError::OutsideProgram`], so a lost tape-start mark costs that one program and the
//! next `%` resynchronises. Blanks (feed, delete, space, tab, EOB) there are not reported.
//!
//! The code is only known for sure from a whole program ([`tape::detect`]), so the assembler
//! keeps each program's raw bytes until its EOR, then decodes the program as a whole. To
//! find the marks it needs only to tell EIA from the others:
//! - a program's tape-start mark fixes its family: ER (0Bh) an EIA program, whose EOR is the
//!   next ER (25h is `V` in it); `%` (A5h, 25h) an ISO or ASCII one, whose EOR is the next
//!   `%`. The program is then decoded as EIA, or as what [`tape::decode`] finds;
//! - before a tape start, 0Bh and A5h are marks whatever came before (neither is valid in the
//!   other codes); 25h is `%` unless the punch-out looks like EIA: from an ER (0Bh) or EOB
//!   (80h) until a non-blank byte with even parity, which no EIA tape holds.
//!
//! Bounds: a program's raw bytes are limited to `max_program`; a longer one is reported as
//! [`PunchError::TooLarge`] and skipped through its EOR. Blanks between a tape-start mark and
//! the text are kept only up to 64 bytes. Nothing else is held.
//!
//! # The text
//!
//! [`PunchedText::text`] is plain 7-bit text from the tape-start `%` through the EOR `%`.
//! Feed and delete are dropped (as readers skip them) and every EOB is a single LF: the CRs
//! an ISO CNC punches after LF (LF CR CR, parameter 0000#3 NCR = 0) are dropped, so a
//! program gives the same text in every code and setting (and those CRs do not keep it
//! from a Protocol A link whose end code is CR, §4.1).
//!
//! # End of punch-out
//!
//! Bytes after the last EOR stay pending until more arrive. [`PunchAssembler::finish`] (at the
//! end of a punch-out, DC4) reports a program without EOR as
//! [`PunchError::Unterminated`] and does not hand it out: the CNC sends a program's EOR
//! last, so a program without it was cut short (STOP, reset, or a lost line).

use super::name::O_DIGITS_MAX;
use crate::fanuc::code::{CR, EOR, LF, has_even_parity, is_eor, is_significant};
use crate::program::tape::{self, EIA_EOB, EIA_ER, TapeCode, TapeError};

/// Blanks kept between a tape-start mark and the program text.
const TAPE_START_KEEP: usize = 64;

/// One program punched out by the CNC.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PunchedText {
    /// The code it was punched in.
    pub code: TapeCode,
    /// Plain 7-bit text from the tape-start `%` through the EOR `%`, EOB = LF.
    pub text: Vec<u8>,
    /// The first program number at the start of a block, `O` and the digits as punched:
    /// `O1234`, also for ISO's `:1234`.
    pub o_number: Option<String>,
    /// The first comment of the program number's block (of the first block when there is no
    /// program number), trimmed: a display name.
    pub comment: Option<String>,
    /// Why the program is not good, when the punch-out was damaged while it was punched (a
    /// line error, characters dropped): it has a character wrong or missing.
    pub damage: Option<String>,
}

impl PunchedText {
    /// The program `text` (plain, EOB = LF) with its program number and comment.
    pub fn from_text(code: TapeCode, text: Vec<u8>) -> Self {
        let (o_number, comment) = number_and_comment(&text);
        PunchedText {
            code,
            text,
            o_number,
            comment,
            damage: None,
        }
    }
}

/// Why punched bytes gave no program.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum PunchError {
    /// A program longer than the assembler holds; skipped through its EOR.
    #[error(
        "punched program starting at byte {offset} of the punch-out is longer than {max} bytes; skipped through its EOR"
    )]
    TooLarge {
        /// Where the program starts, bytes from the start of the punch-out.
        offset: u64,
        /// The most raw bytes a program may have (`max_program`).
        max: usize,
    },
    /// A program whose bytes are not valid in its code.
    #[error("punched program starting at byte {offset} of the punch-out: {error}")]
    Code {
        /// Where the program starts, bytes from the start of the punch-out.
        offset: u64,
        /// What is wrong with its bytes.
        #[source]
        error: TapeError,
    },
    /// Significant bytes before any tape-start mark; skipped.
    #[error(
        "{len} punched bytes from byte {offset} of the punch-out precede any tape-start `%` (protocol notes 8) and were skipped"
    )]
    OutsideProgram {
        /// Where the bytes start, from the start of the punch-out.
        offset: u64,
        /// Bytes skipped.
        len: u64,
    },
    /// The punch-out ended inside a program, before its EOR; the program was dropped.
    #[error(
        "the punch-out ended inside the program starting at byte {offset} ({len} bytes, no EOR `%`); it was dropped"
    )]
    Unterminated {
        /// Where the program starts, bytes from the start of the punch-out.
        offset: u64,
        /// Raw bytes of the program received.
        len: usize,
    },
}

/// Where the assembler stands (protocol notes 8).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    /// Before a tape-start mark.
    Leader,
    /// After a tape-start mark, nothing significant yet.
    TapeStart,
    /// Program text: the next mark is EOR.
    Body,
    /// A program over the size limit: its bytes are dropped through its EOR.
    Skip,
}

/// The marks and blanks of a tape: EIA, or ISO / ASCII.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Family {
    Eia,
    Percent,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Class {
    Mark,
    Blank,
    Significant,
}

/// Splits punched bytes into programs (see the module documentation).
#[derive(Debug, Clone)]
pub struct PunchAssembler {
    max_program: usize,
    state: State,
    /// The current program's raw bytes from its tape-start mark.
    raw: Vec<u8>,
    /// Offset of the current program's tape-start mark.
    start: u64,
    /// The current program's family, from its tape-start mark.
    family: Family,
    /// Bytes fed since the punch-out began.
    offset: u64,
    /// The punch-out looks like EIA (see the module documentation).
    eia: bool,
    /// Significant bytes outside any program: (offset, length).
    outside: Option<(u64, u64)>,
    /// The punch-out was damaged since the last program ended: the program in progress (or,
    /// between programs, the next one, whose tape-start may be what was lost) is not good.
    damage: Option<String>,
}

impl PunchAssembler {
    /// An assembler for programs of at most `max_program` raw bytes (at least 1).
    pub fn new(max_program: usize) -> Self {
        PunchAssembler {
            max_program: max_program.max(1),
            state: State::Leader,
            raw: Vec::new(),
            start: 0,
            family: Family::Percent,
            offset: 0,
            eia: false,
            outside: None,
            damage: None,
        }
    }

    /// The punch-out was damaged at this point (see [`PunchedText::damage`]).
    pub fn damaged(&mut self, cause: impl std::fmt::Display) {
        if self.damage.is_none() {
            self.damage = Some(cause.to_string());
        }
    }

    /// Raw bytes of the program in progress.
    pub fn pending(&self) -> usize {
        self.raw.len()
    }

    /// Takes the next punched piece, as received (parity bit included); returns every
    /// program that ended in it, and every error, in order.
    pub fn feed(&mut self, piece: &[u8]) -> Vec<Result<PunchedText, PunchError>> {
        let mut out = Vec::new();
        for &b in piece {
            self.step(b, &mut out);
            self.offset += 1;
        }
        out
    }

    /// The punch-out has ended: reports what was left open, and starts afresh for the next.
    pub fn finish(&mut self) -> Option<PunchError> {
        let left = match self.state {
            State::Leader => self.outside.take().map(outside_error),
            State::Body => Some(PunchError::Unterminated {
                offset: self.start,
                len: self.raw.len(),
            }),
            State::TapeStart | State::Skip => None,
        };
        *self = PunchAssembler::new(self.max_program);
        left
    }

    /// What `b` is in a tape of `family`.
    fn classify(b: u8, family: Family) -> Class {
        match family {
            Family::Eia => match b {
                EIA_ER => Class::Mark,
                0x00 | 0x7F | EIA_EOB | 0x10 | 0x3E | 0x7A | 0x7C => Class::Blank,
                _ => Class::Significant,
            },
            Family::Percent if is_eor(b) => Class::Mark,
            Family::Percent if is_significant(b) => Class::Significant,
            Family::Percent => Class::Blank,
        }
    }

    /// What `b` is before a program's text, and the family of the program it would start.
    fn classify_leader(&self, b: u8) -> (Class, Family) {
        let guess = match self.state {
            State::TapeStart => self.family,
            _ if self.eia => Family::Eia,
            _ => Family::Percent,
        };
        match b {
            EIA_ER => (Class::Mark, Family::Eia),
            0xA5 => (Class::Mark, Family::Percent),
            _ => (Self::classify(b, guess), guess),
        }
    }

    fn step(&mut self, b: u8, out: &mut Vec<Result<PunchedText, PunchError>>) {
        if b == EIA_ER || b == EIA_EOB {
            self.eia = true;
        } else if b != 0 && has_even_parity(b) {
            self.eia = false;
        }
        if matches!(self.state, State::Body | State::Skip) {
            let class = Self::classify(b, self.family);
            if self.state == State::Skip {
                if class == Class::Mark {
                    self.state = State::Leader;
                }
                return;
            }
            self.push(b, class, out);
            if self.state == State::Body && class == Class::Mark {
                out.push(self.program());
                self.state = State::Leader;
            }
            return;
        }
        let (class, family) = self.classify_leader(b);
        match (self.state, class) {
            (_, Class::Mark) => {
                if let Some(outside) = self.outside.take() {
                    out.push(Err(outside_error(outside)));
                }
                self.raw.clear();
                self.raw.push(b);
                self.start = self.offset;
                self.family = family;
                self.state = State::TapeStart;
            }
            (State::TapeStart, Class::Blank) => {
                if self.raw.len() < TAPE_START_KEEP.min(self.max_program) {
                    self.raw.push(b);
                }
            }
            (State::TapeStart, _) => {
                self.state = State::Body;
                self.push(b, class, out);
            }
            (_, Class::Blank) => {
                if let Some((_, len)) = self.outside.as_mut() {
                    *len += 1;
                }
            }
            (_, _) => self.outside.get_or_insert((self.offset, 0)).1 += 1,
        }
    }

    /// Appends a program byte, or drops the program once it is over the limit.
    fn push(&mut self, b: u8, class: Class, out: &mut Vec<Result<PunchedText, PunchError>>) {
        if self.raw.len() < self.max_program {
            self.raw.push(b);
            return;
        }
        out.push(Err(PunchError::TooLarge {
            offset: self.start,
            max: self.max_program,
        }));
        self.raw = Vec::new();
        self.damage = None;
        self.state = if class == Class::Mark {
            State::Leader
        } else {
            State::Skip
        };
    }

    /// The program held, decoded.
    fn program(&mut self) -> Result<PunchedText, PunchError> {
        let raw = std::mem::take(&mut self.raw);
        let damage = self.damage.take();
        let decoded = match self.family {
            Family::Eia => tape::decode_as(&raw, TapeCode::Eia).map(|t| (TapeCode::Eia, t)),
            // All odd parity with EIA marks, yet started by `%`: no ISO or ASCII tape.
            Family::Percent if tape::detect(&raw) == TapeCode::Eia => {
                tape::decode_as(&raw, TapeCode::Iso).map(|t| (TapeCode::Iso, t))
            }
            Family::Percent => tape::decode(&raw),
        };
        let (code, text) = decoded.map_err(|error| PunchError::Code {
            offset: self.start,
            error,
        })?;
        let mut program = PunchedText::from_text(code, single_lf_eob(text));
        program.damage = damage;
        Ok(program)
    }
}

fn outside_error((offset, len): (u64, u64)) -> PunchError {
    PunchError::OutsideProgram { offset, len }
}

/// Drops the CRs that follow an LF (the ISO EOB LF CR CR of 0000#3 NCR = 0).
fn single_lf_eob(text: Vec<u8>) -> Vec<u8> {
    let mut out = Vec::with_capacity(text.len());
    let mut after_lf = false;
    for b in text {
        if b == CR && after_lf {
            continue;
        }
        after_lf = b == LF;
        out.push(b);
    }
    out
}

/// Longest comment kept as a display name.
const COMMENT_MAX: usize = 64;

fn is_blank(b: u8) -> bool {
    matches!(b, b' ' | b'\t' | CR | 0x00 | 0x7F)
}

/// The program number of a block that starts with one: `O1234` or `:1234` → "O1234".
fn block_number(block: &[u8]) -> Option<String> {
    let mut rest = block
        .iter()
        .copied()
        .skip_while(|&b| is_blank(b) || b == EOR);
    if !matches!(rest.next()?, b'O' | b'o' | b':') {
        return None;
    }
    let digits: String = rest
        .take_while(u8::is_ascii_digit)
        .map(char::from)
        .collect();
    (1..=O_DIGITS_MAX)
        .contains(&digits.len())
        .then(|| format!("O{digits}"))
}

/// The first complete comment of a block, trimmed, printable characters only.
fn block_comment(block: &[u8]) -> Option<String> {
    let open = block.iter().position(|&b| b == b'(')?;
    let body = block.get(open + 1..)?;
    let close = body.iter().position(|&b| b == b')')?;
    let comment: String = body
        .get(..close)?
        .iter()
        .map(|&b| {
            if b.is_ascii_graphic() {
                char::from(b)
            } else {
                ' '
            }
        })
        .collect();
    let comment: String = comment.trim().chars().take(COMMENT_MAX).collect();
    let comment = comment.trim_end();
    (!comment.is_empty()).then(|| comment.to_string())
}

fn number_and_comment(text: &[u8]) -> (Option<String>, Option<String>) {
    let mut first = None;
    for block in text.split(|&b| b == LF) {
        if block.iter().all(|&b| is_blank(b) || b == EOR) {
            continue;
        }
        first.get_or_insert(block);
        if let Some(o) = block_number(block) {
            return (Some(o), block_comment(block));
        }
    }
    (None, first.and_then(block_comment))
}

/// Most `-2`, `-3`... suffixes [`library_name`] tries.
pub const NAME_SUFFIX_MAX: u32 = 9999;

/// Longest machine part of a library name, so that the name stays within the library's 128.
const MACHINE_PART_MAX: usize = 64;

/// The library name for a punched program: `<machine>-<O-number>-<UTC time>`, e.g.
/// `mill-1-O1234-20261122T061500Z`, or `<machine>-punch-<UTC time>` without a program
/// number. The time is to the second, without `:` (the name is one key chunk). When
/// `exists` says a name is taken, `-2`, `-3`... is appended; `None` when all up to
/// [`NAME_SUFFIX_MAX`] are taken.
///
/// Machine and program number are reduced to library name characters (`A-Z a-z 0-9 . _ + -`,
/// others become `_`; leading non-alphanumerics dropped; the machine part is cut at 64), so
/// the name is a valid library name and zenoh key chunk (no `/ * $ ? #`).
pub fn library_name(
    machine: &str,
    o_number: Option<&str>,
    unix_ms: u64,
    exists: impl Fn(&str) -> bool,
) -> Option<String> {
    let machine = name_part(machine, MACHINE_PART_MAX);
    let machine = if machine.is_empty() {
        "machine".to_string()
    } else {
        machine
    };
    let program = o_number
        .map(|o| name_part(o, O_DIGITS_MAX + 1))
        .filter(|o| !o.is_empty())
        .unwrap_or_else(|| "punch".to_string());
    let base = format!("{machine}-{program}-{}", compact_utc(unix_ms));
    if !exists(&base) {
        return Some(base);
    }
    (2..=NAME_SUFFIX_MAX)
        .map(|n| format!("{base}-{n}"))
        .find(|name| !exists(name))
}

/// Whether `name` is one [`library_name`] gives a program `machine` punched:
/// `<machine>-<O-number or punch>-<YYYYMMDDTHHMMSSZ>`, maybe with `-<n>`.
pub fn is_punched_name(machine: &str, name: &str) -> bool {
    let machine = name_part(machine, MACHINE_PART_MAX);
    let Some(rest) = name
        .strip_prefix(machine.as_str())
        .and_then(|r| r.strip_prefix('-'))
    else {
        return false;
    };
    let is_stamp = |s: &str| {
        let b = s.as_bytes();
        b.len() == 16
            && b[8] == b'T'
            && b[15] == b'Z'
            && b[..8].iter().chain(&b[9..15]).all(u8::is_ascii_digit)
    };
    // `<program>-<stamp>` or `<program>-<stamp>-<n>`; the program part is the O-number or
    // `punch`, so a machine whose name starts another's (`lathe`, `lathe-1`) takes only its own.
    let parts: Vec<&str> = rest.split('-').collect();
    let (program, stamp) = match parts.as_slice() {
        [program, stamp] => (*program, *stamp),
        [program, stamp, n] if n.parse::<u32>().is_ok() => (*program, *stamp),
        _ => return false,
    };
    let program_ok = program == "punch"
        || program
            .strip_prefix('O')
            .is_some_and(|d| !d.is_empty() && d.bytes().all(|b| b.is_ascii_digit()));
    program_ok && is_stamp(stamp)
}

/// `s` in library name characters, starting with a letter or digit, at most `max` long.
fn name_part(s: &str, max: usize) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '+' | '-') {
                c
            } else {
                '_'
            }
        })
        .skip_while(|c| !c.is_ascii_alphanumeric())
        .take(max)
        .collect()
}

/// `unix_ms` as UTC `YYYYMMDDTHHMMSSZ` (ISO 8601 basic format, to the second).
pub fn compact_utc(unix_ms: u64) -> String {
    let secs = unix_ms / 1000;
    let (days, rem) = (secs / 86_400, secs % 86_400);
    let (y, m, d) = civil_from_days(days);
    format!(
        "{y:04}{m:02}{d:02}T{:02}{:02}{:02}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

/// Year, month, day of the `days`-th day after 1970-01-01 (proleptic Gregorian; H. Hinnant's
/// `civil_from_days`, for non-negative days).
pub fn civil_from_days(days: u64) -> (u64, u64, u64) {
    let z = days + 719_468;
    let era = z / 146_097;
    let doe = z % 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + u64::from(m <= 2);
    (y, m, d)
}

/// The request patterns used when the cell file names none.
pub const DEFAULT_REQUEST_PATTERNS: [&str; 2] = ["(REQ O{n})", "(PRG={n})"];

/// The placeholder for the program number in a request pattern.
const PLACEHOLDER: &str = "{n}";

/// Why a request pattern is not usable.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum PatternError {
    /// The pattern cannot be used.
    #[error("request pattern {pattern:?}: {reason}")]
    Invalid {
        /// The pattern given.
        pattern: String,
        /// Why it cannot be used.
        reason: &'static str,
    },
}

/// A program punched to ask the host for a program.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RemoteRequest {
    /// `O` and the digits without leading zeros: `O12` for `0012` (`O0` for all zeros).
    pub program: String,
    /// `O` and the digits as punched: `O0012`.
    pub written: String,
}

impl RemoteRequest {
    /// The library names to try for the requested program, in order: without leading zeros,
    /// with zeros to 4 digits (FANUC's usual `O0012`), and as punched. FANUC counts `O12`
    /// and `O0012` as the same program, so a library may hold it under either spelling.
    pub fn candidates(&self) -> Vec<String> {
        let digits = self.program.get(1..).unwrap_or_default();
        let padded = format!("O{digits:0>4}");
        let mut out = vec![self.program.clone()];
        for name in [padded, self.written.clone()] {
            if !out.contains(&name) {
                out.push(name);
            }
        }
        out
    }
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct Pattern {
    before: Vec<u8>,
    after: Vec<u8>,
}

/// Recognises a punched program that asks for a program (a remote request).
///
/// A pattern is text with one placeholder `{n}`, which stands for 1 to 8 digits: the
/// requested program number. A program is a request when its whole content is the pattern:
/// `%`, spaces, tabs, EOBs (LF, CR), feed and delete are ignored in both, and letters match
/// either case. So with the default `(REQ O{n})`, the program `%\n(req o 1234)\n%` asks
/// for O1234; a program with that comment among other blocks is no request. Patterns may not
/// contain `%` (EOR), other braces or non-printable characters, and need some text besides
/// `{n}`. The default `(PRG={n})` cannot be punched in EIA (no `=`); `(REQ O{n})` can.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RequestPatterns {
    patterns: Vec<Pattern>,
}

impl Default for RequestPatterns {
    fn default() -> Self {
        let patterns = DEFAULT_REQUEST_PATTERNS
            .iter()
            .filter_map(|p| parse_pattern(p).ok())
            .collect();
        RequestPatterns { patterns }
    }
}

fn parse_pattern(pattern: &str) -> Result<Pattern, PatternError> {
    let invalid = |reason| PatternError::Invalid {
        pattern: pattern.to_string(),
        reason,
    };
    if !pattern
        .bytes()
        .all(|b| (0x20..0x7F).contains(&b) || b == b'\t')
    {
        return Err(invalid("use only printable ASCII characters"));
    }
    if pattern.contains('%') {
        return Err(invalid(
            "`%` ends a program (EOR) and cannot be part of one",
        ));
    }
    let mut parts = pattern.split(PLACEHOLDER);
    let (Some(before), Some(after), None) = (parts.next(), parts.next(), parts.next()) else {
        return Err(invalid("it must contain {n} exactly once"));
    };
    if (before.chars().chain(after.chars())).any(|c| c == '{' || c == '}') {
        return Err(invalid("braces are only allowed in {n}"));
    }
    let before = squeeze(before.as_bytes());
    let after = squeeze(after.as_bytes());
    if before.is_empty() && after.is_empty() {
        return Err(invalid("it must hold some text besides {n}"));
    }
    Ok(Pattern { before, after })
}

/// Text without the characters a request ignores, upper case.
fn squeeze(text: &[u8]) -> Vec<u8> {
    text.iter()
        .copied()
        .filter(|&b| b != EOR && is_significant(b))
        .map(|b| b.to_ascii_uppercase())
        .collect()
}

impl RequestPatterns {
    /// Patterns that recognise no request.
    pub fn none() -> Self {
        RequestPatterns {
            patterns: Vec::new(),
        }
    }

    /// The patterns of the cell file (see [`RequestPatterns`] for the syntax). An empty list
    /// recognises no request.
    pub fn parse(patterns: &[String]) -> Result<Self, PatternError> {
        let patterns = patterns
            .iter()
            .map(|p| parse_pattern(p))
            .collect::<Result<_, _>>()?;
        Ok(RequestPatterns { patterns })
    }

    /// The request `program` makes, if it is one.
    pub fn match_program(&self, program: &PunchedText) -> Option<RemoteRequest> {
        self.match_text(&program.text)
    }

    /// The request the program text `text` makes, if it is one.
    pub fn match_text(&self, text: &[u8]) -> Option<RemoteRequest> {
        let content = squeeze(text);
        self.patterns.iter().find_map(|p| {
            let rest = content.strip_prefix(p.before.as_slice())?;
            let digits = rest.strip_suffix(p.after.as_slice())?;
            if !(1..=O_DIGITS_MAX).contains(&digits.len()) || !digits.iter().all(u8::is_ascii_digit)
            {
                return None;
            }
            let written: String = digits.iter().copied().map(char::from).collect();
            let trimmed = written.trim_start_matches('0');
            let trimmed = if trimmed.is_empty() { "0" } else { trimmed };
            Some(RemoteRequest {
                program: format!("O{trimmed}"),
                written: format!("O{written}"),
            })
        })
    }
}

#[cfg(test)]
mod tests;
