//! A client of the cell's bus contract: the library side of `cellgate submit`, `status`,
//! `watch`, `do`, `di`, `program` and `cancel`.
//!
//! [`Client::connect`] opens a zenoh session in client mode that connects to one endpoint
//! only, listens nowhere and has multicast scouting off, then finds the cell: the one named,
//! or, if none is, the only cell whose gateway answers `P/*/@admin` there. Every operation
//! after that speaks the contract of [`crate::bus`] (keys of [`CellKeys`], protobuf payloads
//! of [`cellgate_core::pb`], `ErrorReply` on refusal) and nothing else, so it works against any
//! gateway of the same contract. [`cli`] turns the operations into the commands; [`render`]
//! formats their results for people (text) and programs (JSON).

pub mod cli;
pub mod plc;
pub mod records;
pub mod render;
pub mod sim;

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use prost::Message;
use zenoh::Session;
use zenoh::bytes::{Encoding, ZBytes};
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::query::{ConsolidationMode, Reply};
use zenoh::sample::{Sample, SampleKind};

use crate::bus::keys::{
    CellKey, CellKeys, G05Part, KeyError, MachineLeaf, admin_selector, cell_of_admin_key,
    cell_of_gateway_key, gateway_selector, is_plain_chunk,
};
use crate::bus::payload::{BusMessage, encoding, schema_of};
use crate::bus::{BusConfig, BusError, BusMode};
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;
use cellgate_core::program::name::{NameError, check_name};

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
            "cannot connect to {endpoint}: nothing accepted a zenoh session there. Is `cellgate \
             run` running and listening there? (it listens on tcp/127.0.0.1:7447 unless told \
             otherwise; give its endpoint with --connect; a gateway with [security.tls] listens \
             on tls/ and needs --tls-ca, --tls-cert and --tls-key)"
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

