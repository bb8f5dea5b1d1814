//! The historian against a real PostgreSQL: two cells on one bus, jobs, alarms and audit
//! records on both, every record in the tables once; the historian killed and started again,
//! a gateway restarted, the database stopped and started while jobs run: the sets of
//! `(cell, seq)` in the tables equal the gateways' own, and the jobs view agrees with them.

use crate::common;

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use cellgate::bus;
use cellgate::client::Client;
use cellgate_core::pb;
use common::bus::{connect_args, free_port};
use common::postgres::Postgres;

use super::gateway::Gateway;

/// The historian running in this process until stopped (or aborted, as `kill -9` ends it).
struct Historian {
    /// Where it serves its Prometheus metrics.
    metrics: String,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<Result<(), cellgate::historian::HistorianError>>,
}

impl Historian {
    fn start(router: u16, database: String) -> Historian {
        let port = free_port();
        let args = cellgate::historian::HistorianArgs {
            connect: connect_args(format!("tcp/127.0.0.1:{router}"), None),
            database,
            database_password_file: None,
            database_ca: None,
            prometheus: Some(format!("127.0.0.1:{port}")),
            status: false,
            json: false,
        };
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            cellgate::historian::run(&args, async {
                let _ = stopped.await;
            })
            .await
        });
        Historian {
            metrics: format!("http://127.0.0.1:{port}/metrics"),
            stop,
            task,
        }
    }

    async fn stop(self) {
        let _ = self.stop.send(());
        tokio::time::timeout(Duration::from_secs(30), self.task)
            .await
            .expect("the historian stops")
            .unwrap()
            .unwrap();
    }
}

/// Time the gateway knew something of, over `buckets`.
fn b_known(buckets: &[pb::UtilisationBucket]) -> u64 {
    buckets
        .iter()
        .map(|b| {
            b.reading_ms + b.idle_ms + b.alarm_ms + b.reset_ms + b.punching_ms + b.link_down_ms
        })
        .sum()
}

/// The database `site` on a server the test started, and its URL; `None`, said, where there
/// is no PostgreSQL to start.
fn site_database(pg: Option<Postgres>) -> Option<(Postgres, String)> {
    let Some(pg) = pg else {
        eprintln!("skipped: no PostgreSQL server here (Debian's postgresql; .ci/run installs it)");
        return None;
    };
    pg.create("site");
    let url = pg.url("site");
    Some((pg, url))
}

/// A zenoh router on a free loopback port, for the cells' gateways and the historian.
async fn router() -> (u16, zenoh::Session) {
    let port = free_port();
    let router = bus::open(&bus::BusConfig {
        mode: bus::BusMode::Router,
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        ..bus::BusConfig::default()
    })
    .await
    .unwrap();
    (port, router)
}

/// Every `(seq)` of `cell`'s log as its gateway answers it.
async fn gateway_seqs(client: &Client, audit: bool) -> BTreeSet<i64> {
    let mut seqs = BTreeSet::new();
    let mut after = 0;
    loop {
        let mut params = vec![
            ("_time".to_string(), "[..]".to_string()),
            ("limit".to_string(), "1000".to_string()),
        ];
        if after > 0 {
            params.push(("after".to_string(), after.to_string()));
        }
        if !audit {
            params.push((
                "kind".to_string(),
                "job,alarm,link,cnc,station,g05,tag,gateway,punch".to_string(),
            ));
        }
        let page: pb::HistoryPage = client.history(audit, &params).await.unwrap();
        for r in &page.records {
            seqs.insert(r.seq as i64);
        }
        if !page.more {
            return seqs;
        }
        after = page.next_after;
    }
}

/// Every `seq` of `cell` in `table` (none before the historian made the table).
async fn table_seqs(db: &tokio_postgres::Client, table: &str, cell: &str) -> Vec<i64> {
    db.query(
        &format!("SELECT seq FROM cellgate.{table} WHERE cell = $1 ORDER BY seq"),
        &[&cell],
    )
    .await
    .map(|rows| rows.iter().map(|r| r.get(0)).collect())
    .unwrap_or_default()
}

