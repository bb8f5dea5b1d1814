//! Following cells as the MTConnect agent and the OPC UA server do: the cells' publications,
//! subscribed once, and what each gateway answers when it comes (its statuses and queues),
//! all read with `status.read` (and `admin.read` where the role has it, for tag addresses
//! and part counters), handed to a [`Follower`] as [`Update`]s.
//!
//! A gateway's liveliness token (`P/C/gateway`) says when it comes and goes: when it goes,
//! the follower is told (every value of its devices becomes unknown); when it comes (or
//! comes back), the gateway is asked for the state it missed. A reload it took
//! (`P/C/reload`) is asked about the same way: the cell's devices follow what the cell file
//! now holds.

use std::sync::Arc;
use std::time::Duration;

use prost::Message;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use zenoh::Session;
use zenoh::sample::{Sample, SampleKind};

use crate::client::Client;
use cellgate_core::mtconnect::{CellDesc, Update};
use cellgate_core::pb;

/// What follows cells: the MTConnect agent, the OPC UA server.
pub trait Follower: Send + Sync + 'static {
    /// How `cell` was last described, if it is followed.
    fn known(&self, cell: &str) -> Option<CellDesc>;
    /// Takes a cell's description: a cell new to it, or one whose machines or PLCs changed.
    fn describe(&self, desc: &CellDesc);
    /// Takes what `cell`'s gateway said, in order; nothing for a cell not followed.
    fn take(&self, cell: &str, updates: Vec<Update>);
}

/// How long the follower waits for a gateway's answers.
const ASK_TIMEOUT: Duration = Duration::from_secs(10);
/// Publications waiting to be taken, at most; beyond, they are dropped (the next status of
/// the same machine says it again).
const WAITING: usize = 16_384;

/// A key read back: its cell and what it carries.
fn classify(prefix: &str, key: &str) -> Option<(String, Kind)> {
    let rest = key.strip_prefix(prefix)?.strip_prefix('/')?;
    let c: Vec<&str> = rest.split('/').collect();
    let kind = match c.as_slice() {
        [_, "machine", _, "status"] => Kind::Status,
        [_, "machine", _, "job", _] => Kind::Job,
        [_, "machine", _, "g05", _] => Kind::G05,
        [_, "machine", _, "punch"] => Kind::Punch,
        [_, "plc", _, "status"] => Kind::Plc,
        [_, "plc", _, "tag", _] => Kind::Tag,
        [_, "gateway"] => Kind::Gateway,
        [_, "reload"] => Kind::Reload,
        _ => return None,
    };
    Some((c[0].to_string(), kind))
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Status,
    Job,
    G05,
    Punch,
    Plc,
    Tag,
    Gateway,
    Reload,
}

/// What a sample of `cell` says, decoded; `None` for what does not decode (nothing from the
/// bus can stop the follower).
fn decode(prefix: &str, cell: &str, kind: Kind, s: &Sample) -> Option<Update> {
    let bytes = s.payload().to_bytes();
    Some(match kind {
        Kind::Gateway => Update::Gateway(s.kind() == SampleKind::Put),
        // A delete on a job's key is a cancel request, not an event.
        _ if s.kind() != SampleKind::Put => return None,
        Kind::Status => Update::Status(Box::new(pb::MachineStatus::decode(bytes.as_ref()).ok()?)),
        Kind::Job => Update::Job(pb::JobEvent::decode(bytes.as_ref()).ok()?),
        Kind::G05 => Update::G05(pb::G05Status::decode(bytes.as_ref()).ok()?),
        Kind::Punch => {
            let p = pb::PunchedProgram::decode(bytes.as_ref()).ok()?;
            // Where the library keeps it: its key on the bus (an asset's FileLocation).
            let keys = crate::bus::keys::CellKeys::new(prefix, cell).ok()?;
            let location = keys.program(&p.library_name);
            Update::Punch(Box::new(p), location)
        }
        Kind::Plc => Update::Plc(pb::PlcStatus::decode(bytes.as_ref()).ok()?),
        Kind::Tag => Update::Tag(pb::TagValue::decode(bytes.as_ref()).ok()?),
        // A reload taken is asked about as a gateway that came.
        Kind::Reload => {
            let r = pb::ReloadResult::decode(bytes.as_ref()).ok()?;
            if !r.applied {
                return None;
            }
            Update::Gateway(true)
        }
    })
}

/// A cell's description as its gateway gave it: whole (its `@admin` document's
/// configuration) or only what its statuses show.
#[derive(Debug)]
enum Described {
    Whole(CellDesc),
    FromStatus(CellDesc),
}

/// What a cell's gateway tells a newcomer: the cell's description, then its state.
async fn ask(session: &Session, prefix: &str, cell: &str) -> Option<(Described, Vec<Update>)> {
    // A gateway that does not answer tells nothing: what was known of its cell stays (an
    // empty answer would take every machine away).
    let admin = Client::discover(session, prefix, ASK_TIMEOUT)
        .await
        .ok()?
        .into_iter()
        .find(|(c, _)| c == cell)
        .map(|(_, a)| a)?;
    let client = Client::attach(session.clone(), prefix, cell, admin.clone(), ASK_TIMEOUT).ok()?;
    let (machines, plcs) = tokio::join!(client.status(None), client.plc_status(None));
    // A cell without PLCs answers nothing there: that is no error.
    let plcs = plcs.unwrap_or_default();
    // Its description from its configuration where the role reads it; else from its
    // statuses, which must then have come (none would describe a cell without machines).
    let (desc, machines) = match CellDesc::from_admin(cell, &admin) {
        Some(d) => (Described::Whole(d), machines.unwrap_or_default()),
        None => {
            let machines = machines.ok()?;
            let d = CellDesc::from_status(cell, &machines, &plcs);
            (Described::FromStatus(d), machines)
        }
    };
    let mut updates = Vec::new();
    // How each machine's last job ended (one that failed when the gateway restarted under it
    // included): EXECUTION says it until a newer job starts.
    let mut ended: std::collections::BTreeMap<String, pb::JobEvent> = Default::default();
    for e in client.recent_jobs(None).await.unwrap_or_default() {
        if crate::client::is_end(&e) {
            ended.insert(e.machine.clone(), e);
        }
    }
    for m in &machines {
        if m.current_job_id.is_empty()
            && let Some(e) = ended.remove(&m.machine)
        {
            updates.push(Update::Job(e));
        }
    }
    for m in &machines {
        if !m.current_job_id.is_empty()
            && let Ok(q) = client.queue(&m.machine).await
        {
            updates.push(Update::Queue(m.machine.clone(), q));
        }
    }
    updates.extend(machines.into_iter().map(|m| Update::Status(Box::new(m))));
    updates.extend(plcs.into_iter().map(Update::Plc));
    Some((desc, updates))
}

