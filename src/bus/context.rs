//! What every route shares (`RouteContext`): the session, the cell's keys, its machines and
//! program library, and the bound on requests that may wait. Also the typed errors a request
//! is refused with (`RequestError`, coded in `cellgate_core::codes`) and the reply helpers.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use prost::Message;
use tokio::sync::Semaphore;
use zenoh::Session;
use zenoh::bytes::Encoding;
use zenoh::handlers::FifoChannelHandler;
use zenoh::key_expr::KeyExpr;
use zenoh::pubsub::Subscriber;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Locality, Sample};

use super::audit::{Audit, Auditor};
use super::error::BusError;
use super::keys::{CellKey, CellKeys, MachineLeaf, intersects};
use super::machine::Machine;
use super::payload::{BusMessage, encoding, error_reply};
use super::published::{MachinePublication, Published};
use crate::history::History;
use crate::jobs::JobError;
use crate::library::{LibraryError, ProgramLibrary};
use cellgate_core::bounds::{self, BoundError, Bounded, Limits};
use cellgate_core::codes::BusCode;
use cellgate_core::fanuc::Protocol;
use cellgate_core::pb;
use zenoh::pubsub::Publisher;

/// Requests whose reply may wait (a job whose program is scanned or fetched, a DI read, a DO
/// output, a library transfer) that run at once, over every [`Pool`]. The bound keeps a flood
/// of requests from becoming an unbounded number of tasks.
pub const MAX_WAITING_REQUESTS: usize = 256;

/// Programs fetched from keys at once (`JobRequest.key`): each may hold `programs.max_inline`.
pub const MAX_FETCHES: usize = 2;

/// How long a write's answer waits for its audit record to be committed.
pub(crate) const ANSWER_AUDIT_WAIT: std::time::Duration = std::time::Duration::from_secs(2);

/// The share of the request slots a kind of request runs in, so that a flood of one kind (a
/// dashboard's DI reads) never takes the slots of another (the MES's submits): with its pool
/// full, a request is answered `ERROR_CODE_BUSY` at once while the other pools serve on.
/// zenoh's stable API does not tell the gateway which client sent a query, so the shares are
/// per kind of request, which is also per permission.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Pool {
    /// Status, DI, the queue, job events, PLC status and tag reads: `status.read`.
    Read,
    /// Job submits and cancels: `job.submit`, `job.cancel`.
    Jobs,
    /// Program reads: each holds a whole program in memory, so few at once
    /// (`programs.max_size` each).
    ProgramRead,
    /// Program stores and removals: `program.write`.
    ProgramWrite,
    /// DO outputs: `io.do`.
    Io,
    /// PLC memory, tag writes, transfers.
    Plc,
    /// G05 stream requests.
    G05,
    /// Controls of simulated machines: `sim.control`.
    Sim,
}

impl Pool {
    /// Every pool.
    pub const ALL: [Pool; 8] = [
        Pool::Read,
        Pool::Jobs,
        Pool::ProgramRead,
        Pool::ProgramWrite,
        Pool::Io,
        Pool::Plc,
        Pool::G05,
        Pool::Sim,
    ];

    /// Requests of this kind that run at once; together [`MAX_WAITING_REQUESTS`].
    pub const fn slots(self) -> usize {
        match self {
            Pool::Read => 88,
            Pool::Jobs => 64,
            Pool::ProgramRead => 4,
            Pool::ProgramWrite => 12,
            Pool::Io => 32,
            Pool::Plc => 32,
            Pool::G05 => 16,
            Pool::Sim => 8,
        }
    }

    fn index(self) -> usize {
        match self {
            Pool::Read => 0,
            Pool::Jobs => 1,
            Pool::ProgramRead => 2,
            Pool::ProgramWrite => 3,
            Pool::Io => 4,
            Pool::Plc => 5,
            Pool::G05 => 6,
            Pool::Sim => 7,
        }
    }

    pub(crate) fn name(self) -> &'static str {
        match self {
            Pool::Read => "reads",
            Pool::Jobs => "job requests",
            Pool::ProgramRead => "program reads",
            Pool::ProgramWrite => "program stores",
            Pool::Io => "DO outputs",
            Pool::Plc => "PLC requests",
            Pool::G05 => "G05 requests",
            Pool::Sim => "simulation controls",
        }
    }
}

const _: () = {
    let mut sum = 0;
    let mut i = 0;
    while i < Pool::ALL.len() {
        sum += Pool::ALL[i].slots();
        i += 1;
    }
    assert!(sum == MAX_WAITING_REQUESTS);
};

