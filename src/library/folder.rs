//! A watched folder: the library's (`programs.dir`) or a machine's drop folder. Lists the
//! folder, follows its change events (inotify through `notify`) or polls it, and hands on each
//! file once it is complete, and each file that went away. When a file is complete is the
//! core's rule ([`cellgate_core::program::folder`]); this is the shell that feeds it the
//! listings, the events and the clock.
//!
//! Events are a hint, never the record: every event only makes the watcher look at the file
//! again, and a full listing now and then (every `poll_ms` when polling, every 30 of them
//! otherwise) catches whatever the events missed. An event queue that overflowed, a watcher
//! that fails, or a folder that cannot be read (an unmounted share) all fall back to that
//! listing, and say so; nothing is lost, only later.
//!
//! Only regular files are complete files. Entries are looked at without following a link
//! (`lstat`), so a symbolic link is a link whatever it points at, and a FIFO or a device is
//! never opened here (a FIFO would block the watcher). Such a file, or one whose name the
//! folder refuses, is reported once while it is there ([`Seen::Refused`]); subfolders are
//! passed over.

use std::collections::{BTreeMap, BTreeSet};
use std::ffi::{OsStr, OsString};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use notify::{EventKind, RecursiveMode, Watcher as _};
use tokio::sync::{Notify, mpsc};
use tokio_util::sync::CancellationToken;

use cellgate_core::config::Watch;
use cellgate_core::pb;
use cellgate_core::program::folder::{Settle, Stat};

/// Events the watcher holds before it overflows to a rescan.
const EVENT_QUEUE: usize = 4096;
/// With change events, a full listing every this many `poll_ms`.
const RESCAN_POLLS: u32 = 30;

/// What the watcher saw.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Seen {
    /// A file is complete (still for `settle_ms`, closed by its writer).
    Complete { file: String },
    /// A file taken before is changing (rewritten in place): not complete until it is
    /// `Complete` again.
    Changing { file: String },
    /// A file went away (deleted, or renamed to a name that is not taken).
    Gone { file: String },
    /// The folder could not be read (`error`); it is tried again at every listing.
    Unreadable { error: String },
    /// It can be read again.
    Readable,
    /// A full listing was made (the first at start): what is not there is gone.
    Listed,
    /// A file that is not taken, reported once while it is there: its name is refused
    /// ([`Verdict::Refuse`]), or it is not a regular file (a symbolic link, a FIFO, a device).
    Refused { file: OsString, why: String },
}

/// What a folder makes of a file's name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    /// A file taken once it is complete (if it is a regular file).
    Take,
    /// Passed over without a word: hidden and temporary files, the gateway's own.
    Pass,
    /// Not taken, and said once: why.
    Refuse(String),
}

/// What a directory entry is, for a message: "a symbolic link", "a FIFO"...
pub fn file_kind(t: std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt as _;
    if t.is_file() {
        "a regular file"
    } else if t.is_symlink() {
        "a symbolic link"
    } else if t.is_dir() {
        "a directory"
    } else if t.is_fifo() {
        "a FIFO (named pipe)"
    } else if t.is_socket() {
        "a socket"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else {
        "not a regular file"
    }
}

/// Why an entry of kind `t` is not taken, when it is not a regular file.
pub fn not_regular(t: std::fs::FileType) -> String {
    format!(
        "it is {}: only regular files inside the folder are taken (a link is never followed)",
        file_kind(t)
    )
}

/// A folder being followed.
#[derive(Debug)]
pub struct Followed {
    /// What the watcher sees.
    pub seen: mpsc::Receiver<Seen>,
    /// A file to look at again once it is still (the other file of a conflict, once one
    /// went).
    pub retry: mpsc::UnboundedSender<String>,
    pub task: tokio::task::JoinHandle<()>,
}

/// What to watch and how.
#[derive(Clone)]
pub struct FolderWatch {
    pub dir: PathBuf,
    pub watch: Watch,
    pub settle_ms: u64,
    pub poll: Duration,
    /// What the folder makes of each file name.
    pub takes: Arc<dyn Fn(&OsStr) -> Verdict + Send + Sync>,
}

impl std::fmt::Debug for FolderWatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FolderWatch")
            .field("dir", &self.dir)
            .field("watch", &self.watch)
            .field("settle_ms", &self.settle_ms)
            .finish_non_exhaustive()
    }
}

