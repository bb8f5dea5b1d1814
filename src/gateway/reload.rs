//! Reloading the cell file while the gateway runs (docs/configuration.md, "Reloading").
//!
//! `cellgate reload` (through `P/C/@admin/reload`) and SIGHUP come here, one at a time: the
//! file is read and checked as `cellgate check-config` checks it, compared with the running
//! cell ([`cellgate_core::config::reload`]), and only what changed is applied. A file that does
//! not check, or that changes what cannot change while the gateway runs, is refused whole: the
//! gateway goes on with the cell it had. Links of added machines and PLCs start first, so that
//! one that cannot start refuses the reload before anything else is touched.
//!
//! A removed or changed machine's jobs are held ([`crate::jobs::Hold`]): its link stops or
//! restarts once the job it is sending has ended, watched here in the background, and a later
//! reload may change what becomes of it before then (give it its old entry back, and it goes
//! on as if nothing happened). Every other link, and its jobs, is never touched.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use zenoh::Session;

use crate::bus::admin::AdminRoute;
use crate::bus::keys::CellKeys;
use crate::bus::route_reload::{self, ReloadAnswer, ReloadAsk};
use crate::bus::{MachineRoutes, PlcRoutes};
use crate::cell::Cell;
use crate::history::History;
use crate::jobs::Hold;
use crate::library::{Quota, Retention};
use cellgate_core::config::reload::{CellChange, compare};
use cellgate_core::config::{CellConfig, MachineConfig};
use cellgate_core::pb;

/// What is written over each configuration read (the command line's options).
type Adjust = Arc<dyn Fn(&mut CellConfig) + Send + Sync>;

/// Where a reload reads the cell from: the file `cellgate run --config` was given, with the
/// command line's options written over it again, as `run` did at start.
#[derive(Clone, Default)]
pub struct CellSource {
    path: Option<PathBuf>,
    adjust: Option<Adjust>,
}

impl std::fmt::Debug for CellSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CellSource")
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

impl CellSource {
    /// The cell file at `path`.
    pub fn file(path: impl Into<PathBuf>) -> Self {
        CellSource {
            path: Some(path.into()),
            adjust: None,
        }
    }

    /// The embedded default cell: no file, so a reload is refused, saying so.
    pub fn embedded() -> Self {
        CellSource::default()
    }

    /// The same source, with `adjust` written over each configuration read (the command
    /// line's options).
    pub fn with_adjust(mut self, adjust: impl Fn(&mut CellConfig) + Send + Sync + 'static) -> Self {
        self.adjust = Some(Arc::new(adjust));
        self
    }

    /// The cell file, if there is one.
    pub fn path(&self) -> Option<&Path> {
        self.path.as_deref()
    }

    /// Reads and checks the file as `check-config` does, then writes the adjustments over it
    /// and checks the result as `run` does. Every error, one a line, naming the file.
    pub fn load(&self) -> Result<CellConfig, Vec<String>> {
        let Some(path) = &self.path else {
            return Err(vec![EMBEDDED.to_string()]);
        };
        let mut config = check_cell_file(path)?;
        if let Some(adjust) = &self.adjust {
            adjust(&mut config);
            let origin = format!("{} (with command-line options)", path.display());
            if let Err(errors) = config.validate() {
                return Err(lines(&origin, errors.iter().map(ToString::to_string)));
            }
            if let Err(e) = crate::bus::session::cell_zenoh_config(&config) {
                return Err(vec![format!("{origin}: {e}")]);
            }
        }
        Ok(config)
    }
}

const EMBEDDED: &str = "this gateway runs the embedded default cell (`cellgate run` without \
                        --config): there is no cell file to read again; restart it with \
                        --config FILE to reload a file";

/// Each error on a line of its own, starting with where it comes from (unless it does).
fn lines(origin: &str, errors: impl Iterator<Item = String>) -> Vec<String> {
    errors
        .map(|e| {
            if e.starts_with(origin) {
                e
            } else {
                format!("{origin}: {e}")
            }
        })
        .collect()
}

/// Reads and checks a cell file as `cellgate check-config` does: every rule of the file, and
/// the zenoh configuration its `[bus]` and `[security]` make. Every error, one a line, naming
/// the file and the line or the key and value at fault.
pub fn check_cell_file(path: &Path) -> Result<CellConfig, Vec<String>> {
    let origin = path.display().to_string();
    let config = CellConfig::load(path)
        .and_then(|c| c.validate().map(|()| c))
        .map_err(|errors| lines(&origin, errors.iter().map(ToString::to_string)))?;
    crate::bus::session::cell_zenoh_config(&config).map_err(|e| vec![format!("{origin}: {e}")])?;
    Ok(config)
}

