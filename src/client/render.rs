//! Text for people and JSON for programs, from the contract's messages.
//!
//! JSON keeps the field names and enum value names of `proto/cellgate/v1/*.proto` (e.g.
//! `"link_state": "LINK_STATE_IDLE"`); optional fields that are absent are `null`. 64-bit
//! integers are plain JSON numbers.

use std::collections::HashMap;
use std::fmt::Write as _;

use serde_json::{Value, json};

use super::WatchEvent;
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;

// ---- small pieces ----------------------------------------------------------------------------

/// `HH:MM:SS.mmmZ` (UTC) of a Unix time in milliseconds.
pub fn clock(unix_ms: u64) -> String {
    let secs = unix_ms / 1000;
    let day = secs % 86_400;
    format!(
        "{:02}:{:02}:{:02}.{:03}Z",
        day / 3600,
        day / 60 % 60,
        day % 60,
        unix_ms % 1000
    )
}

/// `YYYY-MM-DD HH:MM:SSZ` (UTC) of a Unix time in milliseconds.
pub fn date_time(unix_ms: u64) -> String {
    let secs = unix_ms / 1000;
    let (y, m, d) = cellgate_core::program::punch::civil_from_days(secs / 86_400);
    let day = secs % 86_400;
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02}:{:02}Z",
        day / 3600,
        day / 60 % 60,
        day % 60
    )
}

/// A byte count for people: `512 B`, `40.0 KiB`, `1.5 MiB`.
pub fn bytes(n: u64) -> String {
    const KIB: f64 = 1024.0;
    let f = n as f64;
    if n < 1024 {
        format!("{n} B")
    } else if f < KIB * KIB {
        format!("{:.1} KiB", f / KIB)
    } else if f < KIB * KIB * KIB {
        format!("{:.1} MiB", f / (KIB * KIB))
    } else {
        format!("{:.1} GiB", f / (KIB * KIB * KIB))
    }
}

/// An 8-bit image as `0x5A 0b01011010`.
pub fn byte_image(value: u32) -> String {
    format!("0x{value:02X} 0b{value:08b}")
}

/// `ENUM_PREFIX_SOME_NAME` → `some name`.
fn short(name: &str, prefix: &str) -> String {
    name.strip_prefix(prefix)
        .unwrap_or(name)
        .to_ascii_lowercase()
        .replace('_', " ")
}

pub fn protocol_text(p: pb::Protocol) -> &'static str {
    match p {
        pb::Protocol::Unspecified => "?",
        pb::Protocol::A => "A",
        pb::Protocol::ExpansionA => "Expansion A",
        pb::Protocol::B => "B",
        pb::Protocol::ExpansionB => "Expansion B",
    }
}

pub fn link_text(s: pb::LinkState) -> String {
    short(s.as_str_name(), "LINK_STATE_")
}

/// The LINK column: the link's state, but `waiting for CNC` while a job waits for the CNC to
/// ask for it (the link itself is idle then, which reads as if nothing were pending).
pub fn link_cell(s: &pb::MachineStatus) -> String {
    let state = s.link_state();
    if state == pb::LinkState::Idle && !s.current_job_id.is_empty() && !s.waiting_for.is_empty() {
        "waiting for CNC".to_string()
    } else {
        link_text(state)
    }
}

/// A duration for people: `45 s`, `12 min`, `3 h`, `2 d`.
pub fn age(ms: u64) -> String {
    let secs = ms / 1000;
    if secs < 120 {
        format!("{secs} s")
    } else if secs < 2 * 3600 {
        format!("{} min", secs / 60)
    } else if secs < 2 * 86_400 {
        format!("{} h", secs / 3600)
    } else {
        format!("{} d", secs / 86_400)
    }
}

/// What a machine waits for, as a sentence; `None` when it waits for nothing.
pub fn waiting_text(s: &pb::MachineStatus) -> Option<String> {
    if s.waiting_for.is_empty() {
        return None;
    }
    let since = if s.waiting_since_unix_ms > 0 && s.unix_ms >= s.waiting_since_unix_ms {
        format!(" for {}", age(s.unix_ms - s.waiting_since_unix_ms))
    } else {
        String::new()
    };
    Some(if link_cell(s) == "waiting for CNC" {
        format!(
            "{}: job {} waits{since} for the CNC to read it ({})",
            s.machine, s.current_job_id, s.waiting_for
        )
    } else {
        format!("{}: waiting{since} for {}", s.machine, s.waiting_for)
    })
}

/// Whether the gateway holds `s` in alarm: its link in alarm, or its last SAT in alarm
/// status (§4.4.2).
pub fn in_alarm(s: &pb::MachineStatus) -> bool {
    s.link_state() == pb::LinkState::Alarm
        || s.sat
            .as_ref()
            .is_some_and(|sat| sat.buffer_status() == pb::BufferStatus::Alarm)
}

