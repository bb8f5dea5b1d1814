//! SHDR, the line format an MTConnect agent takes from an adapter over TCP (MTConnect Part 1,
//! "adapter"; as the reference agent reads it): `TIMESTAMP|DEVICE:KEY|VALUE`, a condition as
//! `TIMESTAMP|DEVICE:KEY|LEVEL|NATIVE_CODE|NATIVE_SEVERITY|QUALIFIER|TEXT`, and the heartbeat
//! `* PING` answered by `* PONG MILLISECONDS`. Keys are the data items' ids, so an agent
//! given cellgate's `/probe` as its device file takes the lines as they are. An asset event
//! is `TIMESTAMP|DEVICE:KEY|ASSET_TYPE|ASSET_ID`, and a punched program's asset goes before
//! it whole, as `TIMESTAMP|@ASSET@|ASSET_ID|File|<File …>…</File>`, so that the agent's
//! `/assets` holds it too.

use std::fmt::Write as _;

use super::agent::Agent;
use super::buffer::{Level, Observation, Value};
use super::model::{Category, Role};
use super::xml;

/// How often the adapter expects a `* PING` at least, said in every `* PONG`.
pub const HEARTBEAT_MS: u64 = 10_000;

/// The answer to `* PING`.
pub fn pong() -> String {
    format!("* PONG {HEARTBEAT_MS}\n")
}

/// A field without the separator or a line end (SHDR has no escape for them).
fn field(s: &str) -> String {
    s.replace(['|', '\n', '\r'], " ")
}

/// One line per observation.
pub fn lines(agent: &Agent, obs: &[&Observation]) -> String {
    let m = agent.model();
    let mut out = String::with_capacity(obs.len() * 64);
    for o in obs {
        let Some(item) = m.items.get(o.item as usize) else {
            continue;
        };
        let dev = &m.devices[item.device].name;
        let ts = xml::timestamp(o.time_us);
        let asset_event = matches!(item.role, Role::AssetChanged | Role::AssetRemoved);
        if item.role == Role::AssetChanged
            && let Value::Text(id) = &o.value
            && let Some(element) = agent.asset_element(id)
        {
            let _ = writeln!(out, "{ts}|@ASSET@|{}|File|{element}", field(id));
        }
        let _ = write!(out, "{ts}|{dev}:{}|", item.id);
        match (&o.value, item.category) {
            // The type before the id, as the reference agent reads an asset event.
            (Value::Text(id), _) if asset_event => {
                let _ = write!(out, "File|{}", field(id));
            }
            _ if asset_event => out.push_str("UNAVAILABLE|UNAVAILABLE"),
            (Value::Cond(c), _) => {
                let level = match c.level {
                    Level::Normal => "NORMAL",
                    Level::Warning => "WARNING",
                    Level::Fault => "FAULT",
                };
                let _ = write!(
                    out,
                    "{level}|{}|||{}",
                    field(&c.native_code),
                    field(&c.text)
                );
            }
            (_, Category::Condition) => out.push_str("UNAVAILABLE||||"),
            (Value::Text(t), _) => out.push_str(&field(t)),
            _ => out.push_str("UNAVAILABLE"),
        }
        out.push('\n');
    }
    out
}

/// Every data item's state now, as lines: what a newly connected agent needs first.
pub fn snapshot(agent: &Agent) -> String {
    let obs: Vec<&Observation> = agent
        .buffer()
        .latest()
        .iter()
        .enumerate()
        // The Agent device's own items are the agent's, not an adapter's to send.
        .filter(|(i, _)| agent.model().items[*i].device != 0)
        .flat_map(|(_, s)| s.shown())
        .collect();
    lines(agent, &obs)
}
