//! One machine on the bus: its view (status, DI, recent jobs) kept up to date from its link's
//! and its job manager's events, and the task that publishes them through the machine's
//! publishers of each route (status, DI, alarm, punch, job events) and holds its liveliness
//! token `P/C/machine/M` while its link is up.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::{broadcast, watch};
use tokio_util::sync::CancellationToken;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Publisher;
use zenoh::qos::CongestionControl;

use super::BusError;
use super::context::RouteContext;
use super::keys::MachineLeaf;
use super::payload::{self, BusMessage, encoding};
use super::route_job::JobEventPublisher;
use super::route_punch::{Outcome, PunchDesk, PunchSettings};
use super::route_status::StatusPublisher;
use super::{route_alarm, route_io, route_punch};
use crate::config::MachineConfig;
use crate::fanuc::host::LinkState;
use crate::g05::G05Desk;
use crate::jobs::{self, JobsHandle, JobsSnapshot};
use crate::link::driver::{LinkCommand, LinkEvent, LinkHandle};
use crate::pb;

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
    pub g05: Arc<G05Desk>,
    view: Mutex<View>,
}

impl Machine {
    pub fn new(
        config: MachineConfig,
        link: LinkHandle,
        jobs: JobsHandle,
        g05: Arc<G05Desk>,
    ) -> Self {
        let status = pb::MachineStatus {
            machine: config.name.clone(),
            protocol: payload::protocol(config.protocol) as i32,
            link_state: pb::LinkState::Down as i32,
            counters: Some(pb::LinkCounters::default()),
            ..pb::MachineStatus::default()
        };
        // The jobs the journal kept answer gets by id from the start.
        let recent_jobs = jobs.restored_events().iter().cloned().collect();
        Machine {
            config,
            link,
            jobs,
            g05,
            view: Mutex::new(View {
                status,
                recent_jobs,
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
        s.g05 = self
            .g05
            .current()
            .map(|h| payload::g05_status(&h.status().borrow()));
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
            LinkEvent::Waiting {
                what,
                since_unix_ms,
            } => {
                view.status.waiting_for = what.unwrap_or_default().to_string();
                view.status.waiting_since_unix_ms = if what.is_some() { *since_unix_ms } else { 0 };
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

    /// Keeps `event` as the latest of its job, and at most `keep` jobs.
    pub fn remember_job_event(&self, event: &pb::JobEvent, keep: usize) {
        let mut view = self.view();
        let recent = &mut view.recent_jobs;
        if let Some(i) = recent.iter().position(|e| e.job_id == event.job_id) {
            recent.remove(i);
        }
        recent.push_back(event.clone());
        while recent.len() > keep {
            recent.pop_front();
        }
    }
}

enum Extra {
    Di(pb::DiImage),
    Alarm(pb::AlarmEvent),
}

/// One of a machine's publishers: messages `M` on `P/C/machine/M/<leaf>`, with the QoS its
/// route chose. Undeclared when dropped.
pub(crate) struct MachinePublisher<M> {
    publisher: Publisher<'static>,
    message: std::marker::PhantomData<fn(&M)>,
}

impl<M: BusMessage> MachinePublisher<M> {
    pub async fn declare(
        ctx: &RouteContext,
        machine: &str,
        leaf: MachineLeaf,
        congestion: CongestionControl,
    ) -> Result<Self, BusError> {
        let key = ctx.keys.leaf(machine, leaf);
        let publisher = ctx
            .session
            .declare_publisher(key.clone())
            .encoding(encoding::<M>())
            .congestion_control(congestion)
            .await
            .map_err(|source| BusError::Declare {
                what: "publisher",
                key,
                source,
            })?;
        Ok(MachinePublisher {
            publisher,
            message: std::marker::PhantomData,
        })
    }

    pub async fn publish(&self, message: &M) {
        if let Err(e) = self.publisher.put(message.encode_to_vec()).await {
            tracing::warn!(key = %self.publisher.key_expr(), error = %e, "publishing failed");
        }
    }
}

/// A machine's task and what it publishes through.
pub(crate) struct MachineTask {
    machine: Arc<Machine>,
    ctx: RouteContext,
    status: StatusPublisher,
    job_publisher: JobEventPublisher,
    di: MachinePublisher<pb::DiImage>,
    alarm: MachinePublisher<pb::AlarmEvent>,
    punch: MachinePublisher<pb::PunchedProgram>,
    desk: PunchDesk,
    token: Option<LivelinessToken>,
    link_events: broadcast::Receiver<LinkEvent>,
    job_events: broadcast::Receiver<Arc<pb::JobEvent>>,
    snapshot: watch::Receiver<JobsSnapshot>,
}

/// What a machine's task listens to, subscribed before the gateway first awaits so that no
/// event of a running link is missed.
pub(crate) struct MachineFeeds {
    pub link_events: broadcast::Receiver<LinkEvent>,
    pub job_events: broadcast::Receiver<Arc<pb::JobEvent>>,
    pub snapshot: watch::Receiver<JobsSnapshot>,
}

impl MachineFeeds {
    /// `job_events`: the job manager's events subscribed before it ran.
    pub fn subscribe(
        link: &LinkHandle,
        jobs: &JobsHandle,
        job_events: broadcast::Receiver<Arc<pb::JobEvent>>,
    ) -> Self {
        MachineFeeds {
            link_events: link.subscribe(),
            job_events,
            snapshot: jobs.snapshot(),
        }
    }
}

impl MachineTask {
    /// Declares the machine's publishers.
    pub async fn declare(
        ctx: &RouteContext,
        machine: Arc<Machine>,
        feeds: MachineFeeds,
        punch: PunchSettings,
    ) -> Result<Self, BusError> {
        let name = machine.name().to_string();
        Ok(MachineTask {
            status: StatusPublisher::declare(ctx, &name).await?,
            job_publisher: JobEventPublisher::default(),
            di: route_io::declare_di_publisher(ctx, &name).await?,
            alarm: route_alarm::declare_publisher(ctx, &name).await?,
            punch: route_punch::declare_publisher(ctx, &name).await?,
            desk: PunchDesk::new(&name, punch),
            token: None,
            ctx: ctx.clone(),
            machine,
            link_events: feeds.link_events,
            job_events: feeds.job_events,
            snapshot: feeds.snapshot,
        })
    }

    /// Keeps the view, publishes status on change, DI when read, alarms, punched programs
    /// and job events; holds the liveliness token while the link is up; polls DI when
    /// configured. Ends when `stop` is cancelled, after publishing the job events still
    /// pending; its publishers and token are undeclared when it returns.
    pub async fn run(mut self, stop: CancellationToken) {
        let machine = Arc::clone(&self.machine);
        let mut poll = machine
            .config
            .di_poll_ms
            .filter(|_| machine.config.protocol.is_a_family())
            .map(|ms| {
                let mut t = tokio::time::interval(Duration::from_millis(u64::from(ms)));
                t.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
                t
            });
        let mut jobs_running = true;
        // Events the link sent before this task subscribed are not replayed: start from its
        // state.
        if let Some(state) = machine.link.state() {
            let _ = machine.on_link_event(&LinkEvent::State { state });
            self.sync_token().await;
        }
        self.status.publish(&machine).await;
        loop {
            tokio::select! {
                () = stop.cancelled() => break,
                event = self.link_events.recv() => match event {
                    Ok(event) => self.on_link_event(event).await,
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        tracing::warn!(machine = %machine.name(), missed = n, "the bus fell behind this link's events");
                        let outcome = self.desk.lost(n);
                        self.publish_punch_outcome(outcome).await;
                    }
                    // Cannot happen while the machine holds its link handle.
                    Err(broadcast::error::RecvError::Closed) => break,
                },
                event = self.job_events.recv() => match event {
                    Ok(event) => self.job_publisher.publish(&self.ctx, &machine, &event).await,
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        tracing::warn!(machine = %machine.name(), missed = n, "the bus fell behind this machine's job events");
                    }
                    Err(broadcast::error::RecvError::Closed) => break,
                },
                changed = self.snapshot.changed(), if jobs_running => {
                    if changed.is_ok() {
                        let s = self.snapshot.borrow_and_update().clone();
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
            self.status.publish(&machine).await;
        }
        // The job manager stopped first: publish the ends it reported.
        while let Ok(event) = self.job_events.try_recv() {
            self.job_publisher
                .publish(&self.ctx, &machine, &event)
                .await;
        }
        let s = self.snapshot.borrow().clone();
        machine.on_jobs_snapshot(&s);
        self.status.publish(&machine).await;
        if let Some(t) = self.token.take() {
            undeclare_token(t).await;
        }
    }

    async fn on_link_event(&mut self, event: LinkEvent) {
        let machine = Arc::clone(&self.machine);
        if let LinkEvent::Punched { data } = &event {
            for outcome in self.desk.feed(data, &machine.jobs).await {
                self.publish_punch_outcome(outcome).await;
            }
            return;
        }
        if let LinkEvent::PunchDamaged { cause } = &event {
            return self.desk.damaged(cause);
        }
        let was_receiving = machine.view().link_state == Some(LinkState::Receiving);
        match machine.on_link_event(&event) {
            Some(Extra::Di(di)) => self.di.publish(&di).await,
            Some(Extra::Alarm(alarm)) => self.alarm.publish(&alarm).await,
            None => {}
        }
        // The punch-out is over once the link stops receiving (DC4, §6.1.1 2).
        let receiving = machine.view().link_state == Some(LinkState::Receiving);
        if was_receiving
            && !receiving
            && let Some(outcome) = self.desk.finish()
        {
            self.publish_punch_outcome(outcome).await;
        }
        self.sync_token().await;
    }

    /// Publishes a punched program and the alarm that may come with it.
    async fn publish_punch_outcome(&self, outcome: Outcome) {
        if let Some(punched) = outcome.punched {
            Machine::counters(&mut self.machine.view()).programs_punched += 1;
            self.punch.publish(&punched).await;
        }
        if let Some((message, kind)) = outcome.alarm {
            let event = self.machine.alarm_event(kind, "", message);
            self.machine.view().status.last_alarm = Some(event.clone());
            self.alarm.publish(&event).await;
        }
    }

    /// Declares the machine's liveliness token while its link is up, and withdraws it
    /// otherwise.
    async fn sync_token(&mut self) {
        let up = self.machine.link_up();
        if up && self.token.is_none() {
            let key = self.ctx.keys.machine(self.machine.name());
            match self
                .ctx
                .session
                .liveliness()
                .declare_token(key.as_str())
                .await
            {
                Ok(t) => self.token = Some(t),
                Err(e) => {
                    tracing::warn!(%key, error = %e, "cannot declare the machine's liveliness token")
                }
            }
        } else if !up && let Some(t) = self.token.take() {
            undeclare_token(t).await;
        }
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
