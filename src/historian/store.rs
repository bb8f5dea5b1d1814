//! The historian's database: one connection, made again whenever it was lost (the schema
//! migrated each time, so a database recreated meanwhile is whole again), and the inserts,
//! idempotent on `(cell, seq)`.

use std::path::Path;
use std::sync::Arc;

use postgres_rustls::MakeTlsConnector;
use tokio::sync::Mutex;
use tokio_postgres::config::SslMode;
use tokio_postgres::{Client, Config, NoTls};
use tokio_rustls::rustls;
use tokio_rustls::rustls::pki_types::CertificateDer;
use tokio_rustls::rustls::pki_types::pem::PemObject;

use super::{HistorianError, schema};
use cellgate_core::pb;

/// Which of a cell's two logs (numbered apart).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Log {
    History,
    Audit,
}

impl Log {
    pub fn name(self) -> &'static str {
        match self {
            Log::History => "history",
            Log::Audit => "audit",
        }
    }

    pub fn is_audit(self) -> bool {
        self == Log::Audit
    }
}

/// The database's settings from the URL, with the password from the URL,
/// `--database-password-file`
/// or `PGPASSWORD`.
pub fn config(url: &str, password_file: Option<&Path>) -> Result<Config, HistorianError> {
    let mut config: Config = url
        .parse()
        .map_err(|e| HistorianError::Config(format!("--database {}: {e}", shown(url))))?;
    if config.get_password().is_none() {
        if let Some(file) = password_file {
            let bytes =
                cellgate_core::config::file::read_bounded(file, 1024 * 1024).map_err(|e| {
                    HistorianError::Config(format!(
                        "--database-password-file {}: {e}",
                        file.display()
                    ))
                })?;
            let text = String::from_utf8_lossy(&bytes);
            config.password(text.lines().next().unwrap_or_default().trim_end());
        } else if let Ok(p) = std::env::var("PGPASSWORD") {
            config.password(p);
        }
    }
    if config.get_connect_timeout().is_none() {
        config.connect_timeout(std::time::Duration::from_secs(10));
    }
    config.application_name("cellgate historian");
    Ok(config)
}

/// TLS to the database as the URL's `sslmode` asks: none for `disable`; with `ca` (the
/// PEM file of the CAs that signed the database server's certificate) the server's
/// certificate and name are checked against it (`prefer`, the default, and `require`);
/// `require` without `ca` is refused, since a certificate nothing vouches for proves nothing.
pub fn tls(config: &Config, ca: Option<&Path>) -> Result<Option<MakeTlsConnector>, HistorianError> {
    let mode = config.get_ssl_mode();
    let Some(ca) = ca.filter(|_| mode != SslMode::Disable) else {
        if mode == SslMode::Require {
            return Err(HistorianError::Config(
                "--database …sslmode=require: give --database-ca FILE, the CA that signed the \
                 database server's certificate"
                    .to_string(),
            ));
        }
        return Ok(None);
    };
    let bad =
        |why: String| HistorianError::Config(format!("--database-ca {}: {why}", ca.display()));
    let pem = cellgate_core::config::file::read_bounded(ca, 1024 * 1024)
        .map_err(|e| bad(e.to_string()))?;
    let mut roots = rustls::RootCertStore::empty();
    for cert in CertificateDer::pem_slice_iter(&pem) {
        let cert = cert.map_err(|e| bad(format!("not PEM certificates: {e}")))?;
        roots
            .add(cert)
            .map_err(|e| bad(format!("a certificate that cannot be a root: {e}")))?;
    }
    if roots.is_empty() {
        return Err(bad("no certificate in it".to_string()));
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut client = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| bad(e.to_string()))?
        .with_root_certificates(roots)
        .with_no_client_auth();
    postgres_rustls::set_postgresql_alpn(&mut client);
    Ok(Some(MakeTlsConnector::new(
        tokio_rustls::TlsConnector::from(Arc::new(client)),
    )))
}

/// The URL without its password, for logs.
pub fn shown(url: &str) -> String {
    match (url.find("://"), url.rfind('@')) {
        (Some(s), Some(at)) if at > s => {
            let user = &url[s + 3..at];
            let user = user.split(':').next().unwrap_or_default();
            format!("{}{user}{}", &url[..s + 3], &url[at..])
        }
        _ => url.to_string(),
    }
}

/// The database, shared by every cell's followers.
#[derive(Clone)]
pub struct Db {
    config: Arc<Config>,
    tls: Option<MakeTlsConnector>,
    client: Arc<Mutex<Option<Arc<Client>>>>,
}

const INSERT_HISTORY: &str = "
INSERT INTO cellgate.history (cell, seq, at, machine, kind, record)
SELECT $1::text, s, to_timestamp(ms / 1000.0), m, k, r::jsonb
FROM UNNEST($2::bigint[], $3::bigint[], $4::text[], $5::text[], $6::text[]) AS t(s, ms, m, k, r)
ON CONFLICT (cell, seq) DO NOTHING";

const INSERT_AUDIT: &str = "
INSERT INTO cellgate.audit (cell, seq, at, machine, action, record)
SELECT $1::text, s, to_timestamp(ms / 1000.0), m, k, r::jsonb
FROM UNNEST($2::bigint[], $3::bigint[], $4::text[], $5::text[], $6::text[]) AS t(s, ms, m, k, r)
ON CONFLICT (cell, seq) DO NOTHING";

