//! A client of the cell's bus contract: the library side of `cellgate submit`, `status`,
//! `watch`, `do`, `di`, `program` and `cancel`.
//!
//! [`Client::connect`] opens a zenoh session in client mode that connects to one endpoint
//! only, listens nowhere and has multicast scouting off, then finds the cell: the one named,
//! or, if none is, the only cell whose gateway answers `P/*/@admin` there. Every operation
//! after that speaks the contract of [`crate::bus`] (keys of [`CellKeys`], protobuf payloads
//! of [`cellgate_core::pb`], `ErrorReply` on refusal) and nothing else, so it works against any
//! gateway of the same contract. The operations live by contract area, one file each:
//! machines (status, DI/DO), jobs, programs, history, G05, reload, [`plc`] and [`sim`]; this file
//! holds the connection, errors and the request helpers they share. [`cli`] turns the
//! operations into the commands; [`render`] formats their results for people (text) and
//! programs (JSON).

pub mod cli;
pub mod follow;
mod g05;
mod history;
mod jobs;
mod machines;
mod programs;
mod reload;
pub mod site;
mod watch;

pub use self::jobs::{JobFollower, JobOutcome, is_end, machine_of_job, new_request_id};
pub use self::reload::RELOAD_TIMEOUT;
pub(crate) use self::watch::subscribe_into;
pub use self::watch::{Watch, WatchEvent};
pub mod plc;
pub mod render;
pub mod sim;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use prost::Message;
use zenoh::Session;
use zenoh::bytes::{Encoding, ZBytes};
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::query::{ConsolidationMode, Reply};
use zenoh::sample::Sample;

use crate::bus::keys::{
    CellKeys, KeyError, admin_selector, cell_of_admin_key, cell_of_gateway_key, gateway_selector,
    is_plain_chunk,
};
use crate::bus::payload::{BusMessage, encoding, schema_of};
use crate::bus::{BusConfig, BusError, BusMode};
use cellgate_core::pb;
use cellgate_core::program::name::NameError;

/// The endpoint a client connects to unless told otherwise: where `cellgate run` listens
/// by default.
pub const DEFAULT_ENDPOINT: &str = "tcp/127.0.0.1:7447";

/// How long an ordinary request (status, program library, admin) may wait for its reply.
/// A get ends as soon as every gateway that matches has answered, so this only bounds the
/// wait on a gateway that stopped answering.
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(10);

/// How long a job request may wait for `JobAccepted`: the gateway checks the whole program
/// (and may fetch it from a key, for up to 5 s) before answering.
pub const SUBMIT_TIMEOUT: Duration = Duration::from_secs(60);

/// How long a DI read or a DO output may wait. The gateway answers within 2·Tp + 1 s (the
/// board's next exchange, one missed poll allowed, `bus/machine.rs`), and Tp is at most
/// 99 s (§4.5).
pub const IO_TIMEOUT: Duration = Duration::from_secs(205);

/// How long a followed job may stay silent before the client asks the gateway for its latest
/// event (a job waiting in the queue publishes nothing).
pub const SILENCE: Duration = Duration::from_secs(5);

