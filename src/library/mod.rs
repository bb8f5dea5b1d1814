//! The cell's program library: NC programs kept as files in `programs.dir`, one file per
//! program, named by its library name, and every revision of each.
//!
//! Names are one key chunk of `P/C/program/<name>` and a plain file name at once: 1 to 128
//! characters of `A-Z a-z 0-9 . _ + -`, starting with a letter or digit. That rules out path
//! traversal (`..`, `/`), hidden files, and every zenoh wildcard or reserved character.
//!
//! **Revisions.** Every store makes a revision: its number, the SHA-256 of its content, size,
//! time, who stored it (as the client said), a comment and a state (draft, released, locked).
//! The content is kept once per hash in `.revisions/objects/<sha256>`, the revisions in an
//! index beside it (`.revisions/index.redb`), and the latest revision's content is also the
//! program's own file in `programs.dir` (`<name>.nc`: see `one_file`), so that what is in
//! the directory is what a job sends. Retention (`programs.keep_revisions`, `keep_revision_days`) drops old revisions,
//! never a program's latest, its latest released, or a locked one; content no revision names
//! any more is removed. A file put in the directory by hand becomes a revision (by
//! `(file)`) when the gateway starts.
//!
//! Every file is written by writing a hidden temporary file and renaming it into place, so a
//! reader (a job streaming the program) keeps the complete old or new version, never a mix.
//! The file is synced before the rename and the directory after it, so a power cut leaves
//! the old program or the new one, never an empty name. Temporary files a crash left behind
//! are removed when the gateway starts ([`ProgramLibrary::create_dir`]). A store is on disk
//! (content, the program's file, the index) before it is answered; a failure part way leaves
//! the earlier revision the program's latest.
//!
//! Optional quotas bound the library ([`Quota`]): the bytes of every revision's content kept
//! (once per hash) and the number of programs.
//!
//! **The folder's files.** Only regular files inside the folder are programs: a symbolic
//! link, a FIFO or a device is never opened or followed (`disk`), whatever its name. A
//! folder file is copied into `.revisions` in pieces, so memory stays bounded whatever its
//! size. If the folder is removed and made again, the library notices that its index is gone
//! and starts a new one there at the next store.

mod disk;
mod files;
pub mod folder;
mod index;
mod one_file;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use cellgate_core::codes::BusCode;
use cellgate_core::pb::{self, RevisionState};

use self::disk::{OpenError, is_regular, is_there, open_regular};
pub use self::disk::{escaped, sha256_file, sha256_hex, write_atomically};
pub use self::files::{FolderFile, Taken};
use self::index::Index;
pub use self::index::IndexError;
use cellgate_core::program::folder::FolderRules;
pub use cellgate_core::program::name::NAME_MAX;
use cellgate_core::program::name::check_name;

/// Where revisions live, inside `programs.dir`: hidden, so never a program.
const REVISIONS_DIR: &str = ".revisions";

/// Why a library operation failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LibraryError {
    #[error("program name {name:?} is not valid: {reason}")]
    InvalidName { name: String, reason: &'static str },
    #[error("the program library has no program {name:?}")]
    NotFound { name: String },
    /// The program was removed; its revisions are kept, and each can still be read.
    #[error(
        "program {name:?} was removed (its latest revision was {latest}); its kept revisions \
         can still be read by number: `cellgate program get {name} --revision {latest}` \
         (`cellgate program history {name}` lists them)"
    )]
    Removed { name: String, latest: u32 },
    #[error("the program library already has a program {name:?}")]
    Exists { name: String },
    #[error("program {name:?} is {size} bytes; programs.max_size allows {max}")]
    TooLarge { name: String, size: u64, max: u64 },
    /// Storing the program would take the library past `programs.quota_bytes` or
    /// `programs.quota_files`.
    #[error(
        "program {name:?} not stored: the library would hold {would} {what}, over \
         programs.quota_{what} = {limit}: every kept revision counts (a removed program's too, \
         until retention drops it); keep fewer revisions (programs.keep_revisions, \
         keep_revision_days) or remove programs (`cellgate program rm`)"
    )]
    QuotaExceeded {
        name: String,
        what: &'static str,
        would: u64,
        limit: u64,
    },
    /// The disk (or its quota) is full: nothing was stored, any earlier version of the
    /// program is as it was.
    #[error(
        "program {name:?} not stored: the disk holding {} is full ({source}); the earlier \
         version, if any, is unchanged. Free space and store it again", path.display()
    )]
    StorageFull {
        name: String,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("program {name:?}: cannot {op} {}: {source}", path.display())]
    Io {
        name: String,
        op: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The program's latest revision is locked.
    #[error(
        "program {name:?}: revision {number} is locked, so the program may not be {what}; a \
         role with program.release may unlock it (`cellgate program release {name} \
         {number} --state draft`)"
    )]
    Locked {
        name: String,
        number: u32,
        what: &'static str,
    },
    /// No revision of that number or hash is kept.
    #[error(
        "program {name:?} has no revision {revision:?}{}", if known.is_empty() { String::new() } else { format!("; its revisions are {known}") }
    )]
    NoRevision {
        name: String,
        revision: String,
        known: String,
    },
    /// A state change the rules do not allow.
    #[error("program {name:?} revision {number}: {why}")]
    Transition {
        name: String,
        number: u32,
        why: String,
    },
    /// The machine takes only released revisions.
    #[error(
        "machine {machine} takes only released revisions (accept = \"released\"), and \
         program {name:?} revision {number} is a draft{}; release it (`cellgate program \
         release {name} {number}`) or name a released revision", latest_released.map(|n| format!(" (its latest released revision is {n})")).unwrap_or_default()
    )]
    NotReleased {
        machine: String,
        name: String,
        number: u32,
        latest_released: Option<u32>,
    },
    /// Two files of the folder give one program name: neither is taken.
    #[error(
        "program {name:?}: the files {files} in the library's folder all give this name \
         (programs.extensions are not part of a name); neither is taken until one is removed \
         or renamed"
    )]
    Conflict { name: String, files: String },
    /// A file of the folder that is not taken: its name gives no program name, or it is not
    /// a regular file (a symbolic link, a FIFO, a device). `file` is escaped.
    #[error("the file {file} in the library's folder is not taken: {why}; it is left as it is")]
    NotTaken { file: String, why: String },
    /// The index names a revision whose content is not in `.revisions/objects` (removed by
    /// hand, or with the folder).
    #[error(
        "program {name:?} revision {number}: its content ({sha256}) is gone from the library's \
         .revisions/objects, so it cannot be sent or read; store the program again"
    )]
    ContentMissing {
        name: String,
        number: u32,
        sha256: String,
    },
    #[error(transparent)]
    Index(#[from] IndexError),
}

