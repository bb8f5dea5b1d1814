//! What the console's pages see as it happens: the cells' publications, subscribed once for
//! every page, coalesced, and handed to each page's event stream.
//!
//! A busy cell publishes a status and a job's progress several times a second per machine;
//! a page needs at most a few a second of each. So the hub keeps, of each machine's status,
//! each job's progress, each tag and each G05 stream, only the latest since the last flush,
//! and flushes every [`FLUSH_EVERY`]; an alarm, a job's end and a punched program go out at
//! once, never dropped. While no page listens, nothing is decoded.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use prost::Message;
use tokio::sync::broadcast;
use tokio_util::sync::CancellationToken;
use zenoh::Session;
use zenoh::sample::Sample;

use cellgate_core::pb;

/// How often coalesced updates go out: at most 4 a second of each.
pub const FLUSH_EVERY: Duration = Duration::from_millis(250);
/// Punched programs kept per machine, for the machine page.
const PUNCHED_KEPT: usize = 20;

/// One event for the pages.
#[derive(Debug, Clone)]
pub struct LiveEvent {
    pub cell: String,
    /// The machine or PLC link it is about.
    pub name: String,
    /// The SSE event name: `status`, `job`, `alarm`, `punch`, `di`, `tag`, `plc`, `g05`.
    pub kind: &'static str,
    /// The message as proto3 JSON.
    pub json: String,
}

/// What arrived, by kind of key.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Kind {
    Status,
    Job,
    Alarm,
    Punch,
    Di,
    Tag,
    Plc,
    G05,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Status => "status",
            Kind::Job => "job",
            Kind::Alarm => "alarm",
            Kind::Punch => "punch",
            Kind::Di => "di",
            Kind::Tag => "tag",
            Kind::Plc => "plc",
            Kind::G05 => "g05",
        }
    }
}

/// A key read back: its cell, machine or PLC, kind, and what coalesces it with later ones.
fn classify(prefix: &str, key: &str) -> Option<(String, String, Kind, String)> {
    let rest = key.strip_prefix(prefix)?.strip_prefix('/')?;
    let c: Vec<&str> = rest.split('/').collect();
    let (cell, kind, name, sub) = match c.as_slice() {
        [cell, "machine", m, "status"] => (cell, Kind::Status, m, ""),
        [cell, "machine", m, "job", id] => (cell, Kind::Job, m, *id),
        [cell, "machine", m, "alarm"] => (cell, Kind::Alarm, m, ""),
        [cell, "machine", m, "punch"] => (cell, Kind::Punch, m, ""),
        [cell, "machine", m, "di"] => (cell, Kind::Di, m, ""),
        [cell, "machine", m, "g05", s] => (cell, Kind::G05, m, *s),
        [cell, "plc", p, "tag", t] => (cell, Kind::Tag, p, *t),
        [cell, "plc", p, "status"] => (cell, Kind::Plc, p, ""),
        _ => return None,
    };
    Some((
        cell.to_string(),
        name.to_string(),
        kind,
        format!("{cell}/{name}/{}/{sub}", kind.name()),
    ))
}

fn to_json<M: Message + Default + serde::Serialize>(bytes: &[u8]) -> Option<(String, M)> {
    let m = M::decode(bytes).ok()?;
    Some((serde_json::to_string(&m).ok()?, m))
}

/// The JSON of a payload of `kind`; whether it must never be coalesced away.
fn render(kind: Kind, bytes: &[u8]) -> Option<String> {
    Some(match kind {
        Kind::Status => to_json::<pb::MachineStatus>(bytes)?.0,
        Kind::Job => to_json::<pb::JobEvent>(bytes)?.0,
        Kind::Alarm => to_json::<pb::AlarmEvent>(bytes)?.0,
        Kind::Punch => to_json::<pb::PunchedProgram>(bytes)?.0,
        Kind::Di => to_json::<pb::DiImage>(bytes)?.0,
        Kind::Tag => to_json::<pb::TagValue>(bytes)?.0,
        Kind::Plc => to_json::<pb::PlcStatus>(bytes)?.0,
        Kind::G05 => to_json::<pb::G05Status>(bytes)?.0,
    })
}

/// Whether an event of `kind` with these bytes must go out as it is (never replaced by a
/// later one): alarms, punched programs, a job's end.
fn urgent(kind: Kind, bytes: &[u8]) -> bool {
    match kind {
        Kind::Alarm | Kind::Punch => true,
        Kind::Job => pb::JobEvent::decode(bytes).is_ok_and(|e| {
            matches!(
                e.kind,
                Some(
                    pb::job_event::Kind::Completed(_)
                        | pb::job_event::Kind::Failed(_)
                        | pb::job_event::Kind::Cancelled(_)
                        | pb::job_event::Kind::Queued(_)
                        | pb::job_event::Kind::Started(_)
                )
            )
        }),
        _ => false,
    }
}

