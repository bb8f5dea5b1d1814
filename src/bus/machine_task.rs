//! A machine's task: it follows the machine's link and job manager and publishes what they
//! report through the publishers of each route (status, job events, DI, alarms, punched
//! programs), and holds the machine's liveliness token while the link is up.

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use zenoh::liveliness::LivelinessToken;

use super::context::MachinePublisher;
use super::context::RouteContext;
use super::error::BusError;
use super::machine::{Extra, Machine};
use super::published::MachinePublication;
use super::record::Recorder;
use super::route_job::JobEventPublisher;
use super::route_punch::{Outcome, PunchDesk, PunchSettings};
use super::route_status::StatusPublisher;
use crate::jobs::{JobsHandle, JobsSnapshot};
use crate::link::driver::{LinkCommand, LinkEvent, LinkHandle};
use crate::link::fanout;
use cellgate_core::fanuc::host::LinkState;
use cellgate_core::pb;

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
    link_events: fanout::Receiver<LinkEvent>,
    job_events: fanout::Receiver<Arc<pb::JobEvent>>,
    snapshot: watch::Receiver<JobsSnapshot>,
    recorder: Recorder,
}

/// What a machine's task listens to, subscribed before the gateway first awaits so that no
/// event of a running link is missed.
pub(crate) struct MachineFeeds {
    pub link_events: fanout::Receiver<LinkEvent>,
    pub job_events: fanout::Receiver<Arc<pb::JobEvent>>,
    pub snapshot: watch::Receiver<JobsSnapshot>,
}

impl MachineFeeds {
    /// `job_events`: the job manager's events subscribed before it ran.
    pub(super) fn subscribe(
        link: &LinkHandle,
        jobs: &JobsHandle,
        job_events: fanout::Receiver<Arc<pb::JobEvent>>,
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
    pub(super) async fn declare(
        ctx: &RouteContext,
        machine: Arc<Machine>,
        feeds: MachineFeeds,
        punch: PunchSettings,
    ) -> Result<Self, BusError> {
        let name = machine.name().to_string();
        Ok(MachineTask {
            status: StatusPublisher::declare(ctx, &name).await?,
            job_publisher: JobEventPublisher::default(),
            di: MachinePublisher::declare(ctx, &name, MachinePublication::Di).await?,
            alarm: MachinePublisher::declare(ctx, &name, MachinePublication::Alarm).await?,
            punch: MachinePublisher::declare(ctx, &name, MachinePublication::Punch).await?,
            desk: PunchDesk::new(&name, punch).receiving(machine.config.receive_dir.clone()),
            token: None,
            ctx: ctx.clone(),
            machine,
            link_events: feeds.link_events,
            job_events: feeds.job_events,
            snapshot: feeds.snapshot,
            recorder: Recorder::default(),
        })
    }

    /// Keeps the view, publishes status on change, DI when read, alarms, punched programs
    /// and job events; holds the liveliness token while the link is up; polls DI when
    /// configured. Ends when `stop` is cancelled, after publishing the job events still
    /// pending; its publishers and token are undeclared when it returns.
    pub(super) async fn run(mut self, stop: CancellationToken) {
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
        self.publish_status().await;
        loop {
            tokio::select! {
                () = stop.cancelled() => break,
                event = self.link_events.recv() => match event {
                    Ok(event) => self.on_link_event(event).await,
                    Err(fanout::RecvError::Lagged(n)) => {
                        tracing::warn!(machine = %machine.name(), missed = n, "the bus fell behind this link's events");
                        let outcome = self.desk.lost(n);
                        self.publish_punch_outcome(outcome).await;
                    }
                    // Cannot happen while the machine holds its link handle.
                    Err(fanout::RecvError::Closed) => break,
                },
                event = self.job_events.recv() => match event {
                    Ok(event) => {
                        self.recorder.job(&self.ctx.history, machine.name(), &event);
                        self.job_publisher.publish(&self.ctx, &machine, &event).await;
                    }
                    Err(fanout::RecvError::Lagged(n)) => {
                        tracing::warn!(machine = %machine.name(), missed = n, "the bus fell behind this machine's job events");
                    }
                    Err(fanout::RecvError::Closed) => break,
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
            self.publish_status().await;
        }
        // The job manager stopped first: publish the ends it reported.
        while let Ok(event) = self.job_events.try_recv() {
            self.recorder.job(&self.ctx.history, machine.name(), &event);
            self.job_publisher
                .publish(&self.ctx, &machine, &event)
                .await;
        }
        let s = self.snapshot.borrow().clone();
        machine.on_jobs_snapshot(&s);
        self.publish_status().await;
        if let Some(t) = self.token.take() {
            undeclare_token(t).await;
        }
    }

    /// Publishes the status if it changed, and records what changed in the history.
    async fn publish_status(&mut self) {
        if let Some(status) = self.status.publish(&self.machine).await {
            self.recorder
                .status(&self.ctx.history, self.machine.name(), &status);
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
            Some(Extra::Alarm(alarm)) => {
                Recorder::alarm(&self.ctx.history, machine.name(), &alarm);
                self.alarm.publish(&alarm).await;
            }
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
            Recorder::punch(&self.ctx.history, self.machine.name(), &punched);
            self.punch.publish(&punched).await;
        }
        if let Some((message, kind)) = outcome.alarm {
            let event = self.machine.alarm_event(kind, "", "", message);
            self.machine.view().status.last_alarm = Some(event.clone());
            Recorder::alarm(&self.ctx.history, self.machine.name(), &event);
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
