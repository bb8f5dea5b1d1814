//! The cell's PLC links on the bus (FFU120B command set, §5-3): memory, transfers, status.
//!
//! - `P/C/plc/L/mem/S/MODULE/ADDR[?count=N]`: a get reads N words (default 1) of MODULE at
//!   station S and answers `PlcWords`; a get with a `PlcWrite` writes them and answers
//!   `PlcWritten` once the module confirmed; a put with a `PlcWrite` writes without answer.
//!   `P/C/plc/L/mem/S/MODULE` with `PlcWrite { clear: true }` clears the module (01/05).
//! - `P/C/plc/L/transfer/MSGNO`: transfers the PLC sends are published here (`PlcTransfer`,
//!   reliable, `Block`: each is a message, none supersedes another); a get with a
//!   `PlcTransfer` sends one to the PLC and answers `PlcTransferred`, a put sends it unanswered.
//! - `P/C/plc/L/message` (modes 4–5, FFU120B §5-5, where the gateway is the module's external
//!   device): each message the PLC sends is published here (`PlcMessage`, reliable, `Block`); a
//!   get on `P/C/plc/L/message/send` with a `PlcMessage` sends one to the PLC and answers
//!   `PlcMessageSent` once it is on its way (nothing on the line answers it), a put sends it
//!   unanswered.
//! - `P/C/plc/L/status`: `PlcStatus` on a get; published (`Drop`: the next supersedes a lost
//!   one) when a station goes up or down and every [`STATUS_EVERY`].
//! - `P/C/plc/L/station/S`: a liveliness token while station S answers.
//!
//! A refusal of the module comes back as an `ErrorReply` whose code names the STA
//! (`ERROR_CODE_PLC_*`) and whose `sta` carries it (`cellgate_core::codes`).

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::broadcast::error::RecvError;
use tokio_util::sync::CancellationToken;
use zenoh::liveliness::LivelinessToken;
use zenoh::query::Query;
use zenoh::sample::{Sample, SampleKind};

use super::audit::{Audit, origin_of};
use super::context::{RouteContext, Routed, reply, reply_err};
use super::keys::PlcKey;
use super::payload::{BusMessage, encoding, schema_of};
use super::published::Published;
use crate::plc::{PlcEvent, PlcHandle, PlcLinkError, PlcSnapshot, TagError, TagWriteError};
use cellgate_core::codes::BusCode;
use cellgate_core::config::Permission;
use cellgate_core::config::PlcConfig;
use cellgate_core::fuji::command::{CommandError, Module, Reply, Request};
use cellgate_core::fuji::master::MasterError;
use cellgate_core::pb;

/// How often a PLC link's status is published when nothing changes.
pub const STATUS_EVERY: Duration = Duration::from_secs(5);

/// A PLC of the cell and its running link.
#[derive(Debug, Clone)]
pub struct PlcLink {
    pub config: PlcConfig,
    pub link: PlcHandle,
}

/// What the PLC routes share.
#[derive(Clone)]
pub(crate) struct PlcContext {
    pub route: RouteContext,
    /// Changed by a reload: a PLC added, removed, or given new tags.
    pub plcs: super::context::Live<BTreeMap<String, PlcLink>>,
}

impl Routed for PlcContext {
    fn route(&self) -> &RouteContext {
        &self.route
    }
}

