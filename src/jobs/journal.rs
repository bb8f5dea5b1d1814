//! The job journal: nothing queued is lost by a restart.
//!
//! Every job lives in an embedded database (redb: one file, ACID, pure Rust) from the moment
//! it is accepted — its request, where its program is, its state, the offset the board
//! acknowledged and its latest event — and its program in the journal's store, so that a
//! restart (SIGTERM or `kill -9`) neither depends on a client sending it again nor on a library
//! program staying as it was. A record is written, and synced, before the submit is answered.
//!
//! The store holds one file per job: inline and fetched programs are written there; library
//! programs are hard-linked (the library replaces a program by rename, so the link keeps the
//! version that was checked; on another file system it is copied). A job does not hold its
//! file open while it waits. Ended jobs are kept up to a limit (their latest event answers
//! `get`s by id, their request id keeps a retried submit from running twice, their program
//! lets a failed job resume); older ones go with their files.
//!
//! Punched programs are journalled from their EOR until the library holds them.
//!
//! Layout of the journal directory: `jobs.redb` and `store/<seq>` files; files left by a
//! crash half-written (`store/.tmp-*`) are removed when the journal opens.

// redb's error type is large (160 bytes); it is built only when a journal write fails, so
// boxing it in every transaction closure would buy nothing.
#![allow(clippy::result_large_err)]

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use redb::{Database, ReadableTable, TableDefinition};
use serde::{Deserialize, Serialize};

/// Job records by sequence number: arrival order across the cell.
const JOBS: TableDefinition<u64, &[u8]> = TableDefinition::new("jobs");
/// Punched programs not yet in the library, by sequence number.
const PUNCHED: TableDefinition<u64, &[u8]> = TableDefinition::new("punched");
/// The next sequence number.
const META: TableDefinition<&str, u64> = TableDefinition::new("meta");
const NEXT_SEQ: &str = "next_seq";

/// Why the journal cannot do its work.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum JournalError {
    #[error("job journal {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("job journal {}: {source}", path.display())]
    Database {
        path: PathBuf,
        #[source]
        source: Box<redb::Error>,
    },
    #[error("job journal {}: record {seq} is unreadable: {source}", path.display())]
    Record {
        path: PathBuf,
        seq: u64,
        #[source]
        source: serde_json::Error,
    },
    /// The journal file is damaged: the gateway does not start on it unless the cell file
    /// says to move it aside (`programs.damaged_journal = "move-aside"`).
    #[error(
        "job journal {} is damaged ({cause}): the jobs it held cannot be read. Move it aside \
         with its store (mv {0} {0}.damaged; mv {1} {1}.damaged: the jobs it held are lost, \
         their program copies stay in {1}.damaged) or set programs.damaged_journal = \
         \"move-aside\" in the cell file to have the gateway do both and start with an empty \
         journal", path.display(), store.display()
    )]
    Damaged {
        path: PathBuf,
        store: PathBuf,
        cause: String,
    },
}

impl JournalError {
    /// Whether the disk (or the file system's quota) is full: the write may succeed once
    /// space is back.
    pub fn is_storage_full(&self) -> bool {
        let io = match self {
            JournalError::Io { source, .. } => Some(source),
            JournalError::Database { source, .. } => match source.as_ref() {
                redb::Error::Io(e) => Some(e),
                _ => None,
            },
            _ => None,
        };
        io.is_some_and(is_storage_full)
    }
}

/// Runs blocking file work (a disk sync takes milliseconds) so that it does not hold up the
/// other tasks of the runtime's worker thread: on a multi-thread runtime through
/// `block_in_place`, which moves them to another worker first; elsewhere (the paused-time
/// tests' current-thread runtime, or no runtime) directly.
fn blocking<T>(f: impl FnOnce() -> T) -> T {
    match tokio::runtime::Handle::try_current() {
        Ok(h) if h.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread => {
            tokio::task::block_in_place(f)
        }
        _ => f(),
    }
}

pub use crate::storage::{OpenError, is_storage_full, open_db, panic_text, quietly};

/// What the gateway does with a journal it finds damaged (`programs.damaged_journal`).
pub use cellgate_core::config::DamagedJournal;

/// Where a job stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum JobState {
    Waiting,
    /// Handed to the link.
    Active,
    Ended,
}

/// Where a job starts in its program when not at the beginning: the stream sent is the
/// program's bytes `[0, header_end)` followed by `[body_start, size)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct StartPoint {
    pub header_end: u64,
    pub body_start: u64,
}