/// Subscribes on `session` to the cells under `prefix` (or the one `only`), and feeds
/// `follower` until `stop`. `own`: the description of the gateway's own cell, which needs no
/// asking.
pub async fn start(
    session: Session,
    prefix: String,
    only: Option<String>,
    own: Option<CellDesc>,
    follower: Arc<dyn Follower>,
    stop: CancellationToken,
) -> zenoh::Result<()> {
    let c = only.clone().unwrap_or_else(|| "*".to_string());
    let keys = [
        format!("{prefix}/{c}/machine/*/status"),
        format!("{prefix}/{c}/machine/*/job/*"),
        format!("{prefix}/{c}/machine/*/g05/*"),
        format!("{prefix}/{c}/machine/*/punch"),
        format!("{prefix}/{c}/plc/*/status"),
        format!("{prefix}/{c}/plc/*/tag/*"),
        format!("{prefix}/{c}/reload"),
    ];
    let (tx, mut rx) = mpsc::channel::<Sample>(WAITING);
    let subscribers = crate::client::subscribe_into(&session, keys, &tx).await?;
    let tokens = {
        let tx = tx.clone();
        session
            .liveliness()
            .declare_subscriber(format!("{prefix}/{c}/gateway"))
            .history(true)
            .callback(move |s| {
                let _ = tx.try_send(s);
            })
            .await?
    };
    let own_cell = own.as_ref().map(|d| d.cell.clone());
    if let Some(desc) = own {
        follower.describe(&desc);
        // The gateway's own cell: it is there while the follower runs.
        follower.take(&desc.cell, vec![Update::Gateway(true)]);
    }
    let (asked_tx, mut asked) = mpsc::channel::<Asked>(64);
    // The cells whose gateway is there (its token): one that does not answer yet is asked
    // again while it is.
    let mut alive: std::collections::HashSet<String> = Default::default();
    if let Some(cell) = own_cell {
        // Its state now, whether or not the session shows its own token to itself.
        alive.insert(cell.clone());
        ask_later(&session, &prefix, &asked_tx, cell, 0);
    }
    tokio::spawn(async move {
        let _keep = (subscribers, tokens);
        loop {
            tokio::select! {
                () = stop.cancelled() => break,
                Some((cell, answer, tries)) = asked.recv() => {
                    let Some((desc, updates)) = answer else {
                        if alive.contains(&cell) {
                            ask_later(&session, &prefix, &asked_tx, cell, tries + 1);
                        }
                        continue;
                    };
                    let desc = match (desc, follower.known(&cell)) {
                        (Described::Whole(d), _) | (Described::FromStatus(d), None) => d,
                        // What statuses cannot show stays as it was known.
                        (Described::FromStatus(d), Some(known)) => known.with_names_of(&d),
                    };
                    follower.describe(&desc);
                    let mut all = vec![Update::Gateway(true)];
                    all.extend(updates);
                    follower.take(&cell, all);
                }
                s = rx.recv() => {
                    let Some(s) = s else { break };
                    let Some((cell, kind)) = classify(&prefix, s.key_expr().as_str()) else {
                        continue;
                    };
                    let Some(update) = decode(&prefix, &cell, kind, &s) else { continue };
                    match update {
                        // Ask what it has (again, if it came back) before marking it up.
                        Update::Gateway(true) => {
                            alive.insert(cell.clone());
                            ask_later(&session, &prefix, &asked_tx, cell, 0);
                        }
                        Update::Gateway(false) => {
                            if kind == Kind::Gateway {
                                alive.remove(&cell);
                            }
                            follower.take(&cell, vec![update]);
                        }
                        update => follower.take(&cell, vec![update]),
                    }
                }
            }
        }
    });
    Ok(())
}

/// A gateway's answer: its cell, what it said (`None`: it did not answer), how many times
/// it was asked before.
type Asked = (String, Option<(Described, Vec<Update>)>, u32);

/// Asks `cell`'s gateway what it has, after a wait that grows with `tries` (none the first
/// time; 1, 2, 4 … s, at most 30 s), and sends the answer to `tx`.
fn ask_later(session: &Session, prefix: &str, tx: &mpsc::Sender<Asked>, cell: String, tries: u32) {
    let (session, prefix, tx) = (session.clone(), prefix.to_string(), tx.clone());
    tokio::spawn(async move {
        if tries > 0 {
            let wait = Duration::from_secs(1 << (tries - 1).min(5)).min(Duration::from_secs(30));
            tokio::time::sleep(wait).await;
        }
        let answer = ask(&session, &prefix, &cell).await;
        let _ = tx.send((cell, answer, tries)).await;
    });
}

#[cfg(test)]
mod tests;
