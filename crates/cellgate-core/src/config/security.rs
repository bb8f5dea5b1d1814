//! `[security]`: who may reach the gateway (TLS, client certificates, user names) and what each
//! role may do on the cell's keys.
//!
//! The section names files (CA, certificate, private key, user-password dictionary), never
//! their content: the configuration is published on `@admin` and printed by `check-config`,
//! and key material must appear in neither. Validation reads each file once to tell a missing,
//! unreadable or wrong file at start rather than at the first connection.
//!
//! Roles become zenoh access-control rules for the cell's own keys in `bus::acl`; with roles,
//! anything no role allows is denied.

use std::collections::{BTreeSet, HashMap};
use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use super::BusConfig;
use super::error::{Checker, ConfigError, q};

/// What a role may do, named after the bus routes it opens.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum Permission {
    /// Read status, DI, alarms, punched programs, the job queues, job events and PLC tags;
    /// see the cell's liveliness tokens; receive what PLC and G05 routes publish.
    #[serde(rename = "status.read")]
    StatusRead,
    /// Submit jobs (a get on `submit`), read the queue and follow job events.
    #[serde(rename = "job.submit")]
    JobSubmit,
    /// Cancel jobs (a delete on `job/ID`) and follow job events.
    #[serde(rename = "job.cancel")]
    JobCancel,
    /// Read the program library (get, list).
    #[serde(rename = "program.read")]
    ProgramRead,
    /// Read and write the program library (store, remove, get, list).
    #[serde(rename = "program.write")]
    ProgramWrite,
    /// Output DO (SDO).
    #[serde(rename = "io.do")]
    IoDo,
    /// Write PLC tags.
    #[serde(rename = "plc.tag")]
    PlcTag,
    /// Read and write PLC memory.
    #[serde(rename = "plc.mem")]
    PlcMem,
    /// Send transfers to the PLC.
    #[serde(rename = "plc.transfer")]
    PlcTransfer,
    /// Open G05 streams and send their blocks.
    #[serde(rename = "g05.stream")]
    G05Stream,
    /// Read the gateway's `@admin` document (version, running configuration).
    #[serde(rename = "admin.read")]
    AdminRead,
    /// Release, lock and unlock program revisions (`P/C/program/NAME/release`).
    #[serde(rename = "program.release")]
    ProgramRelease,
    /// Read the cell's history and utilisation (`P/C/history`, `P/C/utilisation`).
    #[serde(rename = "history.read")]
    HistoryRead,
    /// Read the audit trail (`P/C/audit`): who asked for which write, and what came of it.
    #[serde(rename = "audit.read")]
    AuditRead,
    /// Add to the audit trail what a console refused its own users (`P/C/audit/note`): a
    /// console's own identity needs it.
    #[serde(rename = "audit.note")]
    AuditNote,
    /// Drive the simulated machines (`kind = "sim"`): set their DI, raise and reset CNC
    /// alarms, start and stop reads, punch programs, read their state.
    #[serde(rename = "sim.control")]
    SimControl,
    /// Have the gateway read its cell file again and apply what changed
    /// (`P/C/@admin/reload`): machines and PLCs added, removed or changed, settings.
    #[serde(rename = "cell.reload")]
    CellReload,
}

impl Permission {
    /// Every permission, in the order of the enum.
    pub const ALL: [Permission; 17] = [
        Permission::StatusRead,
        Permission::JobSubmit,
        Permission::JobCancel,
        Permission::ProgramRead,
        Permission::ProgramWrite,
        Permission::IoDo,
        Permission::PlcTag,
        Permission::PlcMem,
        Permission::PlcTransfer,
        Permission::G05Stream,
        Permission::AdminRead,
        Permission::ProgramRelease,
        Permission::HistoryRead,
        Permission::AuditRead,
        Permission::AuditNote,
        Permission::SimControl,
        Permission::CellReload,
    ];

    /// The name the cell file uses.
    pub fn name(self) -> &'static str {
        match self {
            Permission::StatusRead => "status.read",
            Permission::JobSubmit => "job.submit",
            Permission::JobCancel => "job.cancel",
            Permission::ProgramRead => "program.read",
            Permission::ProgramWrite => "program.write",
            Permission::ProgramRelease => "program.release",
            Permission::HistoryRead => "history.read",
            Permission::AuditRead => "audit.read",
            Permission::AuditNote => "audit.note",
            Permission::IoDo => "io.do",
            Permission::PlcTag => "plc.tag",
            Permission::PlcMem => "plc.mem",
            Permission::PlcTransfer => "plc.transfer",
            Permission::G05Stream => "g05.stream",
            Permission::AdminRead => "admin.read",
            Permission::SimControl => "sim.control",
            Permission::CellReload => "cell.reload",
        }
    }

    fn known() -> String {
        let names: Vec<&str> = Self::ALL.iter().map(|p| p.name()).collect();
        names.join(", ")
    }
}

