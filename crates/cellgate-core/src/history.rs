//! The cell's history, sans-IO: what a history or audit query asks (its selector
//! parameters), which records it takes, what a machine is doing as the remote buffer tells
//! it, and utilisation computed from the records.
//!
//! The store (a database, its batching and retention) is the gateway's; the `_time`
//! parameter is read there with zenoh's own time-range parser, so this module gets the range
//! resolved to milliseconds.

pub mod refusals;

use std::collections::BTreeSet;

use crate::pb;
use crate::pb::HistoryKind;

/// Records a page holds by default.
pub const DEFAULT_LIMIT: usize = 1000;
/// Records a page holds at most.
pub const MAX_LIMIT: usize = 10_000;
/// The range read when a query names none: the last 24 hours.
pub const DEFAULT_RANGE_MS: u64 = 24 * 3600 * 1000;
/// How often the gateway records that it is alive; utilisation takes a longer silence
/// before a start for time the gateway was not running.
pub const ALIVE_EVERY_MS: u64 = 60_000;

/// What a history, audit or utilisation query asks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HistoryQuery {
    /// Milliseconds since the Unix epoch, both inclusive.
    pub from_ms: u64,
    /// See `from_ms`.
    pub to_ms: u64,
    /// Machines or PLC links; `None`: all.
    pub machines: Option<BTreeSet<String>>,
    /// Kinds; `None`: all but tag values (history), audit records (audit).
    pub kinds: Option<BTreeSet<i32>>,
    /// Tags (`PLC/NAME`) whose values are asked for.
    pub tags: BTreeSet<String>,
    /// Records a page holds.
    pub limit: usize,
    /// Only records after this `seq` in the page's order: later ones oldest first, earlier
    /// ones newest first (the page's `next_after` reads on either way).
    pub after: u64,
    /// Which end of the range a page starts at.
    pub order: Order,
    /// Utilisation buckets.
    pub bucket: Bucket,
}

/// Which end of the range a history or audit page starts at (`order=`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Order {
    /// The oldest record first (`order=oldest`, the default): a log read on as it grows.
    #[default]
    Oldest,
    /// The newest record first (`order=newest`): what just happened, at the top of a page.
    Newest,
}

/// How utilisation divides time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Bucket {
    /// Whole UTC hours.
    #[default]
    Hour,
    /// The shifts of `[history] shifts`.
    Shift,
}

/// A selector parameter that cannot be taken.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ParamError {
    /// A parameter the query does not know.
    #[error("unknown parameter {name:?}; {takes}")]
    Unknown {
        /// The parameter.
        name: String,
        /// What the query takes.
        takes: &'static str,
    },
    /// A value that cannot be read.
    #[error("parameter {name}={value:?}: {reason}")]
    Value {
        /// The parameter.
        name: &'static str,
        /// Its value.
        value: String,
        /// Why it is refused.
        reason: String,
    },
}

impl crate::codes::BusCode for ParamError {
    fn code(&self) -> pb::ErrorCode {
        pb::ErrorCode::InvalidRequest
    }
}

/// Which store a query reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Store {
    /// `P/C/history`.
    History,
    /// `P/C/audit`.
    Audit,
    /// `P/C/utilisation`.
    Utilisation,
}

/// The kind of a `kind` parameter's name.
pub fn kind_by_name(name: &str) -> Option<HistoryKind> {
    Some(match name {
        "job" => HistoryKind::Job,
        "alarm" => HistoryKind::Alarm,
        "link" => HistoryKind::Link,
        "cnc" => HistoryKind::Cnc,
        "station" => HistoryKind::Station,
        "g05" => HistoryKind::G05,
        "tag" => HistoryKind::Tag,
        "gateway" => HistoryKind::Gateway,
        "punch" => HistoryKind::Punch,
        "audit" => HistoryKind::Audit,
        _ => return None,
    })
}

/// The name [`kind_by_name`] reads.
pub fn kind_name(kind: HistoryKind) -> &'static str {
    match kind {
        HistoryKind::Unspecified => "unspecified",
        HistoryKind::Job => "job",
        HistoryKind::Alarm => "alarm",
        HistoryKind::Link => "link",
        HistoryKind::Cnc => "cnc",
        HistoryKind::Station => "station",
        HistoryKind::G05 => "g05",
        HistoryKind::Tag => "tag",
        HistoryKind::Gateway => "gateway",
        HistoryKind::Punch => "punch",
        HistoryKind::Audit => "audit",
    }
}