impl Client {
    /// Connects to `options.endpoint` and finds the cell. Must run on a multi-thread Tokio
    /// runtime (zenoh's requirement); close the client with [`Client::close`].
    pub async fn connect(options: &ConnectOptions) -> Result<Client, ClientError> {
        // Both checked before any connection: a bad prefix or cell is a usage error.
        CellKeys::new(&options.prefix, options.cell.as_deref().unwrap_or("cell"))?;
        let config = client_config(&options.endpoint, &options.security)?;
        let session = zenoh::open(config)
            .await
            .map_err(|source| ClientError::Unreachable {
                endpoint: options.endpoint.clone(),
                secured: !options.security.is_empty(),
                source,
            })?;
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

    /// Cancels a job with a get on its cancel key and answers how it ended (its `cancelled`
    /// event, or the end it reached first), or its latest event if it has not ended within
    /// the gateway's wait.
    pub async fn cancel_confirmed(
        &self,
        machine: &str,
        job_id: &str,
    ) -> Result<pb::JobEvent, ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.job_cancel(machine, job_id);
        self.get_one(
            &format!("cancel of {job_id}"),
            &key,
            None,
            IO_TIMEOUT.max(Duration::from_secs(30)),
        )
        .await
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

    /// The status of one machine, or of every machine (`None`), sorted by name.
    pub async fn status(
        &self,
        machine: Option<&str>,
    ) -> Result<Vec<pb::MachineStatus>, ClientError> {
        let key = match machine {
            Some(m) => {
                Self::machine_arg(m)?;
                self.keys.leaf(m, MachineLeaf::Status)
            }
            None => self.keys.any_leaf(MachineLeaf::Status),
        };
        let what = match machine {
            Some(m) => format!("status of {m}"),
            None => "status".to_string(),
        };
        let asked = std::time::Instant::now();
        let mut all: Vec<pb::MachineStatus> = self
            .get_all(&what, &key, None, self.timeout)
            .await?
            .into_iter()
            .map(|(_, s)| s)
            .collect();
        if machine.is_some() && all.is_empty() {
            return Err(no_reply(&what, &key, self.timeout, asked.elapsed()));
        }
        all.sort_by(|a, b| a.machine.cmp(&b.machine));
        Ok(all)
    }

    /// Sends a job request to `machine` and returns its `JobAccepted` with a follower of its
    /// events.
    ///
    /// The job id is only known from the reply, so the follower subscribes to every job of
    /// the machine (`P/C/machine/M/job/*`) before the request goes out and keeps the events
    /// of this job. The subscription and the request travel in order on the one link to the
    /// gateway, which processes the subscription first: no event of the job is missed.
    pub async fn submit(
        &self,
        machine: &str,
        request: &pb::JobRequest,
    ) -> Result<(pb::JobAccepted, JobFollower), ClientError> {
        Self::machine_arg(machine)?;
        let what = format!("submit to {machine}");
        let events_key = self.keys.job_events(machine, "*");
        let subscriber = self.subscribe(&events_key).await?;
        let key = self.keys.leaf(machine, MachineLeaf::Submit);
        let payload = (request.encode_to_vec(), encoding::<pb::JobRequest>());
        let accepted: pb::JobAccepted = match self
            .get_one(&what, &key, Some(payload), SUBMIT_TIMEOUT)
            .await
        {
            Ok(a) => a,
            Err(e) => {
                let _ = subscriber.undeclare().await;
                return Err(e);
            }
        };
        let follower = self.follower(subscriber, machine, &accepted.job_id);
        Ok((accepted, follower))
    }

    /// Follows a job already submitted (e.g. by another client).
    pub async fn follow(&self, machine: &str, job_id: &str) -> Result<JobFollower, ClientError> {
        Self::machine_arg(machine)?;
        Self::job_arg(job_id)?;
        let events_key = self.keys.job_events(machine, job_id);
        let subscriber = self.subscribe(&events_key).await?;
        Ok(self.follower(subscriber, machine, job_id))
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

    fn follower(
        &self,
        subscriber: zenoh::pubsub::Subscriber<
            zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>,
        >,
        machine: &str,
        job_id: &str,
    ) -> JobFollower {
        JobFollower {
            session: self.session.clone(),
            subscriber,
            keys: self.keys.clone(),
            machine: machine.to_string(),
            job_id: job_id.to_string(),
            ended: false,
            timeout: self.timeout,
        }
    }

    fn job_arg(job_id: &str) -> Result<(), ClientError> {
        if is_plain_chunk(job_id) {
            Ok(())
        } else {
            Err(ClientError::InvalidArgument {
                what: format!("job {job_id:?}"),
                reason: "name one job id as `submit` printed it, without wildcards".to_string(),
            })
        }
    }

    /// The latest event of a job (the gateway keeps the last 256 jobs of each machine).
    pub async fn job_latest(
        &self,
        machine: &str,
        job_id: &str,
    ) -> Result<pb::JobEvent, ClientError> {
        Self::machine_arg(machine)?;
        Self::job_arg(job_id)?;
        let key = self.keys.job_events(machine, job_id);
        self.get_one(&format!("job {job_id}"), &key, None, self.timeout)
            .await
    }

    /// The last event of every job the gateway keeps (the latest 256 of each machine), of one
    /// machine or of all, oldest first.
    pub async fn recent_jobs(
        &self,
        machine: Option<&str>,
    ) -> Result<Vec<pb::JobEvent>, ClientError> {
        if let Some(m) = machine {
            Self::machine_arg(m)?;
        }
        let key = self.keys.job_events(machine.unwrap_or("*"), "*");
        let mut all: Vec<pb::JobEvent> = self
            .get_all("recent jobs", &key, None, self.timeout)
            .await?
            .into_iter()
            .map(|(_, e)| e)
            .collect();
        all.sort_by(|a, b| (a.unix_ms, &a.job_id).cmp(&(b.unix_ms, &b.job_id)));
        Ok(all)
    }

    /// The queue of one machine.
    pub async fn queue(&self, machine: &str) -> Result<pb::JobQueue, ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.leaf(machine, MachineLeaf::Job);
        self.get_one(&format!("queue of {machine}"), &key, None, self.timeout)
            .await
    }

    /// Cancels a job (a delete on its key) and waits for it to end; returns its last event.
    /// A job that already ended is an error naming how it ended.
    pub async fn cancel(&self, machine: &str, job_id: &str) -> Result<pb::JobEvent, ClientError> {
        let latest = self.job_latest(machine, job_id).await?;
        if is_end(&latest) {
            return Err(ClientError::InvalidArgument {
                what: format!("cancel job {job_id}"),
                reason: format!("the job already ended: {}", render::job_kind_text(&latest)),
            });
        }
        let mut follower = self.follow(machine, job_id).await?;
        let key = self.keys.job_events(machine, job_id);
        let mut delete = self.session.delete(key.as_str());
        if let Some(origin) = &self.origin {
            delete = delete.attachment(ZBytes::from(origin.clone()));
        }
        let deleted = delete.await;
        if let Err(source) = deleted {
            follower.close().await;
            return Err(ClientError::Zenoh {
                what: format!("delete {key}"),
                source,
            });
        }
        let end = follower.wait_end().await;
        follower.close().await;
        end
    }

    /// Outputs DO on `machine` (SDO) with a get, and returns the status the gateway answers
    /// once SDO went out. `mask` `None` sets all 8 bits.
    pub async fn set_do(
        &self,
        machine: &str,
        value: u8,
        mask: Option<u8>,
    ) -> Result<pb::MachineStatus, ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.leaf(machine, MachineLeaf::Do);
        let cmd = pb::DoCommand {
            value: u32::from(value),
            mask: mask.map(u32::from),
        };
        let payload = (cmd.encode_to_vec(), encoding::<pb::DoCommand>());
        self.get_one(&format!("DO of {machine}"), &key, Some(payload), IO_TIMEOUT)
            .await
    }

