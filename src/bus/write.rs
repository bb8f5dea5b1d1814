//! A write's one path. Every write has a key of its own (zenoh's access control sees keys,
//! not payloads), and on it a client may ask two ways: a get with the payload, answered once
//! the write was done, or a put (a delete, where the row takes them), unanswered. One row of
//! the route table ([`Row::write`](super::routes::Row)) declares both; what arrives either
//! way reaches one handler as a [`Write`], and the handler says what it did in a [`Done`].
//! The row then does the rest once for every write: it checks a put's encoding against the
//! message the row expects, records the audit, answers the get or logs the put's refusal.

use std::borrow::Cow;
use std::time::SystemTime;

use zenoh::bytes::{Encoding, ZBytes};
use zenoh::key_expr::KeyExpr;
use zenoh::query::Query;
use zenoh::sample::{Sample, SampleKind};

use super::audit::{Audit, origin_of};
use super::context::{RequestError, RouteContext, reply, reply_err};
use super::payload::{BusMessage, WrongEncoding, schema_of};
use cellgate_core::codes::BusCode;
use cellgate_core::config::Permission;
use cellgate_core::pb;

/// How a write arrived.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Via {
    /// A get: its asker waits for the answer.
    Get,
    /// A put: nobody waits; a refusal is logged.
    Put,
    /// A delete, on rows that take them.
    Delete,
}

/// A write as it arrived, a get's or a put's alike.
pub(crate) struct Write {
    pub(crate) key: KeyExpr<'static>,
    pub(crate) via: Via,
    /// A get's payload, if it carries one; a put's; none for a delete.
    pub(crate) payload: Option<ZBytes>,
    /// What the sender says of itself (its attachment).
    pub(crate) origin: Option<pb::RequestOrigin>,
    /// When the client asked: the put's own time stamp where it set one (so that a delay
    /// counts the bus too), else when it arrived.
    pub(crate) asked: SystemTime,
    /// A put whose encoding names another message than the row's: the handler refuses it
    /// ([`Write::checked`]) where it would act, so that the refusal is audited as the write.
    wrong: Option<WrongEncoding>,
}

impl Write {
    fn of_query(q: &Query) -> Self {
        Write {
            key: q.key_expr().clone().into_owned(),
            via: Via::Get,
            payload: q.payload().cloned(),
            origin: origin_of(q.attachment()),
            asked: SystemTime::now(),
            wrong: None,
        }
    }

    fn of_sample(s: &Sample) -> Self {
        let (via, payload) = match s.kind() {
            SampleKind::Put => (Via::Put, Some(s.payload().clone())),
            SampleKind::Delete => (Via::Delete, None),
        };
        Write {
            key: s.key_expr().clone().into_owned(),
            via,
            payload,
            origin: origin_of(s.attachment()),
            asked: s
                .timestamp()
                .map_or_else(SystemTime::now, |t| t.get_time().to_system_time()),
            wrong: None,
        }
    }

    /// Whether someone waits for the answer (a get).
    pub(crate) fn answered(&self) -> bool {
        self.via == Via::Get
    }

    /// The key, as text.
    pub(crate) fn key(&self) -> &str {
        self.key.as_str()
    }

    /// Whether the payload may be read as the key's message: a put of another encoding may
    /// not (it is refused with a word, never read as the key's message or passed over).
    pub(crate) fn checked(&self) -> Result<(), WrongEncoding> {
        self.wrong.clone().map_or(Ok(()), Err)
    }

    /// The payload's bytes, if there is one.
    pub(crate) fn bytes(&self) -> Option<Cow<'_, [u8]>> {
        self.payload.as_ref().map(ZBytes::to_bytes)
    }
}

/// What the audit records of a write: the row gives the permission, the handler the rest.
pub(crate) struct Audited {
    /// `io.do`, `plc.tag`, `program.store`, ...
    pub(crate) action: &'static str,
    /// The machine or PLC link it acts on (empty for the library).
    pub(crate) machine: String,
    pub(crate) target: String,
    pub(crate) detail: String,
}

/// What a write did.
pub(crate) struct Done<M, E> {
    /// What the audit records; `None` where nothing was asked to be written (a wildcard get
    /// browsing the cell, a check, a key that names no one thing to write).
    pub(crate) audit: Option<Audited>,
    /// The get's answer (`None`: no answer, as a browsing get gets none), or the refusal.
    pub(crate) outcome: Result<Option<M>, E>,
}

impl<M, E> Done<M, E> {
    /// A refusal before anything was asked of a machine: not audited.
    pub(crate) fn refused(e: impl Into<E>) -> Self {
        Done {
            audit: None,
            outcome: Err(e.into()),
        }
    }

    /// Nothing to do and nothing to say (a browsing get, a delete where none is taken).
    pub(crate) fn nothing() -> Self {
        Done {
            audit: None,
            outcome: Ok(None),
        }
    }

    /// A write that has no answer (a put's), audited as `audit`.
    pub(crate) fn taken(audit: Audited, outcome: Result<(), E>) -> Self {
        Done {
            audit: Some(audit),
            outcome: outcome.map(|()| None),
        }
    }

    /// `outcome`, audited as `audit`.
    pub(crate) fn audited(audit: Audited, outcome: Result<M, E>) -> Self {
        Done {
            audit: Some(audit),
            outcome: outcome.map(Some),
        }
    }
}