/// Why a PLC request was refused.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub(crate) enum PlcRequestError {
    #[error("cell {cell} has no PLC {plc:?}; its PLCs are: {known}")]
    UnknownPlc {
        cell: String,
        plc: String,
        known: String,
    },
    #[error("{key}: {what}; expected {expected}")]
    BadKey {
        key: String,
        what: String,
        expected: &'static str,
    },
    #[error(
        "{key}: a put here carries a {expected} (encoding application/protobuf;{expected}, or \
         none said), not {found}: it was not read"
    )]
    Encoding {
        key: String,
        found: String,
        expected: &'static str,
    },
    #[error("PLC {plc}: {error}")]
    Payload {
        plc: String,
        error: cellgate_core::bounds::BoundError,
    },
    #[error("PLC {plc}: {error}")]
    Request {
        plc: String,
        #[source]
        error: CommandError,
    },
    #[error("PLC {plc}: {error}")]
    Plc {
        plc: String,
        #[source]
        error: MasterError,
    },
    #[error(transparent)]
    Tag(#[from] TagError),
    #[error("PLC {plc}: {error}")]
    TagWrite {
        plc: String,
        #[source]
        error: TagWriteError,
    },
    #[error(transparent)]
    Link(#[from] PlcLinkError),
}

impl BusCode for PlcRequestError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            PlcRequestError::UnknownPlc { .. } => pb::ErrorCode::UnknownMachine,
            PlcRequestError::BadKey { .. }
            | PlcRequestError::Encoding { .. }
            | PlcRequestError::Payload { .. }
            | PlcRequestError::Request { .. } => pb::ErrorCode::InvalidRequest,
            PlcRequestError::Plc { error, .. } => error.code(),
            PlcRequestError::Tag(e) => e.code(),
            PlcRequestError::TagWrite { error, .. } => error.code(),
            PlcRequestError::Link(e) => e.code(),
        }
    }
    fn sta(&self) -> Option<u8> {
        match self {
            PlcRequestError::Plc { error, .. } => error.sta(),
            PlcRequestError::TagWrite { error, .. } => error.sta(),
            _ => None,
        }
    }
}

impl PlcContext {
    /// The PLC a key names.
    pub(super) fn plc(&self, name: &str) -> Result<PlcLink, PlcRequestError> {
        let plcs = self.plcs.now();
        plcs.get(name)
            .cloned()
            .ok_or_else(|| PlcRequestError::UnknownPlc {
                cell: self.route.keys.root().to_string(),
                plc: name.to_string(),
                known: if plcs.is_empty() {
                    "none".to_string()
                } else {
                    plcs.keys().cloned().collect::<Vec<_>>().join(", ")
                },
            })
    }

    /// Publishes `message` on `key`, with the QoS of `what`'s row.
    pub(super) async fn publish<M: BusMessage>(&self, what: Published, key: String, message: &M) {
        let sent = self
            .route
            .session
            .put(key.clone(), message.encode_to_vec())
            .encoding(encoding::<M>())
            .congestion_control(what.congestion())
            .priority(what.priority())
            .await;
        if let Err(e) = sent {
            tracing::warn!(%key, error = %e, "publish failed");
        }
    }
}

/// `bytes` as the request message `M`, within its bounds ([`cellgate_core::bounds`]).
pub(crate) fn decode_payload<M: cellgate_core::bounds::Bounded>(
    plc: &str,
    bytes: &[u8],
) -> Result<M, PlcRequestError> {
    // No PLC message depends on the cell file's program limits.
    let limits = cellgate_core::bounds::Limits {
        max_inline: 0,
        max_program: 0,
    };
    cellgate_core::bounds::decode(bytes, &limits).map_err(|error| PlcRequestError::Payload {
        plc: plc.to_string(),
        error,
    })
}

/// A memory key read back: the PLC, station, module and address.
struct MemTarget {
    plc: String,
    station: u8,
    module: Module,
    address: Option<u16>,
    /// The key is a write key (`…/write`).
    write: bool,
}

const MEM_KEY: &str = "P/C/plc/L/mem/STATION/MODULE/ADDRESS to read (e.g. …/mem/0/D/100), \
     …/ADDRESS/write to write, P/C/plc/L/mem/STATION/MODULE/write to clear";

