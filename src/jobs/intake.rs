//! The job intake: a submission checked, its program read and staged in the journal's store,
//! then handed to the manager, which queues it. What a client waits for between `submit` and
//! `JobAccepted`, and why a submission is refused.

use std::path::Path;

use prost::Message as _;
use tokio::sync::oneshot;

use super::journal::{JobOriginRecord, JobRecord, JobState, StartPoint};
use super::source::{self, ProgramError, ProgramInput};
use super::{JobError, JobSubmission, JobsHandle, REQUEST_ID_MAX, Request};
use crate::library::{self, LibraryError};
use cellgate_core::config::Accept;
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;
use cellgate_core::program::blocks::{Block, BlockError, StartAt};

/// A program staged in the journal's store: the name it suggests for the job, the length of
/// its stored file, and the EOR appended when it is sent (empty when stored with it).
struct Staged {
    name: Option<String>,
    file_len: u64,
    suffix: Vec<u8>,
}

impl JobsHandle {
    /// Checks the program, writes it and the job to the journal, and queues the job. On
    /// success the job's `queued` event is out and the job is journalled before this
    /// returns. The check reads a library program once through; it runs in the caller's task.
    pub async fn submit(&self, submission: JobSubmission) -> Result<pb::JobAccepted, JobError> {
        if submission.request_id.len() > REQUEST_ID_MAX {
            return Err(JobError::RequestId {
                machine: self.machine.to_string(),
                len: submission.request_id.len(),
            });
        }
        let seq = self.journal.next_seq().map_err(|e| self.journal_error(e))?;
        let file = seq.to_string();
        let record = match self.stage(seq, &file, submission).await {
            Ok(record) => record,
            Err(e) => {
                let _ = std::fs::remove_file(self.journal.file_path(&file));
                return Err(e);
            }
        };
        let (reply, answer) = oneshot::channel();
        self.requests
            .send(Request::Submit {
                record: Box::new(record),
                reply,
            })
            .await
            .map_err(|_| self.stopped())?;
        let accepted = answer.await.map_err(|_| self.stopped())?;
        if accepted.is_err() {
            let _ = std::fs::remove_file(self.journal.file_path(&file));
        }
        accepted
    }

    /// The program in the journal's store, checked, and the job's record.
    async fn stage(&self, seq: u64, file: &str, s: JobSubmission) -> Result<JobRecord, JobError> {
        self.admits(&s)?;
        let mut origin = JobOriginRecord {
            user: s.submitted_by.user.clone(),
            via: s.submitted_by.via.clone(),
            ..JobOriginRecord::default()
        };
        let mut start = s.start_at;
        let eor = s.append_eor;
        let staged = match s.input {
            ProgramInput::Inline(bytes) => self.stage_bytes(file, &bytes, eor, &mut origin)?,
            ProgramInput::Fetched { key, bytes } => Staged {
                name: Some(key),
                ..self.stage_bytes(file, &bytes, eor, &mut origin)?
            },
            ProgramInput::Library(name) => {
                self.stage_library(file, name, &s.revision, eor, &mut origin)
                    .await?
            }
            ProgramInput::File(path) => self.stage_file(file, &path, eor, &mut origin).await?,
            ProgramInput::Resume(job) => {
                let (staged, next) = self.stage_resume(file, &job, &mut origin).await?;
                start.get_or_insert((StartAt::Line(next), 0));
                staged
            }
        };
        let size = staged.file_len + staged.suffix.len() as u64;
        if size > self.rules.max_size {
            return Err(self.program_error(ProgramError::TooLarge {
                size,
                max: self.rules.max_size,
            }));
        }
        let start = match start {
            None => None,
            Some((at, header_lines)) => Some(
                self.start_point(file, &staged.suffix, at, header_lines)
                    .await?,
            ),
        };
        let name = if s.name.is_empty() {
            staged.name.unwrap_or_else(|| "program".to_string())
        } else {
            s.name
        };
        Ok(JobRecord {
            seq,
            id: String::new(),
            machine: self.machine.to_string(),
            request_id: s.request_id,
            name,
            priority: s.priority,
            accepted_unix_ms: pb::now_ms(),
            file: file.to_string(),
            file_len: staged.file_len,
            suffix: staged.suffix,
            start,
            resume_after_restart: s.resume_after_restart,
            deadline_s: s.deadline_s,
            state: JobState::Waiting,
            acked: 0,
            last_event: Vec::new(),
            origin,
        })
    }

