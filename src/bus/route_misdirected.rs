//! Puts and deletes on read keys: never silent.
//!
//! Every write has a key of its own (`…/program/NAME/write`, `…/submit`, `…/tag/NAME/set`,
//! `…/mem/…/write`, `…/transfer/N/send`, `…/message/send`), so zenoh's access control can
//! tell a read from a write. A client written against an older contract may still put a
//! program on `P/C/program/NAME` or a value on `…/tag/NAME`; a put has no answer, so without
//! this route it would vanish while the client believes it wrote. The gateway subscribes to
//! those read keys (other sessions' samples only: the gateway publishes on some of them
//! itself) and answers each such sample the only ways a put can be answered: a warning in the
//! log naming the key that takes the write, the counter `cellgate.bus.misdirected_writes`, and
//! a refusal in the audit trail (gathered per sender and minute like every refusal).
//!
//! Where `[security]` roles are set, zenoh's access control refuses a put on a read key
//! before it reaches the gateway (no role is granted puts there): that refusal is zenoh's,
//! silent, and invisible to the gateway (docs/security.md).

use zenoh::sample::{Sample, SampleKind};

use super::audit::{Audit, origin_of};
use super::context::{RequestError, RouteContext};
use super::keys::{CellKey, CellKeys, MachineLeaf, PlcArea, PlcKey};
use cellgate_core::config::Permission;

/// The counter of puts and deletes on read keys, by kind of key.
pub const METRIC: &str = "cellgate.bus.misdirected_writes";

/// What a misdirected sample was meant to do: the kind of key (for the metric), the key that
/// takes the write, and the permission that write needs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Misdirected {
    pub kind: &'static str,
    pub write_key: String,
    pub permission: Permission,
    /// The machine or PLC it acts on (empty for the library).
    pub machine: String,
}

/// What a put or delete on `key` was meant to write, if `key` is a read key with a write key
/// beside it.
pub(crate) fn misdirected(keys: &CellKeys, key: &str) -> Option<Misdirected> {
    let m = |kind, write_key, permission, machine: &str| Misdirected {
        kind,
        write_key,
        permission,
        machine: machine.to_string(),
    };
    if let Some(plc) = keys.parse_plc(key) {
        return match plc {
            PlcKey::Tag {
                plc,
                name,
                set: false,
            } => Some(m(
                "plc.tag",
                keys.plc_tag_set(plc, name),
                Permission::PlcTag,
                plc,
            )),
            PlcKey::Mem {
                plc, write: false, ..
            } => Some(m(
                "plc.mem",
                format!("{key}/write"),
                Permission::PlcMem,
                plc,
            )),
            PlcKey::Transfer {
                plc, send: false, ..
            } => Some(m(
                "plc.transfer",
                format!("{key}/send"),
                Permission::PlcTransfer,
                plc,
            )),
            PlcKey::Message { plc, send: false } => Some(m(
                "plc.message",
                keys.plc_message_send(plc),
                Permission::PlcTransfer,
                plc,
            )),
            _ => None,
        };
    }
    match keys.parse(key)? {
        CellKey::Program { name } => Some(m(
            "program",
            keys.program_write(name),
            Permission::ProgramWrite,
            "",
        )),
        CellKey::Leaf {
            machine,
            leaf: MachineLeaf::Job,
        } => Some(m(
            "job",
            keys.leaf(machine, MachineLeaf::Submit),
            Permission::JobSubmit,
            machine,
        )),
        _ => None,
    }
}

/// The read keys that have a write key beside them, subscribed to for the puts and deletes
/// sent there.
pub(super) fn read_keys(k: &CellKeys) -> Vec<String> {
    vec![
        k.any_program(),
        k.any_leaf(MachineLeaf::Job),
        k.any_plc_tag(),
        format!("{}/*/*", k.plc_area("*", PlcArea::Mem)),
        format!("{}/*/*/*", k.plc_area("*", PlcArea::Mem)),
        format!("{}/*", k.plc_area("*", PlcArea::Transfer)),
        k.plc_message("*"),
    ]
}

pub(super) async fn answer(ctx: &RouteContext, s: &Sample) {
    let key = s.key_expr().as_str();
    // A wildcard put, or a key that is not what the subscriptions stand for: nothing to say.
    let Some(m) = misdirected(&ctx.keys, key).filter(|_| !s.key_expr().is_wild()) else {
        return;
    };
    let op = match s.kind() {
        SampleKind::Put => "put",
        SampleKind::Delete => "delete",
    };
    tracing::warn!(
        key,
        write_key = %m.write_key,
        "a {op} on a read key was not taken: writes go to {}",
        m.write_key
    );
    crate::telemetry::metrics::event(METRIC, &[("key", m.kind)], 1);
    let e = RequestError::WrongKey(format!(
        "a {op} on {key} (a read key) is not taken; writes go to {}",
        m.write_key
    ));
    ctx.audit(
        Audit {
            action: "bus.misdirected",
            permission: m.permission,
            key,
            machine: &m.machine,
            target: key.to_string(),
            detail: format!("{op} on a read key; writes go to {}", m.write_key),
            origin: origin_of(s.attachment()),
        },
        Err(&e),
    );
}

#[cfg(test)]
mod tests;
