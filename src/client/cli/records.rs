//! The client side of revisions and the cell's records: `cellgate program history|diff|
//! release|lock|adopt`, `cellgate history`, `cellgate audit` and `cellgate utilisation`.

use std::fmt::Write as _;

use clap::Args;

use super::{ClientCommand, ConnectArgs, Io};
use crate::client::render::{bytes, date_time, origin_text, table};
use crate::client::{Client, ClientError};
use cellgate_core::pb;

/// JSON of any contract message (the proto3 JSON mapping), one object.
fn json<M: serde::Serialize>(m: &M) -> String {
    serde_json::to_string_pretty(m).unwrap_or_default()
}

fn state_name(s: pb::RevisionState) -> &'static str {
    match s {
        pb::RevisionState::Unspecified => "?",
        pb::RevisionState::Draft => "draft",
        pb::RevisionState::Released => "released",
        pb::RevisionState::Locked => "locked",
    }
}

fn who(o: Option<&pb::RequestOrigin>) -> String {
    o.map_or_else(|| "-".to_string(), origin_text)
}

/// The revisions of a program as a table, newest first.
pub fn revisions_text(r: &pb::ProgramRevisions) -> String {
    let rows: Vec<Vec<String>> = r
        .revisions
        .iter()
        .map(|x| {
            let mut state = state_name(x.state()).to_string();
            if x.removed {
                state.push_str(", removed after");
            }
            vec![
                x.number.to_string(),
                state,
                date_time(x.unix_ms),
                who(x.by.as_ref()),
                bytes(x.size),
                x.sha256.chars().take(12).collect(),
                x.comment.clone(),
            ]
        })
        .collect();
    let mut out = table(
        &["REV", "STATE", "STORED", "BY", "SIZE", "SHA-256", "COMMENT"],
        &rows,
    );
    if r.removed {
        let _ = writeln!(
            out,
            "{}: removed from the library (its revisions are kept)",
            r.name
        );
    }
    out
}

/// A diff as people read one: a header, then each hunk with `-`/`+`/` ` lines.
pub fn diff_text(d: &pb::ProgramDiff) -> String {
    let mut out = String::new();
    let rev = |r: Option<&pb::ProgramRevision>| {
        r.map_or_else(String::new, |r| {
            format!(
                "revision {} ({}, {})",
                r.number,
                state_name(r.state()),
                date_time(r.unix_ms)
            )
        })
    };
    let _ = writeln!(out, "--- {} {}", d.name, rev(d.a.as_ref()));
    let _ = writeln!(out, "+++ {} {}", d.name, rev(d.b.as_ref()));
    if !d.ignored.is_empty() {
        let _ = writeln!(out, "(ignoring {})", d.ignored.join(", "));
    }
    if d.same {
        let _ = writeln!(out, "the same, block for block");
        return out;
    }
    for h in &d.hunks {
        let _ = writeln!(out, "@@ a line {} / b line {} @@", h.a_line, h.b_line);
        for l in &h.lines {
            let sign = match l.op() {
                pb::diff_line::Op::Removed => '-',
                pb::diff_line::Op::Added => '+',
                _ => ' ',
            };
            let _ = writeln!(out, "{sign}{}", l.text);
        }
    }
    let _ = writeln!(
        out,
        "{} block(s) changed, {} added, {} removed",
        d.blocks_changed, d.blocks_added, d.blocks_removed
    );
    out
}