/// One stored program.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProgramEntry {
    pub name: String,
    pub size: u64,
    /// Last stored, ms since the Unix epoch (0 if the file system does not say).
    pub modified_unix_ms: u64,
    /// Its latest revision (for a removal: the one that was latest).
    pub latest: Option<pb::ProgramRevision>,
    /// Its latest released (or locked) revision, 0 if none.
    pub latest_released: u32,
    /// The file of the folder that holds it (`O5555.nc`), empty if none.
    pub file: String,
    /// Why the file is not the latest revision, when it is not.
    pub note: String,
    /// The call that answered this made a new revision (a store of the same bytes as the
    /// latest does not).
    pub revised: bool,
}

impl ProgramEntry {
    /// As the bus carries it.
    pub fn info(self) -> pb::ProgramInfo {
        pb::ProgramInfo {
            name: self.name,
            size: self.size,
            modified_unix_ms: self.modified_unix_ms,
            latest: self.latest,
            latest_released: self.latest_released,
            file: self.file,
            note: self.note,
        }
    }
}

/// Whether a store may replace a program of the same name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Place {
    Replace,
    New,
}

/// Bounds on the whole library; `None` is unbounded.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Quota {
    pub bytes: Option<u64>,
    pub files: Option<u64>,
}

/// How many revisions the library keeps (`programs.keep_revisions`, `keep_revision_days`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Retention {
    pub revisions: u32,
    pub days: Option<u32>,
}

impl Default for Retention {
    fn default() -> Self {
        Retention {
            revisions: cellgate_core::config::ProgramsConfig::DEFAULT_KEEP_REVISIONS,
            days: None,
        }
    }
}

/// A store: the content and what the revision records of it.
#[derive(Debug, Clone, Default)]
pub struct Store<'a> {
    /// Owned, it is written as it is; borrowed, it is copied first.
    pub bytes: std::borrow::Cow<'a, [u8]>,
    /// Who stored it, as the client said.
    pub by: pb::RequestOrigin,
    pub comment: String,
    /// Content taken from another program's revision.
    pub adopted: Option<(String, u32)>,
}

/// The program library. Cheap to clone.
#[derive(Debug, Clone)]
pub struct ProgramLibrary {
    dir: Arc<PathBuf>,
    max_size: u64,
    /// Shared by every clone, and replaced by a reload ([`ProgramLibrary::set_limits`]).
    quota: Arc<std::sync::RwLock<Quota>>,
    retention: Arc<std::sync::RwLock<Retention>>,
    /// Held from a store's quota check to its end, so that concurrent stores cannot all
    /// pass the check and then together break the quota, nor number two revisions alike.
    stores: Arc<tokio::sync::Mutex<()>>,
    /// The index as last opened; checked against the folder at every use (it may have been
    /// removed with the folder and the folder made again).
    index: Arc<std::sync::Mutex<Option<Arc<Index>>>>,
    /// Held while the index is (re)opened, so that it is opened once.
    opening: Arc<tokio::sync::Mutex<()>>,
    /// That the index is gone was logged (once until one is opened again).
    gone_said: Arc<AtomicBool>,
    /// The gateway's own files ([`CellConfig::owned_files`]): never a program.
    ///
    /// [`CellConfig::owned_files`]: cellgate_core::config::CellConfig::owned_files
    owned: Arc<[PathBuf]>,
    /// Which files of the folder are programs (`programs.extensions`).
    folder: Arc<FolderRules>,
    /// Why a program's file is not its latest revision, as the folder's watcher found
    /// (a conflict, an edit of a locked revision refused): shown in the listing.
    notes: Arc<std::sync::Mutex<std::collections::BTreeMap<String, String>>>,
}