    /// Outputs DO with a put: no confirmation (the gateway logs a refusal).
    pub async fn put_do(
        &self,
        machine: &str,
        value: u8,
        mask: Option<u8>,
    ) -> Result<(), ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.leaf(machine, MachineLeaf::Do);
        let cmd = pb::DoCommand {
            value: u32::from(value),
            mask: mask.map(u32::from),
        };
        let mut put = self
            .session
            .put(key.as_str(), cmd.encode_to_vec())
            .encoding(encoding::<pb::DoCommand>());
        if let Some(origin) = &self.origin {
            put = put.attachment(ZBytes::from(origin.clone()));
        }
        put.await.map_err(|source| ClientError::Zenoh {
            what: format!("put {key}"),
            source,
        })
    }

    /// Reads DI of `machine` now (RDI → SDI).
    pub async fn read_di(&self, machine: &str) -> Result<pb::DiImage, ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.leaf(machine, MachineLeaf::Di);
        self.get_one(&format!("DI of {machine}"), &key, None, IO_TIMEOUT)
            .await
    }

    // ---- G05 streams -----------------------------------------------------------------------

    /// Opens a G05 stream on `machine` (`stream_id` empty: the gateway names it). With
    /// `producer_token`, the returned token keeps the stream alive: dropping it (or losing
    /// the connection) ends the stream with its end block.
    pub async fn g05_open(
        &self,
        machine: &str,
        stream_id: &str,
        producer_token: bool,
    ) -> Result<(pb::G05Opened, Option<zenoh::liveliness::LivelinessToken>), ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.leaf(machine, MachineLeaf::G05);
        let request = pb::G05Open {
            stream_id: stream_id.to_string(),
            producer_token,
        };
        let payload = (request.encode_to_vec(), encoding::<pb::G05Open>());
        let opened: pb::G05Opened = self
            .get_one(
                &format!("G05 stream on {machine}"),
                &key,
                Some(payload),
                self.timeout,
            )
            .await?;
        let token = if producer_token {
            let key = self.keys.g05(machine, &opened.stream_id, G05Part::Producer);
            let token = self
                .session
                .liveliness()
                .declare_token(key.as_str())
                .await
                .map_err(|source| ClientError::Zenoh {
                    what: format!("liveliness token {key}"),
                    source,
                })?;
            Some(token)
        } else {
            None
        };
        Ok((opened, token))
    }

    /// Sends a batch of a stream (a put: express; errors show in the stream's status).
    pub async fn g05_batch(
        &self,
        machine: &str,
        stream: &str,
        batch: &pb::G05Batch,
    ) -> Result<(), ClientError> {
        let key = self.keys.g05(machine, stream, G05Part::Blocks);
        self.session
            .put(key.as_str(), batch.encode_to_vec())
            .encoding(encoding::<pb::G05Batch>())
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .express(true)
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("put {key}"),
                source,
            })
    }

    /// Sends a batch of a stream and waits for the gateway's answer: the stream's status with
    /// the batch taken, or the refusal (a travel out of range, no credits, a gap).
    pub async fn g05_batch_acked(
        &self,
        machine: &str,
        stream: &str,
        batch: &pb::G05Batch,
    ) -> Result<pb::G05Status, ClientError> {
        let key = self.keys.g05(machine, stream, G05Part::Blocks);
        let payload = (batch.encode_to_vec(), encoding::<pb::G05Batch>());
        self.get_one(
            &format!("batch {} of G05 stream {stream}", batch.seq),
            &key,
            Some(payload),
            self.timeout,
        )
        .await
    }

    /// Follows a stream's status.
    pub async fn g05_status(
        &self,
        machine: &str,
        stream: &str,
    ) -> Result<zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<Sample>>, ClientError>
    {
        self.subscribe(&self.keys.g05(machine, stream, G05Part::Status))
            .await
    }

    /// Cancels a stream: the gateway sends the end block and frees the machine.
    pub async fn g05_cancel(&self, machine: &str, stream: &str) -> Result<(), ClientError> {
        let key = self.keys.g05(machine, stream, G05Part::Status);
        self.session
            .delete(key.as_str())
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("delete {key}"),
                source,
            })
    }

    // ---- program library -------------------------------------------------------------------

    fn program_arg(name: &str) -> Result<(), ClientError> {
        check_name(name).map_err(ClientError::ProgramName)
    }

    /// Every program of the library, sorted by name.
    pub async fn program_list(&self) -> Result<Vec<pb::ProgramInfo>, ClientError> {
        let key = self.keys.any_program();
        let mut all: Vec<pb::ProgramInfo> = self
            .get_all("program library", &key, None, self.timeout)
            .await?
            .into_iter()
            .map(|(_, p)| p)
            .collect();
        all.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(all)
    }

    /// One program's bytes.
    pub async fn program_get(&self, name: &str) -> Result<Vec<u8>, ClientError> {
        Self::program_arg(name)?;
        let key = self.keys.program(name);
        let what = format!("program {name}");
        let replies = self.get_raw(&what, &key, None, self.timeout).await?;
        match replies.into_iter().next() {
            Some(Ok((_, bytes, _))) => Ok(bytes),
            Some(Err((bytes, enc))) => Err(refusal(&what, &bytes, &enc)),
            None => Err(ClientError::NoAnswer {
                what,
                key,
                timeout: self.timeout,
            }),
        }
    }

    /// Stores a program in the library; answers it as stored, once it is on the gateway's
    /// disk (a get with a `ProgramWrite`).
    pub async fn program_put(
        &self,
        name: &str,
        program: &[u8],
    ) -> Result<pb::ProgramInfo, ClientError> {
        Self::program_arg(name)?;
        if let Some(max) = self.admin["config"]["programs"]["max_size"].as_u64()
            && program.len() as u64 > max
        {
            return Err(ClientError::InvalidArgument {
                what: format!("program {name}"),
                reason: format!(
                    "{} bytes; the gateway's programs.max_size allows {max}",
                    program.len()
                ),
            });
        }
        self.program_put_with(name, program, String::new()).await
    }

    /// [`Self::program_put`] with a comment for the revision it makes.
    pub async fn program_put_with(
        &self,
        name: &str,
        program: &[u8],
        comment: String,
    ) -> Result<pb::ProgramInfo, ClientError> {
        self.program_store(name, program.to_vec(), comment).await
    }

    /// [`Self::program_put_with`], taking the program's bytes (no copy of them is made).
    pub async fn program_store(
        &self,
        name: &str,
        program: Vec<u8>,
        comment: String,
    ) -> Result<pb::ProgramInfo, ClientError> {
        Self::program_arg(name)?;
        let write = pb::ProgramWrite {
            op: Some(pb::program_write::Op::Store(program)),
            comment,
        };
        self.program_write(name, "store", write).await
    }

    /// The gateway's `programs.max_inline` (from its admin document), else the default: the
    /// most a console takes in one upload.
    pub fn max_inline(&self) -> u64 {
        self.admin["config"]["programs"]["max_inline"]
            .as_u64()
            .unwrap_or(cellgate_core::config::ProgramsConfig::DEFAULT_MAX_INLINE)
    }

    /// Whether a store of `size` bytes as `name` would be taken (the name, the size, a lock,
    /// the quotas), before the bytes are sent: the program as it stands, or the refusal a
    /// store would get. Nothing is written.
    pub async fn program_check(
        &self,
        name: &str,
        size: u64,
    ) -> Result<pb::ProgramInfo, ClientError> {
        Self::program_arg(name)?;
        let write = pb::ProgramWrite {
            op: Some(pb::program_write::Op::Check(pb::program_write::Check {
                size,
            })),
            comment: String::new(),
        };
        self.program_write(name, "check a store of", write).await
    }

    /// Stores `from`'s revision (empty: its latest) as `name`'s next revision (a punched
    /// program adopted as a revision of the library's program).
    pub async fn program_adopt(
        &self,
        name: &str,
        from: &str,
        revision: &str,
        comment: String,
    ) -> Result<pb::ProgramInfo, ClientError> {
        Self::program_arg(name)?;
        Self::program_arg(from)?;
        let write = pb::ProgramWrite {
            op: Some(pb::program_write::Op::Adopt(pb::program_write::Adopt {
                from: from.to_string(),
                revision: revision.to_string(),
            })),
            comment,
        };
        self.program_write(name, "adopt into", write).await
    }

    /// Every kept revision of a program, newest first.
    pub async fn program_revisions(&self, name: &str) -> Result<pb::ProgramRevisions, ClientError> {
        Self::program_arg(name)?;
        let key = self.keys.program_revisions(name);
        self.get_one(&format!("revisions of {name}"), &key, None, self.timeout)
            .await
    }

    /// One revision's content.
    pub async fn program_revision(
        &self,
        name: &str,
        revision: &str,
    ) -> Result<Vec<u8>, ClientError> {
        Self::program_arg(name)?;
        chunk_arg("revision", revision)?;
        let key = self.keys.program_revision(name, revision);
        let what = format!("revision {revision} of {name}");
        let replies = self.get_raw(&what, &key, None, self.timeout).await?;
        match replies.into_iter().next() {
            Some(Ok((_, bytes, _))) => Ok(bytes),
            Some(Err((bytes, enc))) => Err(refusal(&what, &bytes, &enc)),
            None => Err(no_reply(&what, &key, self.timeout, self.timeout)),
        }
    }

    /// Two revisions compared (`a`, `b`: numbers or hashes; `None`: the defaults, the latest
    /// against the one before), ignoring `ignore` (`sequence,blanks,comments`).
    pub async fn program_diff(
        &self,
        name: &str,
        a: Option<&str>,
        b: Option<&str>,
        ignore: &[String],
    ) -> Result<pb::ProgramDiff, ClientError> {
        Self::program_arg(name)?;
        let mut params = Vec::new();
        if let Some(a) = a {
            params.push(("a".to_string(), a.to_string()));
        }
        if let Some(b) = b {
            params.push(("b".to_string(), b.to_string()));
        }
        if !ignore.is_empty() {
            params.push(("ignore".to_string(), ignore.join(",")));
        }
        let key = with_params(self.keys.program_diff(name), &params)?;
        self.get_one(&format!("diff of {name}"), &key, None, self.timeout)
            .await
    }

    /// Changes a revision's state (`revision` empty: the latest).
    pub async fn program_release(
        &self,
        name: &str,
        revision: &str,
        state: pb::RevisionState,
        comment: String,
    ) -> Result<pb::ProgramRevision, ClientError> {
        Self::program_arg(name)?;
        let key = self.keys.program_release(name);
        let release = pb::ProgramRelease {
            revision: revision.to_string(),
            state: state as i32,
            comment,
        };
        let payload = (release.encode_to_vec(), encoding::<pb::ProgramRelease>());
        self.get_one(
            &format!("release {name}"),
            &key,
            Some(payload),
            self.timeout,
        )
        .await
    }

    // ---- history ---------------------------------------------------------------------------

    /// One page of the history (`audit`: of the audit trail) with these selector parameters
    /// (`_time`, `machine`, `kind`, `tag`, `limit`, `after`).
    pub async fn history(
        &self,
        audit: bool,
        params: &[(String, String)],
    ) -> Result<pb::HistoryPage, ClientError> {
        let base = if audit {
            self.keys.audit()
        } else {
            self.keys.history()
        };
        let key = with_params(base, params)?;
        let what = if audit {
            "the audit trail"
        } else {
            "the history"
        };
        self.get_one(what, &key, None, self.timeout).await
    }

    /// Utilisation with these selector parameters (`_time`, `machine`, `bucket`).
    pub async fn utilisation(
        &self,
        params: &[(String, String)],
    ) -> Result<pb::Utilisation, ClientError> {
        let key = with_params(self.keys.utilisation(), params)?;
        self.get_one("utilisation", &key, None, self.timeout).await
    }

    /// Removes a program from the library; answers it as it was, once it is gone.
    pub async fn program_remove(&self, name: &str) -> Result<pb::ProgramInfo, ClientError> {
        Self::program_arg(name)?;
        let write = pb::ProgramWrite {
            op: Some(pb::program_write::Op::Remove(pb::program_write::Remove {})),
            comment: String::new(),
        };
        self.program_write(name, "remove", write).await
    }

    /// A confirmed library change: a get with a `ProgramWrite` on the program's write key.
    async fn program_write(
        &self,
        name: &str,
        op: &str,
        write: pb::ProgramWrite,
    ) -> Result<pb::ProgramInfo, ClientError> {
        let key = self.keys.program_write(name);
        let payload = (write.encode_to_vec(), encoding::<pb::ProgramWrite>());
        self.get_one(
            &format!("{op} program {name}"),
            &key,
            Some(payload),
            self.timeout,
        )
        .await
    }

    // ---- watch -----------------------------------------------------------------------------

    /// Subscribes to everything the cell publishes (`P/C/**`) and to its liveliness tokens.
    /// The tokens standing now come first (as `Gateway` / `Link` events with `up`).
    pub async fn watch(&self) -> Result<Watch, ClientError> {
        let all = self.keys.all();
        let data = self
            .session
            .declare_subscriber(all.as_str())
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("subscribe to {all}"),
                source,
            })?;
        let tokens = self
            .session
            .liveliness()
            .declare_subscriber(all.as_str())
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("subscribe to the liveliness tokens {all}"),
                source,
            })?;
        let mut watch = Watch {
            keys: self.keys.clone(),
            data,
            tokens,
            pending: VecDeque::new(),
        };
        // The standing tokens, asked for after subscribing so that no change is missed
        // (one may show twice).
        let replies = self
            .session
            .liveliness()
            .get(all.as_str())
            .timeout(self.timeout)
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("get the liveliness tokens {all}"),
                source,
            })?;
        let mut standing = Vec::new();
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result()
                && let Some(event) = watch.token_event(sample)
            {
                standing.push(event);
            }
        }
        // The gateway first, then the machines by name.
        standing.sort_by_key(|e| match e {
            WatchEvent::Link { machine, .. } => (1, machine.clone()),
            _ => (0, String::new()),
        });
        watch.pending.extend(standing);
        Ok(watch)
    }
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