fn mem_target(ctx: &PlcContext, key: &str) -> Result<MemTarget, PlcRequestError> {
    let bad = |what: String| PlcRequestError::BadKey {
        key: key.to_string(),
        what,
        expected: MEM_KEY,
    };
    let Some(PlcKey::Mem {
        plc,
        station,
        module,
        address,
        write,
    }) = ctx.route.keys.parse_plc(key)
    else {
        return Err(bad("not a memory key".to_string()));
    };
    let link = ctx.plc(plc)?;
    let station: u8 = station
        .parse()
        .map_err(|_| bad(format!("station {station:?} is not a number")))?;
    if !link.config.stations.contains(&station) {
        return Err(bad(format!(
            "station {station} is not one of PLC {plc}'s stations {:?}",
            link.config.stations
        )));
    }
    let module = Module::by_name(module).ok_or_else(|| PlcRequestError::Request {
        plc: plc.to_string(),
        error: CommandError::UnknownModule {
            name: module.to_string(),
        },
    })?;
    let address = match address {
        None => None,
        Some(a) => Some(
            a.parse::<u16>()
                .map_err(|_| bad(format!("address {a:?} is not 0..=65535")))?,
        ),
    };
    Ok(MemTarget {
        plc: plc.to_string(),
        station,
        module,
        address,
        write,
    })
}

/// Sends `request` and waits for the module's reply.
async fn exchange(
    ctx: &PlcContext,
    plc: &str,
    station: u8,
    request: Request,
) -> Result<Reply, PlcRequestError> {
    let link = ctx.plc(plc)?;
    link.link
        .request(station, request)
        .await?
        .map_err(|error| PlcRequestError::Plc {
            plc: plc.to_string(),
            error,
        })
}

/// A read, or (with a `PlcWrite` payload) a write or clear.
async fn mem_request(
    ctx: &PlcContext,
    key: &str,
    count: usize,
    payload: Option<&[u8]>,
) -> Result<Answer, PlcRequestError> {
    let t = mem_target(ctx, key)?;
    let req_err = |error| PlcRequestError::Request {
        plc: t.plc.clone(),
        error,
    };
    let wrong_key = |what: &str| PlcRequestError::BadKey {
        key: key.to_string(),
        what: what.to_string(),
        expected: MEM_KEY,
    };
    match payload {
        None if t.write => Err(wrong_key(
            "a get on a …/write key writes and needs a PlcWrite; words are read without /write",
        )),
        Some(_) if !t.write => Err(wrong_key(
            "a get here reads and takes no payload: a PlcWrite goes to the key with /write",
        )),
        None => {
            let address = t.address.ok_or_else(|| PlcRequestError::BadKey {
                key: key.to_string(),
                what: "a read names an address".to_string(),
                expected: MEM_KEY,
            })?;
            let request = Request::read_words(t.module, address, count).map_err(req_err)?;
            let reply = exchange(ctx, &t.plc, t.station, request).await?;
            let words = match reply {
                Reply::Read { words, .. } => words,
                _ => Vec::new(),
            };
            Ok(Answer::Words(pb::PlcWords {
                plc: t.plc.clone(),
                station: u32::from(t.station),
                module: t.module.to_string(),
                address: u32::from(address),
                words,
                attribute: u32::from(t.module.attribute().code()),
                unix_ms: pb::now_ms(),
            }))
        }
        Some(bytes) => {
            let w: pb::PlcWrite = decode_payload(&t.plc, bytes)?;
            let (request, words) = if w.clear {
                (Request::Clear { module: t.module }, 0)
            } else {
                let address = t.address.ok_or_else(|| PlcRequestError::BadKey {
                    key: key.to_string(),
                    what: "a write names an address (a clear does not)".to_string(),
                    expected: MEM_KEY,
                })?;
                (
                    Request::write_words(t.module, address, &w.words).map_err(req_err)?,
                    w.words.len() as u32,
                )
            };
            exchange(ctx, &t.plc, t.station, request).await?;
            Ok(Answer::Written(pb::PlcWritten {
                plc: t.plc.clone(),
                station: u32::from(t.station),
                module: t.module.to_string(),
                address: u32::from(t.address.unwrap_or(0)),
                words,
                cleared: w.clear,
            }))
        }
    }
}

enum Answer {
    Words(pb::PlcWords),
    Written(pb::PlcWritten),
}

