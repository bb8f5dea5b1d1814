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

use crate::fanuc::code::{CR, EOR, LF, has_even_parity, is_eor, is_significant};
use crate::fanuc::tape::{self, EIA_EOB, EIA_ER, TapeCode, TapeError};

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
    #[error(
        "punched program starting at byte {offset} of the punch-out is longer than {max} bytes; skipped through its EOR"
    )]
    TooLarge { offset: u64, max: usize },
    #[error("punched program starting at byte {offset} of the punch-out: {error}")]
    Code {
        offset: u64,
        #[source]
        error: TapeError,
    },
    #[error(
        "{len} punched bytes from byte {offset} of the punch-out precede any tape-start `%` (protocol notes 8) and were skipped"
    )]
    OutsideProgram { offset: u64, len: u64 },
    #[error(
        "the punch-out ended inside the program starting at byte {offset} ({len} bytes, no EOR `%`); it was dropped"
    )]
    Unterminated { offset: u64, len: usize },
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

/// Longest program number: O and up to 8 digits.
const O_DIGITS_MAX: usize = 8;
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
    #[error("request pattern {pattern:?}: {reason}")]
    Invalid {
        pattern: String,
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
mod tests {
    use super::*;
    use crate::fanuc::tape::encode;
    use crate::jobs::library::validate_name;
    use proptest::prelude::*;

    const P1: &[u8] = b"%\nO1234(PART)\nG00X1.Y2.\nM30\n%";
    const P2: &[u8] = b"%\n:0012 ( SECOND  )\nG01Z-1.F100\nM30\n%";
    const P3: &[u8] = b"%\n(NO NUMBER)\nG28U0W0\nM30\n%";

    const CODES: [TapeCode; 3] = [TapeCode::Iso, TapeCode::Ascii, TapeCode::Eia];

    /// A punch-out of `programs` in `code` with feed around and LF between, as a CNC sends it.
    fn punch(code: TapeCode, programs: &[&[u8]]) -> Vec<u8> {
        let mut text = Vec::new();
        for p in programs {
            text.extend(*p);
            text.push(b'\n');
        }
        let mut out = vec![0; 5];
        out.extend(encode(&text, code).unwrap());
        out.extend([0; 5]);
        out
    }

    fn texts(results: Vec<Result<PunchedText, PunchError>>) -> Vec<Vec<u8>> {
        results.into_iter().map(|r| r.unwrap().text).collect()
    }

    fn eia_safe(p: &[u8]) -> Vec<u8> {
        // ':' has no EIA code: EIA punches the program number as O.
        p.iter()
            .map(|&b| if b == b':' { b'O' } else { b })
            .collect()
    }

    #[test]
    fn splits_several_programs_in_one_punch() {
        for code in CODES {
            let (p1, p2, p3) = (eia_safe(P1), eia_safe(P2), eia_safe(P3));
            let programs: [&[u8]; 3] = if code == TapeCode::Eia {
                [&p1, &p2, &p3]
            } else {
                [P1, P2, P3]
            };
            let mut asm = PunchAssembler::new(1 << 20);
            let out = asm.feed(&punch(code, &programs));
            let got: Vec<PunchedText> = out.into_iter().map(Result::unwrap).collect();
            assert_eq!(got.len(), 3, "{code}");
            for (g, want) in got.iter().zip(programs) {
                assert_eq!(g.code, code);
                assert_eq!(g.text, want, "{code}");
            }
            assert_eq!(got[0].o_number.as_deref(), Some("O1234"));
            assert_eq!(got[0].comment.as_deref(), Some("PART"));
            assert_eq!(got[1].o_number.as_deref(), Some("O0012"));
            assert_eq!(got[1].comment.as_deref(), Some("SECOND"));
            assert_eq!(got[2].o_number, None);
            assert_eq!(got[2].comment.as_deref(), Some("NO NUMBER"));
            assert_eq!(asm.pending(), 0);
            assert_eq!(asm.finish(), None);
        }
    }

    #[test]
    fn punched_names_are_recognised_for_their_machine_only() {
        let name =
            |o: Option<&str>| library_name("lathe-1", o, 1_795_000_000_000, |_| false).unwrap();
        let plain = name(Some("O1234"));
        assert!(is_punched_name("lathe-1", &plain));
        assert!(is_punched_name("lathe-1", &format!("{plain}-7")));
        assert!(is_punched_name("lathe-1", &name(None)));
        assert!(!is_punched_name("lathe-2", &plain));
        // A machine whose name starts another's takes only its own.
        assert!(!is_punched_name("lathe", &plain));
        assert!(is_punched_name(
            "lathe",
            &library_name("lathe", Some("O1"), 0, |_| false).unwrap()
        ));
        for other in [
            "lathe-1",
            "lathe-1-O1234",
            "O1234",
            "lathe-1-O1-2026112T061500Z",
            "lathe-1-x",
        ] {
            assert!(!is_punched_name("lathe-1", other), "{other}");
        }
    }

    #[test]
    fn damage_marks_the_program_it_falls_in_and_no_other() {
        let tape = punch(TapeCode::Ascii, &[P1, P2, P3]);
        // The characters as punched carry a parity bit.
        let plain: Vec<u8> = tape.iter().map(|b| b & 0x7F).collect();
        let second = plain.windows(3).position(|w| w == b"SEC").unwrap();
        let mut asm = PunchAssembler::new(1 << 20);
        let mut got = asm.feed(&tape[..second + 3]);
        asm.damaged("parity error in a received character during the punch-out");
        got.extend(asm.feed(&tape[second + 3..]));
        let got: Vec<PunchedText> = got.into_iter().map(Result::unwrap).collect();
        assert_eq!(got.len(), 3);
        assert_eq!(got[0].damage, None);
        assert_eq!(
            got[1].damage.as_deref(),
            Some("parity error in a received character during the punch-out")
        );
        assert_eq!(got[2].damage, None, "the damage ends with its program");

        // Between programs: the next program may have lost its tape-start, it is suspect.
        let mut asm = PunchAssembler::new(1 << 20);
        let mut got = asm.feed(&punch(TapeCode::Ascii, &[P1]));
        asm.damaged("framing error");
        got.extend(asm.feed(&punch(TapeCode::Ascii, &[P2, P3])));
        let got: Vec<PunchedText> = got.into_iter().map(Result::unwrap).collect();
        assert_eq!(got.len(), 3);
        assert_eq!(got[0].damage, None);
        assert_eq!(got[1].damage.as_deref(), Some("framing error"));
        assert_eq!(got[2].damage, None);
    }

    #[test]
    fn each_code_and_eob_setting_gives_the_same_text() {
        let ncr0 = b"%\n\r\rO1234(PART)\n\r\rG00X1.Y2.\n\r\rM30\n\r\r%";
        for (code, text) in [
            (TapeCode::Iso, &ncr0[..]),
            (TapeCode::Iso, P1),
            (TapeCode::Ascii, &ncr0[..]),
            (TapeCode::Eia, P1),
        ] {
            let mut asm = PunchAssembler::new(1000);
            let got = texts(asm.feed(&encode(text, code).unwrap()));
            assert_eq!(got, [P1.to_vec()], "{code}");
        }
    }

    #[test]
    fn programs_split_across_pieces_at_every_boundary() {
        for code in CODES {
            let whole = punch(code, &[&eia_safe(P1), &eia_safe(P2)]);
            let want = texts(PunchAssembler::new(1000).feed(&whole));
            assert_eq!(want.len(), 2);
            for cut in 0..=whole.len() {
                let mut asm = PunchAssembler::new(1000);
                let mut got = texts(asm.feed(&whole[..cut]));
                got.extend(texts(asm.feed(&whole[cut..])));
                assert_eq!(got, want, "{code} cut at {cut}");
            }
            let mut asm = PunchAssembler::new(1000);
            let got: Vec<Vec<u8>> = whole.iter().flat_map(|b| texts(asm.feed(&[*b]))).collect();
            assert_eq!(got, want, "{code} byte by byte");
        }
    }

    #[test]
    fn eia_v_is_no_eor() {
        // 25h is `V` in EIA and `%` in ASCII.
        let text = b"%\nO1(V)\nG01V5.\nM30\n%";
        let mut asm = PunchAssembler::new(1000);
        assert_eq!(
            texts(asm.feed(&punch(TapeCode::Eia, &[text]))),
            [text.to_vec()]
        );
    }

    #[test]
    fn eia_v_between_programs_is_no_tape_start() {
        let tape = encode(b"%\nO1\nM30\n%\nV1\n%\nO2\nM30\n%", TapeCode::Eia).unwrap();
        let mut asm = PunchAssembler::new(1000);
        let out = asm.feed(&tape);
        assert_eq!(out.len(), 3, "{out:?}");
        assert_eq!(
            out[1],
            Err(PunchError::OutsideProgram { offset: 11, len: 3 })
        );
        assert_eq!(out[2].as_ref().unwrap().text, b"%\nO2\nM30\n%");
        // After an ISO byte, 25h is `%` again.
        let mut asm = PunchAssembler::new(1000);
        let mut tape = encode(b"%\nO1\n%", TapeCode::Eia).unwrap();
        tape.extend(b"\n%\nO2\n%");
        let out = texts(asm.feed(&tape));
        assert_eq!(out, [b"%\nO1\n%".to_vec(), b"%\nO2\n%".to_vec()]);
    }

    #[test]
    fn garbage_between_programs_is_skipped_and_reported() {
        let mut tape = b"%\nO1\nM30\n%\nGARBAGE\n%\nO2\nM30\n%\n".to_vec();
        let mut asm = PunchAssembler::new(1000);
        let out = asm.feed(&tape);
        assert_eq!(out.len(), 3, "{out:?}");
        assert_eq!(out[0].as_ref().unwrap().o_number.as_deref(), Some("O1"));
        assert_eq!(
            out[1],
            Err(PunchError::OutsideProgram { offset: 11, len: 8 })
        );
        assert_eq!(out[2].as_ref().unwrap().text, b"%\nO2\nM30\n%");
        // Garbage before the first program, and at the end of the punch-out.
        tape.splice(0..0, b"xx".iter().copied());
        tape.extend(b"TRAILING");
        let mut asm = PunchAssembler::new(1000);
        let out = asm.feed(&tape);
        assert_eq!(
            out[0],
            Err(PunchError::OutsideProgram { offset: 0, len: 2 })
        );
        assert_eq!(out.len(), 4);
        assert_eq!(
            asm.finish(),
            Some(PunchError::OutsideProgram {
                offset: tape.len() as u64 - 8,
                len: 8
            })
        );
    }

    #[test]
    fn blanks_and_repeated_tape_starts_are_not_garbage() {
        let tape = b"\0\0\r\n \t%%\n%\nO7\n%\n\r\r\0\x7f%\n%";
        let mut asm = PunchAssembler::new(1000);
        let out = asm.feed(tape);
        assert_eq!(texts(out), [b"%\nO7\n%".to_vec()]);
        assert_eq!(asm.finish(), None);
    }

    #[test]
    fn oversize_program_is_refused_and_resyncs() {
        let mut big = b"%\nO9(BIG)\n".to_vec();
        big.extend(std::iter::repeat_n(b"G01X1.\n".as_slice(), 100).flatten());
        big.extend(b"%\n");
        big.extend(P1);
        for code in [TapeCode::Iso, TapeCode::Eia] {
            let tape = encode(&big, code).unwrap();
            let mut asm = PunchAssembler::new(200);
            let mut out = Vec::new();
            for piece in tape.chunks(7) {
                out.extend(asm.feed(piece));
                assert!(asm.pending() <= 200);
            }
            assert_eq!(out.len(), 2, "{code}");
            assert_eq!(
                out[0],
                Err(PunchError::TooLarge {
                    offset: 0,
                    max: 200
                })
            );
            assert_eq!(out[1].as_ref().unwrap().text, P1);
        }
        // Exactly at the limit is fine; one byte over is not.
        let mut asm = PunchAssembler::new(P1.len());
        assert_eq!(texts(asm.feed(P1)), [P1.to_vec()]);
        let mut asm = PunchAssembler::new(P1.len() - 1);
        assert!(matches!(
            asm.feed(P1).as_slice(),
            [Err(PunchError::TooLarge { .. })]
        ));
        assert_eq!(asm.finish(), None);
    }

    #[test]
    fn unterminated_program_is_reported_at_finish() {
        let mut asm = PunchAssembler::new(1000);
        let out = asm.feed(b"%\nO1\n%\n%\nO2\nG00");
        assert_eq!(out.len(), 1);
        assert_eq!(asm.pending(), 8);
        assert_eq!(
            asm.finish(),
            Some(PunchError::Unterminated { offset: 7, len: 8 })
        );
        // Afresh: offsets count from the new punch-out.
        assert_eq!(asm.pending(), 0);
        assert_eq!(texts(asm.feed(b"%\nO3\n%")), [b"%\nO3\n%".to_vec()]);
        // A lone tape-start mark left open is no program.
        asm.feed(b"\n%\n");
        assert_eq!(asm.finish(), None);
    }

    #[test]
    fn code_errors_name_the_program() {
        let mut tape = encode(P1, TapeCode::Iso).unwrap();
        tape[4] ^= 0x80;
        tape.extend(encode(P1, TapeCode::Iso).unwrap());
        let mut asm = PunchAssembler::new(1000);
        let out = asm.feed(&tape);
        assert_eq!(out.len(), 2);
        assert!(matches!(
            &out[0],
            Err(PunchError::Code {
                offset: 0,
                error: TapeError::Parity {
                    code: TapeCode::Iso,
                    offset: 4,
                    ..
                }
            })
        ));
        assert_eq!(out[1].as_ref().unwrap().text, P1);
    }

    #[test]
    fn program_numbers_and_comments() {
        let cases: [(&[u8], Option<&str>, Option<&str>); 8] = [
            (b"%\nO1234(PART)\nM30\n%", Some("O1234"), Some("PART")),
            (b"%\n:1234\nM30\n%", Some("O1234"), None),
            (b"%O0012(A)(B)\nM30\n%", Some("O0012"), Some("A")),
            (b"%\n(HEAD)\nO5 (  FIVE )\n%", Some("O5"), Some("FIVE")),
            (b"%\nG00X0\n(CUT)\n%", None, None),
            (b"%\nO123456789\n%", None, None),
            (b"%\nO12345678\n%", Some("O12345678"), None),
            (b"%\nO1(UNCLOSED\n%", Some("O1"), None),
        ];
        for (text, o, c) in cases {
            let p = PunchedText::from_text(TapeCode::Ascii, text.to_vec());
            assert_eq!(
                p.o_number.as_deref(),
                o,
                "{:?}",
                String::from_utf8_lossy(text)
            );
            assert_eq!(
                p.comment.as_deref(),
                c,
                "{:?}",
                String::from_utf8_lossy(text)
            );
        }
        let long = format!("%\nO1({})\n%", "X".repeat(100));
        let p = PunchedText::from_text(TapeCode::Ascii, long.into_bytes());
        assert_eq!(p.comment.map(|c| c.len()), Some(COMMENT_MAX));
    }

    fn request(text: &[u8]) -> Option<RemoteRequest> {
        RequestPatterns::default()
            .match_program(&PunchedText::from_text(TapeCode::Ascii, text.to_vec()))
    }

    #[test]
    fn default_request_patterns() {
        let o1234 = Some(RemoteRequest {
            program: "O1234".into(),
            written: "O1234".into(),
        });
        assert_eq!(request(b"%\n(REQ O1234)\n%"), o1234);
        assert_eq!(request(b"%\n( req  o 1234 )\n\r\r%"), o1234);
        assert_eq!(request(b"%\n(PRG=1234)\n%"), o1234);
        assert_eq!(request(b"%(prg = 1234)%"), o1234);
        let r = request(b"%\n(PRG=0012)\n%").unwrap();
        assert_eq!(r.program, "O12");
        assert_eq!(r.written, "O0012");
        // The EIA spelling of a request.
        let mut asm = PunchAssembler::new(100);
        let out = asm.feed(&encode(b"%\n(REQ O55)\n%", TapeCode::Eia).unwrap());
        let program = out.into_iter().next().unwrap().unwrap();
        assert_eq!(
            RequestPatterns::default()
                .match_program(&program)
                .map(|r| r.program),
            Some("O55".to_string())
        );
    }

    #[test]
    fn programs_that_are_no_requests() {
        for text in [
            &b"%\nO1(REQ O1234)\nM30\n%"[..],
            b"%\n(REQ O1234)\nM30\n%",
            b"%\n(REQ O1234)(REQ O1234)\n%",
            b"%\n(REQ O)\n%",
            b"%\n(REQ O123456789)\n%",
            b"%\n(REQ OA12)\n%",
            b"%\n(REQ P1234)\n%",
            b"%\n(PRG=1234\n%",
            b"%\n%",
            b"",
        ] {
            assert_eq!(request(text), None, "{:?}", String::from_utf8_lossy(text));
        }
    }

    #[test]
    fn custom_request_patterns() {
        let pats =
            RequestPatterns::parse(&["CALL{n}".to_string(), "(SEND {n} NOW)".to_string()]).unwrap();
        let m = |t: &[u8]| pats.match_text(t).map(|r| r.program);
        assert_eq!(m(b"%\nCALL 77\n%"), Some("O77".into()));
        assert_eq!(m(b"%\n(send 0 now)\n%"), Some("O0".into()));
        assert_eq!(m(b"%\n(REQ O1234)\n%"), None);
        assert_eq!(m(b"%\nCALL 77\nM30\n%"), None);
        assert_eq!(
            RequestPatterns::parse(&[])
                .unwrap()
                .match_text(b"%\n(REQ O1)\n%"),
            None
        );
    }

    #[test]
    fn bad_request_patterns() {
        for bad in [
            "(REQ O)",
            "(REQ O{n}{n})",
            "{n}",
            "  {n} ",
            "(REQ {x}{n})",
            "(REQ O{n}%)",
            "(REQ O{N})",
            "(REQ\nO{n})",
            "(RÉQ O{n})",
        ] {
            let e = RequestPatterns::parse(&[bad.to_string()]).unwrap_err();
            assert!(e.to_string().contains(&format!("{bad:?}")), "{e}");
        }
    }

    #[test]
    fn request_candidates() {
        let c = |text: &[u8]| request(text).unwrap().candidates();
        assert_eq!(c(b"%\n(PRG=12)\n%"), ["O12", "O0012"]);
        assert_eq!(c(b"%\n(PRG=0012)\n%"), ["O12", "O0012"]);
        assert_eq!(c(b"%\n(PRG=00012)\n%"), ["O12", "O0012", "O00012"]);
        assert_eq!(c(b"%\n(PRG=1234)\n%"), ["O1234"]);
        assert_eq!(c(b"%\n(PRG=12345678)\n%"), ["O12345678"]);
        assert_eq!(c(b"%\n(PRG=0)\n%"), ["O0", "O0000"]);
    }

    #[test]
    fn timestamps_of_known_dates() {
        for (secs, want) in [
            (0, "19700101T000000Z"),
            (951_782_400, "20000229T000000Z"),
            (946_684_799, "19991231T235959Z"),
            (1_709_210_096, "20240229T123456Z"),
            (1_795_328_100, "20261122T061500Z"),
            (4_107_542_400, "21000301T000000Z"),
        ] {
            assert_eq!(compact_utc(secs * 1000 + 999), want, "{secs}");
        }
        assert_eq!(civil_from_days(0), (1970, 1, 1));
        assert_eq!(civil_from_days(59), (1970, 3, 1));
        assert_eq!(civil_from_days(11_016), (2000, 2, 29));
        let _ = compact_utc(u64::MAX);
    }

    #[test]
    fn library_names() {
        let ms = 1_795_328_100_000;
        let none = |_: &str| false;
        assert_eq!(
            library_name("mill-1", Some("O1234"), ms, none).unwrap(),
            "mill-1-O1234-20261122T061500Z"
        );
        assert_eq!(
            library_name("mill-1", None, ms, none).unwrap(),
            "mill-1-punch-20261122T061500Z"
        );
        let taken = [
            "mill-1-O1234-20261122T061500Z",
            "mill-1-O1234-20261122T061500Z-2",
        ];
        assert_eq!(
            library_name("mill-1", Some("O1234"), ms, |n| taken.contains(&n)).unwrap(),
            "mill-1-O1234-20261122T061500Z-3"
        );
        assert_eq!(library_name("mill-1", Some("O1"), ms, |_| true), None);
        for (machine, o) in [
            ("a/b*c$d?e#f", Some("O1")),
            ("_x", Some("O1/2")),
            ("", Some("")),
            ("ü", None),
            (&"m".repeat(300), Some("O12345678")),
        ] {
            let name = library_name(machine, o, ms, none).unwrap();
            assert!(validate_name(&name).is_ok(), "{name}");
            assert!(!name.contains(['/', '*', '$', '?', '#', ':']), "{name}");
        }
        assert_eq!(
            library_name("a/b", Some(""), ms, none).unwrap(),
            "a_b-punch-20261122T061500Z"
        );
    }

    fn realistic_punch() -> impl Strategy<Value = Vec<u8>> {
        (0..3usize, proptest::bool::ANY).prop_map(|(code, ncr0)| {
            let code = CODES[code];
            let mut text = Vec::new();
            for p in [P1, &eia_safe(P2), P3] {
                text.extend(p);
                text.extend(b"\n\n");
            }
            if ncr0 && code != TapeCode::Eia {
                text = text
                    .iter()
                    .flat_map(|&b| if b == LF { vec![LF, CR, CR] } else { vec![b] })
                    .collect();
            }
            encode(&text, code).unwrap()
        })
    }

    proptest! {
        #[test]
        fn any_split_gives_the_same_programs(
            tape in realistic_punch(),
            cuts in proptest::collection::vec(any::<proptest::sample::Index>(), 0..10),
        ) {
            let want = texts(PunchAssembler::new(1000).feed(&tape));
            prop_assert_eq!(want.len(), 3);
            let mut cuts: Vec<usize> = cuts.iter().map(|i| i.index(tape.len() + 1)).collect();
            cuts.sort_unstable();
            let mut asm = PunchAssembler::new(1000);
            let mut got = Vec::new();
            let mut from = 0;
            for cut in cuts.into_iter().chain([tape.len()]) {
                got.extend(texts(asm.feed(&tape[from..cut])));
                from = cut;
            }
            prop_assert_eq!(got, want);
            prop_assert_eq!(asm.finish(), None);
        }

        #[test]
        fn garbage_never_panics(
            pieces in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..64), 0..20),
            max in 1..100usize,
        ) {
            let mut asm = PunchAssembler::new(max);
            for piece in &pieces {
                for program in asm.feed(piece).into_iter().flatten() {
                    prop_assert!(program.text.first() == Some(&EOR));
                    prop_assert!(program.text.last() == Some(&EOR));
                    let _ = RequestPatterns::default().match_program(&program);
                }
                prop_assert!(asm.pending() <= max);
            }
            asm.finish();
            prop_assert_eq!(asm.pending(), 0);
        }
    }
}