/// Whether a job event is the last of its job.
pub fn is_end(event: &pb::JobEvent) -> bool {
    matches!(
        event.kind,
        Some(Kind::Completed(_) | Kind::Failed(_) | Kind::Cancelled(_))
    )
}

/// How a job ended.
#[derive(Debug, Clone, PartialEq)]
pub enum JobOutcome {
    Completed(pb::job_event::Completed),
    Failed(pb::job_event::Failed),
    Cancelled(pb::job_event::Cancelled),
}

impl JobOutcome {
    /// The outcome a job's last event tells; `None` for an event that is not the last.
    pub fn of(event: &pb::JobEvent) -> Option<JobOutcome> {
        match &event.kind {
            Some(Kind::Completed(c)) => Some(JobOutcome::Completed(*c)),
            Some(Kind::Failed(f)) => Some(JobOutcome::Failed(f.clone())),
            Some(Kind::Cancelled(c)) => Some(JobOutcome::Cancelled(c.clone())),
            _ => None,
        }
    }

    /// 0 when the program was delivered, 1 otherwise.
    pub fn exit_code(&self) -> u8 {
        match self {
            JobOutcome::Completed(_) => 0,
            JobOutcome::Failed(_) | JobOutcome::Cancelled(_) => 1,
        }
    }
}