/// The SAT's buffer status, with the alarm cause when in alarm (§4.4.2).
pub fn sat_text(sat: Option<&pb::Sat>) -> String {
    let Some(sat) = sat else {
        return "-".to_string();
    };
    let status = short(sat.buffer_status().as_str_name(), "BUFFER_STATUS_");
    if sat.buffer_status() == pb::BufferStatus::Alarm {
        let cause = short(sat.alarm_cause().as_str_name(), "ALARM_CAUSE_");
        format!("alarm: {cause}")
    } else {
        status
    }
}

fn opt_image(v: Option<u32>) -> String {
    v.map_or_else(|| "-".to_string(), |v| format!("0x{v:02X}"))
}

fn dash(s: &str) -> &str {
    if s.is_empty() { "-" } else { s }
}

/// Rows as a table with columns padded to their widest cell.
pub(crate) fn table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut widths: Vec<usize> = header.iter().map(|h| h.chars().count()).collect();
    for row in rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let mut out = String::new();
    let mut line = |cells: Vec<&str>| {
        let mut l = String::new();
        for (i, (cell, w)) in cells.iter().zip(&widths).enumerate() {
            if i + 1 == cells.len() {
                l.push_str(cell);
            } else {
                let _ = write!(l, "{cell:<w$}  ");
            }
        }
        out.push_str(l.trim_end());
        out.push('\n');
    };
    line(header.to_vec());
    for row in rows {
        line(row.iter().map(String::as_str).collect());
    }
    out
}

// ---- status ----------------------------------------------------------------------------------

/// The status of machines as a table, then one line per machine with a last alarm.
pub fn status_table(statuses: &[pb::MachineStatus]) -> String {
    if statuses.is_empty() {
        return "no machine answered\n".to_string();
    }
    let header = [
        "MACHINE",
        "PROTOCOL",
        "LINK",
        "SAT",
        "BUFFERED",
        "JOB",
        "WAITING",
        "DO",
        "DI",
        "NC SENT",
        "JOBS OK",
        "FAILED",
        "PUNCHED",
        "RETRIES",
        "ERRORS",
        "LINK ALARMS",
    ];
    let rows: Vec<Vec<String>> = statuses
        .iter()
        .map(|s| {
            let c = s.counters.unwrap_or_default();
            vec![
                s.machine.clone(),
                protocol_text(s.protocol()).to_string(),
                link_cell(s),
                sat_text(s.sat.as_ref()),
                s.sat
                    .as_ref()
                    .and_then(|sat| sat.bytes_buffered)
                    .map_or_else(|| "-".to_string(), |b| b.to_string()),
                dash(&s.current_job_id).to_string(),
                s.jobs_waiting.to_string(),
                opt_image(s.do_image),
                opt_image(s.di_image),
                bytes(c.nc_bytes_sent),
                c.jobs_completed.to_string(),
                c.jobs_failed.to_string(),
                c.programs_punched.to_string(),
                c.retries.to_string(),
                c.protocol_errors.to_string(),
                c.link_alarms.to_string(),
            ]
        })
        .collect();
    let mut out = table(&header, &rows);
    for s in statuses {
        if let Some(w) = waiting_text(s) {
            let _ = writeln!(out, "{w}");
        }
        if !s.storage_fault.is_empty() {
            let _ = writeln!(
                out,
                "{}: the job journal cannot write: {}",
                s.machine, s.storage_fault
            );
        }
        if let Some(a) = &s.last_alarm {
            let _ = writeln!(out, "{}: last alarm {}", s.machine, alarm_text(a));
        }
    }
    out
}

pub fn sat_json(sat: &pb::Sat) -> Value {
    json!({
        "remote": sat.remote,
        "buffer_status": sat.buffer_status().as_str_name(),
        "buffer_status_digit": sat.buffer_status_digit,
        "alarm_cause": sat.alarm_cause().as_str_name(),
        "alarm_cause_digit": sat.alarm_cause_digit,
        "bytes_buffered": sat.bytes_buffered,
        "params": sat.params.as_ref().map(|p| json!({
            "nb": p.nb, "no": p.no, "ne": p.ne, "tp": p.tp,
            "to": p.to, "ti": p.ti, "tx": p.tx, "tw": p.tw,
        })),
        "packet_n": sat.packet_n,
    })
}

pub fn counters_json(c: &pb::LinkCounters) -> Value {
    json!({
        "bytes_sent": c.bytes_sent,
        "bytes_received": c.bytes_received,
        "frames": c.frames,
        "retries": c.retries,
        "checksum_errors": c.checksum_errors,
        "protocol_errors": c.protocol_errors,
        "link_alarms": c.link_alarms,
        "nc_bytes_sent": c.nc_bytes_sent,
        "jobs_completed": c.jobs_completed,
        "jobs_failed": c.jobs_failed,
        "programs_punched": c.programs_punched,
    })
}

