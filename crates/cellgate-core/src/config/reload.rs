//! What a reload changes: the running cell file against a new one, each difference sorted by
//! what applying it takes (docs/configuration.md, "Reloading").
//!
//! - A machine or PLC added, removed or changed: its link starts, stops or restarts; the other
//!   links are not touched. A PLC whose entry differs in its tags only keeps its link: the
//!   tags and poll groups are swapped in the running link.
//! - Settings that apply without touching a link ([`LIVE_KEYS`]): library quotas and
//!   retention, history retention and shifts, console sessions.
//! - Everything else is fixed while the gateway runs (the bus session and its access control,
//!   the TLS identity, telemetry, the journal and the library's place, the console's and the
//!   MTConnect agent's listeners): a difference there refuses the whole reload, naming each
//!   key, since nothing of it could be applied without a restart.

use super::{CellConfig, ConsoleConfig, HistoryConfig, ProgramsConfig};

/// The keys a reload applies without touching a link, beside the machines, the PLCs and
/// their tags.
pub const LIVE_KEYS: &[&str] = &[
    "programs.quota_bytes",
    "programs.quota_files",
    "programs.keep_revisions",
    "programs.keep_revision_days",
    "history.keep_days",
    "history.keep_audit_days",
    "history.max_records",
    "history.max_refusals",
    "history.tag_values",
    "history.shifts",
    "console.session_idle_minutes",
    "console.session_hours",
    "console.sessions_per_user",
];

/// The differences a reload applies, by what each takes. Names are in the new file's order
/// (removed ones in the old file's).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct CellChange {
    /// Machines the new file adds: their links start.
    pub machines_added: Vec<String>,
    /// Machines the new file no longer has: their links stop once their running job ended.
    pub machines_removed: Vec<String>,
    /// Machines whose entry differs: their links restart once their running job ended.
    pub machines_changed: Vec<String>,
    /// PLCs the new file adds.
    pub plcs_added: Vec<String>,
    /// PLCs the new file no longer has.
    pub plcs_removed: Vec<String>,
    /// PLCs whose entry differs beyond their tags: their links restart.
    pub plcs_changed: Vec<String>,
    /// PLCs whose tags (and so poll groups) alone differ: swapped in the running link.
    pub plc_tags: Vec<String>,
    /// The keys of [`LIVE_KEYS`] that differ.
    pub settings: Vec<String>,
}

impl CellChange {
    /// Whether the new file changes nothing.
    pub fn is_empty(&self) -> bool {
        *self == CellChange::default()
    }

    /// Whether a link starts, stops or restarts.
    pub fn touches_links(&self) -> bool {
        !(self.machines_added.is_empty()
            && self.machines_removed.is_empty()
            && self.machines_changed.is_empty()
            && self.plcs_added.is_empty()
            && self.plcs_removed.is_empty()
            && self.plcs_changed.is_empty())
    }

    /// One line for people: `machines added: m4; PLC tags: plc-1` or `nothing changed`.
    pub fn summary(&self) -> String {
        summary_of([
            &self.machines_added,
            &self.machines_removed,
            &self.machines_changed,
            &self.plcs_added,
            &self.plcs_removed,
            &self.plcs_changed,
            &self.plc_tags,
            &self.settings,
        ])
    }
}

/// Keys that differ and cannot change while the gateway runs, each with why
/// (`bus.listen: ...`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RestartNeeded(pub Vec<String>);

impl std::fmt::Display for RestartNeeded {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "a restart is needed for: {}; nothing of this reload was applied",
            self.0.join("; ")
        )
    }
}

