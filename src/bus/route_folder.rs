//! The cell's folders on the bus: the library's folder (`programs.dir`), whose complete files
//! become revisions and whose deleted files mark their programs removed; each machine's drop
//! folder (`drop_dir`), whose complete files are queued to it as jobs. What the folder takes is
//! a change like any other (`P/C/program/NAME/changed`); what it cannot take, and a folder that
//! cannot be read, are published on `P/C/program/@events`.
//!
//! What comes from a folder is written by whoever may write the folder, not by a bus client:
//! it goes through the same checks as a bus store or submit, and the audit records it with
//! the folder as its origin and the file's owner as its user, where the system says (the
//! owner of the entry itself: a link's, never its target's).
//!
//! A file the library's folder does not take (a name that gives no program name, a link, a
//! FIFO, a device) is logged, audited and published once while it is there; a drop folder's
//! link or special file is moved to `refused/` as a refused file is.

use std::ffi::{OsStr, OsString};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;

use super::audit::Audit;
use super::context::RouteContext;
use crate::jobs::JobSubmission;
use crate::jobs::source::ProgramInput;
use crate::library::folder::{FolderWatch, Followed, Seen, Verdict};
use crate::library::{FolderFile, LibraryError, Taken, escaped};
use cellgate_core::codes::BusCode;
use cellgate_core::config::{CellConfig, Permission};
use cellgate_core::pb;
use cellgate_core::program::folder::is_temporary;

/// Where a drop folder puts a file once its job is queued, and once it is refused.
pub(crate) const SENT: &str = "sent";
pub(crate) const REFUSED: &str = "refused";

/// Publishes `event` on `P/C/program/@events`. Blocking congestion control: such an event is
/// rare and a client that follows the folder must not miss one.
pub(crate) async fn publish_library_event(ctx: &RouteContext, mut event: pb::LibraryEvent) {
    if event.unix_ms == 0 {
        event.unix_ms = pb::now_ms();
    }
    super::context::publish_event(
        ctx,
        super::published::Published::LibraryEvent,
        &ctx.keys.program_events(),
        &event,
        None,
    )
    .await;
}

/// Who made a file: its owner's user name where the system says, else no user (the origin
/// is then the folder alone). The entry's own owner: a link is not followed (its target's
/// owner made nothing).
fn owner_of(path: &Path, via: &str) -> pb::RequestOrigin {
    use std::os::unix::fs::MetadataExt as _;
    let user = std::fs::symlink_metadata(path)
        .ok()
        .and_then(|m| user_name(m.uid()))
        .unwrap_or_default();
    pb::RequestOrigin {
        user,
        via: via.chars().take(128).collect(),
    }
}

/// The user name of `uid`, from the system's user database.
fn user_name(uid: u32) -> Option<String> {
    let user = nix::unistd::User::from_uid(nix::unistd::Uid::from_raw(uid)).ok()??;
    Some(user.name.chars().take(128).collect())
}

/// Follows the library's folder and every machine's drop folder until `stop`.
pub(crate) fn spawn(
    ctx: &RouteContext,
    config: &CellConfig,
    stop: &CancellationToken,
) -> JoinSet<()> {
    let mut tasks = JoinSet::new();
    let programs = &config.programs;
    let poll = Duration::from_millis(u64::from(programs.poll_ms));
    let settle_ms = u64::from(programs.settle_ms);
    let library = ctx.library.clone();
    let watch = FolderWatch {
        dir: library.dir().to_path_buf(),
        watch: programs.watch,
        settle_ms,
        poll,
        takes: Arc::new(move |f: &OsStr| library.verdict(f)),
    };
    let followed = watch.spawn(stop.clone());
    tasks.spawn(follow_library(ctx.clone(), followed));
    // The machines at start; a drop folder of a machine a reload adds is followed from the
    // next start (docs/library.md).
    for m in ctx.machines.now().values() {
        let Some(dir) = m.config.drop_dir.clone() else {
            continue;
        };
        if let Err(e) = std::fs::create_dir_all(&dir) {
            tracing::warn!(machine = %m.name(), dir = %dir.display(), error = %e, "drop folder not created; it is followed once it is there");
        }
        let watch = FolderWatch {
            dir: dir.clone(),
            watch: programs.watch,
            settle_ms,
            poll,
            takes: Arc::new(|f: &OsStr| match f.to_str() {
                Some(f) if !is_temporary(f) => Verdict::Take,
                _ => Verdict::Pass,
            }),
        };
        tracing::info!(machine = %m.name(), dir = %dir.display(), "drop folder followed: its files are queued to the machine");
        let followed = watch.spawn(stop.clone());
        tasks.spawn(follow_drop(
            ctx.clone(),
            m.name().to_string(),
            dir,
            followed,
        ));
    }
    tasks
}

