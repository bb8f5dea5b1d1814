//! The library's revision index: every revision of every program, in an embedded database
//! beside the content it names (`programs.dir/.revisions/index.redb`), read and written off
//! the runtime's threads.

// redb's error is large; it stays inside this module's transactions.
#![allow(clippy::result_large_err)]

use std::os::unix::fs::MetadataExt as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering;

use prost::Message;
use redb::{Database, ReadableTable, TableDefinition};

use cellgate_core::pb;

use super::disk::is_there;
use super::{LibraryError, ProgramLibrary, blocking};

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
    /// The file's device and inode when it was opened (`None`: held in memory), so that a
    /// file put in its place is noticed.
    id: Option<(u64, u64)>,
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
        let db = match crate::storage::open_db(path) {
            Ok(db) => db,
            Err(crate::storage::OpenError::Redb(e)) => return Err(err(e.into())),
            Err(crate::storage::OpenError::Panicked(text)) => {
                return Err(err(redb::Error::Io(std::io::Error::other(format!(
                    "the index is damaged ({text}); move it aside: the gateway builds a new \
                     one from the programs in the directory, each as revision 1"
                )))));
            }
        };
        let id = std::fs::symlink_metadata(path)
            .ok()
            .map(|m| (m.dev(), m.ino()));
        let index = Index {
            path: path.to_path_buf(),
            db,
            id,
        };
        index.write(|tx| {
            tx.open_table(REVISIONS)?;
            Ok(())
        })?;
        Ok(index)
    }

    /// An empty index in memory: what a folder without one holds.
    pub(super) fn empty() -> Result<Index, IndexError> {
        let path = PathBuf::from("(none)");
        let db = Database::builder()
            .create_with_backend(redb::backends::InMemoryBackend::new())
            .map_err(|e| IndexError {
                path: path.clone(),
                source: Box::new(e.into()),
            })?;
        let index = Index { path, db, id: None };
        index.write(|tx| {
            tx.open_table(REVISIONS)?;
            Ok(())
        })?;
        Ok(index)
    }

    /// The file's device and inode when it was opened; `None` in memory.
    pub(super) fn id(&self) -> Option<(u64, u64)> {
        self.id
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

/// Finding the index: the library holds the one it opened, and checks at every use that it
/// is still the folder's.
impl ProgramLibrary {
    pub(super) fn index_path(&self) -> PathBuf {
        self.revisions_dir().join("index.redb")
    }

    /// The revision index, to read: opened on first use, and opened again if the folder's
    /// index is another file now (the folder made again, a share mounted again). While the
    /// folder has none (removed with the folder), an empty one: nothing is created until
    /// something is stored.
    pub(super) async fn index(&self) -> Result<Arc<Index>, LibraryError> {
        self.index_for(false).await
    }

    /// The revision index, to store into: as [`Self::index`], but one is created in the
    /// folder if it has none.
    pub(super) async fn index_to_store(&self) -> Result<Arc<Index>, LibraryError> {
        self.index_for(true).await
    }

    async fn index_for(&self, store: bool) -> Result<Arc<Index>, LibraryError> {
        if let Some(index) = self.index_held() {
            return Ok(index);
        }
        let _opening = self.opening.lock().await;
        if let Some(index) = self.index_held() {
            return Ok(index);
        }
        let lib = self.clone();
        blocking(move || lib.open_index(store)).await
    }

    /// The index held, if it is still the folder's. One `lstat`.
    fn index_held(&self) -> Option<Arc<Index>> {
        let held = self.index.lock().ok()?.clone()?;
        let now = std::fs::symlink_metadata(self.index_path()).ok()?;
        (held.id() == Some((now.dev(), now.ino()))).then_some(held)
    }

    /// Opens the folder's index, creating it (with `.revisions/objects`) if there is none
    /// and this is the first use or a store. The folder's files are taken in by
    /// [`Self::take_file`]: the folder's watcher, at start and while the gateway runs.
    /// Blocking.
    fn open_index(&self, store: bool) -> Result<Arc<Index>, LibraryError> {
        let path = self.index_path();
        let held = self.index.lock().ok().and_then(|h| h.clone());
        let there = is_there(&path);
        if held.is_some() && !there {
            if !self.gone_said.swap(true, Ordering::Relaxed) {
                tracing::warn!(
                    index = %path.display(),
                    "program library: its revision index is gone (the folder removed or made \
                     again?): the revisions it held are gone with their content; a new index \
                     is started at the next store"
                );
            }
            if !store {
                return Ok(Arc::new(Index::empty()?));
            }
        } else if held.is_some() {
            tracing::warn!(
                index = %path.display(),
                "program library: its revision index was replaced (the folder made again, a \
                 share mounted again): the one there now is used"
            );
        }
        // The first time, the folder is made if need be; later, only what it lacks inside
        // (a folder that is gone is not made again behind its owner's back).
        let made = if held.is_none() {
            std::fs::create_dir_all(self.objects_dir())
        } else {
            self.make_objects_dir()
        };
        made.map_err(|source| LibraryError::Io {
            name: String::new(),
            op: "create",
            path: self.objects_dir(),
            source,
        })?;
        let index = Arc::new(Index::open(&path)?);
        if held.is_some() {
            // What the watcher noted of the old folder's files says nothing of the new one.
            if let Ok(mut notes) = self.notes.lock() {
                notes.clear();
            }
        }
        if let Ok(mut h) = self.index.lock() {
            *h = Some(Arc::clone(&index));
        }
        self.gone_said.store(false, Ordering::Relaxed);
        Ok(index)
    }

    /// Makes `.revisions` and `.revisions/objects` in the folder if they are not there, but
    /// never the folder itself. Blocking.
    pub(super) fn make_objects_dir(&self) -> std::io::Result<()> {
        for dir in [self.revisions_dir(), self.objects_dir()] {
            match std::fs::create_dir(&dir) {
                Err(e) if e.kind() != std::io::ErrorKind::AlreadyExists => return Err(e),
                _ => {}
            }
        }
        Ok(())
    }
}
