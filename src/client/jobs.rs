//! Jobs: submit, follow, the queue, cancel.

use std::time::Duration;

use prost::Message as _;
use zenoh::Session;
use zenoh::bytes::ZBytes;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::{Sample, SampleKind};

use super::{
    Client, ClientError, IO_TIMEOUT, SILENCE, SUBMIT_TIMEOUT, decode, decode_all, get_raw, render,
};
use crate::bus::keys::{CellKey, CellKeys, MachineLeaf, is_plain_chunk};
use crate::bus::payload::encoding;
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;

/// A new request id for a `JobRequest`: unique per process and moment.
pub fn new_request_id() -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNT: AtomicU64 = AtomicU64::new(0);
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    format!(
        "{nanos:x}-{:x}-{}",
        std::process::id(),
        COUNT.fetch_add(1, Ordering::Relaxed)
    )
}

impl Client {
    fn follower(
        &self,
        subscriber: zenoh::pubsub::Subscriber<
            zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>,
        >,
        gateway: Option<Subscriber<FifoChannelHandler<Sample>>>,
        machine: &str,
        job_id: &str,
    ) -> JobFollower {
        JobFollower {
            session: self.session.clone(),
            subscriber,
            gateway,
            keys: self.keys.clone(),
            machine: machine.to_string(),
            job_id: job_id.to_string(),
            ended: false,
            timeout: self.timeout,
        }
    }

    /// A subscriber of the gateway's liveliness token (`P/C/gateway`), standing token first:
    /// its withdrawal tells a follower at once that the gateway is gone. `None` (followed
    /// without it, as before) where it cannot be declared.
    async fn gateway_token(&self) -> Option<Subscriber<FifoChannelHandler<Sample>>> {
        let key = self.keys.gateway();
        match self
            .session
            .liveliness()
            .declare_subscriber(key.as_str())
            .history(true)
            .await
        {
            Ok(s) => Some(s),
            Err(e) => {
                tracing::debug!(%key, error = %e, "not watching the gateway's liveliness token");
                None
            }
        }
    }

    pub(crate) fn job_arg(job_id: &str) -> Result<(), ClientError> {
        if is_plain_chunk(job_id) {
            Ok(())
        } else {
            Err(ClientError::InvalidArgument {
                what: format!("job {job_id:?}"),
                reason: "name one job id as `submit` printed it, without wildcards".to_string(),
            })
        }
    }

    /// Cancels a job with a get on its cancel key and answers how it ended (its `cancelled`
    /// event, or the end it reached first), or its latest event if it has not ended within
    /// the gateway's wait.
    pub async fn cancel_confirmed(
        &self,
        machine: &str,
        job_id: &str,
    ) -> Result<pb::JobEvent, ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.job_cancel(machine, job_id);
        self.get_one(
            &format!("cancel of {job_id}"),
            &key,
            None,
            IO_TIMEOUT.max(Duration::from_secs(30)),
        )
        .await
    }

    /// Sends a job request to `machine` and returns its `JobAccepted` with a follower of its
    /// events.
    ///
    /// The job id is only known from the reply, so the follower subscribes to every job of
    /// the machine (`P/C/machine/M/job/*`) before the request goes out and keeps the events
    /// of this job. The subscription and the request travel in order on the one link to the
    /// gateway, which processes the subscription first: no event of the job is missed.
    pub async fn submit(
        &self,
        machine: &str,
        request: &pb::JobRequest,
    ) -> Result<(pb::JobAccepted, JobFollower), ClientError> {
        Self::machine_arg(machine)?;
        let what = format!("submit to {machine}");
        let events_key = self.keys.job_events(machine, "*");
        let subscriber = self.subscribe(&events_key).await?;
        let gateway = self.gateway_token().await;
        let key = self.keys.leaf(machine, MachineLeaf::Submit);
        let payload = (request.encode_to_vec(), encoding::<pb::JobRequest>());
        let accepted: pb::JobAccepted = match self
            .get_one(&what, &key, Some(payload), SUBMIT_TIMEOUT)
            .await
        {
            Ok(a) => a,
            Err(e) => {
                let _ = subscriber.undeclare().await;
                if let Some(g) = gateway {
                    let _ = g.undeclare().await;
                }
                return Err(e);
            }
        };
        let follower = self.follower(subscriber, gateway, machine, &accepted.job_id);
        Ok((accepted, follower))
    }

    /// Follows a job already submitted (e.g. by another client).
    pub async fn follow(&self, machine: &str, job_id: &str) -> Result<JobFollower, ClientError> {
        Self::machine_arg(machine)?;
        Self::job_arg(job_id)?;
        let events_key = self.keys.job_events(machine, job_id);
        let subscriber = self.subscribe(&events_key).await?;
        let gateway = self.gateway_token().await;
        Ok(self.follower(subscriber, gateway, machine, job_id))
    }

    /// The latest event of a job (the gateway keeps the last 256 jobs of each machine).
    pub async fn job_latest(
        &self,
        machine: &str,
        job_id: &str,
    ) -> Result<pb::JobEvent, ClientError> {
        Self::machine_arg(machine)?;
        Self::job_arg(job_id)?;
        let key = self.keys.job_events(machine, job_id);
        self.get_one(&format!("job {job_id}"), &key, None, self.timeout)
            .await
    }

    /// The last event of every job the gateway keeps (the latest 256 of each machine), of one
    /// machine or of all, oldest first.
    pub async fn recent_jobs(
        &self,
        machine: Option<&str>,
    ) -> Result<Vec<pb::JobEvent>, ClientError> {
        if let Some(m) = machine {
            Self::machine_arg(m)?;
        }
        let key = self.keys.job_events(machine.unwrap_or("*"), "*");
        let mut all: Vec<pb::JobEvent> = self
            .get_all("recent jobs", &key, None, self.timeout)
            .await?
            .into_iter()
            .map(|(_, e)| e)
            .collect();
        all.sort_by(|a, b| (a.unix_ms, &a.job_id).cmp(&(b.unix_ms, &b.job_id)));
        Ok(all)
    }

    /// The queue of one machine.
    pub async fn queue(&self, machine: &str) -> Result<pb::JobQueue, ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys.leaf(machine, MachineLeaf::Job);
        self.get_one(&format!("queue of {machine}"), &key, None, self.timeout)
            .await
    }

    /// Cancels a job (a delete on its key) and waits for it to end; returns its last event.
    /// A job that already ended is an error naming how it ended.
    pub async fn cancel(&self, machine: &str, job_id: &str) -> Result<pb::JobEvent, ClientError> {
        let latest = self.job_latest(machine, job_id).await?;
        if is_end(&latest) {
            return Err(ClientError::InvalidArgument {
                what: format!("cancel job {job_id}"),
                reason: format!("the job already ended: {}", render::job_kind_text(&latest)),
            });
        }
        let mut follower = self.follow(machine, job_id).await?;
        let key = self.keys.job_events(machine, job_id);
        let mut delete = self.session.delete(key.as_str());
        if let Some(origin) = &self.origin {
            delete = delete.attachment(ZBytes::from(origin.clone()));
        }
        let deleted = delete.await;
        if let Err(source) = deleted {
            follower.close().await;
            return Err(ClientError::Zenoh {
                what: format!("delete {key}"),
                source,
            });
        }
        let end = follower.wait_end().await;
        follower.close().await;
        end
    }
}

