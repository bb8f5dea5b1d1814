//! The running gateway: one per cell.
//!
//! [`run`] opens the Zenoh session, announces the cell (its liveliness token `P/C/gateway`
//! and its `P/C/@admin` key, [`crate::bus::admin`]), starts the cell's links, serves the
//! routes, and returns once the `shutdown` future completes, after undeclaring everything
//! and closing the session. Taking shutdown as a future (rather than catching signals here)
//! lets the binary stop it on SIGINT/SIGTERM and tests stop it at will. While it runs it takes
//! reloads of its cell file ([`reload`]): from `P/C/@admin/reload` and from a
//! [`ReloadHandle`] (the binary's SIGHUP).

pub mod reload;

pub use crate::bus::route_reload::ReloadAnswer;
pub use reload::{CellSource, ReloadHandle, Reloads, check_cell_file};

use std::future::Future;
use std::sync::Arc;

use tokio_util::sync::CancellationToken;
use zenoh::Session;

use crate::bus::admin::AdminRoute;
pub use crate::bus::admin::{VERSION, admin_document};
use crate::bus::keys::CellKeys;
use crate::bus::route_reload::{ReloadAsk, ReloadRoute};
use crate::bus::{self, BusError};
use crate::cell::Cell;
use crate::history::{History, HistoryError};
use cellgate_core::config::CellConfig;

/// What a running gateway tells whoever started it, once it serves.
#[derive(Debug, Clone, Default)]
pub struct Ready {
    /// The console's URL, when it serves one.
    pub console: Option<String>,
    /// The MTConnect agent's URL, when it serves one.
    pub mtconnect: Option<String>,
    /// The OPC UA server's URL, when it serves one.
    pub opcua: Option<String>,
}

