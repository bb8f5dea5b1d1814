//! `cellgate sim soak`: a simulated cell run through a seeded schedule of faults while clients
//! load it, with its invariants checked against the boards' own record (docs/reliability.md).
//!
//! - `rig`: the processes (boards, PLC modules, router, gateway) and the cell file;
//!   `proxy`: the line in front of each board, which cuts, corrupts and drops.
//! - [`schedule`]: the faults, drawn from a seed; `faults`: what each one does.
//! - `load`: the clients and the ledger of the jobs they got accepted.
//! - `check`: the invariants; [`figures`]: the samples, slopes and the picture.

mod check;
mod faults;
pub mod figures;
mod load;
mod proxy;
mod rig;
pub mod schedule;

use std::path::PathBuf;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use tokio_util::sync::CancellationToken;

use crate::client::{Client, ConnectOptions};
use cellgate_core::pb;
use figures::{Mark, Sample};
use load::lock;
use rig::Rig;
use schedule::FaultKind;

/// `cellgate sim soak`.
#[derive(Debug, Clone, clap::Args)]
pub struct SoakArgs {
    /// How long the faults and the load run, in minutes (decimals allowed); then the jobs
    /// drain and the invariants are checked. Without it: until SIGINT or SIGTERM.
    #[arg(long)]
    pub minutes: Option<f64>,
    /// The seed of the fault schedule and of the load; printed at the start, so that a run can
    /// be repeated. Default: from the clock.
    #[arg(long)]
    pub seed: Option<u64>,
    /// FANUC machines, spread over the four protocols (one board process each).
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u16).range(4..=256))]
    pub machines: u16,
    /// Seconds between faults, on average (each ±30 %).
    #[arg(long, default_value_t = 25.0)]
    pub fault_every_s: f64,
    /// The kinds of fault to inject, comma-separated (default: every kind): line-cut,
    /// device-server-restart, checksum-error, dropped-byte, cnc-alarm, cnc-reset,
    /// gateway-kill, reload, router-restart, disk-full, slow-subscriber, hostile-burst.
    #[arg(long, value_delimiter = ',', value_parser = schedule::parse_kind, value_name = "KINDS")]
    pub faults: Vec<schedule::FaultKind>,
    /// MES clients submitting jobs.
    #[arg(long, default_value_t = 3)]
    pub clients: usize,
    /// The first seconds of each gateway run left out of the slopes (start-up is not growth).
    #[arg(long, default_value_t = 60.0)]
    pub warm_s: f64,
    /// How long the jobs may take to end once the load stops, in seconds.
    #[arg(long, default_value_t = 240)]
    pub drain_s: u64,
    /// Write the report as JSON to this file.
    #[arg(long, value_name = "FILE")]
    pub report: Option<PathBuf>,
    /// Draw memory, CPU and jobs over the run, with the faults marked, as SVG to this file.
    #[arg(long, value_name = "FILE")]
    pub plot: Option<PathBuf>,
    /// Keep the run's directory (cell file, logs, the gateway's data) here instead of a
    /// temporary one removed at the end.
    #[arg(long, value_name = "DIR")]
    pub dir: Option<PathBuf>,
    /// The gateway's log filter (its log is `gateway.log` in the run's directory).
    #[arg(long, default_value = "warn", value_name = "FILTER")]
    pub gateway_log: String,
    /// Resident memory may grow at most this many KiB an hour once warm.
    #[arg(long, default_value_t = 8192.0)]
    pub rss_bound_kib_per_hour: f64,
}

/// Why the soak could not run (as opposed to an invariant that did not hold).
#[derive(Debug, thiserror::Error)]
pub enum SoakError {
    #[error("soak: {0}")]
    Io(#[source] std::io::Error),
    #[error("soak: cannot start {0}: {1}")]
    Spawn(&'static str, #[source] std::io::Error),
    #[error("soak: {0}")]
    Setup(String),
}

/// How a process's resources went over the run.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub struct Trend {
    pub start: f64,
    pub end: f64,
    /// Least-squares slope over the warm samples, per hour.
    pub slope_per_hour: Option<f64>,
    /// Minutes between the first and the last warm sample.
    pub warm_minutes: f64,
}

/// Warm minutes below which a slope is printed but not judged: a few minutes of start-up
/// and restarts say nothing of growth per hour.
const JUDGED_WARM_MINUTES: f64 = 10.0;

/// What a run found: the JSON of `--report`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Report {
    pub passed: bool,
    pub seed: u64,
    pub minutes: f64,
    pub machines: u16,
    pub jobs: serde_json::Value,
    pub faults: std::collections::BTreeMap<String, u64>,
    pub faults_skipped: Vec<String>,
    pub history: serde_json::Value,
    pub audit: serde_json::Value,
    pub unaudited_submits: u64,
    pub panics: u64,
    pub rss_kib: Trend,
    pub open_files: Trend,
    pub threads: Trend,
    pub rss_bound_kib_per_hour: f64,
    pub load: serde_json::Value,
    pub broken: Vec<String>,
}

