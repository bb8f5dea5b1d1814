//! `P/C/machine/M/punch`: programs a CNC punches out (Protocol B family, §6.1.1 2), each a
//! `PunchedProgram` published reliably (QoS `Block`).
//!
//! The link hands punched bytes on as they arrive ([`LinkEvent::Punched`]); the machine's task
//! feeds them to a [`PunchDesk`], which splits them into programs at EOR and decodes ISO,
//! ASCII or EIA to text ([`jobs::punch`]). For each program the desk
//! - stores it in the program library under a new name `<machine>-<O-number>-<UTC time>`
//!   (`programs.store_punched`; never over an existing program);
//! - or, when the program is a remote request (`programs.requests`, by default a program
//!   holding only `(REQ O1234)` or `(PRG=1234)`), queues the library program it names as a
//!   job for the machine. A request is not stored: it is a message, not a program.
//!
//! It returns the `PunchedProgram` to publish on `P/C/machine/M/punch` and, when something
//! went wrong that an operator must see (a request for a program the library lacks, a
//! punched program lost), an `AlarmEvent`.
//!
//! [`LinkEvent::Punched`]: crate::link::driver::LinkEvent::Punched

use crate::jobs::source::ProgramInput;
use crate::jobs::{JobError, JobSubmission, JobsHandle};
use crate::library::{LibraryError, Store};
use cellgate_core::config::ProgramsConfig;
use cellgate_core::pb;
use cellgate_core::program::diff::{self, DiffOptions};
use cellgate_core::program::punch::{
    PunchAssembler, PunchError, PunchedText, RemoteRequest, RequestPatterns, is_punched_name,
    library_name,
};
use cellgate_core::program::tape::TapeCode;

/// What the cell file says about punched programs.
#[derive(Debug, Clone)]
pub(crate) struct PunchSettings {
    pub store: bool,
    pub requests: RequestPatterns,
    /// Largest punched program kept, bytes (`programs.max_size`, at most 64 MiB: a punched
    /// program is held whole until its EOR).
    pub max_program: usize,
    /// Punched programs older than this are removed when the next one is stored.
    pub retention: Option<std::time::Duration>,
}

/// Most bytes of one punched program held in memory.
const MAX_PUNCHED_PROGRAM: u64 = 64 * 1024 * 1024;

impl PunchSettings {
    pub(super) fn from_config(programs: &ProgramsConfig) -> Self {
        PunchSettings {
            store: programs.store_punched,
            // Checked when the cell file was read; a pattern that fails here recognises
            // nothing rather than stopping the gateway.
            requests: RequestPatterns::parse(&programs.requests).unwrap_or_else(|e| {
                tracing::error!(error = %e, "remote requests are off");
                RequestPatterns::none()
            }),
            max_program: usize::try_from(programs.max_size.min(MAX_PUNCHED_PROGRAM))
                .unwrap_or(usize::MAX),
            retention: programs
                .punched_retention_days
                .map(|d| std::time::Duration::from_secs(u64::from(d) * 86_400)),
        }
    }
}

/// What one punched program (or a punch-out gone wrong) comes to.
#[derive(Debug, Default)]
pub(crate) struct Outcome {
    pub punched: Option<pb::PunchedProgram>,
    pub alarm: Option<(String, pb::AlarmKind)>,
}

/// The punched-program side of one machine.
pub(crate) struct PunchDesk {
    machine: String,
    settings: PunchSettings,
    assembler: PunchAssembler,
    /// The machine's receive folder (`receive_dir`): each punched program also as a file.
    receive_dir: Option<std::path::PathBuf>,
}

impl PunchDesk {
    pub(super) fn new(machine: &str, settings: PunchSettings) -> Self {
        PunchDesk {
            machine: machine.to_string(),
            assembler: PunchAssembler::new(settings.max_program),
            settings,
            receive_dir: None,
        }
    }