/// Why a client operation failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ClientError {
    /// The endpoint given with `--connect` is not one (zenoh's own error, a JSON5 parse
    /// error with source paths, is kept as the source, not shown).
    #[error(
        "--connect {endpoint}: not a zenoh endpoint: endpoints look like tcp/127.0.0.1:7447 \
         (PROTOCOL/ADDRESS: tcp/HOST:PORT, tls/HOST:PORT, unixsock-stream/PATH)"
    )]
    Endpoint {
        endpoint: String,
        #[source]
        source: Option<BusError>,
    },
    /// Nothing accepted the connection.
    #[error("{}", unreachable_message(endpoint, *secured))]
    Unreachable {
        endpoint: String,
        /// Whether the client used TLS or a user name: the gateway may have refused it.
        secured: bool,
        #[source]
        source: zenoh::Error,
    },
    /// The TLS or user-name options do not fit together or with the endpoint.
    #[error("{what}: {reason}")]
    Security { what: String, reason: String },
    /// The session opened, but no gateway of the cell (or of any cell) answered its admin
    /// key.
    #[error("{}", no_gateway_message(endpoint, prefix, cell.as_deref(), others))]
    NoGateway {
        endpoint: String,
        prefix: String,
        cell: Option<String>,
        /// Cells whose gateways did answer.
        others: Vec<String>,
    },
    /// No cell was named and several answer.
    #[error(
        "gateways of several cells answer at {endpoint}: {}; choose one with --cell",
        cells.join(", ")
    )]
    SeveralCells {
        endpoint: String,
        cells: Vec<String>,
    },
    /// `--prefix` and `--cell` do not make a key.
    #[error("--prefix/--cell: {0}")]
    Keys(#[from] KeyError),
    /// A command-line value that cannot be used (a machine name with a wildcard, a DO value
    /// out of range, ...).
    #[error("{what}: {reason}")]
    InvalidArgument { what: String, reason: String },
    /// A library name the gateway would refuse.
    #[error("{0}")]
    ProgramName(#[source] NameError),
    /// The gateway answered with an `ErrorReply`.
    #[error("{what}: refused by the gateway ({}): {message}", code.as_str_name())]
    Refused {
        what: String,
        code: pb::ErrorCode,
        message: String,
    },
    /// No gateway answered the request in time.
    #[error(
        "{what}: no answer on {key} within {} s; is the gateway of this cell still running?",
        timeout.as_secs()
    )]
    NoAnswer {
        what: String,
        key: String,
        timeout: Duration,
    },
    /// The request ended at once without a reply: nothing that serves the key would take it
    /// from this client. On a cell with roles, that is a request no role of the client's
    /// certificate or user name allows.
    #[error(
        "{what}: nothing answered on {key}: the request was not taken. On a cell with \
         [security] roles, your certificate or user name lacks the permission; otherwise the \
         gateway has stopped"
    )]
    NotTaken { what: String, key: String },
    /// The reply could not be read as the message the contract names.
    #[error("{what}: the reply on {key} is not a {expected}: {detail}")]
    BadReply {
        what: String,
        key: String,
        expected: &'static str,
        detail: String,
    },
    /// Zenoh failed a declaration, a put or a get.
    #[error("{what}: zenoh: {source}")]
    Zenoh {
        what: String,
        #[source]
        source: zenoh::Error,
    },
    /// The session closed under a subscriber.
    #[error("{what}: the zenoh session closed")]
    Closed { what: String },
    /// The gateway's liveliness token was withdrawn while a job was followed.
    #[error(
        "{what}: the gateway went away (its liveliness token {key} was withdrawn): it \
         stopped, crashed or can no longer be reached. What became of the job is not known \
         here; the gateway keeps it in its journal, and once it is back `cellgate job {job}` \
         tells (a job that was being sent fails at the restart, at what the board \
         acknowledged, unless it was submitted with --resume-after-restart)"
    )]
    GatewayGone {
        what: String,
        key: String,
        job: String,
    },
    /// A get was answered by more replies than a client keeps.
    #[error("{what}: more than {max} replies on {key}; ask for fewer (name a machine)")]
    TooManyReplies {
        what: String,
        key: String,
        max: usize,
    },
    /// A file given on the command line could not be read or written.
    #[error("{}: cannot {op}: {source}", path.display())]
    File {
        path: std::path::PathBuf,
        op: &'static str,
        #[source]
        source: std::io::Error,
    },
}

/// A file the user named, read whole; a failure names the file.
pub(crate) async fn read_file(path: &std::path::Path) -> Result<Vec<u8>, ClientError> {
    tokio::fs::read(path)
        .await
        .map_err(|source| ClientError::File {
            path: path.to_path_buf(),
            op: "read",
            source,
        })
}

fn unreachable_message(endpoint: &str, secured: bool) -> String {
    if secured {
        format!(
            "cannot connect to {endpoint}: no zenoh session was accepted there. Is `cellgate run` \
             listening there, on tls/ if it has [security.tls]? A gateway that requires client \
             certificates refuses a client without one signed by its CA (--tls-cert, \
             --tls-key), and the gateway's certificate must be signed by --tls-ca and name the \
             host of the endpoint; with a users file, --user and the password must match"
        )
    } else {
        format!(
            "cannot connect to {endpoint}: no zenoh session was accepted there. Is `cellgate \
             run` running and listening there? (it listens on tcp/127.0.0.1:7447 unless told \
             otherwise; give its endpoint with --connect.) A gateway with [security] refuses a \
             client that does not say who it is: with a users file, give --user and its \
             password (--password-file or CELLGATE_PASSWORD); with [security.tls] it listens \
             on tls/ and needs --tls-ca (and --tls-cert, --tls-key if it requires client \
             certificates)"
        )
    }
}

