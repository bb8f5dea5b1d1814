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

use std::time::SystemTime;

use zenoh::query::Query;
use zenoh::sample::{Sample, SampleKind};

use super::audit::{Audit, origin_of};
use super::context::{RequestError, RouteContext, Target, publish_event, reply, reply_err};
use super::keys::MachineLeaf;
use super::machine::Machine;
use super::published::Published;
use crate::link::driver::{LinkCommand, LinkEvent};
use cellgate_core::config::Permission;
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

/// A put on `do`: outputs the DO image (SDO). A put has no reply: refusals are logged.
pub(super) async fn do_put(ctx: &RouteContext, sample: &Sample) {
    if sample.kind() != SampleKind::Put {
        return;
    }
    let key = sample.key_expr();
    let m = match ctx.target(key) {
        Target::One(m) => m.clone(),
        Target::Unknown(name) => {
            return tracing::warn!(%key, "DO refused: {}", ctx.unknown_machine(&name));
        }
        Target::Wild => return tracing::warn!(%key, "DO refused: name one machine"),
    };
    if !m.config.protocol.is_a_family() {
        return tracing::warn!(%key, "DO refused: Protocol B has no SDO (§4.4.1)");
    }
    let origin = origin_of(sample.attachment());
    match do_command(ctx, &m, sample.payload().to_bytes().as_ref()) {
        Ok((value, mask)) => {
            // Without waiting: a flood of puts is refused past the link's command queue
            // rather than stalling this route.
            // The client's timestamp, when it set one, so that the delay counts the bus too.
            let asked = sample
                .timestamp()
                .map_or_else(SystemTime::now, |t| t.get_time().to_system_time());
            let sent = m
                .link
                .try_send(LinkCommand::SetDo { value, mask, asked })
                .map_err(RequestError::from);
            audit_do(
                ctx,
                key.as_str(),
                &m,
                Some((value, mask)),
                origin,
                sent.as_ref(),
            );
            if let Err(e) = sent {
                tracing::warn!(%key, "DO refused: {e}");
            }
        }
        Err(e) => {
            audit_do(ctx, key.as_str(), &m, None, origin, Err(&e));
            tracing::warn!(%key, "DO refused: {e}");
        }
    }
}

/// Records a DO output in the audit: a put's outcome is that the link took it (the SDO goes
/// out with its next exchange), a get's that the SDO went out.
fn audit_do(
    ctx: &RouteContext,
    key: &str,
    m: &Machine,
    command: Option<(u8, u8)>,
    origin: Option<pb::RequestOrigin>,
    outcome: Result<&(), &RequestError>,
) {
    ctx.audit(
        Audit {
            action: "io.do",
            permission: Permission::IoDo,
            key,
            machine: m.name(),
            target: m.name().to_string(),
            detail: command
                .map(|(v, mask)| format!("DO {v:#04x} mask {mask:#04x}"))
                .unwrap_or_default(),
            origin,
        },
        outcome.map(|_| ()),
    );
}

/// A get with a `DoCommand` on `do`: outputs the DO image and answers the status once the
/// SDO went out.
pub(super) async fn do_get(ctx: &RouteContext, q: &Query) {
    let m = match ctx.target(q.key_expr()) {
        Target::One(m) => m.clone(),
        Target::Unknown(_) => return ctx.unmatched(q).await,
        // A wildcard get without payload (e.g. on `P/C/**`) browses; `do` has nothing to show.
        Target::Wild if q.payload().is_none() => return,
        Target::Wild => {
            let e = RequestError::OneMachine {
                what: "DoCommand",
                expected: ctx.keys.leaf("<machine>", MachineLeaf::Do),
                got: None,
            };
            return reply_err(q, &e).await;
        }
    };
    let Some(payload) = q.payload() else {
        let e = RequestError::Invalid {
            machine: m.name().to_string(),
            what: "a get on do carries a DoCommand".to_string(),
        };
        return reply_err(q, &e).await;
    };
    let origin = origin_of(q.attachment());
    let key = q.key_expr().as_str();
    let (value, mask) = match do_command(ctx, &m, payload.to_bytes().as_ref()) {
        Ok(c) => c,
        Err(e) => {
            audit_do(ctx, key, &m, None, origin, Err(&e));
            return reply_err(q, &e).await;
        }
    };
    if let Some(e) = io_refusal(&m) {
        audit_do(ctx, key, &m, Some((value, mask)), origin, Err(&e));
        return reply_err(q, &e).await;
    }
    let sent = exchange(
        &m,
        LinkCommand::SetDo {
            value,
            mask,
            asked: SystemTime::now(),
        },
        "SDO went out",
        |e| match e {
            LinkEvent::Do { value: out } if out & mask == value & mask => Some(()),
            _ => None,
        },
    )
    .await;
    audit_do(
        ctx,
        key,
        &m,
        Some((value, mask)),
        origin.clone(),
        sent.as_ref(),
    );
    match sent {
        Ok(()) => {
            // The machine's task folds the same event into the view; make sure the reply
            // shows it even if that task has not run yet.
            let mut status = m.status();
            let old = status.do_image.unwrap_or(0);
            let image = (u8::try_from(old).unwrap_or(0) & !mask) | (value & mask);
            status.do_image = Some(u32::from(image));
            reply(q, q.key_expr().to_string(), &status).await;
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
                origin.as_ref(),
            )
            .await;
        }
        Err(e) => reply_err(q, &e).await,
    }
}