/// Asks the running gateway for reloads (SIGHUP, tests): cheap to clone.
#[derive(Debug, Clone)]
pub struct ReloadHandle(mpsc::Sender<ReloadAsk>);

impl ReloadHandle {
    /// Asks for a reload and waits for what came of it; `None` once the gateway has stopped.
    pub async fn reload(
        &self,
        force: bool,
        via: &'static str,
        origin: Option<pb::RequestOrigin>,
    ) -> Option<ReloadAnswer> {
        let (reply, answer) = tokio::sync::oneshot::channel();
        let ask = ReloadAsk {
            force,
            via,
            origin,
            reply,
        };
        self.0.send(ask).await.ok()?;
        answer.await.ok()
    }
}

/// The reloads a gateway takes: from its bus route and from its [`ReloadHandle`]s.
#[derive(Debug)]
pub struct Reloads {
    tx: mpsc::Sender<ReloadAsk>,
    pub(super) rx: mpsc::Receiver<ReloadAsk>,
}

impl Reloads {
    /// A gateway's reloads, and a handle to ask for them.
    pub fn new() -> (ReloadHandle, Reloads) {
        let (tx, rx) = mpsc::channel(16);
        (ReloadHandle(tx.clone()), Reloads { tx, rx })
    }

    pub(super) fn sender(&self) -> mpsc::Sender<ReloadAsk> {
        self.tx.clone()
    }
}

/// A machine whose link stops (`target` none) or restarts with `target` once it is idle.
struct Pending {
    op: u64,
    target: Option<MachineConfig>,
    watcher: JoinHandle<()>,
}

/// What the reloader needs of the running gateway.
pub(super) struct Running {
    pub cell: Cell,
    pub machines: MachineRoutes,
    pub plcs: PlcRoutes,
    pub history: History,
    pub console: Option<Arc<crate::console::Console>>,
    /// The OPC UA server's users, when it has some: a reload reads them again.
    pub opcua_auth: Option<Arc<crate::console::auth::Auth>>,
    pub admin: Arc<AdminRoute>,
    pub session: Session,
    pub keys: CellKeys,
}

/// Applies reloads to the running gateway, one at a time.
pub(super) struct Reloader {
    source: CellSource,
    current: CellConfig,
    generation: u64,
    run: Running,
    pending: BTreeMap<String, Pending>,
    next_op: u64,
    drained: mpsc::UnboundedSender<(String, u64)>,
    /// The last reload taken, published again as the machines it waited for leave.
    last_taken: Option<pb::ReloadResult>,
}

/// Why a reload was refused, its code.
type Refusal = pb::ErrorCode;

/// A cell file read for a reload, or why not (every error, and the code the answer carries).
pub(super) type Read = Result<CellConfig, (Vec<String>, Refusal)>;

/// A read under way ([`Reloader::read`]).
pub(super) type Reading = std::pin::Pin<Box<dyn Future<Output = Read> + Send>>;

/// How long reading and checking the cell file may take before the reload is refused.
const READ_LIMIT: std::time::Duration = std::time::Duration::from_secs(10);

impl Reloader {
    /// A reloader for the gateway running `config` from `source`; it reports a machine whose
    /// running job has ended on `drained`, for [`Reloader::on_drained`].
    pub(super) fn new(
        source: CellSource,
        config: CellConfig,
        run: Running,
        drained: mpsc::UnboundedSender<(String, u64)>,
    ) -> Self {
        Reloader {
            source,
            current: config,
            generation: 1,
            run,
            pending: BTreeMap::new(),
            next_op: 1,
            drained,
            last_taken: None,
        }
    }

    /// The links, for the gateway to stop; the machines still waiting stop with them.
    pub(super) fn into_cell(self) -> Cell {
        for p in self.pending.into_values() {
            p.watcher.abort();
        }
        self.run.cell
    }

