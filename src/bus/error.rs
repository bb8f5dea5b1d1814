//! The bus's errors: why the session could not be opened or a route declared
//! ([`BusError`]), and why the roles' access-control rules cannot join the zenoh file's
//! ([`AclError`]). Apart from the modules that raise them, so that every module of `bus/`
//! can name them without importing the one that opens the session.

use std::path::PathBuf;

/// The id prefix of every rule, subject and policy cellgate generates; a zenoh file's own
/// access-control entries may not use it.
pub const ID_PREFIX: &str = "cellgate/";

/// Why the generated rules cannot be merged into the zenoh configuration.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum AclError {
    /// The zenoh file turns access control on with `default_permission = allow`: cellgate's
    /// keys would then be open to anyone no rule names.
    #[error(
        "access_control.default_permission = \"allow\" in the zenoh configuration file: with \
         [[security.roles]] everything no role or rule allows must be denied; set it to \"deny\" \
         and add allow rules for your own keys"
    )]
    DefaultAllow,
    /// An entry of the zenoh file uses an id cellgate keeps for its own.
    #[error(
        "access_control.{list}: id {id:?} in the zenoh configuration file starts with \
         {ID_PREFIX:?}, which cellgate keeps for the rules it generates; rename it"
    )]
    ReservedId { list: &'static str, id: String },
    /// The zenoh file's access_control section is not what zenoh documents.
    #[error("access_control in the zenoh configuration file: {0}")]
    Malformed(String),
}

/// Why the Zenoh session could not be opened.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BusError {
    /// The json5 file named by `bus.zenoh_config` could not be read or parsed.
    #[error("zenoh configuration file {}: {source}", path.display())]
    ConfigFile {
        path: PathBuf,
        #[source]
        source: zenoh::Error,
    },
    /// Zenoh refused a value the cell file supplies (e.g. a malformed endpoint).
    #[error("bus.{field} = {value}: zenoh refuses it: {source}")]
    ConfigValue {
        /// The `[bus]` key the value came from.
        field: &'static str,
        value: String,
        #[source]
        source: zenoh::Error,
    },
    /// The session did not open: typically an endpoint already in use, or unreachable in
    /// client mode.
    #[error("cannot open the zenoh session (listen {listen:?}, connect {connect:?}): {source}")]
    Open {
        listen: Vec<String>,
        connect: Vec<String>,
        #[source]
        source: zenoh::Error,
    },
    /// `bus.prefix` and `cell` do not make a key prefix.
    #[error(transparent)]
    Keys(#[from] super::keys::KeyError),
    /// A `[security]` path zenoh cannot take: its configuration holds paths as UTF-8 text.
    #[error("{field} = {}: zenoh takes only UTF-8 paths", path.display())]
    Path { field: &'static str, path: PathBuf },
    /// Zenoh refused a `[security]` setting.
    #[error("{field}: zenoh refuses it: {source}")]
    SecurityValue {
        field: &'static str,
        #[source]
        source: zenoh::Error,
    },
    /// The roles' access-control rules cannot join the zenoh file's.
    #[error(transparent)]
    AccessControl(#[from] AclError),
    /// Zenoh refused to declare a route's queryable, subscriber or publisher.
    #[error("cannot declare the {what} on {key:?}: {source}")]
    Declare {
        what: &'static str,
        key: String,
        #[source]
        source: zenoh::Error,
    },
    /// The job journal could not be opened.
    #[error(transparent)]
    Journal(#[from] crate::jobs::journal::JournalError),
    /// A task of the gateway's own ended abnormally.
    #[error("internal: {0}")]
    Internal(String),
}
