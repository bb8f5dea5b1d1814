//! Refusals gathered for the audit trail: one record per sender, action, reason and minute,
//! with a count, so that a flood of refused requests leaves a few records, never thousands
//! that push the taken writes out of the trail.
//!
//! The first refusal of a kind in a minute is recorded at once (with the target it named),
//! so that the trail shows it as soon as it happens; the rest of that minute's are counted and
//! recorded once the minute is over, as one record whose `count` says how many it stands for
//! and whose detail names a few of their targets. Kinds are bounded per minute
//! ([`MAX_KINDS`]): a sender that varies the names it claims or the actions it asks for
//! lands, past the bound, in one record of "many kinds".
//!
//! Sans-IO: refused records and `now` in, records to write out. Both the gateway (the
//! refusals it answers) and the console (the requests it refuses its users, failed logins)
//! use it.

use std::collections::{BTreeMap, BTreeSet};

use crate::pb;

/// The window refusals are gathered over, ms: a minute of the clock.
pub const WINDOW_MS: u64 = 60_000;
/// Kinds of refusal kept apart in one window; beyond, they are counted together.
pub const MAX_KINDS: usize = 64;
/// Targets named in a window's summary.
const TARGETS_NAMED: usize = 5;

/// What tells one kind of refusal from another.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct Kind {
    machine: String,
    user: String,
    via: String,
    principal: String,
    action: String,
    code: i32,
}

impl Kind {
    fn of(machine: &str, r: &pb::AuditRecord) -> Self {
        let origin = r.origin.clone().unwrap_or_default();
        Kind {
            machine: machine.to_string(),
            user: origin.user,
            via: origin.via,
            principal: r.principal.clone(),
            action: r.action.clone(),
            code: r.code,
        }
    }

    fn many() -> Self {
        Kind {
            machine: String::new(),
            user: "(many)".to_string(),
            via: String::new(),
            principal: String::new(),
            action: "(many)".to_string(),
            code: 0,
        }
    }
}

#[derive(Debug)]
struct Window {
    /// The record the summary is made from (the first of the kind).
    first: pb::AuditRecord,
    /// Refusals after the first.
    more: u64,
    targets: BTreeSet<String>,
}

/// Refusals of the current window, by kind.
#[derive(Debug, Default)]
pub struct Refusals {
    /// The window's start, ms.
    window: u64,
    open: BTreeMap<Kind, Window>,
}

/// A record to write: about `machine` (empty for the library's and the console's).
pub type Out = (String, pb::AuditRecord);

impl Refusals {
    /// Takes a refused request's record at `now_ms`. The records to write now: the window's
    /// summaries if a new window began, then this one if it is the first of its kind.
    pub fn refuse(&mut self, machine: &str, mut record: pb::AuditRecord, now_ms: u64) -> Vec<Out> {
        let mut out = self.flush(now_ms);
        let mut kind = Kind::of(machine, &record);
        if !self.open.contains_key(&kind) && self.open.len() >= MAX_KINDS {
            kind = Kind::many();
        }
        match self.open.get_mut(&kind) {
            Some(w) => {
                w.more += u64::from(record.count.max(1));
                if w.targets.len() < TARGETS_NAMED {
                    w.targets.insert(record.target);
                }
            }
            None => {
                if kind == Kind::many() {
                    // The first of many kinds: recorded as what it is, counted as many.
                    let first = pb::AuditRecord {
                        action: kind.action.clone(),
                        origin: Some(pb::RequestOrigin {
                            user: kind.user.clone(),
                            via: String::new(),
                        }),
                        ..Default::default()
                    };
                    self.open.insert(
                        kind,
                        Window {
                            first,
                            more: u64::from(record.count.max(1)),
                            targets: BTreeSet::from([record.target]),
                        },
                    );
                } else {
                    record.count = record.count.max(1);
                    self.open.insert(
                        kind,
                        Window {
                            first: record.clone(),
                            more: 0,
                            targets: BTreeSet::new(),
                        },
                    );
                    out.push((machine.to_string(), record));
                }
            }
        }
        out
    }

    /// The summaries of the window that ended by `now_ms` (none while it runs).
    pub fn flush(&mut self, now_ms: u64) -> Vec<Out> {
        let window = now_ms - now_ms % WINDOW_MS;
        if window == self.window {
            return Vec::new();
        }
        self.window = window;
        std::mem::take(&mut self.open)
            .into_iter()
            .filter(|(_, w)| w.more > 0)
            .map(|(kind, w)| {
                let targets: Vec<&str> = w.targets.iter().map(String::as_str).collect();
                let named = if targets.iter().all(|t| t.is_empty()) {
                    String::new()
                } else {
                    format!(" (targets: {})", targets.join(", "))
                };
                let detail = if kind == Kind::many() {
                    format!(
                        "{} refused requests past {MAX_KINDS} kinds in one minute{named}",
                        w.more
                    )
                } else {
                    format!(
                        "{} more like it in the minute after the first{named}",
                        w.more
                    )
                };
                let record = pb::AuditRecord {
                    detail,
                    target: String::new(),
                    count: u32::try_from(w.more).unwrap_or(u32::MAX),
                    ..w.first
                };
                (kind.machine, record)
            })
            .collect()
    }

    /// When the current window ends, if anything waits for it, ms.
    pub fn deadline(&self) -> Option<u64> {
        (!self.open.is_empty()).then_some(self.window + WINDOW_MS)
    }
}

#[cfg(test)]
mod tests;
