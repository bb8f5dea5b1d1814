//! `[history]`: the cell's history and audit trail, and how utilisation divides the day.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::error::{Checker, q};

/// `[history]`: where the history store lives and how much it keeps.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HistoryConfig {
    /// Keep the history and the audit trail. Off: `P/C/history`, `P/C/audit` and
    /// `P/C/utilisation` answer `ERROR_CODE_UNAVAILABLE`.
    pub enabled: bool,
    /// The store's directory. Default: `.history` in `programs.dir`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dir: Option<PathBuf>,
    /// Days history records are kept (tag values, jobs, alarms, states).
    pub keep_days: u32,
    /// Days audit records are kept.
    pub keep_audit_days: u32,
    /// Most records kept in all (history and audit each): the oldest go first beyond it.
    pub max_records: u64,
    /// Most refusal records the audit keeps (requests refused, gathered per sender, action,
    /// code and minute): the oldest refusals go first beyond it, never a write that was
    /// taken, so that what anyone can send cannot push the real writes out of the trail.
    pub max_refusals: u64,
    /// Values kept per tag with `history = true`: the oldest go first beyond it.
    pub tag_values: u32,
    /// Where shifts start, `HH:MM` UTC, for utilisation by shift: each runs to the next one's
    /// start, the last one into the next day.
    pub shifts: Vec<String>,
}

impl Default for HistoryConfig {
    fn default() -> Self {
        HistoryConfig {
            enabled: true,
            dir: None,
            keep_days: 90,
            keep_audit_days: 400,
            max_records: 5_000_000,
            max_refusals: 100_000,
            tag_values: 10_000,
            shifts: vec!["06:00".into(), "14:00".into(), "22:00".into()],
        }
    }
}

impl HistoryConfig {
    /// The store's directory in force, with the library's directory `programs_dir`.
    pub fn dir_in(&self, programs_dir: &Path) -> PathBuf {
        self.dir
            .clone()
            .unwrap_or_else(|| programs_dir.join(".history"))
    }

    /// The shifts' starts, minutes after midnight UTC, ascending; shifts that cannot be read
    /// are left out (`check-config` refuses them).
    pub fn shift_minutes(&self) -> Vec<u16> {
        let mut m: Vec<u16> = self.shifts.iter().filter_map(|s| minutes(s)).collect();
        m.sort_unstable();
        m.dedup();
        m
    }
}

fn minutes(hhmm: &str) -> Option<u16> {
    let (h, m) = hhmm.split_once(':')?;
    let (h, m): (u16, u16) = (h.parse().ok()?, m.parse().ok()?);
    (h < 24 && m < 60 && hhmm.len() == 5).then_some(h * 60 + m)
}

pub(super) fn check_history(c: &mut Checker, h: &HistoryConfig) {
    for (key, v, max) in [
        ("keep_days", u64::from(h.keep_days), 36_500),
        ("keep_audit_days", u64::from(h.keep_audit_days), 36_500),
        ("tag_values", u64::from(h.tag_values), 10_000_000),
        ("max_records", h.max_records, 1_000_000_000),
        ("max_refusals", h.max_refusals, 1_000_000_000),
    ] {
        c.range(|| format!("history.{key}"), v, 1, max, "", "");
    }
    if h.shifts.is_empty() {
        c.invalid(
            "history.shifts".to_string(),
            "[]".to_string(),
            "name at least one shift start, e.g. [\"06:00\", \"14:00\", \"22:00\"]".to_string(),
            "",
        );
    }
    for (i, s) in h.shifts.iter().enumerate() {
        if minutes(s).is_none() {
            c.invalid(
                format!("history.shifts[{i}]"),
                q(s),
                "must be HH:MM (UTC), 00:00 to 23:59".to_string(),
                "",
            );
        }
    }
}