    /// The same desk, writing each punched program into `dir` as a file too.
    pub(super) fn receiving(mut self, dir: Option<std::path::PathBuf>) -> Self {
        self.receive_dir = dir;
        self
    }

    /// Takes a piece of punched data; handles every program that ended in it.
    pub(super) async fn feed(&mut self, data: &[u8], jobs: &JobsHandle) -> Vec<Outcome> {
        let mut out = Vec::new();
        for result in self.assembler.feed(data) {
            out.push(match result {
                Ok(program) => self.program(program, jobs).await,
                Err(e) => self.error(&e),
            });
        }
        out
    }

    /// The punch-out was damaged here: the program in progress is not good.
    pub(super) fn damaged(&mut self, cause: impl std::fmt::Display) {
        tracing::warn!(machine = %self.machine, %cause, "punch-out damaged");
        self.assembler.damaged(cause);
    }

    /// The punch-out has ended (the link left the receiving state): a program without EOR
    /// is reported and dropped.
    pub(super) fn finish(&mut self) -> Option<Outcome> {
        self.assembler.finish().map(|e| self.error(&e))
    }

    /// The link's events were lost (the bus fell behind): what was pending is dropped.
    pub(super) fn lost(&mut self, missed: u64) -> Outcome {
        let pending = self.assembler.pending();
        self.assembler = PunchAssembler::new(self.settings.max_program);
        let message = format!(
            "{missed} link event(s) lost while a punch-out may have been under way; \
             {pending} punched byte(s) of an unfinished program dropped"
        );
        tracing::warn!(machine = %self.machine, %message);
        Outcome {
            punched: None,
            alarm: (pending > 0).then_some((message, pb::AlarmKind::LinkAlarm)),
        }
    }

    fn error(&self, e: &PunchError) -> Outcome {
        tracing::warn!(machine = %self.machine, error = %e, "punched data");
        // Bytes outside any program are line noise between programs; the others lose a
        // program, which the operator must hear about.
        let alarm = match e {
            PunchError::OutsideProgram { .. } => None,
            _ => Some((
                format!("punched program lost: {e}"),
                pb::AlarmKind::LinkAlarm,
            )),
        };
        Outcome {
            punched: None,
            alarm,
        }
    }

    async fn program(&self, program: PunchedText, jobs: &JobsHandle) -> Outcome {
        let unix_ms = pb::now_ms();
        let request = self.settings.requests.match_program(&program);
        tracing::info!(
            machine = %self.machine,
            o_number = ?program.o_number,
            code = %program.code,
            bytes = program.text.len(),
            request = ?request.as_ref().map(|r| &r.program),
            "program punched out"
        );
        let mut punched = pb::PunchedProgram {
            machine: self.machine.clone(),
            name: program
                .comment
                .clone()
                .or_else(|| program.o_number.clone())
                .unwrap_or_default(),
            o_number: program.o_number.clone().unwrap_or_default(),
            code_system: code_system(program.code) as i32,
            program: program.text.clone(),
            library_name: String::new(),
            unix_ms,
            request: None,
            damaged: program.damage.is_some(),
            damage: program.damage.clone().unwrap_or_default(),
            comparison: None,
        };
        let mut alarm = None;
        if let Some(damage) = &program.damage {
            // Stored, it would be taken for the program the CNC holds; as a request, it could
            // ask for the wrong program.
            alarm = Some((
                format!(
                    "punched program {} damaged ({damage}): not stored; punch it again",
                    if punched.name.is_empty() {
                        "without a name"
                    } else {
                        &punched.name
                    }
                ),
                pb::AlarmKind::LinkAlarm,
            ));
        } else if let Some(request) = request {
            let answer = self.request(&request, jobs).await;
            if !answer.error.is_empty() {
                alarm = Some((
                    format!(
                        "remote request for {} from the CNC: {}",
                        request.program, answer.error
                    ),
                    pb::AlarmKind::RemoteRequest,
                ));
            }
            punched.request = Some(answer);
        } else {
            punched.comparison = self.compare(&program, jobs).await;
        }
        if program.damage.is_none() && punched.request.is_none() && self.settings.store {
            match self.store(&program, unix_ms, jobs).await {
                Ok(name) => punched.library_name = name,
                Err(e) => {
                    tracing::warn!(machine = %self.machine, error = %e, "punched program not stored");
                    alarm = Some((
                        format!("punched program not stored in the library: {e}"),
                        pb::AlarmKind::LinkAlarm,
                    ));
                }
            }
        }
        if program.damage.is_none()
            && punched.request.is_none()
            && let Some(dir) = &self.receive_dir
        {
            match self
                .receive(dir, &program, &punched.library_name, unix_ms)
                .await
            {
                Ok(file) => {
                    tracing::info!(machine = %self.machine, file = %file.display(), "punched program written to the receive folder");
                }
                Err(e) => {
                    tracing::warn!(machine = %self.machine, dir = %dir.display(), error = %e, "punched program not written to the receive folder");
                    alarm.get_or_insert((
                        format!(
                            "punched program not written to the receive folder {}: {e}",
                            dir.display()
                        ),
                        pb::AlarmKind::LinkAlarm,
                    ));
                }
            }
        }
        Outcome {
            punched: Some(punched),
            alarm,
        }
    }

