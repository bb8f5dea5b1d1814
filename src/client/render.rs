//! Text for people and JSON for programs, from the contract's messages.
//!
//! JSON keeps the field names and enum value names of `proto/cellgate/v1/*.proto` (e.g.
//! `"link_state": "LINK_STATE_IDLE"`); optional fields that are absent are `null`. 64-bit
//! integers are plain JSON numbers.

use std::collections::HashMap;
use std::fmt::Write as _;

use serde_json::{Value, json};

use super::WatchEvent;
use crate::pb;
use crate::pb::job_event::Kind;

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
    let (y, m, d) = crate::jobs::punch::civil_from_days(secs / 86_400);
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
fn table(header: &[&str], rows: &[Vec<String>]) -> String {
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
        "MACHINE", "PROTOCOL", "LINK", "SAT", "BUFFERED", "JOB", "WAITING", "DO", "DI", "NC SENT",
        "JOBS OK", "FAILED", "PUNCHED", "RETRIES", "ERRORS", "ALARMS",
    ];
    let rows: Vec<Vec<String>> = statuses
        .iter()
        .map(|s| {
            let c = s.counters.unwrap_or_default();
            vec![
                s.machine.clone(),
                protocol_text(s.protocol()).to_string(),
                link_text(s.link_state()),
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
            t
        }
        Some(Kind::Failed(f)) => failed_text(f),
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
                p.name.clone(),
                p.size.to_string(),
                date_time(p.modified_unix_ms),
            ]
        })
        .collect();
    table(&["NAME", "BYTES", "MODIFIED"], &rows)
}

pub fn program_json(p: &pb::ProgramInfo) -> Value {
    json!({ "name": p.name, "size": p.size, "modified_unix_ms": p.modified_unix_ms })
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
                    link_text(s.link_state()),
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
            WatchEvent::Tag(t) => format!("{} {}", clock(now_ms), super::plc::tag_text(t)),
            WatchEvent::Transfer(t) => format!(
                "{} {} transfer {} {} {} bytes: {}",
                clock(now_ms),
                t.plc,
                t.message,
                if t.from_plc { "from PLC" } else { "to PLC" },
                t.data.len(),
                hex::encode_upper(&t.data)
            ),
            WatchEvent::PlcStation { plc, station, up } => format!(
                "{} {plc} station {station} {}",
                clock(now_ms),
                if *up { "up" } else { "down" }
            ),
            WatchEvent::Unexpected { key, detail } => {
                format!("{} {key}: unexpected sample: {detail}", clock(now_ms))
            }
        };
        Some(line)
    }
}

