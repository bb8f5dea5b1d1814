//! `cellgate jobs`, `cellgate job` and `cellgate cancel`.

use clap::Args;

use super::{ClientCommand, ConnectArgs, EXIT_INTERRUPTED, Io};
use crate::client::{Client, ClientError, JobOutcome, render};
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;

/// `cellgate jobs`.
#[derive(Debug, Clone, Args)]
pub struct JobsArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// One machine; default every machine of the cell.
    #[arg(value_name = "MACHINE")]
    pub machine: Option<String>,
    /// Also the jobs that ended (the gateway keeps the latest 256 of each machine), with how
    /// each ended.
    #[arg(long)]
    pub all: bool,
    /// Print JSON (an array of each machine's queue: active, waiting; with --all, ended: the
    /// last event of each ended job).
    #[arg(long)]
    pub json: bool,
}

impl ClientCommand for JobsArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        // One machine: its queue (the gateway names the cell's machines if it is none of
        // them); all: the machines the status names.
        let machines: Vec<String> = match &self.machine {
            Some(m) => vec![m.clone()],
            None => client
                .status(None)
                .await?
                .into_iter()
                .map(|s| s.machine)
                .collect(),
        };
        let mut queues = Vec::new();
        for m in &machines {
            queues.push(client.queue(m).await?);
        }
        let ended: Vec<pb::JobEvent> = if self.all {
            client
                .recent_jobs(self.machine.as_deref())
                .await?
                .into_iter()
                .filter(crate::client::is_end)
                .collect()
        } else {
            Vec::new()
        };
        if self.json {
            let all: Vec<serde_json::Value> = queues
                .iter()
                .map(|q| {
                    let mut v = render::queue_json(q);
                    if self.all {
                        v["ended"] = ended
                            .iter()
                            .filter(|e| e.machine == q.machine)
                            .map(render::job_event_json)
                            .collect();
                    }
                    v
                })
                .collect();
            let text = serde_json::to_string_pretty(&all).unwrap_or_default();
            let _ = writeln!(io.out, "{text}");
        } else {
            let _ = write!(io.out, "{}", render::queue_table(&queues, &ended));
        }
        Ok(0)
    }
}

/// `cellgate job`.
#[derive(Debug, Clone, Args)]
pub struct JobArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The job id `submit` printed; it names the machine (`mill-1-tpfqpi-3` runs on mill-1).
    #[arg(value_name = "JOB_ID")]
    pub job_id: String,
    /// Follow the job's events until it ends; the exit code is then the job's (0 completed,
    /// 1 failed or cancelled), as for `submit`.
    #[arg(long)]
    pub follow: bool,
    /// Print JSON (the job's latest event; with --follow, each event a line).
    #[arg(long)]
    pub json: bool,
}

impl JobArgs {
    fn show(&self, io: &mut Io<'_>, e: &pb::JobEvent) {
        if self.json {
            let _ = writeln!(io.out, "{}", render::job_event_json(e));
        } else {
            let _ = writeln!(
                io.out,
                "{} {} on {}: {}",
                render::clock(e.unix_ms),
                e.job_id,
                e.machine,
                render::job_kind_text(e)
            );
        }
        let _ = io.out.flush();
    }
}

impl ClientCommand for JobArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        let (machine, job) = job_target(&self.job_id, None)?;
        if !self.follow {
            let latest = client.job_latest(&machine, &job).await?;
            self.show(io, &latest);
            return Ok(0);
        }
        // Subscribed before the latest event is asked for, so that nothing falls between.
        let mut follower = client.follow(&machine, &job).await?;
        let mut last = match client.job_latest(&machine, &job).await {
            Ok(e) => e,
            Err(e) => {
                follower.close().await;
                return Err(e);
            }
        };
        self.show(io, &last);
        let interrupt = tokio::signal::ctrl_c();
        tokio::pin!(interrupt);
        while !crate::client::is_end(&last) {
            let next = tokio::select! {
                e = follower.next() => e,
                _ = &mut interrupt => break,
            };
            match next {
                Ok(Some(e)) => {
                    // Progress comes four times a second; as text, the steps are enough.
                    if self.json || !matches!(e.kind, Some(Kind::Progress(_))) {
                        self.show(io, &e);
                    }
                    last = e;
                }
                Ok(None) => break,
                Err(e) => {
                    follower.close().await;
                    return Err(e);
                }
            }
        }
        follower.close().await;
        Ok(JobOutcome::of(&last).map_or(EXIT_INTERRUPTED, |o| o.exit_code()))
    }
}

/// `cellgate cancel`.
#[derive(Debug, Clone, Args)]
pub struct CancelArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The job id `submit` printed; it names the machine (`mill-1-tpfqpi-3` runs on mill-1).
    #[arg(value_name = "JOB_ID")]
    pub job_id: String,
    /// The job id, after a machine: the older form `cancel MACHINE JOB_ID`.
    #[arg(value_name = "JOB", hide = true)]
    pub legacy_job_id: Option<String>,
    /// Print JSON (the job's last event) instead of text.
    #[arg(long)]
    pub json: bool,
}

/// The machine and job a job id names (`JOB_ID`, or the older `MACHINE JOB_ID`).
pub fn job_target(first: &str, second: Option<&str>) -> Result<(String, String), ClientError> {
    if let Some(job) = second {
        return Ok((first.to_string(), job.to_string()));
    }
    match crate::client::machine_of_job(first) {
        Some(machine) => Ok((machine.to_string(), first.to_string())),
        None => Err(ClientError::InvalidArgument {
            what: format!("job {first:?}"),
            reason: "not a job id: ids are MACHINE-RUN-N, as `submit` prints them \
                     (e.g. mill-1-tpfqpi-3)"
                .to_string(),
        }),
    }
}

impl ClientCommand for CancelArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        let (machine, job) = job_target(&self.job_id, self.legacy_job_id.as_deref())?;
        let last = client.cancel(&machine, &job).await?;
        if self.json {
            let _ = writeln!(io.out, "{}", render::job_event_json(&last));
        }
        let _ = writeln!(io.err, "{}: {}", last.job_id, render::job_kind_text(&last));
        Ok(match JobOutcome::of(&last) {
            Some(JobOutcome::Cancelled(_)) => 0,
            _ => 1,
        })
    }
}