fn no_gateway_message(
    endpoint: &str,
    prefix: &str,
    cell: Option<&str>,
    others: &[String],
) -> String {
    match cell {
        None => format!(
            "no gateway answered at {endpoint} (on {prefix}/*/@admin): is `cellgate run` running? \
             (if it serves another key prefix, give it with --prefix; a gateway with [security] \
             roles shows itself only to the certificates and user names its roles name)"
        ),
        Some(cell) if others.is_empty() => format!(
            "no gateway of cell {cell} answered at {endpoint} (on {prefix}/{cell}/@admin): is \
             `cellgate run` running for that cell? (a gateway with [security] roles shows itself \
             only to the certificates and user names its roles name)"
        ),
        Some(cell) => format!(
            "no gateway of cell {cell} answered at {endpoint}; cells answering there: {}",
            others.join(", ")
        ),
    }
}

impl ClientError {
    /// The exit code a command ends with on this error: 2 when the request itself is wrong
    /// (usage, a refusal by the gateway), 1 when something failed at run time.
    pub fn exit_code(&self) -> u8 {
        match self {
            ClientError::Endpoint { .. }
            | ClientError::SeveralCells { .. }
            | ClientError::Keys(_)
            | ClientError::InvalidArgument { .. }
            | ClientError::ProgramName(_)
            | ClientError::Refused { .. }
            | ClientError::Security { .. }
            | ClientError::File { op: "read", .. } => 2,
            _ => 1,
        }
    }

    /// The gateway's error code, when the gateway refused.
    pub fn refusal(&self) -> Option<pb::ErrorCode> {
        match self {
            ClientError::Refused { code, .. } => Some(*code),
            _ => None,
        }
    }
}

/// Where and how to connect.
#[derive(Debug, Clone)]
pub struct ConnectOptions {
    /// The zenoh endpoint to connect to (the only one).
    pub endpoint: String,
    /// Key prefix `P`.
    pub prefix: String,
    /// The cell `C`; `None` to discover it.
    pub cell: Option<String>,
    /// Timeout of ordinary requests.
    pub timeout: Duration,
    /// TLS and user name, for a gateway with `[security]`.
    pub security: ClientSecurity,
    /// Who the client says it is, attached to every request (the gateway's audit records
    /// it); `None`: nothing attached.
    pub origin: Option<pb::RequestOrigin>,
}

/// How many times a request that nothing took is sent (see `Client::get_one`).
const NOT_TAKEN_ATTEMPTS: u32 = 3;

/// How long a client keeps asking for a gateway that does not answer yet.
const DISCOVERY_GRACE: Duration = Duration::from_secs(3);

impl Default for ConnectOptions {
    fn default() -> Self {
        ConnectOptions {
            endpoint: DEFAULT_ENDPOINT.to_string(),
            prefix: "cellgate".to_string(),
            cell: None,
            timeout: DEFAULT_TIMEOUT,
            security: ClientSecurity::default(),
            origin: None,
        }
    }
}

/// How a client proves who it is to a gateway with `[security]`, and checks the gateway.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ClientSecurity {
    /// The CA that signed the gateway's certificate (PEM); needed for a `tls/` endpoint.
    pub ca: Option<PathBuf>,
    /// The client's certificate and private key (PEM), for a gateway that requires client
    /// certificates: its common name is what the gateway's roles name.
    pub certificate: Option<PathBuf>,
    pub private_key: Option<PathBuf>,
    /// User name and password, for a gateway with a users file.
    pub credentials: Option<Credentials>,
}

/// A user name and its password. The password is never shown.
#[derive(Clone, PartialEq, Eq)]
pub struct Credentials {
    pub user: String,
    pub password: String,
}

impl std::fmt::Debug for Credentials {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Credentials")
            .field("user", &self.user)
            .finish_non_exhaustive()
    }
}

impl ClientSecurity {
    /// Whether nothing is set: a plain session.
    pub fn is_empty(&self) -> bool {
        *self == ClientSecurity::default()
    }