/// Whether a job event is the last of its job.
pub fn is_end(event: &pb::JobEvent) -> bool {
    matches!(
        event.kind,
        Some(Kind::Completed(_) | Kind::Failed(_) | Kind::Cancelled(_))
    )
}

/// How a job ended.
#[derive(Debug, Clone, PartialEq)]
pub enum JobOutcome {
    Completed(pb::job_event::Completed),
    Failed(pb::job_event::Failed),
    Cancelled(pb::job_event::Cancelled),
}

impl JobOutcome {
    /// The outcome a job's last event tells; `None` for an event that is not the last.
    pub fn of(event: &pb::JobEvent) -> Option<JobOutcome> {
        match &event.kind {
            Some(Kind::Completed(c)) => Some(JobOutcome::Completed(*c)),
            Some(Kind::Failed(f)) => Some(JobOutcome::Failed(f.clone())),
            Some(Kind::Cancelled(c)) => Some(JobOutcome::Cancelled(c.clone())),
            _ => None,
        }
    }

    /// 0 when the program was delivered, 1 otherwise.
    pub fn exit_code(&self) -> u8 {
        match self {
            JobOutcome::Completed(_) => 0,
            JobOutcome::Failed(_) | JobOutcome::Cancelled(_) => 1,
        }
    }
}

/// The events of one job, as [`Client::submit`] or [`Client::follow`] subscribed to them.
pub struct JobFollower {
    session: Session,
    subscriber: Subscriber<FifoChannelHandler<Sample>>,
    /// The gateway's liveliness token, when it could be watched.
    gateway: Option<Subscriber<FifoChannelHandler<Sample>>>,
    keys: CellKeys,
    machine: String,
    job_id: String,
    ended: bool,
    timeout: Duration,
}

impl JobFollower {
    pub fn job_id(&self) -> &str {
        &self.job_id
    }

    pub fn machine(&self) -> &str {
        &self.machine
    }

