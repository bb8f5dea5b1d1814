//! `P/C/program/NAME`: the cell's program library.
//!
//! - get → the program's bytes (`application/octet-stream`); a wildcard get → a
//!   `ProgramInfo` per program it takes in;
//! - get with a `ProgramWrite` → stores or removes the program and answers its
//!   `ProgramInfo` once the change is on disk (or an `ErrorReply`): the confirmed form;
//! - put → stores, delete → removes, without an answer (refusals are logged).
//!
//! Library I/O may wait on the disk, so every request runs off the route's loop.

use prost::Message;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use zenoh::bytes::Encoding;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Locality, Sample, SampleKind};

use super::BusError;
use super::context::{RequestError, RouteContext, reply, reply_bytes, reply_err};
use super::keys::{CellKey, intersects};
use crate::jobs::library::ProgramEntry;
use crate::pb;

/// The library queryable and subscriber of the cell. Undeclared when dropped.
pub(crate) struct ProgramRoute {
    queryable: Queryable<FifoChannelHandler<Query>>,
    subscriber: Subscriber<FifoChannelHandler<Sample>>,
}

impl ProgramRoute {
    pub async fn declare(ctx: &RouteContext) -> Result<Self, BusError> {
        Ok(ProgramRoute {
            queryable: ctx.queryable(ctx.keys.any_program()).await?,
            subscriber: ctx
                .subscriber(ctx.keys.any_program(), Locality::Any)
                .await?,
        })
    }

    pub async fn run(self, ctx: RouteContext, stop: CancellationToken) {
        let mut tasks = JoinSet::new();
        loop {
            tokio::select! {
                () = stop.cancelled() => break,
                q = self.queryable.recv_async() => match q {
                    Ok(q) => {
                        let c = ctx.clone();
                        ctx.spawn_query(&mut tasks, q, |q| async move { program_query(&c, &q).await }).await;
                    }
                    Err(_) => break,
                },
                s = self.subscriber.recv_async() => match s {
                    Ok(s) => {
                        let c = ctx.clone();
                        ctx.spawn_sample(&mut tasks, s, |s| async move { program_sample(&c, &s).await });
                    }
                    Err(_) => break,
                },
                Some(_) = tasks.join_next() => {}
            }
        }
        tasks.shutdown().await;
    }
}

fn info(e: ProgramEntry) -> pb::ProgramInfo {
    pb::ProgramInfo {
        name: e.name,
        size: e.size,
        modified_unix_ms: e.modified_unix_ms,
    }
}

async fn program_query(ctx: &RouteContext, q: &Query) {
    if q.key_expr().is_wild() {
        // A wildcard get lists; a write names one program.
        if q.payload().is_some() {
            return;
        }
        match ctx.library.list().await {
            Ok(entries) => {
                for e in entries {
                    let key = ctx.keys.program(&e.name);
                    if intersects(q.key_expr(), &key) {
                        reply(q, key, &info(e)).await;
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
    let Some(payload) = q.payload() else {
        match ctx.library.read(name).await {
            Ok(program) => reply_bytes(q, program, Encoding::APPLICATION_OCTET_STREAM).await,
            Err(e) => reply_err(q, &RequestError::from(e)).await,
        }
        return;
    };
    let write = match pb::ProgramWrite::decode(payload.to_bytes().as_ref()) {
        Ok(w) => w,
        Err(error) => {
            let e = RequestError::ProgramWritePayload {
                name: name.to_string(),
                error,
            };
            return reply_err(q, &e).await;
        }
    };
    let done = match write.op {
        Some(pb::program_write::Op::Store(bytes)) => ctx.library.store(name, &bytes).await,
        Some(pb::program_write::Op::Remove(_)) => ctx.library.remove(name).await,
        None => {
            let e = RequestError::ProgramWriteEmpty {
                name: name.to_string(),
            };
            return reply_err(q, &e).await;
        }
    };
    match done {
        Ok(entry) => {
            tracing::info!(program = %entry.name, size = entry.size, "program library changed");
            reply(q, q.key_expr().to_string(), &info(entry)).await;
        }
        Err(e) => reply_err(q, &RequestError::from(e)).await,
    }
}

/// A put on `P/C/program/NAME` stores the program; a delete removes it.
async fn program_sample(ctx: &RouteContext, sample: &Sample) {
    let key = sample.key_expr();
    if key.is_wild() {
        return tracing::warn!(%key, "program library: name one program, without wildcards");
    }
    let Some(CellKey::Program { name }) = ctx.keys.parse(key.as_str()) else {
        return;
    };
    let result = match sample.kind() {
        SampleKind::Put => {
            let program = sample.payload().to_bytes();
            ctx.library.store(name, &program).await.map(|e| {
                tracing::info!(program = %e.name, size = e.size, "program stored");
            })
        }
        SampleKind::Delete => ctx.library.remove(name).await.map(|e| {
            tracing::info!(program = %e.name, "program removed");
        }),
    };
    if let Err(e) = result {
        tracing::warn!(%key, error = %e, "program library request refused");
    }
}
