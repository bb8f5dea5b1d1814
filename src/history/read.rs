//! Reading the store: a page of a query, oldest or newest first, through the subject index
//! where the query names machines, kinds or tags; and the marks utilisation is computed from.

use prost::Message as _;

use super::{HISTORY, HistoryError, Inner, Log, MachineMarks, db_error, tag_subject};
use cellgate_core::history::{HistoryQuery, Mark, Order};
use cellgate_core::pb::{self, HistoryKind};

/// One page of `query`, oldest or newest first as it asks.
pub(super) fn read_page(
    inner: &Inner,
    log: Log,
    q: &HistoryQuery,
) -> Result<pb::HistoryPage, HistoryError> {
    let path = &inner.path;
    let e = |x: redb::Error| db_error(path, x);
    let t = log.tables();
    let tx = inner.db()?.begin_read().map_err(|x| e(x.into()))?;
    let records = tx.open_table(t.records).map_err(|x| e(x.into()))?;
    let newest = q.order == Order::Newest;
    // Paging: go on past the record numbered `after`, found by its number: after it oldest
    // first, before it newest first.
    let mut start = (q.from_ms, 0u64);
    let mut end = (q.to_ms, u64::MAX);
    if q.after > 0 {
        let seqs = tx.open_table(t.seqs).map_err(|x| e(x.into()))?;
        let ms = seqs
            .get(q.after)
            .map_err(|x| e(x.into()))?
            .ok_or(HistoryError::NoSuchRecord(q.after))?
            .value();
        if newest {
            end = end.min((ms, q.after.saturating_sub(1)));
        } else {
            start = start.max((ms, q.after.saturating_add(1)));
        }
    }
    if start > end {
        return Ok(page(q, Vec::new(), false));
    }
    let mut keys: Vec<(u64, u64)> = Vec::new();
    let want = q.limit + 1;
    // Through the index where the query names machines, kinds or tags; else in time order.
    let subjects = query_subjects(q, log);
    if let Some(subjects) = subjects {
        let subj = tx.open_table(t.subjects).map_err(|x| e(x.into()))?;
        for s in subjects {
            let range = (s.as_str(), start.0, start.1)..=(s.as_str(), end.0, end.1);
            let items = subj.range(range).map_err(|x| e(x.into()))?;
            let items: Box<dyn Iterator<Item = _>> = match newest {
                true => Box::new(items.rev()),
                false => Box::new(items),
            };
            for item in items.take(want) {
                let (k, _) = item.map_err(|x| e(x.into()))?;
                let (_, ms, seq) = k.value();
                keys.push((ms, seq));
            }
        }
        keys.sort_unstable();
        keys.dedup();
        if newest {
            keys.reverse();
        }
    }
    let mut out = Vec::new();
    let mut more = false;
    let mut take = |bytes: &[u8]| -> bool {
        let Ok(r) = pb::HistoryRecord::decode(bytes) else {
            return true;
        };
        if !q.takes(&r) {
            return true;
        }
        if out.len() == q.limit {
            more = true;
            return false;
        }
        out.push(r);
        true
    };
    match subjects_used(q, log) {
        true => {
            for k in keys {
                if let Some(v) = records.get(k).map_err(|x| e(x.into()))?
                    && !take(v.value())
                {
                    break;
                }
            }
        }
        false => {
            let items = records.range(start..=end).map_err(|x| e(x.into()))?;
            let items: Box<dyn Iterator<Item = _>> = match newest {
                true => Box::new(items.rev()),
                false => Box::new(items),
            };
            for item in items {
                let (_, v) = item.map_err(|x| e(x.into()))?;
                if !take(v.value()) {
                    break;
                }
            }
        }
    }
    Ok(page(q, out, more))
}

/// A page of `records`; `next_after` the last one's number when more follow.
fn page(q: &HistoryQuery, records: Vec<pb::HistoryRecord>, more: bool) -> pb::HistoryPage {
    let next_after = if more {
        records.last().map_or(0, |r| r.seq)
    } else {
        0
    };
    pb::HistoryPage {
        records,
        more,
        next_after,
        from_unix_ms: q.from_ms,
        to_unix_ms: q.to_ms,
    }
}

fn subjects_used(q: &HistoryQuery, log: Log) -> bool {
    query_subjects(q, log).is_some()
}