pub fn status_json(s: &pb::MachineStatus) -> Value {
    json!({
        "machine": s.machine,
        "protocol": s.protocol().as_str_name(),
        "link_state": s.link_state().as_str_name(),
        "sat": s.sat.as_ref().map(sat_json),
        "counters": s.counters.as_ref().map(counters_json),
        "current_job_id": s.current_job_id,
        "jobs_waiting": s.jobs_waiting,
        "do_image": s.do_image,
        "di_image": s.di_image,
        "last_alarm": s.last_alarm.as_ref().map(alarm_json),
        "unix_ms": s.unix_ms,
        "g05": s.g05.as_ref().map(g05_json),
        "waiting_for": s.waiting_for,
        "waiting_since_unix_ms": s.waiting_since_unix_ms,
        "storage_fault": s.storage_fault,
    })
}

// ---- jobs ------------------------------------------------------------------------------------

/// What a job event says, without the job id: `queued (0 ahead)`, `failed at byte 512: ...`.
pub fn job_kind_text(e: &pb::JobEvent) -> String {
    match &e.kind {
        Some(Kind::Queued(q)) => format!("queued ({} ahead)", q.queue_position),
        Some(Kind::Started(s)) => match s.bytes_total {
            Some(t) => format!("started ({})", bytes(t)),
            None => "started".to_string(),
        },
        Some(Kind::Progress(p)) => {
            let mut t = format!("sent {}", bytes(p.bytes_sent));
            if let Some(total) = p.bytes_total.filter(|t| *t > 0) {
                let _ = write!(
                    t,
                    " of {} ({}%)",
                    bytes(total),
                    p.bytes_sent.saturating_mul(100) / total
                );
            }
            if p.bytes_on_line > p.bytes_sent {
                let _ = write!(t, ", {} on the line", bytes(p.bytes_on_line));
            }
            let _ = write!(t, ", {} B/s", p.rate_bps);
            t
        }
        Some(Kind::Completed(c)) => {
            let mut t = format!(
                "completed: {} sent in {:.1} s",
                bytes(c.bytes_sent),
                c.duration_ms as f64 / 1000.0
            );
            match c.confirmation() {
                pb::Confirmation::EndOfRead => t.push_str(" (end of read)"),
                pb::Confirmation::Unverified => t.push_str(
                    " (unverified: this link cannot tell the end of a read from a CNC reset)",
                ),
                _ => {}
            }
            if c.bytes_after_eor > 0 {
                let _ = write!(
                    t,
                    "; the {} after the EOR % not sent (the CNC ignores them)",
                    bytes(c.bytes_after_eor)
                );
            }
            t
        }
        Some(Kind::Failed(f)) => failed_text(f),
        Some(Kind::Cancelled(c)) if c.next_block.is_none() && c.bytes_on_line == 0 => {
            format!(
                "cancelled by {} before the CNC read any of it: nothing was sent",
                dash(&c.by)
            )
        }
        Some(Kind::Cancelled(c)) => {
            let mut t = format!("cancelled by {} at byte {}", dash(&c.by), c.byte_offset);
            if let Some(b) = &c.next_block {
                t.push_str(&resume_text(b));
            }
            t
        }
        None => "event of an unknown kind".to_string(),
    }
}

/// `failed at byte 512: <reason> [SR0945] (LINK_FAILED)`.
pub fn failed_text(f: &pb::job_event::Failed) -> String {
    let mut t = format!("failed at byte {}: {}", f.byte_offset, f.reason);
    if !f.alarm_number.is_empty() {
        let _ = write!(t, " [{}]", f.alarm_number);
    }
    if f.code() != pb::ErrorCode::Unspecified {
        let _ = write!(t, " ({})", short(f.code().as_str_name(), "ERROR_CODE_"));
    }
    if let Some(b) = &f.next_block {
        t.push_str(&resume_text(b));
    }
    t
}

/// `; resumes at line 57 (N1234)`.
fn resume_text(b: &pb::BlockPosition) -> String {
    if b.sequence_number.is_empty() {
        format!("; resumes at line {}", b.line)
    } else {
        format!("; resumes at line {} ({})", b.line, b.sequence_number)
    }
}

fn block_json(b: &Option<pb::BlockPosition>) -> Value {
    match b {
        Some(b) => json!({
            "line": b.line,
            "sequence_number": b.sequence_number,
            "byte_offset": b.byte_offset,
        }),
        None => Value::Null,
    }
}

pub fn job_event_json(e: &pb::JobEvent) -> Value {
    let (kind, detail) = match &e.kind {
        Some(Kind::Queued(q)) => ("queued", json!({ "queue_position": q.queue_position })),
        Some(Kind::Started(s)) => ("started", json!({ "bytes_total": s.bytes_total })),
        Some(Kind::Progress(p)) => (
            "progress",
            json!({
                "bytes_sent": p.bytes_sent,
                "bytes_total": p.bytes_total,
                "bytes_on_line": p.bytes_on_line,
                "rate_bps": p.rate_bps,
            }),
        ),
        Some(Kind::Completed(c)) => (
            "completed",
            json!({
                "bytes_sent": c.bytes_sent,
                "bytes_after_eor": c.bytes_after_eor,
                "duration_ms": c.duration_ms,
                "confirmation": c.confirmation().as_str_name(),
            }),
        ),
        Some(Kind::Failed(f)) => (
            "failed",
            json!({
                "reason": f.reason,
                "byte_offset": f.byte_offset,
                "alarm_number": f.alarm_number,
                "code": f.code().as_str_name(),
                "bytes_on_line": f.bytes_on_line,
                "next_block": block_json(&f.next_block),
            }),
        ),
        Some(Kind::Cancelled(c)) => (
            "cancelled",
            json!({
                "byte_offset": c.byte_offset,
                "by": c.by,
                "bytes_on_line": c.bytes_on_line,
                "next_block": block_json(&c.next_block),
            }),
        ),
        None => ("unknown", Value::Null),
    };
    json!({
        "job_id": e.job_id,
        "machine": e.machine,
        "unix_ms": e.unix_ms,
        kind: detail,
    })
}

