//! The cell's program library.
//!
//! - `P/C/program/NAME`: a get → the program's bytes (`application/octet-stream`); a wildcard
//!   get → a `ProgramInfo` per program it takes in. Reads only.
//! - `P/C/program/NAME/revisions`: a get → `ProgramRevisions`, newest first.
//! - `P/C/program/NAME/rev/REV`: a get → that revision's bytes.
//! - `P/C/program/NAME/diff?a=..;b=..;ignore=..`: a get → `ProgramDiff`.
//! - `P/C/program/NAME/write`: a get with a `ProgramWrite` → stores (a new revision), adopts
//!   or removes the program and answers its `ProgramInfo` once the change is on disk (or an
//!   `ErrorReply`): the confirmed form; a put stores, a delete removes, without an answer
//!   (refusals are logged). The writes have a key of their own, so that a role that reads
//!   programs can never write one.
//! - `P/C/program/NAME/release`: a get with a `ProgramRelease` → the revision in its new
//!   state (`program.release`).
//!
//! Every write is in the audit trail. Library I/O may wait on the disk, so every request
//! runs off the route's loop; a read holds the whole program, so few run at once
//! ([`Pool::ProgramRead`]).

use zenoh::bytes::Encoding;
use zenoh::query::Query;

use super::context::{RequestError, RouteContext, publish_event, reply, reply_bytes, reply_err};
use super::keys::{CellKey, intersects};
use super::published::Published;
use super::write::{Audited, Done, Via, Write};
use crate::library::{LibraryError, ProgramEntry, Store};
use cellgate_core::pb;
use cellgate_core::program::diff::{self, DiffOptions};

/// Equal blocks of context around each change of a diff.
const DIFF_CONTEXT: usize = 3;

/// A get on a read key with a payload, which only a write key takes.
async fn refuse_payload(ctx: &RouteContext, q: &Query) -> bool {
    if q.payload().is_none() {
        return false;
    }
    let e = RequestError::WrongKey(format!(
        "a get on {} reads and takes no payload: a ProgramWrite goes to {}, a ProgramRelease \
         to {}",
        q.key_expr(),
        ctx.keys.program_write("<name>"),
        ctx.keys.program_release("<name>")
    ));
    reply_err(q, &e).await;
    true
}

/// A get on `P/C/program/NAME`.
pub(super) async fn program_read(ctx: &RouteContext, q: &Query) {
    if refuse_payload(ctx, q).await {
        return;
    }
    if q.key_expr().is_wild() {
        match ctx.library.list().await {
            Ok(entries) => {
                for e in entries {
                    // A file the folder refuses has no program name: a chunk no program
                    // name can be (it starts with '-') stands for it.
                    let key = if e.name.is_empty() {
                        use sha2::Digest as _;
                        let id = hex::encode(sha2::Sha256::digest(e.file.as_bytes()));
                        ctx.keys.program(&format!("-refused-{}", &id[..16]))
                    } else {
                        ctx.keys.program(&e.name)
                    };
                    if intersects(q.key_expr(), &key) {
                        reply(q, key, &e.info()).await;
                    }
                }
            }
            Err(e) => reply_err(q, &RequestError::from(e)).await,
        }
        return;
    }
    let Some(CellKey::Program { name }) = ctx.keys.parse(q.key_expr().as_str()) else {
        return;
    };
    match ctx.library.read(name).await {
        Ok(program) => reply_bytes(q, program, Encoding::APPLICATION_OCTET_STREAM).await,
        Err(e) => reply_err(q, &ctx.naming_programs(e.into(), true).await).await,
    }
}

/// The one program a concrete key names; a wildcard key is left unanswered (browsing).
fn one_program<'k>(q: &'k Query, ctx: &RouteContext) -> Option<CellKey<'k>> {
    if q.key_expr().is_wild() {
        return None;
    }
    ctx.keys.parse(q.key_expr().as_str())
}

/// A get on `P/C/program/NAME/revisions`.
pub(super) async fn program_revisions(ctx: &RouteContext, q: &Query) {
    if refuse_payload(ctx, q).await {
        return;
    }
    let Some(CellKey::ProgramRevisions { name }) = one_program(q, ctx) else {
        return;
    };
    match ctx.library.revisions(name).await {
        Ok(r) => reply(q, q.key_expr().to_string(), &r).await,
        Err(e) => reply_err(q, &ctx.naming_programs(e.into(), true).await).await,
    }
}

/// A get on `P/C/program/NAME/rev/REV`.
pub(super) async fn program_revision(ctx: &RouteContext, q: &Query) {
    if refuse_payload(ctx, q).await {
        return;
    }
    let Some(CellKey::ProgramRevision { name, revision }) = one_program(q, ctx) else {
        return;
    };
    match ctx.library.read_revision(name, revision).await {
        Ok((_, bytes)) => reply_bytes(q, bytes, Encoding::APPLICATION_OCTET_STREAM).await,
        Err(e) => reply_err(q, &ctx.naming_programs(e.into(), true).await).await,
    }
}