/// What a route's context gives the loop that serves it.
pub(crate) trait Routed: Clone + Send + Sync + 'static {
    fn route(&self) -> &RouteContext;
}

impl Routed for RouteContext {
    fn route(&self) -> &RouteContext {
        self
    }
}

/// A value the routes read while a reload may replace it: a read takes the whole value as it
/// stands, never a half-changed one; a request that holds it finishes with it.
pub(crate) struct Live<T>(Arc<std::sync::RwLock<Arc<T>>>);

impl<T> Clone for Live<T> {
    fn clone(&self) -> Self {
        Live(Arc::clone(&self.0))
    }
}

impl<T: Default> Default for Live<T> {
    fn default() -> Self {
        Live::new(T::default())
    }
}

impl<T> Live<T> {
    pub(crate) fn new(value: T) -> Self {
        Live(Arc::new(std::sync::RwLock::new(Arc::new(value))))
    }

    /// The value as it stands now.
    pub(crate) fn now(&self) -> Arc<T> {
        Arc::clone(&self.0.read().unwrap_or_else(|p| p.into_inner()))
    }

    /// Replaces the value for every holder of this `Live`.
    pub(crate) fn set(&self, value: T) {
        *self.0.write().unwrap_or_else(|p| p.into_inner()) = Arc::new(value);
    }

    /// Replaces the value with what `f` makes of the current one.
    pub(crate) fn update(&self, f: impl FnOnce(&T) -> T) {
        let mut guard = self.0.write().unwrap_or_else(|p| p.into_inner());
        *guard = Arc::new(f(&guard));
    }
}

impl<T: Clone> Live<BTreeMap<String, T>> {
    /// Serves `value` as `name` (a machine or PLC added, or its link replaced).
    pub(crate) fn insert(&self, name: &str, value: T) {
        self.update(|m| {
            let mut m = m.clone();
            m.insert(name.to_string(), value);
            m
        });
    }

    /// No longer serves `name`: the routes refuse it from the next request on.
    pub(crate) fn remove(&self, name: &str) {
        self.update(|m| {
            let mut m = m.clone();
            m.remove(name);
            m
        });
    }
}

/// The cell's machines by name.
pub(crate) type Machines = BTreeMap<String, Arc<Machine>>;

/// What the routes of one cell share.
#[derive(Clone)]
pub(crate) struct RouteContext {
    pub session: Session,
    pub keys: Arc<CellKeys>,
    /// Changed by a reload: a machine added or removed.
    pub machines: Live<Machines>,
    pub library: ProgramLibrary,
    /// Largest inline program a `JobRequest` may carry (`programs.max_inline`); a program
    /// fetched from a key too.
    pub max_inline: u64,
    /// Key prefixes a `JobRequest.key` may name (`programs.fetch_prefixes`).
    pub fetch_prefixes: Arc<[String]>,
    /// Fetches of a job's program at once: each may hold `max_inline` bytes.
    pub fetches: Arc<Semaphore>,
    /// The cell's history and audit trail (disabled: records nothing).
    pub history: History,
    /// Who may have sent a write, for the audit.
    pub auditor: Arc<Auditor>,
    /// The cell's link and tag names, for questions about records that name them.
    pub names: Live<CellNames>,
    slots: Arc<[Arc<Semaphore>]>,
}

/// The names a question about the cell's records may use: its machines and PLC links, and
/// its tags as `PLC/TAG`. Empty when not known (then names are not checked).
#[derive(Debug, Default)]
pub(crate) struct CellNames {
    pub links: std::collections::BTreeSet<String>,
    pub tags: std::collections::BTreeSet<String>,
}

impl CellNames {
    pub(crate) fn of(config: &cellgate_core::config::CellConfig) -> Self {
        CellNames {
            links: config
                .machines
                .iter()
                .map(|m| m.name.clone())
                .chain(config.plcs.iter().map(|p| p.name.clone()))
                .collect(),
            tags: config
                .plcs
                .iter()
                .flat_map(|p| p.tags.iter().map(move |t| format!("{}/{}", p.name, t.name)))
                .collect(),
        }
    }

    /// The first of `asked` that is not one of `known`, with the known ones for the message.
    pub(crate) fn unknown<'a>(
        known: &std::collections::BTreeSet<String>,
        asked: impl IntoIterator<Item = &'a String>,
    ) -> Option<(&'a String, String)> {
        if known.is_empty() {
            return None;
        }
        let unknown = asked.into_iter().find(|n| !known.contains(*n))?;
        let list: Vec<&str> = known.iter().map(String::as_str).collect();
        Some((unknown, list.join(", ")))
    }
}

