//! What the link reports about the job on it, one method per event: the job's clock and
//! `started`, its progress (and the journal's checkpoint), and how it ended.

use std::sync::Arc;
use std::time::Duration;

use prost::Message as _;
use tokio::time::Instant;

use super::progress::ProgressShaper;
use super::{End, Manager, published_bytes};
use crate::link::JobId;
use crate::link::driver::{JobFailure, LinkEvent};
use cellgate_core::codes::BusCode as _;
use cellgate_core::fanuc::host::Confirmation;
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;

impl Manager {
    pub(super) async fn on_link_event(&mut self, event: LinkEvent) {
        match event {
            LinkEvent::Stopped { error } => {
                let why = match error {
                    Some(e) => format!("the link stopped: {e}"),
                    None => "the link stopped".to_string(),
                };
                self.link_gone(&why).await;
            }
            LinkEvent::Alarm(alarm) => {
                if let Some(active) = self.active.as_mut() {
                    active.alarm = alarm.cnc_alarm().or(active.alarm);
                }
            }
            LinkEvent::CncReset => {
                if let Some(active) = self.active.as_mut() {
                    active.cnc_reset = true;
                }
            }
            LinkEvent::Waiting {
                what,
                since_unix_ms,
            } => {
                self.link_waiting = what.map(|w| (w, since_unix_ms));
            }
            LinkEvent::JobStarted { job } => self.job_started(job),
            LinkEvent::Progress {
                job,
                acked,
                sent,
                block,
                ..
            } => self.job_progress(job, acked, sent, block),
            LinkEvent::JobDone {
                job,
                bytes,
                confirmation,
                block,
            } => self.job_done(job, bytes, confirmation, block),
            LinkEvent::JobFailed {
                job,
                offset,
                sent,
                reason,
            } => self.job_failed(job, offset, sent, reason).await,
            LinkEvent::JobCancelled { job, offset, sent } => {
                self.job_cancelled(job, offset, sent).await;
            }
            _ => {}
        }
    }

    /// The link began sending the job: its clock, its deadline, and `started`.
    fn job_started(&mut self, job: JobId) {
        let Some(active) = self.active_for(job) else {
            return;
        };
        let now = Instant::now();
        active.started_at = Some(now);
        if active.record.deadline_s > 0 {
            active.deadline = Some(now + Duration::from_secs(u64::from(active.record.deadline_s)));
        }
        active.shaper = ProgressShaper::new(now, Some(active.record.stream_size()));
        active.record.origin.started_unix_ms = pb::now_ms();
        let (id, size) = (active.record.id.clone(), active.record.stream_size());
        let origin = active.record.origin_pb();
        tracing::info!(job = %id, "job started");
        self.trace_started(&id);
        let event = self.emit(
            &id,
            Kind::Started(pb::job_event::Started {
                bytes_total: Some(size),
            }),
            Some(origin),
        );
        if let Some(active) = self.active.as_mut() {
            active.record.last_event = event.encode_to_vec();
        }
    }

    /// Bytes acknowledged and on the line: a `progress` event at most every
    /// [`PROGRESS_MIN_INTERVAL`], and the journal's checkpoint.
    fn job_progress(&mut self, job: JobId, acked: u64, sent: u64, block: Option<Arc<str>>) {
        let Some(active) = self.active_for(job) else {
            return;
        };
        let published = published_bytes(active);
        active.acked = acked.max(active.acked);
        active.sent = sent.max(active.sent);
        if block.is_some() {
            active.block = block;
        }
        let Some(rate) = active
            .shaper
            .offer(Instant::now(), active.acked, active.sent)
        else {
            return;
        };
        let (id, acked, sent, size) = (
            active.record.id.clone(),
            active.acked,
            active.sent,
            active.record.stream_size(),
        );
        let block = active.block.as_deref().unwrap_or_default().to_string();
        self.totals.nc_bytes_sent += acked.saturating_sub(published);
        let event = self.emit(
            &id,
            Kind::Progress(pb::job_event::Progress {
                bytes_sent: acked,
                bytes_total: Some(size),
                rate_bps: rate,
                bytes_on_line: sent,
                block,
            }),
            None,
        );
        if let Some(active) = self.active.as_mut() {
            active.published_block.clone_from(&active.block);
            // The acknowledged offset survives a crash once the checkpoint is written.
            active.record.acked = acked;
            active.record.last_event = event.encode_to_vec();
            // Held, and written with the cell's next commit, at least once a second
            // (`put_progress`).
            if let Err(e) = self.journal.put_progress(&active.record) {
                tracing::error!(job = %active.record.id, error = %e, "job journal write failed");
            }
        }
    }

