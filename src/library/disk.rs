//! How the library touches the disk: a program's file is opened only if it is a regular file
//! inside the folder (never through a link, never a FIFO or a device), content is copied in
//! fixed-size pieces (so memory stays bounded whatever a file's size), and every file it
//! writes is written beside its place and renamed or linked into it, synced.

use std::ffi::OsStr;
use std::fs::{File, Metadata, OpenOptions};
use std::io::{Read as _, Seek as _, SeekFrom, Write as _};
use std::os::unix::fs::OpenOptionsExt as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use sha2::{Digest, Sha256};

/// The piece a file is copied in.
const CHUNK: usize = 64 * 1024;

static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A hidden temporary name beside `name` in `dir`, unique in this process: `.NAME.PID.N.tmp`
/// (never a program, never listed, removed at start if a crash left it).
fn temp_path(dir: &Path, name: &str) -> PathBuf {
    dir.join(format!(
        ".{name}.{}.{}.tmp",
        std::process::id(),
        TEMP_COUNTER.fetch_add(1, Ordering::Relaxed)
    ))
}

/// Creates `path` for writing, failing if anything (a link someone placed there) has the
/// name: a temporary file is never written through a link.
fn create_new(path: &Path) -> std::io::Result<File> {
    OpenOptions::new().write(true).create_new(true).open(path)
}

/// Writes `parts` to `path` atomically and durably: into a hidden temporary file beside it,
/// synced, then renamed over `path` (or, with `replace = false`, linked, which fails if the
/// name is taken), and the directory synced. Any failure (a full disk) removes the temporary
/// file and leaves whatever `path` held as it was. Blocking: call it off the runtime's
/// threads.
pub fn write_atomically(path: &Path, parts: &[&[u8]], replace: bool) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let temp = temp_path(dir, &name);
    let written = (|| {
        let mut file = create_new(&temp)?;
        for part in parts {
            file.write_all(part)?;
        }
        file.sync_all()?;
        drop(file);
        place(&temp, path, replace)?;
        File::open(dir)?.sync_all()
    })();
    if written.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    written
}

/// Moves the synced `temp` to `path`: renamed over it, or linked (failing if the name is
/// taken) and the temporary name removed.
fn place(temp: &Path, path: &Path, replace: bool) -> std::io::Result<()> {
    if replace {
        std::fs::rename(temp, path)
    } else {
        let linked = std::fs::hard_link(temp, path);
        let _ = std::fs::remove_file(temp);
        linked
    }
}

/// The SHA-256 of the file at `path`, read in pieces, in lower-case hex. Blocking.
pub fn sha256_file(path: &Path) -> std::io::Result<String> {
    let mut hasher = Sha256::new();
    std::io::copy(&mut File::open(path)?, &mut hasher)?;
    Ok(hex::encode(hasher.finalize()))
}

/// The SHA-256 of `bytes`, in lower-case hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// Why a file was not opened.
#[derive(Debug)]
pub(super) enum OpenError {
    /// It is not a regular file: what it is ("a symbolic link", "a FIFO (named pipe)"...).
    NotRegular(&'static str),
    Io(std::io::Error),
}

/// Opens `path` for reading if it is a regular file, and answers it with its metadata.
///
/// It is looked at first without following a link (so a device is never opened), then opened
/// with `O_NOFOLLOW` (a link put in its place meanwhile fails to open) and `O_NONBLOCK` (a
/// FIFO put in its place never blocks the open), and the open file's own metadata (`fstat`)
/// decides: what is read is what was checked. Blocking.
pub(super) fn open_regular(path: &Path) -> Result<(File, Metadata), OpenError> {
    let before = std::fs::symlink_metadata(path).map_err(OpenError::Io)?;
    if !before.is_file() {
        return Err(OpenError::NotRegular(crate::library::folder::file_kind(
            before.file_type(),
        )));
    }
    let file = OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_NOCTTY)
        .open(path)
        .map_err(|e| match e.raw_os_error() {
            Some(libc::ELOOP) => OpenError::NotRegular("a symbolic link"),
            _ => OpenError::Io(e),
        })?;
    let meta = file.metadata().map_err(OpenError::Io)?;
    if !meta.is_file() {
        return Err(OpenError::NotRegular(crate::library::folder::file_kind(
            meta.file_type(),
        )));
    }
    Ok((file, meta))
}

