//! How long the cell's history takes to answer over a week of a busy cell.
//!
//! A week of 64 machines is generated into a history store (the gateway's own, through
//! `History::record_at`): a job every 5 minutes per machine (its start and end states, its
//! link states and its record), an audit record per submit, a part counter per machine every
//! 2 minutes, an alarm per machine every 500 minutes, and the gateway's alive records. Then
//! the queries a console or an MES asks are timed, each five times (median and slowest).
//!
//! `cargo bench --bench history_query` prints the table (a week, 64 machines); under `cargo
//! test` a short smoke run (a day, 2 machines) checks that it runs.

use std::time::{Duration, Instant};

use cellgate::history::{History, Log};
use cellgate_core::config::HistoryConfig;
use cellgate_core::history::{self, HistoryQuery, Store};
use cellgate_core::pb::{self, HistoryKind, history_record::Record};
use tokio_util::sync::CancellationToken;

const MINUTE: u64 = 60_000;

fn query(store: Store, params: &[(&str, &str)], from: u64, to: u64) -> HistoryQuery {
    let mut q = HistoryQuery::parse(store, params.iter().copied(), |_| Err(String::new()), to)
        .expect("valid parameters");
    q.from_ms = from;
    q.to_ms = to;
    q
}

fn median(mut v: Vec<Duration>) -> (Duration, Duration) {
    v.sort();
    (v[v.len() / 2], *v.last().unwrap_or(&Duration::ZERO))
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let (machines, days) = if full { (64u64, 7u64) } else { (2, 1) };
    let dir = tempfile::tempdir().unwrap();
    let stop = CancellationToken::new();
    let config = HistoryConfig {
        max_records: 50_000_000,
        tag_values: 100_000,
        keep_days: 3650,
        keep_audit_days: 3650,
        ..HistoryConfig::default()
    };
    let (h, writer) = History::open(dir.path(), &config, stop.clone())
        .await
        .unwrap();
    // The week lies ahead of the store's own records (its start, its alive records while
    // this runs): a record's time never goes back, so a week in the past would be written
    // at the time of the last record.
    let start = pb::unix_ms(std::time::SystemTime::now()) + MINUTE;
    let end = start + days * 24 * 60 * MINUTE;
    let generated = Instant::now();
    let mut n = 0u64;
    for minute in 0..days * 24 * 60 {
        let t = start + minute * MINUTE;
        for m in 0..machines {
            let name = format!("m{m:02}");
            // Each machine's jobs start at its own minute of the five.
            match (minute + m) % 5 {
                0 => {
                    h.record_at(
                        Log::Audit,
                        &name,
                        HistoryKind::Audit,
                        Record::Audit(pb::AuditRecord {
                            action: "job.submit".into(),
                            target: name.clone(),
                            detail: "O1000 revision 3".into(),
                            ok: true,
                            ..Default::default()
                        }),
                        t,
                    );
                    h.record_at(
                        Log::History,
                        &name,
                        HistoryKind::Link,
                        Record::Link(pb::LinkState::Sending as i32),
                        t,
                    );
                    h.record_at(
                        Log::History,
                        &name,
                        HistoryKind::Cnc,
                        Record::Cnc(pb::MachineActivity::Reading as i32),
                        t,
                    );
                    n += 3;
                }
                4 => {
                    h.record_at(
                        Log::History,
                        &name,
                        HistoryKind::Link,
                        Record::Link(pb::LinkState::Idle as i32),
                        t,
                    );
                    h.record_at(
                        Log::History,
                        &name,
                        HistoryKind::Cnc,
                        Record::Cnc(pb::MachineActivity::Idle as i32),
                        t,
                    );
                    h.record_at(
                        Log::History,
                        &name,
                        HistoryKind::Job,
                        Record::Job(pb::JobHistory {
                            job_id: format!("{name}-{minute}"),
                            ended_unix_ms: t,
                            bytes_total: 40_000,
                            bytes_sent: 40_000,
                            outcome: pb::JobOutcome::Completed as i32,
                            ..Default::default()
                        }),
                        t,
                    );
                    n += 3;
                }
                _ => {}
            }
            if minute % 2 == 0 {
                h.record_at(
                    Log::History,
                    "plc-1",
                    HistoryKind::Tag,
                    Record::Tag(pb::TagValue {
                        plc: "plc-1".into(),
                        name: format!("parts-{name}"),
                        value: Some((minute / 2) as f64),
                        ..Default::default()
                    }),
                    t,
                );
                n += 1;
            }
            if (minute + m * 7) % 500 == 0 {
                h.record_at(
                    Log::History,
                    &name,
                    HistoryKind::Alarm,
                    Record::Alarm(pb::AlarmEvent {
                        machine: name.clone(),
                        kind: pb::AlarmKind::CncAlarm as i32,
                        alarm_number: "SR0945".into(),
                        ..Default::default()
                    }),
                    t,
                );
                n += 1;
            }
        }
        h.record_at(
            Log::History,
            "",
            HistoryKind::Gateway,
            Record::Gateway(pb::GatewayRecord {
                event: pb::gateway_record::Event::Alive as i32,
                version: String::new(),
            }),
            t,
        );
        n += 1;
        // Keep the writer's queue from overflowing.
        while h.backlog() > 12_000 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }
    assert!(
        h.settled(Duration::from_secs(600)).await,
        "the store took everything"
    );
    assert_eq!(h.health().dropped, 0, "nothing dropped while generating");
    let took = generated.elapsed();
    let size: u64 = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().metadata().unwrap().len())
        .sum();
    println!(
        "history of {machines} machines over {days} day(s): {n} records written in {:.1} s ({:.0} records/s), store {:.1} MiB",
        took.as_secs_f64(),
        n as f64 / took.as_secs_f64(),
        size as f64 / (1024.0 * 1024.0)
    );

    let week = |store, p: &[(&str, &str)]| query(store, p, start, end);
    let cases: Vec<(&str, Log, HistoryQuery)> = vec![
        (
            "jobs of one machine, whole range",
            Log::History,
            week(
                Store::History,
                &[("machine", "m01"), ("kind", "job"), ("limit", "10000")],
            ),
        ),
        (
            "alarms of every machine, whole range",
            Log::History,
            week(Store::History, &[("kind", "alarm"), ("limit", "10000")]),
        ),
        (
            "everything of one machine, last day",
            Log::History,
            query(
                Store::History,
                &[("machine", "m01"), ("limit", "10000")],
                end - 24 * 60 * MINUTE,
                end,
            ),
        ),
        (
            "everything, last hour (time order)",
            Log::History,
            query(
                Store::History,
                &[("limit", "10000")],
                end - 60 * MINUTE,
                end,
            ),
        ),
        (
            "one tag's values, whole range",
            Log::History,
            week(
                Store::History,
                &[("tag", "plc-1/parts-m01"), ("limit", "10000")],
            ),
        ),
        (
            "audit, whole range (first 10 000)",
            Log::Audit,
            week(Store::Audit, &[("limit", "10000")]),
        ),
    ];
    println!(
        "{:<42} {:>9} {:>10} {:>10}",
        "query", "records", "median", "slowest"
    );
    for (what, log, q) in cases {
        let mut times = Vec::new();
        let mut count = 0;
        for _ in 0..5 {
            let t = Instant::now();
            let page = h.query(log, q.clone()).await.unwrap();
            times.push(t.elapsed());
            count = page.records.len();
        }
        let (med, max) = median(times);
        println!(
            "{what:<42} {count:>9} {:>8.1} ms {:>8.1} ms",
            med.as_secs_f64() * 1e3,
            max.as_secs_f64() * 1e3
        );
        assert!(count > 0, "{what}: no records");
    }
    // Utilisation of every machine, by hour and by shift, as the route computes it.
    for bucket in [history::Bucket::Hour, history::Bucket::Shift] {
        let mut times = Vec::new();
        let mut reading = 0u64;
        for _ in 0..5 {
            let t = Instant::now();
            let buckets = history::buckets(start, end, bucket, &h.shifts());
            let gateway = h.gateway_marks(start, end).await.unwrap();
            for m in 0..machines {
                let marks = h
                    .machine_marks(
                        format!("m{m:02}"),
                        Some(format!("plc-1/parts-m{m:02}")),
                        start,
                        end,
                    )
                    .await
                    .unwrap();
                let mut all = gateway.clone();
                all.extend(marks.marks);
                cellgate::history::sort_marks(&mut all);
                let u = history::utilisation(&all, &marks.jobs, &marks.parts, true, &buckets, end);
                reading = u.iter().map(|b| b.reading_ms).sum();
            }
            times.push(t.elapsed());
        }
        let (med, max) = median(times);
        println!(
            "{:<42} {:>9} {:>8.1} ms {:>8.1} ms",
            format!("utilisation of {machines} machines by {bucket:?}"),
            "-",
            med.as_secs_f64() * 1e3,
            max.as_secs_f64() * 1e3
        );
        assert!(reading > 0, "utilisation counted reading time");
    }
    stop.cancel();
    writer.await.unwrap();
}
