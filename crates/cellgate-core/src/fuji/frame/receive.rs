//! The receive errors of §5-6 ("details of receiving data error", bits D–F): what the
//! decoder drops, classified and counted as the module does (FFU120B notes 6).

use std::fmt;

use serde::Serialize;

use super::BccMismatch;
use crate::engine::LineError;

/// The receive errors of §5-6 ("details of receiving data error", bits D–F).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ReceiveErrorKind {
    /// 1: receiving buffer full (512 bytes).
    BufferFull,
    /// 2: start code unidentified.
    StartCode,
    /// 5: BCC error.
    Bcc,
    /// 6: text is too long.
    TooLong,
    /// 7: text form unidentified.
    TextForm,
    /// A character of the text came with a parity, framing or overrun error: the status
    /// word's own bits, no number of bits D–F, and "receiving ends to error" (§5-6).
    Character,
}

impl ReceiveErrorKind {
    /// Every kind, in the order of their numbers.
    pub const ALL: [ReceiveErrorKind; 6] = [
        ReceiveErrorKind::BufferFull,
        ReceiveErrorKind::StartCode,
        ReceiveErrorKind::Bcc,
        ReceiveErrorKind::TooLong,
        ReceiveErrorKind::TextForm,
        ReceiveErrorKind::Character,
    ];

    /// The error number the module shows in bits D–F of its status word (§5-6); a character
    /// error has bits of its own instead.
    pub fn number(self) -> Option<u8> {
        match self {
            ReceiveErrorKind::BufferFull => Some(1),
            ReceiveErrorKind::StartCode => Some(2),
            ReceiveErrorKind::Bcc => Some(5),
            ReceiveErrorKind::TooLong => Some(6),
            ReceiveErrorKind::TextForm => Some(7),
            ReceiveErrorKind::Character => None,
        }
    }

    /// The manual's name of the error.
    pub fn name(self) -> &'static str {
        match self {
            ReceiveErrorKind::BufferFull => "receiving buffer full",
            ReceiveErrorKind::StartCode => "start code unidentified",
            ReceiveErrorKind::Bcc => "BCC error",
            ReceiveErrorKind::TooLong => "text is too long",
            ReceiveErrorKind::TextForm => "text form unidentified",
            ReceiveErrorKind::Character => "character error (parity, framing or overrun)",
        }
    }
}

impl fmt::Display for ReceiveErrorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.number() {
            Some(n) => write!(f, "{} (receive error {n})", self.name()),
            None => write!(f, "{} (status bits, FFU120B §5-6)", self.name()),
        }
    }
}

/// Receive errors counted by kind (§5-6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct ReceiveCounts {
    /// Receive error 1: receiving buffer full.
    pub buffer_full: u64,
    /// Receive error 2: start code unidentified.
    pub start_code: u64,
    /// Receive error 5: BCC error.
    pub bcc: u64,
    /// Receive error 6: text too long.
    pub too_long: u64,
    /// Receive error 7: text form unidentified.
    pub text_form: u64,
    /// Texts ended by a character with a parity, framing or overrun error.
    pub character: u64,
}

impl ReceiveCounts {
    /// Counts one error of `kind`.
    pub fn add(&mut self, kind: ReceiveErrorKind) {
        let c = self.slot(kind);
        *c = c.saturating_add(1);
    }

    fn slot(&mut self, kind: ReceiveErrorKind) -> &mut u64 {
        match kind {
            ReceiveErrorKind::BufferFull => &mut self.buffer_full,
            ReceiveErrorKind::StartCode => &mut self.start_code,
            ReceiveErrorKind::Bcc => &mut self.bcc,
            ReceiveErrorKind::TooLong => &mut self.too_long,
            ReceiveErrorKind::TextForm => &mut self.text_form,
            ReceiveErrorKind::Character => &mut self.character,
        }
    }

    /// The count of `kind`.
    pub fn get(&self, kind: ReceiveErrorKind) -> u64 {
        match kind {
            ReceiveErrorKind::BufferFull => self.buffer_full,
            ReceiveErrorKind::StartCode => self.start_code,
            ReceiveErrorKind::Bcc => self.bcc,
            ReceiveErrorKind::TooLong => self.too_long,
            ReceiveErrorKind::TextForm => self.text_form,
            ReceiveErrorKind::Character => self.character,
        }
    }