/// The events of one job, as [`Client::submit`] or [`Client::follow`] subscribed to them.
pub struct JobFollower {
    session: Session,
    subscriber: Subscriber<FifoChannelHandler<Sample>>,
    keys: CellKeys,
    machine: String,
    job_id: String,
    ended: bool,
    timeout: Duration,
}

impl JobFollower {
    pub fn job_id(&self) -> &str {
        &self.job_id
    }

    pub fn machine(&self) -> &str {
        &self.machine
    }

    /// The job's next event; `None` once its last event (completed, failed, cancelled) was
    /// returned. When the job stays silent for [`SILENCE`], the gateway is asked for its
    /// latest event, so an end is seen even if its publication was lost.
    pub async fn next(&mut self) -> Result<Option<pb::JobEvent>, ClientError> {
        if self.ended {
            return Ok(None);
        }
        loop {
            match tokio::time::timeout(SILENCE, self.subscriber.recv_async()).await {
                Ok(Ok(sample)) => {
                    if let Some(event) = self.accept(&sample) {
                        self.ended = is_end(&event);
                        return Ok(Some(event));
                    }
                }
                Ok(Err(_)) => {
                    return Err(ClientError::Closed {
                        what: format!("following job {}", self.job_id),
                    });
                }
                Err(_) => match self.latest().await {
                    Ok(latest) if is_end(&latest) => {
                        self.ended = true;
                        return Ok(Some(latest));
                    }
                    Ok(_) => {}
                    // The question was only a check for a lost end: a gateway slow to answer
                    // it (or a reply lost on the way) is no reason to stop following a job
                    // whose events still come.
                    Err(e @ ClientError::NoAnswer { .. }) => {
                        tracing::debug!(error = %e, "the job's latest event did not come; following on");
                    }
                    Err(e) => return Err(e),
                },
            }
        }
    }