/// Punched programs by (cell, machine), newest first.
type Punched = HashMap<(String, String), VecDeque<pb::PunchedProgram>>;

/// The hub: a broadcast of events and the recent punched programs.
#[derive(Clone)]
pub struct Live {
    tx: broadcast::Sender<Arc<LiveEvent>>,
    punched: Arc<Mutex<Punched>>,
}

impl Live {
    /// Subscribes to every cell under `prefix` (or the one `cell`) on `session` and runs the
    /// hub until `stop`.
    pub async fn start(
        session: &Session,
        prefix: &str,
        cell: Option<&str>,
        stop: CancellationToken,
    ) -> zenoh::Result<Live> {
        let (tx, _) = broadcast::channel(8192);
        let live = Live {
            tx,
            punched: Arc::default(),
        };
        let c = cell.unwrap_or("*");
        let keys = [
            format!("{prefix}/{c}/machine/*/status"),
            format!("{prefix}/{c}/machine/*/job/*"),
            format!("{prefix}/{c}/machine/*/alarm"),
            format!("{prefix}/{c}/machine/*/punch"),
            format!("{prefix}/{c}/machine/*/di"),
            format!("{prefix}/{c}/machine/*/g05/*"),
            format!("{prefix}/{c}/plc/*/tag/*"),
            format!("{prefix}/{c}/plc/*/status"),
        ];
        let (sample_tx, mut samples) = tokio::sync::mpsc::channel::<Sample>(16_384);
        let subscribers = crate::client::subscribe_into(session, keys, &sample_tx).await?;
        let hub = live.clone();
        let prefix = prefix.to_string();
        tokio::spawn(async move {
            let _subscribers = subscribers;
            let mut pending: HashMap<String, (String, String, Kind, Vec<u8>)> = HashMap::new();
            let mut flush = tokio::time::interval(FLUSH_EVERY);
            flush.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tokio::select! {
                    () = stop.cancelled() => break,
                    s = samples.recv() => {
                        let Some(s) = s else { break };
                        hub.take(&prefix, &s, &mut pending);
                    }
                    _ = flush.tick() => {
                        for (_, (cell, name, kind, bytes)) in pending.drain() {
                            hub.send(cell, name, kind, &bytes);
                        }
                    }
                }
            }
        });
        Ok(live)
    }

    fn take(
        &self,
        prefix: &str,
        s: &Sample,
        pending: &mut HashMap<String, (String, String, Kind, Vec<u8>)>,
    ) {
        let Some((cell, name, kind, key)) = classify(prefix, s.key_expr().as_str()) else {
            return;
        };
        // A delete on a job's key is a cancel request, not an event.
        if s.kind() != zenoh::sample::SampleKind::Put {
            return;
        }
        let bytes = s.payload().to_bytes().into_owned();
        if kind == Kind::Punch
            && let Ok(p) = pb::PunchedProgram::decode(bytes.as_slice())
            && let Ok(mut all) = self.punched.lock()
        {
            let list = all.entry((cell.clone(), name.clone())).or_default();
            list.push_front(p);
            list.truncate(PUNCHED_KEPT);
        }
        if self.tx.receiver_count() == 0 {
            return;
        }
        if urgent(kind, &bytes) {
            // What was pending of the same key went before it.
            if let Some((c, n, k, b)) = pending.remove(&key) {
                self.send(c, n, k, &b);
            }
            self.send(cell, name, kind, &bytes);
        } else {
            pending.insert(key, (cell, name, kind, bytes));
        }
    }

    fn send(&self, cell: String, name: String, kind: Kind, bytes: &[u8]) {
        if self.tx.receiver_count() == 0 {
            return;
        }
        if let Some(json) = render(kind, bytes) {
            let _ = self.tx.send(Arc::new(LiveEvent {
                cell,
                name,
                kind: kind.name(),
                json,
            }));
        }
    }

    /// A page's feed.
    pub fn subscribe(&self) -> broadcast::Receiver<Arc<LiveEvent>> {
        self.tx.subscribe()
    }

    /// The programs `machine` of `cell` punched since the console started, newest first.
    pub fn punched(&self, cell: &str, machine: &str) -> Vec<pb::PunchedProgram> {
        self.punched
            .lock()
            .ok()
            .and_then(|all| {
                all.get(&(cell.to_string(), machine.to_string()))
                    .map(|l| l.iter().cloned().collect())
            })
            .unwrap_or_default()
    }
}

#[cfg(test)]
mod tests;