/// One entry of a listing.
fn stat_of(meta: &std::fs::Metadata) -> Stat {
    Stat {
        size: meta.len(),
        modified_ms: meta.modified().map_or(0, cellgate_core::pb::unix_ms),
    }
}

/// What a look at one entry found.
enum Found {
    /// A regular file the folder takes, as it is now.
    File(String, Stat),
    /// An entry not taken, and why.
    Refused(String),
    /// Nothing to say: not there, passed over, a subfolder.
    Nothing,
}

/// Looks at `file` of `dir` without following a link. Blocking (one `lstat`).
fn look(dir: &Path, file: &OsStr, takes: &(dyn Fn(&OsStr) -> Verdict + Send + Sync)) -> Found {
    let verdict = takes(file);
    if verdict == Verdict::Pass {
        return Found::Nothing;
    }
    // A file removed between the listing and its stat is simply not there.
    let Ok(meta) = std::fs::symlink_metadata(dir.join(file)) else {
        return Found::Nothing;
    };
    let kind = meta.file_type();
    if kind.is_dir() {
        return Found::Nothing;
    }
    match (verdict, file.to_str()) {
        (Verdict::Refuse(why), _) => Found::Refused(why),
        (Verdict::Take, Some(name)) if kind.is_file() => {
            Found::File(name.to_string(), stat_of(&meta))
        }
        (Verdict::Take, Some(_)) => Found::Refused(not_regular(kind)),
        (Verdict::Take | Verdict::Pass, _) => Found::Nothing,
    }
}

/// A listing: the regular files that count, with what they are now, and the entries not
/// taken, with why.
#[derive(Default)]
struct Listing {
    files: BTreeMap<String, Stat>,
    refused: BTreeMap<OsString, String>,
}

/// Lists the folder. Blocking.
fn list(dir: &Path, takes: &(dyn Fn(&OsStr) -> Verdict + Send + Sync)) -> std::io::Result<Listing> {
    let mut out = Listing::default();
    for item in std::fs::read_dir(dir)? {
        let file = item?.file_name();
        match look(dir, &file, takes) {
            Found::File(name, stat) => {
                out.files.insert(name, stat);
            }
            Found::Refused(why) => {
                out.refused.insert(file, why);
            }
            Found::Nothing => {}
        }
    }
    Ok(out)
}

/// What a change event says of a file.
enum Hint {
    Look(OsString),
    Writing(String),
    Closed(String),
    /// The folder itself was removed or moved: its watch is gone with it.
    Folder,
}

impl FolderWatch {
    /// Lists the folder once and reports its complete files on the returned channel, then
    /// follows it until `stop` (with `watch = "off"`, only until the files there at start
    /// are complete).
    pub fn spawn(mut self, stop: CancellationToken) -> Followed {
        // The system's events name files by absolute path (a relative `programs.dir` is the
        // working directory's): the folder is matched as the same.
        if let Ok(dir) = std::path::absolute(&self.dir) {
            self.dir = dir;
        }
        let (tx, seen) = mpsc::channel(1024);
        let (retry, retries) = mpsc::unbounded_channel();
        let task = tokio::spawn(self.run(tx, retries, stop));
        Followed { seen, retry, task }
    }

