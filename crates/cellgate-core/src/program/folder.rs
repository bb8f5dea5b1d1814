//! The DNC folder, sans-IO: which files of a watched folder are programs, under which name,
//! and when a file is complete enough to take.
//!
//! A CAM system posts programs into the library's folder (`programs.dir`), or into a
//! machine's drop folder, in any of three ways: it writes the file in place over seconds, it
//! writes a temporary name and renames it into place, or a copy arrives over a network share.
//! A file must never be taken half written, and nothing here can see another process's open
//! files on a share. So a file is taken when it has been **still**: its size and modification
//! time the same at two looks at least `settle` apart, its modification time at least
//! `settle` old, not empty, and (where the watcher reports them, inotify) no write seen since
//! the writer last closed it. A file first seen already `settle` old (at start, or renamed into
//! place keeping its time) is taken at once.
//!
//! The shell lists and stats the folder and feeds what it sees to [`Settle`] with the time;
//! [`Settle::due`] answers the files now complete and [`Settle::next_deadline`] when to look
//! again.

use std::collections::BTreeMap;

use super::name::check_name;

/// What a folder takes: the extensions stripped from a file's name, how long a file must be
/// still.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FolderRules {
    /// Extensions (without the dot, compared without regard to case) that are not part of
    /// the program's name: `O5555.nc` is program `O5555`.
    pub extensions: Vec<String>,
    /// How long, in ms, a file's size and modification time must stay the same.
    pub settle_ms: u64,
}

/// Why a file of the folder is not a program.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Skip {
    /// Hidden (`.name`), an editor's or a copy's temporary file (`*.tmp`, `~*`, `*~`,
    /// `*.part`, `*.swp`): silently passed over.
    Temporary,
    /// What is left once the extension is stripped is not a program name.
    BadName(&'static str),
}

impl FolderRules {
    /// The program a file of the folder holds: its name with a listed extension stripped.
    pub fn program_name<'f>(&self, file: &'f str) -> Result<&'f str, Skip> {
        if is_temporary(file) {
            return Err(Skip::Temporary);
        }
        let name = self.strip(file);
        check_name(name).map_err(|e| Skip::BadName(e.reason))?;
        Ok(name)
    }

    /// `file` without a listed extension.
    pub fn strip<'f>(&self, file: &'f str) -> &'f str {
        match file.rsplit_once('.') {
            Some((stem, ext))
                if !stem.is_empty()
                    && self.extensions.iter().any(|e| e.eq_ignore_ascii_case(ext)) =>
            {
                stem
            }
            _ => file,
        }
    }

    /// Whether `name` ends in a listed extension, so that no file can give it: `O5555.nc`
    /// is a file of program `O5555`, never a program of its own.
    pub fn ends_in_extension(&self, name: &str) -> bool {
        self.strip(name) != name
    }
}

/// Hidden files and the temporary names editors, copies and CAM posts write before renaming.
pub fn is_temporary(file: &str) -> bool {
    let lower = file.to_ascii_lowercase();
    file.starts_with('.')
        || file.starts_with('~')
        || file.ends_with('~')
        || [
            ".tmp",
            ".part",
            ".partial",
            ".swp",
            ".crdownload",
            ".filepart",
        ]
        .iter()
        .any(|s| lower.ends_with(s))
}

/// What the shell saw of a file: its size and modification time (ms since the epoch).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stat {
    /// Bytes.
    pub size: u64,
    /// Last modified, ms since the Unix epoch.
    pub modified_ms: u64,
}

#[derive(Debug, Clone, Copy)]
struct Look {
    stat: Stat,
    /// When the file was first seen as `stat`.
    since_ms: u64,
    /// A write was reported and no close since.
    writing: bool,
    /// Taken as `stat` already: not due again until it changes.
    taken: bool,
}

/// Files of a folder on their way to being complete. Times are the shell's clock in ms (the
/// wall clock, since modification times are).
#[derive(Debug, Clone, Default)]
pub struct Settle {
    settle_ms: u64,
    files: BTreeMap<String, Look>,
    /// Files taken before that changed since: rewritten in place, not yet complete again.
    rewritten: std::collections::BTreeSet<String>,
}

impl Settle {
    /// Files must stay the same `settle_ms` to be due.
    pub fn new(settle_ms: u64) -> Self {
        Settle {
            settle_ms,
            files: BTreeMap::new(),
            rewritten: std::collections::BTreeSet::new(),
        }
    }

