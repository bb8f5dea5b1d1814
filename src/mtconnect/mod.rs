//! The MTConnect agent (docs/mtconnect.md): the cell's machines and PLCs as MTConnect 2.5
//! devices, over the standard's HTTP interface and as an SHDR adapter, built only from the
//! public bus contract like the console. The gateway serves it for its own cell
//! (`[mtconnect]`), on its own session; `cellgate mtconnect` serves every cell behind a
//! router, on a session of its own: the same code. It only reads.
//!
//! - the cells are followed by [`crate::client::follow`], the console's and the OPC UA
//!   server's way too: the [`Hub`] is its [`Follower`];
//! - [`http`]: `/probe`, `/current`, `/sample` (streamed as multipart), `/assets`, errors;
//! - [`shdr`]: the adapter's TCP port.
//!
//! The model, the mapping, the buffer and the documents are the core's
//! ([`cellgate_core::mtconnect`]): this room only does I/O.

pub mod http;
pub mod shdr;

use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use zenoh::Session;

use crate::client::follow::{self, Follower};
use crate::door::Door;
use cellgate_core::config::MtconnectConfig;
use cellgate_core::mtconnect::{Agent, CellDesc, Update};

/// The agent behind a lock, and a signal that says its buffer moved on.
pub struct Hub {
    agent: Mutex<Agent>,
    /// The buffer's `nextSequence`, sent whenever it moves.
    next: watch::Sender<u64>,
}

impl Hub {
    /// A hub for `agent`.
    pub fn new(agent: Agent) -> Arc<Hub> {
        let next = agent.buffer().next();
        Arc::new(Hub {
            agent: Mutex::new(agent),
            next: watch::Sender::new(next),
        })
    }

    /// The agent. A panic while it was held cannot leave it half-written in a way that
    /// matters more than stopping every request would: take it anyway.
    pub fn lock(&self) -> MutexGuard<'_, Agent> {
        self.agent.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Tells the streams that the buffer moved on.
    pub fn changed(&self) {
        let next = self.lock().buffer().next();
        self.next.send_replace(next);
    }

    /// A receiver of the buffer's `nextSequence`.
    pub fn watch(&self) -> watch::Receiver<u64> {
        self.next.subscribe()
    }
}

impl Follower for Hub {
    fn known(&self, cell: &str) -> Option<CellDesc> {
        self.lock().desc(cell).cloned()
    }

    fn describe(&self, desc: &CellDesc) {
        self.lock().change_cell(desc, now_us());
        self.changed();
    }

    fn take(&self, cell: &str, updates: Vec<Update>) {
        let now = now_us();
        let mut agent = self.lock();
        if !agent.has_cell(cell) {
            return;
        }
        let mut n = 0;
        for u in updates {
            n += agent.update(cell, u, now);
        }
        drop(agent);
        if n > 0 {
            self.changed();
        }
    }
}

/// Now, in microseconds since the Unix epoch.
pub fn now_us() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

/// What the agent serves and how.
#[derive(Debug, Clone)]
pub struct MtconnectSettings {
    pub config: MtconnectConfig,
    /// The bus prefix `P` of the cells.
    pub prefix: String,
    /// The one cell served; `None`: every cell that answers (site view).
    pub only: Option<String>,
    /// The gateway's own cell, described by its cell file (its gateway is not asked).
    pub own: Option<CellDesc>,
    /// Names the agent in every document's header (`sender`).
    pub sender: String,
}

/// Why the agent stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MtconnectError {
    #[error("mtconnect: cannot listen on {addr}: {source}")]
    Bind {
        addr: String,
        #[source]
        source: std::io::Error,
    },
    #[error("mtconnect: subscribing to the cells' publications: {0}")]
    Subscribe(#[source] zenoh::Error),
    #[error("mtconnect: serving HTTP: {0}")]
    Serve(#[source] std::io::Error),
}

/// How long the agent lets requests under way finish when it stops.
const STOP_GRACE: Duration = Duration::from_secs(5);

/// An agent listening, and the URL it is reached at.
pub struct Served {
    pub url: String,
    /// The SHDR adapter's address, if it serves one.
    pub shdr: Option<SocketAddr>,
    pub hub: Arc<Hub>,
    task: tokio::task::JoinHandle<()>,
}

impl Served {
    /// Waits for the agent to stop (its stop token cancelled), at most `STOP_GRACE`.
    pub async fn join(mut self) {
        if tokio::time::timeout(STOP_GRACE, &mut self.task)
            .await
            .is_err()
        {
            tracing::warn!("mtconnect: requests still under way when it stopped; cut short");
            self.task.abort();
        }
    }
}

async fn bind(addr: &str) -> Result<tokio::net::TcpListener, MtconnectError> {
    tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|source| MtconnectError::Bind {
            addr: addr.to_string(),
            source,
        })
}