    async fn run(
        self,
        out: mpsc::Sender<Seen>,
        mut retry: mpsc::UnboundedReceiver<String>,
        stop: CancellationToken,
    ) {
        let (hints_tx, mut hints) = mpsc::channel::<Hint>(EVENT_QUEUE);
        let overflowed = Arc::new(AtomicBool::new(false));
        let woken = Arc::new(Notify::new());
        let mut watcher = None;
        if self.watch == Watch::Auto {
            watcher = self.watcher(hints_tx, Arc::clone(&overflowed), Arc::clone(&woken));
        }
        let every = if self.watch == Watch::Poll || watcher.is_none() {
            self.poll
        } else {
            self.poll * RESCAN_POLLS
        };
        let mut settle = Settle::new(self.settle_ms);
        let mut known: BTreeSet<String> = BTreeSet::new();
        // The entries not taken that were reported, while they are there: said once each.
        let mut refused: BTreeSet<OsString> = BTreeSet::new();
        let mut readable = true;
        let mut placed = false;
        // The folder was removed or moved away: a watch on it sees nothing any more.
        let mut lost = false;
        let mut first = true;
        let mut next_scan = tokio::time::Instant::now();
        loop {
            let now_ms = pb::now_ms();
            if tokio::time::Instant::now() >= next_scan || overflowed.swap(false, Ordering::Relaxed)
            {
                let dir = self.dir.clone();
                let takes = Arc::clone(&self.takes);
                let listed = tokio::task::spawn_blocking(move || list(&dir, takes.as_ref()))
                    .await
                    .unwrap_or_else(|e| Err(std::io::Error::other(e.to_string())));
                match listed {
                    Ok(listing) => {
                        if !readable {
                            readable = true;
                            tracing::info!(dir = %self.dir.display(), "folder readable again");
                            let _ = out.send(Seen::Readable).await;
                        }
                        if lost && let Some(w) = watcher.as_mut() {
                            // The old folder's watch, if the system still has it.
                            let _ = w.unwatch(&self.dir);
                            placed = false;
                        }
                        lost = false;
                        // The watch is placed once the folder exists (it may have been missing).
                        if !placed && let Some(w) = watcher.as_mut() {
                            match w.watch(&self.dir, RecursiveMode::NonRecursive) {
                                Ok(()) => placed = true,
                                Err(e) => tracing::warn!(
                                    dir = %self.dir.display(), error = %e,
                                    "no change events for the folder yet: it is listed now and then"
                                ),
                            }
                        }
                        let files = listing.files;
                        for gone in known.iter().filter(|f| !files.contains_key(*f)) {
                            let _ = out.send(Seen::Gone { file: gone.clone() }).await;
                        }
                        known = files.keys().cloned().collect();
                        settle.retain(&known);
                        for (file, stat) in files {
                            settle.observe(&file, stat, now_ms);
                        }
                        refused.retain(|f| listing.refused.contains_key(f));
                        for (file, why) in listing.refused {
                            if refused.insert(file.clone()) {
                                let _ = out.send(Seen::Refused { file, why }).await;
                            }
                        }
                        let _ = out.send(Seen::Listed).await;
                    }
                    Err(e) => {
                        if readable || first {
                            readable = false;
                            placed = false;
                            tracing::warn!(
                                dir = %self.dir.display(), error = %e,
                                "the folder cannot be read: nothing in it is taken until it can; \
                                 the library keeps what it has"
                            );
                            let _ = out
                                .send(Seen::Unreadable {
                                    error: e.to_string(),
                                })
                                .await;
                        }
                    }
                }
                // A folder that cannot be read is tried again soon: a share coming back.
                next_scan = tokio::time::Instant::now() + if readable { every } else { self.poll };
            }
            for file in settle.rewritten() {
                if out.send(Seen::Changing { file }).await.is_err() {
                    return;
                }
            }
            for (file, _) in settle.due(pb::now_ms()) {
                if out.send(Seen::Complete { file }).await.is_err() {
                    return;
                }
            }
            first = false;
            // Off: the folder is read at start only, until what was there then is taken.
            if self.watch == Watch::Off && settle.next_deadline().is_none() {
                return;
            }
            let deadline = settle
                .next_deadline()
                .map(|at| Duration::from_millis(at.saturating_sub(pb::now_ms())))
                .map(|d| tokio::time::Instant::now() + d)
                .map_or(next_scan, |at| at.min(next_scan));
            tokio::select! {
                () = stop.cancelled() => return,
                () = tokio::time::sleep_until(deadline) => {}
                () = woken.notified() => {}
                Some(file) = retry.recv() => settle.retry(&file, pb::now_ms()),
                Some(hint) = hints.recv() => {
                    let mut batch = vec![hint];
                    while let Ok(h) = hints.try_recv() {
                        batch.push(h);
                    }
                    if batch.iter().any(|h| matches!(h, Hint::Folder)) {
                        // Listed at once: what is there now, and the watch placed again.
                        lost = true;
                        next_scan = tokio::time::Instant::now();
                    }
                    self.apply(&mut settle, &mut known, &mut refused, batch, &out).await;
                }
            }
        }
    }