    /// Writes the punched program into the receive folder under its library name (or the
    /// name it would have had), never over a file already there.
    async fn receive(
        &self,
        dir: &std::path::Path,
        program: &PunchedText,
        stored_as: &str,
        unix_ms: u64,
    ) -> std::io::Result<std::path::PathBuf> {
        let dir = dir.to_path_buf();
        let machine = self.machine.clone();
        let o_number = program.o_number.clone();
        let text = program.text.clone();
        let stored_as = stored_as.to_string();
        tokio::task::spawn_blocking(move || {
            std::fs::create_dir_all(&dir)?;
            let first =
                (!stored_as.is_empty() && !dir.join(&stored_as).exists()).then_some(stored_as);
            let name = first
                .or_else(|| {
                    library_name(&machine, o_number.as_deref(), unix_ms, |n| {
                        dir.join(n).exists()
                    })
                })
                .ok_or_else(|| std::io::Error::other("every name for it is taken"))?;
            let path = dir.join(name);
            crate::library::write_atomically(&path, &[&text], false)?;
            Ok(path)
        })
        .await
        .unwrap_or_else(|e| Err(std::io::Error::other(e.to_string())))
    }

    /// The punched program against the library's program of its O-number (FANUC counts
    /// `O12` and `O0012` as one program: each spelling is tried), blanks and EOBs aside.
    async fn compare(
        &self,
        program: &PunchedText,
        jobs: &JobsHandle,
    ) -> Option<pb::PunchComparison> {
        let written = program.o_number.clone()?;
        let digits = written.get(1..)?.trim_start_matches('0');
        let lookup = RemoteRequest {
            program: format!("O{}", if digits.is_empty() { "0" } else { digits }),
            written,
        };
        for name in lookup.candidates() {
            let Ok((revision, bytes)) = jobs.library().read_revision(&name, "").await else {
                continue;
            };
            let options = DiffOptions {
                blanks: true,
                ..DiffOptions::default()
            };
            let counts = match diff::counts(&bytes, &program.text, options) {
                Ok(c) => c,
                Err(e) => {
                    tracing::info!(machine = %self.machine, program = %name, error = %e, "punched program not compared");
                    return None;
                }
            };
            return Some(pb::PunchComparison {
                library_name: name,
                revision: revision.number,
                same: counts.same(),
                blocks_added: counts.added,
                blocks_removed: counts.removed,
                blocks_changed: counts.changed,
            });
        }
        None
    }

