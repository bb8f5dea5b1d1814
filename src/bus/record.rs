//! What a machine's task records in the cell's history: a job once it ended, alarms, the
//! link's state and what the CNC is doing when they change. (A G05 stream is recorded by its
//! route once it is over: `route_g05`.)

use cellgate_core::history::activity;
use cellgate_core::pb::{self, HistoryKind, history_record::Record, job_event::Kind};

use crate::history::History;

/// A finished job as the history keeps it; `None` for an event that does not end a job.
pub(crate) fn job_history(event: &pb::JobEvent) -> Option<pb::JobHistory> {
    let origin = event.origin.clone().unwrap_or_default();
    let mut h = pb::JobHistory {
        job_id: event.job_id.clone(),
        ended_unix_ms: event.unix_ms,
        ..Default::default()
    };
    match event.kind.as_ref()? {
        Kind::Completed(c) => {
            h.outcome = pb::JobOutcome::Completed as i32;
            h.bytes_sent = c.bytes_sent;
            h.bytes_total = c.bytes_sent;
        }
        Kind::Failed(f) => {
            h.outcome = pb::JobOutcome::Failed as i32;
            h.bytes_sent = f.byte_offset;
            h.reason = f.reason.clone();
            h.code = f.code;
            h.alarm_number = f.alarm_number.clone();
        }
        Kind::Cancelled(c) => {
            h.outcome = pb::JobOutcome::Cancelled as i32;
            h.bytes_sent = c.byte_offset;
            h.reason = if c.by.is_empty() {
                "cancelled".to_string()
            } else {
                format!("cancelled by {}", c.by)
            };
        }
        Kind::Queued(_) | Kind::Started(_) | Kind::Progress(_) => return None,
    }
    h.origin = Some(origin);
    Some(h)
}

/// A finished job's last event, told again from its history record (`machine`'s), for a job
/// the machine no longer keeps.
pub(crate) fn job_event_from_history(machine: &str, h: pb::JobHistory) -> pb::JobEvent {
    let kind = match h.outcome() {
        pb::JobOutcome::Completed => Kind::Completed(pb::job_event::Completed {
            bytes_sent: h.bytes_sent,
            duration_ms: h.origin.as_ref().map_or(0, |o| {
                h.ended_unix_ms
                    .saturating_sub(o.started_unix_ms.max(o.queued_unix_ms))
            }),
            ..Default::default()
        }),
        pb::JobOutcome::Cancelled => Kind::Cancelled(pb::job_event::Cancelled {
            byte_offset: h.bytes_sent,
            by: h
                .reason
                .strip_prefix("cancelled by ")
                .unwrap_or_default()
                .to_string(),
            ..Default::default()
        }),
        pb::JobOutcome::Failed | pb::JobOutcome::Unspecified => {
            Kind::Failed(pb::job_event::Failed {
                reason: h.reason.clone(),
                byte_offset: h.bytes_sent,
                alarm_number: h.alarm_number.clone(),
                code: h.code,
                ..Default::default()
            })
        }
    };
    pb::JobEvent {
        job_id: h.job_id,
        machine: machine.to_string(),
        unix_ms: h.ended_unix_ms,
        origin: h.origin,
        kind: Some(kind),
    }
}

/// The last states recorded of one machine, so that only changes are recorded.
#[derive(Debug, Default)]
pub(crate) struct Recorder {
    link: Option<i32>,
    activity: Option<i32>,
    /// Job sizes seen in `started` events, for the record of their end.
    totals: std::collections::HashMap<String, u64>,
}

impl Recorder {
    /// Records what changed in `status`.
    pub(super) fn status(&mut self, history: &History, machine: &str, status: &pb::MachineStatus) {
        if !history.enabled() {
            return;
        }
        if self.link != Some(status.link_state) {
            self.link = Some(status.link_state);
            history.event(machine, HistoryKind::Link, Record::Link(status.link_state));
        }
        let a = activity(status) as i32;
        if self.activity != Some(a) {
            self.activity = Some(a);
            history.event(machine, HistoryKind::Cnc, Record::Cnc(a));
        }
    }

    /// Records a job that ended.
    pub(super) fn job(&mut self, history: &History, machine: &str, event: &pb::JobEvent) {
        if !history.enabled() {
            return;
        }
        // The size is known from acceptance (`queued`), so a job that ends before it
        // starts keeps it too; `started` says it again.
        let total = match &event.kind {
            Some(Kind::Queued(q)) => Some(q.bytes_total),
            Some(Kind::Started(s)) => Some(s.bytes_total),
            _ => None,
        };
        if let Some(total) = total {
            if let Some(t) = total {
                self.totals.insert(event.job_id.clone(), t);
            }
            return;
        }
        if let Some(mut h) = job_history(event) {
            if let Some(total) = self.totals.remove(&event.job_id) {
                h.bytes_total = total;
            }
            history.event(machine, HistoryKind::Job, Record::Job(h));
        }
    }

    /// Records an alarm.
    pub(super) fn alarm(history: &History, machine: &str, alarm: &pb::AlarmEvent) {
        history.event(machine, HistoryKind::Alarm, Record::Alarm(alarm.clone()));
    }

    /// Records a punched program without its text: the library keeps that under its
    /// `library_name`, and a record stays small.
    pub(super) fn punch(history: &History, machine: &str, punched: &pb::PunchedProgram) {
        let record = pb::PunchedProgram {
            program: Vec::new(),
            ..punched.clone()
        };
        history.event(machine, HistoryKind::Punch, Record::Punch(record));
    }
}

#[cfg(test)]
mod tests;