pub fn accepted_json(a: &pb::JobAccepted) -> Value {
    json!({ "job_id": a.job_id, "queue_position": a.queue_position })
}

/// The gateway's version and uptime from its admin document; `None` when the gateway does
/// not show the document (a cell with roles, without `admin.read`).
pub fn gateway_line(admin: &Value, now_ms: u64) -> Option<String> {
    let version = admin["version"].as_str()?;
    let cell = admin["cell"].as_str().unwrap_or("?");
    let mut t = format!("gateway: cellgate {version}, cell {cell}");
    if let Some(started) = admin["started_unix_ms"].as_u64() {
        let _ = write!(
            t,
            ", up {} (since {})",
            age(now_ms.saturating_sub(started)),
            date_time(started)
        );
    }
    // A cell reloaded since the gateway started says so.
    if let Some(generation) = admin["generation"].as_u64().filter(|g| *g > 1) {
        let _ = write!(t, ", configuration generation {generation}");
        if let Some(waiting) = admin["waiting"].as_array().filter(|w| !w.is_empty()) {
            let names: Vec<&str> = waiting.iter().filter_map(Value::as_str).collect();
            let _ = write!(t, " (waiting for their running job: {})", names.join(", "));
        }
    }
    Some(t)
}

fn queued_row(machine: &str, state: &str, j: &pb::QueuedJob) -> Vec<String> {
    vec![
        machine.to_string(),
        j.job_id.clone(),
        state.to_string(),
        j.name.clone(),
        j.priority.to_string(),
        format!("{} of {}", bytes(j.bytes_sent), bytes(j.bytes_total)),
        clock(j.accepted_unix_ms),
    ]
}

/// The machines' queues as a table: the active job, then the waiting ones in run order;
/// then the ended jobs given, one line each.
pub fn queue_table(queues: &[pb::JobQueue], ended: &[pb::JobEvent]) -> String {
    let mut rows = Vec::new();
    for q in queues {
        if let Some(a) = &q.active {
            rows.push(queued_row(&q.machine, "active", a));
        }
        for (i, w) in q.waiting.iter().enumerate() {
            rows.push(queued_row(&q.machine, &format!("waiting, {i} ahead"), w));
        }
    }
    let mut out = if rows.is_empty() {
        "no job active or waiting\n".to_string()
    } else {
        table(
            &[
                "MACHINE", "JOB", "STATE", "NAME", "PRIORITY", "SENT", "ACCEPTED",
            ],
            &rows,
        )
    };
    if !ended.is_empty() {
        let _ = writeln!(out, "ended:");
        for e in ended {
            let _ = writeln!(
                out,
                "  {} {} {}: {}",
                clock(e.unix_ms),
                e.machine,
                e.job_id,
                job_kind_text(e)
            );
        }
    }
    out
}

fn queued_json(j: &pb::QueuedJob) -> Value {
    json!({
        "job_id": j.job_id, "name": j.name, "priority": j.priority,
        "bytes_total": j.bytes_total, "bytes_sent": j.bytes_sent,
        "accepted_unix_ms": j.accepted_unix_ms,
    })
}

/// A machine's queue as JSON.
pub fn queue_json(q: &pb::JobQueue) -> Value {
    json!({
        "machine": q.machine,
        "active": q.active.as_ref().map(queued_json),
        "waiting": q.waiting.iter().map(queued_json).collect::<Vec<_>>(),
    })
}

// ---- alarms, DI, programs --------------------------------------------------------------------

/// `12:00:01.250Z link alarm SR0945: <message>`.
pub fn alarm_text(a: &pb::AlarmEvent) -> String {
    let mut t = format!(
        "{} {}",
        clock(a.unix_ms),
        short(a.kind().as_str_name(), "ALARM_KIND_")
    );
    if !a.alarm_number.is_empty() {
        let _ = write!(t, " {}", a.alarm_number);
    }
    if !a.message.is_empty() {
        let _ = write!(t, ": {}", a.message);
    }
    t
}

pub fn alarm_json(a: &pb::AlarmEvent) -> Value {
    json!({
        "machine": a.machine,
        "kind": a.kind().as_str_name(),
        "alarm_number": a.alarm_number,
        "message": a.message,
        "unix_ms": a.unix_ms,
    })
}