    /// Writes the settings into a client's zenoh configuration, after checking that they fit
    /// together and with `endpoint`.
    fn apply(&self, endpoint: &str, config: &mut zenoh::Config) -> Result<(), ClientError> {
        let bad = |what: &str, reason: &str| ClientError::Security {
            what: what.to_string(),
            reason: reason.to_string(),
        };
        let tls = endpoint.starts_with("tls/");
        let any_tls = self.ca.is_some() || self.certificate.is_some() || self.private_key.is_some();
        if any_tls && !tls {
            return Err(bad(
                "--tls-ca/--tls-cert/--tls-key",
                &format!("they apply to a tls/ endpoint; --connect is {endpoint}"),
            ));
        }
        if tls && self.ca.is_none() {
            return Err(bad(
                &format!("--connect {endpoint}"),
                "a tls/ endpoint needs --tls-ca, the CA that signed the gateway's certificate",
            ));
        }
        if self.certificate.is_some() != self.private_key.is_some() {
            return Err(bad(
                "--tls-cert/--tls-key",
                "give both the certificate and its private key, or neither",
            ));
        }
        let set = |config: &mut zenoh::Config, what: &str, key: &str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| bad(what, &format!("zenoh refuses it: {e}")))
        };
        let path = |what: &str, p: &Path| -> Result<String, ClientError> {
            p.to_str()
                .map(|s| serde_json::Value::from(s).to_string())
                .ok_or_else(|| bad(what, "zenoh takes only UTF-8 paths"))
        };
        const TLS: &str = "transport/link/tls";
        if let Some(ca) = &self.ca {
            let v = path("--tls-ca", ca)?;
            set(config, "--tls-ca", &format!("{TLS}/root_ca_certificate"), v)?;
        }
        if let (Some(cert), Some(key)) = (&self.certificate, &self.private_key) {
            let c = path("--tls-cert", cert)?;
            let k = path("--tls-key", key)?;
            set(
                config,
                "--tls-cert",
                &format!("{TLS}/connect_certificate"),
                c,
            )?;
            set(
                config,
                "--tls-key",
                &format!("{TLS}/connect_private_key"),
                k,
            )?;
            set(
                config,
                "--tls-cert",
                &format!("{TLS}/enable_mtls"),
                "true".into(),
            )?;
        }
        if let Some(c) = &self.credentials {
            let user = serde_json::Value::from(c.user.as_str()).to_string();
            let password = serde_json::Value::from(c.password.as_str()).to_string();
            set(config, "--user", "transport/auth/usrpwd/user", user)?;
            set(config, "--user", "transport/auth/usrpwd/password", password)?;
        }
        Ok(())
    }
}

/// One reply to a get: the sample's key, payload and encoding, or the error's payload and
/// encoding.
type RawReply = Result<(String, Vec<u8>, Encoding), (Vec<u8>, Encoding)>;
type RawReplies = Vec<RawReply>;

/// A connected client of one cell.
#[derive(Clone)]
pub struct Client {
    session: Session,
    keys: CellKeys,
    endpoint: String,
    timeout: Duration,
    admin: Arc<serde_json::Value>,
    /// The encoded `RequestOrigin` attached to every request, if any.
    origin: Option<Vec<u8>>,
}

impl std::fmt::Debug for Client {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Client")
            .field("root", &self.keys.root())
            .field("endpoint", &self.endpoint)
            .finish_non_exhaustive()
    }
}

/// The zenoh configuration of a client session: client mode, the one endpoint, no listen,
/// no multicast scouting, and the TLS and user settings of `security`. In client mode zenoh
/// tries the endpoint once and fails at once if nothing accepts, which is what a command
/// wants.
pub fn client_config(
    endpoint: &str,
    security: &ClientSecurity,
) -> Result<zenoh::Config, ClientError> {
    let bus = BusConfig {
        mode: BusMode::Client,
        listen: Vec::new(),
        connect: vec![endpoint.to_string()],
        multicast_scouting: false,
        ..BusConfig::default()
    };
    let shaped = endpoint
        .split_once('/')
        .is_some_and(|(proto, addr)| !proto.is_empty() && !addr.is_empty());
    if !shaped {
        return Err(ClientError::Endpoint {
            endpoint: endpoint.to_string(),
            source: None,
        });
    }
    let mut config =
        crate::bus::session::zenoh_config(&bus).map_err(|source| ClientError::Endpoint {
            endpoint: endpoint.to_string(),
            source: Some(source),
        })?;
    security.apply(endpoint, &mut config)?;
    Ok(config)
}

/// A client session to `options.endpoint` (client mode, no listen endpoint, multicast
/// scouting off), as every client of the bus contract opens it: the CLI, the site console,
/// the site MTConnect agent, the historian.
pub async fn open_session(options: &ConnectOptions) -> Result<Session, ClientError> {
    let config = client_config(&options.endpoint, &options.security)?;
    zenoh::open(config)
        .await
        .map_err(|source| ClientError::Unreachable {
            endpoint: options.endpoint.clone(),
            secured: !options.security.is_empty(),
            source,
        })
}

impl Client {
    /// Connects to `options.endpoint` and finds the cell. Must run on a multi-thread Tokio
    /// runtime (zenoh's requirement); close the client with [`Client::close`].
    pub async fn connect(options: &ConnectOptions) -> Result<Client, ClientError> {
        // Both checked before any connection: a bad prefix or cell is a usage error.
        CellKeys::new(&options.prefix, options.cell.as_deref().unwrap_or("cell"))?;
        let session = open_session(options).await?;
        match Self::find_cell(&session, options).await {
            Ok((cell, admin)) => match CellKeys::new(&options.prefix, &cell) {
                Ok(keys) => Ok(Client {
                    session,
                    keys,
                    endpoint: options.endpoint.clone(),
                    timeout: options.timeout,
                    admin: Arc::new(admin),
                    origin: options.origin.as_ref().map(Message::encode_to_vec),
                }),
                Err(e) => {
                    let _ = session.close().await;
                    Err(e.into())
                }
            },
            Err(e) => {
                let _ = session.close().await;
                Err(e)
            }
        }
    }