/// What a write row knows besides its handler.
#[derive(Clone, Copy)]
pub(crate) struct WriteRow {
    pub(crate) permission: Permission,
    /// The message a put carries, checked against the put's encoding; `None`: not a
    /// protobuf message (a program's own bytes), or read whatever the encoding says.
    pub(crate) expects: Option<&'static str>,
    /// Whether a delete is a write here (a program's removal); elsewhere it is ignored.
    pub(crate) deletes: bool,
}

impl WriteRow {
    /// A write that `permission` takes, of any encoding, deletes ignored.
    pub(crate) const fn of(permission: Permission) -> Self {
        WriteRow {
            permission,
            expects: None,
            deletes: false,
        }
    }

    /// The same, its puts carrying `M`.
    pub(crate) const fn expecting<M: BusMessage>(mut self) -> Self {
        self.expects = Some(M::SCHEMA);
        self
    }

    /// The same, a delete a write too.
    pub(crate) const fn deleting(mut self) -> Self {
        self.deletes = true;
        self
    }

    /// The write `item` (a query or a sample), or `None` for what the row ignores (a browsing
    /// get, a delete where deletes are not writes). A put whose encoding is another message's
    /// is marked so ([`Write::checked`]).
    fn arrived<Item: Arrived>(&self, item: &Item) -> Option<Write> {
        let mut w = item.write();
        match w.via {
            // A wildcard get without payload (`P/C/**`) browses the cell: no write of anyone's.
            Via::Get if w.payload.is_none() && w.key.is_wild() => None,
            Via::Delete if !self.deletes => None,
            Via::Put => {
                if let (Some(expected), Some(e)) = (self.expects, item.encoding())
                    && *e != Encoding::default()
                    && schema_of(e).as_deref() != Some(expected)
                {
                    w.wrong = Some(WrongEncoding {
                        key: w.key().to_string(),
                        found: e.to_string(),
                        expected,
                    });
                }
                Some(w)
            }
            Via::Get | Via::Delete => Some(w),
        }
    }

    /// Serves `q` with `serve`: audits what it did once and answers.
    pub(crate) async fn query<M, E, F, Fut>(&self, ctx: &RouteContext, q: &Query, serve: F)
    where
        M: BusMessage,
        E: BusCode + std::fmt::Display + Sync,
        F: FnOnce(Write) -> Fut,
        Fut: Future<Output = Done<M, E>>,
    {
        let Some(w) = self.arrived(q) else {
            return;
        };
        if let Err(e) = ctx.history.audit_writable() {
            return reply_err(q, &RequestError::from(e)).await;
        }
        let key = w.key.clone();
        let done = self.audit(ctx, w, serve).await;
        match done {
            Ok(Some(m)) => reply(q, key.to_string(), &m).await,
            Ok(None) => {}
            Err(e) => reply_err(q, &e).await,
        }
    }

    /// Serves `s` with `serve`: audits what it did once; a refusal is logged, since a put has
    /// nobody to answer.
    pub(crate) async fn sample<M, E, F, Fut>(&self, ctx: &RouteContext, s: &Sample, serve: F)
    where
        M: BusMessage,
        E: BusCode + std::fmt::Display + Sync,
        F: FnOnce(Write) -> Fut,
        Fut: Future<Output = Done<M, E>>,
    {
        let Some(w) = self.arrived(s) else {
            return;
        };
        if let Err(e) = ctx.history.audit_writable() {
            tracing::warn!(key = %s.key_expr(), error = %e, "write refused");
            return;
        }
        let done = self.audit(ctx, w, serve).await;
        if let Err(e) = done {
            tracing::warn!(
                key = %s.key_expr(),
                permission = self.permission.name(),
                error = %e,
                "write refused"
            );
        }
    }

    async fn audit<M, E, F, Fut>(
        &self,
        ctx: &RouteContext,
        w: Write,
        serve: F,
    ) -> Result<Option<M>, E>
    where
        E: BusCode + std::fmt::Display,
        F: FnOnce(Write) -> Fut,
        Fut: Future<Output = Done<M, E>>,
    {
        let key = w.key.clone();
        let origin = w.origin.clone();
        let answered = w.via == Via::Get;
        let done = serve(w).await;
        if let Some(a) = done.audit {
            let a = Audit {
                action: a.action,
                permission: self.permission,
                key: key.as_str(),
                machine: &a.machine,
                target: a.target,
                detail: a.detail,
                origin,
            };
            let outcome = done.outcome.as_ref().map(|_| ());
            if answered {
                ctx.audit_answered(a, outcome).await;
            } else {
                ctx.audit(a, outcome);
            }
        }
        done.outcome
    }
}

/// What a write may arrive as: a query or a sample.
trait Arrived {
    fn write(&self) -> Write;
    /// The encoding it says its payload has (a query's payload says none we check).
    fn encoding(&self) -> Option<&Encoding>;
}

impl Arrived for Query {
    fn write(&self) -> Write {
        Write::of_query(self)
    }
    fn encoding(&self) -> Option<&Encoding> {
        None
    }
}

impl Arrived for Sample {
    fn write(&self) -> Write {
        Write::of_sample(self)
    }
    fn encoding(&self) -> Option<&Encoding> {
        Some(self.encoding())
    }
}
