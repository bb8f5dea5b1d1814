//! What the OPC UA server costs on a cell of 64, 256 and 1 024 machines.
//!
//! Each size runs in a process of its own (this binary, started again), so that one size's
//! memory does not hide in the next one's:
//!
//! 1. **building the address space**: `opcua::serve` with the cell's description, from the
//!    call to the server answering with every machine tool built (the six NodeSets imported,
//!    then one MachineToolType instance and a channel per machine), and the resident set it
//!    added (`VmRSS`), per machine over a cell of none;
//! 2. **a bus event to the address space**: a machine's status taken by the server (the
//!    follower's `take`, as the bus subscription calls it), the values set and handed to the
//!    subscriptions: p50 and p99 over one status per machine, alternating link states so
//!    that every one changes a value. A client sees it at its next publishing interval on
//!    top.
//! 3. **ten clients on a busy cell**: every machine's status changes once a second (its
//!    ActiveProgram state and ChannelState with it); the process's CPU over 10 s as a share
//!    of one core, without clients and with ten asyncua clients (`opcua_client.py monitor`,
//!    run where asyncua is installed) each monitoring every ActiveProgram Name and State at
//!    a 1 s publishing interval. The clients run on the same two cores: their own CPU is not
//!    counted, but they take cores the server could use.
//!
//! `cargo bench --bench opcua` prints the figures; under `cargo test` a short smoke run
//! (16 machines) checks that it runs.

use std::time::{Duration, Instant};

use cellgate::client::follow::Follower as _;
use cellgate_core::config::{OpcuaConfig, SecurityConfig};
use cellgate_core::fanuc::Protocol;
use cellgate_core::mtconnect::Update;
use cellgate_core::mtconnect::desc::{CellDesc, MachineDesc};
use cellgate_core::pb;
use tokio_util::sync::CancellationToken;

fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0)
}

fn cell(machines: usize) -> CellDesc {
    CellDesc {
        cell: "bench".into(),
        machines: (0..machines)
            .map(|i| MachineDesc {
                name: format!("m{i:04}"),
                protocol: if i % 2 == 0 { Protocol::A } else { Protocol::B },
                part_counter: None,
                g05: false,
                identification: Default::default(),
            })
            .collect(),
        plcs: Vec::new(),
    }
}

fn cpu_seconds() -> f64 {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: getrusage writes a rusage into the pointer it is given.
    let usage = unsafe {
        libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr());
        usage.assume_init()
    };
    let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 / 1e6;
    t(usage.ru_utime) + t(usage.ru_stime)
}

/// Every machine's status, flipped once a second, for `span`: the process's CPU share.
async fn busy(shown: &cellgate::opcua::Shown, machines: usize, span: Duration) -> f64 {
    let (t0, c0) = (Instant::now(), cpu_seconds());
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    let mut flip = false;
    while t0.elapsed() < span {
        tick.tick().await;
        flip = !flip;
        for i in 0..machines {
            let state = if flip == (i % 2 == 0) {
                pb::LinkState::Sending
            } else {
                pb::LinkState::Idle
            };
            let status = pb::MachineStatus {
                machine: format!("m{i:04}"),
                link_state: state as i32,
                ..Default::default()
            };
            shown.take("bench", vec![Update::Status(Box::new(status))]);
        }
    }
    (cpu_seconds() - c0) / t0.elapsed().as_secs_f64()
}

