//! The site's history in PostgreSQL (`cellgate historian`): a client of the bus contract, as
//! the site console and the MTConnect agent are, that follows every cell whose gateway is on
//! the bus and copies each cell's history and audit records into `cellgate.history` and
//! `cellgate.audit`, one row per record, unique on `(cell, seq)`.
//!
//! Each cell's log is read by sequence from the highest `seq` the database holds for it
//! (`after`, oldest first, a page at a time) and then followed by asking again every second;
//! inserts are idempotent on `(cell, seq)`, so a restart of the historian, of a gateway or of
//! the database loses nothing and copies nothing twice. A record the gateway trimmed before
//! the historian saw it is a row of `cellgate.gaps` and a warning. One page per cell and log
//! is in flight at most: a database slower than the cells makes the historian fall behind
//! (the lag is in `--status` and the log), never grow.
//!
//! - [`schema`]: the tables and views, created and migrated by the historian itself;
//! - [`store`]: the database connection, kept and made again, and the inserts.

pub mod schema;
pub mod store;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

use tokio_util::sync::CancellationToken;

use crate::client::{Client, ClientError};
use cellgate_core::pb;
use store::{Db, Log};

/// Records asked for at once.
pub const PAGE: u32 = 500;
/// How often a cell that is caught up is asked again: records reach the tables within about
/// this long of the gateway recording them.
pub const FOLLOW_EVERY: Duration = Duration::from_secs(1);
/// The longest wait between two tries after a failure (the database or a gateway away).
pub const RETRY_MAX: Duration = Duration::from_secs(10);
/// How often the bus is asked which cells there are.
const DISCOVER_EVERY: Duration = Duration::from_secs(5);

/// `cellgate historian`: the site's history in PostgreSQL.
#[derive(Debug, Clone, clap::Args)]
pub struct HistorianArgs {
    #[command(flatten)]
    pub connect: crate::client::cli::ConnectArgs,
    /// The database: postgresql://USER@HOST:PORT/DBNAME (the password from the URL,
    /// PGPASSWORD or --database-password-file).
    #[arg(long, value_name = "URL", env = "CELLGATE_DATABASE")]
    pub database: String,
    /// A file holding the database user's password (its first line).
    #[arg(long, value_name = "FILE")]
    pub database_password_file: Option<PathBuf>,
    /// The CA certificates (PEM) that signed the database server's certificate: TLS to the
    /// database, its certificate and name checked (the URL's sslmode: prefer or require).
    #[arg(long, value_name = "FILE")]
    pub database_ca: Option<PathBuf>,
    /// Print, for each cell, the newest record in the database and on its gateway, and the
    /// gaps, then exit.
    #[arg(long)]
    pub status: bool,
    /// Serve Prometheus metrics (records copied, failures, lag per cell) on
    /// ADDRESS:PORT/metrics; OTLP too where OTEL_EXPORTER_OTLP_ENDPOINT is set.
    #[arg(long, value_name = "ADDR")]
    pub prometheus: Option<String>,
    /// With --status: print a JSON array (cell, log, database, gateway, lag, gaps).
    #[arg(long, requires = "status")]
    pub json: bool,
}

