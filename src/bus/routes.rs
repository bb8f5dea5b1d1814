//! The cell on the bus: every machine's link, job queue, DI/DO and alarms, and the cell's
//! program library, served under `P/C/` ([`keys`](super::keys)).
//!
//! One queryable or subscriber per route serves every machine (`P/C/machine/*/status`, ...),
//! as the zenoh bridges do: a request for a machine the cell does not have still reaches the
//! gateway, which answers `ERROR_CODE_UNKNOWN_MACHINE` instead of leaving the client to time
//! out. Requests that wait (a job whose program is scanned or fetched, a DI read, a DO
//! output) run in their own tasks, so one slow request never holds up another.
//!
//! Status: published on change with `CongestionControl::Drop` and answered on `get`. A late
//! joiner gets the current value with a `get` (or subscribes, then gets). zenoh-ext's
//! `AdvancedPublisher` would replay a cache to late subscribers, but it is not a dependency
//! and its API is marked unstable in zenoh 1.x; a queryable holding the last value gives the
//! same with the stable API.
//!
//! QoS: job requests, DO commands and program transfers are queries or puts the client
//! sends (a query is `Block` by default, and its replies follow it); job events and alarms
//! are published reliable with `Block`; status and DI telemetry with `Drop`, since the next
//! value supersedes a lost one.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use prost::Message;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use zenoh::Session;
use zenoh::bytes::Encoding;
use zenoh::key_expr::KeyExpr;
use zenoh::query::Query;
use zenoh::sample::{Locality, Sample, SampleKind};

use super::BusError;
use super::keys::{CellKey, CellKeys, MachineLeaf, intersects, is_plain_chunk};
use super::machine::{self, Machine};
use super::payload::{BusMessage, encoding, error_reply};
use super::punch::PunchSettings;
use crate::codes::BusCode;
use crate::config::{CellConfig, MachineConfig};
use crate::jobs::library::ProgramLibrary;
use crate::jobs::source::ProgramInput;
use crate::jobs::{self, JobSubmission};
use crate::link::driver::{LinkCommand, LinkEvent, LinkHandle};
use crate::pb;

/// How long fetching a job's program from a `key` may take.
pub const FETCH_TIMEOUT: Duration = Duration::from_secs(5);

/// A machine of the cell and its running link, as the gateway hands them to [`serve`].
#[derive(Debug, Clone)]
pub struct MachineLink {
    pub config: MachineConfig,
    pub link: LinkHandle,
}

