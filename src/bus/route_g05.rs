//! G05 streams on the bus (§9; the contract is in `proto/cellgate/v1/g05.proto`).
//!
//! - `P/C/machine/M/g05`: a get with a `G05Open` opens a stream (`G05Opened` or `ErrorReply`);
//!   without payload it answers the current (or last) stream's `G05Status`.
//! - `P/C/machine/M/g05/S`: the stream's `G05Status`, published every
//!   [`STATUS_INTERVAL`] while it is open (QoS `Drop`: the next one supersedes it) and once,
//!   reliably, when it is over; a get answers the latest; a delete from another session
//!   cancels it (the end block goes out).
//! - `P/C/machine/M/g05/S/blocks`: `G05Batch`es, put (errors show in the status) or sent as a
//!   get's payload (answered with the status or an `ErrorReply`). Batches are express,
//!   real-time data: the producer decides their pace through the credits.
//! - `P/C/machine/M/g05/S/producer`: the producer's liveliness token; its loss ends the
//!   stream.

use std::sync::{Arc, Mutex, PoisonError};

use prost::Message;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use zenoh::qos::CongestionControl;
use zenoh::query::Query;
use zenoh::sample::{Sample, SampleKind};

use super::audit::{Audit, origin_of};
use super::context::{
    MachinePublisher, RequestError, RouteContext, Routed, Target, reply, reply_err,
};
use super::keys::{CellKey, G05Part, MachineLeaf};
use super::machine::Machine;
use super::payload::{encoding, g05_status};
use super::published::{MachinePublication, Published};
use super::write::{Done, Write};
use crate::link::g05::{STATUS_INTERVAL, StreamHandle, StreamStatus};
use cellgate_core::config::Permission;
use cellgate_core::fanuc::g05::AuxWord;
use cellgate_core::fanuc::g05::stream::{Batch, BlockIn, EndReason, G05Watch};
use cellgate_core::pb;

/// What the G05 rows share: the cell's context, and the tasks that publish each open
/// stream's status (aborted with the route, when the last clone of this goes).
#[derive(Clone)]
pub(crate) struct G05Context {
    pub(crate) route: RouteContext,
    stop: CancellationToken,
    followers: Arc<Mutex<JoinSet<()>>>,
}

impl Routed for G05Context {
    fn route(&self) -> &RouteContext {
        &self.route
    }
}

impl G05Context {
    /// The G05 rows' context; their streams' publishers stop with `stop`.
    pub(crate) fn new(route: RouteContext, stop: CancellationToken) -> Self {
        G05Context {
            route,
            stop,
            followers: Arc::new(Mutex::new(JoinSet::new())),
        }
    }
}

/// A get on `P/C/machine/M/g05`: with a `G05Open`, opens a stream and follows it; without a
/// payload (browsing the cell), the machines' current streams.
pub(super) async fn open_get(ctx: &G05Context, q: &Query) {
    if q.payload().is_none() {
        return current_streams(&ctx.route, q).await;
    }
    if let Some((machine, handle, token)) = open(&ctx.route, q).await {
        let follow = follow(ctx.route.clone(), machine, handle, token, ctx.stop.clone());
        let mut followers = ctx.followers.lock().unwrap_or_else(PoisonError::into_inner);
        while followers.try_join_next().is_some() {}
        followers.spawn(follow);
    }
}

/// A get on `P/C/machine/M/g05/S`.
pub(super) async fn status_get(ctx: &G05Context, q: &Query) {
    status(&ctx.route, q).await;
}

/// `P/C/machine/M/g05/S/blocks` (its write row, without a pool: batches are served in order
/// on the route's loop, since they are numbered and must not overtake one another): a put
/// or a get with a payload is a batch, the get answered with the status; a get without one
/// the status alone (never an empty batch 0, which would make the producer's real batch 0 a
/// repeat). A batch is not audited: the stream's opening was.
pub(super) async fn blocks_write(ctx: &G05Context, w: Write) -> Done<pb::G05Status, RequestError> {
    let outcome = match w.bytes() {
        None => stream_of(&ctx.route, w.key()).map(|h| g05_status(&h.status().borrow())),
        Some(p) => match w.checked() {
            Ok(()) => batch(&ctx.route, w.key(), &p).await,
            Err(e) => Err(e.into()),
        },
    };
    Done {
        audit: None,
        outcome: outcome.map(Some),
    }
}

/// A delete on `P/C/machine/M/g05/S` from another session cancels the stream.
pub(super) async fn status_delete(ctx: &G05Context, s: &Sample) {
    if s.kind() == SampleKind::Delete {
        cancel(&ctx.route, s).await;
    }
}

/// A get without payload on `P/C/machine/M/g05`: the status of each matching machine's
/// current (or last) stream.
async fn current_streams(ctx: &RouteContext, q: &Query) {
    for (_, m) in ctx.matching(q, MachineLeaf::G05) {
        if let Some(h) = m.g05.current() {
            let msg = g05_status(&h.status().borrow());
            reply(q, ctx.keys.leaf(m.name(), MachineLeaf::G05), &msg).await;
        }
    }
}

