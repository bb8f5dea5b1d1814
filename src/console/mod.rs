//! The web console (docs/console.md): pages for the floor and the office, served over HTTP(S)
//! by axum, built only from the public bus contract.
//!
//! The console is a client of the bus like the command line: it asks the cells' gateways
//! with gets on their keys ([`crate::client::Client`]), subscribes to what they publish
//! ([`live`]), and acts as each browser user: their roles decide what the console lets them
//! do ([`auth`]), and every request it sends carries their name, so that the cell's audit
//! trail records them. The gateway serves it for its own cell (`[console]`), on its own
//! session; `cellgate console` serves every cell behind a router, on a session of its own:
//! the same code.
//!
//! - [`listen`]: HTTP or HTTPS, the peer's client certificate;
//! - [`auth`]: logins, sessions, CSRF, permissions; [`throttle`]: password guesses cost time;
//! - [`extract`]: what a request brings, checked before its handler and before its body is
//!   read (the caller and their permission, the origin, the names, the JSON body);
//! - [`api`]: the JSON API;
//! - [`live`]: publications coalesced for the pages' event streams;
//! - [`assets`]: the pages, compiled into the binary.

pub mod api;
pub mod assets;
pub mod auth;
pub mod extract;
mod headers;
pub mod listen;
pub mod live;
pub mod throttle;

use std::collections::BTreeMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::Router;
use axum::routing::{get, post};
use prost::Message as _;
use tokio::sync::{Mutex, Semaphore, mpsc};
use tokio_util::sync::CancellationToken;
use zenoh::Session;

use crate::client::Client;
pub use crate::client::site::SiteError;
use crate::door::Door;
use crate::telemetry::prometheus::Exposition;
use cellgate_core::config::{ConsoleConfig, Permission, SecurityConfig};
use cellgate_core::history::refusals::{self, Refusals};
use cellgate_core::pb;

use self::auth::Auth;
use self::listen::{ListenError, PlainListener, TlsListener};
use self::live::Live;

/// How long the console waits for a gateway's answer.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(10);
/// How often the list of cells is asked again at most.
const DISCOVERY_EVERY: Duration = Duration::from_secs(5);
/// Program uploads sent to a gateway at once: each is held whole while it is sent (one bus
/// message); the others wait spooled to files, not in memory.
const UPLOADS_AT_ONCE: usize = 2;
/// Body limit of every request but a program upload (which takes `programs.max_inline`).
const BODY_LIMIT: usize = 16 * 1024;
/// Audit notes waiting to be sent, at most; beyond, they are dropped and logged.
const NOTES_WAITING: usize = 1024;

/// What the console serves and how.
#[derive(Debug, Clone)]
pub struct ConsoleSettings {
    pub console: ConsoleConfig,
    /// The bus prefix `P` of the cells.
    pub prefix: String,
    /// The one cell served (the gateway's own); `None`: every cell that answers (site view).
    pub cell: Option<String>,
    /// Users, roles and the certificates for HTTPS.
    pub security: SecurityConfig,
    /// The MTConnect agent's URL, when one serves the same cells: the pages link to it.
    pub mtconnect: Option<String>,
}

/// The console's state, shared by every request.
pub struct Console {
    session: Session,
    prefix: String,
    only: Option<String>,
    auth: Auth,
    live: Live,
    /// Cells found, with their admin documents, and when they were last asked for.
    cells: Mutex<(Instant, BTreeMap<String, serde_json::Value>)>,
    clients: Mutex<BTreeMap<String, Client>>,
    https: bool,
    /// The host names it answers to.
    hosts: Arc<extract::Hosts>,
    metrics: Option<Exposition>,
    /// Cancelled when the console stops: the pages' event streams end with it.
    stop: CancellationToken,
    /// Program uploads being sent.
    uploads: Semaphore,
    /// Refusals of the current minute, gathered before they go to the cells' audit trails.
    refusals: std::sync::Mutex<Refusals>,
    /// Audit notes to send: (cell, empty for every cell; the record).
    notes: mpsc::Sender<refusals::Out>,
    /// The MTConnect agent's URL, if any.
    mtconnect: Option<String>,
}

impl Console {
    /// The cells that answer, asked again at most every [`DISCOVERY_EVERY`].
    async fn refresh(&self) -> BTreeMap<String, serde_json::Value> {
        let mut cells = self.cells.lock().await;
        if cells.0.elapsed() < DISCOVERY_EVERY && !cells.1.is_empty() {
            return cells.1.clone();
        }
        let found = match Client::discover(&self.session, &self.prefix, REQUEST_TIMEOUT).await {
            Ok(f) => f,
            Err(e) => {
                tracing::warn!(error = %e, "console: looking for cells failed");
                Vec::new()
            }
        };
        let found: BTreeMap<String, serde_json::Value> = found
            .into_iter()
            .filter(|(c, _)| self.only.as_ref().is_none_or(|o| o == c))
            .collect();
        *cells = (Instant::now(), found.clone());
        found
    }

