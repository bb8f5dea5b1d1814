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

use super::context::{RouteContext, Routed, reply, reply_err};
use super::keys::PlcKey;
use super::payload::{BusMessage, WrongEncoding, encoding};
use super::published::Published;
use super::write::{Audited, Done, Write};
use crate::plc::{PlcEvent, PlcHandle, PlcLinkError, PlcSnapshot, TagError, TagWriteError};
use cellgate_core::codes::BusCode;
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
    #[error(transparent)]
    Encoding(#[from] WrongEncoding),
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
            | PlcRequestError::Encoding(_)
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

/// A read of `count` words.
async fn read_words(
    ctx: &PlcContext,
    key: &str,
    count: usize,
) -> Result<pb::PlcWords, PlcRequestError> {
    let t = mem_target(ctx, key)?;
    let wrong_key = |what: &str| PlcRequestError::BadKey {
        key: key.to_string(),
        what: what.to_string(),
        expected: MEM_KEY,
    };
    if t.write {
        return Err(wrong_key(
            "a get on a …/write key writes and needs a PlcWrite; words are read without /write",
        ));
    }
    let address = t
        .address
        .ok_or_else(|| wrong_key("a read names an address"))?;
    let request = Request::read_words(t.module, address, count).map_err(|error| {
        PlcRequestError::Request {
            plc: t.plc.clone(),
            error,
        }
    })?;
    let reply = exchange(ctx, &t.plc, t.station, request).await?;
    let words = match reply {
        Reply::Read { words, .. } => words,
        _ => Vec::new(),
    };
    Ok(pb::PlcWords {
        plc: t.plc.clone(),
        station: u32::from(t.station),
        module: t.module.to_string(),
        address: u32::from(address),
        words,
        attribute: u32::from(t.module.attribute().code()),
        unix_ms: pb::now_ms(),
    })
}

/// A write or clear (a `PlcWrite` in `bytes`).
async fn write_words(
    ctx: &PlcContext,
    key: &str,
    bytes: &[u8],
) -> Result<pb::PlcWritten, PlcRequestError> {
    let t = mem_target(ctx, key)?;
    let wrong_key = |what: &str| PlcRequestError::BadKey {
        key: key.to_string(),
        what: what.to_string(),
        expected: MEM_KEY,
    };
    if !t.write {
        return Err(wrong_key(
            "a get here reads and takes no payload: a PlcWrite goes to the key with /write",
        ));
    }
    let w: pb::PlcWrite = decode_payload(&t.plc, bytes)?;
    let (request, words) = if w.clear {
        (Request::Clear { module: t.module }, 0)
    } else {
        let address = t
            .address
            .ok_or_else(|| wrong_key("a write names an address (a clear does not)"))?;
        let request = Request::write_words(t.module, address, &w.words).map_err(|error| {
            PlcRequestError::Request {
                plc: t.plc.clone(),
                error,
            }
        })?;
        (request, w.words.len() as u32)
    };
    exchange(ctx, &t.plc, t.station, request).await?;
    Ok(pb::PlcWritten {
        plc: t.plc.clone(),
        station: u32::from(t.station),
        module: t.module.to_string(),
        address: u32::from(t.address.unwrap_or(0)),
        words,
        cleared: w.clear,
    })
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

/// A get on a memory key reads words. The writes' own keys (`…/write`) are the write row's:
/// a get there is answered by it, not here.
pub(super) async fn mem_query(ctx: &PlcContext, q: &Query) {
    let key = q.key_expr().to_string();
    if let Some(PlcKey::Mem { write: true, .. }) = ctx.route.keys.parse_plc(&key) {
        return;
    }
    let read = match (count_of(q), q.payload()) {
        (Err(e), _) => Err(e),
        (Ok(_), Some(_)) => Err(PlcRequestError::BadKey {
            key: key.clone(),
            what: "a get here reads and takes no payload: a PlcWrite goes to the key with /write"
                .to_string(),
            expected: MEM_KEY,
        }),
        (Ok(count), None) => read_words(ctx, &key, count).await,
    };
    match read {
        Ok(w) => reply(q, key, &w).await,
        Err(e) => reply_err(q, &e).await,
    }
}

/// A `PlcWrite` on a memory key's `write` (its write row): writes the words, or clears the
/// module (01/05), and answers `PlcWritten` once the module confirmed.
pub(super) async fn mem_write(ctx: &PlcContext, w: Write) -> Done<pb::PlcWritten, PlcRequestError> {
    let Some(bytes) = w.bytes() else {
        return Done::refused(PlcRequestError::BadKey {
            key: w.key().to_string(),
            what: "a get on a …/write key writes and needs a PlcWrite; words are read without \
                   /write"
                .to_string(),
            expected: MEM_KEY,
        });
    };
    let written = match w.checked() {
        Ok(()) => write_words(ctx, w.key(), &bytes).await,
        Err(e) => Err(e.into()),
    };
    Done {
        audit: mem_audited(ctx, w.key(), &bytes),
        outcome: written.map(Some),
    }
}

/// The words a memory write asked for, as the audit trail says them (the first 16).
fn mem_detail(payload: &[u8]) -> String {
    let Ok(w) = <pb::PlcWrite as prost::Message>::decode(payload) else {
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

/// What the audit says of a memory write or clear, when the key names one.
fn mem_audited(ctx: &PlcContext, key: &str, payload: &[u8]) -> Option<Audited> {
    let Some(PlcKey::Mem {
        plc,
        station,
        module,
        address,
        write: true,
    }) = ctx.route.keys.parse_plc(key)
    else {
        return None;
    };
    let (action, target) = match address {
        Some(a) => (
            "plc.mem.write",
            format!("{plc} station {station} {module}{a}"),
        ),
        None => ("plc.mem.clear", format!("{plc} station {station} {module}")),
    };
    Some(Audited {
        action,
        machine: plc.to_string(),
        target,
        detail: mem_detail(payload),
    })
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

/// A `PlcTransfer` on a transfer's `send` (its write row): sends it to the PLC and answers
/// `PlcTransferred`.
pub(super) async fn transfer_write(
    ctx: &PlcContext,
    w: Write,
) -> Done<pb::PlcTransferred, PlcRequestError> {
    let Some(bytes) = w.bytes() else {
        return Done::refused(PlcRequestError::BadKey {
            key: w.key().to_string(),
            what: "a get here sends a transfer and needs a PlcTransfer payload".to_string(),
            expected: "subscribe to P/C/plc/L/transfer/** for the PLC's transfers",
        });
    };
    let sent = match w.checked() {
        Ok(()) => send_transfer(ctx, w.key(), &bytes).await,
        Err(e) => Err(e.into()),
    };
    let (plc, target) = match ctx.route.keys.parse_plc(w.key()) {
        Some(PlcKey::Transfer { plc, message, .. }) => {
            (plc.to_string(), format!("{plc} message {message}"))
        }
        _ => (String::new(), w.key().to_string()),
    };
    let audited = Audited {
        action: "plc.transfer",
        machine: plc,
        target,
        detail: match &sent {
            Ok(t) => format!("{} bytes", t.bytes),
            Err(_) => String::new(),
        },
    };
    Done::audited(audited, sent)
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

/// A `PlcMessage` on `message/send` (its write row): sends it to the PLC (modes 4–5) and
/// answers `PlcMessageSent` once it is on its way.
pub(super) async fn message_write(
    ctx: &PlcContext,
    w: Write,
) -> Done<pb::PlcMessageSent, PlcRequestError> {
    let Some(bytes) = w.bytes() else {
        return Done::refused(PlcRequestError::BadKey {
            key: w.key().to_string(),
            what: "a get here sends a message and needs a PlcMessage payload".to_string(),
            expected: "subscribe to P/C/plc/L/message for the PLC's messages",
        });
    };
    let sent = match w.checked() {
        Ok(()) => send_message(ctx, w.key(), &bytes).await,
        Err(e) => Err(e.into()),
    };
    let plc = match ctx.route.keys.parse_plc(w.key()) {
        Some(PlcKey::Message { plc, .. }) => plc.to_string(),
        _ => String::new(),
    };
    let audited = Audited {
        action: "plc.message",
        machine: plc.clone(),
        target: plc,
        detail: match &sent {
            Ok(m) => format!("{} bytes", m.bytes),
            Err(_) => String::new(),
        },
    };
    Done::audited(audited, sent)
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
