//! What a reload changes: the running cell file against a new one, each difference sorted by
//! what applying it takes (docs/configuration.md, "Reloading").
//!
//! - A machine or PLC added, removed or changed: its link starts, stops or restarts; the other
//!   links are not touched. A PLC whose entry differs in its tags only keeps its link: the
//!   tags and poll groups are swapped in the running link.
//! - Settings that apply without touching a link ([`Takes::Live`]): library quotas and
//!   retention, history retention and shifts, console sessions.
//! - Everything else is fixed while the gateway runs (the bus session and its access control,
//!   the TLS identity, telemetry, the journal and the library's place, the console's and the
//!   MTConnect agent's listeners): a difference there refuses the whole reload, naming each
//!   key, since nothing of it could be applied without a restart.

use super::{BusConfig, CellConfig, ConsoleConfig, HistoryConfig, ProgramsConfig, SecurityConfig};

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
    /// The keys applied without touching a link ([`Takes::Live`]) that differ.
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

/// How a reload takes a key of the cell file (the machines and PLCs aside: their entries
/// start, stop or restart their own links).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Takes {
    /// Applied at once, without touching a link.
    Live,
    /// Fixed while the gateway runs, and why: a difference refuses the whole reload.
    Restart(&'static str),
}

/// Every key a reload compares, with how it takes it and whether `old` and `new` differ.
/// Each section of `new` is taken apart field by field, without `..`: a key added to the
/// cell file does not compile until it is said here whether a reload applies it at once or
/// needs a restart for it.
pub fn keys(old: &CellConfig, new: &CellConfig) -> Vec<(&'static str, Takes, bool)> {
    use Takes::{Live, Restart};
    let mut out = Vec::new();
    let mut key =
        |name: &'static str, takes: Takes, differs: bool| out.push((name, takes, differs));
    let CellConfig {
        cell,
        bus,
        telemetry,
        programs,
        history,
        machines: _,
        plcs: _,
        security,
        console,
        mtconnect,
        opcua,
    } = new;
    key(
        "cell",
        Restart("every key of the cell starts with it"),
        *cell != old.cell,
    );

    let BusConfig {
        prefix,
        mode,
        listen,
        connect,
        multicast_scouting,
        zenoh_config,
    } = bus;
    let ob = &old.bus;
    let session = Restart("the zenoh session is opened with it at start");
    key(
        "bus.prefix",
        Restart("every key of the cell starts with it"),
        *prefix != ob.prefix,
    );
    key("bus.mode", session, *mode != ob.mode);
    key(
        "bus.listen",
        Restart("the bus listen endpoints are bound at start"),
        *listen != ob.listen,
    );
    key("bus.connect", session, *connect != ob.connect);
    key(
        "bus.multicast_scouting",
        session,
        *multicast_scouting != ob.multicast_scouting,
    );
    key(
        "bus.zenoh_config",
        session,
        *zenoh_config != ob.zenoh_config,
    );
    key(
        "telemetry",
        Restart("logs, traces and metrics are set up once at start"),
        *telemetry != old.telemetry,
    );

    let SecurityConfig {
        tls,
        users_file,
        roles,
    } = security;
    let os = &old.security;
    key(
        "security.tls",
        Restart("the TLS identity is the zenoh session's, loaded at start"),
        *tls != os.tls,
    );
    key(
        "security.users_file",
        Restart("zenoh reads its user-password dictionary at start"),
        *users_file != os.users_file,
    );
    key(
        "security.roles",
        Restart("the roles are zenoh's own access control, fixed when the session opens"),
        *roles != os.roles,
    );

    let ProgramsConfig {
        dir,
        max_size,
        max_inline,
        store_punched,
        requests,
        journal,
        keep_jobs,
        quota_bytes,
        quota_files,
        punched_retention_days,
        damaged_journal,
        fetch_prefixes,
        keep_revisions,
        keep_revision_days,
        watch,
        extensions,
        settle_ms,
        poll_ms,
    } = programs;
    let op = &old.programs;
    let place = Restart("the library and the journal are opened at start");
    let machines = Restart(
        "each machine's job manager takes it when its link starts; restart the gateway to \
         apply it to every machine alike",
    );
    let folder = Restart("the library's folder is followed as it was set at start");
    key("programs.dir", place, *dir != op.dir);
    key("programs.journal", place, *journal != op.journal);
    key(
        "programs.damaged_journal",
        place,
        *damaged_journal != op.damaged_journal,
    );
    key("programs.max_size", machines, *max_size != op.max_size);
    key(
        "programs.max_inline",
        machines,
        *max_inline != op.max_inline,
    );
    key("programs.keep_jobs", machines, *keep_jobs != op.keep_jobs);
    key(
        "programs.store_punched",
        machines,
        *store_punched != op.store_punched,
    );
    key("programs.requests", machines, *requests != op.requests);
    key(
        "programs.punched_retention_days",
        machines,
        *punched_retention_days != op.punched_retention_days,
    );
    key(
        "programs.fetch_prefixes",
        Restart("the job routes take it at start"),
        *fetch_prefixes != op.fetch_prefixes,
    );
    key("programs.watch", folder, *watch != op.watch);
    key("programs.extensions", folder, *extensions != op.extensions);
    key("programs.settle_ms", folder, *settle_ms != op.settle_ms);
    key("programs.poll_ms", folder, *poll_ms != op.poll_ms);
    key("programs.quota_bytes", Live, *quota_bytes != op.quota_bytes);
    key("programs.quota_files", Live, *quota_files != op.quota_files);
    key(
        "programs.keep_revisions",
        Live,
        *keep_revisions != op.keep_revisions,
    );
    key(
        "programs.keep_revision_days",
        Live,
        *keep_revision_days != op.keep_revision_days,
    );

    let HistoryConfig {
        enabled,
        dir,
        keep_days,
        keep_audit_days,
        max_records,
        max_refusals,
        tag_values,
        shifts,
    } = history;
    let oh = &old.history;
    let store = Restart("the store is opened at start");
    key("history.enabled", store, *enabled != oh.enabled);
    key("history.dir", store, *dir != oh.dir);
    key("history.keep_days", Live, *keep_days != oh.keep_days);
    key(
        "history.keep_audit_days",
        Live,
        *keep_audit_days != oh.keep_audit_days,
    );
    key("history.max_records", Live, *max_records != oh.max_records);
    key(
        "history.max_refusals",
        Live,
        *max_refusals != oh.max_refusals,
    );
    key("history.tag_values", Live, *tag_values != oh.tag_values);
    key("history.shifts", Live, *shifts != oh.shifts);

    match (&old.console, console) {
        (None, None) => {}
        (Some(oc), Some(nc)) => {
            let ConsoleConfig {
                listen,
                session_idle_minutes,
                session_hours,
                sessions_per_user,
                allow_remote,
                host_names,
            } = nc;
            let bound = Restart("the console's listener is bound at start");
            key("console.listen", bound, *listen != oc.listen);
            key(
                "console.allow_remote",
                bound,
                *allow_remote != oc.allow_remote,
            );
            key(
                "console.host_names",
                Restart("the console's host names are taken at start"),
                *host_names != oc.host_names,
            );
            key(
                "console.session_idle_minutes",
                Live,
                *session_idle_minutes != oc.session_idle_minutes,
            );
            key(
                "console.session_hours",
                Live,
                *session_hours != oc.session_hours,
            );
            key(
                "console.sessions_per_user",
                Live,
                *sessions_per_user != oc.sessions_per_user,
            );
        }
        _ => key(
            "console",
            Restart("the console is started or not at start"),
            true,
        ),
    }
    key(
        "mtconnect",
        Restart("the MTConnect agent and its listeners are set up at start"),
        *mtconnect != old.mtconnect,
    );
    key(
        "opcua",
        Restart("the OPC UA server, its endpoints and certificates are set up at start"),
        *opcua != old.opcua,
    );
    out
}