/// The machine an event concerns, if one.
pub fn watch_machine(event: &WatchEvent) -> Option<&str> {
    match event {
        WatchEvent::Status(s) => Some(&s.machine),
        WatchEvent::Job(e) => Some(&e.machine),
        WatchEvent::Alarm(a) => Some(&a.machine),
        WatchEvent::Punched(p) => Some(&p.machine),
        WatchEvent::Di(d) => Some(&d.machine),
        WatchEvent::G05(g) => Some(&g.machine),
        WatchEvent::DoCommand { machine, .. }
        | WatchEvent::CancelRequested { machine, .. }
        | WatchEvent::Link { machine, .. } => Some(machine),
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
        WatchEvent::Link { machine, up } => json!({
            "event": if *up { "link_up" } else { "link_down" }, "machine": machine, "unix_ms": now_ms,
        }),
        WatchEvent::Gateway { up } => json!({
            "event": if *up { "gateway_up" } else { "gateway_gone" }, "unix_ms": now_ms,
        }),
        WatchEvent::Tag(t) => json!({ "event": "tag", "tag": super::plc::tag_json(t) }),
        WatchEvent::Transfer(t) => json!({
            "event": "transfer", "plc": t.plc, "message": t.message, "from_plc": t.from_plc,
            "data": hex::encode_upper(&t.data), "unix_ms": t.unix_ms,
        }),
        WatchEvent::PlcStation { plc, station, up } => json!({
            "event": if *up { "plc_station_up" } else { "plc_station_down" },
            "plc": plc, "station": station, "unix_ms": now_ms,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_are_utc() {
        assert_eq!(clock(0), "00:00:00.000Z");
        assert_eq!(clock(1_700_000_000_123), "22:13:20.123Z");
        assert_eq!(date_time(1_700_000_000_123), "2023-11-14 22:13:20Z");
        assert_eq!(date_time(951_782_400_000), "2000-02-29 00:00:00Z");
    }

    #[test]
    fn sizes_and_images_read_well() {
        assert_eq!(bytes(512), "512 B");
        assert_eq!(bytes(40 * 1024), "40.0 KiB");
        assert_eq!(bytes(3 * 1024 * 1024 / 2), "1.5 MiB");
        assert_eq!(byte_image(0x5A), "0x5A 0b01011010");
    }

    fn status() -> pb::MachineStatus {
        pb::MachineStatus {
            machine: "mill-1".to_string(),
            protocol: pb::Protocol::ExpansionA as i32,
            link_state: pb::LinkState::Sending as i32,
            sat: Some(pb::Sat {
                buffer_status: pb::BufferStatus::Alarm as i32,
                alarm_cause: pb::AlarmCause::ChecksumRetryOver as i32,
                bytes_buffered: Some(300),
                ..pb::Sat::default()
            }),
            counters: Some(pb::LinkCounters {
                nc_bytes_sent: 2048,
                jobs_completed: 3,
                programs_punched: 5,
                retries: 4,
                ..pb::LinkCounters::default()
            }),
            current_job_id: "mill-1-x-7".to_string(),
            do_image: Some(0xA5),
            last_alarm: Some(pb::AlarmEvent {
                machine: "mill-1".to_string(),
                kind: pb::AlarmKind::LinkAlarm as i32,
                alarm_number: "SR0945".to_string(),
                message: "retry over".to_string(),
                unix_ms: 0,
            }),
            ..pb::MachineStatus::default()
        }
    }

    #[test]
    fn the_status_table_shows_what_the_contract_carries() {
        let t = status_table(&[status()]);
        let mut lines = t.lines();
        let header = lines.next().unwrap();
        assert!(header.starts_with("MACHINE"), "{t}");
        let row = lines.next().unwrap();
        for cell in [
            "mill-1",
            "Expansion A",
            "sending",
            "alarm: checksum retry over",
            "300",
            "mill-1-x-7",
            "0xA5",
            "2.0 KiB",
        ] {
            assert!(row.contains(cell), "{cell:?} missing from {row:?}");
        }
        assert!(
            lines
                .next()
                .unwrap()
                .contains("link alarm SR0945: retry over"),
            "{t}"
        );
        assert_eq!(status_table(&[]), "no machine answered\n");
    }

    #[test]
    fn punched_programs_read_as_sentences() {
        let mut p = pb::PunchedProgram {
            machine: "lathe-1".to_string(),
            name: "SHAFT".to_string(),
            o_number: "O1234".to_string(),
            code_system: pb::CodeSystem::Eia as i32,
            program: b"%\nO1234(SHAFT)\n%".to_vec(),
            library_name: "lathe-1-O1234-20261122T061500Z".to_string(),
            unix_ms: 0,
            request: None,
            damaged: false,
            damage: String::new(),
        };
        let mut printer = WatchPrinter::new();
        let line = printer
            .line(&WatchEvent::Punched(Box::new(p.clone())), 0)
            .unwrap();
        assert!(
            line.contains("lathe-1 punched SHAFT (16 bytes, CODE_SYSTEM_EIA)"),
            "{line}"
        );
        assert!(
            line.ends_with("stored as lathe-1-O1234-20261122T061500Z"),
            "{line}"
        );
        p.library_name.clear();
        p.request = Some(pb::RemoteRequest {
            program: "O12".to_string(),
            error: "no program O12".to_string(),
            ..pb::RemoteRequest::default()
        });
        let line = printer
            .line(&WatchEvent::Punched(Box::new(p.clone())), 0)
            .unwrap();
        assert!(
            line.ends_with("remote request for O12 refused: no program O12"),
            "{line}"
        );
        let damaged = pb::PunchedProgram {
            damaged: true,
            damage: "parity error in a received character during the punch-out".to_string(),
            library_name: String::new(),
            ..p.clone()
        };
        let line = printer
            .line(&WatchEvent::Punched(Box::new(damaged)), 0)
            .unwrap();
        assert!(
            line.ends_with(
                "DAMAGED (parity error in a received character during the punch-out): not \
                 stored, punch it again"
            ),
            "{line}"
        );
        let j = watch_json(&WatchEvent::Punched(Box::new(p)), 0);
        assert_eq!(j["event"], "punched");
        assert_eq!(j["punched"]["code_system"], "CODE_SYSTEM_EIA");
        assert_eq!(j["punched"]["request"]["program"], "O12");
        assert_eq!(
            watch_machine(&WatchEvent::Punched(Box::default())),
            Some("")
        );
    }

    #[test]
    fn status_json_uses_the_proto_names() {
        let j = status_json(&status());
        assert_eq!(j["protocol"], "PROTOCOL_EXPANSION_A");
        assert_eq!(j["link_state"], "LINK_STATE_SENDING");
        assert_eq!(j["sat"]["buffer_status"], "BUFFER_STATUS_ALARM");
        assert_eq!(j["sat"]["bytes_buffered"], 300);
        assert_eq!(j["do_image"], 0xA5);
        assert_eq!(j["di_image"], Value::Null);
        assert_eq!(j["counters"]["jobs_completed"], 3);
        assert_eq!(j["counters"]["programs_punched"], 5);
        assert_eq!(j["last_alarm"]["alarm_number"], "SR0945");
    }

    #[test]
    fn job_events_read_as_sentences() {
        let ev = |kind| pb::JobEvent {
            job_id: "j".to_string(),
            machine: "m".to_string(),
            unix_ms: 0,
            kind: Some(kind),
        };
        let p = ev(Kind::Progress(pb::job_event::Progress {
            bytes_sent: 512,
            bytes_total: Some(2048),
            rate_bps: 1900,
            bytes_on_line: 512,
        }));
        assert_eq!(job_kind_text(&p), "sent 512 B of 2.0 KiB (25%), 1900 B/s");
        let p = ev(Kind::Progress(pb::job_event::Progress {
            bytes_on_line: 1024,
            ..pb::job_event::Progress::default()
        }));
        assert_eq!(job_kind_text(&p), "sent 0 B, 1.0 KiB on the line, 0 B/s");
        let f = ev(Kind::Failed(pb::job_event::Failed {
            reason: "retry over".to_string(),
            byte_offset: 512,
            alarm_number: "SR0945".to_string(),
            code: pb::ErrorCode::LinkFailed as i32,
            bytes_on_line: 700,
            next_block: Some(pb::BlockPosition {
                line: 20,
                sequence_number: "N190".to_string(),
                byte_offset: 500,
            }),
        }));
        assert_eq!(
            job_kind_text(&f),
            "failed at byte 512: retry over [SR0945] (link failed); resumes at line 20 (N190)"
        );
        let j = job_event_json(&f);
        assert_eq!(j["failed"]["byte_offset"], 512);
        assert_eq!(j["failed"]["code"], "ERROR_CODE_LINK_FAILED");
        assert_eq!(j["failed"]["next_block"]["line"], 20);
    }

    #[test]
    fn di_is_shown_in_hex_and_bits() {
        let t = di_text(&pb::DiImage {
            machine: "mill-1".to_string(),
            value: 0x5A,
            unix_ms: 0,
        });
        assert!(t.starts_with("mill-1 DI 0x5A 0b01011010 (90)"), "{t}");
        assert!(t.contains("0 1 0 1 1 0 1 0"), "{t}");
    }

    #[test]
    fn watch_prints_a_status_only_when_its_headline_changes() {
        let mut p = WatchPrinter::new();
        let mut s = status();
        assert!(
            p.line(&WatchEvent::Status(Box::new(s.clone())), 0)
                .is_some()
        );
        s.counters.as_mut().unwrap().retries += 1;
        assert!(
            p.line(&WatchEvent::Status(Box::new(s.clone())), 0)
                .is_none()
        );
        s.do_image = Some(0);
        let line = p.line(&WatchEvent::Status(Box::new(s)), 0).unwrap();
        assert!(line.contains("DO 0x00"), "{line}");
        let link = WatchEvent::Link {
            machine: "mill-1".to_string(),
            up: false,
        };
        assert!(p.line(&link, 0).unwrap().ends_with("mill-1 link down"));
        assert_eq!(watch_json(&link, 5)["event"], "link_down");
        assert_eq!(watch_machine(&link), Some("mill-1"));
    }
}