fn audit_library(
    ctx: &RouteContext,
    action: &str,
    path: &Path,
    name: &str,
    detail: String,
    by: pb::RequestOrigin,
    outcome: Result<(), &LibraryError>,
) {
    ctx.audit(
        Audit {
            action,
            permission: Permission::ProgramWrite,
            key: &format!("folder:{}", path.display()),
            machine: "",
            target: name.to_string(),
            detail,
            origin: Some(by),
        },
        outcome,
    );
}

fn refused(name: &str, file: &str, e: &LibraryError, by: pb::RequestOrigin) -> pb::LibraryEvent {
    pb::LibraryEvent {
        kind: pb::LibraryEventKind::Refused as i32,
        name: name.to_string(),
        file: file.to_string(),
        error: e.to_string(),
        code: e.code() as i32,
        by: Some(by),
        ..Default::default()
    }
}

async fn follow_library(ctx: RouteContext, mut followed: Followed) {
    let library = ctx.library.clone();
    let dir = library.dir().to_path_buf();
    let mut listed = false;
    while let Some(seen) = followed.seen.recv().await {
        match seen {
            Seen::Changing { file } => {
                if let Ok(name) = library.program_of(&file) {
                    library.set_note(
                        &name,
                        Some(format!(
                            "not yet complete: {file} is being rewritten; it becomes the next \
                             revision once it has been still for programs.settle_ms and closed"
                        )),
                    );
                }
            }
            Seen::Complete { file } => {
                let path = dir.join(&file);
                let by = owner_of(&path, "folder");
                let name = library.program_of(&file).unwrap_or_else(|_| file.clone());
                // What the listing said while it was written no longer holds; taking it
                // says anew what does (a conflict, a locked revision).
                library.set_note(&name, None);
                let taken = library
                    .take_file(FolderFile {
                        file: file.clone(),
                        by: by.clone(),
                    })
                    .await;
                match taken {
                    Ok(Taken::Revision(entry)) => {
                        let detail = entry.latest.as_ref().map_or_else(String::new, |r| {
                            format!(
                                "from the folder: {file}; revision {} ({}), {} bytes",
                                r.number,
                                r.sha256.chars().take(12).collect::<String>(),
                                r.size
                            )
                        });
                        tracing::info!(program = %entry.name, %file, "program library: the folder's file taken as a revision");
                        audit_library(
                            &ctx,
                            "program.store",
                            &path,
                            &name,
                            detail,
                            by.clone(),
                            Ok(()),
                        );
                        super::route_program::changed(&ctx, entry.info(), false, Some(&by)).await;
                    }
                    Ok(Taken::Unchanged | Taken::Nothing | Taken::Removed(_)) => {}
                    Err(e) => {
                        tracing::warn!(%file, error = %e, "program library: a file of the folder not taken; it is left as it is");
                        audit_library(
                            &ctx,
                            "program.store",
                            &path,
                            &name,
                            format!("from the folder: {file}"),
                            by.clone(),
                            Err(&e),
                        );
                        publish_library_event(&ctx, refused(&name, &file, &e, by)).await;
                    }
                }
            }
            Seen::Gone { file } => gone(&ctx, &followed, &file).await,
            Seen::Refused { file, why } => refuse(&ctx, &file, &why).await,
            Seen::Listed if !listed => {
                listed = true;
                // Deleted while the gateway was stopped: as if deleted now.
                match library.files_missing().await {
                    Ok(names) => {
                        for name in names {
                            gone(&ctx, &followed, &name).await;
                        }
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "program library: programs without a file not looked for")
                    }
                }
            }
            Seen::Listed => {}
            Seen::Unreadable { error } => {
                publish_library_event(
                    &ctx,
                    pb::LibraryEvent {
                        kind: pb::LibraryEventKind::FolderUnreadable as i32,
                        file: dir.display().to_string(),
                        error,
                        ..Default::default()
                    },
                )
                .await;
            }
            Seen::Readable => {
                publish_library_event(
                    &ctx,
                    pb::LibraryEvent {
                        kind: pb::LibraryEventKind::FolderReadable as i32,
                        file: dir.display().to_string(),
                        ..Default::default()
                    },
                )
                .await;
            }
        }
    }
}