    /// The cells whose gateways answer `P/<cell>/@admin` (`cell` may be `*`), with their
    /// admin documents.
    async fn admin_answers(
        session: &Session,
        prefix: &str,
        cell: &str,
        timeout: Duration,
    ) -> Result<Vec<(String, serde_json::Value)>, ClientError> {
        let key = admin_selector(prefix, cell);
        let replies = session
            .get(key.as_str())
            .consolidation(ConsolidationMode::None)
            .timeout(timeout)
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("get {key}"),
                source,
            })?;
        let mut found = Vec::new();
        while let Ok(reply) = replies.recv_async().await {
            let Ok(sample) = reply.result() else { continue };
            let Some(name) = cell_of_admin_key(prefix, sample.key_expr().as_str()) else {
                continue;
            };
            let doc = serde_json::from_slice(&sample.payload().to_bytes())
                .unwrap_or(serde_json::Value::Null);
            if !found.iter().any(|(c, _)| c == name) {
                found.push((name.to_string(), doc));
            }
        }
        if found.is_empty() {
            // A gateway with roles answers @admin only to `admin.read`; its liveliness token
            // stands for every role.
            for cell in Self::gateway_tokens(session, prefix, cell, timeout).await? {
                found.push((cell, serde_json::Value::Null));
            }
        }
        found.sort_by(|a, b| a.0.cmp(&b.0));
        Ok(found)
    }

    /// The cells whose gateways' liveliness tokens `P/<cell>/gateway` stand.
    async fn gateway_tokens(
        session: &Session,
        prefix: &str,
        cell: &str,
        timeout: Duration,
    ) -> Result<Vec<String>, ClientError> {
        let key = gateway_selector(prefix, cell);
        let replies = session
            .liveliness()
            .get(key.as_str())
            .timeout(timeout)
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("get the liveliness tokens {key}"),
                source,
            })?;
        let mut cells = Vec::new();
        while let Ok(reply) = replies.recv_async().await {
            let Ok(sample) = reply.result() else { continue };
            if let Some(name) = cell_of_gateway_key(prefix, sample.key_expr().as_str())
                && !cells.iter().any(|c| c == name)
            {
                cells.push(name.to_string());
            }
        }
        Ok(cells)
    }

    /// [`Self::find_cell_once`], asked again for a short while when no gateway answered: a
    /// gateway that is starting shows itself once its routes are declared, and a session that
    /// has just opened may not have heard of the gateway's declarations yet.
    async fn find_cell(
        session: &Session,
        options: &ConnectOptions,
    ) -> Result<(String, serde_json::Value), ClientError> {
        let grace = options.timeout.min(DISCOVERY_GRACE);
        let started = tokio::time::Instant::now();
        loop {
            match Self::find_cell_once(session, options).await {
                Err(ClientError::NoGateway { .. }) if started.elapsed() < grace => {
                    tokio::time::sleep(Duration::from_millis(200)).await;
                }
                found => return found,
            }
        }
    }

    async fn find_cell_once(
        session: &Session,
        options: &ConnectOptions,
    ) -> Result<(String, serde_json::Value), ClientError> {
        let prefix = options.prefix.as_str();
        let no_gateway = |cell: Option<&str>, others: Vec<String>| ClientError::NoGateway {
            endpoint: options.endpoint.clone(),
            prefix: prefix.to_string(),
            cell: cell.map(str::to_string),
            others,
        };
        if let Some(cell) = options.cell.as_deref() {
            let mut answers = Self::admin_answers(session, prefix, cell, options.timeout).await?;
            return match answers.pop() {
                Some(answer) => Ok(answer),
                None => {
                    let others = Self::admin_answers(session, prefix, "*", options.timeout)
                        .await?
                        .into_iter()
                        .map(|(c, _)| c)
                        .collect();
                    Err(no_gateway(Some(cell), others))
                }
            };
        }
        let mut answers = Self::admin_answers(session, prefix, "*", options.timeout).await?;
        match answers.len() {
            0 => Err(no_gateway(None, Vec::new())),
            1 => Ok(answers.remove(0)),
            _ => Err(ClientError::SeveralCells {
                endpoint: options.endpoint.clone(),
                cells: answers.into_iter().map(|(c, _)| c).collect(),
            }),
        }
    }

    /// A client of `cell` over a session opened elsewhere (the console's), with the admin
    /// document found for it. Closing it closes that session: drop it instead.
    pub fn attach(
        session: Session,
        prefix: &str,
        cell: &str,
        admin: serde_json::Value,
        timeout: Duration,
    ) -> Result<Client, ClientError> {
        Ok(Client {
            keys: CellKeys::new(prefix, cell)?,
            endpoint: String::new(),
            session,
            timeout,
            admin: Arc::new(admin),
            origin: None,
        })
    }

    /// The same client, saying `origin` sent what it asks.
    pub fn with_origin(&self, origin: &pb::RequestOrigin) -> Client {
        Client {
            origin: Some(origin.encode_to_vec()),
            ..self.clone()
        }
    }

    /// The cells whose gateways answer under `prefix`, with their admin documents (`Null`
    /// where a gateway does not show it): what a site view serves.
    pub async fn discover(
        session: &Session,
        prefix: &str,
        timeout: Duration,
    ) -> Result<Vec<(String, serde_json::Value)>, ClientError> {
        Self::admin_answers(session, prefix, "*", timeout).await
    }

    /// Closes the session. Call it before the runtime ends.
    pub async fn close(self) {
        if let Err(e) = self.session.close().await {
            tracing::debug!(error = %e, "closing the client session");
        }
    }

    /// The cell's keys.
    pub fn keys(&self) -> &CellKeys {
        &self.keys
    }

    /// The cell's name.
    pub fn cell(&self) -> &str {
        self.keys
            .root()
            .rsplit_once('/')
            .map_or(self.keys.root(), |(_, c)| c)
    }

    /// The gateway's admin document (`name`, `version`, `cell`, `zid`, `config`); `Null` when
    /// the gateway does not show it to this client (a cell with roles, without `admin.read`).
    pub fn admin(&self) -> &serde_json::Value {
        &self.admin
    }

    /// The zenoh session, for what the commands do not cover.
    pub fn session(&self) -> &Session {
        &self.session
    }

    /// The machines the gateway's configuration names, if its admin document says.
    pub fn configured_machines(&self) -> Vec<String> {
        self.admin["config"]["machines"]
            .as_array()
            .map(|ms| {
                ms.iter()
                    .filter_map(|m| m["name"].as_str().map(str::to_string))
                    .collect()
            })
            .unwrap_or_default()
    }

    // ---- requests --------------------------------------------------------------------------

    /// Every reply to a get on `key`.
    async fn get_raw(
        &self,
        what: &str,
        key: &str,
        payload: Option<(Vec<u8>, Encoding)>,
        timeout: Duration,
    ) -> Result<RawReplies, ClientError> {
        get_raw(
            &self.session,
            what,
            key,
            payload,
            timeout,
            self.origin.clone(),
        )
        .await
    }

    /// The replies to a get, each decoded as `M`; the first `ErrorReply` fails the whole.
    async fn get_all<M: BusMessage>(
        &self,
        what: &str,
        key: &str,
        payload: Option<(Vec<u8>, Encoding)>,
        timeout: Duration,
    ) -> Result<Vec<(String, M)>, ClientError> {
        let replies = self.get_raw(what, key, payload, timeout).await?;
        decode_all(what, replies)
    }

    /// The one message a concrete get answers.
    async fn get_one<M: BusMessage>(
        &self,
        what: &str,
        key: &str,
        payload: Option<(Vec<u8>, Encoding)>,
        timeout: Duration,
    ) -> Result<M, ClientError> {
        let asked = std::time::Instant::now();
        let mut attempts = 0;
        loop {
            attempts += 1;
            let first = self
                .get_all(what, key, payload.clone(), timeout)
                .await?
                .into_iter()
                .next()
                .map(|(_, m)| m);
            match first {
                Some(m) => return Ok(m),
                // Ended at once with no reply: nothing took it. A session that has just
                // opened may not know the gateway's queryable yet, so ask again twice; a
                // request the access rules refuse stays refused. Asking again is harmless:
                // what was not taken did nothing.
                None if attempts < NOT_TAKEN_ATTEMPTS && asked.elapsed() < timeout / 2 => {
                    tokio::time::sleep(Duration::from_millis(300)).await;
                }
                None => return Err(no_reply(what, key, timeout, asked.elapsed())),
            }
        }
    }

    /// [`Self::get_one`] with the PLC time-out, for `client::plc`.
    pub(crate) async fn get_one_pub<M: BusMessage>(
        &self,
        what: &str,
        key: &str,
        payload: Option<(Vec<u8>, Encoding)>,
    ) -> Result<M, ClientError> {
        self.get_one(what, key, payload, plc::PLC_TIMEOUT).await
    }

    /// [`Self::get_all`] with the ordinary time-out, for `client::plc`.
    pub(crate) async fn get_all_pub<M: BusMessage>(
        &self,
        what: &str,
        key: &str,
        payload: Option<(Vec<u8>, Encoding)>,
    ) -> Result<Vec<(String, M)>, ClientError> {
        self.get_all(what, key, payload, self.timeout).await
    }

    pub(crate) fn machine_arg(machine: &str) -> Result<(), ClientError> {
        if is_plain_chunk(machine) {
            Ok(())
        } else {
            Err(ClientError::InvalidArgument {
                what: format!("machine {machine:?}"),
                reason: "name one machine: one key chunk, without '/', '*', '$', '?' or '#'"
                    .to_string(),
            })
        }
    }

    /// Subscribes to job events on `key`.
    async fn subscribe(
        &self,
        key: &str,
    ) -> Result<Subscriber<FifoChannelHandler<Sample>>, ClientError> {
        self.session
            .declare_subscriber(key)
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("subscribe to {key}"),
                source,
            })
    }

    // ---- G05 streams -----------------------------------------------------------------------

    // ---- program library -------------------------------------------------------------------

    // ---- history ---------------------------------------------------------------------------

    /// A confirmed library change: a get with a `ProgramWrite` on the program's write key.
    async fn program_write(
        &self,
        name: &str,
        op: &str,
        write: pb::ProgramWrite,
    ) -> Result<pb::ProgramInfo, ClientError> {
        let key = self.keys.program_write(name);
        // Encoded, the message is not kept beside its encoding while it is sent: a store's
        // program may be large.
        let payload = ({ write }.encode_to_vec(), encoding::<pb::ProgramWrite>());
        self.get_one(
            &format!("{op} program {name}"),
            &key,
            Some(payload),
            self.timeout,
        )
        .await
    }

    // ---- watch -----------------------------------------------------------------------------
}

