//! The Zenoh side of the gateway: the cell's machines, jobs and program library as keys,
//! queryables, publishers and liveliness tokens, with protobuf payloads.
//!
//! One file per concern, as the zenoh bridges do it:
//! - [`session`]: opening the session from `[bus]` (loopback, multicast scouting off by default)
//!   and `[security]` (TLS, user names);
//! - [`acl`]: the cell file's roles as zenoh access-control rules for the cell's keys;
//! - [`keys`]: every key expression of the cell, built and parsed in one place;
//! - [`payload`]: the protobuf messages and their encodings, and the link's data as messages;
//! - `context`: what every route shares, the typed request errors, the reply helpers;
//! - `routes`: the table of every queryable and subscriber served (key, what arrives there,
//!   pool, permission, handler), declared and served from there, and undeclared when a
//!   route stops (a write's row declares its get and its put at once, and `write` gives both
//!   one path: the put's encoding checked, the audit recorded once, the get answered or the
//!   put's refusal logged); `published`: the table of every publication (key, message, QoS, the
//!   permissions that may subscribe): together the bus contract, which [`acl`] takes its
//!   keys from and docs/bus.md is checked against;
//! - one module per kind of route, with its handlers and publishers: `route_status`,
//!   `route_job`, `route_io` (DI/DO), `route_punch`, `route_program` (library),
//!   `route_history`, `route_misdirected`, `route_g05` (G05 streams: batches in order on
//!   their route's loop, a status publisher per open stream), `route_plc` (PLC memory, transfers, status), `route_tag` (PLC tags),
//!   `route_sim` (the controls of simulated machines);
//! - `machine`: a machine's view (its status) and its publishers; `machine_task`: the task
//!   that publishes what the link and the job manager report through them; `served`: the
//!   machines and PLCs served, which a reload changes while the routes run
//!   ([`MachineRoutes`], [`PlcRoutes`]);
//! - [`admin`]: the gateway's own token and `@admin` key.
//!
//! One queryable or subscriber per route serves every machine (`P/C/machine/*/status`, …): a
//! request for a machine the cell does not have still reaches the gateway, which answers
//! `ERROR_CODE_UNKNOWN_MACHINE` instead of leaving the client to time out. Each route runs in
//! its own task, and requests that may wait run off it within a bound
//! ([`context::MAX_WAITING_REQUESTS`]), so one slow querier stalls no other request.
//!
//! QoS: job requests, DO commands and program transfers are queries or puts the client
//! sends (a query is `Block` by default, and its replies follow it); what the gateway
//! publishes goes with the QoS of its row in `published`: job events, alarms and punched
//! programs reliable with `Block`, status and DI telemetry with `Drop`, since the next value
//! supersedes a lost one.

pub mod acl;
pub mod admin;
mod audit;
pub mod context;
mod error;
pub mod keys;
mod machine;
mod machine_task;
pub mod payload;
mod published;
mod record;
mod route_folder;
mod route_g05;
mod route_history;
mod route_io;
mod route_job;
pub mod route_misdirected;
mod route_plc;
mod route_program;
mod route_punch;
pub mod route_reload;
mod route_sim;
mod route_status;
mod route_tag;
mod routes;
mod served;
pub mod session;
mod write;

pub use error::BusError;
pub use route_job::{FETCH_TIMEOUT, RECENT_JOBS};
pub use route_plc::{PlcLink, STATUS_EVERY as PLC_STATUS_EVERY};
pub use served::{MachineLink, MachineRoutes, PlcRoutes};
pub use session::{open, open_cell};

pub use cellgate_core::config::{BusConfig, BusMode};

use std::sync::Arc;

use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use zenoh::Session;

use self::audit::Auditor;
use self::context::{Live, RouteContext};
use self::keys::CellKeys;
use self::route_g05::G05Context;
use crate::history::History;
use crate::jobs::journal::Journal;
use crate::library::ProgramLibrary;
use cellgate_core::config::CellConfig;

