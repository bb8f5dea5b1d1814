//! The machines and PLCs the routes serve, changed while they run (a reload,
//! docs/configuration.md "Reloading"): a machine's job manager and task are started, its jobs
//! held, and both stopped, each machine on its own tokens, so that no other machine's jobs
//! are touched. The routes find machines and PLCs by name in [`Live`] maps, so one added or
//! removed is served or refused from the next request on.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use super::context::{CellNames, Live, RouteContext};
use super::error::BusError;
use super::machine::Machine;
use super::machine_task::{MachineFeeds, MachineTask};
use super::route_plc::{PlcContext, PlcLink};
use super::route_punch::PunchSettings;
use super::{route_plc, route_tag, routes};
use crate::jobs::journal::{JobRecord, Journal};
use crate::jobs::{self, Hold, JobError, JobsSettings};
use crate::link::driver::LinkHandle;
use crate::link::g05::G05Desk;
use cellgate_core::config::{CellConfig, MachineConfig};
use cellgate_core::fanuc::g05::stream::EndReason;

/// A machine of the cell and its running link, as the gateway hands them to
/// [`serve`](super::serve).
#[derive(Debug, Clone)]
pub struct MachineLink {
    pub config: MachineConfig,
    pub link: LinkHandle,
    /// The simulated board on the far end of a `sim` transport, for the `P/C/sim/M/...`
    /// controls; `None` for a real machine.
    pub sim: Option<crate::sim::BoardControl>,
}

/// A machine served: its job manager and task, each on a token of its own.
struct Served {
    machine: Arc<Machine>,
    jobs_stop: CancellationToken,
    machine_stop: CancellationToken,
    job_task: JoinHandle<()>,
    /// Running once the machine's publishers are declared.
    machine_task: Option<JoinHandle<()>>,
}

/// A machine's job manager started and its feeds subscribed, before anything awaits.
struct Prepared {
    served: Served,
    feeds: MachineFeeds,
}

/// The cell's machines as the routes serve them: cheap to clone, shared with the gateway,
/// which adds, holds and removes machines through it while the routes run.
#[derive(Clone)]
pub struct MachineRoutes {
    inner: Arc<Inner>,
}

struct Inner {
    ctx: RouteContext,
    journal: Journal,
    punch: PunchSettings,
    keep_jobs: usize,
    /// Parents of every machine's own tokens: the gateway's stop ends them all at once.
    jobs_stop: CancellationToken,
    machines_stop: CancellationToken,
    routes_stop: CancellationToken,
    served: std::sync::Mutex<BTreeMap<String, Served>>,
    /// The simulated machines' controls, declared with the first simulated machine.
    sim_declared: AtomicBool,
    late_routes: std::sync::Mutex<Vec<JoinHandle<()>>>,
}

impl MachineRoutes {
    pub(super) fn new(
        ctx: RouteContext,
        journal: Journal,
        config: &CellConfig,
        jobs_stop: CancellationToken,
        routes_stop: CancellationToken,
    ) -> Self {
        MachineRoutes {
            inner: Arc::new(Inner {
                ctx,
                journal,
                punch: PunchSettings::from_config(&config.programs),
                keep_jobs: config.programs.keep_jobs,
                jobs_stop,
                machines_stop: CancellationToken::new(),
                routes_stop,
                served: std::sync::Mutex::new(BTreeMap::new()),
                sim_declared: AtomicBool::new(false),
                late_routes: std::sync::Mutex::new(Vec::new()),
            }),
        }
    }