/// Checks a library name (see [`cellgate_core::program::name`]).
pub fn validate_name(name: &str) -> Result<(), LibraryError> {
    check_name(name).map_err(|e| LibraryError::InvalidName {
        name: e.name,
        reason: e.reason,
    })
}

fn is_released(r: &pb::ProgramRevision) -> bool {
    matches!(r.state(), RevisionState::Released | RevisionState::Locked)
}

/// The revision `rev` names in `revisions` (oldest first): a number, a SHA-256 (or a prefix
/// of at least 8 hex digits that only one revision has), or, empty, the latest.
fn find<'r>(
    name: &str,
    revisions: &'r [pb::ProgramRevision],
    rev: &str,
) -> Result<&'r pb::ProgramRevision, LibraryError> {
    let missing = || LibraryError::NoRevision {
        name: name.to_string(),
        revision: rev.to_string(),
        known: revisions
            .iter()
            .map(|r| r.number.to_string())
            .collect::<Vec<_>>()
            .join(", "),
    };
    let rev = rev.trim();
    if rev.is_empty() || rev == "latest" {
        return revisions.last().ok_or_else(|| LibraryError::NotFound {
            name: name.to_string(),
        });
    }
    if let Ok(n) = rev.parse::<u32>()
        && rev.len() < 8
    {
        return revisions.iter().find(|r| r.number == n).ok_or_else(missing);
    }
    let rev = rev.to_ascii_lowercase();
    if rev.len() >= 8 && rev.bytes().all(|b| b.is_ascii_hexdigit()) {
        let hits: Vec<&pb::ProgramRevision> = revisions
            .iter()
            .filter(|r| r.sha256.starts_with(&rev))
            .collect();
        // The same content stored twice is two revisions with one hash: the newer one.
        let hashes: BTreeSet<&str> = hits.iter().map(|r| r.sha256.as_str()).collect();
        if hashes.len() == 1 {
            return hits.last().copied().ok_or_else(missing);
        }
    }
    Err(missing())
}

impl ProgramLibrary {
    pub fn new(dir: impl Into<PathBuf>, max_size: u64) -> Self {
        ProgramLibrary {
            stores: Arc::default(),
            dir: Arc::new(dir.into()),
            max_size,
            quota: Arc::default(),
            retention: Arc::default(),
            index: Arc::default(),
            opening: Arc::default(),
            gone_said: Arc::default(),
            owned: Arc::new([]),
            folder: Arc::new(cellgate_core::config::ProgramsConfig::default().folder_rules()),
            notes: Arc::default(),
        }
    }

    /// The same library, taking the folder's files as `rules` say.
    pub fn with_folder(mut self, rules: FolderRules) -> Self {
        self.folder = Arc::new(rules);
        self
    }

    /// What the folder takes.
    pub fn folder_rules(&self) -> &FolderRules {
        &self.folder
    }

    /// The same library, never taking `owned` (the gateway's journal, history, keys) for
    /// programs.
    pub fn with_owned(mut self, owned: Vec<PathBuf>) -> Self {
        self.owned = owned.into();
        self
    }

    /// Checks a name as [`validate_name`] does, and refuses the gateway's own files.
    fn check_name(&self, name: &str) -> Result<(), LibraryError> {
        validate_name(name)?;
        let path = self.dir.join(name);
        if cellgate_core::config::owned::is_owned(&self.owned, &self.dir, &path) {
            return Err(LibraryError::InvalidName {
                name: name.to_string(),
                reason: "it is a file of the gateway's own (its job journal, history or keys), \
                         never a program",
            });
        }
        if self.folder.ends_in_extension(name) {
            return Err(LibraryError::InvalidName {
                name: name.to_string(),
                reason: "it ends in one of programs.extensions, which the library's folder \
                         takes as a file's extension, not part of a name: name the program \
                         without it",
            });
        }
        Ok(())
    }

    /// The same library, bounded by `quota`.
    pub fn with_quota(mut self, quota: Quota) -> Self {
        self.quota = Arc::new(std::sync::RwLock::new(quota));
        self
    }

