//! CNC alarms of §11 that a remote-buffer link raises, by their manual numbers.

use std::fmt;

use serde::Serialize;

/// A remote-buffer alarm as the CNC shows it (§11).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[non_exhaustive]
pub enum CncAlarm {
    /// SR0855 DATA SET READY DOWN: DR (or CD on RS-232-C) went off.
    Sr0855DataSetReadyDown,
    /// SR0856 BUFFER OVERFLOW: data past the overrun allowance after DC3 (Protocol B).
    Sr0856BufferOverflow,
    /// SR0944 time-out in Protocol A (abnormality in host).
    Sr0944TimeOut,
    /// SR0945 retry count exceeded in Protocol A (abnormality in host).
    Sr0945RetryOver,
    /// SR0946 framing or overrun error.
    Sr0946FramingOverrun,
    /// SR0947 invalid response command received in Protocol A.
    Sr0947InvalidResponse,
    /// SR0948 error code detected in Protocol A: end code in a command name, undefined
    /// command, or a command other than the expected one.
    Sr0948BadCommand,
    /// SR0890 CHECK SUM ERROR (G05): a binary input block's check byte is wrong (§9.1 (9)).
    Sr0890G05CheckSum,
    /// SR0891 ILLEGAL COMMAND G05: G05 was issued when it could not be issued (§9.3 2).
    Sr0891IllegalG05,
}

impl CncAlarm {
    /// The number as the manual prints it, e.g. "SR0945".
    pub fn number(self) -> &'static str {
        match self {
            Self::Sr0855DataSetReadyDown => "SR0855",
            Self::Sr0856BufferOverflow => "SR0856",
            Self::Sr0944TimeOut => "SR0944",
            Self::Sr0945RetryOver => "SR0945",
            Self::Sr0946FramingOverrun => "SR0946",
            Self::Sr0947InvalidResponse => "SR0947",
            Self::Sr0948BadCommand => "SR0948",
            Self::Sr0890G05CheckSum => "SR0890",
            Self::Sr0891IllegalG05 => "SR0891",
        }
    }

    /// The CNC's message text (§11).
    pub fn message(self) -> &'static str {
        match self {
            Self::Sr0855DataSetReadyDown => "DATA SET READY DOWN (RMT-BUF)",
            Self::Sr0856BufferOverflow => "BUFFER OVERFLOW (RMT-BUF)",
            Self::Sr0944TimeOut => "COMMUNICATION ERROR (RMT-BUF): time-out in protocol A",
            Self::Sr0945RetryOver => "COMMUNICATION ERROR (RMT-BUF): retry count exceeded",
            Self::Sr0946FramingOverrun => "COMMUNICATION ERROR (RMT-BUF): framing or overrun error",
            Self::Sr0947InvalidResponse => {
                "COMMUNICATION ERROR (RMT-BUF): invalid response command in protocol A"
            }
            Self::Sr0948BadCommand => "COMMUNICATION ERROR (RMT-BUF): error code in protocol A",
            Self::Sr0890G05CheckSum => "CHECK SUM ERROR (G05)",
            Self::Sr0891IllegalG05 => "ILLEGAL COMMAND G05",
        }
    }
}

impl fmt::Display for CncAlarm {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}", self.number(), self.message())
    }
}
