//! Every queryable and subscriber the routes serve, one [`Row`] each: its key (built in
//! [`keys`](super::keys)), what arrives on it (queries, or puts and deletes from which
//! sessions), the [`Pool`] its requests run in, the permission of the cell file's roles
//! that lets a client reach it ([`acl`](super::acl) takes the keys of its rules from here,
//! and its tests check each row), and the handler. A new endpoint is a row here and a
//! handler in its route's module.
//!
//! A [`Route`] is a group of rows served by one task ([`serve_route`]): a request answered
//! on a route's loop (`pool` `None`, a cheap answer from memory) never waits behind
//! another route's. The G05 streams' batches are served in order on their route's loop.

use std::future::Future;
use std::sync::Arc;

use futures::future::BoxFuture;
use futures::stream::BoxStream;
use futures::{FutureExt as _, StreamExt as _};
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use zenoh::handlers::FifoChannelHandler;
use zenoh::key_expr::{KeyExpr, keyexpr};
use zenoh::pubsub::Subscriber;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Locality, Sample};

use super::context::{Pool, RequestError, RouteContext, Routed, reply_err};
use super::error::BusError;
use super::keys::{CellKeys, G05Part, MachineLeaf, PlcArea};
use super::payload::BusMessage;
use super::route_g05::G05Context;
use super::route_plc::PlcContext;
use super::write::{Done, Write, WriteRow};
use super::{
    route_g05, route_history, route_io, route_job, route_misdirected, route_plc, route_program,
    route_sim, route_status, route_tag,
};
use cellgate_core::codes::BusCode;
use cellgate_core::config::Permission;
use cellgate_core::pb;

/// What arrives on a row's key.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Arrives {
    /// Gets: a queryable.
    Queries,
    /// Puts and deletes from sessions of this locality: a subscriber.
    Samples(Locality),
    /// A write's own key: gets with its payload (a queryable) and, where the write takes them,
    /// puts from sessions of this locality (a subscriber), served alike
    /// ([`write`](super::write)).
    Writes(Option<Locality>),
}

/// One queryable or subscriber and what serves it.
pub(crate) struct Row<C> {
    pub(crate) key: String,
    pub(crate) arrives: Arrives,
    /// `None`: answered on the route's loop itself; else run in a slot of the pool.
    pub(crate) pool: Option<Pool>,
    /// A write row's puts: `None` answered on the route's loop itself, else in the pool's
    /// slots (its gets run in `pool`).
    put_pool: Option<Pool>,
    /// The permission whose rules let a client send what arrives here; `None` for keys no
    /// role is meant to send it to (the misdirected writes).
    pub(crate) permission: Option<Permission>,
    handle: Handler<C>,
}

/// A handler as the route modules write it: an async fn of the context and the query or
/// sample, both borrowed. A trait of its own because the future borrows the arguments, for
/// whatever lifetime they have, which a plain `Fn(&C, &I) -> Fut` bound cannot say.
pub(crate) trait Serve<'a, C: 'a, I: 'a>: Send + Sync + 'static {
    type Fut: Future<Output = ()> + Send + 'a;
    fn serve(&self, ctx: &'a C, item: &'a I) -> Self::Fut;
}

impl<'a, C: 'a, I: 'a, F, Fut> Serve<'a, C, I> for F
where
    F: Fn(&'a C, &'a I) -> Fut + Send + Sync + 'static,
    Fut: Future<Output = ()> + Send + 'a,
{
    type Fut = Fut;
    fn serve(&self, ctx: &'a C, item: &'a I) -> Fut {
        self(ctx, item)
    }
}

impl<C: Send + Sync + 'static> Row<C> {
    /// Gets on `key`, each served by `f`.
    fn query<F>(key: String, pool: Option<Pool>, permission: Option<Permission>, f: F) -> Self
    where
        F: for<'a> Serve<'a, C, Query>,
    {
        let f = Arc::new(f);
        Row {
            key,
            arrives: Arrives::Queries,
            pool,
            put_pool: None,
            permission,
            handle: Arc::new(move |c, i| {
                let f = Arc::clone(&f);
                async move {
                    if let Incoming::Query(q) = i {
                        f.serve(&c, &q).await;
                    }
                }
                .boxed()
            }),
        }
    }

    /// Puts and deletes on `key` from `origin`, each served by `f`.
    fn samples<F>(
        key: String,
        origin: Locality,
        pool: Option<Pool>,
        permission: Option<Permission>,
        f: F,
    ) -> Self
    where
        F: for<'a> Serve<'a, C, Sample>,
    {
        let f = Arc::new(f);
        Row {
            key,
            arrives: Arrives::Samples(origin),
            pool,
            put_pool: None,
            permission,
            handle: Arc::new(move |c, i| {
                let f = Arc::clone(&f);
                async move {
                    if let Incoming::Sample(s) = i {
                        f.serve(&c, &s).await;
                    }
                }
                .boxed()
            }),
        }
    }
}

