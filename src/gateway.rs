//! The running gateway: one per cell.
//!
//! [`run`] opens the Zenoh session, announces the cell with a liveliness token, serves
//! the admin key, and returns once the `shutdown` future completes, after undeclaring
//! everything and closing the session. Taking shutdown as a future (rather than catching
//! signals here) lets the binary stop it on SIGINT/SIGTERM and tests stop it at will.
//!
//! Keys (with `P` = `bus.prefix`, `C` = `cell`):
//! - `P/C/gateway` — liveliness token, present while the gateway runs;
//! - `P/C/@admin` — queryable answering a JSON document with the version and the running
//!   configuration. `@admin` is a verbatim chunk: wildcards such as `P/C/**` do not match
//!   it, so subscribers to a cell's data never see admin traffic, and it stays apart from
//!   zenoh's own `@/<zid>/...` admin space.

use std::future::Future;

use tokio_util::sync::CancellationToken;
use zenoh::Session;

use crate::bus::{self, BusError};
use crate::cell::Cell;
use crate::config::CellConfig;

/// The crate version, as reported by `--version` and the admin key.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// Why the gateway stopped with an error.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GatewayError {
    #[error(transparent)]
    Bus(#[from] BusError),
    /// A key built from `bus.prefix` and `cell` was refused, or zenoh failed to declare it.
    #[error("cannot declare the {what} on {key:?}: {source}")]
    Declare {
        what: &'static str,
        key: String,
        #[source]
        source: zenoh::Error,
    },
    /// A machine link could not be started.
    #[error(transparent)]
    Cell(#[from] crate::cell::CellError),
    /// The session did not close cleanly.
    #[error("closing the zenoh session: {0}")]
    Close(#[source] zenoh::Error),
}

/// The liveliness token key of a cell's gateway: `P/C/gateway`.
pub fn liveliness_key(config: &CellConfig) -> String {
    format!("{}/{}/gateway", config.bus.prefix, config.cell)
}

/// The admin key of a cell's gateway: `P/C/@admin`.
pub fn admin_key(config: &CellConfig) -> String {
    format!("{}/{}/@admin", config.bus.prefix, config.cell)
}

/// The JSON document the admin key answers with.
pub fn admin_document(config: &CellConfig, zid: &str) -> serde_json::Value {
    serde_json::json!({
        "name": "cellgate",
        "version": VERSION,
        "cell": config.cell,
        "zid": zid,
        "config": config,
    })
}

/// Runs the gateway for `config` until `shutdown` completes, then stops cleanly.
///
/// Must run on a multi-thread Tokio runtime (zenoh's requirement).
pub async fn run(
    config: CellConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<(), GatewayError> {
    let session = bus::open(&config.bus).await?;
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
    let token_key = liveliness_key(config);
    let token = session
        .liveliness()
        .declare_token(token_key.as_str())
        .await
        .map_err(|source| GatewayError::Declare {
            what: "liveliness token",
            key: token_key.clone(),
            source,
        })?;
    let admin = admin_key(config);
    let queryable = session
        .declare_queryable(admin.as_str())
        .await
        .map_err(|source| GatewayError::Declare {
            what: "admin queryable",
            key: admin.clone(),
            source,
        })?;
    let zid = session.zid().to_string();
    let admin_reply = admin_document(config, &zid).to_string();

    // The links run until the routes have stopped, so that every job's end is reported.
    let links_stop = CancellationToken::new();
    let cell = Cell::start(config, &links_stop).await?;
    let machines = cell.machine_links();
    let routes_stop = CancellationToken::new();
    let routes = bus::serve(session, config, machines, routes_stop.clone());
    tokio::pin!(routes);
    let mut routes_result = None;

    // Zenoh's own list of bound locators is an unstable API; the configured endpoints
    // are what the session bound, since opening fails otherwise.
    let listening = if config.bus.listen.is_empty() {
        "no endpoint".to_string()
    } else {
        config.bus.listen.join(", ")
    };
    tracing::info!(
        cell = %config.cell,
        %zid,
        liveliness = %token_key,
        admin = %admin,
        "cellgate {} running, listening on {}",
        config.cell,
        listening,
    );

    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            () = &mut shutdown => {
                tracing::info!(cell = %config.cell, "shutdown requested");
                break;
            }
            query = queryable.recv_async() => match query {
                Ok(query) => {
                    if let Err(e) = query.reply(admin.as_str(), admin_reply.as_str()).await {
                        tracing::warn!(selector = %query.selector(), error = %e, "admin reply failed");
                    }
                }
                // The session was closed under us: nothing more will arrive.
                Err(_) => break,
            },
            result = &mut routes, if routes_result.is_none() => {
                // The routes only end early on an error: the gateway cannot serve its cell.
                if let Err(e) = &result {
                    tracing::error!(error = %e, "the bus routes stopped");
                }
                routes_result = Some(result);
                break;
            }
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
    let undeclared_admin = queryable.undeclare().await;
    let undeclared_token = token.undeclare().await;
    for (what, result) in [
        ("admin queryable", undeclared_admin),
        ("liveliness token", undeclared_token),
    ] {
        if let Err(e) = result {
            tracing::warn!(error = %e, "undeclaring the {what} failed");
        }
    }
    routes_result.map_err(GatewayError::from)
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    fn free_port() -> u16 {
        std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port()
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn announces_the_cell_answers_admin_and_stops_on_shutdown() {
        let port = free_port();
        let mut config = CellConfig::embedded_default();
        config.bus.listen = vec![format!("tcp/127.0.0.1:{port}")];
        config.bus.connect = Vec::new();
        let token_key = liveliness_key(&config);
        let admin = admin_key(&config);
        let cell = config.cell.clone();

        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let gateway = tokio::spawn(run(config, async {
            let _ = stopped.await;
        }));

        let client_cfg = bus::BusConfig {
            mode: bus::BusMode::Client,
            listen: Vec::new(),
            connect: vec![format!("tcp/127.0.0.1:{port}")],
            ..bus::BusConfig::default()
        };
        // The gateway may still be starting: retry opening the client for a while.
        let mut client = None;
        for _ in 0..100 {
            match bus::open(&client_cfg).await {
                Ok(s) => {
                    client = Some(s);
                    break;
                }
                Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
        let client = client.expect("the gateway never accepted a connection");

        // The token shows the gateway is up (declarations propagate asynchronously).
        let mut alive = false;
        for _ in 0..100 {
            let replies = client.liveliness().get(token_key.as_str()).await.unwrap();
            if replies.recv_async().await.is_ok() {
                alive = true;
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(alive, "no liveliness token on {token_key}");

        let replies = client.get(admin.as_str()).await.unwrap();
        let reply = replies.recv_async().await.expect("no admin reply");
        let sample = reply.result().expect("admin replied with an error");
        let text = sample.payload().try_to_string().unwrap().into_owned();
        let doc: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(doc["version"], VERSION);
        assert_eq!(doc["cell"], cell.as_str());
        assert_eq!(doc["config"]["cell"], cell.as_str());

        stop.send(()).unwrap();
        let result = tokio::time::timeout(Duration::from_secs(10), gateway)
            .await
            .expect("the gateway did not stop within 10 s")
            .unwrap();
        result.unwrap();

        // Once stopped, the token is gone.
        let replies = client.liveliness().get(token_key.as_str()).await.unwrap();
        assert!(
            replies.recv_async().await.is_err(),
            "token still alive after shutdown"
        );
        client.close().await.unwrap();
    }
}
