//! The cell file: what one gateway serves, how each link is carried, and the settings both ends
//! of each link must agree on.
//!
//! A cell file is TOML. Every key is optional where a sensible default exists, and unknown keys
//! are errors (a misspelt key would otherwise be silently ignored). Reading a file happens in
//! two steps:
//!
//! 1. parsing (TOML syntax, key names, value types), whose errors come from the toml crate one at
//!    a time, with the line and the key;
//! 2. validation against the manuals (ranges, combinations, names), which reports *every* error
//!    at once, each naming its key path (`machines.mill-1.tw`), the value, what is allowed and
//!    the manual section.
//!
//! Sections are cited as "§4.5" for the FANUC remote-buffer manual (B-63322EN-1) and as
//! "FFU120B §4-3" for the Fuji MICREX-F general interface module manual (FEH087b).
//!
//! One file per concern: `bus` (the session and telemetry sections), `programs`,
//! `transport` (what carries each link), `fanuc` (`[[machines]]`), `plc` (`[[plcs]]`),
//! `security` (TLS, user names, roles), `summary` (what `check-config` prints),
//! [`reload`] (what a reload changes) and `error` (every error, collected at once).

mod bus;
mod console;
mod error;
mod fanuc;
pub mod file;
mod g05;
mod history;
mod mtconnect;
pub mod mtconnect_types;
mod opcua;
pub mod owned;
mod plc;
mod programs;
pub mod reload;
mod security;
mod summary;
pub mod telemetry;
mod transport;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

pub use self::bus::{BusConfig, BusMode};
use self::bus::{check_bus, check_telemetry};
pub use self::console::ConsoleConfig;
use self::console::check_console;
use self::error::{Checker, q};
pub use self::error::{ConfigError, ConfigErrors};
pub use self::fanuc::{
    Accept, BoardSimConfig, FANUC_BAUD_RATES, Identification, Interface, MachineConfig,
};
use self::fanuc::{RawMachine, check_machine};
pub use self::g05::{G05Config, Refill};
pub use self::history::HistoryConfig;
use self::history::check_history;
pub use self::mtconnect::MtconnectConfig;
use self::mtconnect::check_mtconnect;
pub use self::opcua::OpcuaConfig;
use self::opcua::check_opcua;
pub use self::plc::{
    FUJI_BAUD_RATES, FUJI_MAX_STATIONS, PlcConfig, PlcSimConfig, Real, SimTick, TagConfig,
    TagMtconnect, TagType,
};
use self::plc::{RawPlc, check_plc};
use self::programs::check_programs;
pub use self::programs::{DEFAULT_KEEP_JOBS, DamagedJournal, ProgramsConfig, Watch};
pub use self::security::{Permission, Role, SecurityConfig, TlsConfig};
use self::security::{RawSecurity, check_security};
pub use self::transport::{TransportConfig, TransportKind};

use self::telemetry::TelemetryConfig;

/// A whole cell file, validated.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct CellConfig {
    /// Cell id: `[A-Za-z0-9_-]+`. It becomes the key chunk `C` of every key `P/C/...`.
    pub cell: String,
    /// `[bus]`: the zenoh session the gateway opens.
    pub bus: BusConfig,
    /// `[telemetry]`: logs, the OTLP export and the Prometheus endpoint.
    pub telemetry: TelemetryConfig,
    /// `[programs]`: the program library and what becomes of punched programs.
    pub programs: ProgramsConfig,
    /// `[history]`: the cell's history and audit trail.
    pub history: HistoryConfig,
    /// `[[machines]]`: the FANUC CNCs behind a remote buffer, one entry each.
    pub machines: Vec<MachineConfig>,
    /// `[[plcs]]`: the MICREX-F PLCs reached through an FFU120B, one entry each.
    pub plcs: Vec<PlcConfig>,
    /// TLS, user names and roles; none by default.
    #[serde(skip_serializing_if = "SecurityConfig::is_empty")]
    pub security: SecurityConfig,
    /// `[console]`: the web console; none without the section.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub console: Option<ConsoleConfig>,
    /// `[mtconnect]`: the MTConnect agent; none without the section.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mtconnect: Option<MtconnectConfig>,
    /// `[opcua]`: the OPC UA server; none without the section.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opcua: Option<OpcuaConfig>,
}