/// Why the gateway stopped with an error.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GatewayError {
    #[error(transparent)]
    Bus(#[from] BusError),
    /// A machine link could not be started.
    #[error(transparent)]
    Cell(#[from] crate::cell::CellError),
    /// The history store could not be opened.
    #[error(transparent)]
    History(#[from] HistoryError),
    /// The console (`[console]`) could not be served.
    #[error(transparent)]
    Console(#[from] crate::console::ConsoleError),
    /// The OPC UA server (`[opcua]`) could not be served.
    #[error(transparent)]
    Opcua(#[from] crate::opcua::OpcuaError),
    /// The MTConnect agent (`[mtconnect]`) could not be served.
    #[error(transparent)]
    Mtconnect(#[from] crate::mtconnect::MtconnectError),
    /// The session did not close cleanly.
    #[error("closing the zenoh session: {0}")]
    Close(#[source] zenoh::Error),
}

/// How a gateway runs beside its cell file.
#[derive(Debug, Default)]
pub struct RunOptions {
    /// Told once the gateway serves its cell (its routes answer, it is announced).
    pub ready: Option<tokio::sync::oneshot::Sender<Ready>>,
    /// Where a reload reads the cell from; none: the gateway has no file to read again (the
    /// embedded default cell), and a reload is refused, saying so.
    pub source: Option<CellSource>,
    /// Reloads asked for through a [`ReloadHandle`] (SIGHUP); the bus route's come too.
    pub reloads: Option<Reloads>,
}

/// Runs the gateway for `config` until `shutdown` completes, then stops cleanly.
///
/// Must run on a multi-thread Tokio runtime (zenoh's requirement).
pub async fn run(
    config: CellConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<(), GatewayError> {
    run_ready(config, shutdown, None).await
}

/// [`run`], sending on `ready` once the gateway serves its cell (its routes answer, it is
/// announced): what `cellgate run` waits for before it prints what the cell offers.
pub async fn run_ready(
    config: CellConfig,
    shutdown: impl Future<Output = ()>,
    ready: Option<tokio::sync::oneshot::Sender<Ready>>,
) -> Result<(), GatewayError> {
    let options = RunOptions {
        ready,
        ..RunOptions::default()
    };
    run_with(config, shutdown, options).await
}

/// [`run`] with [`RunOptions`]: the cell file a reload reads, the reloads asked for.
pub async fn run_with(
    config: CellConfig,
    shutdown: impl Future<Output = ()>,
    options: RunOptions,
) -> Result<(), GatewayError> {
    // The uptime `cellgate status` shows counts from here.
    crate::bus::admin::started_unix_ms();
    let session = bus::open_cell(&config).await?;
    let security = &config.security;
    if security.enforces_roles() {
        tracing::info!(
            roles = security.roles.len(),
            tls = security.tls.is_some(),
            users = security.users_file.is_some(),
            "access control on: what no role allows is denied"
        );
    } else if security.tls.is_none() && security.users_file.is_none() {
        tracing::info!("no [security]: any session that reaches the gateway may do anything");
    }
    // Whatever happens from here on, the session is closed before returning.
    let served = serve(&config, &session, shutdown, options).await;
    let closed = session.close().await.map_err(GatewayError::Close);
    tracing::info!(cell = %config.cell, "cellgate stopped");
    served.and(closed)
}

async fn serve(
    config: &CellConfig,
    session: &Session,
    shutdown: impl Future<Output = ()>,
    options: RunOptions,
) -> Result<(), GatewayError> {
    let keys = CellKeys::new(&config.bus.prefix, &config.cell).map_err(BusError::from)?;

    // The history first: its writer outlives the routes, so that what they record at the end
    // (the last job events, the stop) is written.
    let history_stop = CancellationToken::new();
    let (history, history_writer) = if config.history.enabled {
        let dir = config.history.dir_in(&config.programs.dir);
        let (h, w) = History::open(&dir, &config.history, history_stop.clone()).await?;
        tracing::info!(store = %dir.display(), "history on");
        (h, Some(w))
    } else {
        (History::disabled(), None)
    };
    let served = serve_with(config, session, shutdown, &keys, history, options).await;
    history_stop.cancel();
    if let Some(w) = history_writer {
        let _ = w.await;
    }
    served
}

/// Says the cell is running, and where it listens.
fn log_running(config: &CellConfig, session: &Session, keys: &CellKeys) {
    // Zenoh's own list of bound locators is an unstable API; the configured endpoints are
    // what the session bound, since opening fails otherwise.
    let listening = if config.bus.listen.is_empty() {
        "no endpoint".to_string()
    } else {
        config.bus.listen.join(", ")
    };
    tracing::info!(
        cell = %config.cell,
        zid = %session.zid(),
        liveliness = %keys.gateway(),
        admin = %keys.admin(),
        "cellgate {} running, listening on {}",
        config.cell,
        listening,
    );
}

/// The cell's own MTConnect agent, where `[mtconnect]` asks for one: a client of the routes
/// that only reads.
async fn start_mtconnect(
    config: &CellConfig,
    session: &Session,
    stop: &CancellationToken,
) -> Result<Option<crate::mtconnect::Served>, GatewayError> {
    let Some(m) = &config.mtconnect else {
        return Ok(None);
    };
    let settings = crate::mtconnect::MtconnectSettings {
        config: m.clone(),
        prefix: config.bus.prefix.clone(),
        only: Some(config.cell.clone()),
        own: Some(cellgate_core::mtconnect::CellDesc::from_config(config)),
        sender: format!("cellgate {}", config.cell),
    };
    let served = crate::mtconnect::serve(session.clone(), settings, stop.clone()).await?;
    tracing::info!(url = %served.url, shdr = ?served.shdr, "MTConnect agent at {}", served.url);
    Ok(Some(served))
}

/// The cell's own OPC UA server, where `[opcua]` asks for one: a client of the routes that
/// only reads.
async fn start_opcua(
    config: &CellConfig,
    session: &Session,
    stop: &CancellationToken,
) -> Result<Option<crate::opcua::Served>, GatewayError> {
    let Some(o) = &config.opcua else {
        return Ok(None);
    };
    let settings = crate::opcua::OpcuaSettings {
        config: o.clone(),
        prefix: config.bus.prefix.clone(),
        only: Some(config.cell.clone()),
        own: Some(cellgate_core::mtconnect::CellDesc::from_config(config)),
        security: config.security.clone(),
        default_pki: config.programs.journal_dir().join("pki"),
    };
    let served = crate::opcua::serve(session.clone(), settings, stop.clone()).await?;
    tracing::info!(url = %served.url, "OPC UA server at {}", served.url);
    Ok(Some(served))
}

/// The cell's console, where `[console]` asks for one, linking to the agent at `mtconnect`.
async fn start_console(
    config: &CellConfig,
    session: &Session,
    mtconnect: Option<String>,
    stop: &CancellationToken,
) -> Result<Option<crate::console::Served>, GatewayError> {
    let Some(c) = &config.console else {
        return Ok(None);
    };
    let settings = crate::console::ConsoleSettings {
        console: c.clone(),
        prefix: config.bus.prefix.clone(),
        cell: Some(config.cell.clone()),
        security: config.security.clone(),
        mtconnect,
    };
    let served = crate::console::serve(session.clone(), settings, None, stop.clone()).await?;
    tracing::info!(url = %served.url, "console at {}", served.url);
    Ok(Some(served))
}

async fn serve_with(
    config: &CellConfig,
    session: &Session,
    shutdown: impl Future<Output = ()>,
    keys: &CellKeys,
    history: History,
    options: RunOptions,
) -> Result<(), GatewayError> {
    let RunOptions {
        ready: serving,
        source,
        reloads,
    } = options;
    let reloads = reloads.unwrap_or_else(|| Reloads::new().1);
    // The links run until the routes have stopped, so that every job's end is reported.
    let links_stop = CancellationToken::new();
    let mut cell = Some(Cell::start(config, &links_stop).await?);
    let (machines, plcs) = match &cell {
        Some(c) => (c.machine_links(), c.plc_links()),
        None => (Vec::new(), Vec::new()),
    };
    let routes_stop = CancellationToken::new();
    let (machines_tx, machines_rx) = tokio::sync::oneshot::channel();
    let (plcs_tx, plcs_rx) = tokio::sync::oneshot::channel();
    // Either half failing (a journal that cannot be opened, a route zenoh refuses) ends both:
    // the gateway stops at once with the error rather than serving half a cell.
    let routes = async {
        tokio::try_join!(
            bus::serve_live(
                session,
                config,
                machines,
                routes_stop.clone(),
                history.clone(),
                move |r| {
                    let _ = machines_tx.send(r);
                },
            ),
            bus::serve_plcs_live(
                session,
                config,
                plcs,
                routes_stop.clone(),
                history.clone(),
                move |r| {
                    let _ = plcs_tx.send(r);
                },
            ),
        )
        .map(|_| ())
    };
    let served_routes = async { (machines_rx.await, plcs_rx.await) };
    tokio::pin!(routes);
    tokio::pin!(shutdown);
    tokio::pin!(served_routes);

    // Whatever is started below is stopped after the block, in order, however it ends.
    let mut admin: Option<Arc<AdminRoute>> = None;
    let (mtconnect_stop, console_stop) = (CancellationToken::new(), CancellationToken::new());
    let mut mtconnect = None;
    let mut console: Option<crate::console::Served> = None;
    let opcua_stop = CancellationToken::new();
    let mut opcua: Option<crate::opcua::Served> = None;
    let reload_stop = CancellationToken::new();
    let mut reload_task = None;
    let mut routes_result = None;
    let outcome: Result<(), GatewayError> = 'serve: {
        // The cell is announced (admin key, liveliness token) once its routes answer: a client
        // that finds the gateway finds every route.
        let (machine_routes, plc_routes) = tokio::select! {
            (Ok(m), Ok(p)) = &mut served_routes => (m, p),
            result = &mut routes => {
                routes_result = Some(result);
                break 'serve Ok(());
            }
            () = &mut shutdown => {
                tracing::info!(cell = %config.cell, "shutdown requested while starting");
                break 'serve Ok(());
            }
        };
        let a = match AdminRoute::declare(session, keys, config).await {
            Ok(a) => Arc::new(a.with_history(history.clone())),
            Err(e) => break 'serve Err(e.into()),
        };
        admin = Some(Arc::clone(&a));

        log_running(config, session, keys);
        // The MTConnect agent and the console: clients of the routes just announced, on this
        // session.
        match start_mtconnect(config, session, &mtconnect_stop).await {
            Ok(served) => mtconnect = served,
            Err(e) => break 'serve Err(e),
        }
        let mtconnect_url = mtconnect.as_ref().map(|m| m.url.clone());
        match start_console(config, session, mtconnect_url, &console_stop).await {
            Ok(served) => console = served,
            Err(e) => break 'serve Err(e),
        }

        match start_opcua(config, session, &opcua_stop).await {
            Ok(served) => opcua = served,
            Err(e) => break 'serve Err(e),
        }

        match ReloadRoute::declare(session, keys, reloads.sender()).await {
            Ok(route) => reload_task = Some(tokio::spawn(route.run(reload_stop.clone()))),
            Err(e) => break 'serve Err(e.into()),
        }

        if let Some(serving) = serving {
            let _ = serving.send(Ready {
                console: console.as_ref().map(|c| c.url.clone()),
                mtconnect: mtconnect.as_ref().map(|m| m.url.clone()),
                opcua: opcua.as_ref().map(|o| o.url.clone()),
            });
        }

        let Some(links) = cell.take() else {
            break 'serve Ok(());
        };
        let (drained_tx, mut drained) = tokio::sync::mpsc::unbounded_channel();
        let running = reload::Running {
            cell: links,
            machines: machine_routes,
            plcs: plc_routes,
            history: history.clone(),
            console: console.as_ref().map(|c| Arc::clone(&c.console)),
            opcua_auth: opcua.as_ref().and_then(|o| o.auth.clone()),
            admin: Arc::clone(&a),
            session: session.clone(),
            keys: keys.clone(),
        };
        let source = source.unwrap_or_else(CellSource::embedded);
        let mut reloader = reload::Reloader::new(source, config.clone(), running, drained_tx);
        let mut asks = reloads.rx;
        let admin_stop = CancellationToken::new();
        let admin_run = a.run(&admin_stop);
        tokio::pin!(admin_run);
        let mut reading: Option<(ReloadAsk, reload::Reading)> = None;
        loop {
            tokio::select! {
                () = &mut shutdown => {
                    tracing::info!(cell = %config.cell, "shutdown requested");
                    break;
                }
                () = &mut admin_run => break,
                result = &mut routes => {
                    // The routes only end early on an error: the gateway cannot serve its cell.
                    if let Err(e) = &result {
                        tracing::error!(error = %e, "the bus routes stopped");
                    }
                    routes_result = Some(result);
                    break;
                }
                // The file is read beside everything else here (the admin key, the shutdown):
                // no file, a FIFO or a share that hangs, holds the gateway.
                Some(ask) = asks.recv(), if reading.is_none() => {
                    reading = Some((ask, Box::pin(reloader.read())));
                }
                Some(read) = async {
                    match reading.as_mut() {
                        Some((_, read)) => Some(read.await),
                        None => None,
                    }
                } => {
                    if let Some((ask, _)) = reading.take() {
                        reloader.reload(ask, read).await;
                    }
                }
                Some((name, op)) = drained.recv() => reloader.on_drained(name, op).await,
            }
        }
        cell = Some(reloader.into_cell());
        Ok(())
    };

    opcua_stop.cancel();
    if let Some(o) = opcua {
        o.join().await;
    }
    mtconnect_stop.cancel();
    if let Some(m) = mtconnect {
        m.join().await;
    }
    console_stop.cancel();
    if let Some(c) = console {
        c.join().await;
    }
    reload_stop.cancel();
    if let Some(t) = reload_task {
        let _ = t.await;
    }
    routes_stop.cancel();
    let routes_result = match routes_result {
        Some(r) => r,
        None => routes.await,
    };
    links_stop.cancel();
    if let Some(c) = cell {
        c.join().await;
    }
    // Undeclare explicitly so peers see the token go at once rather than on session close.
    if let Some(a) = admin.and_then(|a| Arc::try_unwrap(a).ok()) {
        a.undeclare().await;
    }
    outcome.and(routes_result.map_err(GatewayError::from))
}