    /// Both sets of counts added up.
    pub fn merged(mut self, other: &ReceiveCounts) -> ReceiveCounts {
        for kind in ReceiveErrorKind::ALL {
            let c = self.slot(kind);
            *c = c.saturating_add(other.get(kind));
        }
        self
    }

    /// Every error counted, of all kinds.
    pub fn total(&self) -> u64 {
        ReceiveErrorKind::ALL.iter().map(|k| self.get(*k)).sum()
    }
}

/// Why a text's form was not recognised (§5-6 receive error 7).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum TextForm {
    /// A transposed text with an odd number of characters.
    #[error("transposed text has an odd number ({len}) of characters")]
    OddLength {
        /// Characters in the transposed text.
        len: usize,
    },
    /// A character of a transposed text that is not an upper-case hex digit.
    #[error("character {byte:#04x} at offset {offset} of the text is not an upper-case hex digit")]
    NotHex {
        /// The character's offset in the transposed text.
        offset: usize,
        /// The character.
        byte: u8,
    },
    /// A text shorter than the shortest allowed.
    #[error("text of {len} bytes is shorter than {min}")]
    TooShort {
        /// The text's length, bytes.
        len: usize,
        /// The shortest text allowed, bytes.
        min: usize,
    },
    /// No end code where BYTEN says the text ends.
    #[error("no end code where BYTEN says the text ends")]
    NoEndCode,
    /// A new start code arrived inside a text.
    #[error("a new start code arrived {after} bytes into a text")]
    Truncated {
        /// Characters of the text before the new start code.
        after: usize,
    },
    /// BYTEN does not count the bytes that follow it.
    #[error("BYTEN {byten} does not match the {actual} bytes that follow it")]
    Byten {
        /// BYTEN as received.
        byten: u8,
        /// Bytes that follow BYTEN.
        actual: usize,
    },
}

/// A received frame that was dropped, classified as §5-6 does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ReceiveError {
    /// Receive error 1: the buffer (`RX_BUFFER`) filled without a whole text.
    #[error("receive buffer full: {dropped} bytes dropped (receive error 1, FFU120B §5-6)")]
    BufferFull {
        /// Bytes dropped.
        dropped: usize,
    },
    /// Receive error 2: bytes without a start code.
    #[error(
        "{dropped} byte(s) without a start code dropped (start code unidentified, receive error 2, FFU120B §5-6)"
    )]
    StartCode {
        /// Bytes dropped.
        dropped: usize,
    },
    /// Receive error 5: the BCC does not match.
    #[error("{0} (receive error 5)")]
    Bcc(BccMismatch),
    /// Receive error 6: the text is longer than the decoder takes.
    #[error(
        "text of {len} bytes or more exceeds {max} (text too long, receive error 6, FFU120B §5-6)"
    )]
    TooLong {
        /// The text's length, bytes, or as much of it as had arrived.
        len: usize,
        /// The longest text the decoder takes, bytes.
        max: usize,
    },
    /// Receive error 7: the text's form is not recognised.
    #[error("text form unidentified: {0} (receive error 7, FFU120B §5-6)")]
    TextForm(TextForm),
    /// A character of the text arrived with a line error: the text ends as a receive error
    /// (§5-6 "receiving error"), whatever the rest of it holds.
    #[error("{0}: the text it belongs to is dropped (receiving error, FFU120B §5-6)")]
    Character(LineError),
}

impl ReceiveError {
    /// The §5-6 kind of this error.
    pub fn kind(&self) -> ReceiveErrorKind {
        match self {
            ReceiveError::BufferFull { .. } => ReceiveErrorKind::BufferFull,
            ReceiveError::StartCode { .. } => ReceiveErrorKind::StartCode,
            ReceiveError::Bcc(_) => ReceiveErrorKind::Bcc,
            ReceiveError::TooLong { .. } => ReceiveErrorKind::TooLong,
            ReceiveError::TextForm(_) => ReceiveErrorKind::TextForm,
            ReceiveError::Character(_) => ReceiveErrorKind::Character,
        }
    }
}
