//! The historian as it runs on a site: a process of its own (`cellgate historian`) following
//! gateways on a router over the bus, into a real PostgreSQL. Two figures the store-only
//! bench (`historian`) cannot give:
//!
//! - **the bus side of a catch-up**: a gateway whose history already holds many records
//!   (written into its store before it starts) is read from nothing, in pages over the bus,
//!   until the table holds every record: time, and the historian's CPU and peak memory;
//! - **the steady cost of following busy cells**: 64 gateways, each with a simulated PLC
//!   whose counted parts tag (kept in the history) changes ten times a second, followed once
//!   caught up: the historian's share of a core, its resident size, and the records a second
//!   that reach the table.
//!
//! The gateways run in this process, the historian and the database in their own, so the
//! historian's CPU is its own (`/proc/PID/stat`). `cargo bench --bench historian_follow`
//! prints the table; under `cargo test` a short smoke run checks that it runs. Needs Debian's
//! `postgresql` (a server is started in a temporary folder on loopback); says so and skips
//! where it is missing.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use cellgate::history::{History, Log};
use cellgate_core::config::{CellConfig, HistoryConfig, TagConfig};
use cellgate_core::pb::{self, HistoryKind, history_record::Record};
use tokio_util::sync::CancellationToken;

#[path = "../tests/common/postgres.rs"]
#[allow(dead_code)]
mod postgres;

mod bus {
    /// A free TCP port on loopback.
    pub fn free_port() -> u16 {
        std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map(|a| a.port())
            .unwrap_or(55431)
    }
}
use bus::free_port;

/// CPU time (user and system) and peak resident size of process `pid`.
fn usage(pid: u32) -> (Duration, u64) {
    let ticks = std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .ok()
        .and_then(|s| {
            // The fields after the command's name, which is in parentheses.
            let rest = s.rsplit_once(')')?.1.split_whitespace().collect::<Vec<_>>();
            Some(rest.get(11)?.parse::<u64>().ok()? + rest.get(12)?.parse::<u64>().ok()?)
        })
        .unwrap_or(0);
    let hwm = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0);
    // Clock ticks are 1/100 s on Linux (`getconf CLK_TCK`).
    (Duration::from_millis(ticks * 10), hwm)
}

/// A cell of the embedded default whose only link is its simulated PLC, its parts counted
/// every `tick_ms` and kept in the history, on the router.
fn busy_cell(name: &str, router: u16, dir: &std::path::Path, tick_ms: u32) -> CellConfig {
    let mut c = CellConfig::embedded_default();
    c.cell = name.to_string();
    c.machines.clear();
    c.console = None;
    c.mtconnect = None;
    c.opcua = None;
    c.bus.listen = vec![format!("tcp/127.0.0.1:{}", free_port())];
    c.bus.connect = vec![format!("tcp/127.0.0.1:{router}")];
    c.programs.dir = dir.join("programs");
    let plc = &mut c.plcs[0];
    plc.tags.retain(|t: &TagConfig| t.name == "parts");
    for t in &mut plc.tags {
        t.poll_ms = tick_ms;
    }
    for tick in &mut plc.sim.ticks {
        tick.every_ms = tick_ms;
    }
    c
}

/// A gateway of `config` running in this process until `stop`.
fn gateway(config: CellConfig, stop: &CancellationToken) -> tokio::task::JoinHandle<()> {
    let stop = stop.clone();
    tokio::spawn(async move {
        if let Err(e) = cellgate::gateway::run(config, stop.cancelled_owned()).await {
            eprintln!("gateway: {e}");
        }
    })
}

/// `cellgate historian` in a process of its own.
fn historian(router: u16, database: &str) -> Child {
    Command::new(env!("CARGO_BIN_EXE_cellgate"))
        .args([
            "historian",
            "-e",
            &format!("tcp/127.0.0.1:{router}"),
            "--database",
            database,
        ])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("cellgate historian starts")
}

/// Records of `cell` in the history table.
async fn held(db: &tokio_postgres::Client, cell: &str) -> i64 {
    db.query_one(
        "SELECT count(*) FROM cellgate.history WHERE cell = $1",
        &[&cell],
    )
    .await
    .map(|r| r.get(0))
    .unwrap_or(0)
}

/// Records of every cell in the history table.
async fn held_all(db: &tokio_postgres::Client) -> i64 {
    db.query_one("SELECT count(*) FROM cellgate.history", &[])
        .await
        .map(|r| r.get(0))
        .unwrap_or(0)
}

/// Writes `n` records of a busy day into the history store in `dir` (as the gateway's own
/// writer does), before the gateway opens it.
async fn prefill(dir: &std::path::Path, n: u64) {
    let stop = CancellationToken::new();
    let config = HistoryConfig {
        max_records: 50_000_000,
        tag_values: 10_000_000,
        keep_days: 3650,
        keep_audit_days: 3650,
        ..HistoryConfig::default()
    };
    let (h, writer) = History::open(dir, &config, stop.clone()).await.unwrap();
    let start = pb::unix_ms(std::time::SystemTime::now()) - n * 100;
    for i in 0..n {
        let machine = format!("mill-{}", i % 8);
        let (kind, record) = if i % 10 == 0 {
            (
                HistoryKind::Job,
                Record::Job(pb::JobHistory {
                    job_id: format!("{machine}-{i}"),
                    ended_unix_ms: start + i * 100,
                    bytes_total: 65_536,
                    bytes_sent: 65_536,
                    outcome: pb::JobOutcome::Completed as i32,
                    ..Default::default()
                }),
            )
        } else {
            (
                HistoryKind::Cnc,
                Record::Cnc(pb::MachineActivity::Reading as i32),
            )
        };
        h.record_at(Log::History, &machine, kind, record, start + i * 100);
        // The writer's queue is bounded: a record handed to a full one is dropped (counted),
        // its number a gap in the store.
        while h.backlog() > 12_000 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }
    assert!(
        h.settled(Duration::from_secs(600)).await,
        "the store took them"
    );
    stop.cancel();
    drop(h);
    let _ = writer.await;
}