    /// The same library, keeping revisions as `retention` says.
    pub fn with_retention(mut self, retention: Retention) -> Self {
        self.retention = Arc::new(std::sync::RwLock::new(retention));
        self
    }

    /// Takes a reloaded cell file's quota and retention, for this library and every clone.
    pub fn set_limits(&self, quota: Quota, retention: Retention) {
        *self.quota.write().unwrap_or_else(|p| p.into_inner()) = quota;
        *self.retention.write().unwrap_or_else(|p| p.into_inner()) = retention;
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn max_size(&self) -> u64 {
        self.max_size
    }

    fn revisions_dir(&self) -> PathBuf {
        self.dir.join(REVISIONS_DIR)
    }

    fn objects_dir(&self) -> PathBuf {
        self.revisions_dir().join("objects")
    }

    fn object_path(&self, sha: &str) -> PathBuf {
        self.objects_dir().join(sha)
    }

    /// Creates the directory if it does not exist, removes the temporary files a crash left
    /// in it (those of this process, which has written nothing yet, excepted), and opens the
    /// revision index, taking in the programs it does not know yet.
    pub async fn create_dir(&self) -> std::io::Result<()> {
        tokio::fs::create_dir_all(self.dir.as_path()).await?;
        let own = format!(".{}.", std::process::id());
        for dir in [self.dir.as_path().to_path_buf(), self.objects_dir()] {
            let Ok(mut entries) = tokio::fs::read_dir(&dir).await else {
                continue;
            };
            while let Some(item) = entries.next_entry().await? {
                let Ok(name) = item.file_name().into_string() else {
                    continue;
                };
                if name.starts_with('.') && name.ends_with(".tmp") && !name.contains(&own) {
                    match tokio::fs::remove_file(item.path()).await {
                        Ok(()) => {
                            tracing::info!(file = %name, "temporary file of an earlier run removed")
                        }
                        Err(e) => {
                            tracing::warn!(file = %name, error = %e, "temporary file not removed")
                        }
                    }
                }
            }
        }
        self.index().await.map_err(|e| match e {
            LibraryError::Io { source, .. } | LibraryError::StorageFull { source, .. } => source,
            other => std::io::Error::other(other.to_string()),
        })?;
        Ok(())
    }

    /// Writes content under its hash, once. Blocking.
    fn write_object(&self, name: &str, sha: &str, bytes: &[u8]) -> Result<(), LibraryError> {
        let path = self.object_path(sha);
        if is_regular(&path) {
            return Ok(());
        }
        self.make_objects_dir()
            .map_err(|e| self.write_error(name, self.objects_dir(), e))?;
        match write_atomically(&path, &[bytes], false) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
            Err(e) => Err(self.write_error(name, path, e)),
        }
    }

    fn write_error(&self, name: &str, path: PathBuf, e: std::io::Error) -> LibraryError {
        if crate::storage::is_storage_full(&e) {
            LibraryError::StorageFull {
                name: name.to_string(),
                path,
                source: e,
            }
        } else {
            LibraryError::Io {
                name: name.to_string(),
                op: "write",
                path,
                source: e,
            }
        }
    }

    /// Makes the directory's entries (a rename, a link, a removal) durable.
    async fn sync_dir(&self) -> std::io::Result<()> {
        tokio::fs::File::open(self.dir.as_path())
            .await?
            .sync_all()
            .await
    }

    pub(crate) fn io_error(&self, name: &str, op: &'static str, e: std::io::Error) -> LibraryError {
        if e.kind() == std::io::ErrorKind::NotFound {
            return LibraryError::NotFound {
                name: name.to_string(),
            };
        }
        LibraryError::Io {
            name: name.to_string(),
            op,
            path: self.dir.join(name),
            source: e,
        }
    }

    /// Whether a store of `size` bytes under `name` would be taken, before the bytes are
    /// sent: the name, `programs.max_size`, a locked latest revision and the quota (counting
    /// the content as new). Nothing is written. Answers the program as it stands, if any.
    pub async fn check_store(
        &self,
        name: &str,
        size: u64,
    ) -> Result<Option<ProgramEntry>, LibraryError> {
        let path = self.path_of(name)?;
        if size > self.max_size {
            return Err(LibraryError::TooLarge {
                name: name.to_string(),
                size,
                max: self.max_size,
            });
        }
        let index = self.index().await?;
        let lib = self.clone();
        let name = name.to_string();
        blocking(move || {
            let latest = index.revisions(&name)?.pop();
            let present = latest.as_ref().is_some_and(|r| !r.removed) && is_regular(&path);
            if let Some(l) = &latest
                && !l.removed
                && l.state() == RevisionState::Locked
            {
                return Err(LibraryError::Locked {
                    name,
                    number: l.number,
                    what: "replaced",
                });
            }
            lib.check_quota(&index, &name, "", size, !present)?;
            if present {
                lib.entry_blocking(&name, &index).map(Some)
            } else {
                Ok(None)
            }
        })
        .await
    }

