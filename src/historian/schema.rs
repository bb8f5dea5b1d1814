//! The historian's tables, created and migrated by the historian itself: versioned steps,
//! each recorded in `cellgate.migrations` once applied, taken under an advisory lock so that
//! two historians starting at once apply each step once.

use tokio_postgres::Client;

/// A step of the schema: its version, what it does, its SQL.
pub struct Migration {
    pub version: i32,
    pub name: &'static str,
    pub sql: &'static str,
}

/// Every step, in order. A step once released is never edited: a change is a new step.
pub const MIGRATIONS: &[Migration] = &[
    Migration {
        version: 1,
        name: "history, audit and gaps",
        sql: r#"
CREATE TABLE cellgate.history (
    cell    text        NOT NULL,
    seq     bigint      NOT NULL,
    at      timestamptz NOT NULL,
    machine text        NOT NULL,
    kind    text        NOT NULL,
    record  jsonb       NOT NULL
);
CREATE UNIQUE INDEX history_cell_seq ON cellgate.history (cell, seq);
CREATE INDEX history_cell_at ON cellgate.history (cell, at);
CREATE INDEX history_cell_machine_at ON cellgate.history (cell, machine, at);

CREATE TABLE cellgate.audit (
    cell    text        NOT NULL,
    seq     bigint      NOT NULL,
    at      timestamptz NOT NULL,
    machine text        NOT NULL,
    action  text        NOT NULL,
    record  jsonb       NOT NULL
);
CREATE UNIQUE INDEX audit_cell_seq ON cellgate.audit (cell, seq);
CREATE INDEX audit_cell_at ON cellgate.audit (cell, at);
CREATE INDEX audit_cell_machine_at ON cellgate.audit (cell, machine, at);

-- Records a gateway trimmed before the historian saw them: said, never papered over.
CREATE TABLE cellgate.gaps (
    cell      text        NOT NULL,
    log       text        NOT NULL CHECK (log IN ('history', 'audit')),
    first_seq bigint      NOT NULL,
    last_seq  bigint      NOT NULL,
    noticed   timestamptz NOT NULL DEFAULT now(),
    UNIQUE (cell, log, first_seq)
);
"#,
    },
    Migration {
        version: 2,
        name: "the jobs view",
        sql: r#"
-- One row per ended job: the gateway writes a job's record when it ends (HistoryKind job).
CREATE VIEW cellgate.jobs AS
SELECT
    h.cell,
    h.machine,
    h.record->'job'->>'job_id' AS job_id,
    COALESCE(
        NULLIF(h.record->'job'->'origin'->'program'->>'library', ''),
        h.record->'job'->'origin'->>'name'
    ) AS program,
    NULLIF((h.record->'job'->'origin'->'program'->>'revision')::int, 0) AS revision,
    lower(replace(h.record->'job'->>'outcome', 'JOB_OUTCOME_', '')) AS outcome,
    (h.record->'job'->>'bytes_sent')::bigint AS bytes,
    to_timestamp(
        NULLIF((h.record->'job'->'origin'->>'started_unix_ms')::bigint, 0) / 1000.0
    ) AS started,
    to_timestamp((h.record->'job'->>'ended_unix_ms')::bigint / 1000.0) AS ended
FROM cellgate.history h
WHERE h.kind = 'job';
"#,
    },
];

/// Creates the schema and applies the steps not applied yet; the versions applied now.
pub async fn migrate(db: &mut Client) -> Result<Vec<i32>, tokio_postgres::Error> {
    let tx = db.transaction().await?;
    // One historian at a time past this point; released with the transaction.
    tx.execute("SELECT pg_advisory_xact_lock(7354001)", &[])
        .await?;
    tx.batch_execute(
        "CREATE SCHEMA IF NOT EXISTS cellgate;
         CREATE TABLE IF NOT EXISTS cellgate.migrations (
             version    int         PRIMARY KEY,
             name       text        NOT NULL,
             applied_at timestamptz NOT NULL DEFAULT now()
         );",
    )
    .await?;
    let done: Vec<i32> = tx
        .query("SELECT version FROM cellgate.migrations", &[])
        .await?
        .iter()
        .map(|r| r.get(0))
        .collect();
    let mut applied = Vec::new();
    for m in MIGRATIONS.iter().filter(|m| !done.contains(&m.version)) {
        tx.batch_execute(m.sql).await?;
        tx.execute(
            "INSERT INTO cellgate.migrations (version, name) VALUES ($1, $2)",
            &[&m.version, &m.name],
        )
        .await?;
        applied.push(m.version);
    }
    tx.commit().await?;
    Ok(applied)
}

/// Whether the TimescaleDB extension is installed in the database.
pub async fn has_timescaledb(db: &Client) -> Result<bool, tokio_postgres::Error> {
    Ok(!db
        .query(
            "SELECT 1 FROM pg_extension WHERE extname = 'timescaledb'",
            &[],
        )
        .await?
        .is_empty())
}
