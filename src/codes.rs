//! The one place where typed errors become bus error codes ([`pb::ErrorCode`]), as rustls maps
//! its errors to alert codes in one place. Every error that reaches the bus implements
//! [`BusCode`] here; the message people read is the error's own `Display`.

use crate::fanuc::error::AbortReason;
use crate::fuji::command::Sta;
use crate::fuji::master::MasterError;
use crate::g05::G05Error;
use crate::g05::stream::BatchError;
use crate::jobs::JobError;
use crate::jobs::library::LibraryError;
use crate::link::driver::{JobFailure, LinkError};
use crate::pb;
use crate::plc::{PlcLinkError, TagError, TagWriteError};

/// The bus error code of an error.
pub trait BusCode {
    fn code(&self) -> pb::ErrorCode;
    /// The FFU120B STA code behind the error, if a PLC refused the request (§5-3-5).
    fn sta(&self) -> Option<u8> {
        None
    }
}

impl BusCode for Sta {
    fn code(&self) -> pb::ErrorCode {
        match self {
            Sta::MemoryWrite => pb::ErrorCode::PlcWriteProtected,
            Sta::UndefinedCommand => pb::ErrorCode::PlcUndefinedCommand,
            Sta::Parameter => pb::ErrorCode::PlcParameter,
            Sta::Interlock => pb::ErrorCode::PlcInterlock,
            Sta::ModuleNumber => pb::ErrorCode::PlcNoModule,
            Sta::OverMemorySize => pb::ErrorCode::PlcOverMemory,
            Sta::Transfer => pb::ErrorCode::PlcTransfer,
            Sta::Other(_) => pb::ErrorCode::PlcOtherSta,
        }
    }
    fn sta(&self) -> Option<u8> {
        Some(Sta::code(*self))
    }
}

impl BusCode for MasterError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            MasterError::Refused(_) | MasterError::TooManyStations { .. } => {
                pb::ErrorCode::InvalidRequest
            }
            MasterError::QueueFull { .. } => pb::ErrorCode::Busy,
            MasterError::TimeOut { .. }
            | MasterError::Corrupted { .. }
            | MasterError::BadReply(_) => pb::ErrorCode::LinkFailed,
            MasterError::Sta(e) => BusCode::code(&e.sta),
            MasterError::StationDown { .. } => pb::ErrorCode::Unavailable,
        }
    }
    fn sta(&self) -> Option<u8> {
        match self {
            MasterError::Sta(e) => Some(e.sta.code()),
            _ => None,
        }
    }
}

impl BusCode for TagError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            TagError::Unknown { .. } => pb::ErrorCode::NotFound,
            TagError::ReadOnly { .. } => pb::ErrorCode::NotSupported,
            TagError::OutOfRange { .. } => pb::ErrorCode::InvalidRequest,
        }
    }
}

impl BusCode for TagWriteError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            TagWriteError::Tag(e) => e.code(),
            TagWriteError::Plc(e) => e.code(),
        }
    }
    fn sta(&self) -> Option<u8> {
        match self {
            TagWriteError::Plc(e) => e.sta(),
            TagWriteError::Tag(_) => None,
        }
    }
}

impl BusCode for PlcLinkError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            PlcLinkError::NotRunning { .. } => pb::ErrorCode::Unavailable,
            PlcLinkError::Busy { .. } => pb::ErrorCode::Busy,
        }
    }
}

impl BusCode for LibraryError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            LibraryError::NotFound { .. } => pb::ErrorCode::NotFound,
            LibraryError::InvalidName { .. }
            | LibraryError::TooLarge { .. }
            | LibraryError::Exists { .. } => pb::ErrorCode::InvalidRequest,
            LibraryError::QuotaExceeded { .. } => pb::ErrorCode::QuotaExceeded,
            LibraryError::Io { .. } => pb::ErrorCode::Internal,
        }
    }
}

impl BusCode for JobError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            JobError::Program { .. }
            | JobError::RequestId { .. }
            | JobError::Start { .. }
            | JobError::NotResumable { .. } => pb::ErrorCode::InvalidRequest,
            JobError::Journal { .. } => pb::ErrorCode::Internal,
            JobError::Library { error, .. } => error.code(),
            JobError::QueueFull { .. } => pb::ErrorCode::QueueFull,
            JobError::UnknownJob { .. } => pb::ErrorCode::NotFound,
            JobError::LinkStopped { .. } | JobError::Stopped { .. } => pb::ErrorCode::Unavailable,
        }
    }
}

impl BusCode for AbortReason {
    fn code(&self) -> pb::ErrorCode {
        match self {
            // A reset abandons the program as a cancellation does; it is reported cancelled.
            // CAN: "CNC reset or alarm" (§5.3 1); a reset ends as a cancellation anyway.
            AbortReason::CncAlarm | AbortReason::AlarmNotice | AbortReason::CncStop => {
                pb::ErrorCode::CncAlarm
            }
            _ => pb::ErrorCode::LinkFailed,
        }
    }
}

impl BusCode for LinkError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            LinkError::NotRunning { .. } => pb::ErrorCode::Unavailable,
            LinkError::Busy { .. } => pb::ErrorCode::Busy,
        }
    }
}

impl BusCode for JobFailure {
    fn code(&self) -> pb::ErrorCode {
        match self {
            JobFailure::Aborted(reason) => reason.code(),
            JobFailure::Source(_) | JobFailure::LinkStopped(_) => pb::ErrorCode::LinkFailed,
            JobFailure::Shutdown => pb::ErrorCode::Unavailable,
        }
    }
}

impl BusCode for G05Error {
    fn code(&self) -> pb::ErrorCode {
        match self {
            G05Error::NotConfigured { .. } | G05Error::LineTooSlow { .. } => {
                pb::ErrorCode::NotSupported
            }
            G05Error::Busy { .. } => pb::ErrorCode::Busy,
            G05Error::LinkStopped { .. } => pb::ErrorCode::Unavailable,
            G05Error::BadId { .. } => pb::ErrorCode::InvalidRequest,
            G05Error::StreamEnded { .. } => pb::ErrorCode::NotFound,
        }
    }
}

impl BusCode for BatchError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            BatchError::Credits { .. } => pb::ErrorCode::Busy,
            BatchError::Ended { .. } => pb::ErrorCode::NotFound,
            _ => pb::ErrorCode::InvalidRequest,
        }
    }
}
