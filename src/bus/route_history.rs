//! The cell's history, audit trail and utilisation, read with a get.
//!
//! - `P/C/history` (`history.read`): a `HistoryPage` of history records;
//! - `P/C/audit` (`audit.read`): a `HistoryPage` of audit records;
//! - `P/C/utilisation` (`history.read`): `Utilisation`, time shares per machine and bucket.
//!
//! Selector parameters as `history.proto` lists them; `_time` is read with zenoh's own
//! time-range parser, so it means what it means to zenoh's storages.

use std::time::SystemTime;

use zenoh::query::Query;
use zenoh_util::time_range::{TimeBound, TimeRange};

use super::context::{CellNames, RequestError, RouteContext, reply, reply_err};
use crate::history::Log;
use cellgate_core::history::{self, HistoryQuery, Store};
use cellgate_core::pb;

/// The longest range utilisation divides into buckets: 92 days.
const MAX_UTILISATION_MS: u64 = 92 * 24 * 3600 * 1000;

/// A `_time` value as an inclusive range of ms, with zenoh's parser; an open end is the
/// epoch or now.
pub(crate) fn time_range(value: &str, now: SystemTime) -> Result<(u64, u64), String> {
    let range: TimeRange = value.parse().map_err(|e| format!("{e}"))?;
    let range = range.resolve_at(now);
    let from = match range.start {
        TimeBound::Inclusive(t) => pb::unix_ms(t),
        TimeBound::Exclusive(t) => pb::unix_ms(t).saturating_add(1),
        TimeBound::Unbounded => 0,
    };
    let to = match range.end {
        TimeBound::Inclusive(t) => pb::unix_ms(t),
        TimeBound::Exclusive(t) => pb::unix_ms(t).saturating_sub(1),
        TimeBound::Unbounded => pb::unix_ms(now),
    };
    Ok((from, to))
}

fn parse(q: &Query, store: Store) -> Result<HistoryQuery, RequestError> {
    let now = SystemTime::now();
    let params = q.parameters();
    Ok(HistoryQuery::parse(
        store,
        params.iter(),
        |v| time_range(v, now),
        pb::unix_ms(now),
    )?)
}

/// A page of the cell's history.
pub(super) async fn history_page(ctx: &RouteContext, q: &Query) {
    page(ctx, q, Store::History).await
}

/// A page of the audit trail.
pub(super) async fn audit_page(ctx: &RouteContext, q: &Query) {
    page(ctx, q, Store::Audit).await
}

async fn page(ctx: &RouteContext, q: &Query, store: Store) {
    // A wildcard get (browsing `P/C/**`) is not a question for the records.
    if q.key_expr().is_wild() {
        return;
    }
    if q.payload().is_some() {
        let e = RequestError::WrongKey(format!(
            "a get on {} reads and takes no payload: say what to read in its selector \
             parameters (_time, machine, kind, tag, limit, after)",
            q.key_expr()
        ));
        return reply_err(q, &e).await;
    }
    let query = match parse(q, store) {
        Ok(x) => x,
        Err(e) => return reply_err(q, &e).await,
    };
    // A name the cell does not have would read as "no records": say so instead.
    let names = ctx.names.now();
    let unknown = query
        .machines
        .as_ref()
        .and_then(|m| CellNames::unknown(&names.links, m.iter().filter(|n| !n.is_empty())))
        .map(|(n, known)| {
            RequestError::UnknownLink(format!(
                "the cell has no machine or PLC {n:?}; it has: {known}"
            ))
        })
        .or_else(|| {
            CellNames::unknown(&names.tags, &query.tags).map(|(n, known)| {
                RequestError::UnknownTag(format!("the cell has no tag {n:?}; it has: {known}"))
            })
        });
    if let Some(e) = unknown {
        return reply_err(q, &e).await;
    }
    let log = if store == Store::Audit {
        Log::Audit
    } else {
        Log::History
    };
    match ctx.history.query(log, query).await {
        Ok(page) => reply(q, q.key_expr().to_string(), &page).await,
        Err(e) => reply_err(q, &RequestError::from(e)).await,
    }
}