    /// Whether this machine takes a submission of this kind at all.
    fn admits(&self, s: &JobSubmission) -> Result<(), JobError> {
        if !s.revision.is_empty() && !matches!(s.input, ProgramInput::Library(_)) {
            return Err(JobError::RevisionWithoutLibrary {
                machine: self.machine.to_string(),
            });
        }
        if self.accept == Accept::Released {
            let what = match &s.input {
                ProgramInput::Inline(_) => Some("an inline program"),
                ProgramInput::Fetched { .. } => Some("a program fetched from a key"),
                ProgramInput::File(_) => Some("a file of its drop folder"),
                ProgramInput::Library(_) | ProgramInput::Resume(_) => None,
            };
            if let Some(what) = what {
                return Err(JobError::OnlyReleased {
                    machine: self.machine.to_string(),
                    what,
                });
            }
        }
        Ok(())
    }

    /// A program sent with the request (inline, or fetched from a key), checked and stored
    /// with its EOR; named by its O number, if it has one.
    fn stage_bytes(
        &self,
        file: &str,
        bytes: &[u8],
        append_eor: bool,
        origin: &mut JobOriginRecord,
    ) -> Result<Staged, JobError> {
        origin.sha256 = library::sha256_hex(bytes);
        let report = source::scan(self.rules, bytes);
        let suffix = self.checked_suffix(&report, append_eor)?;
        let file_len = self
            .journal
            .store_bytes(file, &[bytes, suffix])
            .map_err(|e| self.journal_error(e))?;
        Ok(Staged {
            name: report.ok().and_then(|r| r.o_number),
            file_len,
            suffix: Vec::new(),
        })
    }

    /// A revision of a library program, copied, then checked (on a machine that takes only
    /// released programs, a released or locked one).
    async fn stage_library(
        &self,
        file: &str,
        name: String,
        revision: &str,
        append_eor: bool,
        origin: &mut JobOriginRecord,
    ) -> Result<Staged, JobError> {
        let library_error = |error| JobError::Library {
            machine: self.machine.to_string(),
            error,
        };
        // The revision's content never changes: the version checked is the version sent,
        // even if the library stores a new one meanwhile.
        let (revision, path) = self
            .library
            .revision(&name, revision)
            .await
            .map_err(library_error)?;
        if self.accept == Accept::Released
            && !matches!(
                revision.state(),
                pb::RevisionState::Released | pb::RevisionState::Locked
            )
        {
            let latest_released = self.library.latest_released(&name).await;
            return Err(library_error(LibraryError::NotReleased {
                machine: self.machine.to_string(),
                name,
                number: revision.number,
                latest_released,
            }));
        }
        origin.library = name.clone();
        origin.revision = revision.number;
        origin.sha256 = revision.sha256.clone();
        let (file_len, report) = self
            .store_and_scan(file, &path, |error| JobError::Library {
                machine: self.machine.to_string(),
                error: self.library.io_error(&name, "read", error),
            })
            .await?;
        let suffix = self.checked_suffix(&Ok(report), append_eor)?;
        Ok(Staged {
            name: Some(name),
            file_len,
            suffix: suffix.to_vec(),
        })
    }

    /// A file of the machine's drop folder, copied, then checked: the file may change after
    /// it was copied.
    async fn stage_file(
        &self,
        file: &str,
        path: &Path,
        append_eor: bool,
        origin: &mut JobOriginRecord,
    ) -> Result<Staged, JobError> {
        let read_error = |error: std::io::Error| JobError::Start {
            machine: self.machine.to_string(),
            error: BlockError::Read(format!("{}: {error}", path.display())),
        };
        let (file_len, report) = self.store_and_scan(file, path, read_error).await?;
        origin.sha256 = library::sha256_file(&self.journal.file_path(file)).map_err(read_error)?;
        let suffix = self.checked_suffix(&Ok(report.clone()), append_eor)?;
        let stem = path.file_stem().map(|n| n.to_string_lossy().into_owned());
        Ok(Staged {
            name: report.o_number.or(stem),
            file_len,
            suffix: suffix.to_vec(),
        })
    }

