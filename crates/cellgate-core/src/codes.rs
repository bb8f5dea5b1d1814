//! How typed errors become bus error codes ([`pb::ErrorCode`]): the [`BusCode`] trait, which
//! every error that reaches the bus implements beside its own type (as rustls maps each error
//! to its alert code beside the error). The message people read is the error's own `Display`.

use crate::pb;

/// The bus error code of an error.
pub trait BusCode {
    /// The code a client branches on.
    fn code(&self) -> pb::ErrorCode;
    /// The FFU120B STA code behind the error, if a PLC refused the request (§5-3-5).
    fn sta(&self) -> Option<u8> {
        None
    }
}

/// cellgate's own codes for alarms the manual gives no number (`AlarmEvent.code`, and the
/// MTConnect conditions' `nativeCode`; docs/mtconnect.md lists them). An alarm the manual
/// numbers (§11) carries that number instead.
pub mod alarm {
    /// A CNC alarm posted by ALM (Protocol A family, §4.4.1): the message carries no number.
    pub const ALM: &str = "CG-ALM";
    /// A CNC alarm posted by NAK (Protocol B family with notification on, §6.4).
    pub const NAK: &str = "CG-NAK";
    /// The SAT's buffer status says alarm, cause NC alarm (§4.4.2 byte 3 = 0).
    pub const SAT_NC: &str = "CG-SAT-NC";
    /// The SAT's buffer status says alarm for a cause the manual does not list.
    pub const SAT_OTHER: &str = "CG-SAT";
    /// A link alarm the manual gives no number (a parity error, parameters not applied).
    pub const LINK: &str = "CG-LINK";
    /// The link's transport (serial port, device server) is not open.
    pub const DOWN: &str = "CG-DOWN";
    /// A PLC station does not answer (FFU120B §5-6: a missing reply is a time-out).
    pub const STATION: &str = "CG-STATION";
    /// The open G05 stream starved the CNC: unit times without a block (§9.2).
    pub const G05: &str = "CG-G05";
}
