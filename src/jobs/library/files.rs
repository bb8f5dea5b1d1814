//! The library's folder as a CAM system uses it: a file posted or edited in `programs.dir`
//! becomes the program's next revision, a file deleted there marks the program removed. The
//! watcher ([`crate::jobs::folder`]) decides when a file is complete and calls these; here is
//! what the library makes of it, under the same lock, name rules, size bound and quota as a
//! store from the bus. The file itself is never written: it stays as its writer left it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use cellgate_core::pb::{self, RevisionState};
use cellgate_core::program::folder::Skip;

use super::{
    Index, LibraryError, ProgramEntry, ProgramLibrary, blocking, is_released, modified_ms,
    sha256_hex,
};

/// What became of a file of the folder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Taken {
    /// It is the program's new latest revision.
    Revision(ProgramEntry),
    /// Its content is the latest revision's already (the gateway's own store, a touch).
    Unchanged,
    /// It was deleted and its program, marked removed (as it was).
    Removed(ProgramEntry),
    /// Nothing to do: it is gone and was no program's, or another file holds the name now.
    Nothing,
}

/// A file of the folder as the watcher hands it over.
#[derive(Debug, Clone)]
pub struct FolderFile {
    /// Its name in `programs.dir`.
    pub file: String,
    /// Who made it: `(folder)` and the file's owner where the system says.
    pub by: pb::RequestOrigin,
}

/// The file names of `paths`, for a message.
pub(super) fn file_list(paths: &[PathBuf]) -> String {
    paths
        .iter()
        .map(|p| file_name(p))
        .collect::<Vec<_>>()
        .join(", ")
}

pub(super) fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

impl ProgramLibrary {
    /// The program `file` gives, if any: its name without a listed extension.
    pub fn program_of(&self, file: &str) -> Result<String, Skip> {
        self.folder.program_name(file).map(str::to_string)
    }

    /// Takes the complete file `file` of the folder as its program's next revision, by
    /// `by`. Refused as a bus store would be (a locked latest revision, `max_size`, the
    /// quota), and when another file gives the same name; the file is left as it is.
    pub async fn take_file(&self, f: FolderFile) -> Result<Taken, LibraryError> {
        let name = self
            .program_of(&f.file)
            .map_err(|skip| LibraryError::InvalidName {
                name: f.file.clone(),
                reason: match skip {
                    Skip::Temporary => "it is a hidden or temporary file",
                    Skip::BadName(reason) => reason,
                },
            })?;
        self.check_name(&name)?;
        let index = self.index().await?;
        let _store = self.stores.lock().await;
        let lib = self.clone();
        blocking(move || lib.take_blocking(&index, &name, f)).await
    }