/// One history or audit record as a line.
pub fn record_text(r: &pb::HistoryRecord) -> String {
    use pb::history_record::Record;
    let when = date_time(r.unix_ms);
    let machine = if r.machine.is_empty() {
        "-".to_string()
    } else {
        r.machine.clone()
    };
    let what = match &r.record {
        Some(Record::Job(j)) => {
            let o = j.origin.clone().unwrap_or_default();
            let program = o.program.unwrap_or_default();
            let source = if program.library.is_empty() {
                format!(
                    "{} (sha256 {})",
                    o.name,
                    program.sha256.chars().take(12).collect::<String>()
                )
            } else {
                format!("{} revision {}", program.library, program.revision)
            };
            let outcome = match j.outcome() {
                pb::JobOutcome::Completed => "completed".to_string(),
                pb::JobOutcome::Failed => format!("failed: {}", j.reason),
                pb::JobOutcome::Cancelled => j.reason.clone(),
                pb::JobOutcome::Unspecified => "ended".to_string(),
            };
            format!(
                "job {} {source}, {} of {} sent, by {}: {outcome}",
                j.job_id,
                bytes(j.bytes_sent),
                bytes(j.bytes_total),
                who(o.submitted_by.as_ref())
            )
        }
        Some(Record::Alarm(a)) => {
            let n = if a.alarm_number.is_empty() {
                String::new()
            } else {
                format!("{} ", a.alarm_number)
            };
            format!(
                "alarm {}{n}{}",
                a.kind()
                    .as_str_name()
                    .trim_start_matches("ALARM_KIND_")
                    .to_lowercase()
                    + " ",
                a.message
            )
        }
        Some(Record::Link(l)) => format!(
            "link {}",
            pb::LinkState::try_from(*l)
                .unwrap_or_default()
                .as_str_name()
                .trim_start_matches("LINK_STATE_")
                .to_lowercase()
        ),
        Some(Record::Cnc(a)) => format!(
            "cnc {}",
            pb::MachineActivity::try_from(*a)
                .unwrap_or_default()
                .as_str_name()
                .trim_start_matches("MACHINE_ACTIVITY_")
                .to_lowercase()
                .replace('_', " ")
        ),
        Some(Record::Station(s)) => {
            format!("station {} {}", s.station, if s.up { "up" } else { "down" })
        }
        Some(Record::G05(g)) => format!(
            "G05 stream {} ended ({}): {} blocks, {} underruns (estimated)",
            g.stream_id,
            g.end_reason()
                .as_str_name()
                .trim_start_matches("G05_END_REASON_")
                .to_lowercase(),
            g.received,
            g.underruns
        ),
        Some(Record::Tag(t)) => format!(
            "tag {}/{} = {}",
            t.plc,
            t.name,
            t.value.map_or_else(|| "-".to_string(), |v| v.to_string())
        ),
        Some(Record::Gateway(g)) => format!(
            "gateway {} ({})",
            g.event()
                .as_str_name()
                .trim_start_matches("EVENT_")
                .to_lowercase(),
            g.version
        ),
        Some(Record::Punch(p)) => {
            let stored = if p.library_name.is_empty() {
                "not stored".to_string()
            } else {
                format!("stored as {}", p.library_name)
            };
            let against = match (&p.comparison, &p.request, p.damaged) {
                (_, _, true) => format!("damaged: {}", p.damage),
                (_, Some(r), _) => format!("remote request for {}", r.program),
                (Some(c), _, _) if c.same => {
                    format!("same as {} revision {}", c.library_name, c.revision)
                }
                (Some(c), _, _) => format!(
                    "{} changed, {} added, {} removed against {} revision {}",
                    c.blocks_changed, c.blocks_added, c.blocks_removed, c.library_name, c.revision
                ),
                (None, None, false) => "not compared".to_string(),
            };
            format!("punched {}, {stored}: {against}", p.name)
        }
        Some(Record::Audit(a)) => {
            let outcome = if a.ok {
                "ok".to_string()
            } else {
                format!("refused: {}", a.error)
            };
            let mut who = who(a.origin.as_ref());
            if !a.principal.is_empty() {
                let _ = write!(who, " [{}]", a.principal);
            } else if !a.roles.is_empty() {
                let _ = write!(who, " [role {}]", a.roles.join("|"));
            }
            format!("{} {} {} by {who}: {outcome}", a.action, a.target, a.detail)
        }
        None => "?".to_string(),
    };
    format!("{when}  #{:<8} {machine:<12} {what}", r.seq)
}