impl HistoryQuery {
    /// Reads a query's parameters. `time` resolves a `_time` value to an inclusive range in
    /// ms (or says why it cannot); without `_time` the range is the last 24 hours before
    /// `now_ms`.
    pub fn parse<'a>(
        store: Store,
        params: impl IntoIterator<Item = (&'a str, &'a str)>,
        time: impl Fn(&str) -> Result<(u64, u64), String>,
        now_ms: u64,
    ) -> Result<Self, ParamError> {
        let mut q = HistoryQuery {
            from_ms: now_ms.saturating_sub(DEFAULT_RANGE_MS),
            to_ms: now_ms,
            machines: None,
            kinds: None,
            tags: BTreeSet::new(),
            limit: DEFAULT_LIMIT,
            after: 0,
            order: Order::Oldest,
            bucket: Bucket::Hour,
        };
        let value = |name: &'static str, v: &str, reason: String| ParamError::Value {
            name,
            value: v.chars().take(200).collect(),
            reason,
        };
        for (name, v) in params {
            match name {
                "_time" => {
                    let (from, to) = time(v).map_err(|r| value("_time", v, r))?;
                    if from > to {
                        return Err(value("_time", v, "the range is empty".to_string()));
                    }
                    (q.from_ms, q.to_ms) = (from, to);
                }
                "machine" => {
                    let set: BTreeSet<String> = list(v).map(str::to_string).collect();
                    if set.is_empty() {
                        return Err(value("machine", v, "names no machine".to_string()));
                    }
                    q.machines = Some(set);
                }
                "kind" if store != Store::Utilisation => {
                    let mut set = BTreeSet::new();
                    for k in list(v) {
                        let kind = kind_by_name(k)
                            .filter(|k| (*k == HistoryKind::Audit) == (store == Store::Audit))
                            .ok_or_else(|| {
                                value(
                                    "kind",
                                    v,
                                    format!(
                                        "{k:?} is not a kind of this store; the kinds are {}",
                                        if store == Store::Audit {
                                            "audit"
                                        } else {
                                            "job, alarm, link, cnc, station, g05, tag, gateway, punch"
                                        }
                                    ),
                                )
                            })?;
                        set.insert(kind as i32);
                    }
                    if set.is_empty() {
                        return Err(value("kind", v, "names no kind".to_string()));
                    }
                    q.kinds = Some(set);
                }
                "tag" if store == Store::History => {
                    for t in list(v) {
                        if t.split('/').count() != 2 || t.split('/').any(str::is_empty) {
                            return Err(value("tag", v, format!("{t:?} is not PLC/NAME")));
                        }
                        q.tags.insert(t.to_string());
                    }
                }
                "limit" if store != Store::Utilisation => {
                    let n: usize = v
                        .parse()
                        .map_err(|_| value("limit", v, "not a whole number".to_string()))?;
                    if n == 0 || n > MAX_LIMIT {
                        return Err(value("limit", v, format!("must be 1 to {MAX_LIMIT}")));
                    }
                    q.limit = n;
                }
                "after" if store != Store::Utilisation => {
                    q.after = v
                        .parse()
                        .map_err(|_| value("after", v, "not a record number".to_string()))?;
                }
                "order" if store != Store::Utilisation => {
                    q.order = match v {
                        "oldest" => Order::Oldest,
                        "newest" => Order::Newest,
                        _ => {
                            return Err(value("order", v, "must be oldest or newest".to_string()));
                        }
                    }
                }
                "bucket" if store == Store::Utilisation => {
                    q.bucket = match v {
                        "hour" => Bucket::Hour,
                        "shift" => Bucket::Shift,
                        _ => {
                            return Err(value("bucket", v, "must be hour or shift".to_string()));
                        }
                    }
                }
                other => {
                    return Err(ParamError::Unknown {
                        name: other.chars().take(64).collect(),
                        takes: match store {
                            Store::History => {
                                "a history query takes _time, machine, kind, tag, limit, after, order"
                            }
                            Store::Audit => {
                                "an audit query takes _time, machine, limit, after, order"
                            }
                            Store::Utilisation => {
                                "a utilisation query takes _time, machine, bucket"
                            }
                        },
                    });
                }
            }
        }
        if !q.tags.is_empty() {
            q.kinds
                .get_or_insert_with(BTreeSet::new)
                .insert(HistoryKind::Tag as i32);
        }
        Ok(q)
    }

    /// Whether `record` answers the query (its time, machine, kind, tag and, oldest first,
    /// `after`; newest first the store's range ends before `after`'s record).
    pub fn takes(&self, record: &pb::HistoryRecord) -> bool {
        if record.unix_ms < self.from_ms
            || record.unix_ms > self.to_ms
            || (self.order == Order::Oldest && record.seq <= self.after)
        {
            return false;
        }
        if let Some(m) = &self.machines
            && !m.contains(&record.machine)
        {
            return false;
        }
        let kind = record.kind;
        match &self.kinds {
            Some(k) if !k.contains(&kind) => return false,
            // By default, tag values only when asked for: they are many.
            None if kind == HistoryKind::Tag as i32 => return false,
            _ => {}
        }
        if kind == HistoryKind::Tag as i32
            && !self.tags.is_empty()
            && let Some(pb::history_record::Record::Tag(t)) = &record.record
            && !self.tags.contains(&format!("{}/{}", t.plc, t.name))
        {
            return false;
        }
        true
    }
}