/// A get on `P/C/machine/M/g05`: opens a stream.
async fn open(
    ctx: &RouteContext,
    q: &Query,
) -> Option<(std::sync::Arc<Machine>, StreamHandle, bool)> {
    let result = async {
        ctx.history.audit_writable()?;
        let m = ctx.one_machine(q, MachineLeaf::G05, "G05Open")?;
        let payload = q
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        let request: pb::G05Open = ctx.decode(m.name(), &payload)?;
        let (handle, opened) = m.g05.open(Some(request.stream_id)).await?;
        let g = m.g05.config().map(|c| c.format());
        let reply_msg = pb::G05Opened {
            stream_id: opened.stream.clone(),
            block_len: opened.block_len,
            credits: opened.credits,
            window: opened.window,
            prime: opened.prime,
            unit_time_ms: opened.unit_time_ms,
            axes: g.map(|f| u32::from(f.axes)).unwrap_or_default(),
            aux: g.is_some_and(|f| f.aux.rax()),
            required_baud: opened.required_baud,
            actual_baud: opened.actual_baud,
        };
        Ok::<_, RequestError>((m, handle, reply_msg, request.producer_token))
    }
    .await;
    let machine = match ctx.keys.parse(q.key_expr().as_str()) {
        Some(CellKey::Leaf { machine, .. }) => machine.to_string(),
        _ => String::new(),
    };
    ctx.audit_answered(
        Audit {
            action: "g05.open",
            permission: Permission::G05Stream,
            key: q.key_expr().as_str(),
            machine: &machine,
            target: match &result {
                Ok((_, _, opened, _)) => opened.stream_id.clone(),
                Err(_) => machine.clone(),
            },
            detail: String::new(),
            origin: origin_of(q.attachment()),
        },
        result.as_ref().map(|_| ()),
    )
    .await;
    match result {
        Ok((m, handle, opened, token)) => {
            reply(q, q.key_expr().to_string(), &opened).await;
            Some((m, handle, token))
        }
        Err(e) => {
            reply_err(q, &e).await;
            None
        }
    }
}

/// Publishes a stream's status until it is over, and ends it if its producer's liveliness
/// token goes away.
async fn follow(
    ctx: RouteContext,
    machine: std::sync::Arc<Machine>,
    handle: StreamHandle,
    producer_token: bool,
    stop: CancellationToken,
) {
    let key = ctx.keys.g05(machine.name(), &handle.id, G05Part::Status);
    let producer_key = ctx.keys.g05(machine.name(), &handle.id, G05Part::Producer);
    let producer = if producer_token {
        match ctx
            .session
            .liveliness()
            .declare_subscriber(producer_key.as_str())
            .history(true)
            .await
        {
            Ok(s) => Some(s),
            Err(e) => {
                tracing::warn!(key = %producer_key, error = %e, "cannot watch the G05 producer's token");
                None
            }
        }
    } else {
        None
    };
    let publisher = ctx
        .session
        .declare_publisher(key.clone())
        .encoding(encoding::<pb::G05Status>())
        .congestion_control(Published::G05Status.congestion())
        .priority(Published::G05Status.priority())
        .await;
    let publisher = match publisher {
        Ok(p) => p,
        Err(e) => {
            tracing::warn!(%key, error = %e, "cannot publish the G05 stream's status");
            return;
        }
    };
    // Starvation and an idle end are alarms, not only status fields.
    let alarms = match MachinePublisher::declare(&ctx, machine.name(), MachinePublication::Alarm)
        .await
    {
        Ok(p) => Some(p),
        Err(e) => {
            tracing::warn!(stream = %handle.id, error = %e, "cannot publish the G05 stream's alarms");
            None
        }
    };
    let mut watch = G05Watch::new();
    let mut status = handle.status();
    let mut tick = tokio::time::interval(STATUS_INTERVAL);
    let mut producer_seen = false;
    loop {
        let now = status.borrow_and_update().clone();
        raise_alarms(&machine, alarms.as_ref(), &mut watch, &now).await;
        if now.is_over() {
            break;
        }
        if let Err(e) = publisher.put(g05_status(&now).encode_to_vec()).await {
            tracing::debug!(%key, error = %e, "G05 status not published");
        }
        tokio::select! {
            () = stop.cancelled() => break,
            _ = tick.tick() => {}
            changed = status.changed() => if changed.is_err() { break },
            s = async {
                match &producer {
                    Some(p) => p.recv_async().await.ok(),
                    None => std::future::pending().await,
                }
            } => match s {
                Some(s) if s.kind() == SampleKind::Put => producer_seen = true,
                Some(_) if producer_seen => {
                    tracing::warn!(stream = %handle.id, "G05 producer's token went away");
                    let _ = handle.end(EndReason::ProducerLost).await;
                }
                _ => {}
            },
        }
    }
    // The last word, reliably, and in the history.
    let last = g05_status(&status.borrow().clone());
    if status.borrow().is_over() {
        ctx.history.event(
            machine.name(),
            pb::HistoryKind::G05,
            pb::history_record::Record::G05(last.clone()),
        );
    }
    let sent = ctx
        .session
        .put(key.as_str(), last.encode_to_vec())
        .encoding(encoding::<pb::G05Status>())
        // The last word goes reliably, whatever the row says of the ones before it.
        .congestion_control(CongestionControl::Block)
        .priority(Published::G05Status.priority())
        .await;
    if let Err(e) = sent {
        tracing::warn!(%key, error = %e, "the G05 stream's last status was not published");
    }
}