    fn take_blocking(
        &self,
        index: &Index,
        name: &str,
        f: FolderFile,
    ) -> Result<Taken, LibraryError> {
        let path = self.posted_path(index, name, &f.file)?;
        if file_name(&path) != f.file {
            // Renamed or deleted since it was seen: its own event follows.
            return Ok(Taken::Nothing);
        }
        let io = |op| {
            let path = path.clone();
            move |source| LibraryError::Io {
                name: name.to_string(),
                op,
                path,
                source,
            }
        };
        let size = match std::fs::metadata(&path) {
            Ok(m) if m.is_file() => m.len(),
            Ok(_) => return Ok(Taken::Nothing),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Taken::Nothing),
            Err(e) => return Err(io("read")(e)),
        };
        if size > self.max_size {
            return Err(LibraryError::TooLarge {
                name: name.to_string(),
                size,
                max: self.max_size,
            });
        }
        let bytes = std::fs::read(&path).map_err(io("read"))?;
        let size = bytes.len() as u64;
        let sha = sha256_hex(&bytes);
        let revisions = index.revisions(name)?;
        let latest = revisions.last().filter(|r| !r.removed);
        if let Some(l) = latest {
            if l.sha256 == sha {
                self.set_note(name, None);
                return Ok(Taken::Unchanged);
            }
            if l.state() == RevisionState::Locked {
                let e = LibraryError::Locked {
                    name: name.to_string(),
                    number: l.number,
                    what: "replaced by the edit of its file in the folder (the file is left as \
                           it is; the library keeps sending the locked revision)",
                };
                self.set_note(
                    name,
                    Some(format!(
                        "{}: edited, but revision {} is locked; the edit is not taken",
                        f.file, l.number
                    )),
                );
                return Err(e);
            }
        }
        self.check_quota(index, name, &sha, size, latest.is_none())?;
        self.write_object(name, &sha, &bytes)?;
        let now = pb::now_ms();
        let revision = pb::ProgramRevision {
            name: name.to_string(),
            number: revisions.last().map_or(1, |r| r.number + 1),
            sha256: sha,
            size,
            unix_ms: now,
            by: Some(f.by),
            comment: format!("from the folder: {}", f.file),
            state: RevisionState::Draft as i32,
            ..Default::default()
        };
        let mut all = revisions.clone();
        all.push(revision.clone());
        let dropped = self.retained_out(&all, now);
        index.put(&[revision], &dropped)?;
        if !dropped.is_empty() {
            self.collect_objects(index);
        }
        self.set_note(name, None);
        let mut entry = self.entry_blocking(name, index)?;
        entry.revised = true;
        Ok(Taken::Revision(entry))
    }

    /// `file` is gone from the folder: its program is marked removed, its revisions kept
    /// (posting it again makes the next one). A locked program is not removed: refused,
    /// and the library keeps its locked revision.
    pub async fn file_gone(&self, file: &str) -> Result<Taken, LibraryError> {
        let Ok(name) = self.program_of(file) else {
            return Ok(Taken::Nothing);
        };
        if self.check_name(&name).is_err() {
            return Ok(Taken::Nothing);
        }
        let index = self.index().await?;
        let _store = self.stores.lock().await;
        let lib = self.clone();
        let file = file.to_string();
        blocking(move || {
            // Another file still gives the name (one of a conflict removed): it stands.
            match lib.path_of(&name) {
                Ok(p) if p.is_file() => return Ok(Taken::Nothing),
                Err(LibraryError::Conflict { .. }) => return Ok(Taken::Nothing),
                _ => {}
            }
            let revisions = index.revisions(&name)?;
            let Some(latest) = revisions.last().filter(|r| !r.removed) else {
                lib.set_note(&name, None);
                return Ok(Taken::Nothing);
            };
            if latest.state() == RevisionState::Locked {
                lib.set_note(
                    &name,
                    Some(format!(
                        "{file}: deleted, but revision {} is locked; the library keeps it",
                        latest.number
                    )),
                );
                return Err(LibraryError::Locked {
                    name,
                    number: latest.number,
                    what: "removed (its file was deleted from the folder; the library keeps \
                           the locked revision)",
                });
            }
            let mut gone = latest.clone();
            gone.removed = true;
            index.put(std::slice::from_ref(&gone), &[])?;
            lib.set_note(&name, None);
            Ok(Taken::Removed(ProgramEntry {
                name: name.clone(),
                size: latest.size,
                modified_unix_ms: latest.unix_ms,
                latest_released: revisions
                    .iter()
                    .rev()
                    .find(|r| is_released(r))
                    .map_or(0, |r| r.number),
                latest: Some(gone),
                file,
                note: String::new(),
                revised: false,
            }))
        })
        .await
    }

    /// The programs whose latest revision stands (not removed) but whose file the folder
    /// no longer has: deleted while the gateway was stopped or the watcher missed it.
    pub async fn files_missing(&self) -> Result<Vec<String>, LibraryError> {
        let index = self.index().await?;
        let lib = self.clone();
        blocking(move || {
            Ok(index
                .latest_all()?
                .into_iter()
                .filter(|r| !r.removed && !matches!(lib.path_of(&r.name), Ok(p) if p.is_file()))
                .filter(|r| !matches!(lib.path_of(&r.name), Err(LibraryError::Conflict { .. })))
                .map(|r| r.name)
                .collect())
        })
        .await
    }

    /// Whether `name` may be a program of this library (see [`ProgramLibrary::check_name`]).
    pub fn is_program_name(&self, name: &str) -> bool {
        self.check_name(name).is_ok()
    }

    /// The file of the folder that holds `name` now, if one does.
    pub async fn file_of(&self, name: &str) -> Result<Option<String>, LibraryError> {
        let lib = self.clone();
        let name = name.to_string();
        blocking(move || {
            let path = lib.path_of(&name)?;
            Ok(path.is_file().then(|| file_name(&path)))
        })
        .await
    }

    /// Records (or clears) why `name`'s file is not its latest revision, for the listing.
    pub fn set_note(&self, name: &str, note: Option<String>) {
        let Ok(mut notes) = self.notes.lock() else {
            return;
        };
        match note {
            Some(n) => notes.insert(name.to_string(), n),
            None => notes.remove(name),
        };
    }

    pub(super) fn note_of(&self, name: &str) -> String {
        self.notes
            .lock()
            .ok()
            .and_then(|n| n.get(name).cloned())
            .unwrap_or_default()
    }

    /// The listing: every program with a standing revision, and every file of the folder
    /// that gives a name (a file not yet taken shows with no revision and its own size).
    /// Blocking.
    pub(super) fn list_blocking(&self, index: &Index) -> Result<Vec<ProgramEntry>, LibraryError> {
        let dir_error = |source| LibraryError::Io {
            name: String::new(),
            op: "list",
            path: self.dir.as_path().to_path_buf(),
            source,
        };
        let mut files: BTreeMap<String, Vec<(String, std::fs::Metadata)>> = BTreeMap::new();
        match std::fs::read_dir(self.dir.as_path()) {
            Ok(dir) => {
                for item in dir {
                    let item = item.map_err(dir_error)?;
                    let Ok(file) = item.file_name().into_string() else {
                        continue;
                    };
                    let Ok(name) = self.program_of(&file) else {
                        continue;
                    };
                    if self.check_name(&name).is_err() {
                        continue;
                    }
                    let Ok(meta) = item.metadata() else { continue };
                    if meta.is_file() {
                        files.entry(name).or_default().push((file, meta));
                    }
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(dir_error(e)),
        }
        let mut entries = BTreeMap::new();
        for r in index.latest_all()? {
            if r.removed {
                continue;
            }
            let all = index.revisions(&r.name)?;
            entries.insert(
                r.name.clone(),
                ProgramEntry {
                    name: r.name.clone(),
                    size: r.size,
                    modified_unix_ms: r.unix_ms,
                    latest_released: all
                        .iter()
                        .rev()
                        .find(|x| is_released(x))
                        .map_or(0, |x| x.number),
                    latest: Some(r),
                    file: String::new(),
                    note: String::new(),
                    revised: false,
                },
            );
        }
        for (name, found) in files {
            let entry = entries.entry(name.clone()).or_insert_with(|| {
                let (size, modified) = found
                    .first()
                    .map_or((0, 0), |(_, m)| (m.len(), modified_ms(m)));
                ProgramEntry {
                    name: name.clone(),
                    size,
                    modified_unix_ms: modified,
                    latest: None,
                    latest_released: 0,
                    file: String::new(),
                    note: "not yet a revision: the folder's file is still being written, or \
                           the folder is not watched (programs.watch)"
                        .to_string(),
                    revised: false,
                }
            });
            entry.file = found
                .iter()
                .map(|(f, _)| f.as_str())
                .collect::<Vec<_>>()
                .join(", ");
            if found.len() > 1 {
                entry.note = format!(
                    "the files {} all give this name: neither is taken until one is removed \
                     or renamed",
                    entry.file
                );
            }
        }
        for (name, entry) in &mut entries {
            let note = self.note_of(name);
            if !note.is_empty() {
                entry.note = note;
            }
        }
        Ok(entries.into_values().collect())
    }
}
