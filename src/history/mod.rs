//! The cell's history and audit trail: records kept in an embedded database
//! (`[history]`), written in batches off the runtime's threads, read back by time, machine,
//! kind and tag, and dropped by retention.
//!
//! Recording never waits: [`History::record`] numbers the record and hands it to the writer
//! task, which commits what came at least once a second (as the job journal does its
//! progress checkpoints), so a busy cell pays one disk sync a second for its history, not
//! one per event. What a `kill -9` loses is the last second. While the disk refuses writes
//! (full), records wait in memory up to [`MAX_WAITING`] and are written once it takes them
//! again; past that the oldest are dropped, counted and logged: the gateway serves on.
//!
//! The store: `records` by (time, number) holds each record; `seqs` finds a record's time
//! by its number (for paging); `subjects` indexes records by `machine/kind`, by `#kind` and,
//! for tag values, by `plc/tag`, so that a query for one machine, one kind or one tag reads
//! only its own records. The audit trail has the same four tables of its own.
//!
//! Refused requests are gathered before they reach the audit
//! ([`cellgate_core::history::refusals`]: the first of a kind at once, the rest of its
//! minute as one record with a count), indexed under a subject of their own, and bounded by
//! `max_refusals` apart from the writes that were taken. Every record dropped before its
//! retention days (the writer behind, the store full too long, `max_records`,
//! `max_refusals`) is counted on `cellgate.history.dropped` and said in the log.

// redb's error is large; it stays inside this module's transactions.
#![allow(clippy::result_large_err)]

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use prost::Message;
use redb::{Database, ReadableTable, ReadableTableMetadata, TableDefinition};
use tokio::sync::{mpsc, oneshot};
use tokio_util::sync::CancellationToken;

use cellgate_core::codes::BusCode;
use cellgate_core::config::HistoryConfig;
use cellgate_core::history::refusals::Refusals;
use cellgate_core::history::{HistoryQuery, Mark, Order};
use cellgate_core::pb::{self, HistoryKind, history_record::Record};

mod read;
use read::{read_gateway_marks, read_marks, read_page};

/// Records waiting for the disk, at most; beyond, the oldest are dropped and counted.
pub const MAX_WAITING: usize = 65_536;
/// How often the writer commits what came.
const COMMIT_EVERY: Duration = Duration::from_secs(1);
/// Records written in one transaction, at most.
const BATCH: usize = 8192;
/// How often retention runs.
const PRUNE_EVERY: Duration = Duration::from_secs(600);

type Records = TableDefinition<'static, (u64, u64), &'static [u8]>;
type Seqs = TableDefinition<'static, u64, u64>;
/// (subject, time, number) → the record's [`summary`], so that utilisation reads the index
/// alone.
type Subjects = TableDefinition<'static, (&'static str, u64, u64), u64>;
type Counts = TableDefinition<'static, &'static str, u64>;

/// The four tables of one log (history or audit).
#[derive(Clone, Copy)]
struct Tables {
    records: Records,
    seqs: Seqs,
    subjects: Subjects,
    counts: Counts,
}

const HISTORY: Tables = Tables {
    records: TableDefinition::new("records"),
    seqs: TableDefinition::new("seqs"),
    subjects: TableDefinition::new("subjects"),
    counts: TableDefinition::new("counts"),
};

const AUDIT: Tables = Tables {
    records: TableDefinition::new("audit_records"),
    seqs: TableDefinition::new("audit_seqs"),
    subjects: TableDefinition::new("audit_subjects"),
    counts: TableDefinition::new("audit_counts"),
};

/// Which log a record goes to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Log {
    /// `P/C/history`.
    History,
    /// `P/C/audit`.
    Audit,
}

impl Log {
    fn tables(self) -> Tables {
        match self {
            Log::History => HISTORY,
            Log::Audit => AUDIT,
        }
    }
}

/// Why the history could not be opened, written or read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum HistoryError {
    /// The cell file turned it off.
    #[error("this gateway keeps no history ([history] enabled = false in its cell file)")]
    Disabled,
    #[error("history store {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("history store {}: {source}", path.display())]
    Database {
        path: PathBuf,
        #[source]
        source: Box<redb::Error>,
    },
    /// The query reads a record number the store does not have.
    #[error("no record {0} in the store (it may have been dropped by retention)")]
    NoSuchRecord(u64),
    /// The audit trail cannot be written now: a write would go unaudited, so none is taken.
    #[error(
        "not taken: the audit trail cannot be written ({reason}); writes are refused until it \
         can, so that none goes unaudited"
    )]
    AuditUnwritable { reason: String, full: bool },
}

impl BusCode for HistoryError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            HistoryError::Disabled => pb::ErrorCode::Unavailable,
            HistoryError::NoSuchRecord(_) => pb::ErrorCode::NotFound,
            HistoryError::Io { source, .. } if crate::storage::is_storage_full(source) => {
                pb::ErrorCode::StorageFull
            }
            HistoryError::AuditUnwritable { full: true, .. } => pb::ErrorCode::StorageFull,
            HistoryError::Io { .. }
            | HistoryError::Database { .. }
            | HistoryError::AuditUnwritable { .. } => pb::ErrorCode::StorageFailed,
        }
    }
}