/// A job as the journal keeps it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobRecord {
    pub seq: u64,
    pub id: String,
    pub machine: String,
    /// The client's request id, empty if none.
    pub request_id: String,
    pub name: String,
    pub priority: i32,
    pub accepted_unix_ms: u64,
    /// The program's file in the store, by name.
    pub file: String,
    /// Bytes of the file.
    pub file_len: u64,
    /// Bytes appended after the file (an EOR the request asked for).
    pub suffix: Vec<u8>,
    pub start: Option<StartPoint>,
    pub resume_after_restart: bool,
    /// Seconds the job may take from its start; 0: no deadline.
    #[serde(default)]
    pub deadline_s: u32,
    pub state: JobState,
    /// Program bytes the board acknowledged, as last recorded.
    pub acked: u64,
    /// The job's latest `JobEvent`, protobuf-encoded.
    pub last_event: Vec<u8>,
    /// What it sends and who asked (older journals have none).
    #[serde(default)]
    pub origin: JobOriginRecord,
}

/// What a job sends and who submitted it, as the journal keeps it.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct JobOriginRecord {
    /// The library program, if it came from the library.
    #[serde(default)]
    pub library: String,
    /// The library revision; 0 when not from the library.
    #[serde(default)]
    pub revision: u32,
    /// SHA-256 of the program's bytes, hex.
    #[serde(default)]
    pub sha256: String,
    /// Who submitted it, as the client said.
    #[serde(default)]
    pub user: String,
    #[serde(default)]
    pub via: String,
    /// When it started, ms since the Unix epoch; 0 while it has not.
    #[serde(default)]
    pub started_unix_ms: u64,
}

impl JobRecord {
    /// Where the job came from, as its events carry it.
    pub fn origin_pb(&self) -> cellgate_core::pb::JobOrigin {
        let o = &self.origin;
        cellgate_core::pb::JobOrigin {
            program: Some(cellgate_core::pb::ProgramRef {
                library: o.library.clone(),
                revision: o.revision,
                sha256: o.sha256.clone(),
            }),
            submitted_by: (!o.user.is_empty() || !o.via.is_empty()).then(|| {
                cellgate_core::pb::RequestOrigin {
                    user: o.user.clone(),
                    via: o.via.clone(),
                }
            }),
            queued_unix_ms: self.accepted_unix_ms,
            started_unix_ms: o.started_unix_ms,
            name: self.name.clone(),
        }
    }

    /// The program's size: the file and its suffix.
    pub fn program_size(&self) -> u64 {
        self.file_len + self.suffix.len() as u64
    }

    /// Bytes the job sends: the whole program, or its header and the rest from its start.
    pub fn stream_size(&self) -> u64 {
        match self.start {
            None => self.program_size(),
            Some(s) => s.header_end + self.program_size().saturating_sub(s.body_start),
        }
    }

    /// Where an offset of the stream sent lies in the program: within the header, the body
    /// has not begun, so the job's start block is where it stands.
    pub fn program_offset(&self, stream_offset: u64) -> u64 {
        match self.start {
            None => stream_offset,
            Some(s) if stream_offset < s.header_end => s.body_start,
            Some(s) => s.body_start + (stream_offset - s.header_end),
        }
    }
}

/// A program a CNC punched out, not yet stored in the library.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PunchedRecord {
    pub seq: u64,
    pub machine: String,
    pub o_number: Option<String>,
    pub unix_ms: u64,
    pub text: Vec<u8>,
}

/// What the journal held for a cell when it opened.
#[derive(Debug, Default)]
pub struct Restored {
    /// Per machine: its jobs in arrival order.
    pub jobs: BTreeMap<String, Vec<JobRecord>>,
    pub punched: Vec<PunchedRecord>,
}

/// The journal of one cell. Cheap to clone; every clone writes to the same database.
#[derive(Clone)]
pub struct Journal {
    inner: std::sync::Arc<Inner>,
    path: PathBuf,
    store: PathBuf,
}

struct Inner {
    path: PathBuf,
    /// Taken for every write transaction, for the whole of it (a disk sync), so that
    /// checkpoints reach the database in the order they were made. `None` after a write failed
    /// (a full disk): redb refuses every later transaction on a database that saw an I/O
    /// error, so the next write opens the file again, which recovers it, instead of refusing
    /// writes until a restart.
    db: std::sync::Mutex<Option<Database>>,
    /// Taken only for moments, never across a disk write: a link recording a checkpoint while
    /// a commit syncs the disk must not wait for it (its runtime thread would stall every
    /// other link's task with it).
    pending: std::sync::Mutex<Pending>,
}