/// A remote request's outcome, as a suffix of the punched program's line.
fn request_text(r: &pb::RemoteRequest) -> String {
    if r.error.is_empty() {
        format!(
            "; remote request for {}: {} queued as job {}",
            r.program, r.library_name, r.job_id
        )
    } else {
        format!("; remote request for {} refused: {}", r.program, r.error)
    }
}

pub fn punched_json(p: &pb::PunchedProgram) -> Value {
    json!({
        "machine": p.machine,
        "name": p.name,
        "o_number": p.o_number,
        "code_system": p.code_system().as_str_name(),
        "size": p.program.len(),
        "library_name": p.library_name,
        "unix_ms": p.unix_ms,
        "damaged": p.damaged,
        "damage": p.damage,
        "request": p.request.as_ref().map(|r| json!({
            "program": r.program,
            "library_name": r.library_name,
            "job_id": r.job_id,
            "error": r.error,
        })),
    })
}

/// The DI image in hex and bit by bit (bit 7 first, as the manual draws G152).
pub fn di_text(di: &pb::DiImage) -> String {
    let bits: Vec<String> = (0..8)
        .rev()
        .map(|b| ((di.value >> b) & 1).to_string())
        .collect();
    format!(
        "{} DI {} ({}) at {}\n  bit  7 6 5 4 3 2 1 0\n       {}\n",
        di.machine,
        byte_image(di.value),
        di.value,
        clock(di.unix_ms),
        bits.join(" ")
    )
}

pub fn di_json(di: &pb::DiImage) -> Value {
    json!({ "machine": di.machine, "value": di.value, "unix_ms": di.unix_ms })
}

pub fn program_table(programs: &[pb::ProgramInfo]) -> String {
    if programs.is_empty() {
        return "the program library is empty\n".to_string();
    }
    let rows: Vec<Vec<String>> = programs
        .iter()
        .map(|p| {
            vec![
                if p.name.is_empty() {
                    "-".to_string()
                } else {
                    p.name.clone()
                },
                p.latest
                    .as_ref()
                    .filter(|r| !r.removed)
                    .map_or_else(|| "-".to_string(), |r| r.number.to_string()),
                p.size.to_string(),
                date_time(p.modified_unix_ms),
                if p.file.is_empty() {
                    "-".to_string()
                } else {
                    p.file.clone()
                },
            ]
        })
        .collect();
    let mut out = table(&["NAME", "REV", "BYTES", "MODIFIED", "FILE"], &rows);
    // Why a file of the folder is not its program's latest revision, where it is not; a file
    // the folder does not take has no program name, and is named by its file.
    for p in programs.iter().filter(|p| !p.note.is_empty()) {
        let who = if p.name.is_empty() { &p.file } else { &p.name };
        out.push_str(&format!("{who}: {}\n", p.note));
    }
    out
}

pub fn program_json(p: &pb::ProgramInfo) -> Value {
    let latest = p.latest.as_ref().map(|r| {
        json!({
            "number": r.number,
            "sha256": r.sha256,
            "state": r.state().as_str_name(),
            "unix_ms": r.unix_ms,
            "by": r.by.as_ref().map(|o| json!({"user": o.user, "via": o.via})),
            "comment": r.comment,
        })
    });
    json!({
        "name": p.name,
        "size": p.size,
        "modified_unix_ms": p.modified_unix_ms,
        "latest": latest,
        "latest_released": p.latest_released,
        "file": p.file,
        "note": p.note,
    })
}

// ---- watch -----------------------------------------------------------------------------------

/// Turns watch events into lines. A status is published on every change, counters
/// included; as text, a machine's status is printed only when what a person follows changes
/// (link, SAT status, job, queue, DO, DI). JSON prints every event.
#[derive(Debug, Default)]
pub struct WatchPrinter {
    headlines: HashMap<String, String>,
}

impl WatchPrinter {
    pub fn new() -> Self {
        Self::default()
    }

