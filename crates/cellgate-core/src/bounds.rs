//! Bounds on what a client sends: every request message of the bus contract is checked for
//! its encoded size *before* it is decoded (a 300 MB `G05Batch` is never built), and for each
//! string and repeated field after (a 20 MB job name never reaches a log line, a queue listing
//! or the journal). The `.proto` files state the same bounds field by field.

use std::fmt;

use prost::Message;

use crate::pb;
use crate::program::name::NAME_MAX;

/// The cell file's limits that bound some messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// `programs.max_inline`: a `JobRequest`'s inline program.
    pub max_inline: u64,
    /// `programs.max_size`: a `ProgramWrite`'s program.
    pub max_program: u64,
}

/// Longest job name, request id, stream id, tag or PLC name a client may send, characters.
pub const MAX_TEXT: usize = 128;
/// Longest key a `JobRequest.key` may name, bytes.
pub const MAX_KEY: usize = 1024;
/// Most words of one PLC write: 220 data bytes of a write command (FFU120B §5-3-2) in 16-bit
/// words.
pub const MAX_PLC_WORDS: usize = 110;
/// Most data bytes of one transfer (FFU120B §5-3-2).
pub const MAX_TRANSFER_BYTES: usize = 220;
/// Most axes of a G05 block (parameter 7635 takes up to 8 here).
pub const MAX_G05_AXES: usize = 8;
/// Most blocks of one G05 batch: far above any credit window, which refuses more anyway.
pub const MAX_G05_BLOCKS: usize = 16_384;
/// Longest revision a client may name (a number or a SHA-256 in hex), characters.
pub const MAX_REVISION: usize = 64;
/// Longest comment on a revision or its state, characters.
pub const MAX_COMMENT: usize = 1024;
/// Longest `RequestOrigin` attached to a write, bytes.
pub const MAX_ORIGIN: usize = 1024;
/// Most program bytes a simulated CNC is asked to punch at once.
pub const MAX_SIM_PUNCH: usize = 65_536;
/// Room a message takes beyond its variable fields, bytes.
const SLACK: usize = 4096;

/// Why a request message was refused before or after decoding.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BoundError {
    /// The encoded message is larger than any valid one.
    TooLarge {
        /// The message's name.
        message: &'static str,
        /// Its encoded length, bytes.
        len: usize,
        /// The most it may be.
        max: usize,
    },
    /// Not a protobuf encoding of the message.
    Decode {
        /// The message's name.
        message: &'static str,
        /// What prost said.
        error: String,
    },
    /// A field past its bound.
    Field {
        /// The message's name.
        message: &'static str,
        /// The field.
        field: &'static str,
        /// Its length (characters, bytes or items).
        len: usize,
        /// The most it may be.
        max: usize,
    },
}

impl fmt::Display for BoundError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            BoundError::TooLarge { message, len, max } => write!(
                f,
                "a {message} of {len} bytes is over the {max} bytes it may take; nothing was \
                 decoded"
            ),
            BoundError::Decode { message, error } => {
                write!(f, "the payload is not a cellgate.v1.{message}: {error}")
            }
            BoundError::Field {
                message,
                field,
                len,
                max,
            } => write!(f, "{message}.{field} holds {len}; at most {max} are taken"),
        }
    }
}

impl std::error::Error for BoundError {}

/// A request message with bounds.
pub trait Bounded: Message + Default {
    /// The message's name, as errors give it.
    const NAME: &'static str;
    /// The largest encoding of a valid message.
    fn max_len(limits: &Limits) -> usize;
    /// Every string and repeated field within its bound.
    fn check(&self) -> Result<(), BoundError>;
}

/// Decodes `bytes` as `M` within its bounds: the length first, then the fields.
pub fn decode<M: Bounded>(bytes: &[u8], limits: &Limits) -> Result<M, BoundError> {
    let max = M::max_len(limits);
    if bytes.len() > max {
        return Err(BoundError::TooLarge {
            message: M::NAME,
            len: bytes.len(),
            max,
        });
    }
    let m = M::decode(bytes).map_err(|e| BoundError::Decode {
        message: M::NAME,
        error: e.to_string(),
    })?;
    m.check()?;
    Ok(m)
}

fn field(
    message: &'static str,
    field: &'static str,
    len: usize,
    max: usize,
) -> Result<(), BoundError> {
    if len > max {
        return Err(BoundError::Field {
            message,
            field,
            len,
            max,
        });
    }
    Ok(())
}

fn chars(s: &str) -> usize {
    s.chars().count()
}

fn usize_of(n: u64) -> usize {
    usize::try_from(n).unwrap_or(usize::MAX)
}

impl Bounded for pb::JobRequest {
    const NAME: &'static str = "JobRequest";
    fn max_len(limits: &Limits) -> usize {
        usize_of(limits.max_inline).saturating_add(SLACK)
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "name", chars(&self.name), MAX_TEXT)?;
        field(Self::NAME, "request_id", chars(&self.request_id), MAX_TEXT)?;
        field(Self::NAME, "revision", chars(&self.revision), MAX_REVISION)?;
        match &self.program {
            Some(pb::job_request::Program::Library(n)) => {
                field(Self::NAME, "library", chars(n), NAME_MAX)
            }
            Some(pb::job_request::Program::Key(k)) => field(Self::NAME, "key", k.len(), MAX_KEY),
            Some(pb::job_request::Program::ResumeJob(j)) => {
                field(Self::NAME, "resume_job", chars(j), MAX_TEXT)
            }
            Some(pb::job_request::Program::Inline(_)) | None => Ok(()),
        }
    }
}

