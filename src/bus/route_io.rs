//! DI and DO (Protocol A family: RDI → SDI, SDO; §4.4.1).
//!
//! - `P/C/machine/M/di`: a get on one machine reads DI now and answers the `DiImage`; a
//!   wildcard get answers the last image read of each machine. Each image read is published
//!   (QoS `Drop`: the next image supersedes a lost one).
//! - `P/C/machine/M/do`: a put with a `DoCommand` outputs DO; a get with one outputs it and
//!   answers the `MachineStatus` once the SDO went out.
//!
//! The board speaks at its next SAT or GTD, so a read or an output waits up to
//! [`Machine::exchange_timeout`]; it runs off the route's loop.

use zenoh::query::Query;

use super::context::{RequestError, RouteContext, Target, publish_event, reply, reply_err};
use super::keys::MachineLeaf;
use super::machine::Machine;
use super::published::Published;
use super::write::{Audited, Done, Write};
use crate::link::driver::{LinkCommand, LinkEvent};
use cellgate_core::pb;

/// Why `m` cannot do DI/DO now, if it cannot.
fn io_refusal(m: &Machine) -> Option<RequestError> {
    if !m.config.protocol.is_a_family() {
        return Some(RequestError::NoIo {
            machine: m.name().to_string(),
            protocol: m.config.protocol,
        });
    }
    if !m.link_up() {
        return Some(RequestError::NotInitialised {
            machine: m.name().to_string(),
        });
    }
    None
}

/// Gives the link `command` and waits, up to the machine's exchange time-out, for the
/// first link event `answer` picks. `what` names the answer in the time-out error.
async fn exchange<T>(
    m: &Machine,
    command: LinkCommand,
    what: &'static str,
    mut answer: impl FnMut(&LinkEvent) -> Option<T>,
) -> Result<T, RequestError> {
    let mut events = m.link.subscribe();
    m.link
        .send(command)
        .await
        .map_err(|_| RequestError::NotRunning {
            machine: m.name().to_string(),
        })?;
    let waited = m.exchange_timeout();
    let got = tokio::time::timeout(waited, async {
        loop {
            match events.recv().await {
                Ok(LinkEvent::Stopped { .. })
                | Err(tokio::sync::broadcast::error::RecvError::Closed) => return None,
                Ok(event) => {
                    if let Some(t) = answer(&event) {
                        return Some(t);
                    }
                }
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
            }
        }
    })
    .await;
    got.ok().flatten().ok_or_else(|| RequestError::NoAnswer {
        machine: m.name().to_string(),
        answer: what,
        waited,
    })
}

/// A get on `di`: a concrete key reads the DI image now (RDI → SDI); a wildcard answers the
/// last image read of each machine that has one.
pub(super) async fn di_get(ctx: &RouteContext, q: &Query) {
    let m = match ctx.target(q.key_expr()) {
        Target::One(m) => m.clone(),
        Target::Unknown(_) => return ctx.unmatched(q).await,
        Target::Wild => {
            for (key, m) in ctx.matching(q, MachineLeaf::Di) {
                let last = m.view().last_di.clone();
                if let Some(di) = last {
                    reply(q, key, &di).await;
                }
            }
            return;
        }
    };
    if let Some(e) = io_refusal(&m) {
        return reply_err(q, &e).await;
    }
    // Many gets at once share one RDI: each waits its turn, and one that finds an image read
    // since it arrived takes that one instead of asking the board again.
    // A read that failed since it arrived is its answer too: waiting ones do not each try
    // again for a whole exchange time.
    let arrived = tokio::time::Instant::now();
    let mut last = m.di_read.lock().await;
    let read = match *last {
        Some((at, Ok(value))) if at >= arrived => Ok(value),
        Some((at, Err(()))) if at >= arrived => Err(RequestError::NoAnswer {
            machine: m.name().to_string(),
            answer: "SDI answered RDI",
            waited: m.exchange_timeout(),
        }),
        _ => {
            let read = exchange(&m, LinkCommand::ReadDi, "SDI answered RDI", |e| match e {
                LinkEvent::Di { value } => Some(*value),
                _ => None,
            })
            .await;
            *last = Some((
                tokio::time::Instant::now(),
                read.as_ref().map(|v| *v).map_err(|_| ()),
            ));
            read
        }
    };
    drop(last);
    match read {
        Ok(value) => {
            let di = pb::DiImage {
                machine: m.name().to_string(),
                value: u32::from(value),
                unix_ms: pb::now_ms(),
            };
            reply(q, q.key_expr().to_string(), &di).await;
        }
        Err(e) => reply_err(q, &e).await,
    }
}