/// Serves the cell's machines and program library on `session` until `shutdown` is
/// cancelled, then undeclares everything: routes first, then each machine's job manager
/// (jobs still waiting are reported cancelled, the active one failed), then each machine's
/// publishers and liveliness token. The links themselves are left running: they belong to
/// the caller.
///
/// Each link is subscribed to before this function first awaits, so call it as soon as the
/// links are spawned. Must run on a multi-thread Tokio runtime (zenoh's requirement).
pub async fn serve(
    session: &Session,
    config: &CellConfig,
    machines: Vec<MachineLink>,
    shutdown: CancellationToken,
) -> Result<(), BusError> {
    serve_announced(session, config, machines, shutdown, None).await
}

/// [`serve`], sending on `ready` once every route is declared: announce the cell (its admin
/// key, its liveliness token) only then, or a client that found it may ask a route that is
/// not there yet and get no answer at all.
pub async fn serve_announced(
    session: &Session,
    config: &CellConfig,
    machines: Vec<MachineLink>,
    shutdown: CancellationToken,
    ready: Option<tokio::sync::oneshot::Sender<()>>,
) -> Result<(), BusError> {
    serve_recorded(
        session,
        config,
        machines,
        shutdown,
        ready,
        History::disabled(),
    )
    .await
}

/// [`serve_announced`], recording the cell's history and audit trail in `history`.
pub async fn serve_recorded(
    session: &Session,
    config: &CellConfig,
    machines: Vec<MachineLink>,
    shutdown: CancellationToken,
    ready: Option<tokio::sync::oneshot::Sender<()>>,
    history: History,
) -> Result<(), BusError> {
    serve_live(session, config, machines, shutdown, history, |_| {
        if let Some(ready) = ready {
            let _ = ready.send(());
        }
    })
    .await
}

/// [`serve_recorded`], handing `ready` the [`MachineRoutes`] once every route is declared:
/// what a reload adds, holds and removes machines through while the routes run.
pub async fn serve_live(
    session: &Session,
    config: &CellConfig,
    machines: Vec<MachineLink>,
    shutdown: CancellationToken,
    history: History,
    ready: impl FnOnce(MachineRoutes),
) -> Result<(), BusError> {
    let keys = Arc::new(CellKeys::new(&config.bus.prefix, &config.cell)?);
    let library = ProgramLibrary::new(&config.programs.dir, config.programs.max_size)
        .with_quota(crate::library::Quota {
            bytes: config.programs.quota_bytes,
            files: config.programs.quota_files,
        })
        .with_retention(crate::library::Retention {
            revisions: config.programs.keep_revisions,
            days: config.programs.keep_revision_days,
        })
        .with_owned(config.owned_files());
    // Off the runtime's threads: opening reads and checks the whole file.
    let (dir, damaged) = (
        config.programs.journal_dir(),
        config.programs.damaged_journal,
    );
    let (journal, restored) =
        tokio::task::spawn_blocking(move || Journal::open_and_restore(&dir, damaged))
            .await
            .map_err(|e| BusError::Internal(e.to_string()))??;
    let jobs_stop = shutdown.child_token();
    let routes_stop = shutdown.child_token();
    let ctx = RouteContext::new(
        session.clone(),
        Arc::clone(&keys),
        Live::default(),
        library.clone(),
        config.programs.max_inline.min(config.programs.max_size),
    )
    .with_fetch_prefixes(&config.programs.fetch_prefixes)
    .with_names(context::CellNames::of(config))
    .with_history(history, Auditor::new(&config.security));
    let served_machines =
        MachineRoutes::new(ctx.clone(), journal, config, jobs_stop, routes_stop.clone());

    let mut folder_tasks = JoinSet::new();
    let mut route_tasks = JoinSet::new();
    let served = async {
        // The machines first: their job managers subscribe to their links at once.
        served_machines.start(machines, restored.jobs).await?;
        // A folder that cannot be opened (a share not mounted yet) does not stop the cell:
        // its watcher says so and takes it in once it can; the library answers with the
        // error meanwhile (its index opens on first use).
        if let Err(e) = library.create_dir().await {
            tracing::error!(
                dir = %library.dir().display(), error = %e,
                "the program library's folder cannot be opened: library requests fail until it can"
            );
        }
        folder_tasks = route_folder::spawn(&ctx, config, &routes_stop);
        let routes = routes::declare_all(routes::cell(&keys), &ctx).await?;
        let g05_ctx = G05Context::new(ctx.clone(), routes_stop.clone());
        let g05 = routes::g05(&keys).declare(&g05_ctx).await?;
        // Only a cell with simulated machines has their controls.
        if served_machines.any_simulated() {
            served_machines.declare_sim().await?;
        }
        route_tasks.spawn(g05.run(g05_ctx, routes_stop.clone()));
        for route in routes {
            route_tasks.spawn(route.run(ctx.clone(), routes_stop.clone()));
        }
        tracing::info!(root = %keys.root(), machines = ctx.machines.now().len(), "cell routes declared");
        ready(served_machines.clone());
        // A route ends early only when the session closed under it.
        tokio::select! {
            () = shutdown.cancelled() => {}
            _ = route_tasks.join_next() => {}
        }
        Ok(())
    }
    .await;

    // Whatever happened, stop in order: the routes (their queryables go with them), then the
    // job managers report their last events, then the machine tasks publish them and withdraw.
    routes_stop.cancel();
    while route_tasks.join_next().await.is_some() {}
    while folder_tasks.join_next().await.is_some() {}
    served_machines.stop_all().await;
    served
}

