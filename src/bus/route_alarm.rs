//! `P/C/machine/M/alarm`: each machine's `AlarmEvent`s — CNC alarms and resets, link alarms
//! with the manual's number (SR0855, SR0856, SR0944–SR0948), punched programs lost, remote
//! requests that could not be served — published reliably (QoS `Block`): an operator must
//! see every one. The latest is also in the machine's status (`last_alarm`).

use zenoh::pubsub::Publisher;
use zenoh::qos::CongestionControl;

use super::BusError;
use super::context::RouteContext;
use super::keys::MachineLeaf;
use super::machine::{declare_publisher, put};
use super::payload::encoding;
use crate::pb;

/// One machine's alarm publisher.
pub(crate) struct AlarmPublisher {
    publisher: Publisher<'static>,
}

impl AlarmPublisher {
    pub async fn declare(ctx: &RouteContext, machine: &str) -> Result<Self, BusError> {
        let publisher = declare_publisher(
            ctx,
            machine,
            MachineLeaf::Alarm,
            encoding::<pb::AlarmEvent>(),
            CongestionControl::Block,
        )
        .await?;
        Ok(AlarmPublisher { publisher })
    }

    pub async fn publish(&self, alarm: &pb::AlarmEvent) {
        put(&self.publisher, alarm).await;
    }
}