/// Ten `opcua_client.py monitor` clients of `url`, once each says it monitors; none where
/// asyncua is missing.
async fn clients(url: &str, n: usize) -> Vec<tokio::process::Child> {
    use tokio::io::AsyncBufReadExt as _;
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/console/opcua_client.py");
    let mut out = Vec::new();
    for _ in 0..n {
        let Ok(mut child) = tokio::process::Command::new("python3")
            .args([script, "monitor", url])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::null())
            .kill_on_drop(true)
            .spawn()
        else {
            return Vec::new();
        };
        let mut lines = tokio::io::BufReader::new(child.stdout.take().unwrap()).lines();
        let ready = tokio::time::timeout(Duration::from_secs(300), lines.next_line()).await;
        if !matches!(ready, Ok(Ok(Some(ref l))) if l.starts_with("ready")) {
            return Vec::new();
        }
        out.push(child);
    }
    out
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// One size, in this process: prints `machines build_ms rss_kib p50_us p99_us`.
async fn one(machines: usize) {
    let session = cellgate::bus::open(&cellgate::bus::BusConfig {
        listen: Vec::new(),
        ..cellgate::bus::BusConfig::default()
    })
    .await
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let before = rss_kib();
    let start = Instant::now();
    let settings = cellgate::opcua::OpcuaSettings {
        config: OpcuaConfig {
            listen: "127.0.0.1:0".into(),
            pki_dir: Some(dir.path().join("pki")),
            ..OpcuaConfig::default()
        },
        prefix: "bench".into(),
        only: Some("bench".into()),
        own: Some(cell(machines)),
        security: SecurityConfig::default(),
        default_pki: dir.path().join("pki"),
    };
    let stop = CancellationToken::new();
    let served = cellgate::opcua::serve(session.clone(), settings, stop.clone())
        .await
        .unwrap();
    let built = start.elapsed();
    let after = rss_kib();
    let mut delays = Vec::with_capacity(machines);
    for i in 0..machines {
        let state = if i % 2 == 0 {
            pb::LinkState::Sending
        } else {
            pb::LinkState::Idle
        };
        let status = pb::MachineStatus {
            machine: format!("m{i:04}"),
            link_state: state as i32,
            ..Default::default()
        };
        let t = Instant::now();
        served
            .shown
            .take("bench", vec![Update::Status(Box::new(status))]);
        delays.push(t.elapsed());
    }
    delays.sort_unstable();
    let (p50, p99) = if delays.is_empty() {
        (0, 0)
    } else {
        (
            percentile(&delays, 0.5).as_micros(),
            percentile(&delays, 0.99).as_micros(),
        )
    };
    let span = Duration::from_secs(if machines >= 1024 { 10 } else { 2 });
    let (alone, with) = if machines == 0 {
        (0.0, 0.0)
    } else {
        let alone = busy(&served.shown, machines, span).await;
        let n = if machines >= 1024 { 10 } else { 1 };
        let children = clients(&served.url, n).await;
        let with = if children.is_empty() {
            -1.0
        } else {
            busy(&served.shown, machines, span).await
        };
        drop(children);
        (alone, with)
    };
    println!(
        "{machines} {} {} {p50} {p99} {} {}",
        built.as_millis(),
        after.saturating_sub(before),
        (alone * 1000.0) as i64,
        (with * 1000.0) as i64
    );
    stop.cancel();
    served.join().await;
    let _ = session.close().await;
}

fn run_size(machines: usize) -> (u64, u64, u64, u64, i64, i64) {
    let out = std::process::Command::new(std::env::current_exe().unwrap())
        .env("OPCUA_BENCH_MACHINES", machines.to_string())
        .env("RUST_LOG", "error")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find(|l| l.starts_with(&format!("{machines} ")))
        .unwrap_or_else(|| panic!("no figures for {machines}: {text}"));
    let f: Vec<i64> = line
        .split_whitespace()
        .skip(1)
        .map(|x| x.parse().unwrap())
        .collect();
    (
        f[0] as u64,
        f[1] as u64,
        f[2] as u64,
        f[3] as u64,
        f[4],
        f[5],
    )
}

fn main() {
    if let Ok(n) = std::env::var("OPCUA_BENCH_MACHINES") {
        let rt = tokio::runtime::Runtime::new().unwrap();
        rt.block_on(one(n.parse().unwrap()));
        return;
    }
    let full = std::env::args().any(|a| a == "--bench");
    let sizes: &[usize] = if full { &[64, 256, 1024] } else { &[16] };
    let (_, base, _, _, _, _) = run_size(0);
    println!("OPC UA server: the address space and a bus event's way into it");
    println!("  none: NodeSets imported, {base} KiB resident");
    for &n in sizes {
        let (ms, kib, p50, p99, alone, with) = run_size(n);
        println!(
            "  {n:>5} machines: built in {ms} ms, {kib} KiB resident ({:.1} KiB per machine over none); a status into the address space p50 {p50} µs, p99 {p99} µs",
            kib.saturating_sub(base) as f64 / n as f64
        );
        let clients = if n >= 1024 {
            "ten clients"
        } else {
            "one client"
        };
        let with = if with < 0 {
            "not measured (asyncua is not installed)".to_string()
        } else {
            format!("{:.1} %", with as f64 / 10.0)
        };
        println!(
            "         every status once a second: {:.1} % of a core without clients, {with} with {clients} monitoring every ActiveProgram Name and State",
            alone as f64 / 10.0
        );
    }
}