/// The progress checkpoints not yet in the database (the latest record of each running job),
/// and how the last write went.
struct Pending {
    /// Why the last write failed, until one succeeds: what status shows.
    fault: Option<String>,
    /// Encoded when committed: a busy link makes up to four a second, and only the last
    /// of each second is written (encoding each was 2 % of the gateway's CPU at 1024 busy
    /// links).
    records: BTreeMap<u64, JobRecord>,
    /// When the last commit began: every checkpoint before it is on disk.
    last_durable: std::time::Instant,
}

impl Inner {
    fn pending(&self) -> std::sync::MutexGuard<'_, Pending> {
        self.pending
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn db(&self) -> std::sync::MutexGuard<'_, Option<Database>> {
        self.db
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// Runs `f` in one durable write transaction that first writes the pending checkpoints, so
/// that what `f` writes or removes supersedes them. A database closed by an earlier failure
/// is opened again first.
fn commit<T>(
    inner: &Inner,
    f: impl FnOnce(&redb::WriteTransaction) -> Result<T, redb::Error>,
) -> Result<T, redb::Error> {
    let mut db = inner.db();
    // Taken under the writer's lock: a checkpoint made from here on waits for the next commit.
    let records = {
        let mut pending = inner.pending();
        pending.last_durable = std::time::Instant::now();
        std::mem::take(&mut pending.records)
    };
    let result = try_commit(&inner.path, &mut db, &records, f);
    let mut pending = inner.pending();
    match &result {
        Ok(_) => {
            if pending.fault.take().is_some() {
                tracing::info!(path = %inner.path.display(), "job journal writable again");
            }
        }
        Err(e) => {
            // Closed, so that the next write starts from the file as it is on disk.
            *db = None;
            pending.fault = Some(e.to_string());
            // Kept for the next commit, unless the job made a newer one meanwhile.
            for (seq, record) in records {
                pending.records.entry(seq).or_insert(record);
            }
        }
    }
    result
}

fn try_commit<T>(
    path: &Path,
    db: &mut Option<Database>,
    records: &BTreeMap<u64, JobRecord>,
    f: impl FnOnce(&redb::WriteTransaction) -> Result<T, redb::Error>,
) -> Result<T, redb::Error> {
    let db = match db {
        Some(db) => db,
        None => db.insert(match open_db(path) {
            Ok(db) => db,
            Err(OpenError::Redb(e)) => return Err(e.into()),
            Err(OpenError::Panicked(text)) => {
                return Err(redb::Error::Io(std::io::Error::other(text)));
            }
        }),
    };
    let tx = db.begin_write()?;
    if !records.is_empty() {
        let mut jobs = tx.open_table(JOBS)?;
        for (seq, record) in records {
            let bytes = serde_json::to_vec(record)
                .map_err(|e| redb::Error::Io(std::io::Error::other(e)))?;
            jobs.insert(*seq, bytes.as_slice())?;
        }
    }
    let out = f(&tx)?;
    tx.commit()?;
    Ok(out)
}

impl Drop for Inner {
    /// A gateway that stops writes the checkpoints it still holds.
    fn drop(&mut self) {
        if !self.pending().records.is_empty()
            && let Err(e) = commit(self, |_| Ok(()))
        {
            tracing::error!(error = %e, "job journal: last progress checkpoints not written");
        }
    }
}

/// Progress checkpoints ([`Journal::put_progress`]) reach the disk at least this often for the
/// whole cell, in one commit: a crash loses at most this much of the acknowledged offsets,
/// never more, and a thousand busy links cost one transaction and one disk sync a second
/// instead of thousands.
pub const PROGRESS_DURABLE_EVERY: std::time::Duration = std::time::Duration::from_secs(1);

impl std::fmt::Debug for Journal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Journal").field("path", &self.path).finish()
    }
}

impl Journal {
    /// Opens (or creates) the journal in `dir`, and removes the half-written store files a
    /// crash may have left. A second gateway on the same journal is refused: the database
    /// file is locked while open.
    pub fn open(dir: &Path) -> Result<Journal, JournalError> {
        Self::open_and_restore(dir, DamagedJournal::Refuse).map(|(j, _)| j)
    }