impl fmt::Display for Permission {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Permission {
    type Err = ();
    fn from_str(s: &str) -> Result<Self, ()> {
        Self::ALL.into_iter().find(|p| p.name() == s).ok_or(())
    }
}

/// `[security.tls]`: TLS on every listener and connection of the gateway. The same
/// certificate and key serve the listeners and, towards a router that asks for client
/// certificates, the connections.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct TlsConfig {
    /// The CA that signed the clients' (and routers') certificates, PEM.
    pub ca: PathBuf,
    /// The gateway's certificate, PEM.
    pub certificate: PathBuf,
    /// The gateway's private key, PEM.
    pub private_key: PathBuf,
    /// Refuse clients without a certificate signed by `ca` (mutual TLS). Roles by
    /// certificate common name need it.
    pub require_client_certificates: bool,
    /// Check the name of a router the gateway connects to against its certificate.
    pub verify_name_on_connect: bool,
}

/// One `[[security.roles]]`: who (certificate common names, user names) may do what.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Role {
    /// The role's name, unique among the roles.
    pub name: String,
    /// Certificate common names that hold the role (needs `[security.tls]`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub cert_common_names: Vec<String>,
    /// User names that hold the role (needs `security.users_file`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub usernames: Vec<String>,
    /// What the role may do.
    pub permissions: Vec<Permission>,
}

/// `[security]`, validated. The default is none: any session that reaches the gateway may do
/// anything.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize)]
pub struct SecurityConfig {
    /// `[security.tls]`; none by default.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tls: Option<TlsConfig>,
    /// zenoh's user-password dictionary: one `user:password` a line.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub users_file: Option<PathBuf>,
    /// `[[security.roles]]`; with none, access control is off.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub roles: Vec<Role>,
}

impl SecurityConfig {
    /// Whether access control is on: with roles, what no role allows is denied.
    pub fn enforces_roles(&self) -> bool {
        !self.roles.is_empty()
    }

    /// Whether nothing is configured.
    pub fn is_empty(&self) -> bool {
        self.tls.is_none() && self.users_file.is_none() && self.roles.is_empty()
    }
}

// ---- the file's form ----------------------------------------------------------------------

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSecurity {
    tls: Option<RawTls>,
    users_file: Option<PathBuf>,
    #[serde(default)]
    roles: Vec<RawRole>,
}

impl RawSecurity {
    /// Whether TLS or a users file is set: clients then prove who they are.
    pub(super) fn is_configured(&self) -> bool {
        self.tls.is_some() || self.users_file.is_some()
    }

