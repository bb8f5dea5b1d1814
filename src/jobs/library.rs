//! The cell's program library: NC programs kept as files in `programs.dir`, one file per
//! program, named by its library name.
//!
//! Names are one key chunk of `P/C/program/<name>` and a plain file name at once: 1 to 128
//! characters of `A-Z a-z 0-9 . _ + -`, starting with a letter or digit. That rules out path
//! traversal (`..`, `/`), hidden files, and every zenoh wildcard or reserved character.
//!
//! A program is stored by writing a hidden temporary file and renaming it over the old one,
//! so a reader (a job streaming the program) keeps the complete old or new version, never a
//! mix. The file is synced before the rename and the directory after it, so a power cut
//! leaves the old program or the new one, never an empty name. Temporary files a crash left
//! behind are removed when the gateway starts ([`ProgramLibrary::create_dir`]).
//!
//! Optional quotas bound the library's bytes and files ([`Quota`]).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::UNIX_EPOCH;

use tokio::io::AsyncWriteExt;

/// Longest library name.
pub const NAME_MAX: usize = 128;

/// Why a library operation failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LibraryError {
    #[error("program name {name:?} is not valid: {reason}")]
    InvalidName { name: String, reason: &'static str },
    #[error("the program library has no program {name:?}")]
    NotFound { name: String },
    #[error("the program library already has a program {name:?}")]
    Exists { name: String },
    #[error("program {name:?} is {size} bytes; programs.max_size allows {max}")]
    TooLarge { name: String, size: u64, max: u64 },
    /// Storing the program would take the library past `programs.quota_bytes` or
    /// `programs.quota_files`.
    #[error(
        "program {name:?} not stored: the library would hold {would} {what}, over \
         programs.quota_{what} = {limit}; remove programs first (`cellgate program rm`)"
    )]
    QuotaExceeded {
        name: String,
        what: &'static str,
        would: u64,
        limit: u64,
    },
    #[error("program {name:?}: cannot {op} {}: {source}", path.display())]
    Io {
        name: String,
        op: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// One stored program.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProgramEntry {
    pub name: String,
    pub size: u64,
    /// Last stored, ms since the Unix epoch (0 if the file system does not say).
    pub modified_unix_ms: u64,
}

/// Whether a store may replace a program of the same name.
#[derive(Debug, Clone, Copy)]
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

/// The program library. Cheap to clone.
#[derive(Debug, Clone)]
pub struct ProgramLibrary {
    dir: Arc<PathBuf>,
    max_size: u64,
    quota: Quota,
}

static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Checks a library name (see the module documentation).
pub fn validate_name(name: &str) -> Result<(), LibraryError> {
    let invalid = |reason| {
        Err(LibraryError::InvalidName {
            name: name.to_string(),
            reason,
        })
    };
    if name.is_empty() {
        return invalid("it is empty");
    }
    if name.len() > NAME_MAX {
        return invalid("it is longer than 128 characters");
    }
    if !name
        .bytes()
        .all(|b| b.is_ascii_alphanumeric() || b"._+-".contains(&b))
    {
        return invalid("use only letters, digits, '.', '_', '+' and '-'");
    }
    if !name
        .as_bytes()
        .first()
        .is_some_and(u8::is_ascii_alphanumeric)
    {
        return invalid("it must start with a letter or a digit");
    }
    Ok(())
}

impl ProgramLibrary {
    pub fn new(dir: impl Into<PathBuf>, max_size: u64) -> Self {
        ProgramLibrary {
            dir: Arc::new(dir.into()),
            max_size,
            quota: Quota::default(),
        }
    }