    /// Stores `program` under `name` as its next revision, by nobody in particular.
    pub async fn store(&self, name: &str, program: &[u8]) -> Result<ProgramEntry, LibraryError> {
        self.store_as(
            name,
            Store {
                bytes: program.into(),
                ..Store::default()
            },
        )
        .await
    }

    /// Stores a revision of `name`, replacing the program's file.
    pub async fn store_as(
        &self,
        name: &str,
        store: Store<'_>,
    ) -> Result<ProgramEntry, LibraryError> {
        self.write(name, store, Place::Replace).await
    }

    /// Stores `program` under `name` only if no program has that name yet
    /// ([`LibraryError::Exists`] otherwise). Two writers racing for one name cannot both win:
    /// the file is linked into place, which fails when the name is taken.
    pub async fn store_new(
        &self,
        name: &str,
        program: &[u8],
    ) -> Result<ProgramEntry, LibraryError> {
        self.store_new_as(
            name,
            Store {
                bytes: program.into(),
                ..Store::default()
            },
        )
        .await
    }

    /// [`Self::store_new`] with what the revision records.
    pub async fn store_new_as(
        &self,
        name: &str,
        store: Store<'_>,
    ) -> Result<ProgramEntry, LibraryError> {
        self.write(name, store, Place::New).await
    }

    /// Stores `from`'s revision `revision` (empty: its latest) as `name`'s next revision.
    pub async fn adopt(
        &self,
        name: &str,
        from: &str,
        revision: &str,
        by: pb::RequestOrigin,
        comment: String,
    ) -> Result<ProgramEntry, LibraryError> {
        let (source, bytes) = self.read_revision(from, revision).await?;
        let comment = if comment.is_empty() {
            format!("adopted from {from} revision {}", source.number)
        } else {
            comment
        };
        self.write(
            name,
            Store {
                bytes: bytes.into(),
                by,
                comment,
                adopted: Some((from.to_string(), source.number)),
            },
            Place::Replace,
        )
        .await
    }

    async fn write(
        &self,
        name: &str,
        store: Store<'_>,
        place: Place,
    ) -> Result<ProgramEntry, LibraryError> {
        let path = self.store_path(name)?;
        let size = store.bytes.len() as u64;
        if size > self.max_size {
            return Err(LibraryError::TooLarge {
                name: name.to_string(),
                size,
                max: self.max_size,
            });
        }
        let index = self.index_to_store().await?;
        let _store = self.stores.lock().await;
        let lib = self.clone();
        let name = name.to_string();
        let bytes = store.bytes.into_owned();
        let (by, comment, adopted) = (store.by, store.comment, store.adopted);
        blocking(move || {
            let revisions = index.revisions(&name)?;
            let latest = revisions.last();
            let present = latest.is_some_and(|r| !r.removed) && is_regular(&path);
            if place == Place::New && (present || is_there(&path)) {
                return Err(LibraryError::Exists { name });
            }
            if let Some(l) = latest
                && !l.removed
                && l.state() == RevisionState::Locked
            {
                return Err(LibraryError::Locked {
                    name,
                    number: l.number,
                    what: "replaced",
                });
            }
            let sha = sha256_hex(&bytes);
            // The same content again makes no new revision.
            if let Some(l) = latest
                && present
                && l.sha256 == sha
                && adopted.is_none()
            {
                return lib.entry_blocking(&name, &index);
            }
            lib.check_quota(&index, &name, &sha, size, !present)?;
            lib.write_object(&name, &sha, &bytes)?;
            let replace = place == Place::Replace;
            write_atomically(&path, &[&bytes], replace).map_err(|e| {
                if e.kind() == std::io::ErrorKind::AlreadyExists {
                    LibraryError::Exists { name: name.clone() }
                } else {
                    lib.write_error(&name, path.clone(), e)
                }
            })?;
            let now = pb::now_ms();
            let revision = pb::ProgramRevision {
                name: name.clone(),
                number: latest.map_or(1, |r| r.number + 1),
                sha256: sha,
                size,
                unix_ms: now,
                by: Some(by),
                comment,
                state: RevisionState::Draft as i32,
                adopted_from: adopted.as_ref().map(|a| a.0.clone()).unwrap_or_default(),
                adopted_revision: adopted.as_ref().map_or(0, |a| a.1),
                ..Default::default()
            };
            let mut all = revisions.clone();
            all.push(revision.clone());
            let dropped = lib.retained_out(&all, now);
            if let Err(e) = index.put(&[revision], &dropped) {
                // The file holds the new content, the index its earlier revision: put the
                // earlier content back, so the program is what its latest revision says.
                if let Some(l) = latest
                    && let Ok(old) = std::fs::read(lib.object_path(&l.sha256))
                {
                    let _ = write_atomically(&path, &[&old], true);
                }
                return Err(match e.io() {
                    Some(io) if crate::storage::is_storage_full(io) => LibraryError::StorageFull {
                        name,
                        path,
                        source: std::io::Error::new(io.kind(), io.to_string()),
                    },
                    _ => e.into(),
                });
            }
            if !dropped.is_empty() {
                lib.collect_objects(&index);
            }
            let mut entry = lib.entry_blocking(&name, &index)?;
            entry.revised = true;
            Ok(entry)
        })
        .await
    }