/// Serves the cell's machines and program library on `session` until `shutdown` is
/// cancelled, then undeclares everything: routes first, then each machine's job manager
/// (jobs still waiting are reported cancelled, the active one failed), then each machine's
/// publishers and liveliness token. The links themselves are left running: they belong to
/// the caller.
///
/// Each link is subscribed to before this function first awaits, so call it as soon as the
/// links are spawned. Must run on a multi-thread Tokio runtime (zenoh's requirement).
pub async fn serve(
    session: &Session,
    config: &CellConfig,
    machines: Vec<MachineLink>,
    shutdown: CancellationToken,
) -> Result<(), BusError> {
    let keys = Arc::new(CellKeys::new(&config.bus.prefix, &config.cell)?);
    let library = ProgramLibrary::new(&config.programs.dir, config.programs.max_size);
    let jobs_stop = shutdown.child_token();
    let machines_stop = CancellationToken::new();

    // Subscribed before any await, so no event of a link that is already running is missed.
    let mut started = Vec::new();
    let mut by_name = BTreeMap::new();
    let mut job_tasks = JoinSet::new();
    for MachineLink { config: mc, link } in machines {
        if by_name.contains_key(&mc.name) {
            tracing::error!(machine = %mc.name, "machine given twice; serving the first only");
            continue;
        }
        let link_events = link.subscribe();
        let rules = mc.program_rules(library.max_size());
        let (jobs, task) = jobs::spawn(
            &mc.name,
            rules,
            library.clone(),
            link.clone(),
            jobs_stop.clone(),
        );
        job_tasks.spawn(async move {
            let _ = task.await;
        });
        let job_events = jobs.subscribe();
        let snapshot = jobs.snapshot();
        let machine = Arc::new(Machine::new(mc, link, jobs));
        by_name.insert(machine.name().to_string(), machine.clone());
        started.push((machine, link_events, job_events, snapshot));
    }
    let routes = Routes {
        session: session.clone(),
        keys: keys.clone(),
        machines: Arc::new(by_name),
        library: library.clone(),
    };

    let mut machine_tasks = JoinSet::new();
    let served = async {
        library
            .create_dir()
            .await
            .map_err(|source| BusError::ProgramDir {
                dir: library.dir().to_path_buf(),
                source,
            })?;
        for (machine, link_events, job_events, snapshot) in started {
            let publishers = machine::declare_publishers(session, &keys, machine.name())
                .await
                .map_err(|(key, source)| BusError::Declare {
                    what: "publisher",
                    key,
                    source,
                })?;
            machine_tasks.spawn(machine::run(
                machine,
                session.clone(),
                keys.clone(),
                publishers,
                link_events,
                job_events,
                snapshot,
                PunchSettings::from_config(&config.programs),
                machines_stop.clone(),
            ));
        }
        routes.run(shutdown.clone()).await
    }
    .await;

    // Whatever happened, stop in order: job managers report their last events, then the
    // machine tasks publish them and withdraw.
    jobs_stop.cancel();
    while job_tasks.join_next().await.is_some() {}
    machines_stop.cancel();
    while machine_tasks.join_next().await.is_some() {}
    served
}

#[derive(Clone)]
struct Routes {
    session: Session,
    keys: Arc<CellKeys>,
    machines: Arc<BTreeMap<String, Arc<Machine>>>,
    library: ProgramLibrary,
}

/// What a request's key names.
enum Target<'a> {
    /// One machine of the cell.
    One(&'a Arc<Machine>),
    /// A concrete key naming a machine the cell does not have.
    Unknown(String),
    /// A key with wildcards.
    Wild,
}

impl Routes {
    async fn run(&self, shutdown: CancellationToken) -> Result<(), BusError> {
        let k = &self.keys;
        let q_status = self.queryable(k.any_leaf(MachineLeaf::Status)).await?;
        let q_job = self.queryable(k.any_leaf(MachineLeaf::Job)).await?;
        let q_job_events = self.queryable(k.any_job_events()).await?;
        let q_di = self.queryable(k.any_leaf(MachineLeaf::Di)).await?;
        let q_do = self.queryable(k.any_leaf(MachineLeaf::Do)).await?;
        let q_program = self.queryable(k.any_program()).await?;
        // Only other sessions cancel jobs and command DO; this session's own job events
        // need not come back to it.
        let s_job_events = self
            .subscriber(k.any_job_events(), Locality::Remote)
            .await?;
        let s_do = self
            .subscriber(k.any_leaf(MachineLeaf::Do), Locality::Any)
            .await?;
        let s_program = self.subscriber(k.any_program(), Locality::Any).await?;
        tracing::info!(root = %k.root(), machines = self.machines.len(), "cell routes declared");

        let mut tasks = JoinSet::new();
        loop {
            tokio::select! {
                () = shutdown.cancelled() => break,
                q = q_status.recv_async() => match q {
                    Ok(q) => self.status(&q).await,
                    Err(_) => break,
                },
                q = q_job.recv_async() => match q {
                    Ok(q) => { let r = self.clone(); tasks.spawn(async move { r.job(&q).await }); }
                    Err(_) => break,
                },
                q = q_job_events.recv_async() => match q {
                    Ok(q) => self.job_events(&q).await,
                    Err(_) => break,
                },
                q = q_di.recv_async() => match q {
                    Ok(q) => { let r = self.clone(); tasks.spawn(async move { r.di(&q).await }); }
                    Err(_) => break,
                },
                q = q_do.recv_async() => match q {
                    Ok(q) => { let r = self.clone(); tasks.spawn(async move { r.do_query(&q).await }); }
                    Err(_) => break,
                },
                q = q_program.recv_async() => match q {
                    Ok(q) => { let r = self.clone(); tasks.spawn(async move { r.program_query(&q).await }); }
                    Err(_) => break,
                },
                s = s_job_events.recv_async() => match s {
                    Ok(s) => { let r = self.clone(); tasks.spawn(async move { r.job_delete(&s).await }); }
                    Err(_) => break,
                },
                s = s_do.recv_async() => match s {
                    Ok(s) => self.do_put(&s).await,
                    Err(_) => break,
                },
                s = s_program.recv_async() => match s {
                    Ok(s) => { let r = self.clone(); tasks.spawn(async move { r.program_sample(&s).await }); }
                    Err(_) => break,
                },
                Some(_) = tasks.join_next() => {}
            }
        }
        tasks.shutdown().await;
        for (what, r) in [
            ("queryable", q_status.undeclare().await),
            ("queryable", q_job.undeclare().await),
            ("queryable", q_job_events.undeclare().await),
            ("queryable", q_di.undeclare().await),
            ("queryable", q_do.undeclare().await),
            ("queryable", q_program.undeclare().await),
            ("subscriber", s_job_events.undeclare().await),
            ("subscriber", s_do.undeclare().await),
            ("subscriber", s_program.undeclare().await),
        ] {
            if let Err(e) = r {
                tracing::warn!(error = %e, "undeclaring a {what} failed");
            }
        }
        Ok(())
    }