    /// The client of `cell`, if its gateway answers.
    async fn cell(&self, cell: &str) -> Option<Client> {
        if let Some(c) = self.clients.lock().await.get(cell) {
            return Some(c.clone());
        }
        let admin = self.refresh().await.get(cell).cloned()?;
        let client = Client::attach(
            self.session.clone(),
            &self.prefix,
            cell,
            admin,
            REQUEST_TIMEOUT,
        )
        .ok()?;
        self.clients
            .lock()
            .await
            .insert(cell.to_string(), client.clone());
        Some(client)
    }

    /// Adds a request the console refused `user` to the cell's audit trail (as a note: the
    /// gateway never saw the request itself), gathered with the others of its kind and minute.
    /// Best effort: a cell that keeps no history, or a console whose identity may not add
    /// notes, leaves it in the console's log only.
    fn note_refusal(
        &self,
        cell: &str,
        user: &str,
        action: &str,
        p: Permission,
        target: &str,
        why: &str,
    ) {
        let record = pb::AuditRecord {
            action: action.to_string(),
            target: target.to_string(),
            detail: format!("refused by the console: needs {}", p.name()),
            origin: Some(pb::RequestOrigin {
                user: user.to_string(),
                via: "console".to_string(),
            }),
            code: pb::ErrorCode::NotPermitted as i32,
            error: why.to_string(),
            ..Default::default()
        };
        self.note(cell, record);
    }

    /// A failed login, in the audit trail of every cell the console serves, gathered per name
    /// and minute.
    fn note_login_failure(&self, name: &str, addr: IpAddr, why: &str) {
        let record = pb::AuditRecord {
            action: "console.login".to_string(),
            target: name.to_string(),
            detail: format!("from {addr}"),
            origin: Some(pb::RequestOrigin {
                user: name.to_string(),
                via: "console".to_string(),
            }),
            code: pb::ErrorCode::NotPermitted as i32,
            error: why.to_string(),
            ..Default::default()
        };
        self.note("", record);
    }

    fn note(&self, cell: &str, record: pb::AuditRecord) {
        let now = pb::now_ms();
        let out = self
            .refusals
            .lock()
            .map(|mut r| r.refuse(cell, record, now))
            .unwrap_or_default();
        self.send_notes(out);
    }

    fn send_notes(&self, out: Vec<refusals::Out>) {
        for note in out {
            if self.notes.try_send(note).is_err() {
                tracing::warn!(
                    "console: too many audit notes waiting; one dropped (it is in this log)"
                );
            }
        }
    }

    /// Sends one note to `cell` (empty: every cell served).
    async fn send_note(&self, cell: &str, record: &pb::AuditRecord) {
        let cells: Vec<String> = if cell.is_empty() {
            self.refresh().await.into_keys().collect()
        } else {
            vec![cell.to_string()]
        };
        for cell in cells {
            let Some(client) = self.cell(&cell).await else {
                continue;
            };
            let key = client.keys().audit_note();
            let sent = self
                .session
                .get(key.as_str())
                .payload(record.encode_to_vec())
                .timeout(REQUEST_TIMEOUT)
                .await;
            if let Ok(replies) = sent {
                while replies.recv_async().await.is_ok() {}
            }
        }
    }
}

/// Sends the audit notes, and the summaries of each minute's refusals once it is over.
async fn notes_task(
    console: Arc<Console>,
    mut rx: mpsc::Receiver<refusals::Out>,
    stop: CancellationToken,
) {
    let mut flush = tokio::time::interval(Duration::from_secs(5));
    loop {
        tokio::select! {
            () = stop.cancelled() => break,
            got = rx.recv() => match got {
                Some((cell, record)) => console.send_note(&cell, &record).await,
                None => break,
            },
            _ = flush.tick() => {
                let now = pb::now_ms();
                let out = console.refusals.lock().map(|mut r| r.flush(now)).unwrap_or_default();
                console.send_notes(out);
            }
        }
    }
}

impl Console {
    /// Takes a reloaded cell file's `[console]` session settings and `[security]` users and
    /// roles (the users file is read again): the sessions of users who are gone or whose
    /// permissions changed end, with their event streams. Answers how many ended.
    pub fn reload(&self, console: &ConsoleConfig, security: &SecurityConfig) -> usize {
        self.auth.set_limits(
            Duration::from_secs(u64::from(console.session_idle_minutes) * 60),
            Duration::from_secs(u64::from(console.session_hours) * 3600),
            console.sessions_per_user as usize,
        );
        self.auth.set_security(security)
    }
}