/// Serves the agent on `session` until `stop`. Binds at once (so a port taken is an error
/// now), then serves in tasks.
pub async fn serve(
    session: Session,
    settings: MtconnectSettings,
    stop: CancellationToken,
) -> Result<Served, MtconnectError> {
    let tcp = bind(&settings.config.listen).await?;
    let local = tcp.local_addr().map_err(MtconnectError::Serve)?;
    let shdr = match &settings.config.shdr_listen {
        Some(addr) => Some(bind(addr).await?),
        None => None,
    };
    let now = now_us();
    // The instance id changes with every start: a client whose sequence numbers belong to
    // another instance starts over (Part 1, "instanceId").
    let agent = Agent::new(
        &settings.sender,
        now / 1_000_000,
        settings.config.buffer_size as usize,
        now,
    );
    let hub = Hub::new(agent);
    follow::start(
        session,
        settings.prefix.clone(),
        settings.only.clone(),
        settings.own.clone(),
        Arc::clone(&hub) as Arc<dyn Follower>,
        stop.clone(),
    )
    .await
    .map_err(MtconnectError::Subscribe)?;
    let shdr_addr = match shdr {
        Some(listener) => {
            let addr = listener.local_addr().map_err(MtconnectError::Serve)?;
            // SHDR has no answer for "busy": one over the cap is only closed.
            let door = Door::new("shdr", listener, shdr::MAX_CLIENTS, b"");
            tokio::spawn(shdr::serve(door, Arc::clone(&hub), stop.clone()));
            Some(addr)
        }
        None => None,
    };
    let app = http::router(Arc::clone(&hub), stop.clone());
    let url = format!("http://{local}/");
    let door = Door::new(
        "mtconnect",
        tcp,
        crate::door::connection_cap(),
        crate::door::HTTP_FULL,
    );
    let task = tokio::spawn(crate::door::http::serve(door, app, stop));
    Ok(Served {
        url,
        shdr: shdr_addr,
        hub,
        task,
    })
}

/// `cellgate mtconnect`: the site agent, every cell behind the endpoint.
#[derive(Debug, Clone, clap::Args)]
pub struct SiteArgs {
    #[command(flatten)]
    pub connect: crate::client::cli::ConnectArgs,
    /// Where the agent listens, ADDRESS:PORT.
    #[arg(long, value_name = "ADDR", default_value = MtconnectConfig::DEFAULT_LISTEN)]
    pub listen: String,
    /// Where an SHDR adapter listens, ADDRESS:PORT; none by default.
    #[arg(long, value_name = "ADDR")]
    pub shdr: Option<String>,
    /// Observations kept (bufferSize), 1024 to 1048576.
    #[arg(long, value_name = "N", default_value_t = MtconnectConfig::DEFAULT_BUFFER_SIZE)]
    pub buffer_size: u32,
}

pub use crate::client::site::SiteError;

impl crate::client::site::SiteServer for Served {
    fn url(&self) -> &str {
        &self.url
    }

    fn join(self) -> impl std::future::Future<Output = ()> + Send {
        Served::join(self)
    }
}

/// Runs the site agent until `shutdown`: a session of its own to the endpoint, every cell
/// under the prefix (or `--cell`'s).
pub async fn site(
    args: &SiteArgs,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), SiteError> {
    let config = MtconnectConfig {
        listen: args.listen.clone(),
        buffer_size: args.buffer_size,
        shdr_listen: args.shdr.clone(),
    };
    let checked = cellgate_core::config::CellConfig {
        mtconnect: Some(config.clone()),
        ..cellgate_core::config::CellConfig::embedded_default()
    };
    if let Err(e) = checked.validate() {
        let mine: Vec<String> =
            e.0.iter()
                .map(ToString::to_string)
                .filter(|m| m.contains("mtconnect."))
                .collect();
        if !mine.is_empty() {
            return Err(SiteError::Config(mine.join("; ")));
        }
    }
    for w in config.warnings() {
        tracing::warn!("{w}");
    }
    let start = |session, options: crate::client::ConnectOptions, stop| async move {
        let settings = MtconnectSettings {
            config,
            prefix: options.prefix.clone(),
            // A site agent asks each gateway what its cell has; with --cell, only that cell.
            only: options.cell.clone(),
            own: None,
            sender: format!("cellgate site agent ({})", options.endpoint),
        };
        let served = serve(session, settings, stop).await?;
        if let Some(a) = served.shdr {
            eprintln!("SHDR adapter at {a}");
        }
        Ok::<_, MtconnectError>(served)
    };
    crate::client::site::serve(&args.connect, "mtconnect", start, shutdown).await
}