    async fn queryable(
        &self,
        key: String,
    ) -> Result<zenoh::query::Queryable<zenoh::handlers::FifoChannelHandler<Query>>, BusError> {
        self.session
            .declare_queryable(key.clone())
            .await
            .map_err(|source| BusError::Declare {
                what: "queryable",
                key,
                source,
            })
    }

    async fn subscriber(
        &self,
        key: String,
        origin: Locality,
    ) -> Result<zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<Sample>>, BusError>
    {
        self.session
            .declare_subscriber(key.clone())
            .allowed_origin(origin)
            .await
            .map_err(|source| BusError::Declare {
                what: "subscriber",
                key,
                source,
            })
    }

    /// The machine a concrete key names (`machine` being its machine chunk).
    fn target<'a>(&'a self, key: &KeyExpr<'_>) -> Target<'a> {
        if key.is_wild() {
            return Target::Wild;
        }
        let machine = match self.keys.parse(key.as_str()) {
            Some(
                CellKey::Machine { machine }
                | CellKey::Leaf { machine, .. }
                | CellKey::JobEvents { machine, .. },
            ) => machine,
            _ => return Target::Wild,
        };
        match self.machines.get(machine) {
            Some(m) => Target::One(m),
            None => Target::Unknown(machine.to_string()),
        }
    }

    fn unknown_machine_message(&self, machine: &str) -> String {
        let names: Vec<&str> = self.machines.keys().map(String::as_str).collect();
        format!(
            "cell {} has no machine {machine:?}; its machines are: {}",
            self.keys.root(),
            if names.is_empty() {
                "none".to_string()
            } else {
                names.join(", ")
            }
        )
    }

    /// Answers a concrete key of a machine the cell lacks with `UNKNOWN_MACHINE`; leaves a
    /// wildcard that matched nothing unanswered, as zenoh does.
    async fn unmatched(&self, q: &Query) {
        if let Target::Unknown(m) = self.target(q.key_expr()) {
            reply_err(
                q,
                pb::ErrorCode::UnknownMachine,
                self.unknown_machine_message(&m),
            )
            .await;
        }
    }