/// Publishes the alarms a stream's status raises, on the machine's alarm key, and keeps the
/// latest in its status.
async fn raise_alarms(
    machine: &Machine,
    publisher: Option<&MachinePublisher<pb::AlarmEvent>>,
    watch: &mut G05Watch,
    status: &StreamStatus,
) {
    for alarm in watch.observe(crate::link::pump::now(), &status.figures) {
        tracing::warn!(stream = %status.stream, %alarm, "G05 alarm");
        let event = machine.alarm_event(
            pb::AlarmKind::G05,
            "",
            cellgate_core::codes::alarm::G05,
            format!("stream {}: {alarm}", status.stream),
        );
        machine.view().status.last_alarm = Some(event.clone());
        if let Some(p) = publisher {
            p.publish(&event).await;
        }
    }
}

/// The stream a `…/g05/S…` key names, or why none.
fn stream_of(ctx: &RouteContext, key: &str) -> Result<StreamHandle, RequestError> {
    let Some(CellKey::G05 {
        machine, stream, ..
    }) = ctx.keys.parse(key)
    else {
        return Err(RequestError::Invalid {
            machine: String::new(),
            what: format!("{key} is not a G05 stream's key"),
        });
    };
    let m = match ctx.target(&zenoh::key_expr::KeyExpr::try_from(key).map_err(|e| {
        RequestError::Invalid {
            machine: machine.to_string(),
            what: e.to_string(),
        }
    })?) {
        Target::One(m) => m,
        Target::Unknown(m) => return Err(ctx.unknown_machine(&m)),
        Target::Wild => {
            return Err(RequestError::Invalid {
                machine: machine.to_string(),
                what: "name one machine and one stream, without wildcards".to_string(),
            });
        }
    };
    m.g05
        .find(stream)
        .ok_or_else(|| RequestError::NoSuchStream {
            machine: machine.to_string(),
            stream: stream.to_string(),
        })
}

/// A batch on `P/C/machine/M/g05/S/blocks`.
async fn batch(
    ctx: &RouteContext,
    key: &str,
    payload: &[u8],
) -> Result<pb::G05Status, RequestError> {
    let handle = stream_of(ctx, key)?;
    // Sized before it is decoded (`cellgate_core::bounds`).
    let b: pb::G05Batch = ctx.decode(&handle.id, payload)?;
    let batch = Batch {
        seq: b.seq,
        blocks: b
            .blocks
            .into_iter()
            .map(|blk| BlockIn {
                travels: blk.travel,
                aux: blk.aux.map(AuxWord::significant),
            })
            .collect(),
        end: b.end,
    };
    handle.batch(batch).await?;
    Ok(g05_status(&handle.status().borrow()))
}

/// A get on `P/C/machine/M/g05/S`: the stream's latest status.
async fn status(ctx: &RouteContext, q: &Query) {
    if q.key_expr().is_wild() {
        // Every open (or last) stream the query takes in.
        for m in ctx.machines.now().values() {
            if let Some(h) = m.g05.current() {
                let key = ctx.keys.g05(m.name(), &h.id, G05Part::Status);
                if super::keys::intersects(q.key_expr(), &key) {
                    let msg = g05_status(&h.status().borrow());
                    reply(q, key, &msg).await;
                }
            }
        }
        return;
    }
    match stream_of(ctx, q.key_expr().as_str()) {
        Ok(h) => {
            let msg = g05_status(&h.status().borrow());
            reply(q, q.key_expr().to_string(), &msg).await;
        }
        Err(e) => reply_err(q, &e).await,
    }
}

/// A delete on `P/C/machine/M/g05/S` cancels the stream: the end block goes out.
async fn cancel(ctx: &RouteContext, sample: &Sample) {
    let key = sample.key_expr().as_str();
    let (machine, stream) = match ctx.keys.parse(key) {
        Some(CellKey::G05 {
            machine, stream, ..
        }) => (machine.to_string(), stream.to_string()),
        _ => (String::new(), String::new()),
    };
    let found = stream_of(ctx, key);
    ctx.audit(
        Audit {
            action: "g05.cancel",
            permission: Permission::G05Stream,
            key,
            machine: &machine,
            target: stream,
            detail: String::new(),
            origin: origin_of(sample.attachment()),
        },
        found.as_ref().map(|_| ()),
    );
    match found {
        Ok(h) => {
            tracing::info!(stream = %h.id, "G05 stream cancelled on the bus");
            let _ = h.end(EndReason::Cancelled).await;
        }
        Err(e) => tracing::warn!(key = %sample.key_expr(), error = %e, "G05 cancel refused"),
    }
}
