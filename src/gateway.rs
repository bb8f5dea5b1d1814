//! The running gateway: one per cell.
//!
//! [`run`] opens the Zenoh session, announces the cell (its liveliness token `P/C/gateway`
//! and its `P/C/@admin` key, [`crate::bus::admin`]), starts the cell's links, serves the
//! routes, and returns once the `shutdown` future completes, after undeclaring everything
//! and closing the session. Taking shutdown as a future (rather than catching signals here)
//! lets the binary stop it on SIGINT/SIGTERM and tests stop it at will.

use std::future::Future;

use tokio_util::sync::CancellationToken;
use zenoh::Session;

use crate::bus::admin::AdminRoute;
pub use crate::bus::admin::{VERSION, admin_document};
use crate::bus::keys::CellKeys;
use crate::bus::{self, BusError};
use crate::cell::Cell;
use crate::config::CellConfig;

/// Why the gateway stopped with an error.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GatewayError {
    #[error(transparent)]
    Bus(#[from] BusError),
    /// A machine link could not be started.
    #[error(transparent)]
    Cell(#[from] crate::cell::CellError),
    /// The session did not close cleanly.
    #[error("closing the zenoh session: {0}")]
    Close(#[source] zenoh::Error),
}

/// Runs the gateway for `config` until `shutdown` completes, then stops cleanly.
///
/// Must run on a multi-thread Tokio runtime (zenoh's requirement).
pub async fn run(
    config: CellConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<(), GatewayError> {
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
    let served = serve(&config, &session, shutdown).await;
    let closed = session.close().await.map_err(GatewayError::Close);
    tracing::info!(cell = %config.cell, "cellgate stopped");
    served.and(closed)
}

async fn serve(
    config: &CellConfig,
    session: &Session,
    shutdown: impl Future<Output = ()>,
) -> Result<(), GatewayError> {
    let keys = CellKeys::new(&config.bus.prefix, &config.cell).map_err(BusError::from)?;

    // The links run until the routes have stopped, so that every job's end is reported.
    let links_stop = CancellationToken::new();
    let cell = Cell::start(config, &links_stop).await?;
    let machines = cell.machine_links();
    let routes_stop = CancellationToken::new();
    let (ready_tx, ready) = tokio::sync::oneshot::channel();
    let plcs = cell.plc_links();
    let routes = async {
        let (machines, plcs) = tokio::join!(
            bus::serve_announced(
                session,
                config,
                machines,
                routes_stop.clone(),
                Some(ready_tx),
            ),
            bus::serve_plcs(session, config, plcs, routes_stop.clone()),
        );
        machines.and(plcs)
    };
    tokio::pin!(routes);
    let mut routes_result = None;

    // The cell is announced (admin key, liveliness token) once its routes answer: a client
    // that finds the gateway finds every route.
    let admin = tokio::select! {
        Ok(()) = ready => AdminRoute::declare(session, &keys, config).await,
        result = &mut routes => {
            links_stop.cancel();
            cell.join().await;
            return result.map_err(GatewayError::from);
        }
    };
    let admin = match admin {
        Ok(a) => a,
        Err(e) => {
            routes_stop.cancel();
            let _ = routes.await;
            links_stop.cancel();
            cell.join().await;
            return Err(e.into());
        }
    };

    // Zenoh's own list of bound locators is an unstable API; the configured endpoints
    // are what the session bound, since opening fails otherwise.
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

    let admin_stop = CancellationToken::new();
    tokio::pin!(shutdown);
    tokio::select! {
        () = &mut shutdown => tracing::info!(cell = %config.cell, "shutdown requested"),
        () = admin.run(&admin_stop) => {}
        result = &mut routes => {
            // The routes only end early on an error: the gateway cannot serve its cell.
            if let Err(e) = &result {
                tracing::error!(error = %e, "the bus routes stopped");
            }
            routes_result = Some(result);
        }
    }

    routes_stop.cancel();
    let routes_result = match routes_result {
        Some(r) => r,
        None => routes.await,
    };
    links_stop.cancel();
    cell.join().await;
    // Undeclare explicitly so peers see the token go at once rather than on session close.
    admin.undeclare().await;
    routes_result.map_err(GatewayError::from)
}