fn list(v: &str) -> impl Iterator<Item = &str> {
    v.split(',').map(str::trim).filter(|s| !s.is_empty())
}

/// What a machine is doing, from its status: the link's state first (a link that is down
/// tells nothing of the CNC; sending means the CNC reads), then the SAT's buffer status
/// (§4.4.2) while the link is idle.
pub fn activity(status: &pb::MachineStatus) -> pb::MachineActivity {
    use pb::{BufferStatus, LinkState, MachineActivity as A};
    match status.link_state() {
        LinkState::Unspecified | LinkState::Down | LinkState::Connecting => A::LinkDown,
        LinkState::Alarm => A::Alarm,
        LinkState::Sending => A::Reading,
        LinkState::Receiving => A::Punching,
        LinkState::Idle => match status.sat.as_ref().map(pb::Sat::buffer_status) {
            Some(BufferStatus::Alarm) => A::Alarm,
            Some(BufferStatus::Reset) => A::Reset,
            _ => A::Idle,
        },
    }
}

/// Shift boundaries, minutes after midnight UTC, ascending (`[history] shifts`).
pub type Shifts = [u16];

/// The buckets covering `[from_ms, to_ms]`: whole UTC hours, or the shifts (each from its
/// start to the next one's, the last one into the next day).
pub fn buckets(from_ms: u64, to_ms: u64, bucket: Bucket, shifts: &Shifts) -> Vec<(u64, u64)> {
    const HOUR: u64 = 3_600_000;
    const DAY: u64 = 24 * HOUR;
    let mut out = Vec::new();
    let starts: Vec<u64> = match bucket {
        Bucket::Shift if !shifts.is_empty() => {
            let mut day = from_ms / DAY * DAY - DAY;
            let mut s = Vec::new();
            while day <= to_ms {
                s.extend(shifts.iter().map(|m| day + u64::from(*m) * 60_000));
                day += DAY;
            }
            s
        }
        _ => (from_ms / HOUR..=to_ms / HOUR + 1)
            .map(|h| h * HOUR)
            .collect(),
    };
    for w in starts.windows(2) {
        let (s, e) = (w[0], w[1]);
        if e > from_ms && s <= to_ms {
            out.push((s, e));
        }
    }
    out
}

/// One machine's state changes and the gateway's own records, in time order, as
/// utilisation reads them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mark {
    /// The machine's activity from this time on.
    Activity(u64, pb::MachineActivity),
    /// The gateway stopped (cleanly): unknown from here.
    Stopped(u64),
    /// The gateway started: unknown before it, back to the last mark (alive or otherwise)
    /// plus [`ALIVE_EVERY_MS`].
    Started(u64),
    /// The gateway was running at this time.
    Alive(u64),
}

impl Mark {
    fn at(&self) -> u64 {
        match *self {
            Mark::Activity(t, _) | Mark::Stopped(t) | Mark::Started(t) | Mark::Alive(t) => t,
        }
    }
}