/// What taking `new` in place of the running `old` changes, or every key that needs a
/// restart.
pub fn compare(old: &CellConfig, new: &CellConfig) -> Result<CellChange, RestartNeeded> {
    let mut fixed = Vec::new();
    let mut settings = Vec::new();
    for (key, takes, differs) in keys(old, new) {
        match (takes, differs) {
            (_, false) => {}
            (Takes::Restart(why), true) => fixed.push(format!("{key} ({why})")),
            (Takes::Live, true) => settings.push(key.to_string()),
        }
    }
    if !fixed.is_empty() {
        return Err(RestartNeeded(fixed));
    }

    // Machines and PLCs alike: an entry added, removed, or changed; a PLC whose tags alone
    // differ keeps its link and takes them there.
    let (machines_added, machines_removed, machines_changed) =
        entries(&old.machines, &new.machines, |m| &m.name);
    let (plcs_added, plcs_removed, differing) = entries(&old.plcs, &new.plcs, |p| &p.name);
    let (plc_tags, plcs_changed) =
        differing
            .into_iter()
            .partition(|name| match (old.plc(name), new.plc(name)) {
                (Some(o), Some(p)) => {
                    super::PlcConfig {
                        tags: p.tags.clone(),
                        ..o.clone()
                    } == *p
                }
                _ => false,
            });
    Ok(CellChange {
        machines_added,
        machines_removed,
        machines_changed,
        plcs_added,
        plcs_removed,
        plcs_changed,
        plc_tags,
        settings,
    })
}

/// The entries of a list of the cell file (`[[machines]]`, `[[plcs]]`) that `new` adds, that
/// it no longer has, and that differ, by name: added and changed in `new`'s order, removed
/// in `old`'s.
fn entries<T: PartialEq>(
    old: &[T],
    new: &[T],
    name: impl Fn(&T) -> &String,
) -> (Vec<String>, Vec<String>, Vec<String>) {
    let (mut added, mut changed) = (Vec::new(), Vec::new());
    for e in new {
        match old.iter().find(|o| name(o) == name(e)) {
            None => added.push(name(e).clone()),
            Some(o) if o != e => changed.push(name(e).clone()),
            Some(_) => {}
        }
    }
    let removed = old
        .iter()
        .filter(|o| !new.iter().any(|e| name(e) == name(o)))
        .map(|o| name(o).clone())
        .collect();
    (added, removed, changed)
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