/// Waits until the tables hold exactly what both gateways hold, each record once.
async fn agree(db_url: &str, cells: &[(&str, Client)]) {
    let (db, conn) = tokio_postgres::connect(db_url, tokio_postgres::NoTls)
        .await
        .unwrap();
    tokio::spawn(conn);
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let mut differs = Vec::new();
        for (cell, client) in cells {
            for (table, audit) in [("history", false), ("audit", true)] {
                let ours = gateway_seqs(client, audit).await;
                let theirs = table_seqs(&db, table, cell).await;
                let once: BTreeSet<i64> = theirs.iter().copied().collect();
                assert_eq!(once.len(), theirs.len(), "{cell} {table}: a record twice");
                if ours != once {
                    differs.push(format!(
                        "{cell} {table}: gateway {} records (to {:?}), table {} (to {:?})",
                        ours.len(),
                        ours.last(),
                        once.len(),
                        once.last()
                    ));
                }
            }
        }
        if differs.is_empty() {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "the tables never agreed: {differs:#?}"
        );
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

/// Submits a small inline program to mill-1 of the cell `client` reaches, and waits until
/// it ended.
async fn a_job(client: &Client) {
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(
            b"%\nO7001\nG00X0Y0\nM30\n%\n".to_vec(),
        )),
        name: "O7001".to_string(),
        ..Default::default()
    };
    let (_, mut follower) = client.submit("mill-1", &request).await.unwrap();
    tokio::time::timeout(Duration::from_secs(60), follower.wait_end())
        .await
        .expect("the job ends")
        .unwrap();
    follower.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_record_of_two_cells_reaches_postgresql_once_through_restarts_and_outages() {
    let _ = tracing_subscriber::fmt()
        .with_env_filter("cellgate::historian=debug")
        .with_test_writer()
        .try_init();
    let Some((pg, url)) = site_database(Postgres::start()) else {
        return;
    };

    // A router, and the gateways of cells "north" and "south" on it.
    let (router_port, _router) = router().await;
    let north_dir = tempfile::tempdir().unwrap();
    let on_router = |cell: &'static str| {
        move |c: &mut cellgate_core::config::CellConfig, _: &std::path::Path| {
            c.cell = cell.to_string();
            c.bus.connect = vec![format!("tcp/127.0.0.1:{router_port}")];
        }
    };
    let north = Gateway::start_in(north_dir.path(), on_router("north")).await;
    let south = Gateway::start(on_router("south")).await;
    let options = |cell: &str| {
        let mut a = connect_args(format!("tcp/127.0.0.1:{router_port}"), None);
        a.cell = Some(cell.to_string());
        a
    };
    let clients = [
        (
            "north",
            Client::connect(&options("north").options().unwrap())
                .await
                .unwrap(),
        ),
        (
            "south",
            Client::connect(&options("south").options().unwrap())
                .await
                .unwrap(),
        ),
    ];
    for (_, c) in &clients {
        a_job(c).await;
    }

    // The historian copies both; each record once.
    let historian = Historian::start(router_port, url.clone());
    agree(&url, &clients).await;

    // Killed (no clean stop), jobs meanwhile, started again: it catches up.
    historian.task.abort();
    for (_, c) in &clients {
        a_job(c).await;
    }
    let historian = Historian::start(router_port, url.clone());
    agree(&url, &clients).await;

    // The database away while jobs run: the historian keeps trying and catches up.
    pg.down();
    for (_, c) in &clients {
        a_job(c).await;
    }
    tokio::time::sleep(Duration::from_secs(2)).await;
    pg.up();
    agree(&url, &clients).await;

    // A gateway restarted: its records go on where they were, none twice.
    north.stop().await;
    let north = Gateway::start_in(north_dir.path(), on_router("north")).await;
    let clients = [
        (
            "north",
            Client::connect(&options("north").options().unwrap())
                .await
                .unwrap(),
        ),
        clients.into_iter().nth(1).unwrap(),
    ];
    a_job(&clients[0].1).await;
    agree(&url, &clients).await;

    // The jobs view: one row per ended job, as the gateways' history has them.
    let (db, conn) = tokio_postgres::connect(&url, tokio_postgres::NoTls)
        .await
        .unwrap();
    tokio::spawn(conn);
    for (cell, n) in [("north", 3i64), ("south", 3)] {
        let row = db
            .query_one(
                "SELECT count(*), count(*) FILTER (WHERE outcome = 'completed'
                     AND program = 'O7001' AND bytes > 0 AND ended >= started)
                 FROM cellgate.jobs WHERE cell = $1 AND machine = 'mill-1'",
                &[&cell],
            )
            .await
            .unwrap();
        let (all, completed): (i64, i64) = (row.get(0), row.get(1));
        assert_eq!((all, completed), (n, n), "{cell}");
    }
    // The utilisation view divides each hour as the gateway's own answer does (the two asked
    // a moment apart: a share may differ by the time between them).
    let asked: pb::Utilisation = clients[1]
        .1
        .utilisation(&[
            ("_time".to_string(), "[now(-3h)..]".to_string()),
            ("machine".to_string(), "mill-1".to_string()),
        ])
        .await
        .unwrap();
    let buckets = &asked.machines[0].buckets;
    let rows = db
        .query(
            "SELECT (extract(epoch FROM hour) * 1000)::bigint, reading_ms, idle_ms, alarm_ms,
                    reset_ms, punching_ms, link_down_ms, unknown_ms, jobs_completed
             FROM cellgate.utilisation WHERE cell = 'south' AND machine = 'mill-1'
             ORDER BY hour",
            &[],
        )
        .await
        .unwrap();
    assert!(!rows.is_empty(), "no hour in the utilisation view");
    for row in &rows {
        let hour: i64 = row.get(0);
        let b = buckets
            .iter()
            .find(|b| b.start_unix_ms as i64 == hour)
            .unwrap_or_else(|| panic!("no bucket at {hour}: {buckets:?}"));
        let ours = [
            b.reading_ms,
            b.idle_ms,
            b.alarm_ms,
            b.reset_ms,
            b.punching_ms,
            b.link_down_ms,
            b.unknown_ms,
        ];
        for (i, gateway) in ours.iter().enumerate() {
            let view: i64 = row.get(i + 1);
            assert!(
                (view - *gateway as i64).abs() <= 5_000,
                "share {i} of {hour}: view {view} ms, gateway {gateway} ms ({b:?})"
            );
        }
        assert_eq!(row.get::<_, i64>(8), i64::from(b.jobs_completed), "{b:?}");
    }
    assert!(b_known(buckets) > 0);
    // The audit table names each action; a record is the protobuf JSON mapping.
    let row = db
        .query_one(
            "SELECT count(*) FROM cellgate.audit
             WHERE cell = 'south' AND action = 'job.submit' AND record->'audit'->>'action' = 'job.submit'",
            &[],
        )
        .await
        .unwrap();
    assert_eq!(row.get::<_, i64>(0), 3);
    // The schema's steps are recorded once each.
    let row = db
        .query_one("SELECT count(*) FROM cellgate.migrations", &[])
        .await
        .unwrap();
    assert_eq!(
        row.get::<_, i64>(0),
        cellgate::historian::schema::MIGRATIONS.len() as i64
    );

    // Its metrics: records copied per cell and log, and no lag once caught up.
    let text = reqwest::get(&historian.metrics)
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    for cell in ["north", "south"] {
        let copied = text
            .lines()
            .find(|l| {
                l.starts_with(&format!(
                    "cellgate_historian_records_total{{cell=\"{cell}\",log=\"history\""
                ))
            })
            .unwrap_or_else(|| panic!("no records counter of {cell}:\n{text}"));
        let n: f64 = copied.rsplit(' ').next().unwrap().parse().unwrap();
        assert!(n > 0.0, "{copied}");
        let lag = text
            .lines()
            .find(|l| {
                l.starts_with(&format!(
                    "cellgate_historian_lag{{cell=\"{cell}\",log=\"audit\""
                ))
            })
            .unwrap_or_else(|| panic!("no lag of {cell}:\n{text}"));
        assert!(lag.ends_with(" 0"), "{lag}");
    }

    // `--status` says where each cell stands: nothing behind, no gap.
    let out = common::cli::command([
        "historian",
        "-e",
        &format!("tcp/127.0.0.1:{router_port}"),
        "--database",
        &url,
        "--status",
    ])
    .output()
    .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for cell in ["north", "south"] {
        for log in ["history", "audit"] {
            let row: Vec<&str> = text
                .lines()
                .find(|l| l.starts_with(cell) && l.split_whitespace().nth(1) == Some(log))
                .unwrap_or_else(|| panic!("no {cell} {log} in:\n{text}"))
                .split_whitespace()
                .collect();
            // DATABASE and GATEWAY differ by what was recorded since the last copy (asked
            // every second; the gateway commits every second): a few, never far.
            let (held, newest): (u64, u64) = (row[2].parse().unwrap(), row[3].parse().unwrap());
            assert!(newest >= held && newest - held <= 50, "{text}");
            assert_eq!(row[5], "0", "no gap: {text}");
        }
    }

    let out = common::cli::command([
        "historian",
        "-e",
        &format!("tcp/127.0.0.1:{router_port}"),
        "--database",
        &url,
        "--status",
        "--json",
    ])
    .output()
    .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v.as_array().map(Vec::len), Some(4), "{v}");
    assert!(v.as_array().unwrap().iter().all(|r| r["gaps"] == 0), "{v}");

    historian.stop().await;
    north.stop().await;
    south.stop().await;
}

