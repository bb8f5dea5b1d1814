//! Named PLC tags on the bus (`[[plcs.tags]]`): `P/C/plc/L/tag/NAME`.
//!
//! - Each change (past the tag's deadband, or of its quality) is published there as a
//!   `TagValue`, reliable with `Block`: with publish-on-change a lost sample would leave
//!   subscribers on an old value until the next change.
//! - A get answers the latest `TagValue` (value, time stamp, quality); a wildcard get answers
//!   every tag it matches.
//! - A get with a `TagWrite` writes the tag (scale undone, range checked) and answers
//!   `TagWritten` once the module confirmed; a put with one writes it unanswered. A write to
//!   a read-only tag is refused (`ERROR_CODE_NOT_SUPPORTED`) and never reaches the PLC.

use tokio::sync::broadcast::error::RecvError;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::qos::CongestionControl;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Locality, Sample, SampleKind};

use super::BusError;
use super::context::{reply, reply_err};
use super::keys::{PlcArea, PlcKey, intersects};
use super::payload::{BusMessage, schema_of};
use super::route_plc::{PlcContext, PlcLink, PlcRequestError, unix_ms};
use crate::pb;
use crate::plc::{PlcEvent, Quality, TagValue};

/// A tag's value as a message.
pub(crate) fn tag_message(plc: &str, v: &TagValue) -> pb::TagValue {
    pb::TagValue {
        plc: plc.to_string(),
        name: v.name.clone(),
        value: v.value,
        raw: v.raw,
        unix_ms: v.time.map(unix_ms),
        quality: match v.quality {
            Quality::Good => pb::TagQuality::Good,
            Quality::Stale => pb::TagQuality::Stale,
            Quality::StationDown => pb::TagQuality::StationDown,
        } as i32,
        writable: v.writable,
    }
}

/// The tag queryable and the subscriber for tag writes. Undeclared when dropped.
pub(crate) struct TagRoute {
    get: Queryable<FifoChannelHandler<Query>>,
    puts: Subscriber<FifoChannelHandler<Sample>>,
}

impl TagRoute {
    pub async fn declare(ctx: &PlcContext) -> Result<Self, BusError> {
        let key = ctx.route.keys.any_plc_area(PlcArea::Tag);
        Ok(TagRoute {
            get: ctx.route.queryable(key.clone()).await?,
            // Remote only: the gateway's own TagValue publications are not writes.
            puts: ctx.route.subscriber(key, Locality::Remote).await?,
        })
    }

    pub async fn run(self, ctx: PlcContext, stop: CancellationToken) {
        let mut tasks = JoinSet::new();
        loop {
            tokio::select! {
                () = stop.cancelled() => break,
                q = self.get.recv_async() => match q {
                    Ok(q) => {
                        let c = ctx.clone();
                        ctx.route.spawn_query(&mut tasks, q, |q| async move { tag_query(&c, &q).await }).await;
                    }
                    Err(_) => break,
                },
                s = self.puts.recv_async() => match s {
                    Ok(s) => {
                        let c = ctx.clone();
                        ctx.route.spawn_sample(&mut tasks, s, |s| async move {
                            if let Err(e) = tag_put(&c, &s).await {
                                tracing::warn!(key = %s.key_expr(), error = %e, "tag write refused");
                            }
                        });
                    }
                    Err(_) => break,
                },
                Some(_) = tasks.join_next() => {}
            }
        }
        tasks.shutdown().await;
    }
}

fn tag_target<'k>(ctx: &PlcContext, key: &'k str) -> Result<(&'k str, &'k str), PlcRequestError> {
    match ctx.route.keys.parse_plc(key) {
        Some(PlcKey::Tag { plc, name }) => {
            ctx.plc(plc)?;
            Ok((plc, name))
        }
        _ => Err(PlcRequestError::BadKey {
            key: key.to_string(),
            what: "not a tag key".to_string(),
            expected: "P/C/plc/L/tag/NAME",
        }),
    }
}

async fn write_tag(
    ctx: &PlcContext,
    key: &str,
    bytes: &[u8],
) -> Result<pb::TagWritten, PlcRequestError> {
    let (plc, name) = tag_target(ctx, key)?;
    let w: pb::TagWrite =
        prost::Message::decode(bytes).map_err(|error| PlcRequestError::Payload {
            plc: plc.to_string(),
            message: "TagWrite",
            error,
        })?;
    let link = ctx.plc(plc)?;
    link.link
        .write_tag(name, w.value)
        .await?
        .map_err(|error| PlcRequestError::TagWrite {
            plc: plc.to_string(),
            error,
        })?;
    Ok(pb::TagWritten {
        plc: plc.to_string(),
        name: name.to_string(),
        value: w.value,
    })
}

async fn tag_query(ctx: &PlcContext, q: &Query) {
    let key = q.key_expr().to_string();
    if let Some(payload) = q.payload().map(|p| p.to_bytes().to_vec()) {
        match write_tag(ctx, &key, &payload).await {
            Ok(w) => reply(q, key, &w).await,
            Err(e) => reply_err(q, &e).await,
        }
        return;
    }
    if !q.key_expr().is_wild() {
        let result = match tag_target(ctx, &key) {
            Ok((plc, name)) => match ctx.plc(plc) {
                Ok(link) => match link.link.get_tag(name).await {
                    Ok(Ok(v)) => Ok(tag_message(plc, &v)),
                    Ok(Err(e)) => Err(PlcRequestError::from(e)),
                    Err(e) => Err(PlcRequestError::from(e)),
                },
                Err(e) => Err(e),
            },
            Err(e) => Err(e),
        };
        match result {
            Ok(v) => reply(q, key, &v).await,
            Err(e) => reply_err(q, &e).await,
        }
        return;
    }
    for link in ctx.plcs.values() {
        let plc = &link.config.name;
        let Ok(snap) = link.link.snapshot().await else {
            continue;
        };
        for t in &snap.tags {
            let k = ctx.route.keys.plc_tag(plc, &t.name);
            if intersects(q.key_expr(), &k) {
                reply(q, k, &tag_message(plc, t)).await;
            }
        }
    }
}

async fn tag_put(ctx: &PlcContext, s: &Sample) -> Result<(), PlcRequestError> {
    // Only TagWrites are writes; anything else published here is not for the gateway.
    if s.kind() != SampleKind::Put
        || schema_of(s.encoding()).as_deref() != Some(pb::TagWrite::SCHEMA)
    {
        return Ok(());
    }
    write_tag(ctx, s.key_expr().as_str(), &s.payload().to_bytes())
        .await
        .map(|_| ())
}

/// Publishes a PLC link's tag changes until `stop`.
pub(crate) async fn publish_tags(ctx: PlcContext, link: PlcLink, stop: CancellationToken) {
    let mut events = link.link.subscribe();
    let plc = link.config.name.clone();
    loop {
        tokio::select! {
            () = stop.cancelled() => break,
            ev = events.recv() => match ev {
                Ok(PlcEvent::Tag(v)) => {
                    let key = ctx.route.keys.plc_tag(&plc, &v.name);
                    ctx.publish(key, &tag_message(&plc, &v), CongestionControl::Block).await;
                }
                Ok(PlcEvent::Stopped { .. }) | Err(RecvError::Closed) => break,
                Ok(_) => {}
                Err(RecvError::Lagged(n)) => tracing::warn!(%plc, missed = n, "tag changes lagged"),
            }
        }
    }
}
