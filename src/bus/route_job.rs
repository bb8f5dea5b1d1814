//! Jobs on the bus.
//!
//! - `P/C/machine/M/submit`: a get with a `JobRequest` queues a job (`JobAccepted` or
//!   `ErrorReply`): the write has a key of its own, so that a role that reads the queue can
//!   never submit;
//! - `P/C/machine/M/job`: a get answers the machine's `JobQueue`.
//! - `P/C/machine/M/job/ID`: the job's `JobEvent`s, published reliably (QoS `Block`); a get
//!   answers its latest event (the last [`RECENT_JOBS`] jobs are kept); a delete from another
//!   session cancels the job.
//!
//! A submit may wait (a library program is scanned, a `key` program fetched), so it runs off
//! the route's loop, within the context's bound.

use std::time::Duration;

use bytes::Bytes;
use prost::Message;
use zenoh::bytes::Encoding;
use zenoh::key_expr::KeyExpr;
use zenoh::query::Query;
use zenoh::sample::{Sample, SampleKind};

use super::audit::{Audit, origin_of};
use super::context::{RequestError, RouteContext, Target, reply, reply_err};
use super::keys::{CellKey, MachineLeaf, intersects, is_plain_chunk};
use super::machine::Machine;
use super::payload::{BusMessage, encoding, schema_of};
use super::published::Published;
use crate::jobs::JobSubmission;
use crate::jobs::source::ProgramInput;
use cellgate_core::config::Permission;
use cellgate_core::pb;
use cellgate_core::program::blocks::StartAt;

/// How long fetching a job's program from a `key` may take.
pub const FETCH_TIMEOUT: Duration = Duration::from_secs(5);

/// Finished jobs whose last event a `get` on `P/C/machine/M/job/*` still answers.
pub const RECENT_JOBS: usize = 256;

/// A get on `P/C/machine/M/job`: the queue of every machine it takes in.
pub(super) async fn job_queue(ctx: &RouteContext, q: &Query) {
    if q.payload().is_some() {
        let e = RequestError::WrongKey(format!(
            "a get on {} reads the queue and takes no payload: submit a JobRequest on {}",
            q.key_expr(),
            ctx.keys.leaf("<machine>", MachineLeaf::Submit)
        ));
        return reply_err(q, &e).await;
    }
    let matching = ctx.matching(q, MachineLeaf::Job);
    if matching.is_empty() {
        return ctx.unmatched(q).await;
    }
    for (key, m) in matching {
        match m.jobs.queue().await {
            Ok(queue) => reply(q, key, &queue).await,
            Err(e) => reply_err(q, &RequestError::from(e)).await,
        }
    }
}

/// A get with a `JobRequest` on `P/C/machine/M/submit`.
pub(super) async fn job_submit(ctx: &RouteContext, q: &Query) {
    let Some(payload) = q.payload() else {
        if q.key_expr().is_wild() {
            // A wildcard get without payload (`P/C/**`) browses; a submit names one machine.
            return;
        }
        let e = RequestError::WrongKey(format!(
            "a get on {} submits a job and needs a JobRequest; the queue is read on {}",
            q.key_expr(),
            ctx.keys.leaf("<machine>", MachineLeaf::Job)
        ));
        return reply_err(q, &e).await;
    };
    if let Err(e) = ctx.history.audit_writable() {
        return reply_err(q, &RequestError::from(e)).await;
    }
    let payload = payload.to_bytes();
    let origin = origin_of(q.attachment());
    let machine = match ctx.keys.parse(q.key_expr().as_str()) {
        Some(CellKey::Leaf { machine, .. }) => machine.to_string(),
        _ => String::new(),
    };
    let submitted = submit(ctx, q, &payload, origin.clone()).await;
    let detail = match &submitted {
        Ok(a) => describe_program(a.program.as_ref()),
        Err(_) => String::new(),
    };
    ctx.audit_answered(
        Audit {
            action: "job.submit",
            permission: Permission::JobSubmit,
            key: q.key_expr().as_str(),
            machine: &machine,
            target: match &submitted {
                Ok(a) => a.job_id.clone(),
                Err(_) => machine.clone(),
            },
            detail,
            origin,
        },
        submitted.as_ref().map(|_| ()),
    )
    .await;
    match submitted {
        Ok(accepted) => reply(q, q.key_expr().to_string(), &accepted).await,
        Err(e) => reply_err(q, &ctx.naming_programs(e, ctx.open_cell()).await).await,
    }
}

/// A job's program, for the audit: `O1234 revision 3 (3f2a9c1b…)` or `sha256 3f2a9c1b…`.
pub(crate) fn describe_program(p: Option<&pb::ProgramRef>) -> String {
    let Some(p) = p else { return String::new() };
    let short: String = p.sha256.chars().take(12).collect();
    if p.library.is_empty() {
        format!("sha256 {short}")
    } else {
        format!("{} revision {} ({short})", p.library, p.revision)
    }
}