/// Records a gateway trimmed before the historian saw them are a row of `cellgate.gaps`:
/// said, not papered over; what is kept is copied.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn records_trimmed_before_they_were_copied_are_a_gap_in_the_table() {
    let Some((_pg, url)) = site_database(Postgres::start()) else {
        return;
    };
    let (router_port, _router) = router().await;
    // A cell that keeps 20 records of each log: retention runs as the gateway starts.
    let dir = tempfile::tempdir().unwrap();
    let small = |c: &mut cellgate_core::config::CellConfig, _: &std::path::Path| {
        c.cell = "west".to_string();
        c.history.max_records = 20;
        c.bus.connect = vec![format!("tcp/127.0.0.1:{router_port}")];
    };
    let west = Gateway::start_in(dir.path(), small).await;
    let mut options = connect_args(format!("tcp/127.0.0.1:{router_port}"), None);
    options.cell = Some("west".to_string());
    let client = Client::connect(&options.options().unwrap()).await.unwrap();
    // More than 20 records (the PLC's parts tag is recorded every second).
    let deadline = Instant::now() + Duration::from_secs(60);
    while gateway_seqs(&client, false).await.len() <= 40 {
        assert!(Instant::now() < deadline, "the history does not grow");
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    client.close().await;
    west.stop().await;
    let west = Gateway::start_in(dir.path(), small).await;
    let client = Client::connect(&options.options().unwrap()).await.unwrap();
    let kept = gateway_seqs(&client, false).await;
    let first = *kept.first().unwrap();
    assert!(first > 1, "retention trimmed the oldest: {kept:?}");

    let historian = Historian::start(router_port, url.clone());
    let (db, conn) = tokio_postgres::connect(&url, tokio_postgres::NoTls)
        .await
        .unwrap();
    tokio::spawn(conn);
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let gaps = db
            .query(
                "SELECT first_seq, last_seq FROM cellgate.gaps WHERE cell = 'west' AND log = 'history'",
                &[],
            )
            .await
            .map(|rows| {
                rows.iter()
                    .map(|r| (r.get::<_, i64>(0), r.get::<_, i64>(1)))
                    .collect::<Vec<_>>()
            })
            .unwrap_or_default();
        let copied = table_seqs(&db, "history", "west").await;
        if let Some(&(from, to)) = gaps.first()
            && copied.first() == Some(&(to + 1))
        {
            assert_eq!(from, 1, "{gaps:?}");
            assert!(to + 1 >= first, "{gaps:?}, the first kept was {first}");
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no gap said: {gaps:?}, copied from {:?}",
            copied.first()
        );
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
    historian.stop().await;
    client.close().await;
    west.stop().await;
}