/// The error for a get that got no reply after `waited`: a get that ended well before its
/// time-out was not taken (refused by access control, or nothing serves the key any more).
fn no_reply(what: &str, key: &str, timeout: Duration, waited: Duration) -> ClientError {
    if waited < timeout / 2 {
        ClientError::NotTaken {
            what: what.to_string(),
            key: key.to_string(),
        }
    } else {
        ClientError::NoAnswer {
            what: what.to_string(),
            key: key.to_string(),
            timeout,
        }
    }
}

/// `key?name=value;...`: zenoh's selector with parameters. A name or value that would make
/// another parameter (`;`, `=`, `?`, `#`) is refused: what a caller passes through (a
/// console's query string) never becomes more than the one parameter it names.
fn with_params(key: String, params: &[(String, String)]) -> Result<String, ClientError> {
    if params.is_empty() {
        return Ok(key);
    }
    let mut p = Vec::with_capacity(params.len());
    for (k, v) in params {
        let bad = |s: &str| s.contains([';', '=', '?', '#', '&', '$']);
        if k.is_empty() || bad(k) || bad(v) {
            return Err(ClientError::InvalidArgument {
                what: format!("parameter {k:?}"),
                reason: format!(
                    "{v:?}: names and values may not hold ';', '=', '?', '#', '&' or '$'"
                ),
            });
        }
        p.push(format!("{k}={v}"));
    }
    Ok(format!("{key}?{}", p.join(";")))
}