async fn submit(
    ctx: &RouteContext,
    q: &Query,
    payload: &[u8],
    origin: Option<pb::RequestOrigin>,
) -> Result<pb::JobAccepted, RequestError> {
    let m = ctx.one_machine(q, MachineLeaf::Submit, "JobRequest")?;
    let request: pb::JobRequest = ctx.decode(m.name(), payload)?;
    let input = match request.program {
        None => {
            return Err(RequestError::Invalid {
                machine: m.name().to_string(),
                what: "the JobRequest names no program: set one of inline, library or key"
                    .to_string(),
            });
        }
        Some(pb::job_request::Program::Inline(bytes)) => {
            if bytes.len() as u64 > ctx.max_inline {
                return Err(RequestError::Invalid {
                    machine: m.name().to_string(),
                    what: format!(
                        "an inline program of {} bytes is over the inline limit ({} bytes: \
                         programs.max_inline, or programs.max_size if smaller): put it in the \
                         library (`cellgate program put`) and submit it by name",
                        bytes.len(),
                        ctx.max_inline
                    ),
                });
            }
            ProgramInput::Inline(bytes.into())
        }
        Some(pb::job_request::Program::Library(name)) => ProgramInput::Library(name),
        Some(pb::job_request::Program::Key(key)) => {
            let bytes = fetch(ctx, &m, &key).await?;
            ProgramInput::Fetched { key, bytes }
        }
        Some(pb::job_request::Program::ResumeJob(job)) => ProgramInput::Resume(job),
    };
    let start_at = match request.start_at {
        None => None,
        Some(start) => {
            let at = match start.at {
                Some(pb::block_start::At::SequenceNumber(n)) => StartAt::Sequence(n),
                Some(pb::block_start::At::Line(l)) => StartAt::Line(l),
                None => {
                    return Err(RequestError::Invalid {
                        machine: m.name().to_string(),
                        what: "the JobRequest's start_at names no block: set sequence_number \
                               or line"
                            .to_string(),
                    });
                }
            };
            Some((at, start.header_lines))
        }
    };
    let submission = JobSubmission {
        input,
        name: request.name,
        priority: request.priority,
        append_eor: request.append_eor,
        request_id: request.request_id,
        start_at,
        resume_after_restart: request.resume_after_restart,
        deadline_s: request.deadline_s,
        revision: request.revision,
        submitted_by: origin.unwrap_or_default(),
    };
    Ok(m.jobs.submit(submission).await?)
}

/// Fetches a program from `key` with one `get`: the first reply's payload.
///
/// The gateway fetches with its own session, so it fetches only what every `job.submit`
/// client may have fetched itself: one key (no wildcards) under a prefix the cell file lists
/// in `programs.fetch_prefixes`, never a cellgate key, at most `max_inline` bytes, and few at
/// once ([`super::context::MAX_FETCHES`]).
async fn fetch(ctx: &RouteContext, m: &Machine, key: &str) -> Result<Bytes, RequestError> {
    let machine = m.name().to_string();
    let ke = KeyExpr::try_from(key.to_string()).map_err(|error| RequestError::BadKey {
        machine: machine.clone(),
        key: key.to_string(),
        error,
    })?;
    let allowed = !ke.is_wild()
        && !key.split('/').any(|c| c.starts_with('@'))
        && ctx.fetch_prefixes.iter().any(|p| {
            key.strip_prefix(p.as_str())
                .is_some_and(|r| r.starts_with('/'))
        });
    if !allowed {
        return Err(RequestError::NotPermitted(format!(
            "machine {machine}: JobRequest.key {key:?} is not one the cell file lets jobs fetch \
             from (programs.fetch_prefixes: {}): the gateway fetches with its own authority, \
             so only keys under those prefixes, without wildcards; put the program in the \
             library or send it inline",
            if ctx.fetch_prefixes.is_empty() {
                "none".to_string()
            } else {
                ctx.fetch_prefixes.join(", ")
            }
        )));
    }
    let failed = |why: String| RequestError::FetchFailed {
        machine: machine.clone(),
        key: key.to_string(),
        why,
    };
    let Ok(_fetching) = ctx.fetches.clone().try_acquire_owned() else {
        return Err(RequestError::Busy {
            what: "program fetches",
            max: super::context::MAX_FETCHES,
        });
    };
    let replies = ctx
        .session
        .get(ke)
        .timeout(FETCH_TIMEOUT)
        .await
        .map_err(|e| failed(e.to_string()))?;
    let mut error = None;
    while let Ok(reply) = replies.recv_async().await {
        match reply.result() {
            Ok(sample) => {
                let len = sample.payload().len() as u64;
                if len > ctx.max_inline {
                    return Err(failed(format!(
                        "the reply holds {len} bytes, over the {} a job's program may bring \
                         inline or fetched (programs.max_inline)",
                        ctx.max_inline
                    )));
                }
                return Ok(Bytes::from(sample.payload().to_bytes().into_owned()));
            }
            Err(e) => {
                error.get_or_insert_with(|| describe_error(e.payload(), e.encoding()));
            }
        }
    }
    Err(failed(error.unwrap_or_else(|| {
        format!("nothing answered within {} s", FETCH_TIMEOUT.as_secs())
    })))
}

