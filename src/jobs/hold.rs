//! A machine's jobs when a reload takes its link away (docs/configuration.md, "Reloading"):
//! held, the manager hands the link no further job, so that the link can stop or restart once
//! the job it is sending has ended; the waiting jobs stay in the journal, where the manager of
//! the restarted link finds them. A machine leaving the cell also has its waiting jobs
//! cancelled and new ones refused; a forced reload fails the job being sent at once.

use std::time::Duration;

use tokio::sync::oneshot;

use super::{End, JobError, JobsHandle, Manager, Request, published_bytes};
use crate::link::driver::LinkCommand;
use cellgate_core::codes::BusCode;
use cellgate_core::pb;

/// What a reload does to a machine's jobs before its link stops or restarts.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Hold {
    /// Fail the job being sent at once with this reason (a forced reload).
    pub fail_active: Option<String>,
    /// The machine leaves the cell: its waiting jobs are cancelled (by `reload`) and a new
    /// one is refused with this reason. Without it, waiting and new jobs stay queued for the
    /// link that follows.
    pub retire: Option<String>,
}

impl JobsHandle {
    /// Holds the machine's jobs as `hold` says; answered once the manager has done it (a job
    /// failed by it has its end out).
    pub async fn hold(&self, hold: Hold) -> Result<(), JobError> {
        let (reply, answer) = oneshot::channel();
        self.requests
            .send(Request::Hold { hold, reply })
            .await
            .map_err(|_| self.stopped())?;
        answer.await.map_err(|_| self.stopped())
    }

    /// Lets the link take jobs again (a later reload gave the machine its entry back).
    pub async fn release(&self) -> Result<(), JobError> {
        let (reply, answer) = oneshot::channel();
        self.requests
            .send(Request::Release { reply })
            .await
            .map_err(|_| self.stopped())?;
        answer.await.map_err(|_| self.stopped())
    }
}

impl Manager {
    pub(super) async fn on_hold(&mut self, hold: Hold) {
        self.held = true;
        if let Some(why) = hold.retire {
            while let Some(job) = self.waiting.pop() {
                tracing::info!(job = %job.id, "waiting job cancelled: the machine leaves the cell");
                self.end(job, End::Cancelled { by: "reload" }, 0, 0, None);
            }
            self.retired = Some(why);
        }
        if let Some(reason) = hold.fail_active
            && let Some(active) = self.active.take()
        {
            // Best effort: the link stops or restarts right after.
            let cancel = self.link.send(LinkCommand::Cancel(active.link_id));
            let _ = tokio::time::timeout(Duration::from_millis(100), cancel).await;
            self.totals.nc_bytes_sent += active.acked.saturating_sub(published_bytes(&active));
            let next = self.resume_point(&active, active.acked, active.sent).await;
            self.totals.jobs_failed += 1;
            tracing::warn!(job = %active.record.id, %reason, "job failed by a forced reload");
            let end = End::Failed {
                reason,
                alarm: active.alarm,
                code: pb::ErrorCode::Unavailable,
            };
            self.end(active.record, end, active.acked, active.sent, next);
        }
        self.publish_snapshot();
    }

    pub(super) fn on_release(&mut self) {
        self.held = false;
        self.retired = None;
    }

    /// Why a new job is refused: the machine is leaving the cell.
    pub(super) fn retired_error(&self) -> Option<JobError> {
        self.retired.as_ref().map(|why| JobError::Retired {
            machine: self.machine.to_string(),
            why: why.clone(),
        })
    }
}

/// The run stamp of job ids: seconds since the Unix epoch in base 36.
pub(super) fn base36(mut n: u64) -> String {
    const DIGITS: &[u8; 36] = b"0123456789abcdefghijklmnopqrstuvwxyz";
    let mut out = Vec::new();
    loop {
        out.push(DIGITS[(n % 36) as usize]);
        n /= 36;
        if n == 0 {
            break;
        }
    }
    out.reverse();
    String::from_utf8(out).unwrap_or_default()
}

impl BusCode for JobError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            JobError::Program { .. }
            | JobError::RequestId { .. }
            | JobError::Start { .. }
            | JobError::NotResumable { .. }
            | JobError::RevisionWithoutLibrary { .. } => pb::ErrorCode::InvalidRequest,
            JobError::OnlyReleased { .. } => pb::ErrorCode::NotReleased,
            JobError::Journal { error, .. } if error.is_storage_full() => {
                pb::ErrorCode::StorageFull
            }
            JobError::Journal { .. } => pb::ErrorCode::StorageFailed,
            JobError::Library { error, .. } => error.code(),
            JobError::QueueFull { .. } => pb::ErrorCode::QueueFull,
            JobError::UnknownJob { .. } => pb::ErrorCode::NotFound,
            JobError::LinkStopped { .. } | JobError::Stopped { .. } | JobError::Retired { .. } => {
                pb::ErrorCode::Unavailable
            }
        }
    }
}