    /// The protocol confirmed the whole program: `completed`.
    fn job_done(
        &mut self,
        job: JobId,
        bytes: u64,
        confirmation: Confirmation,
        block: Option<Arc<str>>,
    ) {
        if self.active_for(job).is_none() {
            return;
        }
        // The last block, if the progress has not said it yet: the block being fed reaches
        // the program's end before `completed`.
        if let Some(active) = self.active.as_ref()
            && block.is_some()
            && block != active.published_block
        {
            let (id, size, rate) = (
                active.record.id.clone(),
                active.record.stream_size(),
                active.shaper.last_rate,
            );
            let block = block.as_deref().unwrap_or_default().to_string();
            self.emit(
                &id,
                Kind::Progress(pb::job_event::Progress {
                    bytes_sent: bytes,
                    bytes_total: Some(size),
                    rate_bps: rate,
                    bytes_on_line: bytes,
                    block,
                }),
                None,
            );
        }
        let Some(active) = self.active.take() else {
            return;
        };
        let since = active.started_at.unwrap_or(active.handed_at);
        let duration = Instant::now().saturating_duration_since(since);
        self.totals.jobs_completed += 1;
        self.totals.nc_bytes_sent += bytes.saturating_sub(published_bytes(&active));
        tracing::info!(job = %active.record.id, bytes, ?confirmation, "job completed");
        // The link stops at EOR (§8.2): what follows it in the program (a line end
        // after the last `%`) is never sent.
        let after_eor = active.record.stream_size().saturating_sub(bytes);
        let end = End::Completed {
            bytes,
            duration_ms: u64::try_from(duration.as_millis()).unwrap_or(u64::MAX),
            confirmation,
            after_eor,
        };
        self.end(active.record, end, bytes, bytes, None);
    }

    /// The link gave the job up: failed, or cancelled when a reset or a request was behind
    /// it, and where it may resume.
    async fn job_failed(&mut self, job: JobId, offset: u64, sent: u64, reason: JobFailure) {
        if self.active_for(job).is_none() {
            return;
        }
        let Some(active) = self.active.take() else {
            return;
        };
        self.totals.nc_bytes_sent += offset.saturating_sub(published_bytes(&active));
        let next = self.resume_point(&active, offset, sent).await;
        if active.deadline_passed {
            self.totals.jobs_failed += 1;
            let end = End::Failed {
                reason: self.deadline_reason(active.record.deadline_s),
                alarm: active.alarm,
                code: pb::ErrorCode::DeadlineExceeded,
            };
            self.end(active.record, end, offset, sent, next);
            return;
        }
        let reset = matches!(&reason, JobFailure::Aborted(r) if r.is_reset());
        if active.cnc_reset || reset || active.cancel_requested {
            // A CNC reset abandons the program: the proto counts that as a
            // cancellation, as it does one the request asked for.
            let by = if active.cancel_requested {
                "request"
            } else {
                "cnc reset"
            };
            self.end(active.record, End::Cancelled { by }, offset, sent, next);
            return;
        }
        self.totals.jobs_failed += 1;
        tracing::warn!(job = %active.record.id, offset, %reason, "job failed");
        let end = End::Failed {
            reason: reason.to_string(),
            alarm: active.alarm.or(reason.cnc_alarm()),
            code: reason.code(),
        };
        self.end(active.record, end, offset, sent, next);
    }

    /// The link dropped the job: by request, by a CNC reset, or by itself; a passed deadline
    /// makes it a failure.
    async fn job_cancelled(&mut self, job: JobId, offset: u64, sent: u64) {
        if self.active_for(job).is_none() {
            // A waiting job is never on the link, so this is one the link dropped
            // by itself; nothing of ours.
            return;
        }
        let Some(active) = self.active.take() else {
            return;
        };
        self.totals.nc_bytes_sent += offset.saturating_sub(published_bytes(&active));
        if active.deadline_passed {
            let next = self.next_block(&active.record, offset).await;
            self.totals.jobs_failed += 1;
            tracing::warn!(job = %active.record.id, offset, "job failed: deadline passed");
            let end = End::Failed {
                reason: self.deadline_reason(active.record.deadline_s),
                alarm: active.alarm,
                code: pb::ErrorCode::DeadlineExceeded,
            };
            self.end(active.record, end, offset, sent, next);
            return;
        }
        let by = if active.cancel_requested {
            "request"
        } else if active.cnc_reset {
            "cnc reset"
        } else {
            "link"
        };
        tracing::info!(job = %active.record.id, offset, by, "job cancelled");
        let next = self.resume_point(&active, offset, sent).await;
        self.end(active.record, End::Cancelled { by }, offset, sent, next);
    }
}
