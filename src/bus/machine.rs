//! One machine on the bus: its view (status, DI, recent jobs) kept up to date from its link's
//! and its job manager's events, and the task that publishes them.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use prost::Message;
use tokio::sync::{broadcast, watch};
use tokio_util::sync::CancellationToken;
use zenoh::Session;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Publisher;
use zenoh::qos::CongestionControl;

use super::keys::CellKeys;
use super::payload::{self, BusMessage, encoding};
use super::punch::{Outcome, PunchDesk, PunchSettings};
use crate::config::MachineConfig;
use crate::fanuc::host::LinkState;
use crate::jobs::{self, JobsHandle, JobsSnapshot};
use crate::link::driver::{LinkCommand, LinkEvent, LinkHandle};
use crate::pb;

/// Finished jobs whose last event a `get` on `P/C/machine/M/job/*` still answers.
pub const RECENT_JOBS: usize = 256;

/// What the bus knows of a machine right now.
#[derive(Debug, Default)]
pub(crate) struct View {
    pub status: pb::MachineStatus,
    pub link_state: Option<LinkState>,
    pub last_di: Option<pb::DiImage>,
    /// The last event of each recent job, oldest first.
    pub recent_jobs: VecDeque<pb::JobEvent>,
}

/// A machine of the cell, shared by its task and the routes.
#[derive(Debug)]
pub(crate) struct Machine {
    pub config: MachineConfig,
    pub link: LinkHandle,
    pub jobs: JobsHandle,
    view: Mutex<View>,
}

impl Machine {
    pub fn new(config: MachineConfig, link: LinkHandle, jobs: JobsHandle) -> Self {
        let status = pb::MachineStatus {
            machine: config.name.clone(),
            protocol: payload::protocol(config.protocol) as i32,
            link_state: pb::LinkState::Down as i32,
            counters: Some(pb::LinkCounters::default()),
            ..pb::MachineStatus::default()
        };
        Machine {
            config,
            link,
            jobs,
            view: Mutex::new(View {
                status,
                ..View::default()
            }),
        }
    }

    pub fn name(&self) -> &str {
        &self.config.name
    }

    /// The view; never held across an await.
    pub fn view(&self) -> MutexGuard<'_, View> {
        // A panic while the lock was held leaves a view that is still usable.
        self.view
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The status as of now.
    pub fn status(&self) -> pb::MachineStatus {
        let mut s = self.view().status.clone();
        s.unix_ms = jobs::unix_ms();
        s
    }

    pub fn link_up(&self) -> bool {
        self.view().link_state.is_some_and(payload::link_up)
    }

    /// How long to wait for the board to answer RDI or to output SDO: the host speaks at
    /// the next SAT or GTD, and the board sends SAT every Tp seconds (§4.4, §4.5). Right after
    /// an exchange that next SAT is a whole poll plus the board's turnaround away, so allow
    /// one missed poll: 2·Tp + 1 s.
    pub fn exchange_timeout(&self) -> Duration {
        Duration::from_secs(2 * u64::from(self.config.params().tp) + 1)
    }

    fn counters(view: &mut View) -> &mut pb::LinkCounters {
        view.status
            .counters
            .get_or_insert_with(pb::LinkCounters::default)
    }