fn count_of(q: &Query) -> Result<usize, PlcRequestError> {
    match q.parameters().get("count") {
        None => Ok(1),
        Some(c) => c.parse().map_err(|_| PlcRequestError::BadKey {
            key: q.selector().to_string(),
            what: format!("count={c} is not a number"),
            expected: "?count=N, N words",
        }),
    }
}

pub(super) async fn mem_query(ctx: &PlcContext, q: &Query) {
    let key = q.key_expr().to_string();
    let payload = q.payload().map(|p| p.to_bytes().to_vec());
    let result = match count_of(q) {
        Ok(count) => mem_request(ctx, &key, count, payload.as_deref()).await,
        Err(e) => Err(e),
    };
    audit_mem(
        ctx,
        &key,
        payload.as_deref(),
        origin_of(q.attachment()),
        result.as_ref().map(|_| ()),
    );
    match result {
        Ok(Answer::Words(w)) => reply(q, key, &w).await,
        Ok(Answer::Written(w)) => reply(q, key, &w).await,
        Err(e) => reply_err(q, &e).await,
    }
}

/// A put on a PLC's write key is read as `M` when its encoding says so or says nothing (as a
/// DO put is); another encoding is refused with a word (logged by the put's route), never
/// passed over in silence.
pub(super) fn put_encoding<M: BusMessage>(s: &Sample) -> Result<(), PlcRequestError> {
    let e = s.encoding();
    if *e == zenoh::bytes::Encoding::default() || schema_of(e).as_deref() == Some(M::SCHEMA) {
        return Ok(());
    }
    Err(PlcRequestError::Encoding {
        key: s.key_expr().to_string(),
        found: e.to_string(),
        expected: M::SCHEMA,
    })
}

/// The words a memory write asked for, as the audit trail says them (the first 16).
fn mem_detail(payload: Option<&[u8]>) -> String {
    let Some(w) = payload.and_then(|p| <pb::PlcWrite as prost::Message>::decode(p).ok()) else {
        return String::new();
    };
    if w.clear {
        return "clear".to_string();
    }
    let shown: Vec<String> = w
        .words
        .iter()
        .take(16)
        .map(|v| format!("0x{v:04X}"))
        .collect();
    let more = w.words.len().saturating_sub(16);
    format!(
        "{} word(s): {}{}",
        w.words.len(),
        shown.join(" "),
        if more > 0 {
            format!(" … ({more} more)")
        } else {
            String::new()
        }
    )
}

/// A put with a `PlcWrite` on a memory key's `write`; a put has no answer, so a refusal is logged.
pub(super) async fn mem_put(ctx: &PlcContext, s: &Sample) {
    if let Err(e) = put_mem(ctx, s).await {
        tracing::warn!(key = %s.key_expr(), error = %e, "PLC memory put refused");
    }
}

async fn put_mem(ctx: &PlcContext, s: &Sample) -> Result<(), PlcRequestError> {
    if s.kind() != SampleKind::Put {
        return Ok(());
    }
    let bytes = s.payload().to_bytes();
    let done = match put_encoding::<pb::PlcWrite>(s) {
        Ok(()) => mem_request(ctx, s.key_expr().as_str(), 1, Some(&bytes))
            .await
            .map(|_| ()),
        Err(e) => Err(e),
    };
    audit_mem(
        ctx,
        s.key_expr().as_str(),
        Some(&bytes),
        origin_of(s.attachment()),
        done.as_ref().map(|_| ()),
    );
    done
}

/// Records a memory write or clear in the audit (reads are not writes).
fn audit_mem(
    ctx: &PlcContext,
    key: &str,
    payload: Option<&[u8]>,
    origin: Option<pb::RequestOrigin>,
    outcome: Result<(), &PlcRequestError>,
) {
    let Some(PlcKey::Mem {
        plc,
        station,
        module,
        address,
        write: true,
    }) = ctx.route.keys.parse_plc(key)
    else {
        return;
    };
    let (action, target) = match address {
        Some(a) => (
            "plc.mem.write",
            format!("{plc} station {station} {module}{a}"),
        ),
        None => ("plc.mem.clear", format!("{plc} station {station} {module}")),
    };
    ctx.route.audit(
        Audit {
            action,
            permission: Permission::PlcMem,
            key,
            machine: plc,
            target,
            detail: mem_detail(payload),
            origin,
        },
        outcome,
    );
}

