//! `P/C/machine/M/status`: each machine's `MachineStatus`, published when it changes (QoS
//! `Drop`: the next value supersedes a lost one) and answered on `get`, so that a late joiner
//! gets the current value. A wildcard get answers every machine it takes in.
//!
//! zenoh-ext's `AdvancedPublisher` would replay a cache to late subscribers, but its API is
//! unstable in zenoh 1.x; a queryable holding the last value gives the same with the stable API.

use tokio_util::sync::CancellationToken;
use zenoh::handlers::FifoChannelHandler;
use zenoh::qos::CongestionControl;
use zenoh::query::{Query, Queryable};

use super::context::MachinePublisher;
use super::context::{RouteContext, reply};
use super::keys::MachineLeaf;
use super::machine::Machine;
use super::session::BusError;
use cellgate_core::pb;

/// The status queryable of the cell. Undeclared when dropped.
pub(crate) struct StatusRoute {
    queryable: Queryable<FifoChannelHandler<Query>>,
}

impl StatusRoute {
    pub(super) async fn declare(ctx: &RouteContext) -> Result<Self, BusError> {
        let queryable = ctx
            .queryable(ctx.keys.any_leaf(MachineLeaf::Status))
            .await?;
        Ok(StatusRoute { queryable })
    }

    /// Answers gets until `stop`. A status is at hand, so the answer never waits.
    pub(super) async fn run(self, ctx: RouteContext, stop: CancellationToken) {
        loop {
            let q = tokio::select! {
                () = stop.cancelled() => break,
                q = self.queryable.recv_async() => match q {
                    Ok(q) => q,
                    Err(_) => break,
                },
            };
            let matching = ctx.matching(&q, MachineLeaf::Status);
            if matching.is_empty() {
                ctx.unmatched(&q).await;
                continue;
            }
            for (key, m) in matching {
                reply(&q, key, &m.status()).await;
            }
        }
    }
}

/// One machine's status publisher, and what it published last.
pub(crate) struct StatusPublisher {
    publisher: MachinePublisher<pb::MachineStatus>,
    published: Option<pb::MachineStatus>,
}

impl StatusPublisher {
    pub(super) async fn declare(ctx: &RouteContext, machine: &str) -> Result<Self, BusError> {
        // Telemetry: the next status supersedes a lost one.
        let publisher =
            MachinePublisher::declare(ctx, machine, MachineLeaf::Status, CongestionControl::Drop)
                .await?;
        Ok(StatusPublisher {
            publisher,
            published: None,
        })
    }

    /// Publishes the machine's status if it changed since the last publication (the time of
    /// day aside); returns it when it did.
    pub(super) async fn publish(&mut self, machine: &Machine) -> Option<&pb::MachineStatus> {
        let mut current = machine.view().status.clone();
        current.storage_fault = machine.storage_fault();
        if self.published.as_ref() == Some(&current) {
            return None;
        }
        let mut stamped = current.clone();
        stamped.unix_ms = pb::now_ms();
        machine.line_counters(&mut stamped);
        self.publisher.publish(&stamped).await;
        self.published = Some(current);
        self.published.as_ref()
    }
}