/// Selector parameters from the time options: `--since` and `--until` (a duration ago such
/// as `2h`, `3d`, or a time `2026-12-01T06:00:00Z`), or `--time` as zenoh writes ranges.
fn time_param(
    time: &Option<String>,
    since: &Option<String>,
    until: &Option<String>,
) -> Result<Option<(String, String)>, ClientError> {
    if let Some(t) = time {
        return Ok(Some(("_time".to_string(), t.clone())));
    }
    if since.is_none() && until.is_none() {
        return Ok(None);
    }
    let bound = |v: &Option<String>, what: &str| -> Result<String, ClientError> {
        let Some(v) = v else { return Ok(String::new()) };
        let v = v.trim();
        if v == "now" {
            return Ok("now()".to_string());
        }
        let unit_ok = v
            .strip_suffix(['s', 'm', 'h', 'd', 'w'])
            .is_some_and(|n| !n.is_empty() && n.parse::<f64>().is_ok());
        if unit_ok {
            return Ok(format!("now(-{v})"));
        }
        if v.contains('T') || v.contains('-') {
            return Ok(v.to_string());
        }
        Err(ClientError::InvalidArgument {
            what: format!("{what} {v}"),
            reason: "give a duration ago (30m, 2h, 7d) or a UTC time (2026-12-01T06:00:00Z)"
                .to_string(),
        })
    };
    Ok(Some((
        "_time".to_string(),
        format!(
            "[{}..{}]",
            bound(since, "--since")?,
            bound(until, "--until")?
        ),
    )))
}

/// Says on stderr that `-m/--machine` is the older form, when it was used.
fn deprecated_machine_flag(io: &mut Io<'_>, command: &str, machine: &[String]) {
    if !machine.is_empty() {
        let _ = writeln!(
            io.err,
            "note: -m/--machine is the older form and will go; name the machines first, as \
             every command does: `cellgate {command} {}`",
            machine.join(",")
        );
    }
}

/// The page of records `cellgate history` and `cellgate audit` ask for, and how it is printed.
#[derive(Debug, Clone, Args)]
pub struct PageArgs {
    /// From this long ago (30m, 2h, 7d) or this UTC time; default the last 24 hours.
    #[arg(long, value_name = "WHEN")]
    pub since: Option<String>,
    /// Up to this long ago or this UTC time; default now.
    #[arg(long, value_name = "WHEN")]
    pub until: Option<String>,
    /// A time range as zenoh writes it, e.g. `[now(-1h)..]` (instead of --since/--until).
    #[arg(long, value_name = "RANGE", conflicts_with_all = ["since", "until"])]
    pub time: Option<String>,
    /// At most this many records (default 1000, at most 10000); the rest with --after.
    #[arg(long, value_name = "N")]
    pub limit: Option<usize>,
    /// Go on after this record number (the `#` of the last one printed).
    #[arg(long, value_name = "SEQ")]
    pub after: Option<u64>,
    /// The newest record first (--after then goes on to older ones).
    #[arg(long)]
    pub newest: bool,
    /// Print the page as JSON (a HistoryPage).
    #[arg(long)]
    pub json: bool,
}

/// `cellgate history` and `cellgate audit`.
#[derive(Debug, Clone, Args)]
pub struct HistoryArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Only these machines or PLC links (comma-separate, or name several), first as in
    /// every command: `cellgate history mill-1,plc-1`.
    #[arg(value_name = "MACHINE", value_delimiter = ',')]
    pub machines: Vec<String>,
    /// The older form of MACHINE, kept working: name the machines first instead.
    #[arg(short, long, value_name = "NAME", value_delimiter = ',', hide = true)]
    pub machine: Vec<String>,
    /// Only these kinds: job, alarm, link, cnc, station, g05, tag, gateway, punch (history).
    #[arg(short, long, value_name = "KIND", value_delimiter = ',')]
    pub kind: Vec<String>,
    /// Values of these tags, PLC/NAME (tags with history = true).
    #[arg(long, value_name = "PLC/NAME", value_delimiter = ',')]
    pub tag: Vec<String>,
    #[command(flatten)]
    pub page: PageArgs,
}

impl HistoryArgs {
    fn params(&self) -> Result<Vec<(String, String)>, ClientError> {
        let mut p = Vec::new();
        let page = &self.page;
        if let Some(t) = time_param(&page.time, &page.since, &page.until)? {
            p.push(t);
        }
        let machines = [self.machines.as_slice(), self.machine.as_slice()].concat();
        if !machines.is_empty() {
            p.push(("machine".to_string(), machines.join(",")));
        }
        if !self.kind.is_empty() {
            p.push(("kind".to_string(), self.kind.join(",")));
        }
        if !self.tag.is_empty() {
            p.push(("tag".to_string(), self.tag.join(",")));
        }
        if let Some(n) = page.limit {
            p.push(("limit".to_string(), n.to_string()));
        }
        if let Some(a) = page.after {
            p.push(("after".to_string(), a.to_string()));
        }
        if page.newest {
            p.push(("order".to_string(), "newest".to_string()));
        }
        Ok(p)
    }

