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