impl Bounded for pb::DoCommand {
    const NAME: &'static str = "DoCommand";
    fn max_len(_: &Limits) -> usize {
        64
    }
    fn check(&self) -> Result<(), BoundError> {
        Ok(())
    }
}

impl Bounded for pb::ProgramWrite {
    const NAME: &'static str = "ProgramWrite";
    fn max_len(limits: &Limits) -> usize {
        usize_of(limits.max_program).saturating_add(SLACK)
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "comment", chars(&self.comment), MAX_COMMENT)?;
        if let Some(pb::program_write::Op::Adopt(a)) = &self.op {
            field(Self::NAME, "adopt.from", chars(&a.from), NAME_MAX)?;
            field(
                Self::NAME,
                "adopt.revision",
                chars(&a.revision),
                MAX_REVISION,
            )?;
        }
        Ok(())
    }
}

impl Bounded for pb::ProgramRelease {
    const NAME: &'static str = "ProgramRelease";
    fn max_len(_: &Limits) -> usize {
        SLACK
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "revision", chars(&self.revision), MAX_REVISION)?;
        field(Self::NAME, "comment", chars(&self.comment), MAX_COMMENT)
    }
}

impl Bounded for pb::AuditRecord {
    const NAME: &'static str = "AuditRecord";
    fn max_len(_: &Limits) -> usize {
        SLACK
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "action", chars(&self.action), MAX_TEXT)?;
        field(Self::NAME, "key", chars(&self.key), MAX_KEY)?;
        field(Self::NAME, "target", chars(&self.target), MAX_KEY)?;
        field(Self::NAME, "detail", chars(&self.detail), MAX_COMMENT)?;
        field(Self::NAME, "error", chars(&self.error), MAX_COMMENT)?;
        if let Some(o) = &self.origin {
            o.check()?;
        }
        Ok(())
    }
}

impl Bounded for pb::RequestOrigin {
    const NAME: &'static str = "RequestOrigin";
    fn max_len(_: &Limits) -> usize {
        MAX_ORIGIN
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "user", chars(&self.user), MAX_TEXT)?;
        field(Self::NAME, "via", chars(&self.via), MAX_TEXT)
    }
}

impl Bounded for pb::G05Open {
    const NAME: &'static str = "G05Open";
    fn max_len(_: &Limits) -> usize {
        SLACK
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "stream_id", chars(&self.stream_id), MAX_TEXT)
    }
}

impl Bounded for pb::G05Batch {
    const NAME: &'static str = "G05Batch";
    fn max_len(_: &Limits) -> usize {
        // A block: a tag and length, eight axes of at most 5 bytes with their tags, an
        // auxiliary word of at most 6: under 64 bytes.
        MAX_G05_BLOCKS * 64 + SLACK
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "blocks", self.blocks.len(), MAX_G05_BLOCKS)?;
        for b in &self.blocks {
            field(Self::NAME, "blocks.travel", b.travel.len(), MAX_G05_AXES)?;
        }
        Ok(())
    }
}

impl Bounded for pb::PlcWrite {
    const NAME: &'static str = "PlcWrite";
    fn max_len(_: &Limits) -> usize {
        MAX_PLC_WORDS * 6 + SLACK
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "words", self.words.len(), MAX_PLC_WORDS)
    }
}

impl Bounded for pb::TagWrite {
    const NAME: &'static str = "TagWrite";
    fn max_len(_: &Limits) -> usize {
        64
    }
    fn check(&self) -> Result<(), BoundError> {
        Ok(())
    }
}

impl Bounded for pb::PlcMessage {
    const NAME: &'static str = "PlcMessage";
    fn max_len(_: &Limits) -> usize {
        crate::fuji::frame::MAX_NON_PROCEDURE_TEXT + SLACK
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "plc", chars(&self.plc), MAX_TEXT)?;
        field(
            Self::NAME,
            "data",
            self.data.len(),
            crate::fuji::frame::MAX_NON_PROCEDURE_TEXT,
        )
    }
}

impl Bounded for pb::PlcTransfer {
    const NAME: &'static str = "PlcTransfer";
    fn max_len(_: &Limits) -> usize {
        MAX_TRANSFER_BYTES + SLACK
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "plc", chars(&self.plc), MAX_TEXT)?;
        field(Self::NAME, "data", self.data.len(), MAX_TRANSFER_BYTES)
    }
}

impl Bounded for pb::SimDi {
    const NAME: &'static str = "SimDi";
    fn max_len(_: &Limits) -> usize {
        64
    }
    fn check(&self) -> Result<(), BoundError> {
        Ok(())
    }
}

impl Bounded for pb::ReloadRequest {
    const NAME: &'static str = "ReloadRequest";
    fn max_len(_: &Limits) -> usize {
        64
    }
    fn check(&self) -> Result<(), BoundError> {
        Ok(())
    }
}

impl Bounded for pb::SimAutostart {
    const NAME: &'static str = "SimAutostart";
    fn max_len(_: &Limits) -> usize {
        64
    }
    fn check(&self) -> Result<(), BoundError> {
        Ok(())
    }
}

impl Bounded for pb::SimPunch {
    const NAME: &'static str = "SimPunch";
    fn max_len(_: &Limits) -> usize {
        MAX_SIM_PUNCH + SLACK
    }
    fn check(&self) -> Result<(), BoundError> {
        field(Self::NAME, "program", self.program.len(), MAX_SIM_PUNCH)
    }
}

#[cfg(test)]
mod tests;