/// A write handler as the route modules write it: an async fn of the borrowed context and
/// the [`Write`], telling what it did ([`Done`]).
pub(crate) trait Writes<'a, C: 'a, M, E>: Send + Sync + 'static {
    type Fut: Future<Output = Done<M, E>> + Send + 'a;
    fn write(&self, ctx: &'a C, w: Write) -> Self::Fut;
}

impl<'a, C: 'a, M, E, F, Fut> Writes<'a, C, M, E> for F
where
    F: Fn(&'a C, Write) -> Fut + Send + Sync + 'static,
    Fut: Future<Output = Done<M, E>> + Send + 'a,
{
    type Fut = Fut;
    fn write(&self, ctx: &'a C, w: Write) -> Fut {
        self(ctx, w)
    }
}

impl<C: Routed> Row<C> {
    /// A write's own `key`: gets (in `pool`) and puts from `origin` (in `put_pool`; `None`:
    /// gets only) alike served by `f`, which answers with `M` or refuses with `E`; `row` says
    /// the write's permission, the message a put carries and whether a delete is a write.
    fn write<M, E, F>(
        key: String,
        origin: Option<Locality>,
        (pool, put_pool): (Option<Pool>, Option<Pool>),
        row: WriteRow,
        f: F,
    ) -> Self
    where
        F: for<'a> Writes<'a, C, M, E>,
        M: BusMessage + Send + 'static,
        E: BusCode + std::fmt::Display + Send + Sync + 'static,
    {
        let f = Arc::new(f);
        Row {
            key,
            arrives: Arrives::Writes(origin),
            pool,
            put_pool,
            permission: Some(row.permission),
            handle: Arc::new(move |c: C, i| {
                let f = Arc::clone(&f);
                async move {
                    match i {
                        Incoming::Query(q) => row.query(c.route(), &q, |w| f.write(&c, w)).await,
                        Incoming::Sample(s) => row.sample(c.route(), &s, |w| f.write(&c, w)).await,
                        Incoming::Ended => {}
                    }
                }
                .boxed()
            }),
        }
    }
}

/// Rows served together by one task.
pub(crate) struct Route<C> {
    pub(crate) rows: Vec<Row<C>>,
    /// Each machine's key of this leaf declared too, for as long as the route runs (see
    /// [`declare_keys`]).
    hold: Option<MachineLeaf>,
}

impl<C> Route<C> {
    fn new(rows: Vec<Row<C>>) -> Self {
        Route { rows, hold: None }
    }

    fn holding(mut self, leaf: MachineLeaf) -> Self {
        self.hold = Some(leaf);
        self
    }
}

/// The routes of the cell's machines, library and records, on [`RouteContext`].
pub(crate) fn cell(keys: &CellKeys) -> Vec<Route<RouteContext>> {
    use MachineLeaf as L;
    use Permission as P;
    let leaf = |l| keys.any_leaf(l);
    let read = Some(Pool::Read);
    vec![
        // A status is at hand, so the answer never waits.
        Route::new(vec![Row::query(
            leaf(L::Status),
            None,
            Some(P::StatusRead),
            route_status::status_get,
        )]),
        // Jobs: submits, the queue, a job's latest event, cancels.
        Route::new(vec![
            Row::query(
                leaf(L::Submit),
                Some(Pool::Jobs),
                Some(P::JobSubmit),
                route_job::job_submit,
            ),
            Row::query(
                leaf(L::Job),
                read,
                Some(P::StatusRead),
                route_job::job_queue,
            ),
            Row::query(
                keys.any_job_events(),
                None,
                Some(P::StatusRead),
                route_job::job_events,
            ),
            Row::query(
                keys.any_job_cancel(),
                Some(Pool::Jobs),
                Some(P::JobCancel),
                route_job::job_cancel,
            ),
            // Only other sessions cancel jobs; this session's own job events need not
            // come back to it.
            Row::samples(
                keys.any_job_events(),
                Locality::Remote,
                Some(Pool::Jobs),
                Some(P::JobCancel),
                route_job::job_delete,
            ),
        ]),
        // DI reads, DO outputs; each machine's `do` key held declared, so that a DO put's
        // route stays cached (docs/performance.md).
        Route::new(vec![
            Row::query(leaf(L::Di), read, Some(P::StatusRead), route_io::di_get),
            // A put without waiting: a flood of puts is refused past the link's command queue.
            Row::write(
                leaf(L::Do),
                Some(Locality::Any),
                (Some(Pool::Io), None),
                WriteRow::of(P::IoDo).expecting::<pb::DoCommand>(),
                route_io::do_write,
            ),
        ])
        .holding(L::Do),
        // The program library: reads, revisions, comparisons, writes, releases.
        Route::new(vec![
            Row::query(
                keys.any_program(),
                Some(Pool::ProgramRead),
                Some(P::ProgramRead),
                route_program::program_read,
            ),
            Row::query(
                keys.program_revisions("*"),
                read,
                Some(P::ProgramRead),
                route_program::program_revisions,
            ),
            Row::query(
                keys.program_revision("*", "*"),
                Some(Pool::ProgramRead),
                Some(P::ProgramRead),
                route_program::program_revision,
            ),
            Row::query(
                keys.program_diff("*"),
                Some(Pool::ProgramRead),
                Some(P::ProgramRead),
                route_program::program_diff,
            ),
            // A get's payload is a `ProgramWrite`, a put's the program itself.
            Row::write(
                keys.any_program_write(),
                Some(Locality::Any),
                (Some(Pool::ProgramWrite), Some(Pool::ProgramWrite)),
                WriteRow::of(P::ProgramWrite).deleting(),
                route_program::program_write,
            ),
            Row::write(
                keys.program_release("*"),
                None,
                (Some(Pool::ProgramWrite), None),
                WriteRow::of(P::ProgramRelease),
                route_program::program_release,
            ),
        ]),
        // The cell's records: history, audit trail, notes, utilisation.
        Route::new(vec![
            Row::query(
                keys.history(),
                read,
                Some(P::HistoryRead),
                route_history::history_page,
            ),
            Row::query(
                keys.audit(),
                read,
                Some(P::AuditRead),
                route_history::audit_page,
            ),
            Row::query(
                keys.audit_note(),
                read,
                Some(P::AuditNote),
                route_history::note,
            ),
            Row::query(
                keys.utilisation(),
                read,
                Some(P::HistoryRead),
                route_history::utilisation,
            ),
        ]),
        // Puts and deletes on read keys, from other sessions: the gateway publishes on some
        // of them itself.
        Route::new(
            route_misdirected::read_keys(keys)
                .into_iter()
                .map(|key| {
                    Row::samples(key, Locality::Remote, read, None, route_misdirected::answer)
                })
                .collect(),
        ),
    ]
}

/// The controls of simulated machines, declared with the first one.
pub(crate) fn sim(keys: &CellKeys) -> Route<RouteContext> {
    Route::new(vec![Row::query(
        keys.any_sim(),
        Some(Pool::Sim),
        Some(Permission::SimControl),
        route_sim::sim_query,
    )])
}

/// The G05 streams (§9), on [`G05Context`]: opening, batches in order on the route's loop,
/// status, cancel. Reading a stream is part of producing one: every row is `g05.stream`'s.
pub(crate) fn g05(keys: &CellKeys) -> Route<G05Context> {
    let p = Some(Permission::G05Stream);
    let status = keys.any_g05(G05Part::Status);
    let blocks = keys.any_g05(G05Part::Blocks);
    Route::new(vec![
        Row::query(
            keys.any_leaf(MachineLeaf::G05),
            None,
            p,
            route_g05::open_get,
        ),
        Row::query(status.clone(), None, p, route_g05::status_get),
        Row::write(
            blocks,
            Some(Locality::Any),
            (None, None),
            WriteRow::of(Permission::G05Stream).expecting::<pb::G05Batch>(),
            route_g05::blocks_write,
        ),
        // Only another session cancels a stream; this one publishes its status there.
        Row::samples(
            status,
            Locality::Remote,
            Some(Pool::G05),
            p,
            route_g05::status_delete,
        ),
    ])
}

/// The routes of the cell's PLC links, on [`PlcContext`].
pub(crate) fn plc(keys: &CellKeys) -> Vec<Route<PlcContext>> {
    use Permission as P;
    let plc = Some(Pool::Plc);
    vec![
        // PLC memory, transfers, messages, status.
        Route::new(vec![
            // Reads; a get on a write's own key (`…/write`) is the write row's.
            Row::query(
                keys.any_plc_area(PlcArea::Mem),
                plc,
                Some(P::PlcMem),
                route_plc::mem_query,
            ),
            Row::query(
                keys.any_plc_status(),
                Some(Pool::Read),
                Some(P::StatusRead),
                route_plc::status_query,
            ),
            Row::write(
                keys.any_plc_mem_write(),
                Some(Locality::Remote),
                (plc, plc),
                WriteRow::of(P::PlcMem).expecting::<pb::PlcWrite>(),
                route_plc::mem_write,
            ),
            Row::write(
                keys.any_plc_transfer_send(),
                Some(Locality::Remote),
                (plc, plc),
                WriteRow::of(P::PlcTransfer).expecting::<pb::PlcTransfer>(),
                route_plc::transfer_write,
            ),
            Row::write(
                keys.any_plc_message_send(),
                Some(Locality::Remote),
                (plc, plc),
                WriteRow::of(P::PlcTransfer).expecting::<pb::PlcMessage>(),
                route_plc::message_write,
            ),
        ]),
        // PLC tags: reads and writes.
        Route::new(vec![
            Row::query(
                keys.any_plc_tag(),
                Some(Pool::Read),
                Some(P::StatusRead),
                route_tag::tag_query,
            ),
            Row::write(
                keys.any_plc_tag_set(),
                Some(Locality::Remote),
                (plc, plc),
                WriteRow::of(P::PlcTag).expecting::<pb::TagWrite>(),
                route_tag::tag_write,
            ),
        ]),
    ]
}

/// The keys of every row `p` grants, in the table's order, each once, and none that another of
/// them includes (a write key inside an area read and written): the keys the access-control
/// rules ([`acl`](super::acl)) give `p` on the routes.
pub(crate) fn granted(keys: &CellKeys, p: Permission) -> Vec<String> {
    fn of<C>(routes: Vec<Route<C>>, p: Permission) -> impl Iterator<Item = String> {
        routes
            .into_iter()
            .flat_map(|r| r.rows)
            .filter(move |r| r.permission == Some(p))
            .map(|r| r.key)
    }
    let mut found: Vec<String> = Vec::new();
    for key in of(cell(keys), p)
        .chain(of(vec![g05(keys)], p))
        .chain(of(vec![sim(keys)], p))
        .chain(of(plc(keys), p))
    {
        if !found.contains(&key) {
            found.push(key);
        }
    }
    let includes = |a: &str, b: &str| {
        keyexpr::new(a).is_ok_and(|a| keyexpr::new(b).is_ok_and(|b| a.includes(b)))
    };
    found
        .iter()
        .filter(|k| !found.iter().any(|o| o != *k && includes(o, k)))
        .cloned()
        .collect()
}

/// What arrives on a route's queryable or subscriber.
enum Incoming {
    Query(Query),
    Sample(Sample),
    /// The queryable or subscriber ended: the session closed under the route.
    Ended,
}

type Handler<C> = Arc<dyn Fn(C, Incoming) -> BoxFuture<'static, ()> + Send + Sync>;

/// One queryable or subscriber declared, and what serves what arrives on it.
struct Endpoint<C> {
    incoming: BoxStream<'static, Incoming>,
    pool: Option<Pool>,
    handle: Handler<C>,
}

fn queries(queryable: Queryable<FifoChannelHandler<Query>>) -> BoxStream<'static, Incoming> {
    futures::stream::unfold(Some(queryable), |q| async move {
        let q = q?;
        Some(match q.recv_async().await {
            Ok(query) => (Incoming::Query(query), Some(q)),
            Err(_) => (Incoming::Ended, None),
        })
    })
    .boxed()
}