/// A get on `P/C/program/NAME/diff?a=REV;b=REV;ignore=...`.
pub(super) async fn program_diff(ctx: &RouteContext, q: &Query) {
    if refuse_payload(ctx, q).await {
        return;
    }
    let Some(CellKey::ProgramDiff { name }) = one_program(q, ctx) else {
        return;
    };
    match diff_of(ctx, q, name).await {
        Ok(d) => reply(q, q.key_expr().to_string(), &d).await,
        Err(e) => reply_err(q, &ctx.naming_programs(e, true).await).await,
    }
}

async fn diff_of(
    ctx: &RouteContext,
    q: &Query,
    name: &str,
) -> Result<pb::ProgramDiff, RequestError> {
    let invalid = |what: String| RequestError::WrongKey(format!("program {name}: {what}"));
    let (mut a, mut b, mut ignore) = (None, None, String::new());
    for (k, v) in q.parameters().iter() {
        match k {
            "a" => a = Some(v.to_string()),
            "b" => b = Some(v.to_string()),
            "ignore" => ignore = v.to_string(),
            other => {
                return Err(invalid(format!(
                    "unknown parameter {other:?}; a diff takes a, b and ignore"
                )));
            }
        }
    }
    let options = DiffOptions::parse(&ignore).map_err(|e| invalid(e.to_string()))?;
    let revisions = ctx.library.revisions(name).await?;
    // Newest first: the latest, and the one before it.
    let b = b.unwrap_or_else(|| {
        revisions
            .revisions
            .first()
            .map(|r| r.number.to_string())
            .unwrap_or_default()
    });
    let a = match a {
        Some(a) => a,
        None => {
            let (rb, _) = ctx.library.revision(name, &b).await?;
            let before = revisions.revisions.iter().find(|r| r.number < rb.number);
            match before {
                Some(r) => r.number.to_string(),
                None => {
                    return Err(invalid(format!(
                        "revision {} is its first: name the revision to compare with (a=...)",
                        rb.number
                    )));
                }
            }
        }
    };
    let (ra, bytes_a) = ctx.library.read_revision(name, &a).await?;
    let (rb, bytes_b) = ctx.library.read_revision(name, &b).await?;
    let (counts, hunks) =
        tokio::task::spawn_blocking(move || diff::diff(&bytes_a, &bytes_b, options, DIFF_CONTEXT))
            .await
            .map_err(|e| RequestError::WrongKey(e.to_string()))?
            .map_err(|error| RequestError::NotText {
                name: name.to_string(),
                error,
            })?;
    Ok(pb::ProgramDiff {
        name: name.to_string(),
        a: Some(ra),
        b: Some(rb),
        ignored: options.names(),
        same: counts.same(),
        blocks_added: counts.added,
        blocks_removed: counts.removed,
        blocks_changed: counts.changed,
        hunks,
    })
}

/// `P/C/program/NAME/write` (its write row): a get with a `ProgramWrite` stores, removes or
/// adopts the program (or checks a store) and answers its `ProgramInfo`; a put stores the
/// put's bytes as the program, a delete removes it.
pub(super) async fn program_write(
    ctx: &RouteContext,
    w: Write,
) -> Done<pb::ProgramInfo, RequestError> {
    if w.key.is_wild() {
        return Done::refused(RequestError::WrongKey(
            "a ProgramWrite names one program, without wildcards".to_string(),
        ));
    }
    let Some(CellKey::ProgramWrite { name }) = ctx.keys.parse(w.key()) else {
        return Done::nothing();
    };
    let by = w.origin.clone().unwrap_or_default();
    let audited = |action, detail| Audited {
        action,
        machine: String::new(),
        target: name.to_string(),
        detail,
    };
    let (action, detail, done) = match (w.via, w.bytes()) {
        (Via::Delete, _) => (
            "program.remove",
            String::new(),
            ctx.library.remove_by(name).await,
        ),
        (Via::Put, bytes) => {
            let store = Store {
                bytes: bytes.unwrap_or_default(),
                by,
                ..Store::default()
            };
            stored(ctx, name, store).await
        }
        (Via::Get, None) => {
            return Done::refused(RequestError::WrongKey(format!(
                "a get on {} writes and needs a ProgramWrite; the program is read on {}",
                w.key,
                ctx.keys.program(name)
            )));
        }
        (Via::Get, Some(payload)) => {
            let write = match cellgate_core::bounds::decode::<pb::ProgramWrite>(
                payload.as_ref(),
                &ctx.limits(),
            ) {
                Ok(write) => write,
                Err(error) => {
                    let e = RequestError::ProgramWritePayload {
                        name: name.to_string(),
                        error,
                    };
                    return Done::audited(audited("program.store", String::new()), Err(e));
                }
            };
            match write.op {
                Some(pb::program_write::Op::Check(c)) => {
                    // A question, not a write: nothing to audit.
                    let info = match ctx.library.check_store(name, c.size).await {
                        Ok(Some(entry)) => Ok(entry.info()),
                        Ok(None) => Ok(pb::ProgramInfo {
                            name: name.to_string(),
                            ..Default::default()
                        }),
                        Err(e) => Err(RequestError::from(e)),
                    };
                    return Done {
                        audit: None,
                        outcome: info.map(Some),
                    };
                }
                Some(pb::program_write::Op::Store(bytes)) => {
                    let store = Store {
                        // The request's own bytes, not a copy: a program may be large.
                        bytes: bytes.into(),
                        by,
                        comment: write.comment,
                        adopted: None,
                    };
                    stored(ctx, name, store).await
                }
                Some(pb::program_write::Op::Remove(_)) => (
                    "program.remove",
                    String::new(),
                    ctx.library.remove_by(name).await,
                ),
                Some(pb::program_write::Op::Adopt(a)) => (
                    "program.adopt",
                    format!(
                        "from {} revision {}",
                        a.from,
                        if a.revision.is_empty() {
                            "latest"
                        } else {
                            &a.revision
                        }
                    ),
                    ctx.library
                        .adopt(name, &a.from, &a.revision, by, write.comment)
                        .await,
                ),
                None => {
                    return Done::refused(RequestError::ProgramWriteEmpty {
                        name: name.to_string(),
                    });
                }
            }
        }
    };
    let removed = action == "program.remove";
    let entry = match done {
        Ok(entry) => entry,
        Err(e) => {
            // A refusal names the programs near the one asked for, for whoever may list them.
            let e = ctx.naming_programs(e.into(), ctx.open_cell()).await;
            return Done::audited(audited(action, detail), Err(e));
        }
    };
    let detail = match &entry.latest {
        Some(r) if !removed => format!(
            "{detail}; revision {} ({})",
            r.number,
            r.sha256.chars().take(12).collect::<String>()
        ),
        _ => detail,
    };
    tracing::info!(program = %entry.name, size = entry.size, action, "program library changed");
    let revised = entry.revised;
    let info = entry.info();
    // A store of the same bytes again changed nothing: no word.
    if revised || removed {
        changed(ctx, info.clone(), removed, w.origin.as_ref()).await;
    }
    Done::audited(audited(action, detail), Ok(info))
}

