//! `[programs]`: the program library and what becomes of punched programs.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::error::{Checker, q};

/// `[programs]`: where submitted NC programs are kept, and what becomes of punched ones.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ProgramsConfig {
    /// Directory of stored programs; a relative path is taken from the working directory.
    pub dir: PathBuf,
    /// Largest program accepted, bytes.
    pub max_size: u64,
    /// Largest program sent inline in a `JobRequest`, bytes: a larger one goes through the
    /// library (put once, submitted by name), so that no request holds it whole in memory.
    /// `max_size` bounds inline programs too.
    pub max_inline: u64,
    /// Store every program a CNC punches out in the library, under a new name
    /// `<machine>-<O-number>-<UTC time>` (Protocol B family).
    pub store_punched: bool,
    /// Remote request patterns: a punched program that holds nothing but one comment
    /// matching one of these asks for the library program `O<n>` to be sent to the machine.
    /// `{n}` stands for the program number's digits. Empty: punched programs are never
    /// requests.
    pub requests: Vec<String>,
    /// The job journal's directory (jobs and their programs, kept across restarts). Default:
    /// `.journal` in `dir`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub journal: Option<PathBuf>,
    /// Ended jobs each machine keeps in the journal: their latest event answers a `get` by
    /// id, their request id makes a retried submit idempotent, their program lets a failed
    /// job resume.
    pub keep_jobs: usize,
    /// Most bytes the library may hold in all; a store past it is refused. None: unbounded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub quota_bytes: Option<u64>,
    /// Most programs the library may hold; a store past it is refused. None: unbounded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub quota_files: Option<u64>,
    /// Punched programs stored more than this many days ago are removed when the machine
    /// punches the next one. None: kept until removed by hand.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub punched_retention_days: Option<u32>,
}

impl ProgramsConfig {
    pub const DEFAULT_MAX_SIZE: u64 = 512 * 1024 * 1024;
    pub const DEFAULT_MAX_INLINE: u64 = 16 * 1024 * 1024;

    /// The journal's directory in force.
    pub fn journal_dir(&self) -> PathBuf {
        self.journal
            .clone()
            .unwrap_or_else(|| self.dir.join(".journal"))
    }

    /// The default remote request patterns.
    pub fn default_requests() -> Vec<String> {
        crate::jobs::punch::DEFAULT_REQUEST_PATTERNS
            .iter()
            .map(ToString::to_string)
            .collect()
    }
}

impl Default for ProgramsConfig {
    fn default() -> Self {
        ProgramsConfig {
            dir: PathBuf::from("programs"),
            max_size: Self::DEFAULT_MAX_SIZE,
            max_inline: Self::DEFAULT_MAX_INLINE,
            store_punched: true,
            requests: Self::default_requests(),
            journal: None,
            keep_jobs: crate::jobs::KEEP_ENDED,
            quota_bytes: None,
            quota_files: None,
            punched_retention_days: None,
        }
    }
}

pub(super) fn check_programs(c: &mut Checker, p: &ProgramsConfig) {
    if p.dir.as_os_str().is_empty() {
        c.invalid(
            "programs.dir".to_string(),
            "\"\"".to_string(),
            "must name a directory".to_string(),
            "",
        );
    }
    c.range(
        || "programs.keep_jobs".to_string(),
        p.keep_jobs,
        1,
        100_000,
        " jobs",
        "",
    );
    for (key, value) in [
        ("quota_bytes", p.quota_bytes),
        ("quota_files", p.quota_files),
        (
            "punched_retention_days",
            p.punched_retention_days.map(u64::from),
        ),
    ] {
        if value == Some(0) {
            c.invalid(
                format!("programs.{key}"),
                "0".to_string(),
                "must be at least 1 (leave it out for no bound)".to_string(),
                "",
            );
        }
    }
    // Above max_size it is harmless: every program is bounded by max_size as well.
    if p.max_inline == 0 {
        c.invalid(
            "programs.max_inline".to_string(),
            "0".to_string(),
            "must be at least 1 byte".to_string(),
            "",
        );
    }
    if p.max_size == 0 {
        c.invalid(
            "programs.max_size".to_string(),
            "0".to_string(),
            "must be at least 1 byte".to_string(),
            "",
        );
    }
    for (i, pattern) in p.requests.iter().enumerate() {
        if let Err(e) = crate::jobs::punch::RequestPatterns::parse(std::slice::from_ref(pattern)) {
            let crate::jobs::punch::PatternError::Invalid { reason, .. } = e;
            c.invalid(
                format!("programs.requests[{i}]"),
                q(pattern),
                reason.to_string(),
                "",
            );
        }
    }
}