    /// Stores the program under the first free name.
    async fn store(
        &self,
        program: &PunchedText,
        unix_ms: u64,
        jobs: &JobsHandle,
    ) -> Result<String, LibraryError> {
        let mut taken: Vec<String> = Vec::new();
        loop {
            let Some(name) =
                library_name(&self.machine, program.o_number.as_deref(), unix_ms, |n| {
                    taken.iter().any(|t| t == n)
                })
            else {
                // Every suffix up to NAME_SUFFIX_MAX is taken within one second.
                return Err(LibraryError::Exists {
                    name: taken.pop().unwrap_or_default(),
                });
            };
            let store = Store {
                bytes: program.text.as_slice().into(),
                by: pb::RequestOrigin {
                    user: "(punch)".to_string(),
                    via: self.machine.clone(),
                },
                comment: format!("punched out by {}", self.machine),
                adopted: None,
            };
            match jobs.library().store_new_as(&name, store).await {
                Ok(entry) => {
                    self.expire(unix_ms, jobs).await;
                    return Ok(entry.name);
                }
                Err(LibraryError::Exists { .. }) => taken.push(name),
                Err(e) => return Err(e),
            }
        }
    }

    /// Removes this machine's punched programs stored longer ago than the retention.
    async fn expire(&self, now_ms: u64, jobs: &JobsHandle) {
        let Some(retention) = self.settings.retention else {
            return;
        };
        let cutoff =
            now_ms.saturating_sub(u64::try_from(retention.as_millis()).unwrap_or(u64::MAX));
        let Ok(entries) = jobs.library().list().await else {
            return;
        };
        for e in entries {
            if e.modified_unix_ms < cutoff && is_punched_name(&self.machine, &e.name) {
                match jobs.library().remove(&e.name).await {
                    Ok(_) => {
                        tracing::info!(machine = %self.machine, program = %e.name, "punched program past its retention removed")
                    }
                    Err(err) => {
                        tracing::warn!(machine = %self.machine, program = %e.name, error = %err, "punched program past its retention not removed")
                    }
                }
            }
        }
    }

    /// Queues the requested library program; the answer says what became of it.
    async fn request(&self, request: &RemoteRequest, jobs: &JobsHandle) -> pb::RemoteRequest {
        let mut answer = pb::RemoteRequest {
            program: request.program.clone(),
            ..pb::RemoteRequest::default()
        };
        let candidates = request.candidates();
        for name in &candidates {
            // A machine that takes only released revisions gets the latest released one.
            let revision = if jobs.accept() == cellgate_core::config::Accept::Released {
                jobs.library()
                    .latest_released(name)
                    .await
                    .map(|n| n.to_string())
                    .unwrap_or_default()
            } else {
                String::new()
            };
            let submission = JobSubmission {
                input: ProgramInput::Library(name.clone()),
                revision,
                submitted_by: pb::RequestOrigin {
                    user: "(remote request)".to_string(),
                    via: self.machine.clone(),
                },
                ..JobSubmission::default()
            };
            match jobs.submit(submission).await {
                Ok(accepted) => {
                    tracing::info!(machine = %self.machine, program = %name, job = %accepted.job_id, "remote request queued");
                    answer.library_name = name.clone();
                    answer.job_id = accepted.job_id;
                    return answer;
                }
                Err(JobError::Library {
                    error: LibraryError::NotFound { .. } | LibraryError::Removed { .. },
                    ..
                }) => {}
                Err(e) => {
                    answer.library_name = name.clone();
                    answer.error = e.to_string();
                    return answer;
                }
            }
        }
        answer.error = format!(
            "the program library has no program {} (looked for {})",
            request.program,
            candidates.join(", ")
        );
        tracing::warn!(machine = %self.machine, error = %answer.error, "remote request refused");
        answer
    }
}

fn code_system(code: TapeCode) -> pb::CodeSystem {
    match code {
        TapeCode::Iso => pb::CodeSystem::Iso,
        TapeCode::Ascii => pb::CodeSystem::Ascii,
        TapeCode::Eia => pb::CodeSystem::Eia,
    }
}