/// Splits `[from, to)` into time per activity for each bucket, from `marks` (in time order;
/// the first may lie before `from`, giving the state at `from`). Time before the first mark,
/// after a clean stop until the next start, and after a silence of more than
/// [`ALIVE_EVERY_MS`] that ends in a start (a crash) is unknown. Jobs that ended are counted
/// from `jobs` (end time, completed).
pub fn utilisation(
    marks: &[Mark],
    jobs: &[(u64, bool)],
    parts: &[(u64, f64)],
    counter: bool,
    buckets: &[(u64, u64)],
    now_ms: u64,
) -> Vec<pb::UtilisationBucket> {
    use pb::MachineActivity as A;
    // Intervals of known activity: (start, end, activity).
    let mut spans: Vec<(u64, u64, A)> = Vec::new();
    let mut state: Option<(u64, A)> = None;
    let mut last_seen = 0u64;
    for m in marks {
        let t = m.at();
        match *m {
            Mark::Activity(_, a) => {
                if let Some((s, prev)) = state {
                    spans.push((s, t, prev));
                }
                state = Some((t, a));
            }
            Mark::Stopped(_) => {
                if let Some((s, prev)) = state.take() {
                    spans.push((s, t, prev));
                }
            }
            Mark::Started(_) => {
                if let Some((s, prev)) = state.take() {
                    // A crash: the state held until the gateway was last seen alive.
                    let end = (last_seen + ALIVE_EVERY_MS).clamp(s, t);
                    spans.push((s, end, prev));
                }
            }
            Mark::Alive(_) => {}
        }
        last_seen = last_seen.max(t);
    }
    if let Some((s, a)) = state {
        spans.push((s, now_ms.max(s), a));
    }
    // Spans, jobs and values are in time order, buckets too: one sweep each, not a pass over
    // everything per bucket (a week of a busy machine is thousands of each).
    let mut jobs: Vec<(u64, bool)> = jobs.to_vec();
    jobs.sort_unstable();
    let mut out = Vec::new();
    let mut first = 0usize;
    for &(bs, be) in buckets {
        let end = be.min(now_ms.max(bs));
        let mut b = pb::UtilisationBucket {
            start_unix_ms: bs,
            end_unix_ms: be,
            ..Default::default()
        };
        while first < spans.len() && spans[first].1 <= bs {
            first += 1;
        }
        let mut known = 0u64;
        for &(s, e, a) in &spans[first..] {
            if s >= end {
                break;
            }
            let (s, e) = (s.max(bs), e.min(end));
            if e <= s {
                continue;
            }
            let d = e - s;
            known += d;
            match a {
                A::Reading => b.reading_ms += d,
                A::Idle => b.idle_ms += d,
                A::Alarm => b.alarm_ms += d,
                A::Reset => b.reset_ms += d,
                A::Punching => b.punching_ms += d,
                A::LinkDown | A::Unspecified => b.link_down_ms += d,
            }
        }
        b.unknown_ms = end.saturating_sub(bs).saturating_sub(known);
        let lo = jobs.partition_point(|j| j.0 < bs);
        let hi = jobs.partition_point(|j| j.0 < be);
        for &(_, completed) in &jobs[lo..hi] {
            if completed {
                b.jobs_completed += 1;
            } else {
                b.jobs_failed += 1;
            }
        }
        if counter {
            // The value before the bucket is where it starts counting from.
            let lo = parts.partition_point(|p| p.0 < bs).saturating_sub(1);
            let hi = parts.partition_point(|p| p.0 < be);
            b.parts = Some(parts_made(&parts[lo..hi], bs, be));
        }
        out.push(b);
    }
    out
}

/// Parts a counter's values (time order, the last one before `start` first if known) show
/// made in `[start, end)`: the sum of its rises; a fall is a counter reset, and the value it
/// fell to counts as made since.
pub fn parts_made(values: &[(u64, f64)], start: u64, end: u64) -> f64 {
    let mut prev: Option<f64> = None;
    let mut made = 0.0;
    for &(t, v) in values {
        if t >= end {
            break;
        }
        if t >= start
            && let Some(p) = prev
        {
            made += if v >= p { v - p } else { v.max(0.0) };
        }
        prev = Some(v);
    }
    made
}

#[cfg(test)]
mod tests;