    async fn print(
        &self,
        client: &Client,
        io: &mut Io<'_>,
        audit: bool,
    ) -> Result<u8, ClientError> {
        deprecated_machine_flag(io, if audit { "audit" } else { "history" }, &self.machine);
        let page = client.history(audit, &self.params()?).await?;
        if self.page.json {
            let _ = writeln!(io.out, "{}", json(&page));
            return Ok(0);
        }
        if page.records.is_empty() {
            let _ = writeln!(
                io.err,
                "no records from {} to {}",
                date_time(page.from_unix_ms),
                date_time(page.to_unix_ms)
            );
        }
        for r in &page.records {
            let _ = writeln!(io.out, "{}", record_text(r));
        }
        if page.more {
            let _ = writeln!(
                io.err,
                "more records: go on with --after {}",
                page.next_after
            );
        }
        Ok(0)
    }
}

/// `cellgate history`.
#[derive(Debug, Clone, Args)]
pub struct HistoryCommand {
    #[command(flatten)]
    pub args: HistoryArgs,
}

impl ClientCommand for HistoryCommand {
    fn connect_args(&self) -> &ConnectArgs {
        &self.args.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        self.args.print(client, io, false).await
    }
}

/// `cellgate audit`: the history's options but kinds and tags (the audit has one kind).
#[derive(Debug, Clone, Args)]
pub struct AuditCommand {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Only writes to these machines or PLC links (comma-separate, or name several), first
    /// as in every command: `cellgate audit mill-1`.
    #[arg(value_name = "MACHINE", value_delimiter = ',')]
    pub machines: Vec<String>,
    /// The older form of MACHINE, kept working: name the machines first instead.
    #[arg(short, long, value_name = "NAME", value_delimiter = ',', hide = true)]
    pub machine: Vec<String>,
    #[command(flatten)]
    pub page: PageArgs,
}

impl ClientCommand for AuditCommand {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        let args = HistoryArgs {
            connect: self.connect.clone(),
            machines: self.machines.clone(),
            machine: self.machine.clone(),
            kind: Vec::new(),
            tag: Vec::new(),
            page: self.page.clone(),
        };
        args.print(client, io, true).await
    }
}

/// `cellgate utilisation`.
#[derive(Debug, Clone, Args)]
pub struct UtilisationArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Only these machines (comma-separate, or name several), first as in every command:
    /// `cellgate utilisation mill-1`.
    #[arg(value_name = "MACHINE", value_delimiter = ',')]
    pub machines: Vec<String>,
    /// The older form of MACHINE, kept working: name the machines first instead.
    #[arg(short, long, value_name = "NAME", value_delimiter = ',', hide = true)]
    pub machine: Vec<String>,
    /// From this long ago (8h, 7d) or this UTC time; default the last 24 hours.
    #[arg(long, value_name = "WHEN")]
    pub since: Option<String>,
    /// Up to this long ago or this UTC time; default now.
    #[arg(long, value_name = "WHEN")]
    pub until: Option<String>,
    /// A time range as zenoh writes it (instead of --since/--until).
    #[arg(long, value_name = "RANGE", conflicts_with_all = ["since", "until"])]
    pub time: Option<String>,
    /// Buckets: hour (UTC) or shift (the cell file's `[history] shifts`).
    #[arg(long, value_name = "BUCKET", default_value = "hour")]
    pub bucket: String,
    /// Print JSON (a Utilisation).
    #[arg(long)]
    pub json: bool,
}

fn share(ms: u64, of: u64) -> String {
    if of == 0 {
        return "-".to_string();
    }
    format!("{:.0}%", ms as f64 * 100.0 / of as f64)
}

/// The time of `b` that has passed: every state's time and the unknown time (the gateway
/// counts only up to now, so for the current bucket this is less than its length).
pub fn elapsed_ms(b: &pb::UtilisationBucket) -> u64 {
    b.reading_ms
        + b.idle_ms
        + b.alarm_ms
        + b.reset_ms
        + b.punching_ms
        + b.link_down_ms
        + b.unknown_ms
}

