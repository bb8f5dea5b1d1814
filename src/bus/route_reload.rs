//! `P/C/@admin/reload`: a client asks the gateway to read its cell file again
//! (docs/configuration.md, "Reloading"). A get with a `ReloadRequest` (permission
//! `cell.reload`, a key of its own: zenoh's access control sees keys, not payloads) is handed to
//! whoever applies reloads (the gateway) and answered with the `ReloadResult` once the reload
//! is taken, or with an `ErrorReply` listing every reason it was refused. Reloads are applied
//! one at a time, whoever asks (a client, SIGHUP); each is audited (`cell.reload`) and its
//! result published on `P/C/reload`.

use prost::Message as _;
use tokio::sync::{mpsc, oneshot};
use tokio_util::sync::CancellationToken;
use zenoh::Session;
use zenoh::handlers::FifoChannelHandler;
use zenoh::query::{Query, Queryable};

use super::audit::{Audit, Auditor, origin_of};
use super::context::reply_err;
use super::error::BusError;
use super::keys::CellKeys;
use super::payload::encoding;
use super::published::Published;
use crate::history::History;
use cellgate_core::codes::BusCode;
use cellgate_core::config::{Permission, SecurityConfig};
use cellgate_core::pb;

/// Longest a client's reload waits for its answer here: starting the links of added
/// machines may take a connection attempt each.
const ANSWER_WITHIN: std::time::Duration = std::time::Duration::from_secs(120);

/// A reload asked for.
#[derive(Debug)]
pub struct ReloadAsk {
    /// Stop or restart the links of removed and changed machines at once.
    pub force: bool,
    /// `bus` (a client), `signal` (SIGHUP).
    pub via: &'static str,
    /// Who asked, as the request said.
    pub origin: Option<pb::RequestOrigin>,
    pub reply: oneshot::Sender<ReloadAnswer>,
}

/// What came of a reload: its result, and the code of its refusal
/// (`ERROR_CODE_UNSPECIFIED` when it was taken).
#[derive(Debug, Clone, PartialEq)]
pub struct ReloadAnswer {
    pub result: pb::ReloadResult,
    pub code: pb::ErrorCode,
}

impl ReloadAnswer {
    /// Every reason it was refused, one a line.
    pub fn message(&self) -> String {
        self.result.errors.join("\n")
    }
}

impl std::fmt::Display for ReloadAnswer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message())
    }
}

impl BusCode for ReloadAnswer {
    fn code(&self) -> pb::ErrorCode {
        self.code
    }
}

/// The reload queryable. Undeclared when dropped.
pub struct ReloadRoute {
    queryable: Queryable<FifoChannelHandler<Query>>,
    asks: mpsc::Sender<ReloadAsk>,
}

impl ReloadRoute {
    /// Declares `P/C/@admin/reload`; what arrives there is handed to `asks`.
    pub async fn declare(
        session: &Session,
        keys: &CellKeys,
        asks: mpsc::Sender<ReloadAsk>,
    ) -> Result<Self, BusError> {
        let key = keys.reload();
        let queryable = session
            .declare_queryable(key.as_str())
            .await
            .map_err(|source| BusError::Declare {
                what: "reload queryable",
                key,
                source,
            })?;
        Ok(ReloadRoute { queryable, asks })
    }

    /// Serves reload requests until `stop`, one at a time: a reload waits for the one before.
    pub async fn run(self, stop: CancellationToken) {
        loop {
            let query = tokio::select! {
                () = stop.cancelled() => break,
                q = self.queryable.recv_async() => match q {
                    Ok(q) => q,
                    Err(_) => break,
                },
            };
            self.answer(&query).await;
        }
    }

