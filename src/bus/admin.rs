//! The gateway itself on the bus: its liveliness token `P/C/gateway`, present while it runs,
//! and `P/C/@admin`, a queryable answering a JSON document with the version and the running
//! configuration. `@admin` is a verbatim chunk: wildcards such as `P/C/**` do not match it,
//! so subscribers to a cell's data never see admin traffic, and it stays apart from zenoh's
//! own `@/<zid>/...` admin space.

use tokio_util::sync::CancellationToken;
use zenoh::Session;
use zenoh::handlers::FifoChannelHandler;
use zenoh::liveliness::LivelinessToken;
use zenoh::query::{Query, Queryable};

use super::BusError;
use super::keys::CellKeys;
use cellgate_core::config::CellConfig;

/// The crate version, as reported by `--version` and the admin key.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// The running configuration as `@admin` shows it: credentials left out.
fn redacted(config: &CellConfig) -> CellConfig {
    let mut c = config.clone();
    c.telemetry = c.telemetry.redacted();
    c
}

/// The JSON document the admin key answers with.
pub fn admin_document(config: &CellConfig, zid: &str) -> serde_json::Value {
    serde_json::json!({
        "name": "cellgate",
        "version": VERSION,
        "cell": config.cell,
        "zid": zid,
        "started_unix_ms": started_unix_ms(),
        "config": redacted(config),
    })
}

/// When this process's gateway started, milliseconds since the Unix epoch: fixed by the
/// first call ([`crate::gateway::run`] makes it as it starts).
pub fn started_unix_ms() -> u64 {
    static STARTED: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *STARTED.get_or_init(cellgate_core::pb::now_ms)
}

/// The gateway's token and admin queryable. Undeclared when dropped (or explicitly, with
/// [`AdminRoute::undeclare`], so that peers see the token go at once).
pub struct AdminRoute {
    token: LivelinessToken,
    queryable: Queryable<FifoChannelHandler<Query>>,
    key: String,
    document: serde_json::Value,
    /// The cell's history, whose health the document shows.
    history: crate::history::History,
}

impl AdminRoute {
    pub async fn declare(
        session: &Session,
        keys: &CellKeys,
        config: &CellConfig,
    ) -> Result<Self, BusError> {
        let token_key = keys.gateway();
        let token = session
            .liveliness()
            .declare_token(token_key.as_str())
            .await
            .map_err(|source| BusError::Declare {
                what: "liveliness token",
                key: token_key,
                source,
            })?;
        let key = keys.admin();
        let queryable = session
            .declare_queryable(key.as_str())
            .await
            .map_err(|source| BusError::Declare {
                what: "admin queryable",
                key: key.clone(),
                source,
            })?;
        let document = admin_document(config, &session.zid().to_string());
        Ok(AdminRoute {
            token,
            queryable,
            key,
            document,
            history: crate::history::History::disabled(),
        })
    }

    /// The same route, showing the health of `history` (records dropped, why it cannot write).
    pub fn with_history(mut self, history: crate::history::History) -> Self {
        self.history = history;
        self
    }

    /// The document as it stands now.
    fn current(&self) -> String {
        if !self.history.enabled() {
            return self.document.to_string();
        }
        let health = self.history.health();
        let mut doc = self.document.clone();
        if let Some(o) = doc.as_object_mut() {
            o.insert(
                "history".to_string(),
                serde_json::json!({ "dropped": health.dropped, "fault": health.fault }),
            );
        }
        doc.to_string()
    }

    /// Answers admin queries until `stop`.
    pub async fn run(&self, stop: &CancellationToken) {
        loop {
            let query = tokio::select! {
                () = stop.cancelled() => break,
                q = self.queryable.recv_async() => match q {
                    Ok(q) => q,
                    // The session was closed under us: nothing more will arrive.
                    Err(_) => break,
                },
            };
            if let Err(e) = query.reply(self.key.as_str(), self.current()).await {
                tracing::warn!(selector = %query.selector(), error = %e, "admin reply failed");
            }
        }
    }

    pub async fn undeclare(self) {
        for (what, result) in [
            ("admin queryable", self.queryable.undeclare().await),
            ("liveliness token", self.token.undeclare().await),
        ] {
            if let Err(e) = result {
                tracing::warn!(error = %e, "undeclaring the {what} failed");
            }
        }
    }
}