    /// Reads events until the job ends; returns the last one.
    pub async fn wait_end(&mut self) -> Result<pb::JobEvent, ClientError> {
        let mut last = None;
        while let Some(event) = self.next().await? {
            last = Some(event);
        }
        last.ok_or_else(|| ClientError::Closed {
            what: format!("following job {}", self.job_id),
        })
    }

    /// This job's event in a sample of `P/C/machine/M/job/*`, if it is one.
    fn accept(&self, sample: &Sample) -> Option<pb::JobEvent> {
        if sample.kind() != SampleKind::Put {
            return None; // a cancel request
        }
        match self.keys.parse(sample.key_expr().as_str()) {
            Some(CellKey::JobEvents { job, .. }) if job == self.job_id => {}
            _ => return None,
        }
        let event = decode::<pb::JobEvent>(
            "job event",
            sample.key_expr().as_str(),
            &sample.payload().to_bytes(),
            sample.encoding(),
        );
        match event {
            Ok(e) if e.job_id == self.job_id => Some(e),
            Ok(_) => None,
            Err(e) => {
                tracing::warn!(error = %e, "job event skipped");
                None
            }
        }
    }

    async fn latest(&self) -> Result<pb::JobEvent, ClientError> {
        let key = self.keys.job_events(&self.machine, &self.job_id);
        let what = format!("job {}", self.job_id);
        let replies = get_raw(&self.session, &what, &key, None, self.timeout, None).await?;
        decode_all::<pb::JobEvent>(&what, replies)?
            .into_iter()
            .map(|(_, e)| e)
            .find(|e| e.job_id == self.job_id)
            .ok_or(ClientError::NoAnswer {
                what,
                key,
                timeout: self.timeout,
            })
    }

