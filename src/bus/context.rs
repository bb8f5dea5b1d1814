//! What every route shares ([`RouteContext`]): the session, the cell's keys, its machines and
//! program library, and the bound on requests that may wait. Also the typed errors a request
//! is refused with ([`RequestError`], coded in `crate::codes`) and the reply helpers.

use std::collections::BTreeMap;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use prost::Message;
use tokio::sync::Semaphore;
use tokio::task::JoinSet;
use zenoh::Session;
use zenoh::bytes::Encoding;
use zenoh::handlers::FifoChannelHandler;
use zenoh::key_expr::KeyExpr;
use zenoh::pubsub::Subscriber;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Locality, Sample};

use super::BusError;
use super::keys::{CellKey, CellKeys, MachineLeaf, intersects};
use super::machine::Machine;
use super::payload::{BusMessage, encoding, error_reply};
use crate::codes::BusCode;
use crate::fanuc::Protocol;
use crate::jobs::JobError;
use crate::jobs::library::{LibraryError, ProgramLibrary};
use crate::pb;

/// Requests whose reply may wait (a job whose program is scanned or fetched, a DI read, a DO
/// output, a library transfer) that run at once; more wait for a slot. The bound keeps a
/// flood of requests from becoming an unbounded number of tasks.
pub const MAX_WAITING_REQUESTS: usize = 256;

/// What the routes of one cell share.
#[derive(Clone)]
pub(crate) struct RouteContext {
    pub session: Session,
    pub keys: Arc<CellKeys>,
    pub machines: Arc<BTreeMap<String, Arc<Machine>>>,
    pub library: ProgramLibrary,
    /// Largest inline program a `JobRequest` may carry (`programs.max_inline`).
    pub max_inline: u64,
    slots: Arc<Semaphore>,
}