/// Records a transfer sent to the PLC in the audit.
fn audit_transfer(
    ctx: &PlcContext,
    key: &str,
    origin: Option<pb::RequestOrigin>,
    outcome: Result<&pb::PlcTransferred, &PlcRequestError>,
) {
    let (plc, target) = match ctx.route.keys.parse_plc(key) {
        Some(PlcKey::Transfer { plc, message, .. }) => {
            (plc.to_string(), format!("{plc} message {message}"))
        }
        _ => (String::new(), key.to_string()),
    };
    ctx.route.audit(
        Audit {
            action: "plc.transfer",
            permission: Permission::PlcTransfer,
            key,
            machine: &plc,
            target,
            detail: match outcome {
                Ok(t) => format!("{} bytes", t.bytes),
                Err(_) => String::new(),
            },
            origin,
        },
        outcome.map(|_| ()),
    );
}

fn transfer_target(ctx: &PlcContext, key: &str) -> Result<(String, u8), PlcRequestError> {
    let bad = |what: String| PlcRequestError::BadKey {
        key: key.to_string(),
        what,
        expected: "P/C/plc/L/transfer/MSGNO/send (MSGNO 0..=255)",
    };
    let Some(PlcKey::Transfer {
        plc,
        message,
        send: true,
    }) = ctx.route.keys.parse_plc(key)
    else {
        return Err(bad("not a transfer's send key".to_string()));
    };
    ctx.plc(plc)?;
    let message = message
        .parse()
        .map_err(|_| bad(format!("message number {message:?} is not 0..=255")))?;
    Ok((plc.to_string(), message))
}

async fn send_transfer(
    ctx: &PlcContext,
    key: &str,
    bytes: &[u8],
) -> Result<pb::PlcTransferred, PlcRequestError> {
    let (plc, message) = transfer_target(ctx, key)?;
    let t: pb::PlcTransfer = decode_payload(&plc, bytes)?;
    let n = t.data.len() as u32;
    // Transfers work in mode 1 only, to station 00 (§5-3-2, §5-4 iii): the master refuses
    // them otherwise.
    exchange(
        ctx,
        &plc,
        0,
        Request::Transfer {
            message,
            data: t.data,
        },
    )
    .await?;
    Ok(pb::PlcTransferred {
        plc,
        message: u32::from(message),
        bytes: n,
    })
}

pub(super) async fn transfer_query(ctx: &PlcContext, q: &Query) {
    let key = q.key_expr().to_string();
    let Some(payload) = q.payload().map(|p| p.to_bytes().to_vec()) else {
        let e = PlcRequestError::BadKey {
            key,
            what: "a get here sends a transfer and needs a PlcTransfer payload".to_string(),
            expected: "subscribe to P/C/plc/L/transfer/** for the PLC's transfers",
        };
        reply_err(q, &e).await;
        return;
    };
    let sent = send_transfer(ctx, &key, &payload).await;
    audit_transfer(ctx, &key, origin_of(q.attachment()), sent.as_ref());
    match sent {
        Ok(t) => reply(q, key, &t).await,
        Err(e) => reply_err(q, &e).await,
    }
}

/// A put with a `PlcTransfer` on a transfer's `send`; a put has no answer, so a refusal is logged.
pub(super) async fn transfer_put(ctx: &PlcContext, s: &Sample) {
    if let Err(e) = put_transfer(ctx, s).await {
        tracing::warn!(key = %s.key_expr(), error = %e, "PLC transfer put refused");
    }
}