    /// The machines whose `leaf` key the query takes in, by name.
    fn matching(&self, q: &Query, leaf: MachineLeaf) -> Vec<(String, &Arc<Machine>)> {
        self.machines
            .values()
            .map(|m| (self.keys.leaf(m.name(), leaf), m))
            .filter(|(key, _)| intersects(q.key_expr(), key))
            .collect()
    }

    // ---- status ------------------------------------------------------------------------

    async fn status(&self, q: &Query) {
        let matching = self.matching(q, MachineLeaf::Status);
        if matching.is_empty() {
            return self.unmatched(q).await;
        }
        for (key, m) in matching {
            reply(q, key, &m.status()).await;
        }
    }

    // ---- jobs --------------------------------------------------------------------------

    async fn job(&self, q: &Query) {
        let Some(payload) = q.payload() else {
            // No payload: the queue of every machine asked for.
            let matching = self.matching(q, MachineLeaf::Job);
            if matching.is_empty() {
                return self.unmatched(q).await;
            }
            for (key, m) in matching {
                match m.jobs.queue().await {
                    Ok(queue) => reply(q, key, &queue).await,
                    Err(e) => reply_err(q, e.code(), e.to_string()).await,
                }
            }
            return;
        };
        let m = match self.target(q.key_expr()) {
            Target::One(m) => m.clone(),
            Target::Unknown(name) => {
                let msg = self.unknown_machine_message(&name);
                return reply_err(q, pb::ErrorCode::UnknownMachine, msg).await;
            }
            Target::Wild => {
                return reply_err(
                    q,
                    pb::ErrorCode::InvalidRequest,
                    format!(
                        "a JobRequest goes to one machine's key, {}, not to {}",
                        self.keys.leaf("<machine>", MachineLeaf::Job),
                        q.key_expr()
                    ),
                )
                .await;
            }
        };
        let request = match pb::JobRequest::decode(payload.to_bytes().as_ref()) {
            Ok(r) => r,
            Err(e) => {
                return reply_err(
                    q,
                    pb::ErrorCode::InvalidRequest,
                    format!(
                        "machine {}: the payload is not a cellgate.v1.JobRequest: {e}",
                        m.name()
                    ),
                )
                .await;
            }
        };
        let input = match request.program {
            None => {
                return reply_err(
                    q,
                    pb::ErrorCode::InvalidRequest,
                    format!(
                        "machine {}: the JobRequest names no program: set one of inline, \
                         library or key",
                        m.name()
                    ),
                )
                .await;
            }
            Some(pb::job_request::Program::Inline(bytes)) => ProgramInput::Inline(bytes.into()),
            Some(pb::job_request::Program::Library(name)) => ProgramInput::Library(name),
            Some(pb::job_request::Program::Key(key)) => match self.fetch(m.name(), &key).await {
                Ok(bytes) => ProgramInput::Fetched { key, bytes },
                Err((code, message)) => return reply_err(q, code, message).await,
            },
        };
        let submission = JobSubmission {
            input,
            name: request.name,
            priority: request.priority,
            append_eor: request.append_eor,
        };
        match m.jobs.submit(submission).await {
            Ok(accepted) => reply(q, q.key_expr().to_string(), &accepted).await,
            Err(e) => reply_err(q, e.code(), e.to_string()).await,
        }
    }

