//! How fast the historian's inserts go into a real PostgreSQL, and what catching up a cell
//! of many records takes: records of a busy cell (jobs, alarms, link and CNC states, tag
//! values) in pages of the historian's size, through the historian's own store
//! (`historian::store::Db::insert`, idempotent on `(cell, seq)`), one cell after another and
//! several cells at once; then the same pages again (all already there, as after a restart).
//!
//! `cargo bench --bench historian` prints the table (1 000 000 records of one cell, then 64
//! cells of 10 000); under `cargo test` a short smoke run checks that it runs. Needs Debian's
//! `postgresql` (a server is started in a temporary folder on loopback); says so and skips
//! where it is missing. What it does not measure: the bus side (the gateway answering pages),
//! timed by `history_query`.

use std::time::Instant;

use cellgate::historian::store::{Db, Log, config};
use cellgate_core::pb::{self, HistoryKind, history_record::Record};

mod bus {
    /// A free TCP port on loopback.
    pub fn free_port() -> u16 {
        std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map(|a| a.port())
            .unwrap_or(55432)
    }
}

#[path = "../tests/common/postgres.rs"]
#[allow(dead_code)]
mod postgres;

/// Record `seq` of a busy cell: mostly tag values and states, a job's end every 20th.
fn record(seq: u64) -> pb::HistoryRecord {
    let machine = format!("mill-{}", seq % 8);
    let unix_ms = 1_796_000_000_000 + seq * 250;
    let (kind, record) = match seq % 20 {
        0 => (
            HistoryKind::Job,
            Record::Job(pb::JobHistory {
                job_id: format!("{machine}-bench-{seq}"),
                ended_unix_ms: unix_ms,
                bytes_total: 65_536,
                bytes_sent: 65_536,
                outcome: pb::JobOutcome::Completed as i32,
                ..Default::default()
            }),
        ),
        1..=4 => (
            HistoryKind::Cnc,
            Record::Cnc(pb::MachineActivity::Reading as i32),
        ),
        5 => (
            HistoryKind::Alarm,
            Record::Alarm(pb::AlarmEvent {
                machine: machine.clone(),
                kind: pb::AlarmKind::CncAlarm as i32,
                alarm_number: "SR0855".to_string(),
                message: "a bench alarm".to_string(),
                unix_ms,
                code: "SR0855".to_string(),
            }),
        ),
        _ => (
            HistoryKind::Tag,
            Record::Tag(pb::TagValue {
                plc: "plc-1".to_string(),
                name: "parts".to_string(),
                value: Some(seq as f64),
                unix_ms: Some(unix_ms),
                ..Default::default()
            }),
        ),
    };
    pb::HistoryRecord {
        unix_ms,
        seq,
        machine,
        kind: kind as i32,
        record: Some(record),
    }
}

/// Inserts `n` records of `cell` in pages of the historian's size; seconds taken.
async fn fill(db: &Db, cell: &str, n: u64) -> f64 {
    let started = Instant::now();
    let page = u64::from(cellgate::historian::PAGE);
    let mut seq = 1;
    while seq <= n {
        let records: Vec<pb::HistoryRecord> = (seq..(seq + page).min(n + 1)).map(record).collect();
        db.insert(cell, Log::History, &records, &[]).await.unwrap();
        seq += page;
    }
    started.elapsed().as_secs_f64()
}

fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let Some(pg) = postgres::Postgres::start() else {
        println!("historian bench skipped: no PostgreSQL server here (Debian's postgresql)");
        return;
    };
    pg.create("bench");
    let db = Db::new(config(&pg.url("bench"), None).unwrap(), None);
    let (one, cells, each) = if full {
        (1_000_000, 64, 10_000)
    } else {
        (5_000, 4, 1_000)
    };

    println!("| what | records | seconds | records/s | peak RSS of this process |");
    println!("|---|---|---|---|---|");
    let s = fill(&db, "catch-up", one).await;
    println!(
        "| one cell caught up from nothing | {one} | {s:.1} | {:.0} | {} MiB |",
        one as f64 / s,
        rss_kib() / 1024
    );
    let s = fill(&db, "catch-up", one).await;
    println!(
        "| the same again (every record already there) | {one} | {s:.1} | {:.0} | {} MiB |",
        one as f64 / s,
        rss_kib() / 1024
    );
    let started = Instant::now();
    let mut tasks = Vec::new();
    for c in 0..cells {
        let db = db.clone();
        tasks.push(tokio::spawn(async move {
            fill(&db, &format!("cell-{c}"), each).await
        }));
    }
    for t in tasks {
        t.await.unwrap();
    }
    let s = started.elapsed().as_secs_f64();
    let n = cells * each;
    println!(
        "| {cells} cells at once | {n} | {s:.1} | {:.0} | {} MiB |",
        n as f64 / s,
        rss_kib() / 1024
    );
    let held = db.newest("catch-up", Log::History).await.unwrap();
    assert_eq!(held, one, "every record is there");
}