    /// The revisions retention drops from `all` (one program's, oldest first) at `now`.
    fn retained_out(&self, all: &[pb::ProgramRevision], now: u64) -> Vec<(String, u32)> {
        let latest = all.last().map(|r| r.number);
        let latest_released = all.iter().rev().find(|r| is_released(r)).map(|r| r.number);
        let retention = *self.retention.read().unwrap_or_else(|p| p.into_inner());
        let keep_from = all.len().saturating_sub(retention.revisions as usize);
        let cutoff = retention
            .days
            .map(|d| now.saturating_sub(u64::from(d) * 24 * 3600 * 1000));
        all.iter()
            .enumerate()
            .filter(|(i, r)| {
                let protected = Some(r.number) == latest
                    || Some(r.number) == latest_released
                    || r.state() == RevisionState::Locked;
                let old = *i < keep_from || cutoff.is_some_and(|c| r.unix_ms < c);
                old && !protected
            })
            .map(|(_, r)| (r.name.clone(), r.number))
            .collect()
    }

    /// Removes content no kept revision names. Blocking; failures are logged only (the
    /// content is merely kept longer).
    fn collect_objects(&self, index: &Index) {
        let Ok(kept) = index.hashes() else { return };
        let Ok(dir) = std::fs::read_dir(self.objects_dir()) else {
            return;
        };
        for item in dir.flatten() {
            let name = item.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') || kept.contains(&name) {
                continue;
            }
            if let Err(e) = std::fs::remove_file(item.path()) {
                tracing::warn!(object = %name, error = %e, "program library: content not removed");
            }
        }
    }

    /// Refuses a store of `size` bytes of content `sha` under `name` that would break the
    /// quota: every kept revision's content counts once per hash, and the programs.
    fn check_quota(
        &self,
        index: &Index,
        name: &str,
        sha: &str,
        size: u64,
        new_program: bool,
    ) -> Result<(), LibraryError> {
        let quota = *self.quota.read().unwrap_or_else(|p| p.into_inner());
        if quota == Quota::default() {
            return Ok(());
        }
        let mut bytes = 0u64;
        let mut seen_new = false;
        if let Ok(dir) = std::fs::read_dir(self.objects_dir()) {
            for item in dir.flatten() {
                let n = item.file_name().to_string_lossy().into_owned();
                if n.starts_with('.') {
                    continue;
                }
                seen_new |= n == sha;
                bytes += item.metadata().map_or(0, |m| m.len());
            }
        }
        if !seen_new {
            bytes += size;
        }
        let programs = index.latest_all()?.iter().filter(|r| !r.removed).count() as u64
            + u64::from(new_program);
        for (what, limit, would) in [
            ("files", quota.files, programs),
            ("bytes", quota.bytes, bytes),
        ] {
            if let Some(limit) = limit
                && would > limit
            {
                return Err(LibraryError::QuotaExceeded {
                    name: name.to_string(),
                    what,
                    would,
                    limit,
                });
            }
        }
        Ok(())
    }

    /// The program as it stands: its latest revision (size and time are the revision's) and
    /// its file, if the folder has one. Not found when it has neither a revision that is not
    /// removed nor a file.
    fn entry_blocking(&self, name: &str, index: &Index) -> Result<ProgramEntry, LibraryError> {
        let path = self.path_of(name)?;
        let meta = std::fs::symlink_metadata(&path)
            .ok()
            .filter(std::fs::Metadata::is_file);
        let revisions = index.revisions(name)?;
        let latest = revisions.last().filter(|r| !r.removed);
        let (size, modified_unix_ms) = match (latest, &meta) {
            (Some(r), _) => (r.size, r.unix_ms),
            (None, Some(m)) => (m.len(), modified_ms(m)),
            (None, None) => {
                return Err(LibraryError::NotFound {
                    name: name.to_string(),
                });
            }
        };
        Ok(ProgramEntry {
            name: name.to_string(),
            size,
            modified_unix_ms,
            latest_released: revisions
                .iter()
                .rev()
                .find(|r| is_released(r))
                .map_or(0, |r| r.number),
            latest: revisions.last().cloned(),
            file: if meta.is_some() {
                files::file_name(&path)
            } else {
                String::new()
            },
            note: self.note_of(name),
            revised: false,
        })
    }

    pub(crate) async fn entry(&self, name: &str) -> Result<ProgramEntry, LibraryError> {
        self.check_name(name)?;
        let index = self.index().await?;
        let lib = self.clone();
        let name = name.to_string();
        blocking(move || lib.entry_blocking(&name, &index)).await
    }

    /// Opens a program's file for streaming; returns the file and its size. Only a regular
    /// file is opened (see `disk::open_regular`).
    pub async fn open(&self, name: &str) -> Result<(tokio::fs::File, u64), LibraryError> {
        let lib = self.clone();
        let name = name.to_string();
        let (file, meta) = blocking(move || {
            let path = lib.path_of(&name)?;
            open_regular(&path).map_err(|e| match e {
                OpenError::Io(e) => lib.io_error(&name, "open", e),
                OpenError::NotRegular(what) => LibraryError::NotTaken {
                    file: files::file_name(&path),
                    why: format!("it is {what}, not a regular file"),
                },
            })
        })
        .await?;
        Ok((tokio::fs::File::from_std(file), meta.len()))
    }

    /// Reads a whole program, its latest revision, for a bus reply (whose payload is one
    /// message anyway): the content a job sends. Refuses one larger than `programs.max_size`.
    pub async fn read(&self, name: &str) -> Result<Vec<u8>, LibraryError> {
        self.check_name(name)?;
        Ok(self.read_revision(name, "").await?.1)
    }

    /// Every kept revision of `name`, newest first.
    pub async fn revisions(&self, name: &str) -> Result<pb::ProgramRevisions, LibraryError> {
        self.check_name(name)?;
        let index = self.index().await?;
        let n = name.to_string();
        let mut revisions = blocking(move || Ok(index.revisions(&n)?)).await?;
        if revisions.is_empty() {
            return Err(LibraryError::NotFound {
                name: name.to_string(),
            });
        }
        let removed = revisions.last().is_some_and(|r| r.removed);
        revisions.reverse();
        Ok(pb::ProgramRevisions {
            name: name.to_string(),
            revisions,
            removed,
        })
    }

    /// The number of the latest released (or locked) revision of `name`: what a machine with
    /// `accept = "released"` is sent. `None` when it has none, or no such program.
    pub async fn latest_released(&self, name: &str) -> Option<u32> {
        let all = self.revisions(name).await.ok()?;
        all.revisions
            .iter()
            .find(|r| is_released(r))
            .map(|r| r.number)
    }

    /// The revision `rev` names (a number, a SHA-256, or empty for the latest) and the path
    /// of its content, which never changes.
    pub async fn revision(
        &self,
        name: &str,
        rev: &str,
    ) -> Result<(pb::ProgramRevision, PathBuf), LibraryError> {
        self.check_name(name)?;
        let index = self.index().await?;
        let n = name.to_string();
        let revisions = blocking(move || Ok(index.revisions(&n)?)).await?;
        if revisions.is_empty() {
            return Err(LibraryError::NotFound {
                name: name.to_string(),
            });
        }
        let r = find(name, &revisions, rev)?.clone();
        if rev.trim().is_empty() && r.removed {
            return Err(LibraryError::Removed {
                name: name.to_string(),
                latest: r.number,
            });
        }
        let path = self.object_path(&r.sha256);
        // Content that is gone is said so, never served as if it were there.
        match std::fs::symlink_metadata(&path) {
            Ok(m) if m.is_file() => Ok((r, path)),
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                Err(self.io_error(name, "read", e))
            }
            _ => Err(content_missing(&r)),
        }
    }

    /// A revision and its content.
    pub async fn read_revision(
        &self,
        name: &str,
        rev: &str,
    ) -> Result<(pb::ProgramRevision, Vec<u8>), LibraryError> {
        let (r, path) = self.revision(name, rev).await?;
        if r.size > self.max_size {
            return Err(LibraryError::TooLarge {
                name: name.to_string(),
                size: r.size,
                max: self.max_size,
            });
        }
        let lib = self.clone();
        let name = name.to_string();
        blocking(move || {
            use std::io::Read as _;
            let (mut file, meta) = open_regular(&path).map_err(|e| match e {
                OpenError::Io(e) if e.kind() != std::io::ErrorKind::NotFound => {
                    lib.io_error(&name, "read", e)
                }
                _ => content_missing(&r),
            })?;
            let mut bytes = Vec::with_capacity(usize::try_from(meta.len()).unwrap_or(0));
            file.by_ref()
                .take(lib.max_size.saturating_add(1))
                .read_to_end(&mut bytes)
                .map_err(|e| lib.io_error(&name, "read", e))?;
            Ok((r, bytes))
        })
        .await
    }

    /// Changes the state of revision `rev` (empty: the latest): draft → released, draft or
    /// released → locked, released → draft (unreleased), locked → released (unlocked).
    pub async fn set_state(
        &self,
        name: &str,
        rev: &str,
        state: RevisionState,
        by: pb::RequestOrigin,
        comment: String,
    ) -> Result<pb::ProgramRevision, LibraryError> {
        self.check_name(name)?;
        let index = self.index().await?;
        let _store = self.stores.lock().await;
        let (name, rev) = (name.to_string(), rev.to_string());
        blocking(move || {
            let revisions = index.revisions(&name)?;
            if revisions.is_empty() {
                return Err(LibraryError::NotFound { name });
            }
            let mut r = find(&name, &revisions, &rev)?.clone();
            let transition = |why: &str| LibraryError::Transition {
                name: name.clone(),
                number: r.number,
                why: why.to_string(),
            };
            let next = match (r.state(), state) {
                (_, RevisionState::Unspecified) => {
                    return Err(transition(
                        "say the state it takes: released, locked or draft",
                    ));
                }
                (from, to) if from == to => return Ok(r),
                (RevisionState::Locked, RevisionState::Draft) => RevisionState::Released,
                (RevisionState::Draft | RevisionState::Unspecified, RevisionState::Locked) => {
                    RevisionState::Locked
                }
                (_, to) => to,
            };
            r.state = next as i32;
            r.state_unix_ms = pb::now_ms();
            r.state_by = Some(by);
            r.state_comment = comment;
            index.put(std::slice::from_ref(&r), &[])?;
            Ok(r)
        })
        .await
    }

    /// Removes a program, by nobody in particular; returns it as it was.
    pub async fn remove(&self, name: &str) -> Result<ProgramEntry, LibraryError> {
        self.remove_by(name).await
    }

    /// Removes a program; returns it as it was. Its revisions stay readable until retention
    /// drops them; a locked program is not removed.
    pub async fn remove_by(&self, name: &str) -> Result<ProgramEntry, LibraryError> {
        let path = self.path_of(name)?;
        // Only programs: a directory that happens to carry a valid name is not one.
        let entry = self.entry(name).await?;
        if let Some(l) = &entry.latest
            && l.state() == RevisionState::Locked
        {
            return Err(LibraryError::Locked {
                name: name.to_string(),
                number: l.number,
                what: "removed",
            });
        }
        let index = self.index().await?;
        let _store = self.stores.lock().await;
        // Already gone from the folder (its watcher off): the revision is marked all the same.
        match tokio::fs::remove_file(&path).await {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(self.io_error(name, "remove", e)),
        }
        self.sync_dir()
            .await
            .map_err(|e| self.io_error(name, "sync the directory after removing", e))?;
        if let Some(mut latest) = entry.latest.clone() {
            latest.removed = true;
            blocking(move || Ok(index.put(&[latest], &[])?)).await?;
        }
        Ok(entry)
    }

    /// Every program, by name: those with a revision that is not removed, and the folder's
    /// files not yet taken. Files whose names give no program name are skipped.
    pub async fn list(&self) -> Result<Vec<ProgramEntry>, LibraryError> {
        let index = self.index().await?;
        let lib = self.clone();
        blocking(move || lib.list_blocking(&index)).await
    }
}

