//! `P/C/sim/M/...`: the controls of the cell's simulated machines (`kind = "sim"`), what an
//! operator does at a CNC, so that a demo or CI can drive a running simulated cell from the
//! bus (`proto/cellgate/v1/sim.proto`).
//!
//! Each control is a get on a key of its own (`di`, `alarm`, `reset`, `read`, `hold`,
//! `autostart`, `punch`) answered with the machine's `SimState` once the simulated board has
//! taken it; `state` only reads. Declared only on a cell with simulated machines; a control of
//! a real machine is refused (`ERROR_CODE_NOT_SUPPORTED`).

use std::time::Duration;

use zenoh::query::Query;

use super::context::{RequestError, RouteContext, reply, reply_err};
use super::keys::{CellKey, SimLeaf, intersects};
use super::machine::Machine;
use crate::sim::{BoardControl, BoardSnapshot};
use cellgate_core::fanuc::CodeSystem;
use cellgate_core::pb;
use cellgate_core::program::tape::{self, TapeCode};
use cellgate_core::sim::BoardCommand;

/// How long the simulated board may take to take a control: it runs in this process and takes
/// a command at its next step, so anything near this is a board that has stopped.
const TAKE_WITHIN: Duration = Duration::from_secs(5);

/// A machine's state as its operator would see it.
fn state(m: &Machine, s: &BoardSnapshot) -> pb::SimState {
    pb::SimState {
        machine: m.name().to_string(),
        reading: s.reading,
        alarm: s.alarm,
        autostart: s.autostart,
        di: u32::from(s.di_image),
        do_image: u32::from(s.do_image),
        buffered: s.buffered as u64,
        programs_read: u32::try_from(s.programs.len()).unwrap_or(u32::MAX),
        last_program: s
            .programs
            .last()
            .map(|p| p.first_line.clone())
            .unwrap_or_default(),
        punched_bytes: s.punched,
        board_link: s.link.name().to_string(),
    }
}

/// A simulation control as the audit trail says it: what it sets, and to what.
fn describe(c: &BoardCommand) -> String {
    match c {
        BoardCommand::SetDi(v) => format!("DI 0x{v:02X}"),
        BoardCommand::SetAutostart(on) => {
            format!("autostart {}", if *on { "on" } else { "off" })
        }
        BoardCommand::Punch(bytes) => format!("punch {} bytes", bytes.len()),
        BoardCommand::SetConsumeRate(r) => format!("consume rate {r} B/s"),
        other => format!("{other:?}"),
    }
}

pub(super) async fn sim_query(ctx: &RouteContext, q: &Query) {
    let key = q.key_expr();
    if key.is_wild() {
        // A browse (`P/C/sim/**`): the state of each simulated machine it takes in; a control
        // goes to one machine's key.
        for m in ctx.machines.now().values() {
            let Some(sim) = &m.sim else { continue };
            let k = ctx.keys.sim(m.name(), SimLeaf::State);
            if intersects(key, &k) {
                reply(q, k, &state(m, &sim.snapshot())).await;
            }
        }
        return;
    }
    let Some(CellKey::Sim { machine, leaf }) = ctx.keys.parse(key.as_str()) else {
        let e = RequestError::WrongKey(format!(
            "{key} is no simulation key: P/C/sim/M/ takes state, {}",
            SimLeaf::ALL[1..]
                .iter()
                .map(|l| l.chunk())
                .collect::<Vec<_>>()
                .join(", ")
        ));
        return reply_err(q, &e).await;
    };
    let Some(m) = ctx.machines.now().get(machine).cloned() else {
        return reply_err(q, &ctx.unknown_machine(machine)).await;
    };
    let Some(sim) = &m.sim else {
        let e = RequestError::NotSimulated {
            machine: machine.to_string(),
        };
        return reply_err(q, &e).await;
    };
    if leaf != SimLeaf::State
        && let Err(e) = ctx.history.audit_writable()
    {
        return reply_err(q, &RequestError::from(e)).await;
    }
    let payload = q.payload().map(|p| p.to_bytes().to_vec());
    let command = command(ctx, &m, sim, leaf, payload.as_deref());
    // What the control asked for, with its value, for the audit trail.
    let detail = match &command {
        Ok(Some(c)) => describe(c),
        _ => String::new(),
    };
    let result = match command {
        Ok(None) => Ok(sim.snapshot()),
        Ok(Some(command)) => {
            sim.apply(command, TAKE_WITHIN)
                .await
                .map_err(|e| RequestError::SimRefused {
                    machine: machine.to_string(),
                    why: e.to_string(),
                    code: pb::ErrorCode::Unavailable,
                })
        }
        Err(e) => Err(e),
    };
    // Reading the state changes nothing; every control is a write.
    if leaf != SimLeaf::State {
        let action = format!("sim.{}", leaf.chunk());
        ctx.audit_answered(
            crate::bus::audit::Audit {
                action: &action,
                permission: cellgate_core::config::Permission::SimControl,
                key: key.as_str(),
                machine,
                target: machine.to_string(),
                detail,
                origin: crate::bus::audit::origin_of(q.attachment()),
            },
            result.as_ref().map(|_| ()),
        )
        .await;
    }
    match result {
        Ok(s) => reply(q, key.to_string(), &state(&m, &s)).await,
        Err(e) => reply_err(q, &e).await,
    }
}