/// An error reply's text: the `ErrorReply` message if it is one, else the payload as text.
fn describe_error(payload: &zenoh::bytes::ZBytes, encoding: &Encoding) -> String {
    let bytes = payload.to_bytes();
    if schema_of(encoding).as_deref() == Some(pb::ErrorReply::SCHEMA)
        && let Ok(e) = pb::ErrorReply::decode(bytes.as_ref())
    {
        return e.message;
    }
    String::from_utf8_lossy(&bytes).into_owned()
}

/// The last event of every recent job the query takes in.
pub(super) async fn job_events(ctx: &RouteContext, q: &Query) {
    let mut replies = Vec::new();
    for m in ctx.machines.now().values() {
        let view = m.view();
        for event in &view.recent_jobs {
            let key = ctx.keys.job_events(m.name(), &event.job_id);
            if intersects(q.key_expr(), &key) {
                replies.push((key, event.clone()));
            }
        }
    }
    if !replies.is_empty() {
        for (key, event) in replies {
            reply(q, key, &event).await;
        }
        return;
    }
    match ctx.keys.parse(q.key_expr().as_str()) {
        Some(CellKey::JobEvents { machine, job }) if !q.key_expr().is_wild() => {
            // A job the machine no longer keeps (a reload removed the machine, or newer jobs
            // pushed it out) ended as its history record says.
            if ctx.history.enabled()
                && let Ok(Some(h)) = ctx.history.find_job(machine, job).await
            {
                let event = super::record::job_event_from_history(machine, h);
                return reply(q, q.key_expr().to_string(), &event).await;
            }
            if ctx.machines.now().contains_key(machine) {
                let e = RequestError::NoSuchJob {
                    machine: machine.to_string(),
                    job: job.to_string(),
                    kept: RECENT_JOBS,
                };
                reply_err(q, &e).await;
            } else {
                ctx.unmatched(q).await;
            }
        }
        _ => {}
    }
}

/// How long a confirmed cancel waits for a running job to end before it answers the job's
/// latest event (the board stops at its next exchange, §4.4).
const CANCEL_WAIT: Duration = Duration::from_secs(20);

/// A get on `P/C/machine/M/job/ID/cancel`: cancels the job and answers its end (its
/// `cancelled` event, or how it ended first), or why it could not be cancelled.
pub(super) async fn job_cancel(ctx: &RouteContext, q: &Query) {
    let key = q.key_expr().as_str();
    let (Some(CellKey::JobCancel { job, .. }), Target::One(m)) =
        (ctx.keys.parse(key), ctx.target(q.key_expr()))
    else {
        if !q.key_expr().is_wild() {
            ctx.unmatched(q).await;
        }
        return;
    };
    if q.payload().is_some() {
        let e = RequestError::WrongKey(format!(
            "a get on {key} cancels the job and takes no payload"
        ));
        return reply_err(q, &e).await;
    }
    if let Err(e) = ctx.history.audit_writable() {
        return reply_err(q, &RequestError::from(e)).await;
    }
    let mut events = m.jobs.subscribe();
    let cancelled = m.jobs.cancel(job).await;
    ctx.audit_answered(
        Audit {
            action: "job.cancel",
            permission: Permission::JobCancel,
            key,
            machine: m.name(),
            target: job.to_string(),
            detail: String::new(),
            origin: origin_of(q.attachment()),
        },
        cancelled.as_ref().map(|_| ()),
    )
    .await;
    if let Err(e) = cancelled {
        return reply_err(q, &RequestError::from(e)).await;
    }
    let ended = tokio::time::timeout(CANCEL_WAIT, async {
        loop {
            match events.recv().await {
                Ok(e)
                    if e.job_id == job
                        && matches!(
                            e.kind,
                            Some(
                                pb::job_event::Kind::Completed(_)
                                    | pb::job_event::Kind::Failed(_)
                                    | pb::job_event::Kind::Cancelled(_)
                            )
                        ) =>
                {
                    return Some(e);
                }
                Ok(_) => {}
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                Err(_) => return None,
            }
        }
    })
    .await
    .ok()
    .flatten();
    let answer = match ended {
        Some(e) => Some((*e).clone()),
        // Not ended yet (or its end went by): the latest event kept.
        None => m
            .view()
            .recent_jobs
            .iter()
            .find(|e| e.job_id == job)
            .cloned(),
    };
    match answer {
        Some(e) => reply(q, ctx.keys.job_events(m.name(), job), &e).await,
        None => {
            let e = RequestError::NoSuchJob {
                machine: m.name().to_string(),
                job: job.to_string(),
                kept: RECENT_JOBS,
            };
            reply_err(q, &e).await;
        }
    }
}