    /// The shell saw `file` as `stat` at `now`.
    pub fn observe(&mut self, file: &str, stat: Stat, now: u64) {
        match self.files.get_mut(file) {
            Some(look) if look.stat == stat => {}
            Some(look) => {
                if look.taken {
                    self.rewritten.insert(file.to_string());
                }
                *look = Look {
                    stat,
                    since_ms: now,
                    writing: look.writing,
                    taken: false,
                }
            }
            None => {
                // First seen: still since its modification time, as far as anyone can tell.
                let since_ms = if stat.modified_ms <= now {
                    stat.modified_ms
                } else {
                    now
                };
                self.files.insert(
                    file.to_string(),
                    Look {
                        stat,
                        since_ms,
                        writing: false,
                        taken: false,
                    },
                );
            }
        }
    }

    /// A writer wrote to `file` (inotify's modify): not complete until it closes it.
    pub fn writing(&mut self, file: &str, now: u64) {
        if let Some(look) = self.files.get_mut(file) {
            if look.taken {
                self.rewritten.insert(file.to_string());
            }
            look.writing = true;
            look.since_ms = now;
            look.taken = false;
        } else {
            self.files.insert(
                file.to_string(),
                Look {
                    stat: Stat {
                        size: 0,
                        modified_ms: now,
                    },
                    since_ms: now,
                    writing: true,
                    taken: false,
                },
            );
        }
    }

    /// The writer closed `file` (inotify's close-write).
    pub fn closed(&mut self, file: &str) {
        if let Some(look) = self.files.get_mut(file) {
            look.writing = false;
        }
    }

    /// `file` is gone from the folder.
    pub fn gone(&mut self, file: &str) {
        self.files.remove(file);
        self.rewritten.remove(file);
    }

    /// The files taken before that changed since the last call: each is being rewritten in
    /// place and is not complete until it is due again.
    pub fn rewritten(&mut self) -> Vec<String> {
        std::mem::take(&mut self.rewritten).into_iter().collect()
    }

    /// Forgets every file not in `present` (after a full listing).
    pub fn retain(&mut self, present: &std::collections::BTreeSet<String>) {
        self.files.retain(|f, _| present.contains(f));
        self.rewritten.retain(|f| present.contains(f));
    }

    /// Whether `file` is being written, as far as the watcher said.
    pub fn is_writing(&self, file: &str) -> bool {
        self.files.get(file).is_some_and(|l| l.writing)
    }

    fn is_due(&self, look: &Look, now: u64) -> bool {
        !look.taken
            && !look.writing
            && look.stat.size > 0
            && now.saturating_sub(look.since_ms) >= self.settle_ms
            // A modification time ahead of this clock (a share's clock ahead) says nothing.
            && (look.stat.modified_ms > now
                || now - look.stat.modified_ms >= self.settle_ms)
    }

    /// The files complete at `now`, each once per content seen: marked taken.
    pub fn due(&mut self, now: u64) -> Vec<(String, Stat)> {
        let due: Vec<(String, Stat)> = self
            .files
            .iter()
            .filter(|(_, l)| self.is_due(l, now))
            .map(|(f, l)| (f.clone(), l.stat))
            .collect();
        for (f, _) in &due {
            if let Some(l) = self.files.get_mut(f) {
                l.taken = true;
            }
        }
        due
    }

    /// Takes `file` again at its next due time (a take that failed for a reason that may
    /// pass: a full disk, a busy index).
    pub fn retry(&mut self, file: &str, now: u64) {
        if let Some(l) = self.files.get_mut(file) {
            l.taken = false;
            l.since_ms = now;
        }
    }

    /// When the next file may be due: `None` while none waits (a file being written waits
    /// for its close, an empty one for content).
    pub fn next_deadline(&self) -> Option<u64> {
        self.files
            .values()
            .filter(|l| !l.taken && !l.writing && l.stat.size > 0)
            .map(|l| {
                let still = l.since_ms + self.settle_ms;
                if l.stat.modified_ms > l.since_ms + self.settle_ms {
                    still
                } else {
                    still.max(l.stat.modified_ms + self.settle_ms)
                }
            })
            .min()
    }

    /// Files waiting: seen, not yet complete.
    pub fn waiting(&self) -> usize {
        self.files.values().filter(|l| !l.taken).count()
    }
}

#[cfg(test)]
mod tests;
