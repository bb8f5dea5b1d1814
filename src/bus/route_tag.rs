//! Named PLC tags on the bus (`[[plcs.tags]]`): `P/C/plc/L/tag/NAME`.
//!
//! - Each change (past the tag's deadband, or of its quality) is published there as a
//!   `TagValue`, reliable with `Block`: with publish-on-change a lost sample would leave
//!   subscribers on an old value until the next change.
//! - A get answers the latest `TagValue` (value, time stamp, quality); a wildcard get answers
//!   every tag it matches.
//! - `P/C/plc/L/tag/NAME/set`, the write's own key: a get with a `TagWrite` writes the tag
//!   (scale undone, range checked) and answers `TagWritten` once the module confirmed; a put
//!   with one writes it unanswered. A write to a read-only tag is refused
//!   (`ERROR_CODE_NOT_SUPPORTED`) and never reaches the PLC. A role that reads tags can never
//!   write one.

use tokio::sync::broadcast::error::RecvError;
use tokio_util::sync::CancellationToken;
use zenoh::query::Query;

use super::context::{reply, reply_err};
use super::keys::{PlcKey, intersects};
use super::payload::tag_message;
use super::published::Published;
use super::route_plc::{PlcContext, PlcLink, PlcRequestError};
use super::write::{Audited, Done, Write};
use crate::plc::PlcEvent;
use cellgate_core::pb;
use prost::Message as _;

/// The PLC and tag a key names, and whether it is the tag's write key (`…/set`).
fn tag_target<'k>(
    ctx: &PlcContext,
    key: &'k str,
) -> Result<(&'k str, &'k str, bool), PlcRequestError> {
    match ctx.route.keys.parse_plc(key) {
        Some(PlcKey::Tag { plc, name, set }) => {
            ctx.plc(plc)?;
            Ok((plc, name, set))
        }
        _ => Err(PlcRequestError::BadKey {
            key: key.to_string(),
            what: "not a tag key".to_string(),
            expected: "P/C/plc/L/tag/NAME to read, P/C/plc/L/tag/NAME/set to write",
        }),
    }
}

async fn write_tag(
    ctx: &PlcContext,
    key: &str,
    bytes: &[u8],
) -> Result<pb::TagWritten, PlcRequestError> {
    let (plc, name, set) = tag_target(ctx, key)?;
    if !set {
        return Err(PlcRequestError::BadKey {
            key: key.to_string(),
            what: "a tag is written on its own key".to_string(),
            expected: "P/C/plc/L/tag/NAME/set",
        });
    }
    let w: pb::TagWrite = super::route_plc::decode_payload(plc, bytes)?;
    let link = ctx.plc(plc)?;
    let written =
        link.link
            .write_tag(name, w.value)
            .await?
            .map_err(|error| PlcRequestError::TagWrite {
                plc: plc.to_string(),
                error,
            })?;
    // What the tag now reads as, rounded to its scale, not what was asked.
    Ok(pb::TagWritten {
        plc: plc.to_string(),
        name: name.to_string(),
        value: written.value(),
    })
}

/// A `TagWrite` on `P/C/plc/L/tag/NAME/set` (its write row): writes the tag and answers
/// `TagWritten`, the value the tag now reads as, once the module confirmed.
pub(super) async fn tag_write(ctx: &PlcContext, w: Write) -> Done<pb::TagWritten, PlcRequestError> {
    let Some(bytes) = w.bytes() else {
        return Done::refused(PlcRequestError::BadKey {
            key: w.key().to_string(),
            what: "a get here writes the tag and needs a TagWrite".to_string(),
            expected: "P/C/plc/L/tag/NAME to read the tag",
        });
    };
    let written = match w.checked() {
        Ok(()) => write_tag(ctx, w.key(), &bytes).await,
        Err(e) => Err(e.into()),
    };
    let (plc, name) = match tag_target(ctx, w.key()) {
        Ok((p, n, _)) => (p.to_string(), n.to_string()),
        Err(_) => (String::new(), w.key().to_string()),
    };
    let detail = match &written {
        Ok(t) => format!("value {}", t.value),
        Err(_) => pb::TagWrite::decode(bytes.as_ref())
            .map(|t| format!("value {}", t.value))
            .unwrap_or_default(),
    };
    let audited = Audited {
        action: "plc.tag",
        target: format!("{plc}/{name}"),
        machine: plc,
        detail,
    };
    Done::audited(audited, written)
}

/// A get on `P/C/plc/L/tag/NAME`: the tag's latest value.
pub(super) async fn tag_query(ctx: &PlcContext, q: &Query) {
    let key = q.key_expr().to_string();
    if q.payload().is_some() {
        let e = PlcRequestError::BadKey {
            key,
            what: "a get here reads the tag and takes no payload".to_string(),
            expected: "P/C/plc/L/tag/NAME/set for a TagWrite",
        };
        return reply_err(q, &e).await;
    }
    if !q.key_expr().is_wild() {
        let result = match tag_target(ctx, &key) {
            Ok((plc, name, _)) => match ctx.plc(plc) {
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
    for link in ctx.plcs.now().values() {
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

/// Publishes a PLC link's tag changes until `stop`.
pub(crate) async fn publish_tags(ctx: PlcContext, link: PlcLink, stop: CancellationToken) {
    let mut events = link.link.subscribe();
    let plc = link.config.name.clone();
    // The tags whose values the history keeps.
    let kept: std::collections::BTreeSet<String> = link
        .config
        .tags
        .iter()
        .filter(|t| t.history)
        .map(|t| t.name.clone())
        .collect();
    loop {
        tokio::select! {
            () = stop.cancelled() => break,
            ev = events.recv() => match ev {
                Ok(PlcEvent::Tag(v)) => {
                    let key = ctx.route.keys.plc_tag(&plc, &v.name);
                    let message = tag_message(&plc, &v);
                    if kept.contains(&v.name) {
                        ctx.route.history.event(
                            &plc,
                            pb::HistoryKind::Tag,
                            pb::history_record::Record::Tag(message.clone()),
                        );
                    }
                    ctx.publish(Published::TagValue, key, &message).await;
                }
                Ok(PlcEvent::Stopped { .. }) | Err(RecvError::Closed) => break,
                Ok(_) => {}
                Err(RecvError::Lagged(n)) => tracing::warn!(%plc, missed = n, "tag changes lagged"),
            }
        }
    }
}