fn samples(subscriber: Subscriber<FifoChannelHandler<Sample>>) -> BoxStream<'static, Incoming> {
    futures::stream::unfold(Some(subscriber), |s| async move {
        let s = s?;
        Some(match s.recv_async().await {
            Ok(sample) => (Incoming::Sample(sample), Some(s)),
            Err(_) => (Incoming::Ended, None),
        })
    })
    .boxed()
}

/// A route's queryables and subscribers, declared. Undeclared when dropped.
pub(crate) struct Declared<C> {
    endpoints: Vec<Endpoint<C>>,
    /// Held for as long as the route runs.
    held: Vec<KeyExpr<'static>>,
}

impl<C: Routed> Route<C> {
    /// Declares the route's rows, in order.
    pub(crate) async fn declare(self, ctx: &C) -> Result<Declared<C>, BusError> {
        let route = ctx.route();
        let mut endpoints = Vec::with_capacity(self.rows.len());
        for row in self.rows {
            let incoming = match row.arrives {
                Arrives::Queries => queries(route.queryable(row.key).await?),
                Arrives::Samples(origin) => samples(route.subscriber(row.key, origin).await?),
                Arrives::Writes(origin) => {
                    if let Some(origin) = origin {
                        let puts = samples(route.subscriber(row.key.clone(), origin).await?);
                        endpoints.push(Endpoint {
                            incoming: puts,
                            pool: row.put_pool,
                            handle: Arc::clone(&row.handle),
                        });
                    }
                    queries(route.queryable(row.key).await?)
                }
            };
            endpoints.push(Endpoint {
                incoming,
                pool: row.pool,
                handle: row.handle,
            });
        }
        let held = match self.hold {
            Some(leaf) => declare_keys(route, leaf).await,
            None => Vec::new(),
        };
        Ok(Declared { endpoints, held })
    }
}