    /// Looks at the files the events named.
    async fn apply(
        &self,
        settle: &mut Settle,
        known: &mut BTreeSet<String>,
        refused: &mut BTreeSet<OsString>,
        batch: Vec<Hint>,
        out: &mpsc::Sender<Seen>,
    ) {
        let mut look = BTreeSet::new();
        let now = pb::now_ms();
        for h in batch {
            match h {
                Hint::Look(f) => {
                    look.insert(f);
                }
                Hint::Writing(f) => {
                    settle.writing(&f, now);
                    look.insert(f.into());
                }
                Hint::Closed(f) => {
                    settle.closed(&f);
                    look.insert(f.into());
                }
                Hint::Folder => {}
            }
        }
        for file in look {
            match self::look(&self.dir, &file, self.takes.as_ref()) {
                Found::File(name, stat) => {
                    refused.remove(&file);
                    known.insert(name.clone());
                    settle.observe(&name, stat, now);
                }
                found => {
                    if let Some(name) = file.to_str() {
                        settle.gone(name);
                        if known.remove(name) {
                            let _ = out
                                .send(Seen::Gone {
                                    file: name.to_string(),
                                })
                                .await;
                        }
                    }
                    match found {
                        Found::Refused(why) => {
                            if refused.insert(file.clone()) {
                                let _ = out.send(Seen::Refused { file, why }).await;
                            }
                        }
                        _ => {
                            refused.remove(&file);
                        }
                    }
                }
            }
        }
    }

    /// The change-event watcher, or `None` (polling, and saying why) if the system will not
    /// give one (inotify's watch limit, a file system without events).
    fn watcher(
        &self,
        hints: mpsc::Sender<Hint>,
        overflowed: Arc<AtomicBool>,
        woken: Arc<Notify>,
    ) -> Option<notify::RecommendedWatcher> {
        let takes = Arc::clone(&self.takes);
        let dir = self.dir.clone();
        let handler = move |event: notify::Result<notify::Event>| {
            let event = match event {
                Ok(e) if !e.need_rescan() => e,
                Ok(_) | Err(_) => {
                    overflowed.store(true, Ordering::Relaxed);
                    woken.notify_one();
                    return;
                }
            };
            for path in &event.paths {
                let hint = if path == &dir {
                    if !matches!(
                        event.kind,
                        EventKind::Remove(_)
                            | EventKind::Modify(notify::event::ModifyKind::Name(_))
                    ) {
                        continue;
                    }
                    Hint::Folder
                } else if path.parent() == Some(dir.as_path()) {
                    let Some(file) = path.file_name() else {
                        continue;
                    };
                    let verdict = takes(file);
                    match (verdict, file.to_str(), &event.kind) {
                        (Verdict::Pass, _, _) => continue,
                        (Verdict::Refuse(_), _, EventKind::Access(_)) => continue,
                        (Verdict::Refuse(_), _, _) => Hint::Look(file.to_os_string()),
                        (Verdict::Take, None, _) => continue,
                        (
                            Verdict::Take,
                            Some(f),
                            EventKind::Modify(notify::event::ModifyKind::Data(_)),
                        ) => Hint::Writing(f.to_string()),
                        (
                            Verdict::Take,
                            Some(f),
                            EventKind::Access(notify::event::AccessKind::Close(
                                notify::event::AccessMode::Write,
                            )),
                        ) => Hint::Closed(f.to_string()),
                        (Verdict::Take, Some(_), EventKind::Access(_)) => continue,
                        (Verdict::Take, Some(_), _) => Hint::Look(file.to_os_string()),
                    }
                } else {
                    continue;
                };
                if hints.try_send(hint).is_err() {
                    // More than the queue holds at once: a full listing instead.
                    overflowed.store(true, Ordering::Relaxed);
                    woken.notify_one();
                }
            }
        };
        match notify::recommended_watcher(handler) {
            Ok(w) => Some(w),
            Err(e) => {
                tracing::warn!(
                    dir = %self.dir.display(), error = %e,
                    "no change events for the folder: it is listed every poll_ms instead"
                );
                None
            }
        }
    }
}

#[cfg(test)]
mod tests;