    /// Folds a link event into the view; returns what to publish besides the status.
    fn on_link_event(&self, event: &LinkEvent) -> Option<Extra> {
        let mut view = self.view();
        match event {
            LinkEvent::State { state } => {
                view.link_state = Some(*state);
                view.status.link_state = payload::link_state(*state) as i32;
                None
            }
            LinkEvent::Status { status } => {
                view.status.sat = Some(payload::sat(status));
                None
            }
            LinkEvent::Di { value } => {
                let di = pb::DiImage {
                    machine: self.name().to_string(),
                    value: u32::from(*value),
                    unix_ms: jobs::unix_ms(),
                };
                view.status.di_image = Some(u32::from(*value));
                view.last_di = Some(di.clone());
                Some(Extra::Di(di))
            }
            LinkEvent::Do { value } => {
                view.status.do_image = Some(u32::from(*value));
                None
            }
            LinkEvent::ProtocolError { error, retried } => {
                let c = Self::counters(&mut view);
                c.protocol_errors += 1;
                if *retried {
                    c.retries += 1;
                }
                if error.is_checksum() {
                    c.checksum_errors += 1;
                }
                None
            }
            LinkEvent::Alarm(error) => {
                Self::counters(&mut view).link_alarms += 1;
                view.status.link_state = pb::LinkState::Alarm as i32;
                let alarm = error.cnc_alarm();
                let message = match alarm {
                    Some(a) => format!("{}: {error}", a.message()),
                    None => error.to_string(),
                };
                let event = self.alarm_event(
                    pb::AlarmKind::LinkAlarm,
                    alarm.map(|a| a.number()).unwrap_or_default(),
                    message,
                );
                view.status.last_alarm = Some(event.clone());
                Some(Extra::Alarm(event))
            }
            LinkEvent::CncAlarm => {
                view.status.link_state = pb::LinkState::Alarm as i32;
                let how = if self.config.protocol.is_a_family() {
                    "the CNC raised an alarm (ALM; §4.4.1)"
                } else {
                    "the CNC raised an alarm (NAK; §6.4)"
                };
                let event = self.alarm_event(pb::AlarmKind::CncAlarm, "", how.to_string());
                view.status.last_alarm = Some(event.clone());
                Some(Extra::Alarm(event))
            }
            LinkEvent::CncReset => {
                let how = if self.config.protocol.is_a_family() {
                    "the CNC was reset (RST; §4.4.1)"
                } else {
                    "the CNC was reset (SYN; §6.4)"
                };
                let event = self.alarm_event(pb::AlarmKind::CncReset, "", how.to_string());
                view.status.last_alarm = Some(event.clone());
                Some(Extra::Alarm(event))
            }
            LinkEvent::Stopped { .. } => {
                view.link_state = None;
                view.status.link_state = pb::LinkState::Down as i32;
                None
            }
            _ => None,
        }
    }

    fn alarm_event(&self, kind: pb::AlarmKind, number: &str, message: String) -> pb::AlarmEvent {
        pb::AlarmEvent {
            machine: self.name().to_string(),
            kind: kind as i32,
            alarm_number: number.to_string(),
            message,
            unix_ms: jobs::unix_ms(),
        }
    }

    fn on_jobs_snapshot(&self, snapshot: &JobsSnapshot) {
        let mut view = self.view();
        view.status.current_job_id = snapshot.active.clone().unwrap_or_default();
        view.status.jobs_waiting = u32::try_from(snapshot.waiting).unwrap_or(u32::MAX);
        let c = Self::counters(&mut view);
        c.nc_bytes_sent = snapshot.nc_bytes_sent;
        c.jobs_completed = snapshot.jobs_completed;
        c.jobs_failed = snapshot.jobs_failed;
    }

    fn remember_job_event(&self, event: &pb::JobEvent) {
        let mut view = self.view();
        let recent = &mut view.recent_jobs;
        if let Some(i) = recent.iter().position(|e| e.job_id == event.job_id) {
            recent.remove(i);
        }
        recent.push_back(event.clone());
        while recent.len() > RECENT_JOBS {
            recent.pop_front();
        }
    }
}

enum Extra {
    Di(pb::DiImage),
    Alarm(pb::AlarmEvent),
}

/// The publishers of one machine, declared before its task starts.
pub(crate) struct Publishers {
    pub status: Publisher<'static>,
    pub di: Publisher<'static>,
    pub alarm: Publisher<'static>,
    pub punch: Publisher<'static>,
}

/// The machine's task: keeps the view, publishes status on change, DI when read, alarms,
/// and job events; holds the liveliness token while the link is up; polls DI when
/// configured. Ends when `stop` is cancelled, after publishing the job events still pending.
/// Declares the machine's liveliness token while its link is up, and withdraws it otherwise.
async fn sync_token(
    machine: &Machine,
    session: &Session,
    keys: &CellKeys,
    token: &mut Option<LivelinessToken>,
) {
    let up = machine.link_up();
    if up && token.is_none() {
        let key = keys.machine(machine.name());
        match session.liveliness().declare_token(key.as_str()).await {
            Ok(t) => *token = Some(t),
            Err(e) => {
                tracing::warn!(%key, error = %e, "cannot declare the machine's liveliness token")
            }
        }
    } else if !up && let Some(t) = token.take() {
        undeclare_token(t).await;
    }
}

