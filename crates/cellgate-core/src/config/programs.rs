//! `[programs]`: the program library and what becomes of punched programs.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::error::{Checker, q};

/// Ended jobs each machine keeps by default (`programs.keep_jobs`): their latest event,
/// request id and program.
pub const DEFAULT_KEEP_JOBS: usize = 256;

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
    /// What the gateway does when the job journal is damaged: refuse to start (the default:
    /// a person decides what to do with the jobs it held) or move it aside and start empty.
    pub damaged_journal: DamagedJournal,
    /// Key prefixes a `JobRequest.key` may name: the gateway fetches a job's program from such
    /// a key with its own session, so only keys every `job.submit` client may have fetched
    /// are listed here (a CAM system's program store, say). Empty (the default): a job
    /// cannot name a key. Never the cell's own keys.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub fetch_prefixes: Vec<String>,
    /// Revisions kept per program: a store drops the oldest beyond it. Never dropped: a
    /// program's latest revision, its latest released one, and locked ones.
    pub keep_revisions: u32,
    /// Revisions older than this many days are dropped as well (with the same exceptions).
    /// None: kept however old.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub keep_revision_days: Option<u32>,
    /// How the library follows its folder while the gateway runs: `"auto"` (inotify, with a
    /// rescan now and then), `"poll"` (a listing every `poll_ms`, for network shares whose
    /// changes raise no events here) or `"off"` (the folder is read once, at start).
    pub watch: Watch,
    /// Extensions a CAM system writes that are not part of a program's name (`O5555.nc` is
    /// program `O5555`); compared without regard to case.
    pub extensions: Vec<String>,
    /// How long a file in the folder must stay the same (size and modification time) before
    /// it is taken, ms: a file still being written is never a revision.
    pub settle_ms: u32,
    /// How often the folder is listed: every poll with `watch = "poll"`; with `"auto"`, the
    /// rescan that catches what the events missed is every 30 of these.
    pub poll_ms: u32,
}

/// How the library follows its folder (`programs.watch`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Watch {
    /// The system's change events (inotify), and a rescan every 30 × `poll_ms`.
    #[default]
    Auto,
    /// A listing every `poll_ms`.
    Poll,
    /// Read once when the gateway starts.
    Off,
}

/// What the gateway does with a damaged job journal (`programs.damaged_journal`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DamagedJournal {
    /// Refuse to start, naming the file and how to recover (exit code 1).
    #[default]
    Refuse,
    /// Rename the journal and its store aside (`*.damaged-<ms>`), log it as an error, and
    /// start with an empty journal.
    MoveAside,
}

impl ProgramsConfig {
    /// Default of `max_size`: 512 MiB.
    pub const DEFAULT_MAX_SIZE: u64 = 512 * 1024 * 1024;
    /// Default of `max_inline`: 16 MiB.
    pub const DEFAULT_MAX_INLINE: u64 = 16 * 1024 * 1024;
    /// Default of `keep_revisions`.
    pub const DEFAULT_KEEP_REVISIONS: u32 = 20;
    /// Default of `settle_ms`.
    pub const DEFAULT_SETTLE_MS: u32 = 1000;
    /// Default of `poll_ms`.
    pub const DEFAULT_POLL_MS: u32 = 2000;

    /// The default `extensions`.
    pub fn default_extensions() -> Vec<String> {
        ["nc", "tap", "txt"].map(String::from).to_vec()
    }

    /// What the folder takes, as the core's [`crate::program::folder`] reads it.
    pub fn folder_rules(&self) -> crate::program::folder::FolderRules {
        crate::program::folder::FolderRules {
            extensions: self.extensions.clone(),
            settle_ms: u64::from(self.settle_ms),
        }
    }

    /// The journal's directory in force.
    pub fn journal_dir(&self) -> PathBuf {
        self.journal
            .clone()
            .unwrap_or_else(|| self.dir.join(".journal"))
    }

    /// The default remote request patterns.
    pub fn default_requests() -> Vec<String> {
        crate::program::punch::DEFAULT_REQUEST_PATTERNS
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
            keep_jobs: DEFAULT_KEEP_JOBS,
            quota_bytes: None,
            quota_files: None,
            punched_retention_days: None,
            damaged_journal: DamagedJournal::Refuse,
            fetch_prefixes: Vec::new(),
            keep_revisions: Self::DEFAULT_KEEP_REVISIONS,
            keep_revision_days: None,
            watch: Watch::Auto,
            extensions: Self::default_extensions(),
            settle_ms: Self::DEFAULT_SETTLE_MS,
            poll_ms: Self::DEFAULT_POLL_MS,
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
    c.range(
        || "programs.keep_revisions".to_string(),
        p.keep_revisions as usize,
        1,
        100_000,
        " revisions",
        "",
    );
    for (key, value) in [
        ("keep_revision_days", p.keep_revision_days.map(u64::from)),
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
    c.range(
        || "programs.settle_ms".to_string(),
        p.settle_ms as usize,
        50,
        600_000,
        " ms",
        "",
    );
    c.range(
        || "programs.poll_ms".to_string(),
        p.poll_ms as usize,
        100,
        3_600_000,
        " ms",
        "",
    );
    for (i, ext) in p.extensions.iter().enumerate() {
        if ext.is_empty() || ext.len() > 16 || !ext.bytes().all(|b| b.is_ascii_alphanumeric()) {
            c.invalid(
                format!("programs.extensions[{i}]"),
                q(ext),
                "must be 1 to 16 letters or digits, without the dot (\"nc\", not \".nc\")"
                    .to_string(),
                "",
            );
        }
    }
    for (i, prefix) in p.fetch_prefixes.iter().enumerate() {
        let chunks_ok = prefix.split('/').all(crate::keys::is_plain_chunk);
        if !chunks_ok {
            c.invalid(
                format!("programs.fetch_prefixes[{i}]"),
                q(prefix),
                "must be a key prefix of plain chunks (no wildcards, no empty chunk)".to_string(),
                "",
            );
        }
    }
    for (i, pattern) in p.requests.iter().enumerate() {
        if let Err(e) = crate::program::punch::RequestPatterns::parse(std::slice::from_ref(pattern))
        {
            let crate::program::punch::PatternError::Invalid { reason, .. } = e;
            c.invalid(
                format!("programs.requests[{i}]"),
                q(pattern),
                reason.to_string(),
                "",
            );
        }
    }
}
