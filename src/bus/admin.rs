//! The gateway itself on the bus: its liveliness token `P/C/gateway`, present while it runs,
//! and `P/C/@admin`, a queryable answering a JSON document with the version, the running
//! configuration and its generation (1 at start, one more for each reload taken), and what the
//! last reload did. `@admin` is a verbatim chunk: wildcards such as `P/C/**` do not match it,
//! so subscribers to a cell's data never see admin traffic, and it stays apart from zenoh's
//! own `@/<zid>/...` admin space.

use tokio_util::sync::CancellationToken;
use zenoh::Session;
use zenoh::handlers::FifoChannelHandler;
use zenoh::liveliness::LivelinessToken;
use zenoh::query::{Query, Queryable};

use super::error::BusError;
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

/// The JSON document the admin key answers with, as the gateway starts.
pub fn admin_document(config: &CellConfig, zid: &str) -> serde_json::Value {
    admin_document_at(config, zid, 1)
}

/// The JSON document of `config` at configuration generation `generation`.
pub fn admin_document_at(config: &CellConfig, zid: &str, generation: u64) -> serde_json::Value {
    serde_json::json!({
        "name": "cellgate",
        "version": VERSION,
        "cell": config.cell,
        "zid": zid,
        "started_unix_ms": started_unix_ms(),
        "generation": generation,
        "config": redacted(config),
    })
}

/// The last reload as the admin document shows it.
fn reload_json(r: &cellgate_core::pb::ReloadResult) -> serde_json::Value {
    serde_json::json!({
        "applied": r.applied,
        "unix_ms": r.unix_ms,
        "via": r.via,
        "file": r.file,
        "generation": r.generation,
        "machines_added": r.machines_added,
        "machines_removed": r.machines_removed,
        "machines_changed": r.machines_changed,
        "plcs_added": r.plcs_added,
        "plcs_removed": r.plcs_removed,
        "plcs_changed": r.plcs_changed,
        "plc_tags": r.plc_tags,
        "settings": r.settings,
        "waiting": r.waiting,
        "errors": r.errors,
        "restart_needed": r.restart_needed,
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
    /// Replaced by a reload.
    document: std::sync::Mutex<serde_json::Value>,
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
            document: std::sync::Mutex::new(document),
            history: crate::history::History::disabled(),
        })
    }

    /// The same route, showing the health of `history` (records dropped, why it cannot write).
    pub fn with_history(mut self, history: crate::history::History) -> Self {
        self.history = history;
        self
    }

    fn document(&self) -> std::sync::MutexGuard<'_, serde_json::Value> {
        self.document
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Shows `config` at `generation`; `reload`: what the last reload did (taken or not;
    /// none: the one shown stays); `waiting`: the machines whose link stops or restarts once
    /// their running job has ended.
    pub fn set_config(
        &self,
        config: &CellConfig,
        generation: u64,
        reload: Option<&cellgate_core::pb::ReloadResult>,
        waiting: &[String],
    ) {
        let mut doc = self.document();
        let zid = doc["zid"].as_str().unwrap_or_default().to_string();
        let last = doc.get("reload").cloned();
        *doc = admin_document_at(config, &zid, generation);
        let reload = reload.map(reload_json).or(last);
        if let Some(o) = doc.as_object_mut() {
            if let Some(r) = reload {
                o.insert("reload".to_string(), r);
            }
            o.insert("waiting".to_string(), serde_json::json!(waiting));
        }
    }

    /// The document as it stands now.
    fn current(&self) -> String {
        let mut doc = self.document().clone();
        if !self.history.enabled() {
            return doc.to_string();
        }
        let health = self.history.health();
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