type Samples = Arc<Mutex<Vec<Sample>>>;

/// Runs the soak; the report, whether or not every invariant held.
pub async fn run(args: SoakArgs, shutdown: CancellationToken) -> Result<Report, SoakError> {
    let seed = args.seed.unwrap_or_else(|| {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(1, |d| d.as_secs())
    });
    let exe = std::env::current_exe().map_err(SoakError::Io)?;
    let temp = match &args.dir {
        Some(d) => {
            std::fs::create_dir_all(d).map_err(SoakError::Io)?;
            None
        }
        None => Some(tempfile::tempdir().map_err(SoakError::Io)?),
    };
    let dir = match (&args.dir, &temp) {
        (Some(d), _) => d.clone(),
        (None, Some(t)) => t.path().to_path_buf(),
        (None, None) => return Err(SoakError::Setup("no directory".to_string())),
    };
    let end_s = args.minutes.map_or(f64::INFINITY, |m| (m * 60.0).max(1.0));
    let every = args.fault_every_s.max(1.0);
    let horizon = if end_s.is_finite() {
        end_s
    } else {
        7.0 * 86_400.0
    };
    let kinds = if args.faults.is_empty() {
        FaultKind::ALL.to_vec()
    } else {
        args.faults.clone()
    };
    let plan = schedule::schedule(seed, every.min(horizon / 4.0), horizon, every, &kinds);
    eprintln!(
        "soak: seed {seed}, {} machines, {}, a fault every {every:.0} s ({} planned); \
         run again with --seed {seed}",
        args.machines,
        args.minutes
            .map_or("until stopped".to_string(), |m| format!("{m} min")),
        plan.len()
    );
    for f in plan.iter().take(400) {
        eprintln!("soak:   {:>8.1} s  {} #{}", f.at_s, f.kind.name(), f.pick);
    }

    let stop_rig = CancellationToken::new();
    let mut rig = Rig::new(exe, dir.clone(), usize::from(args.machines), stop_rig).await?;
    rig.log_filter = args.gateway_log.clone();
    eprintln!(
        "soak: in {} (data on {})",
        dir.display(),
        if rig.tmpfs {
            "a 64 MiB tmpfs"
        } else {
            "the disk: no tmpfs could be mounted, disk-full faults are skipped"
        }
    );
    rig.start_all().await?;
    let direct = match connect(&format!("tcp/127.0.0.1:{}", rig.bus_port), &shutdown).await {
        Ok(c) => c,
        Err(e) => {
            let log = rig.gateway_log();
            rig.shutdown(false).await;
            let tail: Vec<&str> = log.lines().rev().take(20).collect();
            let tail: Vec<&str> = tail.into_iter().rev().collect();
            return Err(SoakError::Setup(format!(
                "{e}\nthe gateway's log:\n{}",
                tail.join("\n")
            )));
        }
    };
    wait_links_up(&direct, rig.machines.len(), &shutdown).await;

    let started = tokio::time::Instant::now();
    let ledger: load::Shared = Arc::default();
    let samples: Samples = Arc::default();
    let load_stop = CancellationToken::new();
    let watch_stop = CancellationToken::new();
    let router = format!("tcp/127.0.0.1:{}", rig.router_port);
    let mut tasks = tokio::task::JoinSet::new();
    let names: Vec<String> = rig.machines.iter().map(|m| m.name.clone()).collect();
    for i in 0..args.clients.max(1) {
        let c = connect(&router, &shutdown).await?;
        tasks.spawn(load::mes(
            c,
            i,
            seed,
            names.clone(),
            Arc::clone(&ledger),
            load_stop.clone(),
        ));
    }
    tasks.spawn(load::resumer(
        connect(&router, &shutdown).await?,
        Arc::clone(&ledger),
        load_stop.clone(),
    ));
    let a_family: Vec<String> = rig
        .machines
        .iter()
        .filter(|m| m.family.checked())
        .map(|m| m.name.clone())
        .collect();
    tasks.spawn(load::writer(
        connect(&router, &shutdown).await?,
        a_family,
        rig.data.join("programs"),
        Arc::clone(&ledger),
        load_stop.clone(),
    ));
    tasks.spawn(load::readers(
        rig.console_port,
        rig.mtconnect_port,
        Arc::clone(&ledger),
        load_stop.clone(),
    ));
    let watchers = vec![
        tokio::spawn(load::tracker(
            connect(&format!("tcp/127.0.0.1:{}", rig.bus_port), &shutdown).await?,
            Arc::clone(&ledger),
            watch_stop.clone(),
        )),
        tokio::spawn(sampler(
            rig.pid(),
            Arc::clone(&ledger),
            Arc::clone(&samples),
            started,
            watch_stop.clone(),
        )),
    ];

    // The faults, on schedule, until the end or a stop.
    let mut marks: Vec<Mark> = Vec::new();
    let mut skipped: Vec<String> = Vec::new();
    let mut injector = faults::Injector::new(&router, seed);
    for f in &plan {
        let at = started + Duration::from_secs_f64(f.at_s);
        tokio::select! {
            () = shutdown.cancelled() => break,
            () = tokio::time::sleep_until(at) => {}
        }
        match injector.inject(&mut rig, f).await {
            Ok(()) => marks.push(Mark {
                t_s: started.elapsed().as_secs_f64(),
                kind: f.kind.name().to_string(),
            }),
            Err(why) => skipped.push(format!("{} at {:.0} s: {why}", f.kind.name(), f.at_s)),
        }
    }
    if end_s.is_finite() {
        tokio::select! {
            () = shutdown.cancelled() => {}
            () = tokio::time::sleep_until(started + Duration::from_secs_f64(end_s)) => {}
        }
    }
    let minutes = started.elapsed().as_secs_f64() / 60.0;
    eprintln!("soak: load stopped after {minutes:.1} min; the jobs drain");
    load_stop.cancel();
    injector.heal(&mut rig).await;
    while tasks.join_next().await.is_some() {}
    drain(&direct, &ledger, Duration::from_secs(args.drain_s)).await;
    watch_stop.cancel();
    for w in watchers {
        let _ = w.await;
    }

    let report = judge(
        &args, seed, minutes, &rig, &direct, &ledger, &samples, &marks, skipped,
    )
    .await;
    if let Some(path) = &args.plot {
        let title = format!(
            "cellgate soak, seed {seed}, {} machines, {minutes:.0} min",
            args.machines
        );
        let svg = figures::svg(
            &title,
            &samples.lock().unwrap_or_else(PoisonError::into_inner),
            &marks,
        );
        std::fs::write(path, svg).map_err(SoakError::Io)?;
    }
    if let Some(path) = &args.report {
        let json = serde_json::to_string_pretty(&report).unwrap_or_default();
        std::fs::write(path, json).map_err(SoakError::Io)?;
    }
    direct.close().await;
    rig.shutdown(!report.passed).await;
    if !report.passed
        && let Some(t) = temp
    {
        // What failed is looked at in the logs: keep them.
        let kept = t.keep();
        eprintln!("soak: the run's directory is kept: {}", kept.display());
    }
    Ok(report)
}