fn content_missing(r: &pb::ProgramRevision) -> LibraryError {
    LibraryError::ContentMissing {
        name: r.name.clone(),
        number: r.number,
        sha256: r.sha256.clone(),
    }
}

/// Runs library file and index work off the runtime's threads.
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, LibraryError> + Send + 'static,
) -> Result<T, LibraryError> {
    tokio::task::spawn_blocking(f).await.unwrap_or_else(|e| {
        Err(LibraryError::Io {
            name: String::new(),
            op: "run the library task",
            path: PathBuf::new(),
            source: std::io::Error::other(e.to_string()),
        })
    })
}

fn modified_ms(meta: &std::fs::Metadata) -> u64 {
    meta.modified().map_or(0, cellgate_core::pb::unix_ms)
}

impl BusCode for LibraryError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            LibraryError::NotFound { .. }
            | LibraryError::Removed { .. }
            | LibraryError::NoRevision { .. } => pb::ErrorCode::NotFound,
            LibraryError::InvalidName { .. }
            | LibraryError::TooLarge { .. }
            | LibraryError::Exists { .. }
            | LibraryError::Transition { .. } => pb::ErrorCode::InvalidRequest,
            LibraryError::Conflict { .. } => pb::ErrorCode::Conflict,
            LibraryError::NotTaken { .. } => pb::ErrorCode::InvalidRequest,
            LibraryError::ContentMissing { .. } => pb::ErrorCode::StorageFailed,
            LibraryError::QuotaExceeded { .. } => pb::ErrorCode::QuotaExceeded,
            LibraryError::StorageFull { .. } => pb::ErrorCode::StorageFull,
            LibraryError::Io { .. } | LibraryError::Index(_) => pb::ErrorCode::StorageFailed,
            LibraryError::Locked { .. } => pb::ErrorCode::Locked,
            LibraryError::NotReleased { .. } => pb::ErrorCode::NotReleased,
        }
    }
}

#[cfg(test)]
mod tests;