/// A file of the library's folder it does not take: said once while it is there.
async fn refuse(ctx: &RouteContext, file: &OsStr, why: &str) {
    let library = &ctx.library;
    let shown = escaped(file);
    let path = library.dir().join(file);
    let by = owner_of(&path, "folder");
    let name = file
        .to_str()
        .and_then(|f| library.program_of(f).ok())
        .unwrap_or_default();
    let e = library.not_taken(file, why);
    tracing::warn!(file = %shown, error = %e, "program library: a file of the folder not taken");
    let key = format!("folder:{}/{shown}", library.dir().display());
    ctx.audit(
        Audit {
            action: "program.store",
            permission: Permission::ProgramWrite,
            key: &key,
            machine: "",
            target: if name.is_empty() {
                shown.clone()
            } else {
                name.clone()
            },
            detail: format!("from the folder: {shown}"),
            origin: Some(by.clone()),
        },
        Err(&e),
    );
    publish_library_event(ctx, refused(&name, &shown, &e, by)).await;
}

/// A file of the library's folder went away.
async fn gone(ctx: &RouteContext, followed: &Followed, file: &str) {
    let library = &ctx.library;
    let path = library.dir().join(file);
    let name = library
        .program_of(file)
        .unwrap_or_else(|_| file.to_string());
    // A deleted file has no owner left to ask, and the folder does not say who deleted it.
    let by = pb::RequestOrigin {
        user: String::new(),
        via: "folder".to_string(),
    };
    match library.file_gone(file).await {
        Ok(Taken::Removed(entry)) => {
            tracing::info!(program = %name, %file, "program library: the file was deleted from the folder; the program is removed, its revisions kept");
            let detail = format!("the file {file} was deleted from the folder");
            audit_library(
                ctx,
                "program.remove",
                &path,
                &name,
                detail,
                by.clone(),
                Ok(()),
            );
            super::route_program::changed(ctx, entry.info(), true, Some(&by)).await;
        }
        Ok(_) => {
            // Another file gives the name now (one of a conflict went): it is looked at again.
            if let Ok(Some(other)) = library.file_of(&name).await {
                let _ = followed.retry.send(other);
            }
        }
        Err(e) => {
            tracing::warn!(%file, error = %e, "program library: the deletion of a file in the folder not taken");
            audit_library(
                ctx,
                "program.remove",
                &path,
                &name,
                format!("the file {file} was deleted from the folder"),
                by.clone(),
                Err(&e),
            );
            publish_library_event(ctx, refused(&name, file, &e, by)).await;
        }
    }
}