impl Db {
    /// The database of `config`, reached over `tls` where given (see [`tls`]).
    pub fn new(config: Config, tls: Option<MakeTlsConnector>) -> Db {
        Db {
            config: Arc::new(config),
            tls,
            client: Arc::new(Mutex::new(None)),
        }
    }

    /// The connection, made (and the schema migrated) if there is none or it was lost.
    pub async fn client(&self) -> Result<Arc<Client>, tokio_postgres::Error> {
        let mut held = self.client.lock().await;
        if let Some(c) = held.as_ref()
            && !c.is_closed()
        {
            return Ok(Arc::clone(c));
        }
        *held = None;
        let ended = |e: tokio_postgres::Error| {
            tracing::warn!(error = %super::db_text(&e), "the database connection ended");
        };
        let mut client = match &self.tls {
            Some(tls) => {
                let (client, connection) = self.config.connect(tls.clone()).await?;
                tokio::spawn(async move { connection.await.map_err(ended) });
                client
            }
            None => {
                let (client, connection) = self.config.connect(NoTls).await?;
                tokio::spawn(async move { connection.await.map_err(ended) });
                client
            }
        };
        let applied = schema::migrate(&mut client).await?;
        if !applied.is_empty() {
            tracing::info!(?applied, "database schema migrated");
        }
        let client = Arc::new(client);
        *held = Some(Arc::clone(&client));
        Ok(client)
    }

    /// The highest `seq` of `cell`'s `log` the database holds (0: none).
    pub async fn newest(&self, cell: &str, log: Log) -> Result<u64, tokio_postgres::Error> {
        let sql = match log {
            Log::History => "SELECT COALESCE(max(seq), 0) FROM cellgate.history WHERE cell = $1",
            Log::Audit => "SELECT COALESCE(max(seq), 0) FROM cellgate.audit WHERE cell = $1",
        };
        let row = self.client().await?.query_one(sql, &[&cell]).await?;
        Ok(u64::try_from(row.get::<_, i64>(0)).unwrap_or(0))
    }

    /// The cells the database holds records of.
    pub async fn cells(&self) -> Result<Vec<String>, tokio_postgres::Error> {
        let rows = self
            .client()
            .await?
            .query(
                "SELECT DISTINCT cell FROM cellgate.history
                 UNION SELECT DISTINCT cell FROM cellgate.audit ORDER BY 1",
                &[],
            )
            .await?;
        Ok(rows.iter().map(|r| r.get(0)).collect())
    }

    /// The gaps said of `cell`'s `log`.
    pub async fn gaps(&self, cell: &str, log: Log) -> Result<i64, tokio_postgres::Error> {
        let row = self
            .client()
            .await?
            .query_one(
                "SELECT count(*) FROM cellgate.gaps WHERE cell = $1 AND log = $2",
                &[&cell, &log.name()],
            )
            .await?;
        Ok(row.get(0))
    }

    /// Inserts `records` of `cell`'s `log` (each once: one already there is left as it is),
    /// and the `gaps` (first and last `seq` missing) before them.
    pub async fn insert(
        &self,
        cell: &str,
        log: Log,
        records: &[pb::HistoryRecord],
        gaps: &[(u64, u64)],
    ) -> Result<(), tokio_postgres::Error> {
        let client = self.client().await?;
        for (first, last) in gaps {
            client
                .execute(
                    "INSERT INTO cellgate.gaps (cell, log, first_seq, last_seq)
                     VALUES ($1, $2, $3, $4) ON CONFLICT DO NOTHING",
                    &[&cell, &log.name(), &as_i64(*first), &as_i64(*last)],
                )
                .await?;
        }
        if records.is_empty() {
            return Ok(());
        }
        let mut seqs = Vec::with_capacity(records.len());
        let mut times = Vec::with_capacity(records.len());
        let mut machines = Vec::with_capacity(records.len());
        let mut kinds = Vec::with_capacity(records.len());
        let mut json = Vec::with_capacity(records.len());
        for r in records {
            seqs.push(as_i64(r.seq));
            times.push(as_i64(r.unix_ms));
            machines.push(r.machine.clone());
            kinds.push(match (log, &r.record) {
                (Log::Audit, Some(pb::history_record::Record::Audit(a))) => a.action.clone(),
                _ => kind_name(r.kind()),
            });
            // The proto3 JSON mapping (field names as in the .proto files).
            json.push(serde_json::to_string(r).unwrap_or_else(|_| "{}".to_string()));
        }
        let sql = match log {
            Log::History => INSERT_HISTORY,
            Log::Audit => INSERT_AUDIT,
        };
        client
            .execute(sql, &[&cell, &seqs, &times, &machines, &kinds, &json])
            .await?;
        Ok(())
    }
}

/// A history kind's short name: `job` for `HISTORY_KIND_JOB`.
pub fn kind_name(kind: pb::HistoryKind) -> String {
    kind.as_str_name()
        .trim_start_matches("HISTORY_KIND_")
        .to_ascii_lowercase()
}

fn as_i64(v: u64) -> i64 {
    i64::try_from(v).unwrap_or(i64::MAX)
}