/// A client of the cell at `endpoint`, tried until it answers.
async fn connect(endpoint: &str, stop: &CancellationToken) -> Result<Client, SoakError> {
    let options = ConnectOptions {
        endpoint: endpoint.to_string(),
        cell: Some("soak".to_string()),
        timeout: Duration::from_secs(10),
        ..ConnectOptions::default()
    };
    let mut last = String::new();
    for _ in 0..60 {
        if stop.is_cancelled() {
            break;
        }
        match Client::connect(&options).await {
            Ok(c) => return Ok(c),
            Err(e) => last = e.to_string(),
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
    Err(SoakError::Setup(format!(
        "no gateway at {endpoint}: {last}"
    )))
}

/// Waits (a minute at most) until every machine's link is up.
async fn wait_links_up(client: &Client, machines: usize, stop: &CancellationToken) {
    for _ in 0..60 {
        let up = client.status(None).await.map_or(0, |all| {
            all.iter()
                .filter(|s| {
                    matches!(
                        pb::LinkState::try_from(s.link_state),
                        Ok(pb::LinkState::Idle | pb::LinkState::Sending)
                    )
                })
                .count()
        });
        if up >= machines || stop.is_cancelled() {
            return;
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

/// Waits until every job of the ledger ended (asking for those the tracker did not see end),
/// at most `within`.
async fn drain(client: &Client, ledger: &load::Shared, within: Duration) {
    let until = tokio::time::Instant::now() + within;
    while tokio::time::Instant::now() < until {
        let open: Vec<(String, String)> = lock(ledger)
            .jobs
            .iter()
            .filter(|(_, j)| !j.ended())
            .map(|(id, j)| (id.clone(), j.machine.clone()))
            .collect();
        if open.is_empty() {
            return;
        }
        for (id, machine) in open {
            if let Ok(e) = client.job_latest(&machine, &id).await {
                lock(ledger).saw(e);
            }
        }
        tokio::time::sleep(Duration::from_secs(2)).await;
    }
}

/// Samples the gateway process every two seconds.
async fn sampler(
    pid: Arc<std::sync::atomic::AtomicU32>,
    ledger: load::Shared,
    samples: Samples,
    started: tokio::time::Instant,
    stop: CancellationToken,
) {
    let mut last_cpu: Option<(u32, f64, f64)> = None;
    while !stop.is_cancelled() {
        let t_s = started.elapsed().as_secs_f64();
        let p = pid.load(std::sync::atomic::Ordering::SeqCst);
        let (jobs_completed, jobs_failed) = {
            let l = lock(&ledger);
            let mut c = (0, 0);
            for j in l.jobs.values() {
                match j.last.as_ref().and_then(|e| e.kind.as_ref()) {
                    Some(pb::job_event::Kind::Completed(_)) => c.0 += 1,
                    Some(pb::job_event::Kind::Failed(_) | pb::job_event::Kind::Cancelled(_)) => {
                        c.1 += 1
                    }
                    _ => {}
                }
            }
            c
        };
        let proc_ = (p != 0).then(|| rig::process(p)).flatten();
        let sample = match proc_ {
            Some(pr) => {
                let cpu_pct = match last_cpu {
                    Some((lp, lt, lc)) if lp == p && t_s > lt => {
                        (pr.cpu_s - lc) / (t_s - lt) * 100.0
                    }
                    _ => 0.0,
                };
                last_cpu = Some((p, t_s, pr.cpu_s));
                Sample {
                    t_s,
                    rss_kib: pr.rss_kib,
                    cpu_pct,
                    open_files: pr.open_files,
                    threads: pr.threads,
                    jobs_completed,
                    jobs_failed,
                    gateway_up: true,
                }
            }
            None => Sample {
                t_s,
                rss_kib: 0,
                cpu_pct: 0.0,
                open_files: 0,
                threads: 0,
                jobs_completed,
                jobs_failed,
                gateway_up: false,
            },
        };
        samples
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(sample);
        tokio::select! {
            () = stop.cancelled() => {}
            () = tokio::time::sleep(Duration::from_secs(2)) => {}
        }
    }
}

/// A trend of one figure over the samples where the gateway had run `warm_s` already.
fn trend(samples: &[Sample], warm_s: f64, value: impl Fn(&Sample) -> f64) -> Trend {
    let up: Vec<&Sample> = samples.iter().filter(|s| s.gateway_up).collect();
    // The time since the gateway last started, for each sample.
    let mut warm = Vec::new();
    let mut since: Option<f64> = None;
    let mut was_up = false;
    for s in samples {
        if s.gateway_up && !was_up {
            since = Some(s.t_s);
        }
        was_up = s.gateway_up;
        if s.gateway_up && since.is_some_and(|t| s.t_s - t >= warm_s) {
            warm.push((s.t_s, value(s)));
        }
    }
    Trend {
        start: up.first().map_or(0.0, |s| value(s)),
        end: up.last().map_or(0.0, |s| value(s)),
        slope_per_hour: figures::slope_per_hour(&warm),
        warm_minutes: match (warm.first(), warm.last()) {
            (Some(a), Some(b)) => (b.0 - a.0) / 60.0,
            _ => 0.0,
        },
    }
}

#[allow(clippy::too_many_arguments)]
async fn judge(
    args: &SoakArgs,
    seed: u64,
    minutes: f64,
    rig: &Rig,
    direct: &Client,
    ledger: &load::Shared,
    samples: &Samples,
    marks: &[Mark],
    skipped: Vec<String>,
) -> Report {
    let (jobs, mut broken) = {
        let boards = rig.record.lock().unwrap_or_else(PoisonError::into_inner);
        check::jobs(&lock(ledger), &boards)
    };
    let history = check::records(direct, false).await;
    let audit = check::records(direct, true).await;
    let l = lock(ledger);
    let (history, audit, unaudited) = match (history, audit) {
        (Ok(h), Ok(a)) => {
            let unaudited = check::unaudited_submits(&l, &a);
            (check::numbering(&h), check::numbering(&a), unaudited)
        }
        (h, a) => {
            for e in [h.err(), a.err()].into_iter().flatten() {
                broken.push(format!("the history could not be read: {e}"));
            }
            Default::default()
        }
    };
    for (what, s) in [("history", &history), ("audit", &audit)] {
        if s.gaps > 0 {
            broken.push(format!(
                "the {what} misses {} numbers between {} and {}",
                s.gaps, s.first, s.last
            ));
        }
    }
    for id in unaudited.iter().take(20) {
        broken.push(format!(
            "job {id} was accepted but its submit is not in the audit trail"
        ));
    }
    let panics = check::panics(&rig.gateway_log());
    for p in panics.iter().take(20) {
        broken.push(format!("the gateway panicked: {p}"));
    }
    let samples = samples.lock().unwrap_or_else(PoisonError::into_inner);
    let rss = trend(&samples, args.warm_s, |s| s.rss_kib as f64);
    if rss.warm_minutes >= JUDGED_WARM_MINUTES
        && rss
            .slope_per_hour
            .is_some_and(|s| s > args.rss_bound_kib_per_hour)
    {
        broken.push(format!(
            "resident memory grew {:.0} KiB an hour once warm (bound {:.0})",
            rss.slope_per_hour.unwrap_or(0.0),
            args.rss_bound_kib_per_hour
        ));
    }
    let faults = check::counts(marks.iter().map(|m| m.kind.as_str()));
    Report {
        passed: broken.is_empty(),
        seed,
        minutes,
        machines: args.machines,
        jobs: serde_json::to_value(&jobs).unwrap_or_default(),
        faults,
        faults_skipped: skipped,
        history: serde_json::to_value(&history).unwrap_or_default(),
        audit: serde_json::to_value(&audit).unwrap_or_default(),
        unaudited_submits: unaudited.len() as u64,
        panics: panics.len() as u64,
        open_files: trend(&samples, args.warm_s, |s| s.open_files as f64),
        threads: trend(&samples, args.warm_s, |s| s.threads as f64),
        rss_kib: rss,
        rss_bound_kib_per_hour: args.rss_bound_kib_per_hour,
        load: serde_json::to_value(&l.figures).unwrap_or_default(),
        broken,
    }
}

impl Report {
    /// The final line a person reads.
    pub fn line(&self) -> String {
        let j = &self.jobs;
        let n = |k: &str| j[k].as_u64().unwrap_or(0);
        format!(
            "soak {}: {:.1} min, seed {}; jobs {} accepted + {} resumes: {} completed, {} failed \
             with offset, {} cancelled, {} lost, {} twice; {} faults ({} kinds); gaps {} history \
             / {} audit; {} panics; RSS {:.0} → {:.0} KiB, {} KiB/h",
            if self.passed { "passed" } else { "FAILED" },
            self.minutes,
            self.seed,
            n("accepted"),
            n("resumes"),
            n("completed"),
            n("failed_with_offset"),
            n("cancelled"),
            n("lost"),
            n("twice"),
            self.faults.values().sum::<u64>(),
            self.faults.len(),
            self.history["gaps"].as_u64().unwrap_or(0),
            self.audit["gaps"].as_u64().unwrap_or(0),
            self.panics,
            self.rss_kib.start,
            self.rss_kib.end,
            self.rss_kib
                .slope_per_hour
                .map_or("-".to_string(), |s| format!("{s:+.0}")),
        )
    }
}