/// A record on its way to the writer.
struct Waiting {
    log: Log,
    record: pb::HistoryRecord,
}

/// The numbering of one log: numbers and times both increase, so a record's number orders
/// it in time too.
#[derive(Debug, Default)]
struct Clock {
    next_seq: u64,
    last_ms: u64,
}

struct Inner {
    path: PathBuf,
    /// The store; `None` once a write failed on I/O, opened again at its next use (redb
    /// refuses every transaction after an I/O error until the handle is dropped).
    db: Mutex<Option<Arc<Database>>>,
    tx: mpsc::Sender<Waiting>,
    /// Asks the writer to commit what it holds now; answered once it tried.
    flush: mpsc::Sender<oneshot::Sender<()>>,
    clocks: Mutex<[Clock; 2]>,
    /// Retention and shifts: replaced by a reload ([`History::set_config`]).
    config: Mutex<(HistoryConfig, Vec<u16>)>,
    /// Records dropped: the channel was full, or too many waited for the disk.
    dropped: AtomicU64,
    /// Records handed to the writer, and records it wrote (or dropped), for [`History::settled`].
    handed: AtomicU64,
    written: AtomicU64,
    /// Why the last commit failed, while commits fail.
    fault: Mutex<Option<String>>,
    /// Whether that fault is a full disk.
    fault_full: AtomicBool,
    /// Refused requests of the current minute, gathered.
    refusals: Mutex<Refusals>,
}

/// The cell's history: cheap to clone; a disabled one records nothing and answers
/// [`HistoryError::Disabled`].
#[derive(Clone, Default)]
pub struct History {
    inner: Option<Arc<Inner>>,
}

impl std::fmt::Debug for History {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.inner {
            None => f.write_str("History(off)"),
            Some(i) => write!(f, "History({})", i.path.display()),
        }
    }
}

/// What the gateway's status says of the history.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct HistoryHealth {
    /// Records dropped since the gateway started.
    pub dropped: u64,
    /// Why it cannot write now, if it cannot.
    pub fault: Option<String>,
}

impl History {
    /// A history that keeps nothing.
    pub fn disabled() -> Self {
        History { inner: None }
    }

    /// Opens (or creates) the store in `dir` and starts its writer, which runs until `stop`
    /// and then writes what it holds and a `stopped` record. A store that cannot be read
    /// (damaged) is moved aside, loudly, and a new one started: the history is a record,
    /// not what production waits for. The file work runs off the runtime's threads; the
    /// writer is spawned on the current runtime.
    pub async fn open(
        dir: &Path,
        config: &HistoryConfig,
        stop: CancellationToken,
    ) -> Result<(History, tokio::task::JoinHandle<()>), HistoryError> {
        let path = dir.join("history.redb");
        let db = {
            let (dir, path) = (dir.to_path_buf(), path.clone());
            tokio::task::spawn_blocking(move || open_store(&dir, &path))
                .await
                .map_err(|e| HistoryError::Io {
                    path: PathBuf::new(),
                    source: std::io::Error::other(e.to_string()),
                })??
        };
        let db = Arc::new(db);
        let clocks = {
            let db = Arc::clone(&db);
            let p = path.clone();
            tokio::task::spawn_blocking(move || -> Result<[Clock; 2], HistoryError> {
                Ok([clock(&db, HISTORY, &p)?, clock(&db, AUDIT, &p)?])
            })
            .await
            .map_err(|e| HistoryError::Io {
                path: path.clone(),
                source: std::io::Error::other(e.to_string()),
            })??
        };
        let (tx, rx) = mpsc::channel(16_384);
        let (flush, flushes) = mpsc::channel(1024);
        let inner = Arc::new(Inner {
            path,
            db: Mutex::new(Some(db)),
            tx,
            flush,
            clocks: Mutex::new(clocks),
            config: Mutex::new((config.clone(), config.shift_minutes())),
            dropped: AtomicU64::new(0),
            handed: AtomicU64::new(0),
            written: AtomicU64::new(0),
            fault: Mutex::new(None),
            fault_full: AtomicBool::new(false),
            refusals: Mutex::new(Refusals::default()),
        });
        let history = History {
            inner: Some(Arc::clone(&inner)),
        };
        history.gateway(pb::gateway_record::Event::Started);
        let writer = tokio::spawn(write_loop(inner, rx, flushes, stop));
        Ok((history, writer))
    }

    /// Whether it keeps anything.
    pub fn enabled(&self) -> bool {
        self.inner.is_some()
    }

    /// The shift starts in force, minutes after midnight UTC.
    pub fn shifts(&self) -> Vec<u16> {
        self.inner.as_ref().map_or(Vec::new(), |i| i.config().1)
    }