/// A get with an `AuditRecord` on `P/C/audit/note`: a console adds a request it refused
/// its own user. Kept as the console said it, with the roles that may add notes; answered
/// with the record as kept.
pub(super) async fn note(ctx: &RouteContext, q: &Query) {
    if q.key_expr().is_wild() {
        return;
    }
    let Some(payload) = q.payload() else {
        let e = RequestError::WrongKey(format!(
            "a get on {} adds an AuditRecord and needs one",
            q.key_expr()
        ));
        return reply_err(q, &e).await;
    };
    let mut record = match cellgate_core::bounds::decode::<pb::AuditRecord>(
        payload.to_bytes().as_ref(),
        &ctx.limits(),
    ) {
        Ok(r) => r,
        Err(error) => {
            let e = RequestError::WrongKey(format!("AuditRecord: {error}"));
            return reply_err(q, &e).await;
        }
    };
    if !ctx.history.enabled() {
        return reply_err(
            q,
            &RequestError::from(crate::history::HistoryError::Disabled),
        )
        .await;
    }
    // What the console says is kept as its note: the roles and principal are the gateway's
    // own reading of who could have sent it.
    record.action = format!("note:{}", record.action);
    let machine = match ctx.keys.parse(&record.key) {
        Some(
            crate::bus::keys::CellKey::Leaf { machine, .. }
            | crate::bus::keys::CellKey::JobEvents { machine, .. }
            | crate::bus::keys::CellKey::JobCancel { machine, .. },
        ) => machine.to_string(),
        _ => String::new(),
    };
    ctx.audit_note(
        super::audit::Audit {
            action: "audit.note",
            permission: cellgate_core::config::Permission::AuditNote,
            key: q.key_expr().as_str(),
            machine: &machine,
            target: record.target.clone(),
            detail: format!("{}: {}", record.action, record.detail),
            origin: record.origin.clone(),
        },
        Err::<(), _>(&RequestError::NotPermitted(record.error.clone())),
        record.count,
    );
    reply(q, q.key_expr().to_string(), &record).await;
}

pub(super) async fn utilisation(ctx: &RouteContext, q: &Query) {
    if q.key_expr().is_wild() {
        return;
    }
    match utilisation_of(ctx, q).await {
        Ok(u) => reply(q, q.key_expr().to_string(), &u).await,
        Err(e) => reply_err(q, &e).await,
    }
}

async fn utilisation_of(ctx: &RouteContext, q: &Query) -> Result<pb::Utilisation, RequestError> {
    if q.payload().is_some() {
        return Err(RequestError::WrongKey(format!(
            "a get on {} reads and takes no payload: say what to read in its selector \
             parameters (_time, machine, bucket)",
            q.key_expr()
        )));
    }
    let query = parse(q, Store::Utilisation)?;
    if query.to_ms.saturating_sub(query.from_ms) > MAX_UTILISATION_MS {
        return Err(RequestError::WrongKey(format!(
            "utilisation over more than {} days at once: ask for a shorter _time range",
            MAX_UTILISATION_MS / (24 * 3600 * 1000)
        )));
    }
    if !ctx.history.enabled() {
        return Err(crate::history::HistoryError::Disabled.into());
    }
    if let Some(names) = &query.machines
        && let Some(unknown) = names.iter().find(|n| !ctx.machines.now().contains_key(*n))
    {
        return Err(ctx.unknown_machine(unknown));
    }
    let buckets = history::buckets(
        query.from_ms,
        query.to_ms,
        query.bucket,
        &ctx.history.shifts(),
    );
    let now = pb::now_ms();
    let gateway = ctx
        .history
        .gateway_marks(query.from_ms, query.to_ms)
        .await?;
    let mut machines = Vec::new();
    for m in ctx.machines.now().values() {
        if query
            .machines
            .as_ref()
            .is_some_and(|s| !s.contains(m.name()))
        {
            continue;
        }
        let counter = m.config.part_counter.clone();
        let marks = ctx
            .history
            .machine_marks(
                m.name().to_string(),
                counter.clone(),
                query.from_ms,
                query.to_ms,
            )
            .await?;
        let mut all = gateway.clone();
        all.extend(marks.marks);
        crate::history::sort_marks(&mut all);
        machines.push(pb::MachineUtilisation {
            machine: m.name().to_string(),
            buckets: history::utilisation(
                &all,
                &marks.jobs,
                &marks.parts,
                counter.is_some(),
                &buckets,
                now,
            ),
            part_counter: counter.unwrap_or_default(),
        });
    }
    Ok(pb::Utilisation {
        machines,
        bucket: match query.bucket {
            history::Bucket::Hour => "hour",
            history::Bucket::Shift => "shift",
        }
        .to_string(),
        from_unix_ms: query.from_ms,
        to_unix_ms: query.to_ms,
    })
}

#[cfg(test)]
mod tests;