    async fn answer(&self, q: &Query) {
        let limits = cellgate_core::bounds::Limits {
            max_inline: 0,
            max_program: 0,
        };
        let payload = q
            .payload()
            .map(|p| p.to_bytes().to_vec())
            .unwrap_or_default();
        let request = match cellgate_core::bounds::decode::<pb::ReloadRequest>(&payload, &limits) {
            Ok(r) => r,
            Err(e) => {
                let refused = refusal(pb::ErrorCode::InvalidRequest, e.to_string());
                return reply_err(q, &refused).await;
            }
        };
        let (reply, answer) = oneshot::channel();
        let ask = ReloadAsk {
            force: request.force,
            via: "bus",
            origin: origin_of(q.attachment()),
            reply,
        };
        if self.asks.send(ask).await.is_err() {
            let refused = refusal(pb::ErrorCode::Unavailable, "the gateway is stopping".into());
            return reply_err(q, &refused).await;
        }
        let answer = match tokio::time::timeout(ANSWER_WITHIN, answer).await {
            Ok(Ok(a)) => a,
            Ok(Err(_)) => refusal(
                pb::ErrorCode::Unavailable,
                "the gateway stopped before it took the reload".into(),
            ),
            Err(_) => refusal(
                pb::ErrorCode::Unavailable,
                "the reload did not finish in time (see the gateway's log)".into(),
            ),
        };
        if answer.code == pb::ErrorCode::Unspecified {
            let sent = q
                .reply(q.key_expr().to_string(), answer.result.encode_to_vec())
                .encoding(encoding::<pb::ReloadResult>())
                .await;
            if let Err(e) = sent {
                tracing::warn!(selector = %q.selector(), error = %e, "reply failed");
            }
        } else {
            reply_err(q, &answer).await;
        }
    }
}

fn refusal(code: pb::ErrorCode, error: String) -> ReloadAnswer {
    ReloadAnswer {
        result: pb::ReloadResult {
            errors: vec![error],
            unix_ms: pb::now_ms(),
            ..pb::ReloadResult::default()
        },
        code,
    }
}

/// Publishes what a reload did on `P/C/reload`.
pub async fn publish(session: &Session, keys: &CellKeys, result: &pb::ReloadResult) {
    let key = keys.reloads();
    let sent = session
        .put(key.as_str(), result.encode_to_vec())
        .encoding(encoding::<pb::ReloadResult>())
        .congestion_control(Published::Reload.congestion())
        .priority(Published::Reload.priority())
        .await;
    if let Err(e) = sent {
        tracing::warn!(%key, error = %e, "publishing the reload's result failed");
    }
}

/// Records a reload in the audit trail (`cell.reload`): who asked, and what it changed or
/// why it was refused. One a client asked for names the roles that may reload, as every
/// write does; one a signal asked for was the gateway's own host.
pub fn audit(history: &History, security: &SecurityConfig, keys: &CellKeys, a: &ReloadAnswer) {
    let r = &a.result;
    let mut detail = if r.applied {
        format!("generation {}: {}", r.generation, summary(r))
    } else {
        format!("refused; the cell stays at generation {}", r.generation)
    };
    if !r.waiting.is_empty() {
        detail.push_str(&format!(
            "; waiting for their running job: {}",
            r.waiting.join(", ")
        ));
    }
    let key = keys.reload();
    let entry = Audit {
        action: "cell.reload",
        permission: Permission::CellReload,
        key: &key,
        machine: "",
        target: r.file.clone(),
        detail,
        origin: r.origin.clone(),
    };
    let outcome = if r.applied { Ok(()) } else { Err(a) };
    if r.via == "bus" {
        Auditor::new(security).record(history, entry, outcome);
    } else {
        // Not sent over the bus: no role of the cell file had a say in it.
        Auditor::default().record(history, entry, outcome);
    }
}

/// What a taken reload changed, for people: `machines added: m4; settings: history.keep_days`.
pub fn summary(r: &pb::ReloadResult) -> String {
    cellgate_core::config::reload::summary_of([
        &r.machines_added,
        &r.machines_removed,
        &r.machines_changed,
        &r.plcs_added,
        &r.plcs_removed,
        &r.plcs_changed,
        &r.plc_tags,
        &r.settings,
    ])
}
