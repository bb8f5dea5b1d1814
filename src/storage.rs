//! What the gateway's embedded stores share (the job journal, the library's index, the
//! history): opening a database file without letting a damaged one panic the gateway, and
//! telling a full disk from other failures. Below the rooms that keep a store, so that none
//! of them imports another for it.

use std::path::Path;

use redb::Database;

/// Whether an I/O error says the disk or a quota is full.
pub fn is_storage_full(e: &std::io::Error) -> bool {
    e.kind() == std::io::ErrorKind::StorageFull
        || e.kind() == std::io::ErrorKind::QuotaExceeded
        || e.raw_os_error() == Some(libc::ENOSPC)
        || e.raw_os_error() == Some(libc::EDQUOT)
}

/// Whether a database that returned `e` must be closed and opened again before it takes
/// another transaction: after an I/O error (a full disk) redb refuses every later one with
/// `PreviousIo` until the handle is dropped.
pub fn needs_reopen(e: &redb::Error) -> bool {
    matches!(e, redb::Error::Io(_) | redb::Error::PreviousIo)
}

/// Opens the database file, never panicking: redb panics on some damaged files.
pub fn open_db(path: &Path) -> Result<Database, OpenError> {
    match quietly(|| Database::create(path)) {
        Ok(Ok(db)) => Ok(db),
        Ok(Err(e)) => Err(OpenError::Redb(e)),
        Err(panic) => Err(OpenError::Panicked(panic_text(&panic))),
    }
}

/// Why the database file did not open.
pub enum OpenError {
    Redb(redb::DatabaseError),
    Panicked(String),
}

thread_local! {
    /// Set while this thread runs [`quietly`]: its panics are caught and reported as errors.
    static QUIET: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f`, catching a panic of the database library as an `Err` without the panic hook
/// printing it (a damaged journal is an error the gateway reports, not a crash). Panics of
/// other threads meanwhile are printed as always.
pub fn quietly<T>(f: impl FnOnce() -> T) -> std::thread::Result<T> {
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(std::cell::Cell::get) {
                previous(info);
            }
        }));
    });
    QUIET.with(|q| q.set(true));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    QUIET.with(|q| q.set(false));
    result
}

pub fn panic_text(panic: &Box<dyn std::any::Any + Send>) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| (*s).to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "the database library panicked".to_string())
}