    /// Reads the cell file off the runtime's threads, within [`READ_LIMIT`]: the future the
    /// gateway's loop waits on beside its shutdown, so that no file (a FIFO, a hung share)
    /// holds the gateway. What [`Self::reload`] takes.
    pub(super) fn read(&self) -> impl Future<Output = Read> + Send + 'static {
        let source = self.source.clone();
        async move {
            if source.path().is_none() {
                return Err((vec![EMBEDDED.to_string()], pb::ErrorCode::NotSupported));
            }
            let loading = tokio::task::spawn_blocking(move || source.load());
            match tokio::time::timeout(READ_LIMIT, loading).await {
                Ok(Ok(Ok(config))) => Ok(config),
                Ok(Ok(Err(errors))) => Err((errors, pb::ErrorCode::InvalidRequest)),
                Ok(Err(e)) => Err((
                    vec![format!("reading the cell file: {e}")],
                    pb::ErrorCode::Internal,
                )),
                Err(_) => Err((
                    vec![format!(
                        "reading the cell file took longer than {} s (a file system that \
                         does not answer?): nothing of this reload was applied",
                        READ_LIMIT.as_secs()
                    )],
                    pb::ErrorCode::DeadlineExceeded,
                )),
            }
        }
    }

    /// Applies what changed in the cell `read` (from [`Self::read`]) or refuses it whole;
    /// then logs, audits and publishes what came of it, and shows it in the admin document.
    pub(super) async fn reload(&mut self, ask: ReloadAsk, read: Read) {
        let file = self
            .source
            .path()
            .map(|p| p.display().to_string())
            .unwrap_or_default();
        let mut result = pb::ReloadResult {
            file: file.clone(),
            via: ask.via.to_string(),
            origin: ask.origin.clone(),
            unix_ms: pb::now_ms(),
            ..pb::ReloadResult::default()
        };
        let code = match self.apply(ask.force, read, &mut result).await {
            Ok(()) => pb::ErrorCode::Unspecified,
            Err(code) => code,
        };
        result.applied = code == pb::ErrorCode::Unspecified;
        result.generation = self.generation;
        result.waiting = self.pending.keys().cloned().collect();
        let answer = ReloadAnswer { result, code };
        let r = &answer.result;
        if r.applied {
            tracing::info!(
                file = %file, generation = r.generation, via = ask.via,
                waiting = ?r.waiting,
                "cell reloaded: {}", route_reload::summary(r)
            );
        } else {
            for e in &r.errors {
                tracing::error!(file = %file, via = ask.via, "reload refused: {e}");
            }
        }
        route_reload::audit(
            &self.run.history,
            &self.current.security,
            &self.run.keys,
            &answer,
        );
        route_reload::publish(&self.run.session, &self.run.keys, r).await;
        self.show(Some(r));
        if r.applied {
            self.last_taken = Some(r.clone());
        }
        let _ = ask.reply.send(answer);
    }

    /// Shows the running cell in the admin document: the file's, and the machines a reload
    /// removed whose running job has not ended yet (their links still run, and every
    /// surface that follows the cell keeps them until they stop).
    fn show(&self, last: Option<&pb::ReloadResult>) {
        let waiting: Vec<String> = self.pending.keys().cloned().collect();
        let mut running = self.current.clone();
        for (name, p) in &self.pending {
            if p.target.is_none()
                && running.machine(name).is_none()
                && let Some(m) = self.run.cell.machine(name)
            {
                running.machines.push(m.config.clone());
            }
        }
        self.run
            .admin
            .set_config(&running, self.generation, last, &waiting);
    }

    async fn apply(
        &mut self,
        force: bool,
        read: Read,
        result: &mut pb::ReloadResult,
    ) -> Result<(), Refusal> {
        let new = match read {
            Ok(config) => config,
            Err((errors, code)) => {
                result.errors = errors;
                return Err(code);
            }
        };
        let change = match compare(&self.current, &new) {
            Ok(c) => c,
            Err(restart) => {
                result.restart_needed = true;
                result.errors = restart
                    .0
                    .iter()
                    .map(|k| {
                        format!(
                            "{}: {k}: cannot change while the gateway runs; restart it to take \
                             this file (nothing of this reload was applied)",
                            result.file
                        )
                    })
                    .collect();
                return Err(pb::ErrorCode::RestartNeeded);
            }
        };
        for w in new.warnings() {
            tracing::warn!(file = %result.file, "{w}");
        }
        self.start_added(&new, &change, result).await?;
        // From here on nothing refuses: the reload is taken.
        for name in &change.plcs_removed {
            self.run.plcs.remove(name).await;
            self.run.cell.remove_plc(name).await;
        }
        for name in &change.plcs_changed {
            self.run.plcs.remove(name).await;
            self.run.cell.remove_plc(name).await;
            let Some(cfg) = new.plc(name) else { continue };
            match self.run.cell.add_plc(cfg).await {
                Ok(link) => self.run.plcs.add(link),
                Err(e) => {
                    tracing::error!(plc = %name, error = %e, "the PLC's link did not restart");
                    result
                        .errors
                        .push(format!("PLC {name}: its link did not restart: {e}"));
                }
            }
        }
        for name in &change.plc_tags {
            let Some(cfg) = new.plc(name) else { continue };
            match self.run.cell.set_plc_tags(cfg).await {
                Ok(link) => self.run.plcs.retag(link).await,
                Err(e) => result.errors.push(format!("PLC {name}: its tags: {e}")),
            }
        }
        for name in &change.machines_removed {
            self.retarget(name, None, force).await;
        }
        for name in &change.machines_added {
            // Started above unless its link still runs, being removed: then it stays.
            if let Some(cfg) = new.machine(name) {
                self.retarget(name, Some(cfg.clone()), force).await;
            }
        }
        for name in &change.machines_changed {
            let Some(cfg) = new.machine(name) else {
                continue;
            };
            if self.run.cell.machine(name).is_some() {
                self.retarget(name, Some(cfg.clone()), force).await;
            } else if let Err(e) = self.start_machine(cfg).await {
                // Its link did not restart after an earlier reload: it starts with this entry.
                result
                    .errors
                    .push(format!("machine {name}: its link did not start: {e}"));
            }
        }
        if force {
            // --force ends the wait of machines an earlier reload left waiting, too.
            let waiting: Vec<(String, Option<MachineConfig>)> = self
                .pending
                .iter()
                .map(|(n, p)| (n.clone(), p.target.clone()))
                .collect();
            for (name, target) in waiting {
                self.retarget(&name, target, true).await;
            }
        }
        self.settings(&new);
        self.current = new;
        // A file that changes nothing is taken, but is no new configuration.
        if !change.is_empty() {
            self.generation += 1;
        }
        result.machines_added = change.machines_added;
        result.machines_removed = change.machines_removed;
        result.machines_changed = change.machines_changed;
        result.plcs_added = change.plcs_added;
        result.plcs_removed = change.plcs_removed;
        result.plcs_changed = change.plcs_changed;
        result.plc_tags = change.plc_tags;
        result.settings = change.settings;
        Ok(())
    }

    /// Starts the links of the machines and PLCs `change` adds (but a machine whose link still
    /// runs, being removed) and serves them; if one cannot start, stops those started and
    /// refuses the reload.
    async fn start_added(
        &mut self,
        new: &CellConfig,
        change: &CellChange,
        result: &mut pb::ReloadResult,
    ) -> Result<(), Refusal> {
        let mut machines: Vec<String> = Vec::new();
        let mut plcs: Vec<String> = Vec::new();
        let mut failed = None;
        for name in &change.machines_added {
            let Some(cfg) = new.machine(name) else {
                continue;
            };
            if self.run.cell.machine(name).is_some() {
                continue;
            }
            if let Err(e) = self.start_machine(cfg).await {
                failed = Some(format!("machine {name}: its link did not start: {e}"));
                break;
            }
            machines.push(name.clone());
        }
        if failed.is_none() {
            for name in &change.plcs_added {
                let Some(cfg) = new.plc(name) else { continue };
                match self.run.cell.add_plc(cfg).await {
                    Ok(link) => {
                        self.run.plcs.add(link);
                        plcs.push(name.clone());
                    }
                    Err(e) => {
                        failed = Some(format!("PLC {name}: its link did not start: {e}"));
                        break;
                    }
                }
            }
        }
        let Some(why) = failed else {
            return Ok(());
        };
        for name in &machines {
            self.run.machines.stop(name, true).await;
            self.run.cell.remove_machine(name).await;
        }
        for name in &plcs {
            self.run.plcs.remove(name).await;
            self.run.cell.remove_plc(name).await;
        }
        result
            .errors
            .push(format!("{why} (nothing of this reload was applied)"));
        Err(pb::ErrorCode::Unavailable)
    }

    async fn start_machine(&mut self, cfg: &MachineConfig) -> Result<(), String> {
        let link = self
            .run
            .cell
            .add_machine(cfg)
            .await
            .map_err(|e| e.to_string())?;
        if let Err(e) = self.run.machines.add(link).await {
            self.run.machines.stop(&cfg.name, true).await;
            self.run.cell.remove_machine(&cfg.name).await;
            return Err(e.to_string());
        }
        Ok(())
    }

    /// What becomes of the running machine `name`: it stops (`target` none) or restarts with
    /// `target` once its running job has ended (at once with `force`, the job failing). Given
    /// the entry it runs with, it goes on untouched.
    async fn retarget(&mut self, name: &str, target: Option<MachineConfig>, force: bool) {
        let Some(running) = self.run.cell.machine(name).map(|m| m.config.clone()) else {
            return;
        };
        let before = self.pending.remove(name);
        if let Some(p) = &before {
            p.watcher.abort();
        }
        if target.as_ref() == Some(&running) {
            if before.is_some() {
                tracing::info!(machine = %name, "the reload gives the machine its running entry back: it goes on");
                if let Err(e) = self.run.machines.release(name).await {
                    tracing::warn!(machine = %name, error = %e, "releasing the machine's jobs");
                }
            }
            return;
        }
        // A machine that was leaving the cell and stays after all takes jobs again (they wait
        // for its restarted link).
        if before.as_ref().is_some_and(|p| p.target.is_none()) && target.is_some() {
            let _ = self.run.machines.release(name).await;
        }
        let fail_active = force.then(|| match &target {
            None => format!(
                "machine {name} was removed from the cell by a forced reload (cellgate reload \
                 --force)"
            ),
            Some(_) => format!(
                "the link of machine {name} was restarted by a forced reload (cellgate reload \
                 --force) to take its changed entry"
            ),
        });
        let retire = target
            .is_none()
            .then(|| "is leaving the cell (a reload removed it): it takes no new jobs".to_string());
        let hold = Hold {
            fail_active,
            retire,
        };
        if let Err(e) = self.run.machines.hold(name, hold).await {
            tracing::warn!(machine = %name, error = %e, "holding the machine's jobs");
        }
        let op = self.next_op;
        self.next_op += 1;
        let (routes, tx, n) = (
            self.run.machines.clone(),
            self.drained.clone(),
            name.to_string(),
        );
        // A machine sending nothing now stops or restarts at once: it is not listed as
        // waiting for a job it does not have.
        let idle_now = futures::FutureExt::now_or_never(routes.idle(&n)).is_some();
        let watcher = tokio::spawn(async move {
            routes.idle(&n).await;
            let _ = tx.send((n, op));
        });
        tracing::info!(machine = %name, stops = target.is_none(), "the machine's link stops or restarts once its running job has ended");
        self.pending.insert(
            name.to_string(),
            Pending {
                op,
                target,
                watcher,
            },
        );
        if idle_now {
            self.drain(name, op).await;
        }
    }

    /// Machine `name` sends nothing any more (`op`: the wait that said so): its link stops, or
    /// restarts with its new entry.
    pub(super) async fn on_drained(&mut self, name: String, op: u64) {
        if self.drain(&name, op).await {
            self.show(None);
            // The reload is published again, `waiting` as it stands now, so that whoever
            // follows the cell (the MTConnect agent, the console) asks for it as it now is.
            if let Some(mut r) = self.last_taken.clone() {
                r.waiting = self.pending.keys().cloned().collect();
                r.unix_ms = pb::now_ms();
                route_reload::publish(&self.run.session, &self.run.keys, &r).await;
            }
        }
    }

    /// Stops or restarts the link of machine `name`, waiting for it (`op`); whether it did.
    async fn drain(&mut self, name: &str, op: u64) -> bool {
        if self.pending.get(name).is_none_or(|p| p.op != op) {
            return false;
        }
        let Some(p) = self.pending.remove(name) else {
            return false;
        };
        p.watcher.abort();
        let name = name.to_string();
        match p.target {
            None => {
                self.run.machines.stop(&name, true).await;
                self.run.cell.remove_machine(&name).await;
                tracing::info!(machine = %name, "machine removed from the cell: its link stopped");
            }
            Some(cfg) => {
                self.run.machines.stop(&name, false).await;
                self.run.cell.remove_machine(&name).await;
                match self.start_machine(&cfg).await {
                    Ok(()) => {
                        tracing::info!(machine = %name, "the machine's link restarted with its changed entry")
                    }
                    Err(e) => {
                        tracing::error!(machine = %name, error = %e, "the machine's link did not restart: the machine is out of the cell until the next reload or restart");
                        self.run.machines.stop(&name, true).await;
                    }
                }
            }
        }
        true
    }

    /// The settings that apply without touching a link, taken from `new` whether or not they
    /// changed (the console reads its users file again).
    fn settings(&self, new: &CellConfig) {
        let p = &new.programs;
        self.run.machines.library().set_limits(
            Quota {
                bytes: p.quota_bytes,
                files: p.quota_files,
            },
            Retention {
                revisions: p.keep_revisions,
                days: p.keep_revision_days,
            },
        );
        self.run.history.set_config(&new.history);
        if let Some(auth) = &self.run.opcua_auth {
            auth.set_security(&new.security);
        }
        if let (Some(console), Some(c)) = (&self.run.console, &new.console) {
            let ended = console.reload(c, &new.security);
            if ended > 0 {
                tracing::info!(
                    sessions = ended,
                    "console: sessions ended by the reload (user gone or permissions changed)"
                );
            }
        }
        self.run.machines.set_names(new);
    }
}

#[cfg(test)]
mod tests;