    /// The text line for an event, if it is worth one.
    pub fn line(&mut self, event: &WatchEvent, now_ms: u64) -> Option<String> {
        let line = match event {
            WatchEvent::Status(s) => {
                let headline = format!(
                    "link {}, SAT {}, job {}, {} waiting, DO {}, DI {}",
                    link_cell(s),
                    sat_text(s.sat.as_ref()),
                    dash(&s.current_job_id),
                    s.jobs_waiting,
                    opt_image(s.do_image),
                    opt_image(s.di_image),
                );
                if self.headlines.get(&s.machine) == Some(&headline) {
                    return None;
                }
                self.headlines.insert(s.machine.clone(), headline.clone());
                format!("{} {} status: {headline}", clock(s.unix_ms), s.machine)
            }
            WatchEvent::Job(e) => format!(
                "{} {} job {} {}",
                clock(e.unix_ms),
                e.machine,
                e.job_id,
                job_kind_text(e)
            ),
            WatchEvent::Alarm(a) => format!("{} ALARM {}", a.machine, alarm_text(a)),
            WatchEvent::Punched(p) => format!(
                "{} {} punched {} ({} bytes, {}){}{}{}",
                clock(p.unix_ms),
                p.machine,
                if p.name.is_empty() {
                    "a program"
                } else {
                    &p.name
                },
                p.program.len(),
                p.code_system().as_str_name(),
                if p.library_name.is_empty() {
                    String::new()
                } else {
                    format!(" stored as {}", p.library_name)
                },
                p.request.as_ref().map(request_text).unwrap_or_default(),
                if p.damaged {
                    format!(" DAMAGED ({}): not stored, punch it again", p.damage)
                } else {
                    String::new()
                },
            ),
            WatchEvent::Di(d) => format!(
                "{} {} DI {}",
                clock(d.unix_ms),
                d.machine,
                byte_image(d.value)
            ),
            WatchEvent::DoCommand { machine, command } => format!(
                "{} {machine} DO command {} mask {}",
                clock(now_ms),
                byte_image(command.value),
                command
                    .mask
                    .map_or_else(|| "all".to_string(), |m| format!("0x{m:02X}"))
            ),
            WatchEvent::CancelRequested { machine, job_id } => {
                format!("{} {machine} job {job_id} cancel requested", clock(now_ms))
            }
            WatchEvent::G05(g) => format!(
                "{} {} G05 stream {} {}: {} blocks, {} underruns{}",
                clock(now_ms),
                g.machine,
                g.stream_id,
                g05_state_name(g.state()),
                g.received,
                g.underruns,
                if g.last_error.is_empty() {
                    String::new()
                } else {
                    format!(" ({})", g.last_error)
                }
            ),
            WatchEvent::ProgramPut { name, size } => {
                format!("{} program {name} put ({})", clock(now_ms), bytes(*size))
            }
            WatchEvent::ProgramDeleted { name } => {
                format!("{} program {name} removal requested", clock(now_ms))
            }
            WatchEvent::ProgramChanged { info, by } => {
                format!(
                    "{} library {}",
                    clock(now_ms),
                    library_change_text(info, by.as_ref())
                )
            }
            WatchEvent::Library(e) => format!("{} library {}", clock(now_ms), folder_event_text(e)),
            WatchEvent::DoOutput {
                machine,
                command,
                by,
            } => format!(
                "{} {machine} DO output {} mask {}{}",
                clock(now_ms),
                byte_image(command.value),
                command
                    .mask
                    .map_or_else(|| "all".to_string(), |m| format!("0x{m:02X}")),
                by.as_ref()
                    .map(|o| format!(" by {}", origin_text(o)))
                    .unwrap_or_default()
            ),
            WatchEvent::Link { machine, up } => format!(
                "{} {machine} link {}",
                clock(now_ms),
                if *up { "up" } else { "down" }
            ),
            WatchEvent::Gateway { up } => format!(
                "{} gateway {}",
                clock(now_ms),
                if *up { "up" } else { "gone" }
            ),
            WatchEvent::Tag(t) => format!("{} {}", clock(now_ms), tag_text(t)),
            WatchEvent::Transfer(t) => format!(
                "{} {} transfer {} {} {} bytes: {}",
                clock(now_ms),
                t.plc,
                t.message,
                if t.from_plc { "from PLC" } else { "to PLC" },
                t.data.len(),
                hex::encode_upper(&t.data)
            ),
            WatchEvent::PlcMessage(m) => format!(
                "{} {} message {} {} bytes: {}",
                clock(now_ms),
                m.plc,
                if m.from_plc { "from PLC" } else { "to PLC" },
                m.data.len(),
                hex::encode_upper(&m.data)
            ),
            WatchEvent::PlcStation { plc, station, up } => format!(
                "{} {plc} station {station} {}",
                clock(now_ms),
                if *up { "up" } else { "down" }
            ),
            WatchEvent::Reload(r) if r.applied => format!(
                "{} cell reloaded ({}), generation {}: {}{}",
                clock(r.unix_ms),
                r.via,
                r.generation,
                crate::bus::route_reload::summary(r),
                if r.waiting.is_empty() {
                    String::new()
                } else {
                    format!("; waiting for their running job: {}", r.waiting.join(", "))
                }
            ),
            WatchEvent::Reload(r) => format!(
                "{} cell reload refused ({}): {}",
                clock(r.unix_ms),
                r.via,
                r.errors.join("; ")
            ),
            WatchEvent::Unexpected { key, detail } => {
                format!("{} {key}: unexpected sample: {detail}", clock(now_ms))
            }
        };
        Some(line)
    }
}

/// Who sent a write, as its origin says: `ana (console)`, `(folder)`, `ana`, or `-` when nothing is known.
pub fn origin_text(o: &pb::RequestOrigin) -> String {
    match (o.user.is_empty(), o.via.is_empty()) {
        (true, true) => "-".to_string(),
        (false, true) => o.user.clone(),
        (true, false) => format!("({})", o.via),
        (false, false) => format!("{} ({})", o.user, o.via),
    }
}

/// What a library change was, from the `ProgramInfo` the gateway published with it: the
/// latest revision is the one the change made, or the removed one.
fn library_change(info: &pb::ProgramInfo) -> &'static str {
    match &info.latest {
        Some(r) if r.removed => "removed",
        Some(r) if !r.adopted_from.is_empty() => "adopted",
        _ => "stored",
    }
}