/// `store` kept as program `name`: the audit's action and detail, and the library's answer.
async fn stored(
    ctx: &RouteContext,
    name: &str,
    store: Store<'_>,
) -> (&'static str, String, Result<ProgramEntry, LibraryError>) {
    let detail = format!("{} bytes", store.bytes.len());
    (
        "program.store",
        detail,
        ctx.library.store_as(name, store).await,
    )
}

/// Tells the cell that a program changed: its `ProgramInfo` on `…/program/NAME/changed`
/// (`cellgate watch` prints it), whoever asked and however: the write key, the console, the
/// library's folder. After a removal, the revision that was latest says `removed`, as the
/// revisions do from then on. A store of the same bytes again changed nothing: no word.
pub(super) async fn changed(
    ctx: &RouteContext,
    mut info: pb::ProgramInfo,
    removed: bool,
    origin: Option<&pb::RequestOrigin>,
) {
    if removed && let Some(latest) = info.latest.as_mut() {
        latest.removed = true;
    }
    publish_event(
        ctx,
        Published::ProgramChanged,
        &ctx.keys.program_changed(&info.name),
        &info,
        origin,
    )
    .await;
}

/// A get with a `ProgramRelease` on `P/C/program/NAME/release` (its write row): sets a
/// revision's state and answers the revision.
pub(super) async fn program_release(
    ctx: &RouteContext,
    w: Write,
) -> Done<pb::ProgramRevision, RequestError> {
    let Some(CellKey::ProgramRelease { name }) = ctx.keys.parse(w.key()) else {
        return Done::nothing();
    };
    if w.key.is_wild() {
        return Done::refused(RequestError::WrongKey(
            "a ProgramRelease names one program".to_string(),
        ));
    }
    let Some(payload) = w.bytes() else {
        return Done::refused(RequestError::WrongKey(format!(
            "a get on {} changes a revision's state and needs a ProgramRelease; the revisions \
             are read on {}",
            w.key,
            ctx.keys.program_revisions(name)
        )));
    };
    let done = match cellgate_core::bounds::decode::<pb::ProgramRelease>(
        payload.as_ref(),
        &ctx.limits(),
    ) {
        Ok(r) => {
            let state = r.state();
            let by = w.origin.clone().unwrap_or_default();
            match ctx
                .library
                .set_state(name, &r.revision, state, by, r.comment)
                .await
            {
                Ok(r) => Ok(r),
                Err(e) => Err(ctx.naming_programs(e.into(), ctx.open_cell()).await),
            }
        }
        Err(error) => Err(RequestError::ProgramWritePayload {
            name: name.to_string(),
            error,
        }),
    };
    let detail = match &done {
        Ok(r) => format!(
            "revision {} now {}",
            r.number,
            r.state()
                .as_str_name()
                .trim_start_matches("REVISION_STATE_")
                .to_lowercase()
        ),
        Err(_) => String::new(),
    };
    let audited = Audited {
        action: "program.release",
        machine: String::new(),
        target: name.to_string(),
        detail,
    };
    Done::audited(audited, done)
}