/// The index subjects a query reads, or `None` to read the records in time order.
fn query_subjects(q: &HistoryQuery, log: Log) -> Option<Vec<String>> {
    if !q.tags.is_empty() && q.kinds.as_ref().is_some_and(|k| k.len() == 1) {
        return Some(
            q.tags
                .iter()
                .filter_map(|t| t.split_once('/'))
                .map(|(p, n)| tag_subject(p, n))
                .collect(),
        );
    }
    let kinds: Option<Vec<i32>> = q.kinds.as_ref().map(|k| k.iter().copied().collect());
    match (&q.machines, kinds) {
        (Some(machines), Some(kinds)) => Some(
            machines
                .iter()
                .flat_map(|m| kinds.iter().map(move |k| format!("{m}/{k}")))
                .collect(),
        ),
        (Some(machines), None) => {
            let all: Vec<i32> = match log {
                Log::Audit => vec![HistoryKind::Audit as i32],
                Log::History => (1..=8).collect(),
            };
            Some(
                machines
                    .iter()
                    .flat_map(|m| all.iter().map(move |k| format!("{m}/{k}")))
                    .collect(),
            )
        }
        (None, Some(kinds)) => Some(kinds.iter().map(|k| format!("#{k}")).collect()),
        (None, None) => None,
    }
}

pub(super) fn read_gateway_marks(
    inner: &Inner,
    from_ms: u64,
    to_ms: u64,
) -> Result<Vec<Mark>, HistoryError> {
    use pb::gateway_record::Event;
    let subject = format!("/{}", HistoryKind::Gateway as i32);
    Ok(read_subject(inner, &subject, from_ms, to_ms)?
        .into_iter()
        .map(
            |(t, v)| match i32::try_from(v).ok().and_then(|e| Event::try_from(e).ok()) {
                Some(Event::Started) => Mark::Started(t),
                Some(Event::Stopped) => Mark::Stopped(t),
                _ => Mark::Alive(t),
            },
        )
        .collect())
}

/// The (time, summary) of index subject `subject`'s entries in `[from, to]`, with the last
/// one before `from` first: the index alone, no record read.
fn read_subject(
    inner: &Inner,
    subject: &str,
    from_ms: u64,
    to_ms: u64,
) -> Result<Vec<(u64, u64)>, HistoryError> {
    let path = &inner.path;
    let e = |x: redb::Error| db_error(path, x);
    let tx = inner.db()?.begin_read().map_err(|x| e(x.into()))?;
    let subj = tx.open_table(HISTORY.subjects).map_err(|x| e(x.into()))?;
    let mut out = Vec::new();
    let before = subj
        .range((subject, 0u64, 0u64)..(subject, from_ms, 0u64))
        .map_err(|x| e(x.into()))?
        .next_back();
    if let Some(item) = before {
        let (k, v) = item.map_err(|x| e(x.into()))?;
        out.push((k.value().1, v.value()));
    }
    for item in subj
        .range((subject, from_ms, 0u64)..=(subject, to_ms, u64::MAX))
        .map_err(|x| e(x.into()))?
    {
        let (k, v) = item.map_err(|x| e(x.into()))?;
        out.push((k.value().1, v.value()));
    }
    Ok(out)
}

pub(super) fn read_marks(
    inner: &Inner,
    machine: &str,
    counter: Option<&str>,
    from_ms: u64,
    to_ms: u64,
) -> Result<MachineMarks, HistoryError> {
    let read = |subject: &str| read_subject(inner, subject, from_ms, to_ms);
    let marks = read(&format!("{machine}/{}", HistoryKind::Cnc as i32))?
        .into_iter()
        .map(|(t, v)| {
            let a = i32::try_from(v)
                .ok()
                .and_then(|a| pb::MachineActivity::try_from(a).ok())
                .unwrap_or(pb::MachineActivity::Unspecified);
            Mark::Activity(t, a)
        })
        .collect();
    let jobs = read(&format!("{machine}/{}", HistoryKind::Job as i32))?
        .into_iter()
        .filter(|(t, _)| *t >= from_ms)
        .map(|(t, v)| (t, v == 1))
        .collect();
    let mut parts = Vec::new();
    if let Some(counter) = counter
        && let Some((plc, name)) = counter.split_once('/')
    {
        parts = read(&tag_subject(plc, name))?
            .into_iter()
            .map(|(t, v)| (t, f64::from_bits(v)))
            .filter(|(_, v)| !v.is_nan())
            .collect();
    }
    Ok(MachineMarks { marks, jobs, parts })
}