#[allow(clippy::too_many_arguments)]
pub(crate) async fn run(
    machine: Arc<Machine>,
    session: Session,
    keys: Arc<CellKeys>,
    publishers: Publishers,
    mut link_events: broadcast::Receiver<LinkEvent>,
    mut job_events: broadcast::Receiver<pb::JobEvent>,
    mut snapshot: watch::Receiver<JobsSnapshot>,
    punch: PunchSettings,
    stop: CancellationToken,
) {
    let name = machine.name().to_string();
    let mut desk = PunchDesk::new(&name, punch);
    let mut token: Option<LivelinessToken> = None;
    let mut published: Option<pb::MachineStatus> = None;
    let poll = machine
        .config
        .di_poll_ms
        .filter(|_| machine.config.protocol.is_a_family())
        .map(|ms| {
            let mut t = tokio::time::interval(Duration::from_millis(u64::from(ms)));
            t.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            t
        });
    let mut poll = poll;
    let mut jobs_running = true;
    // Events the link sent before this task subscribed are not replayed: start from its state.
    if let Some(state) = machine.link.state() {
        let _ = machine.on_link_event(&LinkEvent::State { state });
        sync_token(&machine, &session, &keys, &mut token).await;
    }
    publish_status(&machine, &publishers.status, &mut published).await;
    loop {
        tokio::select! {
            () = stop.cancelled() => break,
            event = link_events.recv() => match event {
                Ok(LinkEvent::Punched { data }) => {
                    for outcome in desk.feed(&data, &machine.jobs).await {
                        publish_punch_outcome(&machine, &publishers, outcome).await;
                    }
                }
                Ok(event) => {
                    let was_receiving = machine.view().link_state == Some(LinkState::Receiving);
                    let extra = machine.on_link_event(&event);
                    match extra {
                        Some(Extra::Di(di)) => put(&publishers.di, &di).await,
                        Some(Extra::Alarm(alarm)) => put(&publishers.alarm, &alarm).await,
                        None => {}
                    }
                    // The punch-out is over once the link stops receiving (DC4, §6.1.1 2).
                    let receiving = machine.view().link_state == Some(LinkState::Receiving);
                    if was_receiving && !receiving && let Some(outcome) = desk.finish() {
                        publish_punch_outcome(&machine, &publishers, outcome).await;
                    }
                    sync_token(&machine, &session, &keys, &mut token).await;
                }
                Err(broadcast::error::RecvError::Lagged(n)) => {
                    tracing::warn!(machine = %name, missed = n, "the bus fell behind this link's events");
                    let outcome = desk.lost(n);
                    publish_punch_outcome(&machine, &publishers, outcome).await;
                }
                // Cannot happen while the machine holds its link handle.
                Err(broadcast::error::RecvError::Closed) => break,
            },
            event = job_events.recv() => match event {
                Ok(event) => publish_job_event(&machine, &session, &keys, &event).await,
                Err(broadcast::error::RecvError::Lagged(n)) => {
                    tracing::warn!(machine = %name, missed = n, "the bus fell behind this machine's job events");
                }
                Err(broadcast::error::RecvError::Closed) => break,
            },
            changed = snapshot.changed(), if jobs_running => {
                if changed.is_ok() {
                    let s = snapshot.borrow_and_update().clone();
                    machine.on_jobs_snapshot(&s);
                } else {
                    // The job manager has stopped; its last snapshot is folded in below.
                    jobs_running = false;
                }
            }
            () = tick(&mut poll) => {
                // RDI needs an initialised link (§4.4.1); a read that fails is no loss.
                if machine.link_up() {
                    let _ = machine.link.send(LinkCommand::ReadDi).await;
                }
            }
        }
        publish_status(&machine, &publishers.status, &mut published).await;
    }
    // The job manager stopped first: publish the ends it reported.
    while let Ok(event) = job_events.try_recv() {
        publish_job_event(&machine, &session, &keys, &event).await;
    }
    let s = snapshot.borrow().clone();
    machine.on_jobs_snapshot(&s);
    publish_status(&machine, &publishers.status, &mut published).await;
    if let Some(t) = token.take() {
        undeclare_token(t).await;
    }
    for p in [
        publishers.status,
        publishers.di,
        publishers.alarm,
        publishers.punch,
    ] {
        if let Err(e) = p.undeclare().await {
            tracing::debug!(error = %e, "undeclaring a publisher failed");
        }
    }
}