const DEFAULT_CELL: &str = include_str!("default_cell.toml");

impl CellConfig {
    /// Parses and validates a cell file. `origin` names it in parse errors (a file name).
    pub fn from_toml_str(text: &str, origin: &str) -> Result<CellConfig, ConfigErrors> {
        Self::read(text, origin, true)
    }

    /// [`Self::from_toml_str`] without reading the files the cell file names (certificates,
    /// keys, the users file): for what needs only the file's own settings, such as the
    /// access-control rules of its roles.
    pub fn from_toml_str_without_files(
        text: &str,
        origin: &str,
    ) -> Result<CellConfig, ConfigErrors> {
        Self::read(text, origin, false)
    }

    fn read(text: &str, origin: &str, files: bool) -> Result<CellConfig, ConfigErrors> {
        let (raw, mut errors) = parse_all_unknown(text, origin);
        let raw = match raw {
            Ok(raw) => raw,
            Err(e) => {
                errors.push(e);
                return Err(ConfigErrors(errors));
            }
        };
        errors.extend(check_with(&raw, files));
        if !errors.is_empty() {
            return Err(ConfigErrors(errors));
        }
        raw.into_config()
    }

    /// Reads, parses and validates the cell file at `path`.
    pub fn load(path: &Path) -> Result<CellConfig, ConfigErrors> {
        let origin = path.display().to_string();
        let text =
            file::read_text_bounded(path, file::MAX_CELL_FILE).map_err(|e| ConfigError::Read {
                origin: origin.clone(),
                reason: e.to_string(),
            })?;
        let config = Self::from_toml_str(&text, &origin)?;
        // The cell file in the library would be served to anyone who may read programs, keys
        // and user names in it ([`owned`]).
        if owned::listed_in(&config.programs.dir, path) {
            return Err(ConfigErrors(vec![ConfigError::Invalid {
                path: "programs.dir".to_string(),
                value: error::q(&config.programs.dir.display().to_string()),
                reason: format!(
                    "holds the cell file {origin}: the library would list it as a program and \
                     serve it; keep the cell file outside programs.dir"
                ),
                section: "",
            }]));
        }
        Ok(config)
    }

    /// The files and directories the gateway owns: the library never lists, serves or
    /// removes them ([`owned`]).
    pub fn owned_files(&self) -> Vec<PathBuf> {
        let journal = self.programs.journal_dir();
        let history = self.history.dir_in(&self.programs.dir);
        let mut out = vec![
            journal.join("jobs.redb"),
            journal,
            history.join("history.redb"),
            history,
        ];
        out.extend(self.bus.zenoh_config.clone());
        out.extend(self.security.users_file.clone());
        if let Some(t) = &self.security.tls {
            out.extend([t.ca.clone(), t.certificate.clone(), t.private_key.clone()]);
        }
        out.iter().map(|p| owned::lexical(p)).collect()
    }

    /// The cell built into the binary: cell "demo" with three simulated CNCs on loopback.
    pub fn embedded_default() -> CellConfig {
        // The embedded file is part of the program, not input: `embedded_default_is_valid`
        // proves it valid.
        Self::from_toml_str(DEFAULT_CELL, "embedded default cell")
            .expect("the embedded default cell file is valid")
    }