/// A drop folder: each complete file is queued to `machine` as a job, then moved to `sent/`
/// (or to `refused/`, with a `.why.txt` beside it saying why).
async fn follow_drop(ctx: RouteContext, machine: String, dir: PathBuf, mut followed: Followed) {
    let via = format!("drop folder {}", dir.display());
    while let Some(seen) = followed.seen.recv().await {
        let file = match seen {
            Seen::Complete { file } => file,
            Seen::Refused { file, why } => {
                refuse_drop(&ctx, &machine, &dir, &file, why, &via);
                continue;
            }
            _ => continue,
        };
        // A machine a reload removed takes no more jobs: its folder's files wait.
        let Some(m) = ctx.machines.now().get(&machine).cloned() else {
            return;
        };
        let path = dir.join(&file);
        let by = owner_of(&path, &via);
        let rules = ctx.library.folder_rules();
        let request_id = drop_request_id(&path, &file);
        let submission = JobSubmission {
            input: ProgramInput::File(path.clone()),
            name: rules.strip(&file).to_string(),
            request_id,
            submitted_by: by.clone(),
            ..JobSubmission::default()
        };
        let submitted = m.jobs.submit(submission).await;
        let detail = match &submitted {
            Ok(a) => format!("from the drop folder: {file}; job {}", a.job_id),
            Err(_) => format!("from the drop folder: {file}"),
        };
        ctx.audit(
            Audit {
                action: "job.submit",
                permission: Permission::JobSubmit,
                key: &format!("folder:{}", path.display()),
                machine: &machine,
                target: file.clone(),
                detail,
                origin: Some(by),
            },
            submitted.as_ref().map(|_| ()),
        );
        match submitted {
            Ok(accepted) => {
                tracing::info!(%machine, %file, job = %accepted.job_id, "drop folder: file queued as a job");
                if let Err(e) = move_into(&dir, SENT, file.as_ref(), None) {
                    tracing::error!(%machine, %file, error = %e, "drop folder: the file was queued but could not be moved to sent/: move it by hand, or it is queued again after a restart only if changed");
                }
            }
            Err(e) => {
                tracing::warn!(%machine, %file, error = %e, "drop folder: file refused");
                if let Err(io) = move_into(&dir, REFUSED, file.as_ref(), Some(&e)) {
                    tracing::error!(%machine, %file, error = %io, "drop folder: the refused file could not be moved to refused/");
                }
            }
        }
    }
}

/// A drop folder's entry that is not a regular file: never opened or followed.
#[derive(Debug, thiserror::Error)]
#[error("the file {file} in the drop folder is not queued: {why}")]
struct DropRefused {
    file: String,
    why: String,
}

impl BusCode for DropRefused {
    fn code(&self) -> pb::ErrorCode {
        pb::ErrorCode::InvalidRequest
    }
}

/// A link or a special file in `machine`'s drop folder: logged, audited, and moved to
/// `refused/` (the entry itself, not what a link names) with why beside it.
fn refuse_drop(
    ctx: &RouteContext,
    machine: &str,
    dir: &Path,
    file: &OsStr,
    why: String,
    via: &str,
) {
    let shown = escaped(file);
    let path = dir.join(file);
    let e = DropRefused {
        file: shown.clone(),
        why,
    };
    tracing::warn!(%machine, file = %shown, error = %e, "drop folder: file refused");
    ctx.audit(
        Audit {
            action: "job.submit",
            permission: Permission::JobSubmit,
            key: &format!("folder:{}/{shown}", dir.display()),
            machine,
            target: shown.clone(),
            detail: format!("from the drop folder: {shown}"),
            origin: Some(owner_of(&path, via)),
        },
        Err(&e),
    );
    if let Err(io) = move_into(dir, REFUSED, file, Some(&e)) {
        tracing::error!(%machine, file = %shown, error = %io, "drop folder: the refused file could not be moved to refused/");
    }
}

/// A request id for a dropped file: the same file (name, time, size) again is the same job,
/// so a restart between the queueing and the move does not send it twice.
fn drop_request_id(path: &Path, file: &str) -> String {
    use sha2::Digest as _;
    let stat = std::fs::metadata(path)
        .ok()
        .map(|m| (m.len(), m.modified().ok()))
        .unwrap_or_default();
    let mut h = sha2::Sha256::new();
    h.update(file.as_bytes());
    h.update(format!("{stat:?}").as_bytes());
    format!("drop-{}", &hex::encode(h.finalize())[..32])
}

/// Moves `file` of `dir` into `dir/sub/`, under a name not yet taken there; with `why`, writes
/// it beside the file as `<file>.why.txt`.
fn move_into(
    dir: &Path,
    sub: &str,
    file: &OsStr,
    why: Option<&dyn std::fmt::Display>,
) -> std::io::Result<()> {
    let into = dir.join(sub);
    std::fs::create_dir_all(&into)?;
    let mut target = into.join(file);
    let mut n = 1;
    // A dangling link counts as taken too.
    while std::fs::symlink_metadata(&target).is_ok() {
        let mut numbered = OsString::from(file);
        numbered.push(format!(".{n}"));
        target = into.join(numbered);
        n += 1;
    }
    std::fs::rename(dir.join(file), &target)?;
    if let Some(why) = why {
        let mut note = target.clone().into_os_string();
        note.push(".why.txt");
        std::fs::write(note, format!("{why}\n"))?;
    }
    Ok(())
}
