//! `P/C/machine/M/status`: each machine's `MachineStatus`, published when it changes (QoS
//! `Drop`: the next value supersedes a lost one) and answered on `get`, so that a late joiner
//! gets the current value. A wildcard get answers every machine it takes in.
//!
//! zenoh-ext's `AdvancedPublisher` would replay a cache to late subscribers, but its API is
//! unstable in zenoh 1.x; a queryable holding the last value gives the same with the stable API.

use zenoh::query::Query;

use super::context::MachinePublisher;
use super::context::{RouteContext, reply};
use super::error::BusError;
use super::keys::MachineLeaf;
use super::machine::Machine;
use super::published::MachinePublication;
use cellgate_core::pb;

/// A get on `status`: the status of each machine it takes in. A status is at hand, so the
/// answer never waits.
pub(super) async fn status_get(ctx: &RouteContext, q: &Query) {
    let matching = ctx.matching(q, MachineLeaf::Status);
    if matching.is_empty() {
        return ctx.unmatched(q).await;
    }
    for (key, m) in matching {
        reply(q, key, &m.status()).await;
    }
}

/// One machine's status publisher, and what it published last.
pub(crate) struct StatusPublisher {
    publisher: MachinePublisher<pb::MachineStatus>,
    /// The machine's view of its status when last published, and the storage fault then.
    published: Option<(pb::MachineStatus, String)>,
}

impl StatusPublisher {
    pub(super) async fn declare(ctx: &RouteContext, machine: &str) -> Result<Self, BusError> {
        let publisher = MachinePublisher::declare(ctx, machine, MachinePublication::Status).await?;
        Ok(StatusPublisher {
            publisher,
            published: None,
        })
    }

    /// Publishes the machine's status if it changed since the last publication (the time of
    /// day aside); returns it when it did.
    pub(super) async fn publish(&mut self, machine: &Machine) -> Option<pb::MachineStatus> {
        let fault = machine.storage_fault();
        let mut current = {
            // Compared where it lies: the machine's task asks after every event it takes, and
            // a clone each time was the most frequent allocation of a busy gateway.
            let view = machine.view();
            if self
                .published
                .as_ref()
                .is_some_and(|(status, f)| *status == view.status && *f == fault)
            {
                return None;
            }
            view.status.clone()
        };
        self.published = Some((current.clone(), fault.clone()));
        current.storage_fault = fault;
        let mut stamped = current.clone();
        stamped.unix_ms = pb::now_ms();
        machine.line_counters(&mut stamped);
        self.publisher.publish(&stamped).await;
        Some(current)
    }
}