    /// Takes a reloaded `[history]`'s retention, bounds and shifts (not its place, which is
    /// fixed while the gateway runs): the next trim keeps what they say.
    pub fn set_config(&self, config: &HistoryConfig) {
        if let Some(i) = &self.inner {
            *i.config.lock().unwrap_or_else(|p| p.into_inner()) =
                (config.clone(), config.shift_minutes());
        }
    }

    /// Dropped records and the current fault.
    pub fn health(&self) -> HistoryHealth {
        match &self.inner {
            None => HistoryHealth::default(),
            Some(i) => HistoryHealth {
                dropped: i.dropped.load(Ordering::Relaxed),
                fault: i.fault.lock().map(|f| f.clone()).unwrap_or(None),
            },
        }
    }

    /// Records `record` about `machine` (a machine or PLC link; empty for the gateway's own)
    /// now. Never waits: a full queue drops the record and counts it.
    pub fn record(&self, log: Log, machine: &str, kind: HistoryKind, record: Record) {
        self.record_at(log, machine, kind, record, pb::now_ms());
    }

    /// [`Self::record`] at a time of the caller's (a generated or imported history). A time
    /// before the log's last record is taken as that record's: numbers and times increase
    /// together.
    pub fn record_at(
        &self,
        log: Log,
        machine: &str,
        kind: HistoryKind,
        record: Record,
        unix_ms: u64,
    ) {
        let Some(inner) = &self.inner else { return };
        let (seq, unix_ms) = {
            let Ok(mut clocks) = inner.clocks.lock() else {
                return;
            };
            let c = &mut clocks[log as usize];
            let now = unix_ms.max(c.last_ms);
            c.last_ms = now;
            c.next_seq += 1;
            (c.next_seq, now)
        };
        let record = pb::HistoryRecord {
            unix_ms,
            seq,
            machine: machine.to_string(),
            kind: kind as i32,
            record: Some(record),
        };
        if inner.tx.try_send(Waiting { log, record }).is_ok() {
            inner.handed.fetch_add(1, Ordering::Relaxed);
        } else {
            let n = inner.dropped.fetch_add(1, Ordering::Relaxed) + 1;
            dropped(log, "behind", 1);
            if n.is_power_of_two() {
                tracing::warn!(
                    dropped = n,
                    "history: the writer falls behind; records dropped"
                );
            }
        }
    }