    /// The text of the embedded default cell file.
    pub fn embedded_default_text() -> &'static str {
        DEFAULT_CELL
    }

    /// What is allowed but likely a mistake, one line each: a listener beyond loopback on a
    /// cell without `[security]`, where anyone who reaches the port may do anything; a 7-bit
    /// line over a device server that does not say where its parity bit is made; a G05
    /// machine whose line, unit time and board cannot keep a stream going (§9.2).
    pub fn warnings(&self) -> Vec<String> {
        let mut out = Vec::new();
        let links = self
            .machines
            .iter()
            .map(|m| (format!("machines.{}", m.name), &m.transport))
            .chain(
                self.plcs
                    .iter()
                    .map(|p| (format!("plcs.{}", p.name), &p.transport)),
            );
        for (label, transport) in links {
            out.extend(transport.parity_warning(&format!("{label}.transport")));
        }
        for m in &self.machines {
            if let Some(g) = &m.g05
                && let Some(w) = g.standing_start(m.g05_refill())
            {
                out.push(format!("machines.{}.g05: {w}", m.name));
            }
        }
        let secured = self.security.tls.is_some() || self.security.users_file.is_some();
        if !secured
            && let Some(console) = &self.console
            && !console.is_loopback()
        {
            out.push(format!(
                "console.listen {:?} is reachable beyond this host and the cell has no \
                 [security]: anyone who reaches it may do anything (console.allow_remote)",
                console.listen
            ));
        }
        if let Some(m) = &self.mtconnect {
            out.extend(m.warnings());
        }
        if let Some(o) = &self.opcua {
            out.extend(o.warnings(self.security.users_file.is_some()));
        }
        if !secured {
            for ep in &self.bus.listen {
                if !bus::is_loopback_endpoint(ep) {
                    out.push(format!(
                        "bus.listen {ep:?} is reachable beyond this host and the cell has no \
                         [security]: any client that reaches it may submit jobs, write DO, \
                         PLC memory and programs. Listen on 127.0.0.1 or add TLS and roles \
                         (docs/security.md)"
                    ));
                }
            }
        }
        out
    }

    /// Checks every rule and reports every broken one.
    pub fn validate(&self) -> Result<(), ConfigErrors> {
        let errors = check(&RawCell::from(self.clone()));
        if errors.is_empty() {
            Ok(())
        } else {
            Err(ConfigErrors(errors))
        }
    }

    /// The configuration as TOML, in a form [`CellConfig::from_toml_str`] reads back.
    pub fn to_toml_string(&self) -> Result<String, toml::ser::Error> {
        toml::to_string(self)
    }

    /// The machine or PLC named `name`, if any.
    pub fn machine(&self, name: &str) -> Option<&MachineConfig> {
        self.machines.iter().find(|m| m.name == name)
    }

    /// The PLC named `name`, if any.
    pub fn plc(&self, name: &str) -> Option<&PlcConfig> {
        self.plcs.iter().find(|p| p.name == name)
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCell {
    cell: Option<String>,
    #[serde(default)]
    bus: BusConfig,
    #[serde(default)]
    telemetry: TelemetryConfig,
    #[serde(default)]
    programs: ProgramsConfig,
    #[serde(default)]
    history: HistoryConfig,
    #[serde(default)]
    machines: Vec<RawMachine>,
    #[serde(default)]
    plcs: Vec<RawPlc>,
    #[serde(default)]
    security: RawSecurity,
    console: Option<ConsoleConfig>,
    mtconnect: Option<MtconnectConfig>,
    opcua: Option<OpcuaConfig>,
}

impl From<CellConfig> for RawCell {
    fn from(c: CellConfig) -> Self {
        RawCell {
            cell: Some(c.cell),
            bus: c.bus,
            telemetry: c.telemetry,
            programs: c.programs,
            history: c.history,
            machines: c
                .machines
                .into_iter()
                .map(|m| RawMachine::from(&m))
                .collect(),
            plcs: c.plcs.into_iter().map(|p| RawPlc::from(&p)).collect(),
            security: RawSecurity::from(&c.security),
            console: c.console,
            mtconnect: c.mtconnect,
            opcua: c.opcua,
        }
    }
}

impl RawCell {
    /// Builds the typed configuration; only called once `check` found nothing, so every
    /// required key is there. Should one still be absent, it is reported, not unwrapped.
    fn into_config(self) -> Result<CellConfig, ConfigErrors> {
        let missing = |path: String| ConfigError::Missing {
            path,
            hint: "required".to_string(),
        };
        let cell = self.cell.ok_or_else(|| missing("cell".to_string()))?;
        let mut machines = Vec::with_capacity(self.machines.len());
        for (i, m) in self.machines.into_iter().enumerate() {
            let label = format!("machines[{}]", i + 1);
            machines.push(m.into_config(&label)?);
        }
        let mut plcs = Vec::with_capacity(self.plcs.len());
        for (i, p) in self.plcs.into_iter().enumerate() {
            let label = format!("plcs[{}]", i + 1);
            plcs.push(p.into_config(&label)?);
        }
        let security = self.security.into_config()?;
        Ok(CellConfig {
            cell,
            bus: self.bus,
            telemetry: self.telemetry,
            programs: self.programs,
            history: self.history,
            machines,
            plcs,
            security,
            console: self.console,
            mtconnect: self.mtconnect,
            opcua: self.opcua,
        })
    }
}

fn valid_name(s: &str) -> bool {
    !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

/// Parses the cell file, reporting every unknown key rather than the first: each one found is
/// reported (with the known key it most likely means) and left out, and the file parsed again,
/// so that one misspelt key hides no other mistake. Stops at the first other parse error.
fn parse_all_unknown(text: &str, origin: &str) -> (Result<RawCell, ConfigError>, Vec<ConfigError>) {
    let mut text = text.to_string();
    let mut unknown = Vec::new();
    loop {
        let e = match toml::from_str::<RawCell>(&text) {
            Ok(raw) => {
                unknown.sort_by_key(|u| match u {
                    ConfigError::Unknown { line, .. } => *line,
                    _ => 0,
                });
                return (Ok(raw), unknown);
            }
            Err(e) => e,
        };
        let parse_error = || ConfigError::Parse {
            origin: origin.to_string(),
            message: e.to_string().trim_end().to_string(),
        };
        let Some((key, expected)) = unknown_field(e.message()) else {
            return (Err(parse_error()), unknown);
        };
        let Some(span) = e.span().filter(|_| unknown.len() < 100) else {
            return (Err(parse_error()), unknown);
        };
        let line = text[..span.start.min(text.len())].matches('\n').count() + 1;
        let suggestion = closest(&key, &expected);
        unknown.push(ConfigError::Unknown {
            origin: origin.to_string(),
            line,
            key,
            suggestion,
            expected: expected
                .iter()
                .map(|k| format!("`{k}`"))
                .collect::<Vec<_>>()
                .join(", "),
        });
        match without_key(&text, line) {
            Some(next) => text = next,
            None => return (Err(parse_error()), unknown),
        }
    }
}

/// The key and the expected keys of serde's "unknown field `k`, expected `a`, `b` or `c`".
fn unknown_field(message: &str) -> Option<(String, Vec<String>)> {
    let rest = message.strip_prefix("unknown field `")?;
    let (key, rest) = rest.split_once('`')?;
    let expected = rest
        .split('`')
        .skip(1)
        .step_by(2)
        .map(ToString::to_string)
        .collect();
    Some((key.to_string(), expected))
}

/// The text with the key at `line` left out: a `key = value` line, or a table header with
/// the keys under it, commented out. `None` when the line is neither (a value over several
/// lines): the caller stops there.
fn without_key(text: &str, line: usize) -> Option<String> {
    let mut lines: Vec<String> = text.lines().map(ToString::to_string).collect();
    let i = line.checked_sub(1)?;
    let target = lines.get(i)?.trim_start().to_string();
    if target.starts_with('[') {
        // A table of its own: the header and everything until the next header.
        lines[i] = format!("# {}", lines[i]);
        for l in lines.iter_mut().skip(i + 1) {
            if l.trim_start().starts_with('[') {
                break;
            }
            *l = format!("# {l}");
        }
    } else {
        let value = target.split_once('=')?.1;
        let opens = value.matches(['[', '{']).count();
        let closes = value.matches([']', '}']).count();
        if opens != closes || value.trim_start().starts_with("\"\"\"") {
            return None;
        }
        lines[i] = format!("# {}", lines[i]);
    }
    Some(lines.join("\n") + "\n")
}

/// The expected key nearest to `key`, if it is near enough to be a slip, else one that
/// `key` begins or ends (`multicast` for `multicast_scouting`).
fn closest(key: &str, expected: &[String]) -> Option<String> {
    expected
        .iter()
        .map(|k| (crate::near::edit_distance(key, k), k))
        .filter(|(d, k)| *d <= 2.max(k.len() / 3))
        .min_by_key(|(d, _)| *d)
        .map(|(_, k)| k.clone())
        .or_else(|| {
            let key = key.to_ascii_lowercase();
            expected
                .iter()
                .filter(|k| key.len() >= 4 && (k.starts_with(&key) || k.ends_with(&key)))
                .min_by_key(|k| k.len())
                .cloned()
        })
}

/// The files the gateway owns, refused where the library would take them for programs
/// ([`owned`]).
fn check_owned(c: &mut Checker, raw: &RawCell) {
    let dir = &raw.programs.dir;
    let mut files: Vec<(&'static str, PathBuf)> = Vec::new();
    if let Some(j) = &raw.programs.journal {
        files.push(("programs.journal", j.clone()));
    }
    if let Some(h) = &raw.history.dir {
        files.push(("history.dir", h.clone()));
    }
    if let Some(z) = &raw.bus.zenoh_config {
        files.push(("bus.zenoh_config", z.clone()));
    }
    files.extend(raw.security.files());
    for (key, path) in files {
        if owned::listed_in(dir, &path) {
            c.invalid(
                key.to_string(),
                error::q(&path.display().to_string()),
                format!(
                    "must lie outside programs.dir ({}), or in a hidden directory of it (a \
                     name starting with '.'): the library would list it as a program, serve \
                     its bytes and let a library remove delete it",
                    dir.display()
                ),
                "",
            );
        }
    }
}

fn check(raw: &RawCell) -> Vec<ConfigError> {
    check_with(raw, true)
}

fn check_with(raw: &RawCell, files: bool) -> Vec<ConfigError> {
    let mut c = Checker {
        errors: Vec::new(),
        files,
    };
    match &raw.cell {
        None => c.missing(
            "cell".to_string(),
            "name the cell, e.g. cell = \"line-3\" (it becomes the key chunk after the bus prefix)",
        ),
        Some(name) => check_name(&mut c, "cell".to_string(), name),
    }
    check_bus(&mut c, &raw.bus);
    check_telemetry(&mut c, &raw.telemetry);
    check_programs(&mut c, &raw.programs);
    check_history(&mut c, &raw.history);
    // A fetch from a cellgate key would let a job.submit client read, through the gateway,
    // what its role may not read itself (another cell's PLC memory, `@admin`).
    let prefix = raw.bus.prefix.trim_end_matches('/');
    for (i, fetch) in raw.programs.fetch_prefixes.iter().enumerate() {
        let fetch = fetch.trim_end_matches('/');
        let overlaps = |a: &str, b: &str| a == b || a.starts_with(&format!("{b}/"));
        if overlaps(fetch, prefix) || overlaps(prefix, fetch) {
            c.invalid(
                format!("programs.fetch_prefixes[{i}]"),
                error::q(fetch),
                format!(
                    "overlaps bus.prefix {prefix:?}: a job may not fetch its program from \
                     cellgate's own keys"
                ),
                "",
            );
        }
    }
    check_security(&mut c, &raw.security, &raw.bus);
    check_owned(&mut c, raw);
    if let Some(console) = &raw.console {
        check_console(&mut c, console, raw.security.is_configured());
    }
    if let Some(m) = &raw.mtconnect {
        check_mtconnect(&mut c, m);
    }
    if let Some(o) = &raw.opcua {
        check_opcua(&mut c, o);
    }

    // Names are unique over machines and PLCs together: both are links of the cell.
    let mut seen: HashMap<&str, String> = HashMap::new();
    let mut labels = Vec::new();
    for (i, m) in raw.machines.iter().enumerate() {
        labels.push(link_label(
            &mut c,
            &mut seen,
            "machines",
            i,
            m.name.as_deref(),
        ));
    }
    for (i, p) in raw.plcs.iter().enumerate() {
        labels.push(link_label(&mut c, &mut seen, "plcs", i, p.name.as_deref()));
    }
    let (machine_labels, plc_labels) = labels.split_at(raw.machines.len());
    for (m, label) in raw.machines.iter().zip(machine_labels) {
        check_machine(&mut c, label, m);
        if let Some(counter) = &m.part_counter {
            check_part_counter(&mut c, label, counter, &raw.plcs);
        }
    }
    check_folders(
        &mut c,
        &raw.programs.dir,
        raw.machines.iter().zip(machine_labels),
    );
    for (p, label) in raw.plcs.iter().zip(plc_labels) {
        check_plc(&mut c, label, p);
    }
    c.errors
}

/// The machines' drop and receive folders: each a folder of its own, never the library's.
fn check_folders<'a>(
    c: &mut Checker,
    library: &std::path::Path,
    machines: impl Iterator<Item = (&'a RawMachine, &'a String)>,
) {
    let mut taken: HashMap<std::path::PathBuf, String> = HashMap::new();
    taken.insert(library.to_path_buf(), "programs.dir".to_string());
    for (m, label) in machines {
        for (key, dir) in [("drop_dir", &m.drop_dir), ("receive_dir", &m.receive_dir)] {
            let Some(dir) = dir else { continue };
            let path = format!("{label}.{key}");
            if dir.as_os_str().is_empty() {
                c.invalid(
                    path,
                    "\"\"".to_string(),
                    "must name a folder".to_string(),
                    "",
                );
                continue;
            }
            if let Some(other) = taken.get(dir) {
                c.invalid(
                    path,
                    error::q(&dir.display().to_string()),
                    format!(
                        "is {other} already: a file there would be taken twice; give each \
                         folder one use"
                    ),
                    "",
                );
                continue;
            }
            taken.insert(dir.clone(), path);
        }
    }
}

/// A machine's `part_counter` names a tag of the cell's PLCs that keeps history.
fn check_part_counter(c: &mut Checker, label: &str, counter: &str, plcs: &[RawPlc]) {
    let path = format!("{label}.part_counter");
    let Some((plc, tag)) = counter.split_once('/') else {
        return c.invalid(
            path,
            q(counter),
            "must be PLC/TAG, e.g. \"plc-1/parts\"".to_string(),
            "",
        );
    };
    let Some(p) = plcs.iter().find(|p| p.name.as_deref() == Some(plc)) else {
        return c.invalid(path, q(counter), format!("the cell has no PLC {plc:?}"), "");
    };
    match p.tag_history(tag) {
        None => c.invalid(
            path,
            q(counter),
            format!("PLC {plc} has no tag {tag:?}"),
            "",
        ),
        Some(false) => c.invalid(
            path,
            q(counter),
            format!(
                "tag {tag} of {plc} keeps no history: add history = true to the tag, so that \
                 its values are kept to count parts from"
            ),
            "",
        ),
        Some(true) => {}
    }
}

/// Checks a link's name and returns the path prefix its errors use: `machines.mill-1`, or
/// `machines[2]` (counting from 1) when the name is absent, unusable or taken.
fn link_label<'a>(
    c: &mut Checker,
    seen: &mut HashMap<&'a str, String>,
    table: &str,
    index: usize,
    name: Option<&'a str>,
) -> String {
    let position = format!("[[{table}]] #{}", index + 1);
    let fallback = format!("{table}[{}]", index + 1);
    let Some(name) = name else {
        c.missing(
            format!("{fallback}.name"),
            &format!("every {position} table needs a name"),
        );
        return fallback;
    };
    check_name(c, format!("{fallback}.name"), name);
    if !valid_name(name) {
        return fallback;
    }
    let label = format!("{table}.{name}");
    if let Some(first) = seen.get(name) {
        c.errors.push(ConfigError::Duplicate {
            path: label,
            name: name.to_string(),
            first: first.clone(),
            second: position,
        });
        // The second one's own errors are told apart by position.
        return fallback;
    }
    seen.insert(name, position);
    label
}

fn check_name(c: &mut Checker, path: String, name: &str) {
    if !valid_name(name) {
        c.invalid(
            path,
            q(name),
            "use only letters, digits, '_' and '-', at least one (the name becomes a Zenoh key \
             chunk)"
                .to_string(),
            "",
        );
    }
}

#[cfg(test)]
mod tests;
