//! The library's revision index: every revision of every program, in an embedded database
//! beside the content it names (`programs.dir/.revisions/index.redb`), read and written off
//! the runtime's threads.

// redb's error is large; it stays inside this module's transactions.
#![allow(clippy::result_large_err)]

use std::path::{Path, PathBuf};

use prost::Message;
use redb::{Database, ReadableTable, TableDefinition};

use cellgate_core::pb;

/// (program name, revision number) → `ProgramRevision`.
const REVISIONS: TableDefinition<(&str, u32), &[u8]> = TableDefinition::new("revisions");

/// Why the index could not be read or written.
#[derive(Debug, thiserror::Error)]
#[error("revision index {}: {source}", path.display())]
pub struct IndexError {
    pub path: PathBuf,
    #[source]
    pub source: Box<redb::Error>,
}

impl IndexError {
    /// The I/O error under it, if it is one.
    pub fn io(&self) -> Option<&std::io::Error> {
        match self.source.as_ref() {
            redb::Error::Io(e) => Some(e),
            _ => None,
        }
    }
}

/// The open index.
pub(super) struct Index {
    path: PathBuf,
    db: Database,
}

impl std::fmt::Debug for Index {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Index({})", self.path.display())
    }
}

impl Index {
    /// Opens or creates the index at `path`. Blocking.
    pub(super) fn open(path: &Path) -> Result<Index, IndexError> {
        let err = |e: redb::Error| IndexError {
            path: path.to_path_buf(),
            source: Box::new(e),
        };
        let db = match crate::jobs::journal::open_db(path) {
            Ok(db) => db,
            Err(crate::jobs::journal::OpenError::Redb(e)) => return Err(err(e.into())),
            Err(crate::jobs::journal::OpenError::Panicked(text)) => {
                return Err(err(redb::Error::Io(std::io::Error::other(format!(
                    "the index is damaged ({text}); move it aside: the gateway builds a new \
                     one from the programs in the directory, each as revision 1"
                )))));
            }
        };
        let index = Index {
            path: path.to_path_buf(),
            db,
        };
        index.write(|tx| {
            tx.open_table(REVISIONS)?;
            Ok(())
        })?;
        Ok(index)
    }

    fn err(&self, e: impl Into<redb::Error>) -> IndexError {
        IndexError {
            path: self.path.clone(),
            source: Box::new(e.into()),
        }
    }

    fn write<T>(
        &self,
        f: impl FnOnce(&redb::WriteTransaction) -> Result<T, redb::Error>,
    ) -> Result<T, IndexError> {
        let tx = self.db.begin_write().map_err(|e| self.err(e))?;
        let out = f(&tx).map_err(|e| self.err(e))?;
        tx.commit().map_err(|e| self.err(e))?;
        Ok(out)
    }

    /// Every kept revision of `name`, oldest first.
    pub(super) fn revisions(&self, name: &str) -> Result<Vec<pb::ProgramRevision>, IndexError> {
        let tx = self.db.begin_read().map_err(|e| self.err(e))?;
        let t = tx.open_table(REVISIONS).map_err(|e| self.err(e))?;
        let mut out = Vec::new();
        for item in t
            .range((name, 0u32)..=(name, u32::MAX))
            .map_err(|e| self.err(e))?
        {
            let (_, v) = item.map_err(|e| self.err(e))?;
            if let Ok(r) = pb::ProgramRevision::decode(v.value()) {
                out.push(r);
            }
        }
        Ok(out)
    }

    /// Every program's latest revision, by name.
    pub(super) fn latest_all(&self) -> Result<Vec<pb::ProgramRevision>, IndexError> {
        let tx = self.db.begin_read().map_err(|e| self.err(e))?;
        let t = tx.open_table(REVISIONS).map_err(|e| self.err(e))?;
        let mut out: Vec<pb::ProgramRevision> = Vec::new();
        for item in t.iter().map_err(|e| self.err(e))? {
            let (_, v) = item.map_err(|e| self.err(e))?;
            if let Ok(r) = pb::ProgramRevision::decode(v.value()) {
                match out.last_mut() {
                    Some(last) if last.name == r.name => *last = r,
                    _ => out.push(r),
                }
            }
        }
        Ok(out)
    }

    /// Every SHA-256 a kept revision names.
    pub(super) fn hashes(&self) -> Result<std::collections::BTreeSet<String>, IndexError> {
        let tx = self.db.begin_read().map_err(|e| self.err(e))?;
        let t = tx.open_table(REVISIONS).map_err(|e| self.err(e))?;
        let mut out = std::collections::BTreeSet::new();
        for item in t.iter().map_err(|e| self.err(e))? {
            let (_, v) = item.map_err(|e| self.err(e))?;
            if let Ok(r) = pb::ProgramRevision::decode(v.value()) {
                out.insert(r.sha256);
            }
        }
        Ok(out)
    }

    /// Writes `revisions` (new or changed) and removes the revisions `drop` names, in one
    /// transaction.
    pub(super) fn put(
        &self,
        revisions: &[pb::ProgramRevision],
        drop: &[(String, u32)],
    ) -> Result<(), IndexError> {
        self.write(|tx| {
            let mut t = tx.open_table(REVISIONS)?;
            for r in revisions {
                t.insert((r.name.as_str(), r.number), r.encode_to_vec().as_slice())?;
            }
            for (name, number) in drop {
                t.remove((name.as_str(), *number))?;
            }
            Ok(())
        })
    }
}