    /// Fetches a program from `key` with one `get`: the first reply's payload.
    async fn fetch(&self, machine: &str, key: &str) -> Result<Bytes, (pb::ErrorCode, String)> {
        let ke = KeyExpr::try_from(key.to_string()).map_err(|e| {
            (
                pb::ErrorCode::InvalidRequest,
                format!("machine {machine}: JobRequest.key {key:?} is not a key expression: {e}"),
            )
        })?;
        let failed = |why: String| {
            (
                pb::ErrorCode::FetchFailed,
                format!("machine {machine}: fetching the program from {key}: {why}"),
            )
        };
        let replies = self
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

    /// The last event of every recent job the query takes in.
    async fn job_events(&self, q: &Query) {
        let mut replies = Vec::new();
        for m in self.machines.values() {
            let view = m.view();
            for event in &view.recent_jobs {
                let key = self.keys.job_events(m.name(), &event.job_id);
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
        match self.keys.parse(q.key_expr().as_str()) {
            Some(CellKey::JobEvents { machine, job }) if !q.key_expr().is_wild() => {
                if self.machines.contains_key(machine) {
                    let msg = format!(
                        "machine {machine} has no job {job:?} (the last {} jobs are kept)",
                        machine::RECENT_JOBS
                    );
                    reply_err(q, pb::ErrorCode::NotFound, msg).await;
                } else {
                    self.unmatched(q).await;
                }
            }
            _ => {}
        }
    }

    /// A delete on `P/C/machine/M/job/ID` cancels the job.
    async fn job_delete(&self, sample: &Sample) {
        if sample.kind() != SampleKind::Delete {
            return;
        }
        let key = sample.key_expr();
        let (Some(CellKey::JobEvents { job, .. }), Target::One(m)) =
            (self.keys.parse(key.as_str()), self.target(key))
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

    // ---- DI / DO -----------------------------------------------------------------------

    fn io_refusal(m: &Machine) -> Option<(pb::ErrorCode, String)> {
        if !m.config.protocol.is_a_family() {
            return Some((
                pb::ErrorCode::NotSupported,
                format!(
                    "machine {} speaks Protocol {}: only the Protocol A family has DI/DO \
                     (RDI, SDI, SDO; §4.4.1)",
                    m.name(),
                    m.config.protocol.name()
                ),
            ));
        }
        if !m.link_up() {
            return Some((
                pb::ErrorCode::Unavailable,
                format!(
                    "machine {}: the link is not initialised, so RDI/SDO cannot be sent now",
                    m.name()
                ),
            ));
        }
        None
    }

    /// A `get` on `di`: a concrete key reads the DI image now (RDI → SDI); a wildcard
    /// answers the last image read of each machine that has one.
    async fn di(&self, q: &Query) {
        let m = match self.target(q.key_expr()) {
            Target::One(m) => m.clone(),
            Target::Unknown(_) => return self.unmatched(q).await,
            Target::Wild => {
                for (key, m) in self.matching(q, MachineLeaf::Di) {
                    let last = m.view().last_di.clone();
                    if let Some(di) = last {
                        reply(q, key, &di).await;
                    }
                }
                return;
            }
        };
        if let Some((code, message)) = Self::io_refusal(&m) {
            return reply_err(q, code, message).await;
        }
        let mut events = m.link.subscribe();
        if m.link.send(LinkCommand::ReadDi).await.is_err() {
            let msg = format!("machine {}: the link is not running", m.name());
            return reply_err(q, pb::ErrorCode::Unavailable, msg).await;
        }
        let timeout = m.exchange_timeout();
        let read = tokio::time::timeout(timeout, async {
            loop {
                match events.recv().await {
                    Ok(LinkEvent::Di { value }) => return Some(value),
                    Ok(LinkEvent::Stopped { .. })
                    | Err(tokio::sync::broadcast::error::RecvError::Closed) => return None,
                    _ => {}
                }
            }
        })
        .await;
        match read {
            Ok(Some(value)) => {
                let di = pb::DiImage {
                    machine: m.name().to_string(),
                    value: u32::from(value),
                    unix_ms: jobs::unix_ms(),
                };
                reply(q, q.key_expr().to_string(), &di).await;
            }
            _ => {
                let msg = format!(
                    "machine {}: no SDI answered RDI within {} s (§4.4.1)",
                    m.name(),
                    timeout.as_secs()
                );
                reply_err(q, pb::ErrorCode::LinkFailed, msg).await;
            }
        }
    }

    /// Checks a DO command; returns `(value, mask)`.
    fn do_command(m: &Machine, payload: &[u8]) -> Result<(u8, u8), (pb::ErrorCode, String)> {
        let invalid = |why: String| {
            (
                pb::ErrorCode::InvalidRequest,
                format!("machine {}: {why}", m.name()),
            )
        };
        let cmd = pb::DoCommand::decode(payload)
            .map_err(|e| invalid(format!("the payload is not a cellgate.v1.DoCommand: {e}")))?;
        let value = u8::try_from(cmd.value)
            .map_err(|_| invalid(format!("DO value {} is not 8 bits (0..=255)", cmd.value)))?;
        let mask = u8::try_from(cmd.mask.unwrap_or(0xFF))
            .map_err(|_| invalid(format!("DO mask {:?} is not 8 bits (0..=255)", cmd.mask)))?;
        Ok((value, mask))
    }

    /// A put on `do`: outputs the DO image (SDO).
    async fn do_put(&self, sample: &Sample) {
        if sample.kind() != SampleKind::Put {
            return;
        }
        let key = sample.key_expr();
        let m = match self.target(key) {
            Target::One(m) => m.clone(),
            Target::Unknown(name) => {
                return tracing::warn!(%key, "DO refused: {}", self.unknown_machine_message(&name));
            }
            Target::Wild => return tracing::warn!(%key, "DO refused: name one machine"),
        };
        if !m.config.protocol.is_a_family() {
            return tracing::warn!(%key, "DO refused: Protocol B has no SDO (§4.4.1)");
        }
        match Self::do_command(&m, sample.payload().to_bytes().as_ref()) {
            Ok((value, mask)) => {
                if m.link
                    .send(LinkCommand::SetDo { value, mask })
                    .await
                    .is_err()
                {
                    tracing::warn!(%key, "DO refused: the link is not running");
                }
            }
            Err((_, message)) => tracing::warn!(%key, "DO refused: {message}"),
        }
    }

    /// A `get` with a `DoCommand` on `do`: outputs the DO image and answers the status
    /// once the SDO went out.
    async fn do_query(&self, q: &Query) {
        let m = match self.target(q.key_expr()) {
            Target::One(m) => m.clone(),
            Target::Unknown(_) => return self.unmatched(q).await,
            // A wildcard get without payload (e.g. on `P/C/**`) browses; `do` has nothing
            // to show.
            Target::Wild if q.payload().is_none() => return,
            Target::Wild => {
                let msg = format!(
                    "a DoCommand goes to one machine's key, {}",
                    self.keys.leaf("<machine>", MachineLeaf::Do)
                );
                return reply_err(q, pb::ErrorCode::InvalidRequest, msg).await;
            }
        };
        let Some(payload) = q.payload() else {
            let msg = format!("machine {}: a get on do carries a DoCommand", m.name());
            return reply_err(q, pb::ErrorCode::InvalidRequest, msg).await;
        };
        let (value, mask) = match Self::do_command(&m, payload.to_bytes().as_ref()) {
            Ok(c) => c,
            Err((code, message)) => return reply_err(q, code, message).await,
        };
        if let Some((code, message)) = Self::io_refusal(&m) {
            return reply_err(q, code, message).await;
        }
        let mut events = m.link.subscribe();
        if m.link
            .send(LinkCommand::SetDo { value, mask })
            .await
            .is_err()
        {
            let msg = format!("machine {}: the link is not running", m.name());
            return reply_err(q, pb::ErrorCode::Unavailable, msg).await;
        }
        let timeout = m.exchange_timeout();
        let done = tokio::time::timeout(timeout, async {
            loop {
                match events.recv().await {
                    Ok(LinkEvent::Do { value: out }) if out & mask == value & mask => return true,
                    Ok(LinkEvent::Stopped { .. })
                    | Err(tokio::sync::broadcast::error::RecvError::Closed) => return false,
                    _ => {}
                }
            }
        })
        .await;
        if done == Ok(true) {
            // The machine's task folds the same event into the view; make sure the reply
            // shows it even if that task has not run yet.
            let mut status = m.status();
            let old = status.do_image.unwrap_or(0);
            let image = (u8::try_from(old).unwrap_or(0) & !mask) | (value & mask);
            status.do_image = Some(u32::from(image));
            reply(q, q.key_expr().to_string(), &status).await;
        } else {
            let msg = format!(
                "machine {}: no SDO went out within {} s (§4.4.1)",
                m.name(),
                timeout.as_secs()
            );
            reply_err(q, pb::ErrorCode::LinkFailed, msg).await;
        }
    }

    // ---- program library -----------------------------------------------------------------

    /// A `get` on `P/C/program/NAME` answers the program; on a wildcard, a `ProgramInfo`
    /// per matching program.
    async fn program_query(&self, q: &Query) {
        if q.key_expr().is_wild() {
            match self.library.list().await {
                Ok(entries) => {
                    for e in entries {
                        let key = self.keys.program(&e.name);
                        if intersects(q.key_expr(), &key) {
                            let info = pb::ProgramInfo {
                                name: e.name,
                                size: e.size,
                                modified_unix_ms: e.modified_unix_ms,
                            };
                            reply(q, key, &info).await;
                        }
                    }
                }
                Err(e) => reply_err(q, e.code(), e.to_string()).await,
            }
            return;
        }
        let Some(CellKey::Program { name }) = self.keys.parse(q.key_expr().as_str()) else {
            return;
        };
        match self.library.read(name).await {
            Ok(program) => {
                let sent = q
                    .reply(q.key_expr().to_string(), program)
                    .encoding(Encoding::APPLICATION_OCTET_STREAM)
                    .await;
                if let Err(e) = sent {
                    tracing::warn!(key = %q.key_expr(), error = %e, "program reply failed");
                }
            }
            Err(e) => reply_err(q, e.code(), e.to_string()).await,
        }
    }

    /// A put on `P/C/program/NAME` stores the program; a delete removes it.
    async fn program_sample(&self, sample: &Sample) {
        let key = sample.key_expr();
        if key.is_wild() {
            return tracing::warn!(%key, "program library: name one program, without wildcards");
        }
        let Some(CellKey::Program { name }) = self.keys.parse(key.as_str()) else {
            return;
        };
        let result = match sample.kind() {
            SampleKind::Put => {
                let program = sample.payload().to_bytes();
                self.library.store(name, &program).await.map(|e| {
                    tracing::info!(program = %e.name, size = e.size, "program stored");
                })
            }
            SampleKind::Delete => self.library.remove(name).await.map(|()| {
                tracing::info!(program = %name, "program removed");
            }),
        };
        if let Err(e) = result {
            tracing::warn!(%key, error = %e, "program library request refused");
        }
    }
}

/// An error reply's text: the `ErrorReply` message if it is one, else the payload as text.
fn describe_error(payload: &zenoh::bytes::ZBytes, encoding: &Encoding) -> String {
    let bytes = payload.to_bytes();
    if super::payload::schema_of(encoding).as_deref() == Some(pb::ErrorReply::SCHEMA)
        && let Ok(e) = pb::ErrorReply::decode(bytes.as_ref())
    {
        return e.message;
    }
    String::from_utf8_lossy(&bytes).into_owned()
}

async fn reply<M: BusMessage>(q: &Query, key: String, message: &M) {
    let sent = q
        .reply(key, message.encode_to_vec())
        .encoding(encoding::<M>())
        .await;
    if let Err(e) = sent {
        tracing::warn!(selector = %q.selector(), error = %e, "reply failed");
    }
}

async fn reply_err(q: &Query, code: pb::ErrorCode, message: String) {
    tracing::info!(selector = %q.selector(), ?code, %message, "request refused");
    let sent = q
        .reply_err(error_reply(code, message).encode_to_vec())
        .encoding(encoding::<pb::ErrorReply>())
        .await;
    if let Err(e) = sent {
        tracing::warn!(selector = %q.selector(), error = %e, "error reply failed");
    }
}