/// The board command a control asks for (`None`: `state`, which only reads), or why the
/// machine cannot take it.
fn command(
    ctx: &RouteContext,
    m: &Machine,
    sim: &BoardControl,
    leaf: SimLeaf,
    payload: Option<&[u8]>,
) -> Result<Option<BoardCommand>, RequestError> {
    let name = m.name();
    let refused = |why: &str, code: pb::ErrorCode| RequestError::SimRefused {
        machine: name.to_string(),
        why: why.to_string(),
        code,
    };
    let needs = |message: &str| {
        refused(
            &format!("a get on {} carries a {message}", leaf.chunk()),
            pb::ErrorCode::InvalidRequest,
        )
    };
    let now = sim.snapshot();
    Ok(Some(match leaf {
        SimLeaf::State => return Ok(None),
        SimLeaf::Di => {
            if !m.config.protocol.is_a_family() {
                return Err(refused(
                    "Protocol B has no DI (RDI/SDI are Protocol A family, §4.4.1)",
                    pb::ErrorCode::NotSupported,
                ));
            }
            let di: pb::SimDi = ctx.decode(name, payload.ok_or_else(|| needs("SimDi"))?)?;
            let value = u8::try_from(di.value).map_err(|_| {
                refused(
                    &format!("DI value {} is not 8 bits (0..=255)", di.value),
                    pb::ErrorCode::InvalidRequest,
                )
            })?;
            BoardCommand::SetDi(value)
        }
        SimLeaf::Alarm => BoardCommand::RaiseAlarm,
        SimLeaf::Reset => BoardCommand::Reset,
        SimLeaf::Read => {
            if now.alarm {
                return Err(refused(
                    "the CNC is in alarm: reset it first (a get on P/C/sim/M/reset)",
                    pb::ErrorCode::Unavailable,
                ));
            }
            BoardCommand::StartReading
        }
        SimLeaf::Hold => BoardCommand::StopReading,
        SimLeaf::Autostart => {
            let a: pb::SimAutostart =
                ctx.decode(name, payload.ok_or_else(|| needs("SimAutostart"))?)?;
            BoardCommand::SetAutostart(a.on)
        }
        SimLeaf::Punch => {
            if m.config.protocol.is_a_family() {
                return Err(refused(
                    "punch-out is a Protocol B function (§6.1.1 2)",
                    pb::ErrorCode::NotSupported,
                ));
            }
            let p: pb::SimPunch = ctx.decode(name, payload.ok_or_else(|| needs("SimPunch"))?)?;
            if now.alarm {
                return Err(refused(
                    "the CNC is in alarm: reset it first (a get on P/C/sim/M/reset)",
                    pb::ErrorCode::Unavailable,
                ));
            }
            let code = match m.config.code {
                CodeSystem::Iso => TapeCode::Iso,
                CodeSystem::Ascii => TapeCode::Ascii,
            };
            let tape = tape::encode(&p.program, code).map_err(|e| {
                refused(&format!("the program: {e}"), pb::ErrorCode::InvalidRequest)
            })?;
            BoardCommand::Punch(tape)
        }
    }))
}
