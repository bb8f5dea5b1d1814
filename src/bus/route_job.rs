//! Jobs on the bus.
//!
//! - `P/C/machine/M/job`: a get with a `JobRequest` queues a job (`JobAccepted` or
//!   `ErrorReply`); a get without payload answers the machine's `JobQueue`.
//! - `P/C/machine/M/job/ID`: the job's `JobEvent`s, published reliably (QoS `Block`); a get
//!   answers its latest event (the last [`RECENT_JOBS`] jobs are kept); a delete from another
//!   session cancels the job.
//!
//! A submit may wait (a library program is scanned, a `key` program fetched), so it runs off
//! the route's loop, within the context's bound.

use std::time::Duration;

use bytes::Bytes;
use prost::Message;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use zenoh::bytes::Encoding;
use zenoh::handlers::FifoChannelHandler;
use zenoh::key_expr::KeyExpr;
use zenoh::pubsub::Subscriber;
use zenoh::qos::CongestionControl;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Locality, Sample, SampleKind};

use super::BusError;
use super::context::{RequestError, RouteContext, Target, reply, reply_err};
use super::keys::{CellKey, MachineLeaf, intersects, is_plain_chunk};
use super::machine::Machine;
use super::payload::{BusMessage, encoding, schema_of};
use crate::jobs::JobSubmission;
use crate::jobs::blocks::StartAt;
use crate::jobs::source::ProgramInput;
use crate::pb;

/// How long fetching a job's program from a `key` may take.
pub const FETCH_TIMEOUT: Duration = Duration::from_secs(5);

/// Finished jobs whose last event a `get` on `P/C/machine/M/job/*` still answers.
pub const RECENT_JOBS: usize = 256;

/// The job queryables and the cancel subscriber of the cell. Undeclared when dropped.
pub(crate) struct JobRoute {
    requests: Queryable<FifoChannelHandler<Query>>,
    events: Queryable<FifoChannelHandler<Query>>,
    deletes: Subscriber<FifoChannelHandler<Sample>>,
}

impl JobRoute {
    pub async fn declare(ctx: &RouteContext) -> Result<Self, BusError> {
        Ok(JobRoute {
            requests: ctx.queryable(ctx.keys.any_leaf(MachineLeaf::Job)).await?,
            events: ctx.queryable(ctx.keys.any_job_events()).await?,
            // Only other sessions cancel jobs; this session's own job events need not come
            // back to it.
            deletes: ctx
                .subscriber(ctx.keys.any_job_events(), Locality::Remote)
                .await?,
        })
    }

    pub async fn run(self, ctx: RouteContext, stop: CancellationToken) {
        let mut tasks = JoinSet::new();
        loop {
            tokio::select! {
                () = stop.cancelled() => break,
                q = self.requests.recv_async() => match q {
                    Ok(q) => {
                        let c = ctx.clone();
                        ctx.spawn_query(&mut tasks, q, |q| async move { job_request(&c, &q).await }).await;
                    }
                    Err(_) => break,
                },
                q = self.events.recv_async() => match q {
                    Ok(q) => job_events(&ctx, &q).await,
                    Err(_) => break,
                },
                s = self.deletes.recv_async() => match s {
                    Ok(s) => {
                        let c = ctx.clone();
                        ctx.spawn_sample(&mut tasks, s, |s| async move { job_delete(&c, &s).await });
                    }
                    Err(_) => break,
                },
                Some(_) = tasks.join_next() => {}
            }
        }
        tasks.shutdown().await;
    }
}

/// A get on `P/C/machine/M/job`.
async fn job_request(ctx: &RouteContext, q: &Query) {
    let Some(payload) = q.payload() else {
        // No payload: the queue of every machine asked for.
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
        return;
    };
    let payload = payload.to_bytes();
    match submit(ctx, q, &payload).await {
        Ok(accepted) => reply(q, q.key_expr().to_string(), &accepted).await,
        Err(e) => reply_err(q, &e).await,
    }
}

async fn submit(
    ctx: &RouteContext,
    q: &Query,
    payload: &[u8],
) -> Result<pb::JobAccepted, RequestError> {
    let m = ctx.one_machine(q, MachineLeaf::Job, "JobRequest")?;
    let request = pb::JobRequest::decode(payload).map_err(|error| RequestError::Payload {
        machine: m.name().to_string(),
        message: "JobRequest",
        error,
    })?;
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
    };
    Ok(m.jobs.submit(submission).await?)
}

/// Fetches a program from `key` with one `get`: the first reply's payload.
async fn fetch(ctx: &RouteContext, m: &Machine, key: &str) -> Result<Bytes, RequestError> {
    let machine = m.name().to_string();
    let ke = KeyExpr::try_from(key.to_string()).map_err(|error| RequestError::BadKey {
        machine: machine.clone(),
        key: key.to_string(),
        error,
    })?;
    let failed = |why: String| RequestError::FetchFailed {
        machine: machine.clone(),
        key: key.to_string(),
        why,
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
            Ok(sample) => return Ok(Bytes::from(sample.payload().to_bytes().into_owned())),
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
async fn job_events(ctx: &RouteContext, q: &Query) {
    let mut replies = Vec::new();
    for m in ctx.machines.values() {
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
            if ctx.machines.contains_key(machine) {
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

/// A delete on `P/C/machine/M/job/ID` cancels the job.
async fn job_delete(ctx: &RouteContext, sample: &Sample) {
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
    match m.jobs.cancel(job).await {
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
/// declared keys (README, "A thousand links"). A declared key keeps its route cached, so the
/// keys of the last few jobs stay declared; a key dropped from the list is undeclared.
#[derive(Default)]
pub(crate) struct JobEventPublisher {
    declared: std::collections::VecDeque<(String, KeyExpr<'static>)>,
}

impl JobEventPublisher {
    pub async fn publish(&mut self, ctx: &RouteContext, machine: &Machine, event: &pb::JobEvent) {
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
            .congestion_control(CongestionControl::Block)
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