/// TLS to the database: with the CA that signed the server's certificate the connection is
/// encrypted and the server checked; `sslmode=require` without a CA is refused before
/// anything is sent; a server whose certificate another CA signed is not spoken to.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_database_is_reached_over_tls_and_its_certificate_checked() {
    let pki = common::pki::Pki::new();
    let Some((_pg, url)) = site_database(Postgres::start_tls(
        &pki.cert("gateway"),
        &pki.key("gateway"),
    )) else {
        return;
    };
    let url = format!("{url}?sslmode=require");
    let config = cellgate::historian::store::config(&url, None).unwrap();

    let tls = cellgate::historian::store::tls(&config, Some(&pki.ca())).unwrap();
    let db = cellgate::historian::store::Db::new(config.clone(), tls);
    let client = db.client().await.unwrap();
    let row = client
        .query_one(
            "SELECT ssl FROM pg_stat_ssl WHERE pid = pg_backend_pid()",
            &[],
        )
        .await
        .unwrap();
    assert!(row.get::<_, bool>(0), "the connection is encrypted");
    assert_eq!(
        db.newest("north", cellgate::historian::store::Log::History)
            .await
            .unwrap(),
        0
    );

    match cellgate::historian::store::tls(&config, None) {
        Err(refused) => assert!(refused.to_string().contains("--database-ca"), "{refused}"),
        Ok(_) => panic!("sslmode=require without a CA is taken"),
    }

    let other = common::pki::Pki::new();
    let tls = cellgate::historian::store::tls(&config, Some(&other.ca())).unwrap();
    let db = cellgate::historian::store::Db::new(config, tls);
    let e = db.client().await.unwrap_err();
    let text = cellgate::historian::db_text(&e);
    assert!(text.to_lowercase().contains("certificate"), "{text}");
}
