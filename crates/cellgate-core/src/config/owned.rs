//! The files the gateway owns (its job journal, history, keys, users file, zenoh file and the
//! cell file itself) and the library's folder: none of them may be one of the library's
//! programs. A program name is a file name in `programs.dir`, so a journal there would be
//! listed as a program, its bytes served to anyone with `program.read`, and a library remove
//! (`program.write`) would delete accepted jobs. Hidden entries (`.journal`, `.history`, the
//! defaults) are never program names, so they are allowed.
//!
//! Paths are compared as written, made absolute against the working directory and with `.`
//! and `..` folded; nothing here touches the disk (a path that does not exist yet is still
//! checked). A symbolic link that leads into the library is not followed.

use std::path::{Component, Path, PathBuf};

/// `path` made absolute against the working directory, with `.` and `..` folded.
pub fn lexical(path: &Path) -> PathBuf {
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let mut out = PathBuf::new();
    for c in absolute.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                out.pop();
            }
            other => out.push(other.as_os_str()),
        }
    }
    out
}

/// Whether `path` is the library's folder `dir` itself or lies in it through an entry the
/// library would take for a program (not hidden).
pub fn listed_in(dir: &Path, path: &Path) -> bool {
    let (dir, path) = (lexical(dir), lexical(path));
    match path.strip_prefix(&dir) {
        Ok(rest) => rest
            .components()
            .next()
            .is_none_or(|c| !c.as_os_str().to_string_lossy().starts_with('.')),
        Err(_) => false,
    }
}

/// Whether `path` (a file in the library) is, holds or lies in one of `owned`. The library's
/// own guard: check-config refuses such a cell file, so this only holds if a file is moved
/// under a running gateway.
pub fn is_owned(owned: &[PathBuf], dir: &Path, path: &Path) -> bool {
    let (dir, path) = (lexical(dir), lexical(path));
    owned.iter().any(|o| {
        // The library's folder itself may be named as an owned directory (a journal there):
        // then only the owned files in it count, and those are listed apart.
        *o == path || (*o != dir && (path.starts_with(o) || o.starts_with(&path)))
    })
}

#[cfg(test)]
mod tests;