    /// Undeclares the subscription.
    pub async fn close(self) {
        if let Err(e) = self.subscriber.undeclare().await {
            tracing::debug!(error = %e, "undeclaring the job subscriber");
        }
    }
}

/// One thing seen on the cell's keys.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum WatchEvent {
    Status(Box<pb::MachineStatus>),
    Job(pb::JobEvent),
    Alarm(pb::AlarmEvent),
    Di(pb::DiImage),
    /// A program the CNC punched out (and the remote request it carried, if any).
    Punched(Box<pb::PunchedProgram>),
    /// A `DoCommand` put by some client.
    DoCommand {
        machine: String,
        command: pb::DoCommand,
    },
    /// A delete on a job key: a cancel request.
    CancelRequested {
        machine: String,
        job_id: String,
    },
    /// A G05 stream ended.
    G05(pb::G05Status),
    /// A program put into the library.
    ProgramPut {
        name: String,
        size: u64,
    },
    /// A delete on a program: removal requested.
    ProgramDeleted {
        name: String,
    },
    /// A machine's liveliness token: its link came up (`up`) or went down.
    Link {
        machine: String,
        up: bool,
    },
    /// The gateway's liveliness token.
    Gateway {
        up: bool,
    },
    /// A PLC tag changed.
    Tag(pb::TagValue),
    /// A transfer: from the PLC (published by the gateway), or one a client put to it.
    Transfer(pb::PlcTransfer),
    /// A non-procedure message (modes 4–5): from the PLC, or one a client put to it.
    PlcMessage(pb::PlcMessage),
    /// A PLC station's liveliness token: it answers (`up`) or was marked down.
    PlcStation {
        plc: String,
        station: String,
        up: bool,
    },
    /// A sample on the cell's keys that is not what the contract puts there.
    Unexpected {
        key: String,
        detail: String,
    },
}

/// The cell's publications, as [`Client::watch`] subscribed to them.
pub struct Watch {
    keys: CellKeys,
    data: Subscriber<FifoChannelHandler<Sample>>,
    tokens: Subscriber<FifoChannelHandler<Sample>>,
    pending: VecDeque<WatchEvent>,
}

impl Watch {
    /// The next event; `None` when the session closed.
    pub async fn next(&mut self) -> Option<WatchEvent> {
        if let Some(e) = self.pending.pop_front() {
            return Some(e);
        }
        loop {
            let (sample, token) = tokio::select! {
                s = self.tokens.recv_async() => (s.ok()?, true),
                s = self.data.recv_async() => (s.ok()?, false),
            };
            let event = if token {
                self.token_event(&sample)
            } else {
                self.data_event(&sample)
            };
            if let Some(e) = event {
                return Some(e);
            }
        }
    }

    fn token_event(&self, sample: &Sample) -> Option<WatchEvent> {
        let up = sample.kind() == SampleKind::Put;
        let key = sample.key_expr().as_str();
        if let Some(crate::bus::keys::PlcKey::Station { plc, station }) = self.keys.parse_plc(key) {
            return Some(WatchEvent::PlcStation {
                plc: plc.to_string(),
                station: station.to_string(),
                up,
            });
        }
        match self.keys.parse(key) {
            Some(CellKey::Gateway) => Some(WatchEvent::Gateway { up }),
            Some(CellKey::Machine { machine }) => Some(WatchEvent::Link {
                machine: machine.to_string(),
                up,
            }),
            _ => None,
        }
    }