/// Why the historian could not start or stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum HistorianError {
    /// The arguments or the database URL cannot work.
    #[error("{0}")]
    Config(String),
    #[error(transparent)]
    Client(#[from] ClientError),
    #[error("the database: {}", db_text(.0))]
    Database(#[from] tokio_postgres::Error),
}

/// A database error with what the server said (tokio-postgres shows only "db error").
pub fn db_text(e: &tokio_postgres::Error) -> String {
    match e.as_db_error() {
        Some(db) => format!("{} ({})", db.message(), db.code().code()),
        None => match std::error::Error::source(e) {
            Some(source) => format!("{e}: {source}"),
            None => e.to_string(),
        },
    }
}

/// Runs the historian until `shutdown`, or (with `--status`) prints where each cell stands.
pub async fn run(
    args: &HistorianArgs,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), HistorianError> {
    let config = store::config(&args.database, args.database_password_file.as_deref())?;
    let tls = store::tls(&config, args.database_ca.as_deref())?;
    let db = Db::new(config, tls);
    let options = args.connect.options()?;
    let session = crate::client::open_session(&options).await?;
    let timeout = Duration::from_secs(args.connect.timeout);
    let prefix = options.prefix.clone();
    if args.status {
        let result = status(
            &db,
            &session,
            &prefix,
            options.cell.as_deref(),
            timeout,
            args.json,
        )
        .await;
        let _ = session.close().await;
        return result;
    }
    let telemetry = crate::telemetry::TelemetryConfig {
        prometheus: args.prometheus.clone(),
        service_name: "cellgate-historian".to_string(),
        ..Default::default()
    };
    let otlp = std::env::var("OTEL_EXPORTER_OTLP_ENDPOINT").ok();
    let _metrics = crate::telemetry::install_metrics(
        &telemetry,
        crate::telemetry::otlp_endpoint(&telemetry, otlp.as_deref()).as_deref(),
    )
    .map_err(|e| HistorianError::Config(e.to_string()))?;
    // Said at once when the database cannot be reached: the historian keeps trying.
    match db.client().await {
        Ok(c) => {
            if schema::has_timescaledb(&c).await.unwrap_or(false) {
                tracing::info!(
                    "TimescaleDB is installed; the tables stay plain tables: a hypertable needs \
                     its time column in every unique index, and (cell, seq) must stay unique alone"
                );
            }
        }
        Err(e) => {
            tracing::warn!(error = %db_text(&e), "the database cannot be reached yet; trying again");
        }
    }
    eprintln!(
        "cellgate historian: the cells behind {} into {}",
        options.endpoint,
        store::shown(&args.database)
    );
    let stop = CancellationToken::new();
    // The followers end with this future, however it ends (dropped too).
    let _stop_followers = stop.clone().drop_guard();
    let mut followed: BTreeMap<String, tokio::task::JoinHandle<()>> = BTreeMap::new();
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        match Client::discover(&session, &prefix, timeout).await {
            Ok(cells) => {
                for (cell, admin) in cells {
                    if options.cell.as_ref().is_some_and(|c| *c != cell)
                        || followed.contains_key(&cell)
                    {
                        continue;
                    }
                    let client =
                        match Client::attach(session.clone(), &prefix, &cell, admin, timeout) {
                            Ok(c) => c,
                            Err(e) => {
                                tracing::warn!(%cell, error = %e, "a cell not followed");
                                continue;
                            }
                        };
                    tracing::info!(%cell, "following the cell's history and audit trail");
                    let (db, stop) = (db.clone(), stop.clone());
                    followed.insert(
                        cell.clone(),
                        tokio::spawn(async move {
                            tokio::join!(
                                follow(&client, &db, &cell, Log::History, &stop),
                                follow(&client, &db, &cell, Log::Audit, &stop),
                            );
                        }),
                    );
                }
            }
            Err(e) => tracing::warn!(error = %e, "no cell answered"),
        }
        tokio::select! {
            () = &mut shutdown => break,
            () = tokio::time::sleep(DISCOVER_EVERY) => {}
        }
    }
    stop.cancel();
    for (_, task) in followed {
        let _ = task.await;
    }
    let _ = session.close().await;
    Ok(())
}

/// Copies one log of one cell into the database until `stop`: caught up, it asks again every
/// [`FOLLOW_EVERY`]; after a failure, again after a wait that doubles up to [`RETRY_MAX`].
async fn follow(client: &Client, db: &Db, cell: &str, log: Log, stop: &CancellationToken) {
    let mut after: Option<u64> = None;
    let mut wait = Duration::ZERO;
    let mut failing = false;
    loop {
        let next = match step(client, db, cell, log, &mut after).await {
            Ok(true) => {
                if failing {
                    tracing::info!(%cell, log = log.name(), "copying again");
                    failing = false;
                }
                wait = Duration::ZERO;
                FOLLOW_EVERY
            }
            Ok(false) => {
                wait = Duration::ZERO;
                Duration::ZERO
            }
            Err(e) => {
                // What the database holds is read again: it may have lost or gained rows.
                after = None;
                wait = (wait * 2).clamp(Duration::from_millis(500), RETRY_MAX);
                crate::telemetry::metrics::event(
                    "cellgate.historian.failures",
                    &[("cell", cell), ("log", log.name())],
                    1,
                );
                if !failing {
                    tracing::warn!(%cell, log = log.name(), error = %e, retry_in_s = wait.as_secs_f32(), "copying stopped; trying again");
                    failing = true;
                }
                wait
            }
        };
        tokio::select! {
            () = stop.cancelled() => return,
            () = tokio::time::sleep(next) => {}
        }
    }
}

