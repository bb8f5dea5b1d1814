//! One program, one file. A store from the bus writes the file a CAM system would post
//! (`O1234.nc`, with the first of `programs.extensions`), so that a later post of that name
//! is an edit of the same file; and a file posted under another extension of a program
//! whose file is only the library's copy of its latest revision takes that copy's place
//! instead of standing beside it as a conflict.

use std::os::unix::fs::MetadataExt as _;
use std::path::{Path, PathBuf};

use sha2::{Digest as _, Sha256};

use cellgate_core::pb::RevisionState;

use super::{Index, LibraryError, ProgramLibrary, files, is_regular, open_regular};

impl ProgramLibrary {
    /// The file a store of `name` writes: the one that holds the program now, else
    /// `NAME.EXT` for the first of `programs.extensions`, else (no extensions) `NAME`.
    /// Blocking (a few `stat`s).
    pub(super) fn store_path(&self, name: &str) -> Result<PathBuf, LibraryError> {
        let path = self.path_of(name)?;
        if is_regular(&path) {
            return Ok(path);
        }
        Ok(match self.folder.extensions.first() {
            Some(ext) => self.dir.join(format!("{name}.{ext}")),
            None => path,
        })
    }

    /// The file of `name` a take of the folder's `posted` file reads: [`Self::path_of`], but
    /// where several files give the name and all but one hold the program's latest revision
    /// (a copy the library wrote, or the post that revision came from), those copies are
    /// removed and the one that differs is the program's file. Several that differ, a
    /// removed or a locked program stay a conflict. Blocking.
    pub(super) fn posted_path(
        &self,
        index: &Index,
        name: &str,
        posted: &str,
    ) -> Result<PathBuf, LibraryError> {
        let conflict = match self.path_of(name) {
            Err(e @ LibraryError::Conflict { .. }) => e,
            other => return other,
        };
        // A locked revision's file is kept whatever is posted beside it.
        let latest = index
            .revisions(name)?
            .pop()
            .filter(|r| !r.removed && r.state() != RevisionState::Locked);
        let Some(latest) = latest else {
            return Err(conflict);
        };
        let listed = std::fs::read_dir(self.dir.as_path()).map_err(|e| LibraryError::Io {
            name: name.to_string(),
            op: "list",
            path: self.dir.as_path().to_path_buf(),
            source: e,
        })?;
        // The regular files that give the name, as `path_of` finds them (one file under two
        // names, on a file system that ignores case, once).
        let mut seen = Vec::new();
        let files: Vec<PathBuf> = listed
            .filter_map(Result::ok)
            .filter(|f| {
                f.file_name()
                    .to_str()
                    .is_some_and(|f| f == name || self.folder.strip(f) == name)
            })
            .filter(|f| {
                std::fs::symlink_metadata(f.path()).is_ok_and(|m| {
                    let id = (m.dev(), m.ino());
                    let new = m.is_file() && !seen.contains(&id);
                    seen.push(id);
                    new
                })
            })
            .map(|f| f.path())
            .collect();
        let (copies, differing): (Vec<PathBuf>, Vec<PathBuf>) = files
            .into_iter()
            .partition(|p| sha256_regular(p).is_some_and(|sha| sha == latest.sha256));
        let keep = match differing.as_slice() {
            [one] => one.clone(),
            // All the same content: the file just posted is the one its writer uses.
            [] => self.dir.join(posted),
            _ => return Err(conflict),
        };
        for copy in copies.iter().filter(|c| **c != keep) {
            match std::fs::remove_file(copy) {
                Ok(()) => tracing::info!(
                    program = name,
                    copy = %files::file_name(copy),
                    file = %files::file_name(&keep),
                    "a file posted under another extension takes the place of the program's \
                     copy of its latest revision"
                ),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => {
                    return Err(LibraryError::Io {
                        name: name.to_string(),
                        op: "remove",
                        path: copy.clone(),
                        source: e,
                    });
                }
            }
        }
        self.path_of(name)
    }
}

/// The SHA-256 of the regular file at `path`, opened as the library opens a program's file
/// (never through a link, never blocking on a FIFO); `None` if it is none or unreadable.
fn sha256_regular(path: &Path) -> Option<String> {
    let (mut file, _) = open_regular(path).ok()?;
    let mut hasher = Sha256::new();
    std::io::copy(&mut file, &mut hasher).ok()?;
    Some(hex::encode(hasher.finalize()))
}