    /// Opens (or creates) the journal in `dir` and reads back what it holds. A journal that
    /// cannot be read (a damaged or empty database file, an unreadable record) is refused with
    /// [`JournalError::Damaged`], or with `DamagedJournal::MoveAside` renamed aside with its
    /// store (`jobs.redb.damaged-<ms>`, `store.damaged-<ms>`), said loudly, and replaced by an
    /// empty one. Never panics, whatever the file holds.
    pub fn open_and_restore(
        dir: &Path,
        damaged: DamagedJournal,
    ) -> Result<(Journal, Restored), JournalError> {
        match Self::try_open(dir) {
            Err(JournalError::Damaged { path, store, cause })
                if damaged == DamagedJournal::MoveAside =>
            {
                let stamp = cellgate_core::pb::now_ms();
                let aside = dir.join(format!("jobs.redb.damaged-{stamp}"));
                let store_aside = dir.join(format!("store.damaged-{stamp}"));
                let io = |p: &Path| {
                    let p = p.to_path_buf();
                    move |source| JournalError::Io { path: p, source }
                };
                std::fs::rename(&path, &aside).map_err(io(&path))?;
                let programs = std::fs::read_dir(&store).map_or(0, Iterator::count);
                if store.exists() {
                    std::fs::rename(&store, &store_aside).map_err(io(&store))?;
                }
                tracing::error!(
                    journal = %path.display(),
                    moved_to = %aside.display(),
                    store_moved_to = %store_aside.display(),
                    programs,
                    %cause,
                    "job journal damaged: moved aside (programs.damaged_journal = \"move-aside\"); \
                     starting with an empty journal: the jobs it held are not restored"
                );
                Self::try_open(dir)
            }
            other => other,
        }
    }