/// `O7001 stored: revision 3, 1.2 KiB, by ana (console)`.
fn library_change_text(info: &pb::ProgramInfo, by: Option<&pb::RequestOrigin>) -> String {
    let change = library_change(info);
    let mut text = format!("{} {change}", info.name);
    if let Some(r) = &info.latest {
        if change == "removed" {
            text.push_str(&format!(" (its latest revision was {})", r.number));
        } else {
            text.push_str(&format!(": revision {}, {}", r.number, bytes(info.size)));
            if change == "adopted" {
                text.push_str(&format!(
                    ", from {} revision {}",
                    r.adopted_from, r.adopted_revision
                ));
            }
        }
    }
    if let Some(o) = by {
        text.push_str(&format!(", by {}", origin_text(o)));
    }
    text
}

/// What a reload did, for people: the file and generation, then each kind of change on a
/// line of its own, and the machines whose links wait for their running job.
pub fn reload_text(r: &pb::ReloadResult) -> String {
    let what = crate::bus::route_reload::summary(r);
    let mut t = if what == "nothing changed" {
        format!(
            "reloaded {}: nothing changed (configuration generation {})\n",
            r.file, r.generation
        )
    } else {
        format!(
            "reloaded {}: configuration generation {}\n",
            r.file, r.generation
        )
    };
    for part in what.split("; ").filter(|_| what != "nothing changed") {
        let _ = writeln!(t, "  {part}");
    }
    if !r.waiting.is_empty() {
        let _ = writeln!(
            t,
            "  waiting for their running job to end: {} (their links stop or restart then; \
             --force does it at once)",
            r.waiting.join(", ")
        );
    }
    for e in &r.errors {
        let _ = writeln!(t, "  {e}");
    }
    t
}

/// The machine (or PLC) an event concerns, if one.
pub fn watch_machine(event: &WatchEvent) -> Option<&str> {
    match event {
        WatchEvent::Status(s) => Some(&s.machine),
        WatchEvent::Job(e) => Some(&e.machine),
        WatchEvent::Alarm(a) => Some(&a.machine),
        WatchEvent::Punched(p) => Some(&p.machine),
        WatchEvent::Di(d) => Some(&d.machine),
        WatchEvent::G05(g) => Some(&g.machine),
        WatchEvent::DoCommand { machine, .. }
        | WatchEvent::DoOutput { machine, .. }
        | WatchEvent::CancelRequested { machine, .. }
        | WatchEvent::Link { machine, .. } => Some(machine),
        // A PLC's events are its name's, as a machine's are the machine's.
        WatchEvent::Tag(t) => Some(&t.plc),
        WatchEvent::Transfer(t) => Some(&t.plc),
        WatchEvent::PlcStation { plc, .. } => Some(plc),
        _ => None,
    }
}

/// One JSON object per event: `{"event": "<kind>", ...}`.
pub fn watch_json(event: &WatchEvent, now_ms: u64) -> Value {
    match event {
        WatchEvent::Status(s) => json!({ "event": "status", "status": status_json(s) }),
        WatchEvent::Job(e) => json!({ "event": "job", "job": job_event_json(e) }),
        WatchEvent::Alarm(a) => json!({ "event": "alarm", "alarm": alarm_json(a) }),
        WatchEvent::Punched(p) => json!({ "event": "punched", "punched": punched_json(p) }),
        WatchEvent::G05(g) => json!({ "event": "g05", "g05": g05_json(g) }),
        WatchEvent::Di(d) => json!({ "event": "di", "di": di_json(d) }),
        WatchEvent::DoCommand { machine, command } => json!({
            "event": "do_command", "machine": machine, "unix_ms": now_ms,
            "do_command": { "value": command.value, "mask": command.mask },
        }),
        WatchEvent::CancelRequested { machine, job_id } => json!({
            "event": "cancel_requested", "machine": machine, "job_id": job_id, "unix_ms": now_ms,
        }),
        WatchEvent::ProgramPut { name, size } => json!({
            "event": "program_put", "name": name, "size": size, "unix_ms": now_ms,
        }),
        WatchEvent::ProgramDeleted { name } => json!({
            "event": "program_deleted", "name": name, "unix_ms": now_ms,
        }),
        WatchEvent::ProgramChanged { info, by } => json!({
            "event": "program_changed", "change": library_change(info), "unix_ms": now_ms,
            "program": info, "by": by,
        }),
        WatchEvent::Library(e) => json!({
            "event": "library", "folder": e, "unix_ms": now_ms,
        }),
        WatchEvent::DoOutput {
            machine,
            command,
            by,
        } => json!({
            "event": "do_output", "machine": machine, "unix_ms": now_ms,
            "do_command": { "value": command.value, "mask": command.mask }, "by": by,
        }),
        WatchEvent::Link { machine, up } => json!({
            "event": if *up { "link_up" } else { "link_down" }, "machine": machine, "unix_ms": now_ms,
        }),
        WatchEvent::Gateway { up } => json!({
            "event": if *up { "gateway_up" } else { "gateway_gone" }, "unix_ms": now_ms,
        }),
        WatchEvent::Tag(t) => json!({ "event": "tag", "tag": tag_json(t) }),
        WatchEvent::Transfer(t) => json!({
            "event": "transfer", "plc": t.plc, "message": t.message, "from_plc": t.from_plc,
            "data": hex::encode_upper(&t.data), "unix_ms": t.unix_ms,
        }),
        WatchEvent::PlcMessage(m) => json!({
            "event": "plc_message", "plc": m.plc, "from_plc": m.from_plc,
            "data": hex::encode_upper(&m.data), "unix_ms": m.unix_ms,
        }),
        WatchEvent::PlcStation { plc, station, up } => json!({
            "event": if *up { "plc_station_up" } else { "plc_station_down" },
            "plc": plc, "station": station, "unix_ms": now_ms,
        }),
        WatchEvent::Reload(r) => json!({
            "event": "reload", "reload": serde_json::to_value(r).unwrap_or_default(),
        }),
        WatchEvent::Unexpected { key, detail } => json!({
            "event": "unexpected", "key": key, "detail": detail, "unix_ms": now_ms,
        }),
    }
}