async fn connect(url: &str) -> tokio_postgres::Client {
    let (db, connection) = tokio_postgres::connect(url, tokio_postgres::NoTls)
        .await
        .expect("the database answers");
    tokio::spawn(connection);
    db
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let Some(pg) = postgres::Postgres::start() else {
        println!("historian_follow bench skipped: no PostgreSQL server here (Debian's postgresql)");
        return;
    };
    let (records, cells, window) = if full {
        (1_000_000u64, 64usize, Duration::from_secs(60))
    } else {
        (2_000, 2, Duration::from_secs(3))
    };
    let router_port = free_port();
    let _router = cellgate::bus::open(&cellgate::bus::BusConfig {
        mode: cellgate::bus::BusMode::Router,
        listen: vec![format!("tcp/127.0.0.1:{router_port}")],
        ..cellgate::bus::BusConfig::default()
    })
    .await
    .unwrap();

    println!("| what | figure |");
    println!("|---|---|");

    // The bus side of a catch-up: one gateway with `records` records already in its store.
    pg.create("catchup");
    let url = pg.url("catchup");
    let dir = tempfile::tempdir().unwrap();
    let mut config = busy_cell("big", router_port, dir.path(), 60_000);
    config.history.max_records = 50_000_000;
    config.history.tag_values = 10_000_000;
    prefill(&config.history.dir_in(&config.programs.dir), records).await;
    let stop = CancellationToken::new();
    let big = gateway(config, &stop);
    let db = connect(&url).await;
    let mut h = historian(router_port, &url);
    let started = Instant::now();
    // The cell found (a new cell is looked for every few seconds), then every record written
    // before it started.
    let mut first = None;
    loop {
        let n = held(&db, "big").await;
        if n > 0 && first.is_none() {
            first = Some((started.elapsed(), n));
        }
        if n >= records as i64 {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(1800),
            "the catch-up ends"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let took = started.elapsed();
    let (found, at_first) = first.unwrap_or_default();
    let copying = (took - found).as_secs_f64().max(0.001);
    let (cpu, hwm) = usage(h.id());
    println!(
        "| catch-up over the bus: {records} records of one cell | found after {:.1} s, then \
         {:.1} s ({:.0} records/s); historian CPU {:.1} s, peak RSS {} MiB |",
        found.as_secs_f64(),
        copying,
        (records as f64 - at_first as f64) / copying,
        cpu.as_secs_f64(),
        hwm / 1024
    );
    let gaps: i64 = db
        .query_one("SELECT count(*) FROM cellgate.gaps", &[])
        .await
        .map(|r| r.get(0))
        .unwrap_or(-1);
    assert_eq!(gaps, 0, "every record was there to copy");
    let _ = h.kill();
    let _ = h.wait();
    stop.cancel();
    let _ = big.await;

    // The steady cost of following `cells` busy cells.
    pg.create("steady");
    let url = pg.url("steady");
    let stop = CancellationToken::new();
    let dirs: Vec<_> = (0..cells).map(|_| tempfile::tempdir().unwrap()).collect();
    let gateways: Vec<_> = dirs
        .iter()
        .enumerate()
        .map(|(i, d)| {
            gateway(
                busy_cell(&format!("c{i:02}"), router_port, d.path(), 100),
                &stop,
            )
        })
        .collect();
    let db = connect(&url).await;
    let mut h = historian(router_port, &url);
    // Caught up: every cell in the table, and a count that grows at the cells' pace.
    let started = Instant::now();
    loop {
        let present: i64 = db
            .query_one("SELECT count(DISTINCT cell) FROM cellgate.history", &[])
            .await
            .map(|r| r.get(0))
            .unwrap_or(0);
        if present == cells as i64 {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(600),
            "every cell is followed ({present} of {cells})"
        );
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    tokio::time::sleep(Duration::from_secs(5)).await;
    let (cpu0, _) = usage(h.id());
    let rows0 = held_all(&db).await;
    let t0 = Instant::now();
    tokio::time::sleep(window).await;
    let (cpu1, hwm) = usage(h.id());
    let rows1 = held_all(&db).await;
    let secs = t0.elapsed().as_secs_f64();
    println!(
        "| following {cells} busy cells ({} s) | historian {:.1} % of one core, peak RSS {} MiB; \
         {:.0} records/s into the table |",
        window.as_secs(),
        100.0 * (cpu1 - cpu0).as_secs_f64() / secs,
        hwm / 1024,
        (rows1 - rows0) as f64 / secs
    );
    assert!(rows1 > rows0, "records kept arriving");
    let _ = h.kill();
    let _ = h.wait();
    stop.cancel();
    for g in gateways {
        let _ = g.await;
    }
}