/// Publishes a punched program and the alarm that may come with it.
async fn publish_punch_outcome(machine: &Machine, publishers: &Publishers, outcome: Outcome) {
    if let Some(punched) = outcome.punched {
        Machine::counters(&mut machine.view()).programs_punched += 1;
        put(&publishers.punch, &punched).await;
    }
    if let Some((message, kind)) = outcome.alarm {
        let event = machine.alarm_event(kind, "", message);
        machine.view().status.last_alarm = Some(event.clone());
        put(&publishers.alarm, &event).await;
    }
}

async fn tick(poll: &mut Option<tokio::time::Interval>) {
    match poll {
        Some(t) => {
            t.tick().await;
        }
        None => std::future::pending().await,
    }
}

async fn undeclare_token(token: LivelinessToken) {
    if let Err(e) = token.undeclare().await {
        tracing::debug!(error = %e, "undeclaring a liveliness token failed");
    }
}

/// Publishes the status if it changed since `published` (the time of day aside).
async fn publish_status(
    machine: &Machine,
    publisher: &Publisher<'static>,
    published: &mut Option<pb::MachineStatus>,
) {
    let current = machine.view().status.clone();
    if published.as_ref() == Some(&current) {
        return;
    }
    let mut stamped = current.clone();
    stamped.unix_ms = jobs::unix_ms();
    put(publisher, &stamped).await;
    *published = Some(current);
}

async fn put<M: BusMessage>(publisher: &Publisher<'static>, message: &M) {
    if let Err(e) = publisher.put(message.encode_to_vec()).await {
        tracing::warn!(key = %publisher.key_expr(), error = %e, "publishing failed");
    }
}

async fn publish_job_event(
    machine: &Machine,
    session: &Session,
    keys: &CellKeys,
    event: &pb::JobEvent,
) {
    machine.remember_job_event(event);
    let key = keys.job_events(machine.name(), &event.job_id);
    let sent = session
        .put(key.as_str(), event.encode_to_vec())
        .encoding(encoding::<pb::JobEvent>())
        .congestion_control(CongestionControl::Block)
        .await;
    if let Err(e) = sent {
        tracing::warn!(%key, error = %e, "publishing a job event failed");
    }
}

/// Declares the machine's publishers: status and DI telemetry drop under congestion,
/// alarms do not.
pub(crate) async fn declare_publishers(
    session: &Session,
    keys: &CellKeys,
    name: &str,
) -> Result<Publishers, (String, zenoh::Error)> {
    use super::keys::MachineLeaf;
    let declare = |leaf: MachineLeaf, enc: zenoh::bytes::Encoding, cc: CongestionControl| {
        let key = keys.leaf(name, leaf);
        async move {
            session
                .declare_publisher(key.clone())
                .encoding(enc)
                .congestion_control(cc)
                .await
                .map_err(|e| (key, e))
        }
    };
    Ok(Publishers {
        status: declare(
            MachineLeaf::Status,
            encoding::<pb::MachineStatus>(),
            CongestionControl::Drop,
        )
        .await?,
        di: declare(
            MachineLeaf::Di,
            encoding::<pb::DiImage>(),
            CongestionControl::Drop,
        )
        .await?,
        alarm: declare(
            MachineLeaf::Alarm,
            encoding::<pb::AlarmEvent>(),
            CongestionControl::Block,
        )
        .await?,
        punch: declare(
            MachineLeaf::Punch,
            encoding::<pb::PunchedProgram>(),
            CongestionControl::Block,
        )
        .await?,
    })
}