/// `what` names one key chunk: no '/', wildcard or selector character.
pub(crate) fn chunk_arg(what: &str, value: &str) -> Result<(), ClientError> {
    if is_plain_chunk(value) {
        Ok(())
    } else {
        Err(ClientError::InvalidArgument {
            what: format!("{what} {value:?}"),
            reason: "one key chunk, without '/', '*', '$', '?' or '#'".to_string(),
        })
    }
}

async fn get_raw(
    session: &Session,
    what: &str,
    key: &str,
    payload: Option<(Vec<u8>, Encoding)>,
    timeout: Duration,
    origin: Option<Vec<u8>>,
) -> Result<RawReplies, ClientError> {
    let mut builder = session.get(key).timeout(timeout);
    if let Some((bytes, enc)) = payload {
        builder = builder.payload(ZBytes::from(bytes)).encoding(enc);
    }
    if let Some(origin) = origin {
        builder = builder.attachment(ZBytes::from(origin));
    }
    // The replies go through a callback into an unbounded channel, not zenoh's default FIFO
    // of 256: in the gateway's own session (its console) a reply is handed over on the
    // replying route's thread, and a full FIFO blocks that thread. A wildcard status get over
    // more than 256 machines hung the status route for good: its thread parked in the FIFO's
    // send while the runtime's other thread sat idle and the draining task never ran (likely
    // held in the blocked thread's LIFO slot, which tokio does not steal; not proven).
    // The callback never blocks; what it holds is bounded by MAX_REPLIES. zenoh drops the
    // callback when the query ends (final reply or time-out), which ends the channel.
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let taken = std::sync::atomic::AtomicUsize::new(0);
    builder
        .callback(move |reply: Reply| {
            let n = taken.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let _ = tx.send((n < MAX_REPLIES).then(|| raw(&reply)));
        })
        .await
        .map_err(|source| ClientError::Zenoh {
            what: format!("{what}: get {key}"),
            source,
        })?;
    let mut out = Vec::new();
    while let Some(reply) = rx.recv().await {
        match reply {
            Some(r) => out.push(r),
            None => {
                return Err(ClientError::TooManyReplies {
                    what: what.to_string(),
                    key: key.to_string(),
                    max: MAX_REPLIES,
                });
            }
        }
    }
    Ok(out)
}