/// What a request's key names.
pub(crate) enum Target {
    /// One machine of the cell.
    One(Arc<Machine>),
    /// A concrete key naming a machine the cell does not have.
    Unknown(String),
    /// A key with wildcards.
    Wild,
}

/// Why a request was refused. The message says what to do; [`BusCode`] gives its code.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub(crate) enum RequestError {
    #[error("cell {cell} has no machine {machine:?}; its machines are: {known}")]
    UnknownMachine {
        cell: String,
        machine: String,
        known: String,
    },
    /// A request that names one machine sent to a wildcard key.
    #[error("a {what} goes to one machine's key, {expected}{}", not_to(.got))]
    OneMachine {
        what: &'static str,
        expected: String,
        got: Option<String>,
    },
    #[error("machine {machine}: {error}")]
    Payload { machine: String, error: BoundError },
    #[error("machine {machine}: {what}")]
    Invalid { machine: String, what: String },
    /// A request sent to a key that does not take it (a write on a read key).
    #[error("{0}")]
    WrongKey(String),
    /// A put whose encoding names another message than the key takes.
    #[error(transparent)]
    Encoding(#[from] super::payload::WrongEncoding),
    /// A question about records that names a machine or PLC the cell lacks.
    #[error("{0}")]
    UnknownLink(String),
    /// A question about records that names a tag the cell lacks.
    #[error("{0}")]
    UnknownTag(String),
    /// The cell file does not allow what the request asks for.
    #[error("{0}")]
    NotPermitted(String),
    #[error("machine {machine}: JobRequest.key {key:?} is not a key expression: {error}")]
    BadKey {
        machine: String,
        key: String,
        error: zenoh::Error,
    },
    #[error("machine {machine}: fetching the program from {key}: {why}")]
    FetchFailed {
        machine: String,
        key: String,
        why: String,
    },
    #[error(
        "machine {machine} speaks Protocol {}: only the Protocol A family has DI/DO (RDI, SDI, SDO; §4.4.1)",
        .protocol.name()
    )]
    NoIo { machine: String, protocol: Protocol },
    #[error("machine {machine}: the link is not initialised, so RDI/SDO cannot be sent now")]
    NotInitialised { machine: String },
    #[error("machine {machine}: the link is not running")]
    NotRunning { machine: String },
    #[error("machine {machine}: no {answer} within {} s (§4.4.1)", .waited.as_secs())]
    NoAnswer {
        machine: String,
        answer: &'static str,
        waited: Duration,
    },
    #[error("machine {machine} has no job {job:?} (the last {kept} jobs are kept)")]
    NoSuchJob {
        machine: String,
        job: String,
        kept: usize,
    },
    #[error("the gateway is serving {max} {what} already; try again later")]
    Busy { what: &'static str, max: usize },
    #[error(transparent)]
    Link(#[from] crate::link::driver::LinkError),
    #[error(transparent)]
    G05(#[from] crate::link::g05::G05Error),
    #[error(transparent)]
    Batch(#[from] cellgate_core::fanuc::g05::stream::BatchError),
    #[error("machine {machine} has no G05 stream {stream:?} open (only the last one is kept)")]
    NoSuchStream { machine: String, stream: String },
    #[error("program {name}: {error}")]
    ProgramWritePayload { name: String, error: BoundError },
    #[error("program {name}: the ProgramWrite names no operation: set store or remove")]
    ProgramWriteEmpty { name: String },
    #[error(transparent)]
    Job(#[from] JobError),
    #[error(transparent)]
    Library(#[from] LibraryError),
    #[error(transparent)]
    History(#[from] crate::history::HistoryError),
    #[error("{0}")]
    Param(#[from] cellgate_core::history::ParamError),
    #[error("program {name}: {error}")]
    NotText {
        name: String,
        error: cellgate_core::program::diff::NotText,
    },
    /// A program the library lacks, with the names near it (or what the library has).
    #[error("{error}{hint}")]
    NoProgram { error: String, hint: String },
    /// A simulation control for a machine that is not simulated.
    #[error(
        "machine {machine} is not simulated (its transport is not kind = \"sim\"): the \
         sim controls drive simulated machines only"
    )]
    NotSimulated { machine: String },
    /// A simulation control the simulated machine cannot take now, or ever.
    #[error("machine {machine}: {why}")]
    SimRefused {
        machine: String,
        why: String,
        code: pb::ErrorCode,
    },
}

fn not_to(got: &Option<String>) -> String {
    got.as_ref()
        .map(|g| format!(", not to {g}"))
        .unwrap_or_default()
}

impl BusCode for RequestError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            RequestError::UnknownMachine { .. } | RequestError::UnknownLink(_) => {
                pb::ErrorCode::UnknownMachine
            }
            RequestError::UnknownTag(_) => pb::ErrorCode::NotFound,
            RequestError::OneMachine { .. }
            | RequestError::Payload { .. }
            | RequestError::Invalid { .. }
            | RequestError::WrongKey(_)
            | RequestError::Encoding(_)
            | RequestError::BadKey { .. }
            | RequestError::ProgramWritePayload { .. }
            | RequestError::ProgramWriteEmpty { .. } => pb::ErrorCode::InvalidRequest,
            RequestError::FetchFailed { .. } => pb::ErrorCode::FetchFailed,
            RequestError::NoIo { .. } => pb::ErrorCode::NotSupported,
            RequestError::NotInitialised { .. } | RequestError::NotRunning { .. } => {
                pb::ErrorCode::Unavailable
            }
            RequestError::NoAnswer { .. } => pb::ErrorCode::LinkFailed,
            RequestError::NoSuchJob { .. }
            | RequestError::NoSuchStream { .. }
            | RequestError::NoProgram { .. } => pb::ErrorCode::NotFound,
            RequestError::G05(e) => e.code(),
            RequestError::Busy { .. } => pb::ErrorCode::Busy,
            RequestError::NotPermitted(_) => pb::ErrorCode::NotPermitted,
            RequestError::Link(e) => e.code(),
            RequestError::Batch(e) => e.code(),
            RequestError::Job(e) => e.code(),
            RequestError::Library(e) => e.code(),
            RequestError::History(e) => e.code(),
            RequestError::Param(e) => e.code(),
            RequestError::NotText { .. } => pb::ErrorCode::InvalidRequest,
            RequestError::NotSimulated { .. } => pb::ErrorCode::NotSupported,
            RequestError::SimRefused { code, .. } => *code,
        }
    }
}

impl RouteContext {
    pub(crate) fn new(
        session: Session,
        keys: Arc<CellKeys>,
        machines: Live<Machines>,
        library: ProgramLibrary,
        max_inline: u64,
    ) -> Self {
        RouteContext {
            session,
            keys,
            machines,
            library,
            max_inline,
            fetch_prefixes: Arc::new([]),
            fetches: Arc::new(Semaphore::new(MAX_FETCHES)),
            history: History::disabled(),
            auditor: Arc::default(),
            names: Live::default(),
            slots: Pool::ALL
                .iter()
                .map(|p| Arc::new(Semaphore::new(p.slots())))
                .collect(),
        }
    }

    /// The bounds of request messages in this cell.
    pub(crate) fn limits(&self) -> Limits {
        Limits {
            max_inline: self.max_inline,
            max_program: self.library.max_size(),
        }
    }

    /// `bytes` as the request message `M`, within its bounds ([`cellgate_core::bounds`]).
    pub(crate) fn decode<M: Bounded>(
        &self,
        machine: &str,
        bytes: &[u8],
    ) -> Result<M, RequestError> {
        bounds::decode(bytes, &self.limits()).map_err(|error| RequestError::Payload {
            machine: machine.to_string(),
            error,
        })
    }

    /// The same context, recording in `history` and auditing with the cell's roles.
    pub(crate) fn with_history(mut self, history: History, auditor: Auditor) -> Self {
        self.history = history;
        self.auditor = Arc::new(auditor);
        self
    }

    /// Records an audited write and its outcome.
    pub(crate) fn audit<E: BusCode + std::fmt::Display>(
        &self,
        a: Audit<'_>,
        outcome: Result<(), &E>,
    ) {
        self.auditor.record(&self.history, a, outcome);
    }

    /// [`Self::audit`] for a write whose asker waits for the answer: a write taken is on disk
    /// in the audit trail before the answer says so (at most [`ANSWER_AUDIT_WAIT`] later: a
    /// store that cannot write keeps the record in memory), so that a `kill -9` never loses
    /// the record of a write a client was told was done.
    pub(crate) async fn audit_answered<E: BusCode + std::fmt::Display>(
        &self,
        a: Audit<'_>,
        outcome: Result<(), &E>,
    ) {
        let taken = outcome.is_ok();
        self.audit(a, outcome);
        if taken {
            self.history.committed(ANSWER_AUDIT_WAIT).await;
        }
    }

    /// Records a console's note, which stands for `count` refusals ([`Auditor::record_note`]).
    pub(crate) fn audit_note<E: BusCode + std::fmt::Display>(
        &self,
        a: Audit<'_>,
        outcome: Result<(), &E>,
        count: u32,
    ) {
        self.auditor.record_note(&self.history, a, outcome, count);
    }

    /// The same context, knowing the cell's link and tag names.
    pub(crate) fn with_names(mut self, names: CellNames) -> Self {
        self.names = Live::new(names);
        self
    }

    /// The same context, allowing `JobRequest.key` under these prefixes.
    pub(crate) fn with_fetch_prefixes(mut self, prefixes: &[String]) -> Self {
        self.fetch_prefixes = prefixes
            .iter()
            .map(|p| p.trim_end_matches('/').to_string())
            .collect();
        self
    }

    pub(crate) async fn queryable(
        &self,
        key: String,
    ) -> Result<Queryable<FifoChannelHandler<Query>>, BusError> {
        self.session
            .declare_queryable(key.clone())
            .await
            .map_err(|source| BusError::Declare {
                what: "queryable",
                key,
                source,
            })
    }

    pub(crate) async fn subscriber(
        &self,
        key: String,
        origin: Locality,
    ) -> Result<Subscriber<FifoChannelHandler<Sample>>, BusError> {
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

    /// A slot of `pool`, if one is free; the request it runs gives it back when dropped.
    pub(crate) fn slot(&self, pool: Pool) -> Option<tokio::sync::OwnedSemaphorePermit> {
        let semaphore = self.slots.get(pool.index())?;
        Arc::clone(semaphore).try_acquire_owned().ok()
    }

    /// The machine a concrete key names.
    pub(crate) fn target(&self, key: &KeyExpr<'_>) -> Target {
        if key.is_wild() {
            return Target::Wild;
        }
        let machine = match self.keys.parse(key.as_str()) {
            Some(
                CellKey::Machine { machine }
                | CellKey::Leaf { machine, .. }
                | CellKey::JobEvents { machine, .. }
                | CellKey::JobCancel { machine, .. }
                | CellKey::G05 { machine, .. },
            ) => machine,
            _ => return Target::Wild,
        };
        match self.machines.now().get(machine) {
            Some(m) => Target::One(Arc::clone(m)),
            None => Target::Unknown(machine.to_string()),
        }
    }

    pub(crate) fn unknown_machine(&self, machine: &str) -> RequestError {
        let machines = self.machines.now();
        let names: Vec<&str> = machines.keys().map(String::as_str).collect();
        RequestError::UnknownMachine {
            cell: self.keys.root().to_string(),
            machine: machine.to_string(),
            known: if names.is_empty() {
                "none".to_string()
            } else {
                names.join(", ")
            },
        }
    }

    /// `e` as a refusal says it: a program the library lacks, with the names near it or,
    /// when they are few, the ones it has, as an unknown machine is refused with the
    /// machines. `may_list`: whoever asked may read the library's names (a read of the
    /// library, or a cell without roles); else `e` as it is.
    pub(crate) async fn naming_programs(&self, e: RequestError, may_list: bool) -> RequestError {
        let missing = match &e {
            RequestError::Library(LibraryError::NotFound { name })
            | RequestError::Job(JobError::Library {
                error: LibraryError::NotFound { name },
                ..
            }) if may_list => name.clone(),
            _ => return e,
        };
        let Ok(programs) = self.library.list().await else {
            return e;
        };
        let known: Vec<&str> = programs.iter().map(|p| p.name.as_str()).collect();
        RequestError::NoProgram {
            error: e.to_string(),
            hint: cellgate_core::near::hint(&missing, &known, "programs", "`cellgate program ls`"),
        }
    }

    /// Whether the cell has no roles, so that any client may learn the library's names.
    pub(crate) fn open_cell(&self) -> bool {
        self.auditor.open()
    }

    /// The one machine a request for `leaf` (a `what`) names, or why it names none.
    pub(crate) fn one_machine(
        &self,
        q: &Query,
        leaf: MachineLeaf,
        what: &'static str,
    ) -> Result<Arc<Machine>, RequestError> {
        match self.target(q.key_expr()) {
            Target::One(m) => Ok(m),
            Target::Unknown(name) => Err(self.unknown_machine(&name)),
            Target::Wild => Err(RequestError::OneMachine {
                what,
                expected: self.keys.leaf("<machine>", leaf),
                got: Some(q.key_expr().to_string()),
            }),
        }
    }

    /// Answers a concrete key of a machine the cell lacks with `UNKNOWN_MACHINE`; leaves a
    /// wildcard that matched nothing unanswered, as zenoh does.
    pub(crate) async fn unmatched(&self, q: &Query) {
        if let Target::Unknown(m) = self.target(q.key_expr()) {
            reply_err(q, &self.unknown_machine(&m)).await;
        }
    }

    /// The machines whose `leaf` key the query takes in, with that key.
    pub(crate) fn matching(&self, q: &Query, leaf: MachineLeaf) -> Vec<(String, Arc<Machine>)> {
        self.machines
            .now()
            .values()
            .map(|m| (self.keys.leaf(m.name(), leaf), Arc::clone(m)))
            .filter(|(key, _)| intersects(q.key_expr(), key))
            .collect()
    }
}

pub(crate) async fn reply<M: BusMessage>(q: &Query, key: String, message: &M) {
    let sent = q
        .reply(key, message.encode_to_vec())
        .encoding(encoding::<M>())
        .await;
    if let Err(e) = sent {
        tracing::warn!(selector = %q.selector(), error = %e, "reply failed");
    }
}

pub(crate) async fn reply_bytes(q: &Query, bytes: Vec<u8>, enc: Encoding) {
    let sent = q.reply(q.key_expr().to_string(), bytes).encoding(enc).await;
    if let Err(e) = sent {
        tracing::warn!(key = %q.key_expr(), error = %e, "reply failed");
    }
}

/// Answers `q` with an `ErrorReply` carrying the error's code and message.
pub(crate) async fn reply_err(q: &Query, error: &(impl BusCode + std::fmt::Display)) {
    let code = error.code();
    let message = error.to_string();
    tracing::info!(selector = %q.selector(), ?code, %message, "request refused");
    let mut payload = error_reply(code, message);
    payload.sta = error.sta().map(u32::from);
    let sent = q
        .reply_err(payload.encode_to_vec())
        .encoding(encoding::<pb::ErrorReply>())
        .await;
    if let Err(e) = sent {
        tracing::warn!(selector = %q.selector(), error = %e, "error reply failed");
    }
}

/// Publishes one event the gateway tells of what it did for a request (a library change, a
/// DO output) on `key`, reliably, with the requester's origin as the attachment, so that a
/// watcher sees who asked. A failure is logged: the request itself was done.
pub(crate) async fn publish_event<M: BusMessage>(
    ctx: &RouteContext,
    what: Published,
    key: &str,
    message: &M,
    origin: Option<&pb::RequestOrigin>,
) {
    let mut put = ctx
        .session
        .put(key, message.encode_to_vec())
        .encoding(encoding::<M>())
        .congestion_control(what.congestion())
        .priority(what.priority());
    if let Some(o) = origin {
        put = put.attachment(o.encode_to_vec());
    }
    if let Err(e) = put.await {
        tracing::warn!(%key, error = %e, "publishing an event failed");
    }
}

/// One of a machine's publishers: messages `M` on `P/C/machine/M/<leaf>`, with the QoS of
/// its row of [`PUBLICATIONS`](super::published::PUBLICATIONS). Undeclared when dropped.
pub(crate) struct MachinePublisher<M> {
    publisher: Publisher<'static>,
    message: std::marker::PhantomData<fn(&M)>,
}

impl<M: BusMessage> MachinePublisher<M> {
    pub(crate) async fn declare(
        ctx: &RouteContext,
        machine: &str,
        what: MachinePublication,
    ) -> Result<Self, BusError> {
        let key = ctx.keys.leaf(machine, what.leaf());
        let what = what.published();
        let publisher = ctx
            .session
            .declare_publisher(key.clone())
            .encoding(encoding::<M>())
            .congestion_control(what.congestion())
            .priority(what.priority())
            .await
            .map_err(|source| BusError::Declare {
                what: "publisher",
                key,
                source,
            })?;
        Ok(MachinePublisher {
            publisher,
            message: std::marker::PhantomData,
        })
    }

    pub(crate) async fn publish(&self, message: &M) {
        if let Err(e) = self.publisher.put(message.encode_to_vec()).await {
            tracing::warn!(key = %self.publisher.key_expr(), error = %e, "publishing failed");
        }
    }
}