    /// The job's next event; `None` once its last event (completed, failed, cancelled) was
    /// returned. When the job stays silent for [`SILENCE`], the gateway is asked for its
    /// latest event, so an end is seen even if its publication was lost. When the gateway's
    /// liveliness token goes (it stopped, crashed, or cannot be reached), at once
    /// [`ClientError::GatewayGone`], rather than asking a gateway that is not there.
    pub async fn next(&mut self) -> Result<Option<pb::JobEvent>, ClientError> {
        if self.ended {
            return Ok(None);
        }
        loop {
            let got = tokio::select! {
                // An event already here (the end, published as the gateway stopped) first.
                biased;
                s = self.subscriber.recv_async() => Ok(s),
                () = gateway_gone(self.gateway.as_ref()) => {
                    return Err(ClientError::GatewayGone {
                        what: format!("following job {}", self.job_id),
                        key: self.keys.gateway(),
                        job: self.job_id.clone(),
                    });
                }
                () = tokio::time::sleep(SILENCE) => Err(()),
            };
            match got {
                Ok(Ok(sample)) => {
                    if let Some(event) = self.accept(&sample) {
                        self.ended = is_end(&event);
                        return Ok(Some(event));
                    }
                }
                Ok(Err(_)) => {
                    return Err(ClientError::Closed {
                        what: format!("following job {}", self.job_id),
                    });
                }
                Err(_) => match self.latest().await {
                    Ok(latest) if is_end(&latest) => {
                        self.ended = true;
                        return Ok(Some(latest));
                    }
                    Ok(_) => {}
                    // The question was only a check for a lost end: a gateway slow to answer
                    // it (or a reply lost on the way) is no reason to stop following a job
                    // whose events still come.
                    Err(e @ ClientError::NoAnswer { .. }) => {
                        tracing::debug!(error = %e, "the job's latest event did not come; following on");
                    }
                    Err(e) => return Err(e),
                },
            }
        }
    }

    /// Reads events until the job ends; returns the last one.
    pub async fn wait_end(&mut self) -> Result<pb::JobEvent, ClientError> {
        let mut last = None;
        while let Some(event) = self.next().await? {
            last = Some(event);
        }
        last.ok_or_else(|| ClientError::Closed {
            what: format!("following job {}", self.job_id),
        })
    }

    /// This job's event in a sample of `P/C/machine/M/job/*`, if it is one.
    fn accept(&self, sample: &Sample) -> Option<pb::JobEvent> {
        if sample.kind() != SampleKind::Put {
            return None; // a cancel request
        }
        match self.keys.parse(sample.key_expr().as_str()) {
            Some(CellKey::JobEvents { job, .. }) if job == self.job_id => {}
            _ => return None,
        }
        let event = decode::<pb::JobEvent>(
            "job event",
            sample.key_expr().as_str(),
            &sample.payload().to_bytes(),
            sample.encoding(),
        );
        match event {
            Ok(e) if e.job_id == self.job_id => Some(e),
            Ok(_) => None,
            Err(e) => {
                tracing::warn!(error = %e, "job event skipped");
                None
            }
        }
    }

    async fn latest(&self) -> Result<pb::JobEvent, ClientError> {
        let key = self.keys.job_events(&self.machine, &self.job_id);
        let what = format!("job {}", self.job_id);
        let replies = get_raw(&self.session, &what, &key, None, self.timeout, None).await?;
        decode_all::<pb::JobEvent>(&what, replies)?
            .into_iter()
            .map(|(_, e)| e)
            .find(|e| e.job_id == self.job_id)
            .ok_or(ClientError::NoAnswer {
                what,
                key,
                timeout: self.timeout,
            })
    }

    /// Undeclares the subscriptions.
    pub async fn close(self) {
        if let Err(e) = self.subscriber.undeclare().await {
            tracing::debug!(error = %e, "undeclaring the job subscriber");
        }
        if let Some(g) = self.gateway
            && let Err(e) = g.undeclare().await
        {
            tracing::debug!(error = %e, "undeclaring the gateway's token subscriber");
        }
    }
}

/// Completes when the gateway's liveliness token is withdrawn; never without one to watch.
async fn gateway_gone(tokens: Option<&Subscriber<FifoChannelHandler<Sample>>>) {
    let Some(tokens) = tokens else {
        return std::future::pending().await;
    };
    loop {
        match tokens.recv_async().await {
            Ok(s) if s.kind() == SampleKind::Delete => {
                // A token that comes straight back (a link to the gateway re-made under load)
                // is no gateway gone: gone is a token still missing after a moment.
                let back = tokio::time::timeout(GONE_GRACE, async {
                    loop {
                        match tokens.recv_async().await {
                            Ok(s) if s.kind() == SampleKind::Put => return true,
                            Ok(_) => {}
                            Err(_) => return false,
                        }
                    }
                })
                .await;
                if back != Ok(true) {
                    return;
                }
            }
            Ok(_) => {}
            // The session closed: the job subscriber says so.
            Err(_) => return std::future::pending().await,
        }
    }
}

/// How long the gateway's liveliness token may be missing before a follower says it is gone.
const GONE_GRACE: std::time::Duration = std::time::Duration::from_millis(1500);

/// The machine a job id names: ids are `M-<run>-<n>` (`mill-1-tpfqpi-3`), and a machine's
/// name may itself hold `-`. `None` for a text that is not such an id.
pub fn machine_of_job(job_id: &str) -> Option<&str> {
    let mut parts = job_id.rsplitn(3, '-');
    let n = parts.next()?;
    let run = parts.next()?;
    let machine = parts.next()?;
    let numbered = !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit());
    let stamped = !run.is_empty() && run.bytes().all(|b| b.is_ascii_alphanumeric());
    (numbered && stamped && !machine.is_empty()).then_some(machine)
}