    fn try_open(dir: &Path) -> Result<(Journal, Restored), JournalError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| JournalError::Io { path, source }
        };
        let store = dir.join("store");
        std::fs::create_dir_all(&store).map_err(io(&store))?;
        for entry in std::fs::read_dir(&store).map_err(io(&store))? {
            let entry = entry.map_err(io(&store))?;
            if entry.file_name().to_string_lossy().starts_with(".tmp-") {
                let _ = std::fs::remove_file(entry.path());
            }
        }
        let path = dir.join("jobs.redb");
        let store_dir = store.clone();
        let damaged = |cause: String| JournalError::Damaged {
            path: path.clone(),
            store: store_dir.clone(),
            cause,
        };
        // redb writes its header when it creates a file: an empty one lost everything.
        if std::fs::metadata(&path).is_ok_and(|m| m.is_file() && m.len() == 0) {
            return Err(damaged("the file is empty".to_string()));
        }
        let db = match open_db(&path) {
            Ok(db) => db,
            Err(OpenError::Panicked(text)) => return Err(damaged(text)),
            Err(OpenError::Redb(redb::DatabaseError::Storage(redb::StorageError::Io(e))))
                if e.kind() != std::io::ErrorKind::InvalidData =>
            {
                return Err(JournalError::Io { path, source: e });
            }
            Err(OpenError::Redb(e @ redb::DatabaseError::DatabaseAlreadyOpen)) => {
                return Err(JournalError::Database {
                    path,
                    source: Box::new(e.into()),
                });
            }
            Err(OpenError::Redb(e)) => return Err(damaged(e.to_string())),
        };
        let journal = Journal {
            inner: std::sync::Arc::new(Inner {
                path: path.clone(),
                db: std::sync::Mutex::new(Some(db)),
                pending: std::sync::Mutex::new(Pending {
                    fault: None,
                    records: BTreeMap::new(),
                    last_durable: std::time::Instant::now(),
                }),
            }),
            path: path.clone(),
            store,
        };
        // Tables exist from the first write on, so that reads never miss them.
        journal.write(|tx| {
            tx.open_table(JOBS)?;
            tx.open_table(PUNCHED)?;
            tx.open_table(META)?;
            Ok(())
        })?;
        let restored = match quietly(|| journal.restore()) {
            Ok(Ok(r)) => r,
            Ok(Err(e @ (JournalError::Record { .. } | JournalError::Database { .. }))) => {
                return Err(damaged(e.to_string()));
            }
            Ok(Err(e)) => return Err(e),
            Err(panic) => return Err(damaged(panic_text(&panic))),
        };
        Ok((journal, restored))
    }

    /// Why the last write failed, while writes fail (a full disk); `None` when the journal
    /// writes.
    pub fn fault(&self) -> Option<String> {
        self.inner.pending().fault.clone()
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The store file of a job.
    pub fn file_path(&self, file: &str) -> PathBuf {
        self.store.join(file)
    }

    fn db_error(&self, e: impl Into<redb::Error>) -> JournalError {
        JournalError::Database {
            path: self.path.clone(),
            source: Box::new(e.into()),
        }
    }

    /// Runs `f` in one durable write transaction, with the pending progress checkpoints.
    fn write<T>(
        &self,
        f: impl FnOnce(&redb::WriteTransaction) -> Result<T, redb::Error>,
    ) -> Result<T, JournalError> {
        blocking(|| commit(&self.inner, f).map_err(|e| self.db_error(e)))
    }

    /// The next sequence number, taken durably.
    pub fn next_seq(&self) -> Result<u64, JournalError> {
        self.write(|tx| {
            let mut meta = tx.open_table(META)?;
            let seq = meta.get(NEXT_SEQ)?.map_or(1, |v| v.value());
            meta.insert(NEXT_SEQ, seq + 1)?;
            Ok(seq)
        })
    }

    /// Writes a program into the store as file `name`, synced, and returns its length.
    pub fn store_bytes(&self, name: &str, parts: &[&[u8]]) -> Result<u64, JournalError> {
        blocking(|| self.store_bytes_now(name, parts))
    }

    fn store_bytes_now(&self, name: &str, parts: &[&[u8]]) -> Result<u64, JournalError> {
        let tmp = self.store.join(format!(".tmp-{name}"));
        let dest = self.store.join(name);
        let io = |source| JournalError::Io {
            path: dest.clone(),
            source,
        };
        let mut file = std::fs::File::create(&tmp).map_err(io)?;
        let mut len = 0u64;
        for part in parts {
            file.write_all(part).map_err(io)?;
            len += part.len() as u64;
        }
        file.sync_all().map_err(io)?;
        drop(file);
        std::fs::rename(&tmp, &dest).map_err(io)?;
        self.sync_store()?;
        Ok(len)
    }

    /// Links (or, on another file system, copies) the file at `from` into the store as
    /// `name`, and returns its length.
    pub fn store_file(&self, name: &str, from: &Path) -> Result<u64, JournalError> {
        blocking(|| self.store_file_now(name, from))
    }

    fn store_file_now(&self, name: &str, from: &Path) -> Result<u64, JournalError> {
        let dest = self.store.join(name);
        let io = |source| JournalError::Io {
            path: dest.clone(),
            source,
        };
        let _ = std::fs::remove_file(&dest);
        // A link put in the file's place after it was looked at (a drop folder is anyone's
        // who may write it) is never followed: link(2) links the link itself, which is
        // refused here, and the copy opens with O_NOFOLLOW and checks what it opened.
        let not_regular = || {
            io(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("{} is not a regular file", from.display()),
            ))
        };
        if std::fs::hard_link(from, &dest).is_ok() {
            if !std::fs::symlink_metadata(&dest).is_ok_and(|m| m.is_file()) {
                let _ = std::fs::remove_file(&dest);
                return Err(not_regular());
            }
        } else {
            use std::os::unix::fs::OpenOptionsExt as _;
            let mut source = std::fs::OpenOptions::new()
                .read(true)
                .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_NOCTTY)
                .open(from)
                .map_err(|e| match e.raw_os_error() {
                    Some(libc::ELOOP) => not_regular(),
                    _ => io(e),
                })?;
            if !source.metadata().map_err(io)?.is_file() {
                return Err(not_regular());
            }
            let tmp = self.store.join(format!(".tmp-{name}"));
            let mut out = std::fs::File::create(&tmp).map_err(io)?;
            std::io::copy(&mut source, &mut out).map_err(io)?;
            out.sync_all().map_err(io)?;
            std::fs::rename(&tmp, &dest).map_err(io)?;
        }
        self.sync_store()?;
        let len = std::fs::metadata(&dest).map_err(io)?.len();
        Ok(len)
    }

    /// The store directory synced, so that a file renamed or linked into it survives a crash.
    fn sync_store(&self) -> Result<(), JournalError> {
        std::fs::File::open(&self.store)
            .and_then(|d| d.sync_all())
            .map_err(|source| JournalError::Io {
                path: self.store.clone(),
                source,
            })
    }

    /// Writes (inserts or replaces) a job record, durably.
    ///
    /// A record that cannot be written now (a full disk) is held and written with the next
    /// commit that succeeds, as a progress checkpoint is, so that a job's end reaches the
    /// journal once space is back instead of being lost.
    pub fn put_job(&self, record: &JobRecord) -> Result<(), JournalError> {
        let bytes = self.encode(record)?;
        let written = self.write(|tx| {
            tx.open_table(JOBS)?.insert(record.seq, bytes.as_slice())?;
            Ok(())
        });
        if written.is_err() {
            self.inner
                .pending()
                .records
                .insert(record.seq, record.clone());
        }
        written
    }

    /// Checkpoints a running job's acknowledged offset. It is held in memory and reaches the
    /// disk with the next commit, which is made here once the last one is
    /// [`PROGRESS_DURABLE_EVERY`] old. The offset on disk is never ahead of what the board
    /// acknowledged, and at most that far behind while the job makes progress.
    pub fn put_progress(&self, record: &JobRecord) -> Result<(), JournalError> {
        {
            let mut pending = self.inner.pending();
            pending.records.insert(record.seq, record.clone());
            if pending.last_durable.elapsed() < PROGRESS_DURABLE_EVERY {
                return Ok(());
            }
            // This call makes the commit: the others of this second only hold theirs.
            pending.last_durable = std::time::Instant::now();
        }
        self.write(|_| Ok(()))
    }

    fn encode(&self, record: &JobRecord) -> Result<Vec<u8>, JournalError> {
        serde_json::to_vec(record).map_err(|source| JournalError::Record {
            path: self.path.clone(),
            seq: record.seq,
            source,
        })
    }

    /// Forgets job records and removes their store files.
    pub fn remove_jobs(&self, records: &[JobRecord]) -> Result<(), JournalError> {
        if records.is_empty() {
            return Ok(());
        }
        self.write(|tx| {
            let mut jobs = tx.open_table(JOBS)?;
            for r in records {
                jobs.remove(r.seq)?;
            }
            Ok(())
        })?;
        for r in records {
            let _ = std::fs::remove_file(self.store.join(&r.file));
        }
        Ok(())
    }

    /// Journals a punched program until the library holds it.
    pub fn put_punched(&self, record: &PunchedRecord) -> Result<(), JournalError> {
        let bytes = serde_json::to_vec(record).map_err(|source| JournalError::Record {
            path: self.path.clone(),
            seq: record.seq,
            source,
        })?;
        self.write(|tx| {
            tx.open_table(PUNCHED)?
                .insert(record.seq, bytes.as_slice())?;
            Ok(())
        })
    }

    pub fn remove_punched(&self, seq: u64) -> Result<(), JournalError> {
        self.write(|tx| {
            tx.open_table(PUNCHED)?.remove(seq)?;
            Ok(())
        })
    }

    /// Everything the journal holds, jobs grouped by machine in arrival order.
    pub fn restore(&self) -> Result<Restored, JournalError> {
        // The checkpoints held in memory first, so that what is read is what was written.
        self.write(|_| Ok(()))?;
        let guard = self.inner.db();
        let Some(db) = guard.as_ref() else {
            return Err(self.db_error(redb::Error::Io(std::io::Error::other(
                "the journal is closed after a failed write",
            ))));
        };
        let tx = db.begin_read().map_err(|e| self.db_error(e))?;
        drop(guard);
        let mut restored = Restored::default();
        let jobs = tx.open_table(JOBS).map_err(|e| self.db_error(e))?;
        for entry in jobs.iter().map_err(|e| self.db_error(e))? {
            let (seq, bytes) = entry.map_err(|e| self.db_error(e))?;
            let seq = seq.value();
            let record: JobRecord =
                serde_json::from_slice(bytes.value()).map_err(|source| JournalError::Record {
                    path: self.path.clone(),
                    seq,
                    source,
                })?;
            restored
                .jobs
                .entry(record.machine.clone())
                .or_default()
                .push(record);
        }
        let punched = tx.open_table(PUNCHED).map_err(|e| self.db_error(e))?;
        for entry in punched.iter().map_err(|e| self.db_error(e))? {
            let (seq, bytes) = entry.map_err(|e| self.db_error(e))?;
            let seq = seq.value();
            let record: PunchedRecord =
                serde_json::from_slice(bytes.value()).map_err(|source| JournalError::Record {
                    path: self.path.clone(),
                    seq,
                    source,
                })?;
            restored.punched.push(record);
        }
        Ok(restored)
    }
}

#[cfg(test)]
mod tests;