/// One page: the records after the highest the database holds, inserted with the gaps
/// before them; whether the log is caught up.
async fn step(
    client: &Client,
    db: &Db,
    cell: &str,
    log: Log,
    after: &mut Option<u64>,
) -> Result<bool, HistorianError> {
    let from = match *after {
        Some(a) => a,
        None => db.newest(cell, log).await?,
    };
    let page = match client.history(log.is_audit(), &params(log, from)).await {
        // Trimmed past what the database holds: read from the oldest kept; the gap is said.
        Err(ClientError::Refused {
            code: pb::ErrorCode::NotFound,
            ..
        }) if from > 0 => client.history(log.is_audit(), &params(log, 0)).await?,
        r => r?,
    };
    let mut expected = from + 1;
    let mut gaps = Vec::new();
    let mut records = Vec::with_capacity(page.records.len());
    for r in page.records {
        if r.seq < expected {
            continue;
        }
        if r.seq > expected {
            tracing::warn!(%cell, log = log.name(), first = expected, last = r.seq - 1, "records trimmed by the gateway before they were copied: a gap");
            gaps.push((expected, r.seq - 1));
        }
        expected = r.seq + 1;
        records.push(r);
    }
    db.insert(cell, log, &records, &gaps).await?;
    crate::telemetry::metrics::event(
        "cellgate.historian.records",
        &[("cell", cell), ("log", log.name())],
        records.len() as u64,
    );
    let held = expected - 1;
    *after = Some(held);
    // Behind: how far, from the gateway's newest record (caught up, nothing).
    let lag = if page.more {
        newest_on_gateway(client, log)
            .await
            .map_or(0, |n| n.saturating_sub(held))
    } else {
        0
    };
    crate::telemetry::metrics::historian_lag(cell, log.name(), lag);
    Ok(!page.more)
}

/// The `seq` of the newest record of `log` the gateway holds.
async fn newest_on_gateway(client: &Client, log: Log) -> Option<u64> {
    let mut p = params(log, 0);
    p.retain(|(k, _)| k != "limit");
    p.push(("limit".to_string(), "1".to_string()));
    p.push(("order".to_string(), "newest".to_string()));
    client
        .history(log.is_audit(), &p)
        .await
        .ok()
        .and_then(|p| p.records.first().map(|r| r.seq))
}

/// The selector of a page of `log` after `from`: all of its time, every kind (tag values
/// too, which a history query leaves out unless asked), oldest first.
fn params(log: Log, from: u64) -> Vec<(String, String)> {
    let mut p = vec![
        ("_time".to_string(), "[..]".to_string()),
        ("limit".to_string(), PAGE.to_string()),
    ];
    if log == Log::History {
        p.push(("kind".to_string(), every_kind()));
    }
    if from > 0 {
        p.push(("after".to_string(), from.to_string()));
    }
    p
}

/// Every kind of the history log, by its short name (`job,alarm,...`).
fn every_kind() -> String {
    (1..)
        .map_while(|n| pb::HistoryKind::try_from(n).ok())
        .filter(|k| *k != pb::HistoryKind::Audit)
        .map(store::kind_name)
        .collect::<Vec<_>>()
        .join(",")
}

/// `--status`: each cell's newest record in the database and on its gateway, the lag, the
/// gaps.
async fn status(
    db: &Db,
    session: &zenoh::Session,
    prefix: &str,
    only: Option<&str>,
    timeout: Duration,
    json: bool,
) -> Result<(), HistorianError> {
    let mut cells: BTreeMap<String, Option<Client>> =
        db.cells().await?.into_iter().map(|c| (c, None)).collect();
    for (cell, admin) in Client::discover(session, prefix, timeout)
        .await
        .unwrap_or_default()
    {
        let client = Client::attach(session.clone(), prefix, &cell, admin, timeout).ok();
        cells.insert(cell, client);
    }
    if !json {
        println!(
            "{:<16} {:<8} {:>12} {:>12} {:>8} {:>6}",
            "CELL", "LOG", "DATABASE", "GATEWAY", "LAG", "GAPS"
        );
    }
    let mut all = Vec::new();
    for (cell, client) in cells {
        if only.is_some_and(|o| o != cell) {
            continue;
        }
        for log in [Log::History, Log::Audit] {
            let held = db.newest(&cell, log).await?;
            let newest = match &client {
                Some(c) => newest_on_gateway(c, log).await,
                None => None,
            };
            let gaps = db.gaps(&cell, log).await?;
            if json {
                all.push(serde_json::json!({
                    "cell": cell, "log": log.name(), "database": held, "gateway": newest,
                    "lag": newest.map(|n| n.saturating_sub(held)), "gaps": gaps,
                }));
                continue;
            }
            println!(
                "{:<16} {:<8} {:>12} {:>12} {:>8} {:>6}",
                cell,
                log.name(),
                held,
                newest.map_or("-".to_string(), |n| n.to_string()),
                newest.map_or("-".to_string(), |n| n.saturating_sub(held).to_string()),
                gaps
            );
        }
    }
    if json {
        println!("{}", serde_json::Value::Array(all));
    }
    Ok(())
}
