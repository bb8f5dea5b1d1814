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
    Migration {
        version: 3,
        name: "the utilisation view",
        sql: r#"
-- A machine's time per UTC hour, as the gateway's own utilisation divides it (docs/history.md,
-- "Utilisation"): its activity from each `cnc` record on; unknown before the first, from a
-- clean stop to the next start, and after a crash (a start after more than a minute without
-- an `alive` record) from a minute past the last sign of life.
CREATE VIEW cellgate.utilisation_spans AS
WITH machines AS (
    SELECT DISTINCT cell, machine FROM cellgate.history WHERE kind = 'cnc'
), marks AS (
    SELECT cell, machine, (record->>'unix_ms')::bigint AS t, 3 AS ord, seq,
           record->>'cnc' AS activity
    FROM cellgate.history WHERE kind = 'cnc'
    UNION ALL
    SELECT g.cell, m.machine, (g.record->>'unix_ms')::bigint,
           CASE g.record->'gateway'->>'event'
               WHEN 'EVENT_STOPPED' THEN 0 WHEN 'EVENT_STARTED' THEN 1 ELSE 2 END,
           g.seq, NULL
    FROM cellgate.history g JOIN machines m ON m.cell = g.cell
    WHERE g.kind = 'gateway'
), ordered AS (
    SELECT *,
           row_number() OVER w AS n,
           lag(t) OVER w AS prev_t
    FROM marks
    WINDOW w AS (PARTITION BY cell, machine ORDER BY t, ord, seq)
)
SELECT a.cell, a.machine, a.activity, a.t AS start_ms,
       CASE
           WHEN b.n IS NULL THEN greatest((extract(epoch FROM now()) * 1000)::bigint, a.t)
           WHEN b.ord = 1 THEN least(greatest(coalesce(b.prev_t, 0) + 60000, a.t), b.t)
           ELSE b.t
       END AS end_ms
FROM ordered a
LEFT JOIN LATERAL (
    SELECT o.n, o.ord, o.t, o.prev_t FROM ordered o
    WHERE o.cell = a.cell AND o.machine = a.machine AND o.n > a.n AND o.ord <> 2
    ORDER BY o.n LIMIT 1
) b ON true
WHERE a.ord = 3;

CREATE VIEW cellgate.utilisation AS
WITH pieces AS (
    SELECT s.cell, s.machine, s.activity, h.hour,
           least(s.end_ms, (extract(epoch FROM h.hour + interval '1 hour') * 1000)::bigint)
             - greatest(s.start_ms, (extract(epoch FROM h.hour) * 1000)::bigint) AS ms
    FROM cellgate.utilisation_spans s
    CROSS JOIN LATERAL generate_series(
        date_trunc('hour', to_timestamp(s.start_ms / 1000.0)),
        to_timestamp(greatest(s.end_ms - 1, s.start_ms) / 1000.0),
        interval '1 hour'
    ) AS h(hour)
    WHERE s.end_ms > s.start_ms
), hours AS (
    SELECT cell, machine, hour,
        sum(ms) FILTER (WHERE activity = 'MACHINE_ACTIVITY_READING') AS reading,
        sum(ms) FILTER (WHERE activity = 'MACHINE_ACTIVITY_IDLE') AS idle,
        sum(ms) FILTER (WHERE activity = 'MACHINE_ACTIVITY_ALARM') AS alarm,
        sum(ms) FILTER (WHERE activity = 'MACHINE_ACTIVITY_RESET') AS reset,
        sum(ms) FILTER (WHERE activity = 'MACHINE_ACTIVITY_PUNCHING') AS punching,
        sum(ms) FILTER (WHERE activity NOT IN ('MACHINE_ACTIVITY_READING',
            'MACHINE_ACTIVITY_IDLE', 'MACHINE_ACTIVITY_ALARM', 'MACHINE_ACTIVITY_RESET',
            'MACHINE_ACTIVITY_PUNCHING')) AS link_down,
        sum(ms) AS known
    FROM pieces WHERE ms > 0
    GROUP BY cell, machine, hour
)
SELECT h.cell, h.machine, h.hour,
       coalesce(h.reading, 0)::bigint AS reading_ms,
       coalesce(h.idle, 0)::bigint AS idle_ms,
       coalesce(h.alarm, 0)::bigint AS alarm_ms,
       coalesce(h.reset, 0)::bigint AS reset_ms,
       coalesce(h.punching, 0)::bigint AS punching_ms,
       coalesce(h.link_down, 0)::bigint AS link_down_ms,
       greatest(
           least((extract(epoch FROM h.hour + interval '1 hour') * 1000)::bigint,
                 (extract(epoch FROM now()) * 1000)::bigint)
           - (extract(epoch FROM h.hour) * 1000)::bigint - h.known,
           0)::bigint AS unknown_ms,
       (SELECT count(*) FROM cellgate.jobs j WHERE j.cell = h.cell AND j.machine = h.machine
            AND j.ended >= h.hour AND j.ended < h.hour + interval '1 hour'
            AND j.outcome = 'completed') AS jobs_completed,
       (SELECT count(*) FROM cellgate.jobs j WHERE j.cell = h.cell AND j.machine = h.machine
            AND j.ended >= h.hour AND j.ended < h.hour + interval '1 hour'
            AND j.outcome <> 'completed') AS jobs_failed
FROM hours h;
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