async fn put_transfer(ctx: &PlcContext, s: &Sample) -> Result<(), PlcRequestError> {
    if s.kind() != SampleKind::Put {
        return Ok(());
    }
    let sent = match put_encoding::<pb::PlcTransfer>(s) {
        Ok(()) => send_transfer(ctx, s.key_expr().as_str(), &s.payload().to_bytes()).await,
        Err(e) => Err(e),
    };
    audit_transfer(
        ctx,
        s.key_expr().as_str(),
        origin_of(s.attachment()),
        sent.as_ref(),
    );
    sent.map(|_| ())
}

/// A moment of the link's clock as Unix milliseconds.
fn ago_unix_ms(at: std::time::Instant) -> u64 {
    let ago = crate::link::pump::now().saturating_duration_since(at);
    pb::now_ms().saturating_sub(u64::try_from(ago.as_millis()).unwrap_or(u64::MAX))
}

/// The `PlcStatus` of a link.
pub(crate) fn status_message(link: &PlcLink, snap: &PlcSnapshot) -> pb::PlcStatus {
    let plc = link.config.name.clone();
    let c = &snap.counters;
    let r = &c.receive_errors;
    pb::PlcStatus {
        plc: plc.clone(),
        mode: u32::from(link.config.mode),
        line: snap.line.clone(),
        stations: link
            .config
            .stations
            .iter()
            .map(|&n| {
                let s = c.stations.get(&n).cloned().unwrap_or_else(|| {
                    cellgate_core::fuji::master::StationCounters {
                        up: true,
                        ..Default::default()
                    }
                });
                pb::PlcStation {
                    plc: plc.clone(),
                    station: u32::from(n),
                    up: s.up,
                    requests: s.requests,
                    replies: s.replies,
                    timeouts: s.timeouts,
                    retries: s.retries,
                    bcc_errors: s.bcc_errors,
                    corrupted_replies: s.corrupted_replies,
                    error_replies: s
                        .error_replies
                        .iter()
                        .map(|(k, v)| (u32::from(*k), *v))
                        .collect(),
                    refused_down: s.refused_down,
                    last_error_unix_ms: s.last_error_at.map_or(0, ago_unix_ms),
                    last_error: s.last_error.map(|e| e.to_string()).unwrap_or_default(),
                }
            })
            .collect(),
        bytes_in: snap.bytes.0,
        bytes_out: snap.bytes.1,
        transfers_received: c.transfers_received,
        unexpected_texts: c.unexpected_texts,
        receive_errors: [
            ("buffer_full", r.buffer_full),
            ("start_code", r.start_code),
            ("bcc", r.bcc),
            ("too_long", r.too_long),
            ("text_form", r.text_form),
            ("character", r.character),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect(),
        tags: snap
            .tags
            .iter()
            .map(|t| super::payload::tag_message(&plc, t))
            .collect(),
        messages_received: c.messages_received,
        messages_sent: c.messages_sent,
        partial_messages: c.partial_messages,
        fixed_length: link.config.fixed_length.map_or(0, u32::from),
        line_errors: [
            ("parity", c.line_errors.parity),
            ("framing", c.line_errors.framing),
            ("overrun", c.line_errors.overrun),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect(),
        poll_groups: snap
            .groups
            .iter()
            .zip(0u32..)
            .map(|(g, group)| {
                let ms = |d: std::time::Duration| u32::try_from(d.as_millis()).unwrap_or(u32::MAX);
                pb::PlcPollGroup {
                    group,
                    interval_ms: ms(g.interval),
                    reads: u32::try_from(g.reads).unwrap_or(u32::MAX),
                    rounds: g.rounds,
                    last_round_ms: ms(g.last_round),
                    mean_round_ms: ms(g.mean_round),
                    max_round_ms: ms(g.max_round),
                    achieved_interval_ms: ms(g.achieved_interval),
                    overruns: g.overruns,
                }
            })
            .collect(),
    }
}

const MESSAGE_KEY: &str = "P/C/plc/L/message/send, on a PLC in mode 4 or 5";

/// Sends a non-procedure message (modes 4–5, FFU120B §5-5) to the PLC of `key`.
async fn send_message(
    ctx: &PlcContext,
    key: &str,
    bytes: &[u8],
) -> Result<pb::PlcMessageSent, PlcRequestError> {
    let bad = |what: String| PlcRequestError::BadKey {
        key: key.to_string(),
        what,
        expected: MESSAGE_KEY,
    };
    let Some(PlcKey::Message { plc, send: true }) = ctx.route.keys.parse_plc(key) else {
        return Err(bad("not a message's send key".to_string()));
    };
    let link = ctx.plc(plc)?;
    let m: pb::PlcMessage = decode_payload(plc, bytes)?;
    let n = m.data.len() as u32;
    // The master refuses it in modes 1–3 (§5-5) and checks its length (item 15).
    let reply = link
        .link
        .send_message(m.data)
        .await?
        .map_err(|error| PlcRequestError::Plc {
            plc: plc.to_string(),
            error,
        })?;
    let line_bytes = match reply {
        Reply::Sent { bytes } => u32::try_from(bytes).unwrap_or(u32::MAX),
        _ => 0,
    };
    Ok(pb::PlcMessageSent {
        plc: plc.to_string(),
        bytes: n,
        line_bytes,
        receive_message: u32::from(link.config.receive_message),
    })
}

pub(super) async fn message_query(ctx: &PlcContext, q: &Query) {
    let key = q.key_expr().to_string();
    let Some(payload) = q.payload().map(|p| p.to_bytes().to_vec()) else {
        let e = PlcRequestError::BadKey {
            key,
            what: "a get here sends a message and needs a PlcMessage payload".to_string(),
            expected: "subscribe to P/C/plc/L/message for the PLC's messages",
        };
        reply_err(q, &e).await;
        return;
    };
    let sent = send_message(ctx, &key, &payload).await;
    audit_message(ctx, &key, origin_of(q.attachment()), sent.as_ref());
    match sent {
        Ok(m) => reply(q, key, &m).await,
        Err(e) => reply_err(q, &e).await,
    }
}

/// Records a message sent to the PLC (modes 4–5) in the audit.
fn audit_message(
    ctx: &PlcContext,
    key: &str,
    origin: Option<pb::RequestOrigin>,
    outcome: Result<&pb::PlcMessageSent, &PlcRequestError>,
) {
    let plc = match ctx.route.keys.parse_plc(key) {
        Some(PlcKey::Message { plc, .. }) => plc.to_string(),
        _ => String::new(),
    };
    ctx.route.audit(
        Audit {
            action: "plc.message",
            permission: Permission::PlcTransfer,
            key,
            machine: &plc,
            target: plc.clone(),
            detail: match outcome {
                Ok(m) => format!("{} bytes", m.bytes),
                Err(_) => String::new(),
            },
            origin,
        },
        outcome.map(|_| ()),
    );
}

/// A put with a `PlcMessage` on `message/send`; a put has no answer, so a refusal is logged.
pub(super) async fn message_put(ctx: &PlcContext, s: &Sample) {
    if let Err(e) = put_message(ctx, s).await {
        tracing::warn!(key = %s.key_expr(), error = %e, "PLC message put refused");
    }
}

async fn put_message(ctx: &PlcContext, s: &Sample) -> Result<(), PlcRequestError> {
    if s.kind() != SampleKind::Put {
        return Ok(());
    }
    let sent = match put_encoding::<pb::PlcMessage>(s) {
        Ok(()) => send_message(ctx, s.key_expr().as_str(), &s.payload().to_bytes()).await,
        Err(e) => Err(e),
    };
    audit_message(
        ctx,
        s.key_expr().as_str(),
        origin_of(s.attachment()),
        sent.as_ref(),
    );
    sent.map(|_| ())
}

pub(super) async fn status_query(ctx: &PlcContext, q: &Query) {
    let key = q.key_expr().to_string();
    if !key.contains('*') {
        let name = match ctx.route.keys.parse_plc(&key) {
            Some(PlcKey::Status { plc }) => plc.to_string(),
            _ => return,
        };
        let link = match ctx.plc(&name) {
            Ok(l) => l,
            Err(e) => return reply_err(q, &e).await,
        };
        match link.link.snapshot().await {
            Ok(s) => reply(q, key, &status_message(&link, &s)).await,
            Err(e) => reply_err(q, &PlcRequestError::from(e)).await,
        }
        return;
    }
    for link in ctx.plcs.now().values() {
        let k = ctx.route.keys.plc_status(&link.config.name);
        if !super::keys::intersects(q.key_expr(), &k) {
            continue;
        }
        if let Ok(s) = link.link.snapshot().await {
            reply(q, k, &status_message(link, &s)).await;
        }
    }
}

/// Publishes a PLC link's transfers and status, and holds its stations' liveliness tokens,
/// until `stop`.
pub(crate) async fn publish_link(ctx: PlcContext, link: PlcLink, stop: CancellationToken) {
    let mut events = link.link.subscribe();
    let name = link.config.name.clone();
    let keys = Arc::clone(&ctx.route.keys);
    let mut tokens: BTreeMap<u8, LivelinessToken> = BTreeMap::new();
    for &s in &link.config.stations {
        // A station is presumed up until the master marks it down.
        match ctx
            .route
            .session
            .liveliness()
            .declare_token(keys.plc_station(&name, s))
            .await
        {
            Ok(t) => {
                tokens.insert(s, t);
            }
            Err(e) => tracing::warn!(plc = %name, station = s, error = %e, "liveliness token"),
        }
    }
    let mut tick = tokio::time::interval(STATUS_EVERY);
    let status = |ctx: PlcContext, link: PlcLink| async move {
        if let Ok(s) = link.link.snapshot().await {
            let k = ctx.route.keys.plc_status(&link.config.name);
            ctx.publish(Published::PlcStatus, k, &status_message(&link, &s))
                .await;
        }
    };
    loop {
        tokio::select! {
            () = stop.cancelled() => break,
            _ = tick.tick() => status(ctx.clone(), link.clone()).await,
            ev = events.recv() => match ev {
                Ok(PlcEvent::Transfer { message, data, time }) => {
                    let t = pb::PlcTransfer {
                        plc: name.clone(),
                        message: u32::from(message),
                        data,
                        from_plc: true,
                        unix_ms: pb::unix_ms(time),
                    };
                    ctx.publish(Published::PlcTransfer, keys.plc_transfer(&name, message), &t).await;
                }
                Ok(PlcEvent::Message { data, time }) => {
                    let m = pb::PlcMessage {
                        plc: name.clone(),
                        data,
                        from_plc: true,
                        receive_message: 0,
                        unix_ms: pb::unix_ms(time),
                    };
                    ctx.publish(Published::PlcMessage, keys.plc_message(&name), &m).await;
                }
                Ok(PlcEvent::Station { station, up }) => {
                    ctx.route.history.event(
                        &name,
                        pb::HistoryKind::Station,
                        pb::history_record::Record::Station(pb::StationChange {
                            station: u32::from(station),
                            up,
                        }),
                    );
                    if up {
                        if let Ok(t) = ctx.route.session.liveliness().declare_token(keys.plc_station(&name, station)).await {
                            tokens.insert(station, t);
                        }
                    } else if let Some(t) = tokens.remove(&station) {
                        let _ = t.undeclare().await;
                    }
                    status(ctx.clone(), link.clone()).await;
                }
                Ok(PlcEvent::Stopped { .. }) | Err(RecvError::Closed) => break,
                Ok(_) => {}
                Err(RecvError::Lagged(n)) => tracing::warn!(plc = %name, missed = n, "PLC events lagged"),
            }
        }
    }
    for (_, t) in tokens {
        let _ = t.undeclare().await;
    }
}