    /// The files the section names, with their keys.
    pub(super) fn files(&self) -> Vec<(&'static str, PathBuf)> {
        let mut out = Vec::new();
        if let Some(f) = &self.users_file {
            out.push(("security.users_file", f.clone()));
        }
        if let Some(t) = &self.tls {
            for (key, f) in [
                ("security.tls.ca", &t.ca),
                ("security.tls.certificate", &t.certificate),
                ("security.tls.private_key", &t.private_key),
            ] {
                if let Some(f) = f {
                    out.push((key, f.clone()));
                }
            }
        }
        out
    }
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTls {
    ca: Option<PathBuf>,
    certificate: Option<PathBuf>,
    private_key: Option<PathBuf>,
    require_client_certificates: Option<bool>,
    verify_name_on_connect: Option<bool>,
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRole {
    name: Option<String>,
    #[serde(default)]
    cert_common_names: Vec<String>,
    #[serde(default)]
    usernames: Vec<String>,
    #[serde(default)]
    permissions: Vec<String>,
}

impl From<&SecurityConfig> for RawSecurity {
    fn from(s: &SecurityConfig) -> Self {
        RawSecurity {
            tls: s.tls.as_ref().map(|t| RawTls {
                ca: Some(t.ca.clone()),
                certificate: Some(t.certificate.clone()),
                private_key: Some(t.private_key.clone()),
                require_client_certificates: Some(t.require_client_certificates),
                verify_name_on_connect: Some(t.verify_name_on_connect),
            }),
            users_file: s.users_file.clone(),
            roles: s
                .roles
                .iter()
                .map(|r| RawRole {
                    name: Some(r.name.clone()),
                    cert_common_names: r.cert_common_names.clone(),
                    usernames: r.usernames.clone(),
                    permissions: r.permissions.iter().map(|p| p.name().to_string()).collect(),
                })
                .collect(),
        }
    }
}

impl RawSecurity {
    /// The typed section; only called once `check_security` found nothing.
    pub(super) fn into_config(self) -> Result<SecurityConfig, ConfigError> {
        let missing = |path: &str| ConfigError::Missing {
            path: path.to_string(),
            hint: "required".to_string(),
        };
        let tls = match self.tls {
            None => None,
            Some(t) => Some(TlsConfig {
                ca: t.ca.ok_or_else(|| missing("security.tls.ca"))?,
                certificate: t
                    .certificate
                    .ok_or_else(|| missing("security.tls.certificate"))?,
                private_key: t
                    .private_key
                    .ok_or_else(|| missing("security.tls.private_key"))?,
                require_client_certificates: t.require_client_certificates.unwrap_or(true),
                verify_name_on_connect: t.verify_name_on_connect.unwrap_or(true),
            }),
        };
        let mut roles = Vec::with_capacity(self.roles.len());
        for (i, r) in self.roles.into_iter().enumerate() {
            let path = format!("security.roles[{}]", i + 1);
            let mut permissions = Vec::with_capacity(r.permissions.len());
            for name in &r.permissions {
                let p = name.parse().map_err(|()| ConfigError::UnknownPermission {
                    path: format!("{path}.permissions"),
                    name: name.clone(),
                    known: Permission::known(),
                })?;
                if !permissions.contains(&p) {
                    permissions.push(p);
                }
            }
            roles.push(Role {
                name: r.name.ok_or_else(|| missing(&format!("{path}.name")))?,
                cert_common_names: r.cert_common_names,
                usernames: r.usernames,
                permissions,
            });
        }
        Ok(SecurityConfig {
            tls,
            users_file: self.users_file,
            roles,
        })
    }
}

// ---- validation ---------------------------------------------------------------------------

/// What a PEM file must hold.
#[derive(Clone, Copy)]
enum Pem {
    Certificate,
    PrivateKey,
}

/// Reads `file` and checks that it holds the PEM block `kind` asks for. The content is never
/// put in an error: a private key must not end up in a log.
fn check_pem(c: &mut Checker, path: &str, file: &Path, kind: Pem) {
    if !c.files {
        return;
    }
    let text = match super::file::read_bounded(file, super::file::MAX_SIDE_FILE) {
        Ok(bytes) => bytes,
        Err(e) => {
            return c
                .errors
                .push(file_error(path, file, format!("cannot read it: {e}")));
        }
    };
    let text = String::from_utf8_lossy(&text);
    let found = match kind {
        Pem::Certificate => text.contains("-----BEGIN CERTIFICATE-----"),
        Pem::PrivateKey => text
            .lines()
            .any(|l| l.starts_with("-----BEGIN ") && l.ends_with("PRIVATE KEY-----")),
    };
    if !found {
        let what = match kind {
            Pem::Certificate => "a PEM certificate (-----BEGIN CERTIFICATE-----)",
            Pem::PrivateKey => "a PEM private key (-----BEGIN ... PRIVATE KEY-----)",
        };
        c.errors
            .push(file_error(path, file, format!("does not hold {what}")));
    }
}

fn file_error(path: &str, file: &Path, problem: String) -> ConfigError {
    ConfigError::File {
        path: path.to_string(),
        file: file.to_path_buf(),
        problem,
    }
}

/// The user names of zenoh's user-password dictionary, checked as zenoh reads it (one
/// `user:password` a line, neither empty). Errors give line numbers, never the line.
fn read_users(c: &mut Checker, file: &Path) -> Option<BTreeSet<String>> {
    let path = "security.users_file";
    if !c.files {
        return None;
    }
    let text = match super::file::read_text_bounded(file, super::file::MAX_SIDE_FILE) {
        Ok(t) => t,
        Err(e) => {
            c.errors
                .push(file_error(path, file, format!("cannot read it: {e}")));
            return None;
        }
    };
    let mut users = BTreeSet::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        match line.split_once(':') {
            Some((user, password)) if !user.trim().is_empty() && !password.trim().is_empty() => {
                users.insert(user.trim().to_string());
            }
            _ => c.errors.push(file_error(
                path,
                file,
                format!(
                    "line {} is not `user:password` with neither empty (zenoh's user-password \
                     dictionary)",
                    n + 1
                ),
            )),
        }
    }
    if users.is_empty() {
        c.errors
            .push(file_error(path, file, "names no user".to_string()));
    }
    Some(users)
}

pub(super) fn check_security(c: &mut Checker, s: &RawSecurity, bus: &BusConfig) {
    let mut mtls = false;
    if let Some(t) = &s.tls {
        for (key, file, kind) in [
            ("ca", &t.ca, Pem::Certificate),
            ("certificate", &t.certificate, Pem::Certificate),
            ("private_key", &t.private_key, Pem::PrivateKey),
        ] {
            let path = format!("security.tls.{key}");
            match file {
                Some(f) => check_pem(c, &path, f, kind),
                None => c.missing(
                    path,
                    "[security.tls] needs ca, certificate and private_key (PEM files)",
                ),
            }
        }
        mtls = t.require_client_certificates.unwrap_or(true);
        for (key, list) in [("listen", &bus.listen), ("connect", &bus.connect)] {
            for (i, ep) in list.iter().enumerate() {
                if !ep.starts_with("tls/") {
                    c.invalid(
                        format!("bus.{key}[{}]", i + 1),
                        q(ep),
                        format!(
                            "[security.tls] is set, but this endpoint is not TLS: sessions on it \
                             would be neither encrypted nor authenticated; use tls/ADDRESS, e.g. \
                             \"tls/{}\"",
                            ep.split_once('/').map_or("127.0.0.1:7447", |(_, a)| a)
                        ),
                        "",
                    );
                }
            }
        }
    }
    let users = s.users_file.as_ref().and_then(|f| read_users(c, f));

    let mut seen: HashMap<&str, usize> = HashMap::new();
    for (i, r) in s.roles.iter().enumerate() {
        let fallback = format!("security.roles[{}]", i + 1);
        let path = match r.name.as_deref() {
            None => {
                c.missing(
                    format!("{fallback}.name"),
                    "every [[security.roles]] needs a name",
                );
                fallback
            }
            Some(name) if !super::valid_name(name) => {
                c.invalid(
                    format!("{fallback}.name"),
                    q(name),
                    "use only letters, digits, '_' and '-', at least one".to_string(),
                    "",
                );
                fallback
            }
            Some(name) => {
                if let Some(first) = seen.insert(name, i) {
                    c.invalid(
                        format!("{fallback}.name"),
                        q(name),
                        format!(
                            "security.roles[{}] has the same name; role names must be unique",
                            first + 1
                        ),
                        "",
                    );
                    fallback
                } else {
                    format!("security.roles.{name}")
                }
            }
        };
        check_role(c, &path, r, s, mtls, users.as_ref());
    }
}

fn check_role(
    c: &mut Checker,
    path: &str,
    r: &RawRole,
    s: &RawSecurity,
    mtls: bool,
    users: Option<&BTreeSet<String>>,
) {
    if r.cert_common_names.is_empty() && r.usernames.is_empty() {
        c.missing(
            format!("{path}.cert_common_names"),
            "a role names who holds it: certificate common names (cert_common_names, with \
             [security.tls]) or user names (usernames, with security.users_file)",
        );
    }
    for (i, cn) in r.cert_common_names.iter().enumerate() {
        if cn.trim().is_empty() {
            c.invalid(
                format!("{path}.cert_common_names[{}]", i + 1),
                q(cn),
                "must not be empty".to_string(),
                "",
            );
        }
    }
    if !r.cert_common_names.is_empty() {
        if s.tls.is_none() {
            c.not_applicable(
                format!("{path}.cert_common_names"),
                "certificate common names identify clients only over TLS with client \
                 certificates: add [security.tls] (ca, certificate, private_key)"
                    .to_string(),
                "",
            );
        } else if !mtls {
            c.not_applicable(
                format!("{path}.cert_common_names"),
                "security.tls.require_client_certificates = false: clients present no \
                 certificate, so no common name identifies them; set it to true"
                    .to_string(),
                "",
            );
        }
    }
    if !r.usernames.is_empty() {
        match (&s.users_file, users) {
            (None, _) => c.not_applicable(
                format!("{path}.usernames"),
                "user names identify clients only with user-password authentication: set \
                 security.users_file"
                    .to_string(),
                "",
            ),
            (Some(_), Some(users)) => {
                for (i, u) in r.usernames.iter().enumerate() {
                    if !users.contains(u.trim()) || u.trim().is_empty() {
                        c.invalid(
                            format!("{path}.usernames[{}]", i + 1),
                            q(u),
                            "not a user of security.users_file".to_string(),
                            "",
                        );
                    }
                }
            }
            // The file could not be read: that error is already reported.
            (Some(_), None) => {}
        }
    }
    if r.permissions.is_empty() {
        c.missing(
            format!("{path}.permissions"),
            &format!("name what the role may do, from: {}", Permission::known()),
        );
    }
    for (i, name) in r.permissions.iter().enumerate() {
        if name.parse::<Permission>().is_err() {
            c.errors.push(ConfigError::UnknownPermission {
                path: format!("{path}.permissions[{}]", i + 1),
                name: name.clone(),
                known: Permission::known(),
            });
        }
    }
}