/// Whether `path` is a regular file, not following a link. Blocking (one `lstat`).
pub(super) fn is_regular(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok_and(|m| m.is_file())
}

/// Whether anything (a link, even a dangling one) has the name `path`. Blocking.
pub(super) fn is_there(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok()
}

/// Why content was not copied in.
#[derive(Debug)]
pub(super) enum CopyError {
    /// It grew past `max` bytes while it was read: the bytes read so far.
    TooLarge(u64),
    /// Reading the file.
    Read(std::io::Error),
    /// Writing the copy (`path`).
    Write(PathBuf, std::io::Error),
}

/// Content copied into the objects' directory under a hidden temporary name, hashed on the
/// way: kept under its hash by [`Incoming::keep`], removed when dropped otherwise.
#[derive(Debug)]
pub(super) struct Incoming {
    temp: PathBuf,
    pub(super) sha: String,
    pub(super) size: u64,
    kept: bool,
}

impl Incoming {
    /// Copies `from` into `objects` in fixed-size pieces, at most `max` bytes (the file may
    /// grow while it is read), hashing it. A piece of zeros is skipped rather than written,
    /// so a sparse file's copy is sparse too: it costs the disk what it holds. Synced before
    /// it is answered. Blocking.
    pub(super) fn copy(mut from: File, objects: &Path, max: u64) -> Result<Incoming, CopyError> {
        let temp = temp_path(objects, "incoming");
        let mut incoming = Incoming {
            temp,
            sha: String::new(),
            size: 0,
            kept: true,
        };
        let write = |e| CopyError::Write(objects.to_path_buf(), e);
        let mut out = create_new(&incoming.temp).map_err(write)?;
        // From here on the temporary file is ours to remove.
        incoming.kept = false;
        let mut hasher = Sha256::new();
        let mut buf = vec![0u8; CHUNK];
        loop {
            let n = match from.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(CopyError::Read(e)),
            };
            incoming.size += n as u64;
            if incoming.size > max {
                return Err(CopyError::TooLarge(incoming.size));
            }
            let piece = &buf[..n];
            hasher.update(piece);
            if piece.iter().all(|&b| b == 0) {
                out.seek(SeekFrom::Current(n as i64)).map_err(write)?;
            } else {
                out.write_all(piece).map_err(write)?;
            }
        }
        // A trailing hole has no byte written: the length says it.
        out.set_len(incoming.size).map_err(write)?;
        out.sync_all().map_err(write)?;
        incoming.sha = hex::encode(hasher.finalize());
        Ok(incoming)
    }

    /// Links the copy into place as `objects/<sha>` (content already there under its hash
    /// is the same content) and syncs the directory. Blocking.
    pub(super) fn keep(mut self, objects: &Path) -> std::io::Result<()> {
        let path = objects.join(&self.sha);
        match place(&self.temp, &path, false) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => return Err(e),
        }
        self.kept = true;
        File::open(objects)?.sync_all()
    }
}

impl Drop for Incoming {
    fn drop(&mut self) {
        if !self.kept {
            let _ = std::fs::remove_file(&self.temp);
        }
    }
}

/// A file name as a message shows it: a control or unprintable character escaped as Rust
/// escapes it (`\n`, `\u{7f}`), a backslash doubled, a byte that is not UTF-8 as `\xFF`.
pub fn escaped(file: &OsStr) -> String {
    use std::os::unix::ffi::OsStrExt as _;
    let mut out = String::new();
    for chunk in file.as_bytes().utf8_chunks() {
        for c in chunk.valid().chars() {
            if c != '\'' && c != '"' && c.escape_debug().len() > 1 {
                out.extend(c.escape_debug());
            } else {
                out.push(c);
            }
        }
        for b in chunk.invalid() {
            out.push_str(&format!("\\x{b:02X}"));
        }
    }
    out
}
