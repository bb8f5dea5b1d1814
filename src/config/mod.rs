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
//! One file per concern: [`bus`] (the session and telemetry sections), [`programs`],
//! [`transport`] (what carries each link), [`fanuc`] (`[[machines]]`), [`plc`] (`[[plcs]]`),
//! [`security`] (TLS, user names, roles), [`summary`] (what `check-config` prints) and
//! [`error`] (every error, collected at once).

mod bus;
mod error;
mod fanuc;
mod g05;
mod plc;
mod programs;
mod security;
mod summary;
mod transport;

use std::collections::HashMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

pub use self::bus::{BusConfig, BusMode};
use self::bus::{check_bus, check_telemetry};
use self::error::{Checker, q};
pub use self::error::{ConfigError, ConfigErrors};
pub use self::fanuc::{BoardSimConfig, FANUC_BAUD_RATES, Interface, MachineConfig};
use self::fanuc::{RawMachine, check_machine};
pub use self::g05::G05Config;
pub use self::plc::{
    BccCalc, BccCode, BccKind, BccRange, FUJI_BAUD_RATES, FUJI_MAX_STATIONS, PlcConfig, PlcEndCode,
    PlcSimConfig, PlcStartCode, Real, SimTick, TagConfig, TagType,
};
use self::plc::{RawPlc, check_plc};
pub use self::programs::ProgramsConfig;
use self::programs::check_programs;
pub use self::security::{Permission, Role, SecurityConfig, TlsConfig};
use self::security::{RawSecurity, check_security};
pub use self::transport::{TransportConfig, TransportKind};

use crate::telemetry::TelemetryConfig;

/// A whole cell file, validated.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct CellConfig {
    /// Cell id: `[A-Za-z0-9_-]+`. It becomes the key chunk `C` of every key `P/C/...`.
    pub cell: String,
    pub bus: BusConfig,
    pub telemetry: TelemetryConfig,
    pub programs: ProgramsConfig,
    pub machines: Vec<MachineConfig>,
    pub plcs: Vec<PlcConfig>,
    /// TLS, user names and roles; none by default.
    #[serde(skip_serializing_if = "SecurityConfig::is_empty")]
    pub security: SecurityConfig,
}

const DEFAULT_CELL: &str = include_str!("default_cell.toml");

impl CellConfig {
    /// Parses and validates a cell file. `origin` names it in parse errors (a file name).
    pub fn from_toml_str(text: &str, origin: &str) -> Result<CellConfig, ConfigErrors> {
        let raw: RawCell = toml::from_str(text).map_err(|e| ConfigError::Parse {
            origin: origin.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let errors = check(&raw);
        if !errors.is_empty() {
            return Err(ConfigErrors(errors));
        }
        raw.into_config()
    }

    /// Reads, parses and validates the cell file at `path`.
    pub fn load(path: &Path) -> Result<CellConfig, ConfigErrors> {
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| ConfigError::Read {
            origin: origin.clone(),
            reason: e.to_string(),
        })?;
        Self::from_toml_str(&text, &origin)
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
    machines: Vec<RawMachine>,
    #[serde(default)]
    plcs: Vec<RawPlc>,
    #[serde(default)]
    security: RawSecurity,
}

impl From<CellConfig> for RawCell {
    fn from(c: CellConfig) -> Self {
        RawCell {
            cell: Some(c.cell),
            bus: c.bus,
            telemetry: c.telemetry,
            programs: c.programs,
            machines: c
                .machines
                .into_iter()
                .map(|m| RawMachine::from(&m))
                .collect(),
            plcs: c.plcs.into_iter().map(|p| RawPlc::from(&p)).collect(),
            security: RawSecurity::from(&c.security),
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
            machines,
            plcs,
            security,
        })
    }
}

fn valid_name(s: &str) -> bool {
    !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

fn check(raw: &RawCell) -> Vec<ConfigError> {
    let mut c = Checker { errors: Vec::new() };
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
    check_security(&mut c, &raw.security, &raw.bus);

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
    }
    for (p, label) in raw.plcs.iter().zip(plc_labels) {
        check_plc(&mut c, label, p);
    }
    c.errors
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