/// Checks a DO command; returns `(value, mask)`.
fn do_command(ctx: &RouteContext, m: &Machine, payload: &[u8]) -> Result<(u8, u8), RequestError> {
    let invalid = |what: String| RequestError::Invalid {
        machine: m.name().to_string(),
        what,
    };
    let cmd: pb::DoCommand = ctx.decode(m.name(), payload)?;
    let value = u8::try_from(cmd.value)
        .map_err(|_| invalid(format!("DO value {} is not 8 bits (0..=255)", cmd.value)))?;
    let mask = u8::try_from(cmd.mask.unwrap_or(0xFF))
        .map_err(|_| invalid(format!("DO mask {:?} is not 8 bits (0..=255)", cmd.mask)))?;
    Ok((value, mask))
}

/// A `DoCommand` on `do` (its write row): a get outputs the DO image (SDO) and answers the
/// `MachineStatus` once the SDO went out; a put gives it to the link without waiting (a flood
/// of puts is refused past the link's command queue rather than stalling the route), and the
/// SDO goes out with the link's next exchange.
pub(super) async fn do_write(
    ctx: &RouteContext,
    w: Write,
) -> Done<pb::MachineStatus, RequestError> {
    let m = match ctx.target(&w.key) {
        Target::One(m) => m.clone(),
        Target::Unknown(name) => return Done::refused(ctx.unknown_machine(&name)),
        Target::Wild => {
            return Done::refused(RequestError::OneMachine {
                what: "DoCommand",
                expected: ctx.keys.leaf("<machine>", MachineLeaf::Do),
                got: None,
            });
        }
    };
    if !w.answered() && !m.config.protocol.is_a_family() {
        // Protocol B has no SDO (§4.4.1); a get hears it below, with the link's state.
        return Done::refused(RequestError::NoIo {
            machine: m.name().to_string(),
            protocol: m.config.protocol,
        });
    }
    let Some(payload) = w.bytes() else {
        return Done::refused(RequestError::Invalid {
            machine: m.name().to_string(),
            what: "a get on do carries a DoCommand".to_string(),
        });
    };
    let audited = |command: Option<(u8, u8)>| Audited {
        action: "io.do",
        machine: m.name().to_string(),
        target: m.name().to_string(),
        detail: command
            .map(|(v, mask)| format!("DO {v:#04x} mask {mask:#04x}"))
            .unwrap_or_default(),
    };
    let command = match w.checked() {
        Ok(()) => do_command(ctx, &m, &payload),
        Err(e) => Err(e.into()),
    };
    let (value, mask) = match command {
        Ok(c) => c,
        Err(e) => return Done::audited(audited(None), Err(e)),
    };
    let audited = audited(Some((value, mask)));
    if !w.answered() {
        // A put's outcome is that the link took it: the SDO goes out with its next exchange.
        let asked = w.asked;
        let taken = m
            .link
            .try_send(LinkCommand::SetDo { value, mask, asked })
            .map_err(RequestError::from);
        return Done::taken(audited, taken);
    }
    if let Some(e) = io_refusal(&m) {
        return Done::audited(audited, Err(e));
    }
    let sent = exchange(
        &m,
        LinkCommand::SetDo {
            value,
            mask,
            asked: w.asked,
        },
        "SDO went out",
        |e| match e {
            LinkEvent::Do { value: out } if out & mask == value & mask => Some(()),
            _ => None,
        },
    )
    .await;
    if let Err(e) = sent {
        return Done::audited(audited, Err(e));
    }
    // A get is seen by no subscriber of `…/do`: say that the SDO went out.
    let out = pb::DoCommand {
        value: u32::from(value),
        mask: Some(u32::from(mask)),
    };
    publish_event(
        ctx,
        Published::DoOut,
        &ctx.keys.do_out(m.name()),
        &out,
        w.origin.as_ref(),
    )
    .await;
    // The machine's task folds the same event into the view; make sure the answer shows it
    // even if that task has not run yet.
    let mut status = m.status();
    let old = status.do_image.unwrap_or(0);
    let image = (u8::try_from(old).unwrap_or(0) & !mask) | (value & mask);
    status.do_image = Some(u32::from(image));
    Done::audited(audited, Ok(status))
}
