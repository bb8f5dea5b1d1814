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
}

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
}

impl JobRecord {
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
    db: Database,
    /// Taken for every write transaction, so that checkpoints reach the database in the order
    /// they were made.
    pending: std::sync::Mutex<Pending>,
}

/// Progress checkpoints not yet in the database: the latest record of each running job.
struct Pending {
    records: BTreeMap<u64, Vec<u8>>,
    /// When the last commit began: every checkpoint before it is on disk.
    last_durable: std::time::Instant,
}

impl Inner {
    fn pending(&self) -> std::sync::MutexGuard<'_, Pending> {
        self.pending
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// Runs `f` in one durable write transaction that first writes the pending checkpoints, so
/// that what `f` writes or removes supersedes them.
fn commit<T>(
    db: &Database,
    pending: &mut Pending,
    f: impl FnOnce(&redb::WriteTransaction) -> Result<T, redb::Error>,
) -> Result<T, redb::Error> {
    pending.last_durable = std::time::Instant::now();
    let tx = db.begin_write()?;
    if !pending.records.is_empty() {
        let mut jobs = tx.open_table(JOBS)?;
        for (seq, bytes) in &pending.records {
            jobs.insert(*seq, bytes.as_slice())?;
        }
    }
    let out = f(&tx)?;
    tx.commit()?;
    // Only once they are on disk: a failed commit keeps them for the next one.
    pending.records.clear();
    Ok(out)
}

impl Drop for Inner {
    /// A gateway that stops writes the checkpoints it still holds.
    fn drop(&mut self) {
        let Inner { db, pending } = self;
        let pending = pending
            .get_mut()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if !pending.records.is_empty()
            && let Err(e) = commit(db, pending, |_| Ok(()))
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
        let db = Database::create(&path).map_err(|e| JournalError::Database {
            path: path.clone(),
            source: Box::new(e.into()),
        })?;
        let journal = Journal {
            inner: std::sync::Arc::new(Inner {
                db,
                pending: std::sync::Mutex::new(Pending {
                    records: BTreeMap::new(),
                    last_durable: std::time::Instant::now(),
                }),
            }),
            path,
            store,
        };
        // Tables exist from the first write on, so that reads never miss them.
        journal.write(|tx| {
            tx.open_table(JOBS)?;
            tx.open_table(PUNCHED)?;
            tx.open_table(META)?;
            Ok(())
        })?;
        Ok(journal)
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
        let mut pending = self.inner.pending();
        commit(&self.inner.db, &mut pending, f).map_err(|e| self.db_error(e))
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
        let dest = self.store.join(name);
        let io = |source| JournalError::Io {
            path: dest.clone(),
            source,
        };
        let _ = std::fs::remove_file(&dest);
        if std::fs::hard_link(from, &dest).is_err() {
            let tmp = self.store.join(format!(".tmp-{name}"));
            std::fs::copy(from, &tmp).map_err(io)?;
            std::fs::File::open(&tmp)
                .and_then(|f| f.sync_all())
                .map_err(io)?;
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
    pub fn put_job(&self, record: &JobRecord) -> Result<(), JournalError> {
        let bytes = self.encode(record)?;
        self.write(|tx| {
            tx.open_table(JOBS)?.insert(record.seq, bytes.as_slice())?;
            Ok(())
        })
    }

    /// Checkpoints a running job's acknowledged offset. It is held in memory and reaches the
    /// disk with the next commit, which is made here once the last one is
    /// [`PROGRESS_DURABLE_EVERY`] old. The offset on disk is never ahead of what the board
    /// acknowledged, and at most that far behind while the job makes progress.
    pub fn put_progress(&self, record: &JobRecord) -> Result<(), JournalError> {
        let bytes = self.encode(record)?;
        let mut pending = self.inner.pending();
        pending.records.insert(record.seq, bytes);
        if pending.last_durable.elapsed() < PROGRESS_DURABLE_EVERY {
            return Ok(());
        }
        commit(&self.inner.db, &mut pending, |_| Ok(())).map_err(|e| self.db_error(e))
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
        let tx = self.inner.db.begin_read().map_err(|e| self.db_error(e))?;
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
mod tests {
    use super::*;

    fn record(seq: u64, machine: &str, state: JobState) -> JobRecord {
        JobRecord {
            seq,
            id: format!("{machine}-x-{seq}"),
            machine: machine.to_string(),
            request_id: String::new(),
            name: "O1".to_string(),
            priority: 0,
            accepted_unix_ms: 1,
            file: seq.to_string(),
            file_len: 7,
            suffix: b"%".to_vec(),
            start: None,
            resume_after_restart: false,
            deadline_s: 0,
            state,
            acked: 0,
            last_event: Vec::new(),
        }
    }

    #[test]
    fn records_and_files_survive_reopening_and_go_together() {
        let dir = tempfile::tempdir().unwrap();
        let j = Journal::open(dir.path()).unwrap();
        assert_eq!(j.next_seq().unwrap(), 1);
        assert_eq!(j.next_seq().unwrap(), 2);
        let len = j.store_bytes("1", &[b"%\nO1\n", b"X1\n"]).unwrap();
        assert_eq!(len, 8);
        let mut a = record(1, "m1", JobState::Waiting);
        j.put_job(&a).unwrap();
        j.put_job(&record(2, "m2", JobState::Active)).unwrap();
        a.acked = 5;
        a.state = JobState::Active;
        j.put_job(&a).unwrap();
        let p = PunchedRecord {
            seq: 3,
            machine: "m2".into(),
            o_number: Some("O7".into()),
            unix_ms: 9,
            text: b"%\nO7\n%".to_vec(),
        };
        j.put_punched(&p).unwrap();
        drop(j);

        // A half-written store file from a crash is gone after reopening.
        std::fs::write(dir.path().join("store/.tmp-9"), b"partial").unwrap();
        let j = Journal::open(dir.path()).unwrap();
        assert!(!dir.path().join("store/.tmp-9").exists());
        assert_eq!(j.next_seq().unwrap(), 3);
        let r = j.restore().unwrap();
        assert_eq!(r.jobs["m1"], vec![a.clone()]);
        assert_eq!(r.jobs["m2"][0].state, JobState::Active);
        assert_eq!(r.punched, vec![p]);
        assert_eq!(std::fs::read(j.file_path("1")).unwrap(), b"%\nO1\nX1\n");

        j.remove_jobs(&[a]).unwrap();
        j.remove_punched(3).unwrap();
        let r = j.restore().unwrap();
        assert!(!r.jobs.contains_key("m1"));
        assert!(r.punched.is_empty());
        assert!(!j.file_path("1").exists());
    }

    /// The acknowledged offset of job `seq` as the database holds it, without the
    /// checkpoints held in memory.
    fn stored_acked(j: &Journal, seq: u64) -> u64 {
        let tx = j.inner.db.begin_read().unwrap();
        let table = tx.open_table(JOBS).unwrap();
        let bytes = table.get(seq).unwrap().unwrap();
        serde_json::from_slice::<JobRecord>(bytes.value())
            .unwrap()
            .acked
    }

    /// Progress checkpoints are held in memory and reach the disk with the next commit, made
    /// by a checkpoint itself once the last commit is a second old; a gateway that stops
    /// writes what it holds.
    #[test]
    fn progress_checkpoints_reach_the_disk_at_a_bounded_rate() {
        let dir = tempfile::tempdir().unwrap();
        let j = Journal::open(dir.path()).unwrap();
        let mut a = record(1, "m1", JobState::Active);
        j.put_job(&a).unwrap();
        a.acked = 100;
        j.put_progress(&a).unwrap();
        assert_eq!(
            stored_acked(&j, 1),
            0,
            "just after a commit, progress is held"
        );
        // The commit of another record carries it to disk.
        j.put_job(&record(2, "m2", JobState::Waiting)).unwrap();
        assert_eq!(stored_acked(&j, 1), 100);
        // Past the interval, a checkpoint is a commit of its own.
        j.inner.pending().last_durable -= PROGRESS_DURABLE_EVERY;
        a.acked = 200;
        j.put_progress(&a).unwrap();
        assert_eq!(stored_acked(&j, 1), 200);
        // Held again, then written when the journal closes.
        a.acked = 300;
        j.put_progress(&a).unwrap();
        assert_eq!(stored_acked(&j, 1), 200);
        drop(j);
        let j = Journal::open(dir.path()).unwrap();
        assert_eq!(stored_acked(&j, 1), 300);
        // Restoring reads what was written, held checkpoints included.
        a.acked = 400;
        j.put_progress(&a).unwrap();
        assert_eq!(j.restore().unwrap().jobs["m1"][0].acked, 400);
    }

    /// A held checkpoint never overwrites what the job's own later write says, nor brings back
    /// a job that was removed.
    #[test]
    fn a_held_checkpoint_does_not_undo_a_later_write() {
        let dir = tempfile::tempdir().unwrap();
        let j = Journal::open(dir.path()).unwrap();
        let mut a = record(1, "m1", JobState::Active);
        let b = record(2, "m2", JobState::Active);
        j.put_job(&a).unwrap();
        j.put_job(&b).unwrap();
        a.acked = 100;
        j.put_progress(&a).unwrap();
        j.put_progress(&b).unwrap();
        a.state = JobState::Ended;
        a.acked = 120;
        j.put_job(&a).unwrap();
        j.remove_jobs(std::slice::from_ref(&b)).unwrap();
        drop(j);
        let j = Journal::open(dir.path()).unwrap();
        let r = j.restore().unwrap();
        assert_eq!(r.jobs["m1"][0].state, JobState::Ended);
        assert_eq!(r.jobs["m1"][0].acked, 120);
        assert!(!r.jobs.contains_key("m2"));
    }

    #[test]
    fn a_linked_program_keeps_its_version_when_the_library_replaces_it() {
        let dir = tempfile::tempdir().unwrap();
        let j = Journal::open(&dir.path().join("journal")).unwrap();
        let lib = dir.path().join("O1");
        std::fs::write(&lib, b"%\nO1\nold\n%").unwrap();
        assert_eq!(j.store_file("5", &lib).unwrap(), 10);
        // The library replaces by rename: a new inode.
        let tmp = dir.path().join(".O1.tmp");
        std::fs::write(&tmp, b"%\nO1\nnew, longer\n%").unwrap();
        std::fs::rename(&tmp, &lib).unwrap();
        assert_eq!(std::fs::read(j.file_path("5")).unwrap(), b"%\nO1\nold\n%");
    }

    #[test]
    fn a_second_gateway_cannot_open_the_same_journal() {
        let dir = tempfile::tempdir().unwrap();
        let _j = Journal::open(dir.path()).unwrap();
        assert!(Journal::open(dir.path()).is_err());
    }

    #[test]
    fn stream_offsets_map_back_to_the_program() {
        let mut r = record(1, "m", JobState::Ended);
        r.file_len = 100;
        r.suffix.clear();
        assert_eq!(r.stream_size(), 100);
        r.start = Some(StartPoint {
            header_end: 10,
            body_start: 60,
        });
        assert_eq!(r.stream_size(), 50);
        assert_eq!(r.program_offset(4), 60);
        assert_eq!(r.program_offset(10), 60);
        assert_eq!(r.program_offset(25), 75);
    }
}