/// Replies one get keeps at most: every machine of the largest cell answers a wildcard status
/// get, many times over.
const MAX_REPLIES: usize = 1 << 16;

fn raw(reply: &Reply) -> RawReply {
    match reply.result() {
        Ok(s) => Ok((
            s.key_expr().to_string(),
            s.payload().to_bytes().into_owned(),
            s.encoding().clone(),
        )),
        Err(e) => Err((e.payload().to_bytes().into_owned(), e.encoding().clone())),
    }
}

fn decode_all<M: BusMessage>(
    what: &str,
    replies: RawReplies,
) -> Result<Vec<(String, M)>, ClientError> {
    let mut out = Vec::new();
    for reply in replies {
        match reply {
            Ok((reply_key, bytes, enc)) => out.push((
                reply_key.clone(),
                decode::<M>(what, &reply_key, &bytes, &enc)?,
            )),
            Err((bytes, enc)) => return Err(refusal(what, &bytes, &enc)),
        }
    }
    Ok(out)
}

/// Decodes a payload as `M`, checking the schema its encoding names (if any).
fn decode<M: BusMessage>(
    what: &str,
    key: &str,
    bytes: &[u8],
    enc: &Encoding,
) -> Result<M, ClientError> {
    let bad = |detail: String| ClientError::BadReply {
        what: what.to_string(),
        key: key.to_string(),
        expected: M::SCHEMA,
        detail,
    };
    if let Some(schema) = schema_of(enc)
        && schema != M::SCHEMA
    {
        return Err(bad(format!("its encoding names {schema}")));
    }
    M::decode(bytes).map_err(|e| bad(e.to_string()))
}

/// An error reply as a [`ClientError::Refused`]: the `ErrorReply` if it is one, else the
/// payload as text.
fn refusal(what: &str, bytes: &[u8], enc: &Encoding) -> ClientError {
    let is_error_reply = schema_of(enc).is_none_or(|s| s == pb::ErrorReply::SCHEMA);
    match pb::ErrorReply::decode(bytes) {
        Ok(e) if is_error_reply => ClientError::Refused {
            what: what.to_string(),
            code: e.code(),
            message: e.message,
        },
        _ => ClientError::Refused {
            what: what.to_string(),
            code: pb::ErrorCode::Unspecified,
            message: String::from_utf8_lossy(bytes).into_owned(),
        },
    }
}

/// Reads a byte given as `0x..` (hex), `0b..` (binary) or decimal, with optional `_`
/// separators, range-checked 0..=255.
pub fn parse_byte(text: &str) -> Result<u8, String> {
    let t = text.trim().replace('_', "");
    let lower = t.to_ascii_lowercase();
    let (digits, radix) = if let Some(h) = lower.strip_prefix("0x") {
        (h, 16)
    } else if let Some(b) = lower.strip_prefix("0b") {
        (b, 2)
    } else {
        (lower.as_str(), 10)
    };
    if digits.is_empty() {
        return Err(format!("{text:?} has no digits"));
    }
    let value = u64::from_str_radix(digits, radix).map_err(|_| {
        format!("{text:?} is not a number (write 0x.. for hex, 0b.. for binary, or decimal)")
    })?;
    u8::try_from(value).map_err(|_| format!("{text:?} = {value} is out of range 0..=255 (8 bits)"))
}

#[cfg(test)]
mod tests;