/// A delete on `P/C/machine/M/job/ID` cancels the job.
pub(super) async fn job_delete(ctx: &RouteContext, sample: &Sample) {
    if sample.kind() != SampleKind::Delete {
        return;
    }
    let key = sample.key_expr();
    let (Some(CellKey::JobEvents { job, .. }), Target::One(m)) =
        (ctx.keys.parse(key.as_str()), ctx.target(key))
    else {
        tracing::warn!(%key, "cancel refused: a delete cancels one job of one machine of this cell");
        return;
    };
    if !is_plain_chunk(job) {
        tracing::warn!(%key, "cancel refused: name one job, without wildcards");
        return;
    }
    if let Err(e) = ctx.history.audit_writable() {
        tracing::warn!(%key, error = %e, "cancel refused");
        return;
    }
    let cancelled = m.jobs.cancel(job).await;
    ctx.audit(
        Audit {
            action: "job.cancel",
            permission: Permission::JobCancel,
            key: key.as_str(),
            machine: m.name(),
            target: job.to_string(),
            detail: String::new(),
            origin: origin_of(sample.attachment()),
        },
        cancelled.as_ref().map(|_| ()),
    );
    match cancelled {
        Ok(outcome) => {
            tracing::info!(machine = %m.name(), job, ?outcome, "cancel requested on the bus")
        }
        Err(e) => tracing::warn!(%key, error = %e, "cancel refused"),
    }
}

/// Job keys a machine keeps declared: the running job and the latest ones accepted behind it.
const DECLARED_JOB_KEYS: usize = 4;

/// Publishes one machine's job events, and keeps the latest event of its recent jobs.
///
/// Each job has its own key. A put on a key no one declared makes zenoh's router match it
/// against every subscriber and queryable of the session, on every put (a job sends up to four
/// progress events a second): 11 % of the gateway's CPU samples at 256 busy links, 4.7 % with
/// declared keys (docs/performance.md, "A thousand links: the gateway alone"). A declared key
/// keeps its route cached, so the keys of the last few jobs stay declared; a key dropped from
/// the list is undeclared.
#[derive(Default)]
pub(crate) struct JobEventPublisher {
    declared: std::collections::VecDeque<(String, KeyExpr<'static>)>,
}

impl JobEventPublisher {
    pub(super) async fn publish(
        &mut self,
        ctx: &RouteContext,
        machine: &Machine,
        event: &pb::JobEvent,
    ) {
        machine.remember_job_event(event, RECENT_JOBS);
        let key = match self.key(ctx, machine, &event.job_id).await {
            Ok(key) => key,
            Err(e) => {
                tracing::warn!(machine = %machine.name(), job = %event.job_id, error = %e, "a job event has no valid key");
                return;
            }
        };
        let sent = ctx
            .session
            .put(key, event.encode_to_vec())
            .encoding(encoding::<pb::JobEvent>())
            .congestion_control(Published::JobEvent.congestion())
            .priority(Published::JobEvent.priority())
            .await;
        if let Err(e) = sent {
            tracing::warn!(machine = %machine.name(), job = %event.job_id, error = %e, "publishing a job event failed");
        }
    }

    /// The job's key, declared if zenoh takes the declaration (else put as it is).
    async fn key(
        &mut self,
        ctx: &RouteContext,
        machine: &Machine,
        job: &str,
    ) -> zenoh::Result<KeyExpr<'static>> {
        if let Some((_, key)) = self.declared.iter().find(|(id, _)| id == job) {
            return Ok(key.clone());
        }
        let key = ctx.keys.job_events(machine.name(), job);
        let declared = match ctx.session.declare_keyexpr(key.clone()).await {
            Ok(k) => k,
            Err(e) => {
                tracing::debug!(%key, error = %e, "job key not declared");
                return KeyExpr::try_from(key);
            }
        };
        if self.declared.len() >= DECLARED_JOB_KEYS {
            // Dropping the last clone of a declared key undeclares it.
            self.declared.pop_front();
        }
        self.declared.push_back((job.to_string(), declared.clone()));
        Ok(declared)
    }
}
