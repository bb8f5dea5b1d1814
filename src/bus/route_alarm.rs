//! `P/C/machine/M/alarm`: each machine's `AlarmEvent`s — CNC alarms and resets, link alarms
//! with the manual's number (SR0855, SR0856, SR0944–SR0948), punched programs lost, remote
//! requests that could not be served — published reliably (QoS `Block`): an operator must
//! see every one. The latest is also in the machine's status (`last_alarm`).

use zenoh::qos::CongestionControl;

use super::context::MachinePublisher;
use super::context::RouteContext;
use super::error::BusError;
use super::keys::MachineLeaf;
use cellgate_core::pb;

/// Declares one machine's alarm publisher: reliable, an alarm is never dropped.
pub(crate) async fn declare_publisher(
    ctx: &RouteContext,
    machine: &str,
) -> Result<MachinePublisher<pb::AlarmEvent>, BusError> {
    MachinePublisher::declare(ctx, machine, MachineLeaf::Alarm, CongestionControl::Block).await
}