    /// Waits until every record handed over so far reached the store (or `limit` passed):
    /// for a generated history and tests.
    pub async fn settled(&self, limit: Duration) -> bool {
        let Some(inner) = &self.inner else {
            return true;
        };
        let started = std::time::Instant::now();
        while started.elapsed() < limit {
            if inner.written.load(Ordering::Relaxed) >= inner.handed.load(Ordering::Relaxed) {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        false
    }

    /// Records handed to the writer and not yet written: how far it is behind.
    pub fn backlog(&self) -> u64 {
        self.inner.as_ref().map_or(0, |i| {
            i.handed
                .load(Ordering::Relaxed)
                .saturating_sub(i.written.load(Ordering::Relaxed))
        })
    }

    /// Records a history event of `machine`.
    pub fn event(&self, machine: &str, kind: HistoryKind, record: Record) {
        self.record(Log::History, machine, kind, record);
    }

    /// Records the gateway's own event.
    pub fn gateway(&self, event: pb::gateway_record::Event) {
        self.event(
            "",
            HistoryKind::Gateway,
            Record::Gateway(pb::GatewayRecord {
                event: event as i32,
                version: env!("CARGO_PKG_VERSION").to_string(),
            }),
        );
    }

    /// Records an audit record about `machine` (empty for the library's). A refusal (not
    /// `ok`) is gathered with the others of its kind and minute.
    pub fn audit(&self, machine: &str, record: pb::AuditRecord) {
        let Some(inner) = &self.inner else { return };
        if record.ok {
            return self.audit_now(machine, record);
        }
        let now = pb::now_ms();
        let out = inner
            .refusals
            .lock()
            .map(|mut r| r.refuse(machine, record, now))
            .unwrap_or_default();
        for (m, r) in out {
            self.audit_now(&m, r);
        }
    }

    /// Whether a write may be taken: not while the store refuses its commits, since the
    /// write's audit record would wait in memory, and a `kill -9` meanwhile would lose it.
    pub fn audit_writable(&self) -> Result<(), HistoryError> {
        let Some(inner) = &self.inner else {
            return Ok(());
        };
        match inner.fault.lock().ok().and_then(|f| f.clone()) {
            None => Ok(()),
            Some(reason) => Err(HistoryError::AuditUnwritable {
                reason,
                full: inner.fault_full.load(Ordering::Relaxed),
            }),
        }
    }

    /// Waits (at most `within`) until the writer committed every record recorded before
    /// this call, or tried to: what a write's answer waits for, so that a client told "done"
    /// finds the write in the audit trail after a `kill -9`. A store that cannot write (a
    /// full disk) keeps the records in memory, as ever; the answer does not wait for it.
    pub async fn committed(&self, within: Duration) {
        let Some(inner) = &self.inner else { return };
        let (done, wait) = oneshot::channel();
        if inner.flush.try_send(done).is_ok() {
            let _ = tokio::time::timeout(within, wait).await;
        }
    }

    /// Records an audit record that was gathered already (a console's note), as it is.
    pub fn audit_gathered(&self, machine: &str, record: pb::AuditRecord) {
        self.audit_now(machine, record);
    }

    fn audit_now(&self, machine: &str, record: pb::AuditRecord) {
        self.record(
            Log::Audit,
            machine,
            HistoryKind::Audit,
            Record::Audit(record),
        );
    }

    /// Writes the summaries of the refusals of a minute that is over.
    fn flush_refusals(&self) {
        let Some(inner) = &self.inner else { return };
        let now = pb::now_ms();
        let out = inner
            .refusals
            .lock()
            .map(|mut r| r.flush(now))
            .unwrap_or_default();
        for (m, r) in out {
            self.audit_now(&m, r);
        }
    }

    /// The records `query` asks for from `log`: at most `query.limit`, oldest first.
    pub async fn query(
        &self,
        log: Log,
        query: HistoryQuery,
    ) -> Result<pb::HistoryPage, HistoryError> {
        let inner = self.inner.clone().ok_or(HistoryError::Disabled)?;
        blocking(&inner.path.clone(), move || read_page(&inner, log, &query)).await
    }

    /// The record of job `job_id` of `machine`, if the history keeps it: how a job ended
    /// when the machine no longer keeps it (a reload removed the machine, or 256 newer jobs
    /// pushed it out). Reads the machine's job records newest first, a page at a time.
    pub async fn find_job(
        &self,
        machine: &str,
        job_id: &str,
    ) -> Result<Option<pb::JobHistory>, HistoryError> {
        const PAGE: usize = 1000;
        /// Jobs looked through at most: a year of a busy machine.
        const MAX_PAGES: usize = 200;
        let mut query = HistoryQuery {
            from_ms: 0,
            to_ms: pb::now_ms(),
            machines: Some(BTreeSet::from([machine.to_string()])),
            kinds: Some(BTreeSet::from([HistoryKind::Job as i32])),
            tags: BTreeSet::new(),
            limit: PAGE,
            after: 0,
            order: Order::Newest,
            bucket: cellgate_core::history::Bucket::default(),
        };
        // A job that just ended may still be on its way to the store.
        self.settled(Duration::from_secs(2)).await;
        for _ in 0..MAX_PAGES {
            let page = self.query(Log::History, query.clone()).await?;
            let found = page.records.into_iter().find_map(|r| match r.record {
                Some(Record::Job(j)) if j.job_id == job_id => Some(j),
                _ => None,
            });
            if found.is_some() || !page.more {
                return Ok(found);
            }
            query.after = page.next_after;
        }
        Ok(None)
    }

    /// The gateway's own marks over `[from, to]` (with the one before `from`): its starts,
    /// stops and alive records, which utilisation merges into every machine's.
    pub async fn gateway_marks(&self, from_ms: u64, to_ms: u64) -> Result<Vec<Mark>, HistoryError> {
        let inner = self.inner.clone().ok_or(HistoryError::Disabled)?;
        blocking(&inner.path.clone(), move || {
            read_gateway_marks(&inner, from_ms, to_ms)
        })
        .await
    }

    /// What utilisation reads of one machine over `[from, to]`: its activity marks (with the
    /// one before `from`), its jobs' ends, and the part counter's values (with the one before
    /// `from`). The gateway's marks are [`Self::gateway_marks`].
    pub async fn machine_marks(
        &self,
        machine: String,
        counter: Option<String>,
        from_ms: u64,
        to_ms: u64,
    ) -> Result<MachineMarks, HistoryError> {
        let inner = self.inner.clone().ok_or(HistoryError::Disabled)?;
        blocking(&inner.path.clone(), move || {
            read_marks(&inner, &machine, counter.as_deref(), from_ms, to_ms)
        })
        .await
    }
}

/// Marks in time order; at one instant a start comes before the states it starts with.
pub fn sort_marks(marks: &mut [Mark]) {
    marks.sort_by_key(|m| {
        let (t, order) = match *m {
            Mark::Stopped(t) => (t, 0),
            Mark::Started(t) => (t, 1),
            Mark::Alive(t) => (t, 2),
            Mark::Activity(t, _) => (t, 3),
        };
        (t, order)
    });
}

/// What [`History::machine_marks`] reads.
#[derive(Debug, Default)]
pub struct MachineMarks {
    pub marks: Vec<Mark>,
    pub jobs: Vec<(u64, bool)>,
    pub parts: Vec<(u64, f64)>,
}

async fn blocking<T: Send + 'static>(
    path: &Path,
    f: impl FnOnce() -> Result<T, HistoryError> + Send + 'static,
) -> Result<T, HistoryError> {
    tokio::task::spawn_blocking(f).await.unwrap_or_else(|e| {
        Err(HistoryError::Io {
            path: path.to_path_buf(),
            source: std::io::Error::other(e.to_string()),
        })
    })
}

fn db_error(path: &Path, e: impl Into<redb::Error>) -> HistoryError {
    let e: redb::Error = e.into();
    match e {
        redb::Error::Io(source) => HistoryError::Io {
            path: path.to_path_buf(),
            source,
        },
        other => HistoryError::Database {
            path: path.to_path_buf(),
            source: Box::new(other),
        },
    }
}

/// Opens the store, moving a damaged one aside.
fn open_store(dir: &Path, path: &Path) -> Result<Database, HistoryError> {
    std::fs::create_dir_all(dir).map_err(|source| HistoryError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let empty = std::fs::metadata(path).is_ok_and(|m| m.is_file() && m.len() == 0);
    let cause = if empty {
        "the file is empty".to_string()
    } else {
        use crate::storage::OpenError;
        match crate::storage::open_db(path) {
            Ok(db) => match check_tables(&db) {
                Ok(()) => return Ok(db),
                Err(cause) => cause,
            },
            Err(OpenError::Redb(redb::DatabaseError::Storage(redb::StorageError::Io(e))))
                if e.kind() != std::io::ErrorKind::InvalidData =>
            {
                return Err(HistoryError::Io {
                    path: path.to_path_buf(),
                    source: e,
                });
            }
            Err(OpenError::Redb(e @ redb::DatabaseError::DatabaseAlreadyOpen)) => {
                return Err(db_error(path, e));
            }
            Err(OpenError::Redb(e)) => e.to_string(),
            Err(OpenError::Panicked(text)) => text,
        }
    };
    let aside = path.with_extension(format!("redb.damaged-{}", pb::now_ms()));
    std::fs::rename(path, &aside).map_err(|source| HistoryError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    tracing::error!(
        store = %path.display(),
        moved_to = %aside.display(),
        %cause,
        "history store damaged: moved aside; starting a new one (the records it held are \
         in the file moved aside)"
    );
    match crate::storage::open_db(path) {
        Ok(db) => check_tables(&db)
            .map(|()| db)
            .map_err(|cause| HistoryError::Io {
                path: path.to_path_buf(),
                source: std::io::Error::other(cause),
            }),
        Err(_) => Err(HistoryError::Io {
            path: path.to_path_buf(),
            source: std::io::Error::other("a new store could not be created"),
        }),
    }
}

/// Creates the tables and reads each once, so that a damaged file shows now, not later.
fn check_tables(db: &Database) -> Result<(), String> {
    let run = || -> Result<(), redb::Error> {
        let tx = db.begin_write()?;
        for t in [HISTORY, AUDIT] {
            tx.open_table(t.records)?;
            tx.open_table(t.seqs)?;
            tx.open_table(t.subjects)?;
            tx.open_table(t.counts)?;
        }
        tx.commit()?;
        let tx = db.begin_read()?;
        for t in [HISTORY, AUDIT] {
            let records = tx.open_table(t.records)?;
            if let Some(last) = records.last()? {
                pb::HistoryRecord::decode(last.1.value())
                    .map_err(|e| redb::Error::Io(std::io::Error::other(e.to_string())))?;
            }
        }
        Ok(())
    };
    match crate::storage::quietly(run) {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(e.to_string()),
        Err(p) => Err(crate::storage::panic_text(&p)),
    }
}

/// The numbering to go on from: the last record's number and time.
fn clock(db: &Database, t: Tables, path: &Path) -> Result<Clock, HistoryError> {
    let tx = db.begin_read().map_err(|e| db_error(path, e))?;
    let records = tx.open_table(t.records).map_err(|e| db_error(path, e))?;
    let seqs = tx.open_table(t.seqs).map_err(|e| db_error(path, e))?;
    let last_ms = records
        .last()
        .map_err(|e| db_error(path, e))?
        .map_or(0, |(k, _)| k.value().0);
    let next_seq = seqs
        .last()
        .map_err(|e| db_error(path, e))?
        .map_or(0, |(k, _)| k.value());
    Ok(Clock { next_seq, last_ms })
}

/// The index entries of a record: `machine/kind`, `#kind`, and for a tag value `plc/tag`.
fn subjects(r: &pb::HistoryRecord) -> Vec<String> {
    let mut s = vec![format!("{}/{}", r.machine, r.kind), format!("#{}", r.kind)];
    if let Some(Record::Tag(t)) = &r.record {
        s.push(tag_subject(&t.plc, &t.name));
    }
    if let Some(k) = counted_subject(r) {
        s.push(k.to_string());
    }
    s
}

/// The index subject of refused requests in the audit (no machine or kind starts with `!`).
const REFUSED: &str = "!refused";

/// The subject whose records are counted and bounded, if any: a tag's values (bounded by
/// `tag_values`) or the audit's refusals (by `max_refusals`).
fn counted_subject(r: &pb::HistoryRecord) -> Option<std::borrow::Cow<'static, str>> {
    match &r.record {
        Some(Record::Tag(t)) => Some(tag_subject(&t.plc, &t.name).into()),
        Some(Record::Audit(a)) if !a.ok => Some(REFUSED.into()),
        _ => None,
    }
}

/// What utilisation needs of a record, kept in its index entries: a machine's activity, a
/// job's end (1 completed, 0 not), a tag's value (its f64 bits; NaN without one), the
/// gateway's event.
fn summary(r: &pb::HistoryRecord) -> u64 {
    match &r.record {
        Some(Record::Cnc(a)) => u64::try_from(*a).unwrap_or(0),
        Some(Record::Job(j)) => u64::from(j.outcome() == pb::JobOutcome::Completed),
        Some(Record::Tag(t)) => t.value.unwrap_or(f64::NAN).to_bits(),
        Some(Record::Gateway(g)) => u64::try_from(g.event).unwrap_or(0),
        _ => 0,
    }
}

fn tag_subject(plc: &str, name: &str) -> String {
    format!("{plc}/{name}")
}

async fn write_loop(
    inner: Arc<Inner>,
    mut rx: mpsc::Receiver<Waiting>,
    mut flushes: mpsc::Receiver<oneshot::Sender<()>>,
    stop: CancellationToken,
) {
    let mut waiting: Vec<Waiting> = Vec::new();
    let mut tick = tokio::time::interval(COMMIT_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut alive = tokio::time::interval(Duration::from_millis(
        cellgate_core::history::ALIVE_EVERY_MS,
    ));
    alive.tick().await;
    let mut prune = tokio::time::interval(PRUNE_EVERY);
    loop {
        tokio::select! {
            () = stop.cancelled() => break,
            got = rx.recv() => match got {
                Some(w) => {
                    waiting.push(w);
                    if waiting.len() >= BATCH {
                        waiting = commit(&inner, waiting).await;
                    }
                }
                None => break,
            },
            Some(asked) = flushes.recv() => {
                // Every record recorded before the ask is in the channel by now; those asking
                // meanwhile share the commit.
                while let Ok(w) = rx.try_recv() {
                    waiting.push(w);
                }
                let mut asking = vec![asked];
                while let Ok(a) = flushes.try_recv() {
                    asking.push(a);
                }
                while let Ok(w) = rx.try_recv() {
                    waiting.push(w);
                }
                waiting = commit(&inner, waiting).await;
                for a in asking {
                    let _ = a.send(());
                }
            }
            _ = tick.tick() => {
                History { inner: Some(Arc::clone(&inner)) }.flush_refusals();
                if !waiting.is_empty() {
                    waiting = commit(&inner, waiting).await;
                }
            }
            _ = alive.tick() => History { inner: Some(Arc::clone(&inner)) }
                .gateway(pb::gateway_record::Event::Alive),
            _ = prune.tick() => {
                let i = Arc::clone(&inner);
                let _ = tokio::task::spawn_blocking(move || prune_logs(&i)).await;
            }
        }
    }
    History {
        inner: Some(Arc::clone(&inner)),
    }
    .gateway(pb::gateway_record::Event::Stopped);
    while let Ok(w) = rx.try_recv() {
        waiting.push(w);
    }
    let left = commit(&inner, waiting).await;
    if !left.is_empty() {
        tracing::error!(
            records = left.len(),
            "history: records not written when the gateway stopped (the disk refused them)"
        );
    }
}

/// Writes `waiting` in transactions of at most [`BATCH`]; returns what could not be written
/// (to try again), bounded by [`MAX_WAITING`].
async fn commit(inner: &Arc<Inner>, waiting: Vec<Waiting>) -> Vec<Waiting> {
    let i = Arc::clone(inner);
    let result = tokio::task::spawn_blocking(move || {
        let mut waiting = waiting;
        while !waiting.is_empty() {
            let rest = waiting.split_off(waiting.len().min(BATCH));
            if let Err(e) = write_batch(&i, &waiting) {
                i.after_error(&e);
                waiting.extend(rest);
                return (waiting, Some(e));
            }
            i.written.fetch_add(waiting.len() as u64, Ordering::Relaxed);
            waiting = rest;
        }
        (waiting, None)
    })
    .await;
    let (mut left, error) = match result {
        Ok(r) => r,
        Err(e) => {
            tracing::error!(error = %e, "history: the writer's task failed");
            return Vec::new();
        }
    };
    let full = matches!(&error, Some(HistoryError::Io { source, .. }) if crate::storage::is_storage_full(source));
    inner.fault_full.store(full, Ordering::Relaxed);
    let was = inner.fault.lock().ok().and_then(|mut f| match &error {
        Some(e) => f.replace(e.to_string()),
        None => f.take(),
    });
    match (&error, was) {
        (Some(e), None) => tracing::error!(
            error = %e,
            "history: cannot write; records wait in memory (up to {MAX_WAITING}) and are written once the store takes them"
        ),
        (None, Some(_)) => tracing::info!("history: writable again"),
        _ => {}
    }
    if left.len() > MAX_WAITING {
        let over = left.len() - MAX_WAITING;
        for w in left.drain(..over) {
            dropped(w.log, "store_refused", 1);
        }
        inner.dropped.fetch_add(over as u64, Ordering::Relaxed);
        inner.written.fetch_add(over as u64, Ordering::Relaxed);
        tracing::warn!(
            dropped = over,
            "history: records dropped, the store refused writes too long"
        );
    }
    left
}

impl Inner {
    /// The store, opened again if a failed write closed it. Blocking.
    fn db(&self) -> Result<Arc<Database>, HistoryError> {
        let mut slot = self.db.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(db) = slot.as_ref() {
            return Ok(Arc::clone(db));
        }
        let db = match crate::storage::open_db(&self.path) {
            Ok(db) => Arc::new(db),
            Err(crate::storage::OpenError::Redb(e)) => return Err(db_error(&self.path, e)),
            Err(crate::storage::OpenError::Panicked(text)) => {
                return Err(HistoryError::Io {
                    path: self.path.clone(),
                    source: std::io::Error::other(text),
                });
            }
        };
        *slot = Some(Arc::clone(&db));
        Ok(db)
    }

    /// Closes the store after `e` if it must be opened again (the handle is dropped once the
    /// reads that hold it end).
    fn after_error(&self, e: &HistoryError) {
        let reopen = match e {
            HistoryError::Io { .. } => true,
            HistoryError::Database { source, .. } => crate::storage::needs_reopen(source),
            _ => false,
        };
        if reopen {
            *self.db.lock().unwrap_or_else(|p| p.into_inner()) = None;
        }
    }

    fn config(&self) -> (HistoryConfig, Vec<u16>) {
        self.config
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }
}

fn write_batch(inner: &Inner, batch: &[Waiting]) -> Result<(), HistoryError> {
    let (config, _) = inner.config();
    let path = &inner.path;
    let e = |x: redb::Error| db_error(path, x);
    let tx = inner.db()?.begin_write().map_err(|x| e(x.into()))?;
    // Subjects past their bound: (log, subject, bound).
    let mut over: BTreeSet<(usize, String, u64)> = BTreeSet::new();
    {
        for log in [Log::History, Log::Audit] {
            let t = log.tables();
            let mut records = tx.open_table(t.records).map_err(|x| e(x.into()))?;
            let mut seqs = tx.open_table(t.seqs).map_err(|x| e(x.into()))?;
            let mut subj = tx.open_table(t.subjects).map_err(|x| e(x.into()))?;
            let mut counts = tx.open_table(t.counts).map_err(|x| e(x.into()))?;
            for w in batch.iter().filter(|w| w.log == log) {
                let r = &w.record;
                records
                    .insert((r.unix_ms, r.seq), r.encode_to_vec().as_slice())
                    .map_err(|x| e(x.into()))?;
                seqs.insert(r.seq, r.unix_ms).map_err(|x| e(x.into()))?;
                for s in subjects(r) {
                    subj.insert((s.as_str(), r.unix_ms, r.seq), summary(r))
                        .map_err(|x| e(x.into()))?;
                }
                if let Some(s) = counted_subject(r) {
                    let n = counts
                        .get(s.as_ref())
                        .map_err(|x| e(x.into()))?
                        .map_or(0, |v| v.value())
                        + 1;
                    counts.insert(s.as_ref(), n).map_err(|x| e(x.into()))?;
                    let bound = if s == REFUSED {
                        config.max_refusals
                    } else {
                        u64::from(config.tag_values)
                    };
                    if n > bound {
                        over.insert((log as usize, s.into_owned(), bound));
                    }
                }
            }
        }
        // Tag values and refusals beyond their bound go at once: a fast tag must not fill
        // the store, nor refusals push the taken writes out of the audit.
        for (log, subject, bound) in &over {
            let (log, t) = if *log == Log::Audit as usize {
                (Log::Audit, AUDIT)
            } else {
                (Log::History, HISTORY)
            };
            let n = drop_oldest_of(&tx, t, subject, *bound).map_err(e)?;
            if subject == REFUSED && n > 0 {
                dropped(log, "max_refusals", n);
                tracing::warn!(
                    records = n,
                    max_refusals = bound,
                    "history: the oldest refusal records of the audit dropped (history.max_refusals)"
                );
            }
        }
    }
    tx.commit().map_err(|x| e(x.into()))
}

/// Removes one record and its index entries.
fn remove_record(
    tx: &redb::WriteTransaction,
    t: Tables,
    ms: u64,
    seq: u64,
) -> Result<(), redb::Error> {
    let mut records = tx.open_table(t.records)?;
    let Some(bytes) = records.remove((ms, seq))?.map(|v| v.value().to_vec()) else {
        return Ok(());
    };
    tx.open_table(t.seqs)?.remove(seq)?;
    if let Ok(r) = pb::HistoryRecord::decode(bytes.as_slice()) {
        let mut subj = tx.open_table(t.subjects)?;
        for s in subjects(&r) {
            subj.remove((s.as_str(), ms, seq))?;
        }
        if let Some(s) = counted_subject(&r) {
            let mut counts = tx.open_table(t.counts)?;
            let n = counts.get(s.as_ref())?.map_or(0, |v| v.value());
            counts.insert(s.as_ref(), n.saturating_sub(1))?;
        }
    }
    Ok(())
}

/// Drops the oldest records of a counted subject beyond `keep`; how many.
fn drop_oldest_of(
    tx: &redb::WriteTransaction,
    t: Tables,
    subject: &str,
    keep: u64,
) -> Result<u64, redb::Error> {
    let n = tx
        .open_table(t.counts)?
        .get(subject)?
        .map_or(0, |v| v.value());
    if n <= keep {
        return Ok(0);
    }
    let over = usize::try_from(n - keep).unwrap_or(usize::MAX);
    let victims: Vec<(u64, u64)> = {
        let subj = tx.open_table(t.subjects)?;
        let mut v = Vec::new();
        for item in subj.range((subject, 0u64, 0u64)..=(subject, u64::MAX, u64::MAX))? {
            let (k, _) = item?;
            let (_, ms, seq) = k.value();
            v.push((ms, seq));
            if v.len() >= over {
                break;
            }
        }
        v
    };
    let dropped = victims.len() as u64;
    for (ms, seq) in victims {
        remove_record(tx, t, ms, seq)?;
    }
    Ok(dropped)
}

/// Counts records dropped before their retention days.
fn dropped(log: Log, reason: &str, n: u64) {
    let log = match log {
        Log::History => "history",
        Log::Audit => "audit",
    };
    crate::telemetry::metrics::event(
        "cellgate.history.dropped",
        &[("log", log), ("reason", reason)],
        n,
    );
}

/// Retention: records older than their log's days, and the oldest beyond `max_records`.
fn prune_logs(inner: &Inner) {
    let (config, _) = inner.config();
    let now = pb::now_ms();
    let day = 24 * 3600 * 1000u64;
    for (log, days) in [
        (Log::History, config.keep_days),
        (Log::Audit, config.keep_audit_days),
    ] {
        let cutoff = now.saturating_sub(u64::from(days) * day);
        let db = match inner.db() {
            Ok(db) => db,
            Err(e) => {
                tracing::warn!(error = %e, log = ?log, "history: retention failed");
                continue;
            }
        };
        // Records removed in all, and those of them still within their days (`max_records`).
        let run = || -> Result<(u64, u64), redb::Error> {
            let t = log.tables();
            let tx = db.begin_write()?;
            let mut removed = 0u64;
            let mut by_cap = 0u64;
            loop {
                let victims: Vec<(u64, u64)> = {
                    let records = tx.open_table(t.records)?;
                    let len = records.len()?;
                    let over = len.saturating_sub(config.max_records);
                    let mut v = Vec::new();
                    for item in records.iter()? {
                        let (k, _) = item?;
                        let (ms, seq) = k.value();
                        if ms >= cutoff && (v.len() as u64) >= over {
                            break;
                        }
                        v.push((ms, seq));
                        if v.len() >= 10_000 {
                            break;
                        }
                    }
                    v
                };
                if victims.is_empty() {
                    break;
                }
                for (ms, seq) in &victims {
                    remove_record(&tx, t, *ms, *seq)?;
                }
                removed += victims.len() as u64;
                by_cap += victims.iter().filter(|(ms, _)| *ms >= cutoff).count() as u64;
                if victims.len() < 10_000 {
                    break;
                }
            }
            tx.commit()?;
            Ok((removed, by_cap))
        };
        match run() {
            Ok((0, _)) => {}
            Ok((n, by_cap)) => {
                tracing::info!(records = n, log = ?log, "history: retention dropped old records");
                if by_cap > 0 {
                    dropped(log, "max_records", by_cap);
                    tracing::warn!(
                        records = by_cap,
                        max_records = config.max_records,
                        log = ?log,
                        "history: records dropped before their retention days: the log holds \
                         history.max_records"
                    );
                }
            }
            Err(e) => {
                if crate::storage::needs_reopen(&e) {
                    *inner.db.lock().unwrap_or_else(|p| p.into_inner()) = None;
                }
                tracing::warn!(error = %e, log = ?log, "history: retention failed");
            }
        }
    }
}

#[cfg(test)]
mod tests;