/// Serves the cell's PLC links ([`PlcLink`]: memory, transfers, status, station liveliness,
/// tags) on `session` until `shutdown` is cancelled, then undeclares everything. The links
/// are left running: they belong to the caller. Must run on a multi-thread Tokio runtime.
pub async fn serve_plcs(
    session: &Session,
    config: &CellConfig,
    plcs: Vec<PlcLink>,
    shutdown: CancellationToken,
) -> Result<(), BusError> {
    serve_plcs_recorded(session, config, plcs, shutdown, History::disabled()).await
}

/// [`serve_plcs`], recording stations, tag values and writes in `history`.
pub async fn serve_plcs_recorded(
    session: &Session,
    config: &CellConfig,
    plcs: Vec<PlcLink>,
    shutdown: CancellationToken,
    history: History,
) -> Result<(), BusError> {
    serve_plcs_live(session, config, plcs, shutdown, history, |_| {}).await
}

/// [`serve_plcs_recorded`], handing `ready` the [`PlcRoutes`] once the routes are declared:
/// what a reload adds, removes and retags PLCs through.
pub async fn serve_plcs_live(
    session: &Session,
    config: &CellConfig,
    plcs: Vec<PlcLink>,
    shutdown: CancellationToken,
    history: History,
    ready: impl FnOnce(PlcRoutes),
) -> Result<(), BusError> {
    let keys = Arc::new(CellKeys::new(&config.bus.prefix, &config.cell)?);
    // The PLC routes never touch the library (its index opens on first use only).
    let library = ProgramLibrary::new(&config.programs.dir, config.programs.max_size);
    let route = RouteContext::new(
        session.clone(),
        Arc::clone(&keys),
        Live::default(),
        library,
        config.programs.max_inline.min(config.programs.max_size),
    )
    .with_history(history, Auditor::new(&config.security));
    // Its own token: routes that cannot be declared stop the publishers started before.
    let stop = shutdown.child_token();
    let served = PlcRoutes::new(route, stop.clone());
    for link in plcs {
        served.add(link);
    }
    let ctx = served.context().clone();
    let routes = match routes::declare_all(routes::plc(&keys), &ctx).await {
        Ok(routes) => routes,
        Err(e) => {
            stop.cancel();
            served.join_all().await;
            return Err(e);
        }
    };
    let mut tasks = JoinSet::new();
    for route in routes {
        tasks.spawn(route.run(ctx.clone(), stop.clone()));
    }
    tracing::info!(root = %keys.root(), plcs = ctx.plcs.now().len(), "PLC routes declared");
    ready(served.clone());
    while tasks.join_next().await.is_some() {}
    served.join_all().await;
    Ok(())
}
