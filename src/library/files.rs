//! The library's folder as a CAM system uses it: a file posted or edited in `programs.dir`
//! becomes the program's next revision, a file deleted there marks the program removed. The
//! watcher ([`crate::library::folder`]) decides when a file is complete and calls these; here is
//! what the library makes of it, under the same lock, name rules, size bound and quota as a
//! store from the bus. The file itself is never written: it stays as its writer left it.
//!
//! Only regular files are taken, opened without following a link and checked on the open
//! file ([`super::disk::open_regular`]), and copied into `.revisions` in pieces. A file the
//! folder does not take is said: by the watcher's report (the route logs, audits and
//! publishes it) and in the listing's `note`; hidden and temporary files excepted.

use std::collections::BTreeMap;
use std::ffi::OsStr;
use std::os::unix::fs::MetadataExt as _;
use std::path::{Path, PathBuf};

use cellgate_core::pb::{self, RevisionState};
use cellgate_core::program::folder::{Skip, is_temporary};

use super::disk::{CopyError, Incoming, OpenError, escaped, is_regular, open_regular};
use super::{
    Index, LibraryError, ProgramEntry, ProgramLibrary, blocking, is_released, modified_ms,
};
use crate::library::folder::{Verdict, not_regular};

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
    /// The file that holds `name`: `NAME`, or `NAME.EXT` for one of `programs.extensions`
    /// in any case (`O5555.nc`, `O5555.NC`, `O5555.Nc`) when the folder has one; two of them
    /// are a conflict. Only a regular file holds a program: a link or a FIFO of that name is
    /// none. Blocking (a few `lstat`s; a listing of the folder for a long extension).
    pub(crate) fn path_of(&self, name: &str) -> Result<PathBuf, LibraryError> {
        self.check_name(name)?;
        let mut found: Vec<(PathBuf, (u64, u64))> = Vec::new();
        let mut add = |p: PathBuf| {
            if let Ok(m) = std::fs::symlink_metadata(&p)
                && m.is_file()
                // One file under two names (a file system that ignores case) is one file.
                && !found.iter().any(|(_, id)| *id == (m.dev(), m.ino()))
            {
                found.push((p, (m.dev(), m.ino())));
            }
        };
        let plain = self.dir.join(name);
        add(plain.clone());
        let mut long = false;
        for ext in self.folder.extensions.iter() {
            match case_variants(ext) {
                Some(variants) => {
                    for e in variants {
                        add(self.dir.join(format!("{name}.{e}")));
                    }
                }
                None => long = true,
            }
        }
        if long && let Ok(dir) = std::fs::read_dir(self.dir.as_path()) {
            for item in dir.flatten() {
                if let Some(file) = item.file_name().to_str()
                    && file != name
                    && self.folder.strip(file) == name
                {
                    add(item.path());
                }
            }
        }
        match found.len() {
            0 => Ok(plain),
            1 => Ok(found.swap_remove(0).0),
            _ => Err(LibraryError::Conflict {
                name: name.to_string(),
                files: file_list(&found.into_iter().map(|(p, _)| p).collect::<Vec<_>>()),
            }),
        }
    }

    /// The program `file` gives, if any: its name without a listed extension.
    pub fn program_of(&self, file: &str) -> Result<String, Skip> {
        self.folder.program_name(file).map(str::to_string)
    }

    /// What the folder makes of the file name `file`: a program's file, passed over without
    /// a word (hidden and temporary files, the gateway's own), or refused and said, with why
    /// (a name that gives no program name).
    pub fn verdict(&self, file: &OsStr) -> Verdict {
        let path = self.dir.join(file);
        if cellgate_core::config::owned::is_owned(&self.owned, &self.dir, &path) {
            return Verdict::Pass;
        }
        let Some(text) = file.to_str() else {
            if is_temporary(&file.to_string_lossy()) {
                return Verdict::Pass;
            }
            return Verdict::Refuse(
                "its name is not UTF-8 text, so it gives no program name".to_string(),
            );
        };
        match self.program_of(text) {
            Err(Skip::Temporary) => Verdict::Pass,
            Err(Skip::BadName(reason)) => {
                Verdict::Refuse(format!("its name gives no program name: {reason}"))
            }
            Ok(name) => match self.check_name(&name) {
                Ok(()) => Verdict::Take,
                Err(LibraryError::InvalidName { reason, .. }) => {
                    Verdict::Refuse(format!("its name gives no program name: {name:?} {reason}"))
                }
                Err(e) => Verdict::Refuse(e.to_string()),
            },
        }
    }

    /// The refusal of a file the folder does not take (the watcher's report), as an error.
    pub fn not_taken(&self, file: &OsStr, why: &str) -> LibraryError {
        LibraryError::NotTaken {
            file: escaped(file),
            why: why.to_string(),
        }
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
        let index = self.index_to_store().await?;
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
        // Opened as it is now, never through a link: what is checked is what is read.
        let (file, meta) = match open_regular(&path) {
            Ok(opened) => opened,
            Err(OpenError::Io(e)) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok(Taken::Nothing);
            }
            Err(OpenError::Io(e)) => return Err(io("read")(e)),
            Err(OpenError::NotRegular(what)) => {
                return Err(LibraryError::NotTaken {
                    file: escaped(OsStr::new(&f.file)),
                    why: format!(
                        "it is {what}: only regular files inside the folder are taken (a link \
                         is never followed)"
                    ),
                });
            }
        };
        let too_large = |size| LibraryError::TooLarge {
            name: name.to_string(),
            size,
            max: self.max_size,
        };
        // Refused for its size before a byte is read, a sparse file too.
        if meta.len() > self.max_size {
            return Err(too_large(meta.len()));
        }
        self.make_objects_dir()
            .map_err(|e| self.write_error(name, self.objects_dir(), e))?;
        let incoming =
            Incoming::copy(file, &self.objects_dir(), self.max_size).map_err(|e| match e {
                CopyError::TooLarge(size) => too_large(size),
                CopyError::Read(e) => io("read")(e),
                CopyError::Write(path, e) => self.write_error(name, path, e),
            })?;
        let (sha, size) = (incoming.sha.clone(), incoming.size);
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
        incoming
            .keep(&self.objects_dir())
            .map_err(|e| self.write_error(name, self.object_path(&sha), e))?;
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
                Ok(p) if is_regular(&p) => return Ok(Taken::Nothing),
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
                .filter(|r| !r.removed && !matches!(lib.path_of(&r.name), Ok(p) if is_regular(&p)))
                .filter(|r| !matches!(lib.path_of(&r.name), Err(LibraryError::Conflict { .. })))
                .map(|r| r.name)
                .collect())
        })
        .await
    }

    /// Whether `name` may be a program of this library (see `ProgramLibrary::check_name`).
    pub fn is_program_name(&self, name: &str) -> bool {
        self.check_name(name).is_ok()
    }

    /// The file of the folder that holds `name` now, if one does.
    pub async fn file_of(&self, name: &str) -> Result<Option<String>, LibraryError> {
        let lib = self.clone();
        let name = name.to_string();
        blocking(move || {
            let path = lib.path_of(&name)?;
            Ok(is_regular(&path).then(|| file_name(&path)))
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

    /// The listing: every program with a standing revision, every file of the folder that
    /// gives a name (a file not yet taken shows with no revision and its own size), and every
    /// file the folder refuses (a name that gives no program name, a link, a FIFO), with no
    /// name, its `file` escaped and its `note` saying why. Blocking.
    pub(super) fn list_blocking(&self, index: &Index) -> Result<Vec<ProgramEntry>, LibraryError> {
        let dir_error = |source| LibraryError::Io {
            name: String::new(),
            op: "list",
            path: self.dir.as_path().to_path_buf(),
            source,
        };
        let mut files: BTreeMap<String, Vec<(String, std::fs::Metadata)>> = BTreeMap::new();
        let mut refused: BTreeMap<String, String> = BTreeMap::new();
        match std::fs::read_dir(self.dir.as_path()) {
            Ok(dir) => {
                for item in dir {
                    let item = item.map_err(dir_error)?;
                    let file = item.file_name();
                    let verdict = self.verdict(&file);
                    if verdict == Verdict::Pass {
                        continue;
                    }
                    // Not following a link: a link is listed as one.
                    let Ok(meta) = item.metadata() else { continue };
                    let kind = meta.file_type();
                    match (verdict, file.into_string()) {
                        _ if kind.is_dir() => {}
                        (Verdict::Take, Ok(file)) if kind.is_file() => {
                            if let Ok(name) = self.program_of(&file) {
                                files.entry(name).or_default().push((file, meta));
                            }
                        }
                        (Verdict::Take, Ok(file)) => {
                            refused.insert(file, not_regular(kind));
                        }
                        (Verdict::Refuse(why), file) => {
                            let file = match file {
                                Ok(f) => escaped(OsStr::new(&f)),
                                Err(f) => escaped(&f),
                            };
                            refused.insert(file, why);
                        }
                        _ => {}
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
        let mut out: Vec<ProgramEntry> = entries.into_values().collect();
        // No program, so no name: the file (escaped) and why it is not taken.
        out.extend(refused.into_iter().map(|(file, why)| ProgramEntry {
            name: String::new(),
            size: 0,
            modified_unix_ms: 0,
            latest: None,
            latest_released: 0,
            file,
            note: format!("not taken: {why}"),
            revised: false,
        }));
        Ok(out)
    }
}

/// Every spelling of `ext` in upper and lower case (`nc`: `nc`, `nC`, `Nc`, `NC`), or `None`
/// when there are more than 64 (an extension of seven letters or more): the folder is listed
/// instead.
pub(super) fn case_variants(ext: &str) -> Option<Vec<String>> {
    let letters = ext.bytes().filter(u8::is_ascii_alphabetic).count();
    if letters > 6 {
        return None;
    }
    let mut out = Vec::with_capacity(1 << letters);
    for mask in 0u32..(1 << letters) {
        let mut bit = 0;
        out.push(
            ext.chars()
                .map(|c| {
                    if !c.is_ascii_alphabetic() {
                        return c;
                    }
                    bit += 1;
                    if mask & (1 << (bit - 1)) == 0 {
                        c.to_ascii_lowercase()
                    } else {
                        c.to_ascii_uppercase()
                    }
                })
                .collect(),
        );
    }
    Some(out)
}