    /// The same library, bounded by `quota`.
    pub fn with_quota(mut self, quota: Quota) -> Self {
        self.quota = quota;
        self
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn max_size(&self) -> u64 {
        self.max_size
    }

    /// Creates the directory if it does not exist, and removes the temporary files a crash
    /// left in it (those of this process, which has written nothing yet, excepted).
    pub async fn create_dir(&self) -> std::io::Result<()> {
        tokio::fs::create_dir_all(self.dir.as_path()).await?;
        let mut dir = tokio::fs::read_dir(self.dir.as_path()).await?;
        let own = format!(".{}.", std::process::id());
        while let Some(item) = dir.next_entry().await? {
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
        Ok(())
    }

    /// Makes the directory's entries (a rename, a link, a removal) durable.
    async fn sync_dir(&self) -> std::io::Result<()> {
        tokio::fs::File::open(self.dir.as_path())
            .await?
            .sync_all()
            .await
    }

    /// Refuses a store of `size` bytes under `name` that would break the quota.
    async fn check_quota(&self, name: &str, size: u64) -> Result<(), LibraryError> {
        if self.quota == Quota::default() {
            return Ok(());
        }
        // The program it replaces does not count.
        let others: Vec<ProgramEntry> = self
            .list()
            .await?
            .into_iter()
            .filter(|e| e.name != name)
            .collect();
        let checks = [
            (
                "bytes",
                self.quota.bytes,
                others.iter().map(|e| e.size).sum::<u64>() + size,
            ),
            ("files", self.quota.files, others.len() as u64 + 1),
        ];
        for (what, limit, would) in checks {
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

    pub(crate) fn path_of(&self, name: &str) -> Result<PathBuf, LibraryError> {
        validate_name(name)?;
        Ok(self.dir.join(name))
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

    /// Stores `program` under `name`, replacing any program of that name.
    pub async fn store(&self, name: &str, program: &[u8]) -> Result<ProgramEntry, LibraryError> {
        self.write(name, program, Place::Replace).await
    }

    /// Stores `program` under `name` only if no program has that name yet
    /// ([`LibraryError::Exists`] otherwise). Two writers racing for one name cannot both win:
    /// the file is linked into place, which fails when the name is taken.
    pub async fn store_new(
        &self,
        name: &str,
        program: &[u8],
    ) -> Result<ProgramEntry, LibraryError> {
        self.write(name, program, Place::New).await
    }

    async fn write(
        &self,
        name: &str,
        program: &[u8],
        place: Place,
    ) -> Result<ProgramEntry, LibraryError> {
        let path = self.path_of(name)?;
        let size = program.len() as u64;
        if size > self.max_size {
            return Err(LibraryError::TooLarge {
                name: name.to_string(),
                size,
                max: self.max_size,
            });
        }
        self.check_quota(name, size).await?;
        // Hidden (leading '.'), so never a valid name and never listed.
        let temp = self.dir.join(format!(
            ".{name}.{}.{}.tmp",
            std::process::id(),
            TEMP_COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        let written = async {
            let mut file = tokio::fs::File::create(&temp).await?;
            file.write_all(program).await?;
            file.sync_all().await?;
            drop(file);
            match place {
                Place::Replace => tokio::fs::rename(&temp, &path).await,
                Place::New => {
                    let linked = tokio::fs::hard_link(&temp, &path).await;
                    let _ = tokio::fs::remove_file(&temp).await;
                    linked
                }
            }?;
            self.sync_dir().await
        }
        .await;
        if let Err(e) = written {
            let _ = tokio::fs::remove_file(&temp).await;
            if e.kind() == std::io::ErrorKind::AlreadyExists {
                return Err(LibraryError::Exists {
                    name: name.to_string(),
                });
            }
            return Err(LibraryError::Io {
                name: name.to_string(),
                op: "write",
                path,
                source: e,
            });
        }
        self.entry(name).await
    }

    pub(crate) async fn entry(&self, name: &str) -> Result<ProgramEntry, LibraryError> {
        let path = self.path_of(name)?;
        let meta = tokio::fs::metadata(&path)
            .await
            .map_err(|e| self.io_error(name, "read", e))?;
        if !meta.is_file() {
            return Err(LibraryError::NotFound {
                name: name.to_string(),
            });
        }
        Ok(ProgramEntry {
            name: name.to_string(),
            size: meta.len(),
            modified_unix_ms: modified_ms(&meta),
        })
    }

    /// Opens a program for streaming; returns the file and its size.
    pub async fn open(&self, name: &str) -> Result<(tokio::fs::File, u64), LibraryError> {
        let path = self.path_of(name)?;
        let file = tokio::fs::File::open(&path)
            .await
            .map_err(|e| self.io_error(name, "open", e))?;
        let meta = file
            .metadata()
            .await
            .map_err(|e| self.io_error(name, "open", e))?;
        if !meta.is_file() {
            return Err(LibraryError::NotFound {
                name: name.to_string(),
            });
        }
        Ok((file, meta.len()))
    }

    /// Reads a whole program, for a bus reply (whose payload is one message anyway). Refuses
    /// one larger than `programs.max_size`.
    pub async fn read(&self, name: &str) -> Result<Vec<u8>, LibraryError> {
        let entry = self.entry(name).await?;
        if entry.size > self.max_size {
            return Err(LibraryError::TooLarge {
                name: name.to_string(),
                size: entry.size,
                max: self.max_size,
            });
        }
        let path = self.path_of(name)?;
        tokio::fs::read(&path)
            .await
            .map_err(|e| self.io_error(name, "read", e))
    }

    /// Removes a program; returns it as it was.
    pub async fn remove(&self, name: &str) -> Result<ProgramEntry, LibraryError> {
        let path = self.path_of(name)?;
        // Only programs: a directory that happens to carry a valid name is not one.
        let entry = self.entry(name).await?;
        tokio::fs::remove_file(&path)
            .await
            .map_err(|e| self.io_error(name, "remove", e))?;
        self.sync_dir()
            .await
            .map_err(|e| self.io_error(name, "sync the directory after removing", e))?;
        Ok(entry)
    }

    /// Every program, by name. Files whose names are not valid library names are skipped.
    pub async fn list(&self) -> Result<Vec<ProgramEntry>, LibraryError> {
        let dir_error = |e| LibraryError::Io {
            name: String::new(),
            op: "list",
            path: self.dir.as_path().to_path_buf(),
            source: e,
        };
        let mut entries = Vec::new();
        let mut dir = match tokio::fs::read_dir(self.dir.as_path()).await {
            Ok(d) => d,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(entries),
            Err(e) => return Err(dir_error(e)),
        };
        while let Some(item) = dir.next_entry().await.map_err(dir_error)? {
            let Ok(name) = item.file_name().into_string() else {
                continue;
            };
            if validate_name(&name).is_err() {
                continue;
            }
            let Ok(meta) = item.metadata().await else {
                continue;
            };
            if meta.is_file() {
                entries.push(ProgramEntry {
                    name,
                    size: meta.len(),
                    modified_unix_ms: modified_ms(&meta),
                });
            }
        }
        entries.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(entries)
    }
}

fn modified_ms(meta: &std::fs::Metadata) -> u64 {
    meta.modified()
        .ok()
        .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_one_safe_key_chunk() {
        for ok in ["O1234", "part-7.nc", "a", "X_1+2", &"n".repeat(128)] {
            assert!(validate_name(ok).is_ok(), "{ok}");
        }
        for bad in [
            "",
            ".",
            "..",
            "../etc",
            "a/b",
            ".hidden",
            "-x",
            "a*",
            "**",
            "a$b",
            "a?b",
            "a#b",
            "sp ace",
            "@admin",
            "é",
            &"n".repeat(129),
        ] {
            assert!(validate_name(bad).is_err(), "{bad:?}");
        }
    }

    #[tokio::test]
    async fn store_read_list_remove() {
        let dir = tempfile::tempdir().unwrap();
        let lib = ProgramLibrary::new(dir.path(), 100);
        assert!(lib.list().await.unwrap().is_empty());
        let e = lib.store("O1", b"%\nO1\n%").await.unwrap();
        assert_eq!(e.size, 6);
        lib.store("O2", b"%\nO2\n%").await.unwrap();
        lib.store("O1", b"%\nO1\nM30\n%").await.unwrap();
        assert_eq!(lib.read("O1").await.unwrap(), b"%\nO1\nM30\n%");
        let names: Vec<_> = lib
            .list()
            .await
            .unwrap()
            .into_iter()
            .map(|e| e.name)
            .collect();
        assert_eq!(names, ["O1", "O2"]);
        lib.remove("O1").await.unwrap();
        assert!(matches!(
            lib.read("O1").await,
            Err(LibraryError::NotFound { .. })
        ));
        assert!(matches!(
            lib.remove("O1").await,
            Err(LibraryError::NotFound { .. })
        ));
        assert!(matches!(
            lib.store("big", &[b'x'; 101]).await,
            Err(LibraryError::TooLarge { size: 101, .. })
        ));
        assert!(matches!(
            lib.store("../x", b"x").await,
            Err(LibraryError::InvalidName { .. })
        ));
        // No temporary file is left behind, and stray files are not listed.
        std::fs::write(dir.path().join(".junk"), b"x").unwrap();
        let names: Vec<_> = lib
            .list()
            .await
            .unwrap()
            .into_iter()
            .map(|e| e.name)
            .collect();
        assert_eq!(names, ["O2"]);
    }

    #[tokio::test]
    async fn store_new_never_replaces() {
        let dir = tempfile::tempdir().unwrap();
        let lib = ProgramLibrary::new(dir.path(), 100);
        lib.store_new("m-O1", b"%\nO1\n%").await.unwrap();
        assert!(matches!(
            lib.store_new("m-O1", b"%\nO1\nM30\n%").await,
            Err(LibraryError::Exists { .. })
        ));
        assert_eq!(lib.read("m-O1").await.unwrap(), b"%\nO1\n%");
        // Racing writers: exactly one wins each name, and no temporary file is left.
        let tries = (0..8).map(|i| {
            let lib = lib.clone();
            tokio::spawn(async move { lib.store_new("m-O2", format!("%{i}%").as_bytes()).await })
        });
        let mut won = 0;
        for t in tries {
            if t.await.unwrap().is_ok() {
                won += 1;
            }
        }
        assert_eq!(won, 1);
        let mut files: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        files.sort();
        assert_eq!(files, ["m-O1", "m-O2"]);
    }

    #[tokio::test]
    async fn quotas_refuse_what_would_go_past_them_and_a_replaced_program_does_not_count() {
        let dir = tempfile::tempdir().unwrap();
        let lib = ProgramLibrary::new(dir.path(), 100).with_quota(Quota {
            bytes: Some(100),
            files: Some(2),
        });
        lib.store("A", &[b'x'; 60]).await.unwrap();
        // Replacing A: only the new size counts.
        lib.store("A", &[b'x'; 70]).await.unwrap();
        let e = lib.store("B", &[b'y'; 31]).await.unwrap_err();
        assert!(
            matches!(
                e,
                LibraryError::QuotaExceeded {
                    what: "bytes",
                    would: 101,
                    limit: 100,
                    ..
                }
            ),
            "{e}"
        );
        assert!(e.to_string().contains("programs.quota_bytes = 100"), "{e}");
        lib.store("B", &[b'y'; 29]).await.unwrap();
        let e = lib.store_new("C", b"z").await.unwrap_err();
        assert!(
            matches!(
                e,
                LibraryError::QuotaExceeded {
                    what: "files",
                    would: 3,
                    limit: 2,
                    ..
                }
            ),
            "{e}"
        );
        // Nothing of the refused stores is left.
        let names: Vec<String> = lib
            .list()
            .await
            .unwrap()
            .into_iter()
            .map(|e| e.name)
            .collect();
        assert_eq!(names, ["A", "B"]);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    }

    #[tokio::test]
    async fn temporary_files_of_an_earlier_run_are_removed_at_start() {
        let dir = tempfile::tempdir().unwrap();
        let lib = ProgramLibrary::new(dir.path(), 100);
        lib.store("KEEP", b"%\nO1\n%").await.unwrap();
        // What a crash between write and rename leaves, from another process id.
        let stale = dir.path().join(".O1234.999999999.3.tmp");
        std::fs::write(&stale, b"half a prog").unwrap();
        // A hidden file that is not a temporary file of the library stays.
        let other = dir.path().join(".keepme");
        std::fs::write(&other, b"").unwrap();
        lib.create_dir().await.unwrap();
        assert!(!stale.exists());
        assert!(other.exists());
        assert_eq!(lib.read("KEEP").await.unwrap(), b"%\nO1\n%");
    }
}