    fn served(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, Served>> {
        self.inner
            .served
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Starts the job manager of `link` with its jobs `restored` from the journal, and
    /// subscribes to its link and jobs: nothing awaits here, so no event of a link that is
    /// already running is missed.
    fn prepare(&self, link: MachineLink, restored: Vec<JobRecord>) -> Prepared {
        let MachineLink {
            config: mc,
            link,
            sim,
        } = link;
        let ctx = &self.inner.ctx;
        let jobs_stop = self.inner.jobs_stop.child_token();
        let settings = JobsSettings {
            rules: mc.program_rules(ctx.library.max_size()),
            library: ctx.library.clone(),
            journal: self.inner.journal.clone(),
            restored,
            keep: self.inner.keep_jobs,
            accept: mc.accept,
        };
        let (jobs, job_task, job_events) =
            jobs::spawn(&mc.name, settings, link.clone(), jobs_stop.clone());
        let feeds = MachineFeeds::subscribe(&link, &jobs, job_events);
        // Streams end (with their end block) with the machine's job manager.
        let g05 = G05Desk::new(&mc, link.clone(), jobs_stop.clone());
        let machine = Arc::new(Machine::new(mc, link, jobs, g05, sim));
        Prepared {
            served: Served {
                machine,
                jobs_stop,
                machine_stop: self.inner.machines_stop.child_token(),
                job_task,
                machine_task: None,
            },
            feeds,
        }
    }

    /// Declares the machine's publishers, runs its task and serves it on the routes.
    async fn serve(&self, p: Prepared) -> Result<(), BusError> {
        let Prepared { mut served, feeds } = p;
        let ctx = &self.inner.ctx;
        let machine = Arc::clone(&served.machine);
        let task =
            match MachineTask::declare(ctx, Arc::clone(&machine), feeds, self.inner.punch.clone())
                .await
            {
                Ok(t) => t,
                Err(e) => {
                    served.jobs_stop.cancel();
                    let _ = served.job_task.await;
                    return Err(e);
                }
            };
        served.machine_task = Some(tokio::spawn(task.run(served.machine_stop.clone())));
        let name = machine.name().to_string();
        ctx.machines.insert(&name, Arc::clone(&machine));
        if let Some(old) = self.served().insert(name.clone(), served) {
            // Never two tasks for one machine: the gateway stops the old one first.
            tracing::error!(machine = %name, "machine served twice; the older one is stopped");
            old.jobs_stop.cancel();
            old.machine_stop.cancel();
        }
        Ok(())
    }

    /// Serves the cell's machines as the gateway starts, with the jobs the journal held.
    pub(super) async fn start(
        &self,
        machines: Vec<MachineLink>,
        mut restored: BTreeMap<String, Vec<JobRecord>>,
    ) -> Result<(), BusError> {
        let mut prepared = Vec::new();
        for link in machines {
            if prepared
                .iter()
                .any(|p: &Prepared| p.served.machine.name() == link.config.name)
            {
                tracing::error!(machine = %link.config.name, "machine given twice; serving the first only");
                continue;
            }
            let jobs = restored.remove(&link.config.name).unwrap_or_default();
            prepared.push(self.prepare(link, jobs));
        }
        for p in prepared {
            self.serve(p).await?;
        }
        Ok(())
    }

    /// Serves a machine whose link a reload started, with whatever jobs the journal holds for
    /// it (the waiting jobs of the link it replaces).
    pub async fn add(&self, link: MachineLink) -> Result<(), BusError> {
        let journal = self.inner.journal.clone();
        let name = link.config.name.clone();
        let simulated = link.sim.is_some();
        let restored = tokio::task::spawn_blocking(move || journal.restore())
            .await
            .map_err(|e| BusError::Internal(e.to_string()))??
            .jobs
            .remove(&name)
            .unwrap_or_default();
        let prepared = self.prepare(link, restored);
        self.serve(prepared).await?;
        if simulated {
            self.declare_sim().await?;
        }
        Ok(())
    }

    /// The simulated machines' controls, once: a cell that starts without a simulated
    /// machine declares them with the first one a reload adds.
    pub(super) async fn declare_sim(&self) -> Result<(), BusError> {
        if self.inner.sim_declared.swap(true, Ordering::SeqCst) {
            return Ok(());
        }
        let ctx = self.inner.ctx.clone();
        let sim = routes::sim(&ctx.keys).declare(&ctx).await?;
        let task = tokio::spawn(sim.run(ctx, self.inner.routes_stop.clone()));
        self.inner
            .late_routes
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push(task);
        Ok(())
    }

    /// Whether any machine served is simulated.
    pub(super) fn any_simulated(&self) -> bool {
        self.inner
            .ctx
            .machines
            .now()
            .values()
            .any(|m| m.sim.is_some())
    }

    /// The cell's program library, whose quota and retention a reload replaces.
    pub fn library(&self) -> &crate::library::ProgramLibrary {
        &self.inner.ctx.library
    }

    /// The machines served.
    pub fn names(&self) -> Vec<String> {
        self.served().keys().cloned().collect()
    }

    fn machine(&self, name: &str) -> Option<Arc<Machine>> {
        self.served().get(name).map(|s| Arc::clone(&s.machine))
    }

    /// Holds machine `name`'s jobs ([`Hold`]); with `fail_active`, its open G05 stream is
    /// ended too.
    pub async fn hold(&self, name: &str, hold: Hold) -> Result<(), JobError> {
        let Some(m) = self.machine(name) else {
            return Ok(());
        };
        if hold.fail_active.is_some()
            && let Some(stream) = m.g05.current()
            && !stream.status().borrow().is_over()
        {
            let _ = stream.end(EndReason::Cancelled).await;
        }
        m.jobs.hold(hold).await
    }

    /// Lets machine `name` take jobs again.
    pub async fn release(&self, name: &str) -> Result<(), JobError> {
        match self.machine(name) {
            Some(m) => m.jobs.release().await,
            None => Ok(()),
        }
    }

    /// Completes once machine `name` sends nothing: no job active and no G05 stream open
    /// (hold it first, or another job may start).
    pub async fn idle(&self, name: &str) {
        let Some(m) = self.machine(name) else {
            return;
        };
        let mut snapshot = m.jobs.snapshot();
        loop {
            let active = snapshot.borrow_and_update().active.is_some();
            let streaming = m
                .g05
                .current()
                .is_some_and(|s| !s.status().borrow().is_over());
            if !active && !streaming {
                return;
            }
            tokio::select! {
                changed = snapshot.changed() => if changed.is_err() {
                    return;
                },
                // A stream's end is not in the jobs' snapshot.
                () = tokio::time::sleep(Duration::from_millis(250)) => {}
            }
        }
    }

    /// Stops machine `name`'s job manager (its waiting jobs stay in the journal) and then its
    /// task, which publishes the last job events and status and withdraws its liveliness
    /// token. `forget`: the routes no longer know it (removed); otherwise they keep the
    /// stopped machine until [`MachineRoutes::add`] serves its restarted link.
    pub async fn stop(&self, name: &str, forget: bool) {
        let served = self.served().remove(name);
        if forget {
            self.inner.ctx.machines.remove(name);
        }
        let Some(s) = served else { return };
        s.jobs_stop.cancel();
        let _ = s.job_task.await;
        s.machine_stop.cancel();
        if let Some(task) = s.machine_task {
            let _ = task.await;
        }
    }

    /// The cell's link and tag names, for questions about its records.
    pub fn set_names(&self, config: &CellConfig) {
        self.inner.ctx.names.set(CellNames::of(config));
    }

    /// Stops every machine as the gateway stops: every job manager first (they report their
    /// last events), then every machine's task (which publishes them and withdraws).
    pub(super) async fn stop_all(&self) {
        let served: Vec<Served> = std::mem::take(&mut *self.served()).into_values().collect();
        let late: Vec<JoinHandle<()>> = std::mem::take(
            &mut *self
                .inner
                .late_routes
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
        );
        for task in late {
            let _ = task.await;
        }
        self.inner.jobs_stop.cancel();
        let mut machine_tasks = Vec::new();
        for s in served {
            let _ = s.job_task.await;
            machine_tasks.extend(s.machine_task);
        }
        self.inner.machines_stop.cancel();
        for task in machine_tasks {
            let _ = task.await;
        }
    }
}

/// A PLC served: its publishers' tasks.
struct PlcServed {
    link_stop: CancellationToken,
    tags_stop: CancellationToken,
    link_task: JoinHandle<()>,
    tags_task: JoinHandle<()>,
}

/// The cell's PLC links as the routes serve them; a reload adds, removes and retags them.
#[derive(Clone)]
pub struct PlcRoutes {
    ctx: PlcContext,
    stop: CancellationToken,
    served: Arc<std::sync::Mutex<BTreeMap<String, PlcServed>>>,
}

impl PlcRoutes {
    pub(super) fn new(route: RouteContext, stop: CancellationToken) -> Self {
        PlcRoutes {
            ctx: PlcContext {
                route,
                plcs: Live::default(),
            },
            stop,
            served: Arc::default(),
        }
    }

    pub(super) fn context(&self) -> &PlcContext {
        &self.ctx
    }

    fn served(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, PlcServed>> {
        self.served
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn tags_task(&self, link: PlcLink, stop: CancellationToken) -> JoinHandle<()> {
        tokio::spawn(route_tag::publish_tags(self.ctx.clone(), link, stop))
    }

    /// Serves `link`: its status, transfers, stations and tags.
    pub fn add(&self, link: PlcLink) {
        let name = link.config.name.clone();
        let (link_stop, tags_stop) = (self.stop.child_token(), self.stop.child_token());
        let link_task = tokio::spawn(route_plc::publish_link(
            self.ctx.clone(),
            link.clone(),
            link_stop.clone(),
        ));
        let tags_task = self.tags_task(link.clone(), tags_stop.clone());
        self.ctx.plcs.insert(&name, link);
        let served = PlcServed {
            link_stop,
            tags_stop,
            link_task,
            tags_task,
        };
        if let Some(old) = self.served().insert(name, served) {
            old.link_stop.cancel();
            old.tags_stop.cancel();
        }
    }

    /// Stops serving PLC `name` (its station tokens withdrawn); the routes no longer know it.
    pub async fn remove(&self, name: &str) {
        self.ctx.plcs.remove(name);
        let Some(s) = self.served().remove(name) else {
            return;
        };
        s.link_stop.cancel();
        s.tags_stop.cancel();
        let _ = s.link_task.await;
        let _ = s.tags_task.await;
    }

    /// Serves `link`'s new tags: its tags' publisher restarts with them (which are kept in the
    /// history may have changed); its link and stations are not touched.
    pub async fn retag(&self, link: PlcLink) {
        let name = link.config.name.clone();
        self.ctx.plcs.insert(&name, link.clone());
        let old = {
            let mut served = self.served();
            let Some(s) = served.get_mut(&name) else {
                return;
            };
            let stop = self.stop.child_token();
            let old_stop = std::mem::replace(&mut s.tags_stop, stop.clone());
            let old_task = std::mem::replace(&mut s.tags_task, self.tags_task(link, stop));
            (old_stop, old_task)
        };
        old.0.cancel();
        let _ = old.1.await;
    }

    /// Waits for every PLC's publishers to end (after the stop token was cancelled).
    pub(super) async fn join_all(&self) {
        let served: Vec<PlcServed> = std::mem::take(&mut *self.served()).into_values().collect();
        for s in served {
            let _ = s.link_task.await;
            let _ = s.tags_task.await;
        }
    }
}