/// Why the console stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConsoleError {
    #[error(transparent)]
    Listen(#[from] ListenError),
    #[error("console: subscribing to the cells' publications: {0}")]
    Subscribe(#[source] zenoh::Error),
    #[error("console: serving HTTP: {0}")]
    Serve(#[source] std::io::Error),
}

/// The console's routes: each handler's extractors say what it needs of its caller
/// ([`extract::Caller`]), checked before any body is read; bodies are at most
/// `BODY_LIMIT` but a program upload's, which streams within `programs.max_inline`.
pub fn router(console: Arc<Console>) -> Router {
    use api::*;
    let cell = "/api/v1/cells/{cell}";
    let https = console.https;
    Router::new()
        .route("/", get(assets::index))
        .route("/assets/{file}", get(assets::file))
        .route("/favicon.ico", get(assets::favicon))
        .route("/health", get(health))
        .route("/metrics", get(metrics))
        .route("/api/v1/me", get(me))
        .route("/api/v1/login", post(login))
        .route("/api/v1/logout", post(logout))
        .route("/api/v1/cells", get(cells))
        .route(&format!("{cell}/overview"), get(overview))
        .route(&format!("{cell}/events"), get(events))
        .route(&format!("{cell}/machines/{{m}}"), get(machine))
        .route(&format!("{cell}/machines/{{m}}/submit"), post(submit))
        .route(
            &format!("{cell}/machines/{{m}}/jobs/{{id}}/cancel"),
            post(cancel),
        )
        .route(&format!("{cell}/machines/{{m}}/do"), post(set_do))
        .route(&format!("{cell}/programs"), get(programs))
        .route(
            &format!("{cell}/programs/{{name}}"),
            get(program)
                .put(program_put)
                .layer(axum::extract::DefaultBodyLimit::disable())
                .delete(program_delete),
        )
        .route(
            &format!("{cell}/programs/{{name}}/revisions"),
            get(revisions),
        )
        .route(
            &format!("{cell}/programs/{{name}}/rev/{{rev}}"),
            get(revision),
        )
        .route(&format!("{cell}/programs/{{name}}/diff"), get(diff))
        .route(&format!("{cell}/programs/{{name}}/release"), post(release))
        .route(&format!("{cell}/programs/{{name}}/adopt"), post(adopt))
        .route(&format!("{cell}/plcs/{{p}}"), get(plc))
        .route(&format!("{cell}/plcs/{{p}}/tags/{{tag}}"), post(tag_set))
        .route(
            &format!("{cell}/plcs/{{p}}/mem/{{station}}/{{module}}/{{address}}"),
            get(mem),
        )
        .route(&format!("{cell}/history"), get(history))
        .route(&format!("{cell}/audit"), get(audit))
        .route(&format!("{cell}/utilisation"), get(utilisation))
        .fallback(extract::not_found)
        .method_not_allowed_fallback(extract::method_not_allowed)
        .layer(axum::extract::DefaultBodyLimit::max(BODY_LIMIT))
        .layer(axum::middleware::from_fn_with_state(
            Arc::clone(&console.hosts),
            extract::host,
        ))
        .layer(axum::middleware::from_fn_with_state(
            https,
            headers::headers,
        ))
        .with_state(console)
}

/// How long the console lets requests under way finish when it stops.
const STOP_GRACE: Duration = Duration::from_secs(5);

/// A console listening, and the URL it is reached at.
pub struct Served {
    pub url: String,
    pub task: tokio::task::JoinHandle<()>,
    /// The console's state, which a reload updates ([`Console::reload`]).
    pub console: Arc<Console>,
}

impl Served {
    /// Waits for the console to stop (its stop token cancelled), at most `STOP_GRACE`
    /// for the requests under way; then it is stopped whatever they do.
    pub async fn join(mut self) {
        if tokio::time::timeout(STOP_GRACE, &mut self.task)
            .await
            .is_err()
        {
            tracing::warn!("console: requests still under way when it stopped; cut short");
            self.task.abort();
        }
    }
}

impl crate::client::site::SiteServer for Served {
    fn url(&self) -> &str {
        &self.url
    }

    fn join(self) -> impl std::future::Future<Output = ()> + Send {
        Served::join(self)
    }
}

/// Serves the console on `session` until `stop`. Binds at once (so a port taken is an error
/// now), then serves in a task.
pub async fn serve(
    session: Session,
    settings: ConsoleSettings,
    metrics: Option<Exposition>,
    stop: CancellationToken,
) -> Result<Served, ConsoleError> {
    let c = &settings.console;
    let https = settings.security.tls.is_some();
    let tcp = listen::bind(&c.listen).await?;
    let local: SocketAddr = tcp.local_addr().map_err(ConsoleError::Serve)?;
    let live = Live::start(
        &session,
        &settings.prefix,
        settings.cell.as_deref(),
        stop.clone(),
    )
    .await
    .map_err(ConsoleError::Subscribe)?;
    let (notes_tx, notes_rx) = mpsc::channel(NOTES_WAITING);
    let console = Arc::new(Console {
        session,
        prefix: settings.prefix.clone(),
        only: settings.cell.clone(),
        auth: Auth::new(
            &settings.security,
            Duration::from_secs(u64::from(c.session_idle_minutes) * 60),
            Duration::from_secs(u64::from(c.session_hours) * 3600),
            c.sessions_per_user as usize,
        ),
        live,
        cells: Mutex::new((Instant::now() - DISCOVERY_EVERY * 2, BTreeMap::new())),
        clients: Mutex::new(BTreeMap::new()),
        https,
        hosts: Arc::new(extract::Hosts::new(https, local.port(), &c.host_names)),
        metrics,
        stop: stop.clone(),
        uploads: Semaphore::new(UPLOADS_AT_ONCE),
        refusals: std::sync::Mutex::new(Refusals::default()),
        notes: notes_tx,
        mtconnect: settings.mtconnect.clone(),
    });
    tokio::spawn(notes_task(Arc::clone(&console), notes_rx, stop.clone()));
    let handle = Arc::clone(&console);
    let app = router(console);
    let url = format!("{}://{}/", if https { "https" } else { "http" }, local);
    let cap = crate::door::connection_cap();
    let task = if let Some(tls) = &settings.security.tls {
        // A plain 503 means nothing to a TLS client: one over the cap is only closed.
        let door = Door::new("console", tcp, cap, b"");
        let listener =
            TlsListener::new(door, listen::acceptor(tls)?).map_err(ConsoleError::Serve)?;
        tokio::spawn(crate::door::http::serve(listener, app, stop))
    } else {
        let door = Door::new("console", tcp, cap, crate::door::HTTP_FULL);
        tokio::spawn(crate::door::http::serve(PlainListener(door), app, stop))
    };
    Ok(Served {
        url,
        task,
        console: handle,
    })
}

/// `cellgate console`: the site view, every cell behind the endpoint.
#[derive(Debug, Clone, clap::Args)]
pub struct SiteArgs {
    #[command(flatten)]
    pub connect: crate::client::cli::ConnectArgs,
    /// Where the console listens, ADDRESS:PORT (default: console.listen of --config, else
    /// 127.0.0.1:7480).
    #[arg(long, value_name = "ADDR")]
    pub listen: Option<String>,
    /// A cell file whose `[security]` (users file, roles, TLS certificate for HTTPS) and
    /// `[console]` settings the console takes; without one, it serves loopback only and every
    /// user may do what the console's own bus identity may.
    #[arg(short = 'c', long, value_name = "FILE")]
    pub config: Option<std::path::PathBuf>,
}

/// Runs the site console until `shutdown`: a session of its own to the endpoint, every cell
/// under the prefix.
pub async fn site(
    args: &SiteArgs,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), SiteError> {
    let (mut console, security) = match &args.config {
        None => (ConsoleConfig::default(), SecurityConfig::default()),
        Some(path) => {
            let cell = cellgate_core::config::CellConfig::load(path)
                .map_err(|e| SiteError::Config(format!("{}: {e}", path.display())))?;
            (cell.console.unwrap_or_default(), cell.security)
        }
    };
    if let Some(listen) = &args.listen {
        console.listen = listen.clone();
    }
    let secured = security.tls.is_some() || security.users_file.is_some();
    if !secured && !console.is_loopback() && !console.allow_remote {
        return Err(SiteError::Config(format!(
            "--listen {}: beyond this host without [security] anyone who reaches it could do \
             anything; listen on 127.0.0.1, or give --config a cell file with [security] \
             (or console.allow_remote = true)",
            console.listen
        )));
    }
    let start = |session, options: crate::client::ConnectOptions, stop| {
        let settings = ConsoleSettings {
            console,
            prefix: options.prefix.clone(),
            cell: options.cell.clone(),
            security,
            mtconnect: None,
        };
        serve(session, settings, None, stop)
    };
    crate::client::site::serve(&args.connect, "console", start, shutdown).await
}