/// What taking `new` in place of the running `old` changes, or every key that needs a
/// restart.
pub fn compare(old: &CellConfig, new: &CellConfig) -> Result<CellChange, RestartNeeded> {
    let mut fixed = Vec::new();
    let mut note = |differs: bool, key: &str, why: &str| {
        if differs {
            fixed.push(format!("{key} ({why})"));
        }
    };
    note(
        old.cell != new.cell,
        "cell",
        "every key of the cell starts with it",
    );
    let (ob, nb) = (&old.bus, &new.bus);
    let session = "the zenoh session is opened with it at start";
    note(
        ob.prefix != nb.prefix,
        "bus.prefix",
        "every key of the cell starts with it",
    );
    note(ob.mode != nb.mode, "bus.mode", session);
    note(
        ob.listen != nb.listen,
        "bus.listen",
        "the bus listen endpoints are bound at start",
    );
    note(ob.connect != nb.connect, "bus.connect", session);
    note(
        ob.multicast_scouting != nb.multicast_scouting,
        "bus.multicast_scouting",
        session,
    );
    note(
        ob.zenoh_config != nb.zenoh_config,
        "bus.zenoh_config",
        session,
    );
    note(
        old.telemetry != new.telemetry,
        "telemetry",
        "logs, traces and metrics are set up once at start",
    );
    let (os, ns) = (&old.security, &new.security);
    note(
        os.tls != ns.tls,
        "security.tls",
        "the TLS identity is the zenoh session's, loaded at start",
    );
    note(
        os.users_file != ns.users_file,
        "security.users_file",
        "zenoh reads its user-password dictionary at start",
    );
    note(
        os.roles != ns.roles,
        "security.roles",
        "the roles are zenoh's own access control, fixed when the session opens",
    );
    fixed_programs(&old.programs, &new.programs, &mut note);
    let (oh, nh) = (&old.history, &new.history);
    note(
        oh.enabled != nh.enabled,
        "history.enabled",
        "the store is opened at start",
    );
    note(
        oh.dir != nh.dir,
        "history.dir",
        "the store is opened at start",
    );
    match (&old.console, &new.console) {
        (None, None) => {}
        (Some(o), Some(n)) => {
            let why = "the console's listener is bound at start";
            note(o.listen != n.listen, "console.listen", why);
            note(
                o.allow_remote != n.allow_remote,
                "console.allow_remote",
                why,
            );
            note(
                o.host_names != n.host_names,
                "console.host_names",
                "the console's host names are taken at start",
            );
        }
        _ => note(true, "console", "the console is started or not at start"),
    }
    note(
        old.mtconnect != new.mtconnect,
        "mtconnect",
        "the MTConnect agent and its listeners are set up at start",
    );
    if !fixed.is_empty() {
        return Err(RestartNeeded(fixed));
    }

    let mut change = CellChange::default();
    for m in &new.machines {
        match old.machine(&m.name) {
            None => change.machines_added.push(m.name.clone()),
            Some(o) if o != m => change.machines_changed.push(m.name.clone()),
            Some(_) => {}
        }
    }
    for m in &old.machines {
        if new.machine(&m.name).is_none() {
            change.machines_removed.push(m.name.clone());
        }
    }
    for p in &new.plcs {
        match old.plc(&p.name) {
            None => change.plcs_added.push(p.name.clone()),
            Some(o) if o == p => {}
            Some(o) => {
                let same_but_tags = super::PlcConfig {
                    tags: p.tags.clone(),
                    ..o.clone()
                } == *p;
                if same_but_tags {
                    change.plc_tags.push(p.name.clone());
                } else {
                    change.plcs_changed.push(p.name.clone());
                }
            }
        }
    }
    for p in &old.plcs {
        if new.plc(&p.name).is_none() {
            change.plcs_removed.push(p.name.clone());
        }
    }
    change.settings = live_settings(old, new);
    Ok(change)
}

/// The `[programs]` keys fixed while the gateway runs: where the library and the journal
/// are, and what each machine's job manager and punch desk took at start.
fn fixed_programs(o: &ProgramsConfig, n: &ProgramsConfig, note: &mut impl FnMut(bool, &str, &str)) {
    let place = "the library and the journal are opened at start";
    let machines = "each machine's job manager takes it when its link starts; restart the \
                    gateway to apply it to every machine alike";
    note(o.dir != n.dir, "programs.dir", place);
    note(o.journal != n.journal, "programs.journal", place);
    note(
        o.damaged_journal != n.damaged_journal,
        "programs.damaged_journal",
        place,
    );
    note(o.max_size != n.max_size, "programs.max_size", machines);
    note(
        o.max_inline != n.max_inline,
        "programs.max_inline",
        machines,
    );
    note(o.keep_jobs != n.keep_jobs, "programs.keep_jobs", machines);
    note(
        o.store_punched != n.store_punched,
        "programs.store_punched",
        machines,
    );
    note(o.requests != n.requests, "programs.requests", machines);
    note(
        o.punched_retention_days != n.punched_retention_days,
        "programs.punched_retention_days",
        machines,
    );
    note(
        o.fetch_prefixes != n.fetch_prefixes,
        "programs.fetch_prefixes",
        "the job routes take it at start",
    );
}

/// The keys of [`LIVE_KEYS`] whose values differ.
fn live_settings(old: &CellConfig, new: &CellConfig) -> Vec<String> {
    let (op, np) = (&old.programs, &new.programs);
    let (oh, nh): (&HistoryConfig, &HistoryConfig) = (&old.history, &new.history);
    let console = |c: &Option<ConsoleConfig>| c.clone().unwrap_or_default();
    let (oc, nc) = (console(&old.console), console(&new.console));
    let differs = [
        op.quota_bytes != np.quota_bytes,
        op.quota_files != np.quota_files,
        op.keep_revisions != np.keep_revisions,
        op.keep_revision_days != np.keep_revision_days,
        oh.keep_days != nh.keep_days,
        oh.keep_audit_days != nh.keep_audit_days,
        oh.max_records != nh.max_records,
        oh.max_refusals != nh.max_refusals,
        oh.tag_values != nh.tag_values,
        oh.shifts != nh.shifts,
        oc.session_idle_minutes != nc.session_idle_minutes,
        oc.session_hours != nc.session_hours,
        oc.sessions_per_user != nc.sessions_per_user,
    ];
    LIVE_KEYS
        .iter()
        .zip(differs)
        .filter(|(_, d)| *d)
        .map(|(k, _)| (*k).to_string())
        .collect()
}

/// One line for people from a reload's lists, in [`CellChange`]'s order (machines added,
/// removed, changed; PLCs added, removed, changed; PLC tags; settings): a taken reload's
/// `ReloadResult` says it the same way.
pub fn summary_of(lists: [&[String]; 8]) -> String {
    const WHAT: [&str; 8] = [
        "machines added",
        "machines removed",
        "machines changed",
        "PLCs added",
        "PLCs removed",
        "PLCs changed",
        "PLC tags",
        "settings",
    ];
    let parts: Vec<String> = WHAT
        .iter()
        .zip(lists)
        .filter(|(_, v)| !v.is_empty())
        .map(|(what, v)| format!("{what}: {}", v.join(", ")))
        .collect();
    if parts.is_empty() {
        "nothing changed".to_string()
    } else {
        parts.join("; ")
    }
}

#[cfg(test)]
mod tests;