/// Declares `routes`, in order; one that cannot be declared undeclares those before it.
pub(crate) async fn declare_all<C: Routed>(
    routes: Vec<Route<C>>,
    ctx: &C,
) -> Result<Vec<Declared<C>>, BusError> {
    let mut declared = Vec::with_capacity(routes.len());
    for route in routes {
        declared.push(route.declare(ctx).await?);
    }
    Ok(declared)
}

impl<C: Routed> Declared<C> {
    /// Serves the route until `stop`, or until the session closes under it.
    pub(crate) async fn run(self, ctx: C, stop: CancellationToken) {
        serve_route(ctx, stop, self.endpoints).await;
        drop(self.held);
    }
}

/// Serves a route's endpoints until `stop`, or until one of them ends (the session closed):
/// every request in a slot of its pool, off the loop, so that one slow querier holds up
/// neither its route nor the others; the requests still running are dropped when it returns.
async fn serve_route<C: Routed>(ctx: C, stop: CancellationToken, endpoints: Vec<Endpoint<C>>) {
    let mut tasks = JoinSet::new();
    let mut handlers = Vec::new();
    let mut streams = Vec::new();
    for (i, e) in endpoints.into_iter().enumerate() {
        handlers.push((e.pool, e.handle));
        streams.push(e.incoming.map(move |item| (i, item)).boxed());
    }
    let mut incoming = futures::stream::select_all(streams);
    loop {
        tokio::select! {
            () = stop.cancelled() => break,
            next = incoming.next() => {
                let Some((i, item)) = next else { break };
                if matches!(item, Incoming::Ended) {
                    break;
                }
                let Some((pool, handle)) = handlers.get(i) else { continue };
                match pool {
                    None => handle(ctx.clone(), item).await,
                    Some(pool) => spawn_in(&mut tasks, *pool, item, handle, ctx.clone()).await,
                }
            }
            Some(_) = tasks.join_next() => {}
        }
    }
    tasks.shutdown().await;
}