    fn data_event(&self, sample: &Sample) -> Option<WatchEvent> {
        let key = sample.key_expr().as_str();
        let bytes = sample.payload().to_bytes();
        let enc = sample.encoding();
        let put = sample.kind() == SampleKind::Put;
        if let Some(plc_key) = self.keys.parse_plc(key) {
            use crate::bus::keys::PlcKey;
            let schema = schema_of(enc);
            let event = match plc_key {
                PlcKey::Tag { .. } if put && schema.as_deref() == Some(pb::TagValue::SCHEMA) => {
                    decode(key, key, &bytes, enc).map(WatchEvent::Tag)
                }
                PlcKey::Transfer { .. }
                    if put && schema.as_deref() == Some(pb::PlcTransfer::SCHEMA) =>
                {
                    decode(key, key, &bytes, enc).map(WatchEvent::Transfer)
                }
                PlcKey::Message { .. }
                    if put && schema.as_deref() == Some(pb::PlcMessage::SCHEMA) =>
                {
                    decode(key, key, &bytes, enc).map(WatchEvent::PlcMessage)
                }
                // Status every few seconds, writes by other clients: not shown.
                _ => return None,
            };
            return Some(event.unwrap_or_else(|e| WatchEvent::Unexpected {
                key: key.to_string(),
                detail: e.to_string(),
            }));
        }
        let parsed = self.keys.parse(key)?;
        let event = match parsed {
            CellKey::Leaf { leaf, machine } if put => match leaf {
                MachineLeaf::Status => {
                    decode(key, key, &bytes, enc).map(|s| WatchEvent::Status(Box::new(s)))
                }
                MachineLeaf::Alarm => decode(key, key, &bytes, enc).map(WatchEvent::Alarm),
                MachineLeaf::Di => decode(key, key, &bytes, enc).map(WatchEvent::Di),
                MachineLeaf::Punch => {
                    decode(key, key, &bytes, enc).map(|p| WatchEvent::Punched(Box::new(p)))
                }
                MachineLeaf::Do => {
                    decode(key, key, &bytes, enc).map(|command| WatchEvent::DoCommand {
                        machine: machine.to_string(),
                        command,
                    })
                }
                // Job requests and G05 opens are gets, not puts.
                MachineLeaf::Job | MachineLeaf::Submit | MachineLeaf::G05 => return None,
            },
            // A stream's status comes ten times a second: only its end is shown.
            CellKey::G05 {
                part: crate::bus::keys::G05Part::Status,
                ..
            } if put => match decode::<pb::G05Status>(key, key, &bytes, enc) {
                Ok(s)
                    if s.state() == pb::G05State::Completed
                        || s.state() == pb::G05State::Failed =>
                {
                    Ok(WatchEvent::G05(s))
                }
                Ok(_) => return None,
                Err(e) => Err(e),
            },
            CellKey::JobEvents { .. } if put => decode(key, key, &bytes, enc).map(WatchEvent::Job),
            CellKey::JobEvents { machine, job } => Ok(WatchEvent::CancelRequested {
                machine: machine.to_string(),
                job_id: job.to_string(),
            }),
            CellKey::ProgramWrite { name } if put => Ok(WatchEvent::ProgramPut {
                name: name.to_string(),
                size: bytes.len() as u64,
            }),
            CellKey::ProgramWrite { name } => Ok(WatchEvent::ProgramDeleted {
                name: name.to_string(),
            }),
            _ => return None,
        };
        Some(event.unwrap_or_else(|e| WatchEvent::Unexpected {
            key: key.to_string(),
            detail: e.to_string(),
        }))
    }

    /// Undeclares both subscriptions.
    pub async fn close(self) {
        let _ = self.data.undeclare().await;
        let _ = self.tokens.undeclare().await;
    }
}

/// The machine a job id names: ids are `M-<run>-<n>` (`mill-1-tpfqpi-3`), and a machine's
/// name may itself hold `-`. `None` for a text that is not such an id.
pub fn machine_of_job(job_id: &str) -> Option<&str> {
    let mut parts = job_id.rsplitn(3, '-');
    let n = parts.next()?;
    let run = parts.next()?;
    let machine = parts.next()?;
    let numbered = !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit());
    let stamped = !run.is_empty() && run.bytes().all(|b| b.is_ascii_alphanumeric());
    (numbered && stamped && !machine.is_empty()).then_some(machine)
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