    /// `path` copied into the journal's store as `file` (refused unread if it is too large)
    /// and the copy scanned: the copy's length and what the scan found. `read_error` names a
    /// failure to read either.
    async fn store_and_scan(
        &self,
        file: &str,
        path: &Path,
        read_error: impl Fn(std::io::Error) -> JobError,
    ) -> Result<(u64, source::ScanReport), JobError> {
        // Looked at without following a link: what is linked in a file's place is not read.
        let meta = std::fs::symlink_metadata(path).map_err(&read_error)?;
        if !meta.is_file() {
            return Err(read_error(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "not a regular file (a link or a special file is never read)",
            )));
        }
        let size = meta.len();
        if size > self.rules.max_size {
            return Err(self.program_error(ProgramError::TooLarge {
                size,
                max: self.rules.max_size,
            }));
        }
        let len = self
            .journal
            .store_file(file, path)
            .map_err(|e| self.journal_error(e))?;
        let report = source::scan_file(self.rules, &self.journal.file_path(file))
            .await
            .map_err(|e| match e {
                source::ScanFileError::Program(e) => self.program_error(e),
                source::ScanFileError::Io(error) => read_error(error),
            })?;
        Ok((len, report))
    }

    /// An ended job's program again, from its next block: what it sent, where it stopped.
    async fn stage_resume(
        &self,
        file: &str,
        job: &str,
        origin: &mut JobOriginRecord,
    ) -> Result<(Staged, u64), JobError> {
        let (earlier, next) = self.resumable(job).await?;
        // A job that sent no library revision cannot go to such a machine again.
        if self.accept == Accept::Released && earlier.origin.revision == 0 {
            return Err(JobError::OnlyReleased {
                machine: self.machine.to_string(),
                what: "a job that did not send a library revision",
            });
        }
        origin.library = earlier.origin.library.clone();
        origin.revision = earlier.origin.revision;
        origin.sha256 = earlier.origin.sha256.clone();
        let file_len = self
            .journal
            .store_file(file, &self.journal.file_path(&earlier.file))
            .map_err(|e| self.journal_error(e))?;
        Ok((
            Staged {
                name: Some(earlier.name),
                file_len,
                suffix: earlier.suffix,
            },
            next.line,
        ))
    }

    /// Where the job starts in its stored program: after the header, at the block `at`.
    async fn start_point(
        &self,
        file: &str,
        suffix: &[u8],
        at: StartAt,
        header_lines: u32,
    ) -> Result<StartPoint, JobError> {
        let start_error = |error| JobError::Start {
            machine: self.machine.to_string(),
            error,
        };
        let program = source::open_program(&self.journal.file_path(file), suffix)
            .await
            .map_err(|e| start_error(BlockError::Read(e.to_string())))?;
        let (header_end, block) = source::find_start(program, at, header_lines)
            .await
            .map_err(start_error)?;
        Ok(StartPoint {
            header_end,
            body_start: block.offset,
        })
    }

    /// The EOR to append, or why the program is refused.
    fn checked_suffix(
        &self,
        report: &Result<source::ScanReport, ProgramError>,
        append_eor: bool,
    ) -> Result<&'static [u8], JobError> {
        let report = report.clone().map_err(|e| self.program_error(e))?;
        let suffix = source::eor_suffix(&report);
        if !suffix.is_empty() && !append_eor {
            return Err(self.program_error(ProgramError::MissingEor));
        }
        Ok(suffix)
    }

    /// An earlier job that a resume can start from, and its next block.
    async fn resumable(&self, job: &str) -> Result<(JobRecord, Block), JobError> {
        let not = |why: &str| JobError::NotResumable {
            machine: self.machine.to_string(),
            job: job.to_string(),
            why: why.to_string(),
        };
        let (reply, answer) = oneshot::channel();
        self.requests
            .send(Request::Find {
                id: job.to_string(),
                reply,
            })
            .await
            .map_err(|_| self.stopped())?;
        let record =
            answer
                .await
                .map_err(|_| self.stopped())?
                .ok_or_else(|| JobError::UnknownJob {
                    machine: self.machine.to_string(),
                    job: job.to_string(),
                })?;
        if record.state != JobState::Ended {
            return Err(not("it has not ended"));
        }
        let event = pb::JobEvent::decode(record.last_event.as_slice())
            .map_err(|_| not("its last event is unreadable"))?;
        let (next, on_line, acked, ended) = match event.kind {
            Some(Kind::Failed(f)) => (f.next_block, f.bytes_on_line, f.byte_offset, "failed"),
            Some(Kind::Cancelled(c)) => (
                c.next_block,
                c.bytes_on_line,
                c.byte_offset,
                "was cancelled",
            ),
            Some(Kind::Completed(_)) => return Err(not("it completed")),
            _ => (None, 0, 0, "ended"),
        };
        // Whether there is a block to resume from depends on whether the CNC had asked for
        // data when the job ended: say which it was, in bytes, since a client cannot see it.
        let next = next.ok_or_else(|| {
            if on_line == 0 {
                not(&format!(
                    "it {ended} before any of it went to the board (0 B on the line: the CNC \
                     had not asked for data yet), so the CNC holds nothing of it and there is \
                     nothing to resume: submit its program again"
                ))
            } else {
                not(&format!(
                    "it {ended} with {on_line} B on the line, {acked} B of them acknowledged \
                     by the board, but the block where that is could not be found in its \
                     program: submit it again from a block (start_at, --from-block)"
                ))
            }
        })?;
        if !self.journal.file_path(&record.file).exists() {
            return Err(not(
                "its program is no longer kept: only the latest 8 ended jobs of a machine keep \
                 theirs; submit the program again, starting at the block (start_at)",
            ));
        }
        let block = Block {
            line: next.line,
            sequence: (!next.sequence_number.is_empty()).then_some(next.sequence_number),
            offset: next.byte_offset,
        };
        Ok((record, block))
    }
}