/// Runs a request of `pool` off the route's loop, in one of the pool's slots. With every
/// slot of the pool taken a query is answered `ERROR_CODE_BUSY` at once, and a put or
/// delete (which has no answer) is dropped and logged: a flood of requests never becomes
/// an unbounded number of tasks, nor takes the slots of another kind of request.
async fn spawn_in<C: Routed>(
    tasks: &mut JoinSet<()>,
    pool: Pool,
    item: Incoming,
    handle: &Handler<C>,
    ctx: C,
) {
    match ctx.route().slot(pool) {
        Some(slot) => {
            let run = handle(ctx, item);
            tasks.spawn(async move {
                run.await;
                drop(slot);
            });
        }
        None => match item {
            Incoming::Query(q) => {
                reply_err(
                    &q,
                    &RequestError::Busy {
                        what: pool.name(),
                        max: pool.slots(),
                    },
                )
                .await
            }
            Incoming::Sample(s) => tracing::warn!(
                key = %s.key_expr(),
                "request dropped: {} {} are being served already",
                pool.slots(),
                pool.name()
            ),
            Incoming::Ended => {}
        },
    }
}

/// Each machine's `leaf` key declared on the gateway's session, so that zenoh's routing
/// tables hold it and cache its route: a put on a key the gateway's routing tables hold has
/// its route cached there, one that they do not is matched against every declaration of the
/// cell, on every put (a DO put a second on a thousand machines). A key zenoh does not take
/// is left out (its puts are routed all the same, only matched each time).
async fn declare_keys(ctx: &RouteContext, leaf: MachineLeaf) -> Vec<KeyExpr<'static>> {
    let machines = ctx.machines.now();
    let mut keys = Vec::with_capacity(machines.len());
    for name in machines.keys() {
        let key = ctx.keys.leaf(name, leaf);
        match ctx.session.declare_keyexpr(key.clone()).await {
            Ok(k) => keys.push(k),
            Err(e) => tracing::debug!(%key, error = %e, "key not declared"),
        }
    }
    keys
}

#[cfg(test)]
pub(crate) mod tests;