/// A G05 stream's state in words.
pub fn g05_state_name(s: pb::G05State) -> &'static str {
    match s {
        pb::G05State::Unspecified => "unknown",
        pb::G05State::Priming => "priming",
        pb::G05State::Streaming => "streaming",
        pb::G05State::Ending => "ending",
        pb::G05State::Completed => "completed",
        pb::G05State::Failed => "failed",
    }
}

/// A G05 stream's status as JSON.
pub fn g05_json(g: &pb::G05Status) -> Value {
    json!({
        "stream": g.stream_id,
        "machine": g.machine,
        "state": g05_state_name(g.state()),
        "credits": g.credits,
        "received": g.received,
        "on_line": g.on_line,
        "cnc_buffer": g.cnc_buffer,
        "underruns": g.underruns,
        "gaps": g.gaps,
        "repeats": g.repeats,
        "refused": g.refused,
        "next_seq": g.next_seq,
        "last_error": g.last_error,
        "end_reason": format!("{:?}", g.end_reason()),
    })
}

/// A tag in one line: `plc-1/parts = 42 (good, 12:00:01.250)`.
pub fn tag_text(t: &pb::TagValue) -> String {
    let value = match t.value {
        Some(v) => format!("{v}"),
        None => "-".to_string(),
    };
    format!(
        "{}/{} = {} ({}{})",
        t.plc,
        t.name,
        value,
        quality_name(t.quality()),
        if t.writable { ", writable" } else { "" }
    )
}

/// A tag quality as people read it.
pub fn quality_name(q: pb::TagQuality) -> &'static str {
    match q {
        pb::TagQuality::Good => "good",
        pb::TagQuality::Stale => "stale",
        pb::TagQuality::StationDown => "station down",
        pb::TagQuality::Unspecified => "?",
    }
}

/// A tag as one JSON object.
pub fn tag_json(t: &pb::TagValue) -> Value {
    json!({
        "plc": t.plc, "name": t.name, "value": t.value, "raw": t.raw,
        "unix_ms": t.unix_ms, "quality": quality_name(t.quality()), "writable": t.writable,
    })
}

/// A station's last error with how old it is (`12 min ago: ...`), or empty.
pub fn last_error_text(st: &pb::PlcStation, now_ms: u64) -> String {
    if st.last_error.is_empty() {
        return String::new();
    }
    if st.last_error_unix_ms == 0 {
        return st.last_error.clone();
    }
    format!(
        "{} ago: {}",
        age(now_ms.saturating_sub(st.last_error_unix_ms)),
        st.last_error
    )
}

/// Error replies by STA code as the FFU120B manual writes them (`A7`), for JSON.
pub fn error_replies_json(st: &pb::PlcStation) -> Value {
    let mut codes: Vec<(&u32, &u64)> = st.error_replies.iter().collect();
    codes.sort();
    Value::Object(
        codes
            .into_iter()
            .map(|(sta, n)| (format!("{sta:02X}"), json!(n)))
            .collect(),
    )
}

/// The stations of every PLC link, one line each; `now_ms` ages their last errors.
/// A folder event of the library, for `watch`.
fn folder_event_text(e: &pb::LibraryEvent) -> String {
    match e.kind() {
        pb::LibraryEventKind::Refused => format!(
            "{}{}: not taken: {}",
            e.file,
            if e.name.is_empty() || e.name == e.file {
                String::new()
            } else {
                format!(" (program {})", e.name)
            },
            e.error
        ),
        pb::LibraryEventKind::FolderUnreadable => {
            format!("folder {} cannot be read: {}", e.file, e.error)
        }
        pb::LibraryEventKind::FolderReadable => format!("folder {} can be read again", e.file),
        pb::LibraryEventKind::Unspecified => format!("{} {}", e.file, e.error),
    }
}

mod plc;
pub use plc::plc_status_text;

#[cfg(test)]
mod tests;