/// Utilisation as a table: one row per machine and bucket.
pub fn utilisation_text(u: &pb::Utilisation) -> String {
    let mut rows = Vec::new();
    for m in &u.machines {
        for b in &m.buckets {
            // Of the time that has passed: the current bucket has not ended yet.
            let len = elapsed_ms(b);
            let known = len.saturating_sub(b.unknown_ms);
            rows.push(vec![
                m.machine.clone(),
                date_time(b.start_unix_ms),
                share(b.reading_ms, known),
                share(b.idle_ms, known),
                share(b.alarm_ms + b.reset_ms, known),
                share(b.link_down_ms, known),
                share(b.unknown_ms, len),
                format!("{}/{}", b.jobs_completed, b.jobs_failed),
                b.parts.map_or_else(|| "-".to_string(), |p| format!("{p}")),
            ]);
        }
    }
    if rows.is_empty() {
        return "no machine\n".to_string();
    }
    let mut out = table(
        &[
            "MACHINE",
            "FROM",
            "READING",
            "IDLE",
            "ALARM/RESET",
            "LINK DOWN",
            "UNKNOWN",
            "JOBS OK/NOT",
            "PARTS",
        ],
        &rows,
    );
    out.push_str(
        "shares of the time the gateway knew the machine's state (SAT and link, §4.4.2); \
         UNKNOWN: of the time that has passed in the bucket\n",
    );
    out
}

impl ClientCommand for UtilisationArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        deprecated_machine_flag(io, "utilisation", &self.machine);
        let mut p = Vec::new();
        if let Some(t) = time_param(&self.time, &self.since, &self.until)? {
            p.push(t);
        }
        let machines = [self.machines.as_slice(), self.machine.as_slice()].concat();
        if !machines.is_empty() {
            p.push(("machine".to_string(), machines.join(",")));
        }
        p.push(("bucket".to_string(), self.bucket.clone()));
        let u = client.utilisation(&p).await?;
        if self.json {
            let _ = writeln!(io.out, "{}", json(&u));
        } else {
            let _ = write!(io.out, "{}", utilisation_text(&u));
        }
        Ok(0)
    }
}

/// What `cellgate program history|diff|release|lock|adopt` run.
pub(crate) async fn program_history(
    client: &Client,
    io: &mut Io<'_>,
    name: &str,
    as_json: bool,
) -> Result<u8, ClientError> {
    let r = client.program_revisions(name).await?;
    if as_json {
        let _ = writeln!(io.out, "{}", json(&r));
    } else {
        let _ = write!(io.out, "{}", revisions_text(&r));
    }
    Ok(0)
}

pub(crate) async fn program_diff(
    client: &Client,
    io: &mut Io<'_>,
    name: &str,
    a: Option<&str>,
    b: Option<&str>,
    ignore: &[String],
    as_json: bool,
) -> Result<u8, ClientError> {
    let d = client.program_diff(name, a, b, ignore).await?;
    if as_json {
        let _ = writeln!(io.out, "{}", json(&d));
    } else {
        let _ = write!(io.out, "{}", diff_text(&d));
    }
    // As diff(1): 0 the same, 1 different.
    Ok(u8::from(!d.same))
}

pub(crate) async fn program_state(
    client: &Client,
    io: &mut Io<'_>,
    name: &str,
    revision: Option<&str>,
    state: pb::RevisionState,
    comment: Option<&str>,
    as_json: bool,
) -> Result<u8, ClientError> {
    let r = client
        .program_release(
            name,
            revision.unwrap_or_default(),
            state,
            comment.unwrap_or_default().to_string(),
        )
        .await?;
    if as_json {
        let _ = writeln!(io.out, "{}", json(&r));
    }
    let _ = writeln!(
        io.err,
        "{}: revision {} is {}",
        r.name,
        r.number,
        state_name(r.state())
    );
    Ok(0)
}

pub(crate) async fn program_adopt(
    client: &Client,
    io: &mut Io<'_>,
    name: &str,
    from: &str,
    revision: Option<&str>,
    comment: Option<&str>,
    as_json: bool,
) -> Result<u8, ClientError> {
    let info = client
        .program_adopt(
            name,
            from,
            revision.unwrap_or_default(),
            comment.unwrap_or_default().to_string(),
        )
        .await?;
    if as_json {
        let _ = writeln!(io.out, "{}", json(&info));
    }
    let rev = info.latest.as_ref().map_or(0, |r| r.number);
    let _ = writeln!(io.err, "{}: revision {rev} adopted from {from}", info.name);
    Ok(0)
}

#[cfg(test)]
mod tests;
