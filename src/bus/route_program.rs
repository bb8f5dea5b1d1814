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
use zenoh::sample::{Sample, SampleKind};

use super::audit::{Audit, origin_of};
use super::context::{RequestError, RouteContext, publish_event, reply, reply_bytes, reply_err};
use super::keys::{CellKey, intersects};
use super::published::Published;
use crate::library::Store;
use cellgate_core::config::Permission;
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

/// A get with a `ProgramWrite` on `P/C/program/NAME/write`.
pub(super) async fn program_write(ctx: &RouteContext, q: &Query) {
    let Some(CellKey::ProgramWrite { name }) = ctx.keys.parse(q.key_expr().as_str()) else {
        return;
    };
    if q.key_expr().is_wild() {
        if q.payload().is_none() {
            // A wildcard get without payload (`P/C/**`) browses.
            return;
        }
        let e = RequestError::WrongKey("a ProgramWrite names one program".to_string());
        return reply_err(q, &e).await;
    }
    let Some(payload) = q.payload() else {
        let e = RequestError::WrongKey(format!(
            "a get on {} writes and needs a ProgramWrite; the program is read on {}",
            q.key_expr(),
            ctx.keys.program(name)
        ));
        return reply_err(q, &e).await;
    };
    let origin = origin_of(q.attachment());
    let write = match cellgate_core::bounds::decode::<pb::ProgramWrite>(
        payload.to_bytes().as_ref(),
        &ctx.limits(),
    ) {
        Ok(w) => w,
        Err(error) => {
            let e = RequestError::ProgramWritePayload {
                name: name.to_string(),
                error,
            };
            audit_write(
                ctx,
                q.key_expr().as_str(),
                "program.store",
                name,
                String::new(),
                origin,
                Err(&e),
            );
            return reply_err(q, &e).await;
        }
    };
    if let Some(pb::program_write::Op::Check(c)) = &write.op {
        return match ctx.library.check_store(name, c.size).await {
            Ok(Some(entry)) => reply(q, q.key_expr().to_string(), &entry.info()).await,
            Ok(None) => {
                let info = pb::ProgramInfo {
                    name: name.to_string(),
                    ..Default::default()
                };
                reply(q, q.key_expr().to_string(), &info).await;
            }
            Err(e) => reply_err(q, &RequestError::from(e)).await,
        };
    }
    let by = origin.clone().unwrap_or_default();
    let (action, detail, done) = match write.op {
        Some(pb::program_write::Op::Store(bytes)) => (
            "program.store",
            format!("{} bytes", bytes.len()),
            ctx.library
                .store_as(
                    name,
                    Store {
                        // The request's own bytes, not a copy: a program may be large.
                        bytes: bytes.into(),
                        by,
                        comment: write.comment,
                        adopted: None,
                    },
                )
                .await,
        ),
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
        Some(pb::program_write::Op::Check(_)) | None => {
            let e = RequestError::ProgramWriteEmpty {
                name: name.to_string(),
            };
            return reply_err(q, &e).await;
        }
    };
    let done = done.map_err(RequestError::from);
    let detail = match &done {
        Ok(entry) => match &entry.latest {
            Some(r) if action != "program.remove" => format!(
                "{detail}; revision {} ({})",
                r.number,
                r.sha256.chars().take(12).collect::<String>()
            ),
            _ => detail,
        },
        Err(_) => detail,
    };
    audit_write(
        ctx,
        q.key_expr().as_str(),
        action,
        name,
        detail,
        origin.clone(),
        done.as_ref().map(|_| ()),
    );
    match done {
        Ok(entry) => {
            tracing::info!(program = %entry.name, size = entry.size, action, "program library changed");
            let revised = entry.revised || action == "program.remove";
            let info = entry.info();
            reply(q, q.key_expr().to_string(), &info).await;
            if revised {
                changed(ctx, info, action == "program.remove", origin.as_ref()).await;
            }
        }
        Err(e) => reply_err(q, &ctx.naming_programs(e, ctx.open_cell()).await).await,
    }
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

fn audit_write(
    ctx: &RouteContext,
    key: &str,
    action: &'static str,
    name: &str,
    detail: String,
    origin: Option<pb::RequestOrigin>,
    outcome: Result<(), &RequestError>,
) {
    let permission = if action == "program.release" {
        Permission::ProgramRelease
    } else {
        Permission::ProgramWrite
    };
    ctx.audit(
        Audit {
            action,
            permission,
            key,
            machine: "",
            target: name.to_string(),
            detail,
            origin,
        },
        outcome,
    );
}

/// A put on `P/C/program/NAME/write` stores the program; a delete removes it.
pub(super) async fn program_sample(ctx: &RouteContext, sample: &Sample) {
    let key = sample.key_expr();
    if key.is_wild() {
        return tracing::warn!(%key, "program library: name one program, without wildcards");
    }
    let Some(CellKey::ProgramWrite { name }) = ctx.keys.parse(key.as_str()) else {
        return;
    };
    let origin = origin_of(sample.attachment());
    let by = origin.clone().unwrap_or_default();
    let (action, result) = match sample.kind() {
        SampleKind::Put => {
            let program = sample.payload().to_bytes();
            let stored = ctx
                .library
                .store_as(
                    name,
                    Store {
                        bytes: program.as_ref().into(),
                        by,
                        ..Store::default()
                    },
                )
                .await;
            ("program.store", stored)
        }
        SampleKind::Delete => ("program.remove", ctx.library.remove_by(name).await),
    };
    let result = result.map_err(RequestError::from);
    let detail = match &result {
        Ok(e) => e
            .latest
            .as_ref()
            .map(|r| format!("revision {}", r.number))
            .unwrap_or_default(),
        Err(_) => String::new(),
    };
    audit_write(
        ctx,
        key.as_str(),
        action,
        name,
        detail,
        origin.clone(),
        result.as_ref().map(|_| ()),
    );
    match result {
        Ok(e) => {
            tracing::info!(program = %e.name, size = e.size, action, "program library changed");
            if e.revised || action == "program.remove" {
                changed(ctx, e.info(), action == "program.remove", origin.as_ref()).await;
            }
        }
        Err(e) => tracing::warn!(%key, error = %e, "program library request refused"),
    }
}

/// A get with a `ProgramRelease` on `P/C/program/NAME/release`.
pub(super) async fn program_release(ctx: &RouteContext, q: &Query) {
    let Some(CellKey::ProgramRelease { name }) = ctx.keys.parse(q.key_expr().as_str()) else {
        return;
    };
    if q.key_expr().is_wild() {
        if q.payload().is_some() {
            let e = RequestError::WrongKey("a ProgramRelease names one program".to_string());
            reply_err(q, &e).await;
        }
        return;
    }
    let Some(payload) = q.payload() else {
        let e = RequestError::WrongKey(format!(
            "a get on {} changes a revision's state and needs a ProgramRelease; the revisions \
             are read on {}",
            q.key_expr(),
            ctx.keys.program_revisions(name)
        ));
        return reply_err(q, &e).await;
    };
    let origin = origin_of(q.attachment());
    let done = match cellgate_core::bounds::decode::<pb::ProgramRelease>(
        payload.to_bytes().as_ref(),
        &ctx.limits(),
    ) {
        Ok(r) => {
            let state = r.state();
            ctx.library
                .set_state(
                    name,
                    &r.revision,
                    state,
                    origin.clone().unwrap_or_default(),
                    r.comment,
                )
                .await
                .map_err(RequestError::from)
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
    audit_write(
        ctx,
        q.key_expr().as_str(),
        "program.release",
        name,
        detail,
        origin,
        done.as_ref().map(|_| ()),
    );
    match done {
        Ok(r) => reply(q, q.key_expr().to_string(), &r).await,
        Err(e) => reply_err(q, &ctx.naming_programs(e, ctx.open_cell()).await).await,
    }
}
