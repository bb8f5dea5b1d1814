//! The published progress of a job: the link's reports shaped into events a client can
//! follow (see the module documentation of [`crate::jobs`]).

use tokio::time::Instant;

use super::PROGRESS_MIN_INTERVAL;

/// Shapes the link's progress reports into the published stream (see the module
/// documentation).
#[derive(Debug, Clone)]
pub struct ProgressShaper {
    total: Option<u64>,
    last_at: Instant,
    pub(super) last_acked: u64,
    last_sent: u64,
    /// The rate the last published event carried.
    pub(super) last_rate: u64,
}

impl ProgressShaper {
    /// A transfer of `total` bytes (if known) that started at `now`.
    pub fn new(now: Instant, total: Option<u64>) -> Self {
        ProgressShaper {
            total,
            last_at: now,
            last_acked: 0,
            last_sent: 0,
            last_rate: 0,
        }
    }

    /// The link reports `acked` bytes acknowledged and `sent` handed to the line at `now`;
    /// returns the rate in bytes/s (of bytes handed out) since the last published event
    /// when this one is to be published: once either figure reached a further whole percent
    /// (any further byte when the size is unknown), and no sooner than
    /// [`PROGRESS_MIN_INTERVAL`] after the last.
    pub fn offer(&mut self, now: Instant, acked: u64, sent: u64) -> Option<u64> {
        let elapsed = now.saturating_duration_since(self.last_at);
        if elapsed < PROGRESS_MIN_INTERVAL || (acked <= self.last_acked && sent <= self.last_sent) {
            return None;
        }
        if let Some(total) = self.total.filter(|&t| t > 0) {
            let percent = |b: u64| u128::from(b) * 100 / u128::from(total);
            if percent(acked) <= percent(self.last_acked)
                && percent(sent) <= percent(self.last_sent)
            {
                return None;
            }
        }
        let bytes = sent.saturating_sub(self.last_sent);
        let ms = elapsed.as_millis().max(1);
        let rate = u64::try_from(u128::from(bytes) * 1000 / ms).unwrap_or(u64::MAX);
        self.last_at = now;
        self.last_acked = acked.max(self.last_acked);
        self.last_sent = sent.max(self.last_sent);
        self.last_rate = rate;
        Some(rate)
    }
}