/// What a request's key names.
pub(crate) enum Target<'a> {
    /// One machine of the cell.
    One(&'a Arc<Machine>),
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
    #[error("machine {machine}: the payload is not a cellgate.v1.{message}: {error}")]
    Payload {
        machine: String,
        message: &'static str,
        error: prost::DecodeError,
    },
    #[error("machine {machine}: {what}")]
    Invalid { machine: String, what: String },
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
    #[error("the gateway is serving {max} requests already; try again later")]
    Busy { max: usize },
    #[error(transparent)]
    Link(#[from] crate::link::driver::LinkError),
    #[error(transparent)]
    G05(#[from] crate::g05::G05Error),
    #[error(transparent)]
    Batch(#[from] crate::g05::stream::BatchError),
    #[error("machine {machine} has no G05 stream {stream:?} open (only the last one is kept)")]
    NoSuchStream { machine: String, stream: String },
    #[error("program {name}: the payload is not a cellgate.v1.ProgramWrite: {error}")]
    ProgramWritePayload {
        name: String,
        error: prost::DecodeError,
    },
    #[error("program {name}: the ProgramWrite names no operation: set store or remove")]
    ProgramWriteEmpty { name: String },
    #[error(transparent)]
    Job(#[from] JobError),
    #[error(transparent)]
    Library(#[from] LibraryError),
}

fn not_to(got: &Option<String>) -> String {
    got.as_ref()
        .map(|g| format!(", not to {g}"))
        .unwrap_or_default()
}

impl BusCode for RequestError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            RequestError::UnknownMachine { .. } => pb::ErrorCode::UnknownMachine,
            RequestError::OneMachine { .. }
            | RequestError::Payload { .. }
            | RequestError::Invalid { .. }
            | RequestError::BadKey { .. }
            | RequestError::ProgramWritePayload { .. }
            | RequestError::ProgramWriteEmpty { .. } => pb::ErrorCode::InvalidRequest,
            RequestError::FetchFailed { .. } => pb::ErrorCode::FetchFailed,
            RequestError::NoIo { .. } => pb::ErrorCode::NotSupported,
            RequestError::NotInitialised { .. } | RequestError::NotRunning { .. } => {
                pb::ErrorCode::Unavailable
            }
            RequestError::NoAnswer { .. } => pb::ErrorCode::LinkFailed,
            RequestError::NoSuchJob { .. } | RequestError::NoSuchStream { .. } => {
                pb::ErrorCode::NotFound
            }
            RequestError::G05(e) => e.code(),
            RequestError::Busy { .. } => pb::ErrorCode::Busy,
            RequestError::Link(e) => e.code(),
            RequestError::Batch(e) => e.code(),
            RequestError::Job(e) => e.code(),
            RequestError::Library(e) => e.code(),
        }
    }
}

impl RouteContext {
    pub fn new(
        session: Session,
        keys: Arc<CellKeys>,
        machines: Arc<BTreeMap<String, Arc<Machine>>>,
        library: ProgramLibrary,
        max_inline: u64,
    ) -> Self {
        RouteContext {
            session,
            keys,
            machines,
            library,
            max_inline,
            slots: Arc::new(Semaphore::new(MAX_WAITING_REQUESTS)),
        }
    }

    pub async fn queryable(
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

    pub async fn subscriber(
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

    /// Runs a query that may wait off the route's loop, in one of the
    /// [`MAX_WAITING_REQUESTS`] slots: one slow querier holds up neither its route nor the
    /// others. With every slot taken the query is answered `ERROR_CODE_BUSY` at once: a flood
    /// of requests never becomes an unbounded number of tasks.
    pub async fn spawn_query<F, Fut>(&self, tasks: &mut JoinSet<()>, q: Query, request: F)
    where
        F: FnOnce(Query) -> Fut,
        Fut: Future<Output = ()> + Send + 'static,
    {
        match Arc::clone(&self.slots).try_acquire_owned() {
            Ok(slot) => {
                let run = request(q);
                tasks.spawn(async move {
                    run.await;
                    drop(slot);
                });
            }
            Err(_) => {
                reply_err(
                    &q,
                    &RequestError::Busy {
                        max: MAX_WAITING_REQUESTS,
                    },
                )
                .await
            }
        }
    }

    /// As [`Self::spawn_query`] for a put or delete, which has no answer: with every slot
    /// taken it is dropped, and logged.
    pub fn spawn_sample<F, Fut>(&self, tasks: &mut JoinSet<()>, sample: Sample, request: F)
    where
        F: FnOnce(Sample) -> Fut,
        Fut: Future<Output = ()> + Send + 'static,
    {
        match Arc::clone(&self.slots).try_acquire_owned() {
            Ok(slot) => {
                let run = request(sample);
                tasks.spawn(async move {
                    run.await;
                    drop(slot);
                });
            }
            Err(_) => tracing::warn!(
                key = %sample.key_expr(),
                "request dropped: {MAX_WAITING_REQUESTS} requests are being served already"
            ),
        }
    }

    /// The machine a concrete key names.
    pub fn target(&self, key: &KeyExpr<'_>) -> Target<'_> {
        if key.is_wild() {
            return Target::Wild;
        }
        let machine = match self.keys.parse(key.as_str()) {
            Some(
                CellKey::Machine { machine }
                | CellKey::Leaf { machine, .. }
                | CellKey::JobEvents { machine, .. }
                | CellKey::G05 { machine, .. },
            ) => machine,
            _ => return Target::Wild,
        };
        match self.machines.get(machine) {
            Some(m) => Target::One(m),
            None => Target::Unknown(machine.to_string()),
        }
    }

    pub fn unknown_machine(&self, machine: &str) -> RequestError {
        let names: Vec<&str> = self.machines.keys().map(String::as_str).collect();
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

    /// The one machine a request for `leaf` (a `what`) names, or why it names none.
    pub fn one_machine(
        &self,
        q: &Query,
        leaf: MachineLeaf,
        what: &'static str,
    ) -> Result<Arc<Machine>, RequestError> {
        match self.target(q.key_expr()) {
            Target::One(m) => Ok(Arc::clone(m)),
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
    pub async fn unmatched(&self, q: &Query) {
        if let Target::Unknown(m) = self.target(q.key_expr()) {
            reply_err(q, &self.unknown_machine(&m)).await;
        }
    }

    /// The machines whose `leaf` key the query takes in, with that key.
    pub fn matching(&self, q: &Query, leaf: MachineLeaf) -> Vec<(String, &Arc<Machine>)> {
        self.machines
            .values()
            .map(|m| (self.keys.leaf(m.name(), leaf), m))
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
