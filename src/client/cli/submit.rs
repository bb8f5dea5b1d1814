//! `cellgate submit`: a job, its progress, and how it ended.

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use super::{ClientCommand, ConnectArgs, EXIT_INTERRUPTED, INLINE_HINT, Io};
use crate::client::{Client, ClientError, JobOutcome, render};
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;

/// `cellgate submit`.
#[derive(Debug, Clone, Args)]
#[command(
    override_usage = "cellgate submit [OPTIONS] <MACHINE> <FILE|--library <NAME>|--key <KEY>>\n       cellgate submit [OPTIONS] [MACHINE] --resume <JOB_ID>"
)]
#[command(group(
    clap::ArgGroup::new("source")
        .required(true)
        .args(["file", "library", "key", "resume"])
))]
pub struct SubmitArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The machine to send the program to (its name in the cell file). With --resume it may
    /// be left out: the job id names its machine, as for `cancel` and `job`.
    #[arg(value_name = "MACHINE", required_unless_present = "resume")]
    pub machine: Option<String>,
    /// The program file. It is sent inline, in one message, so it is held whole in memory;
    /// for large programs put it in the library first (`cellgate program put`) and use
    /// --library.
    #[arg(value_name = "FILE")]
    pub file: Option<PathBuf>,
    /// A program of the gateway's library instead of a file.
    #[arg(long, value_name = "NAME")]
    pub library: Option<String>,
    /// With --library: the revision to send, by number or SHA-256 (default: the latest; a
    /// machine with `accept = "released"` takes only released ones).
    #[arg(long, value_name = "REV", requires = "library")]
    pub revision: Option<String>,
    /// A zenoh key the gateway fetches the program from (one get), instead of a file.
    #[arg(long, value_name = "KEY")]
    pub key: Option<String>,
    /// Higher runs first; equal priorities run in arrival order.
    #[arg(long, default_value_t = 0, allow_negative_numbers = true)]
    pub priority: i32,
    /// The name shown in status and events (default: derived by the gateway from the
    /// library name, the key or the program's O-number).
    #[arg(long, value_name = "DISPLAY")]
    pub name: Option<String>,
    /// Append the EOR code `%` if the program does not end with one (§4.4.2).
    #[arg(long)]
    pub append_eor: bool,
    /// Print the job id once accepted and return, without following the job.
    #[arg(long)]
    pub detach: bool,
    /// Send the program of an earlier job that failed or was cancelled again, from the
    /// first block the board did not acknowledge whole, with the program's header first.
    #[arg(long, value_name = "JOB_ID")]
    pub resume: Option<String>,
    /// Start at a block: `N1234` (its sequence number) or a line number; the program's
    /// header (its lines before the first numbered block) goes first.
    #[arg(long, value_name = "BLOCK")]
    pub from_block: Option<String>,
    /// Lines of the program's start that make its header (default: up to its first
    /// numbered block).
    #[arg(long, value_name = "LINES")]
    pub header_lines: Option<u32>,
    /// If the gateway restarts while sending this job, resume it from the first block the
    /// board did not acknowledge whole instead of failing it.
    #[arg(long)]
    pub resume_after_restart: bool,
    /// Fail the job if it has not completed this many seconds after it started (a CNC that
    /// never asks for data): it fails at what the board acknowledged (default: no
    /// deadline).
    #[arg(long, value_name = "SECS")]
    pub deadline: Option<u32>,
    /// The request id that makes the submit idempotent (default: a new one for each run):
    /// a retry with the same id queues nothing twice.
    #[arg(long, value_name = "ID")]
    pub request_id: Option<String>,
    /// Print JSON on stdout: the acceptance (job_id, queue_position), then the job's last
    /// event, one object a line, instead of the job id.
    #[arg(long)]
    pub json: bool,
}

/// `N1234` or `1234` → the block, by sequence number or line.
fn parse_block(text: &str) -> Result<pb::block_start::At, ClientError> {
    let bad = || ClientError::InvalidArgument {
        what: format!("--from-block {text}"),
        reason: "give N and a sequence number (N1234) or a line number (57)".to_string(),
    };
    match text.strip_prefix(['N', 'n']) {
        Some(digits) => digits
            .parse()
            .map(pb::block_start::At::SequenceNumber)
            .map_err(|_| bad()),
        None => text
            .parse()
            .map(pb::block_start::At::Line)
            .map_err(|_| bad()),
    }
}

impl SubmitArgs {
    /// The machine named, or the one the job to resume names.
    fn machine(&self) -> Result<String, ClientError> {
        match (&self.machine, &self.resume) {
            (Some(m), _) => Ok(m.clone()),
            (None, Some(job)) => crate::client::machine_of_job(job)
                .map(str::to_string)
                .ok_or_else(|| ClientError::InvalidArgument {
                    what: format!("--resume {job:?}"),
                    reason: "not a job id as `submit` printed it (MACHINE-RUN-N); name the \
                             machine too"
                        .to_string(),
                }),
            (None, None) => Err(ClientError::InvalidArgument {
                what: "MACHINE".to_string(),
                reason: "name the machine to send the program to".to_string(),
            }),
        }
    }

    /// The `JobRequest` these arguments make (reads FILE).
    pub async fn request(&self, io: &mut Io<'_>) -> Result<pb::JobRequest, ClientError> {
        use pb::job_request::Program;
        let program = if let Some(path) = &self.file {
            let data = crate::client::read_file(path).await?;
            if data.len() as u64 > INLINE_HINT {
                let _ = writeln!(
                    io.err,
                    "note: {} is {} and goes inline in one message; for large programs, \
                     `cellgate program put NAME {}` once and submit --library NAME",
                    path.display(),
                    render::bytes(data.len() as u64),
                    path.display()
                );
            }
            Program::Inline(data)
        } else if let Some(name) = &self.library {
            Program::Library(name.clone())
        } else if let Some(key) = &self.key {
            Program::Key(key.clone())
        } else if let Some(job) = &self.resume {
            Program::ResumeJob(job.clone())
        } else {
            return Err(ClientError::InvalidArgument {
                what: "submit".to_string(),
                reason: "give a FILE, --library NAME, --key KEY or --resume JOB_ID".to_string(),
            });
        };
        let start_at = match &self.from_block {
            Some(block) => Some(pb::BlockStart {
                at: Some(parse_block(block)?),
                // 0: up to the first numbered block.
                header_lines: self.header_lines.unwrap_or(0),
            }),
            None => None,
        };
        Ok(pb::JobRequest {
            program: Some(program),
            name: self.name.clone().unwrap_or_default(),
            priority: self.priority,
            append_eor: self.append_eor,
            request_id: self
                .request_id
                .clone()
                .unwrap_or_else(crate::client::new_request_id),
            start_at,
            resume_after_restart: self.resume_after_restart,
            // 0: none.
            deadline_s: self.deadline.unwrap_or(0),
            revision: self.revision.clone().unwrap_or_default(),
        })
    }
}

impl ClientCommand for SubmitArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        let machine = self.machine()?;
        let request = self.request(io).await?;
        // Where a resume starts depends on what the board had taken when the job ended,
        // which the client never saw: say it first.
        if let Some(job) = &self.resume
            && let Ok(latest) = client.job_latest(&machine, job).await
            && let Some(line) = resume_context(&latest)
        {
            let _ = writeln!(io.err, "{line}");
        }
        let (accepted, mut follower) = client.submit(&machine, &request).await?;
        let job = accepted.job_id.clone();
        if self.json {
            let _ = writeln!(io.out, "{}", render::accepted_json(&accepted));
        } else {
            let _ = writeln!(io.out, "{job}");
        }
        let _ = io.out.flush();
        // The position counts waiting jobs only: a job being sent may still be ahead.
        let _ = match accepted.queue_position {
            0 => writeln!(io.err, "{job}: accepted by {machine}, next in its queue"),
            n => writeln!(
                io.err,
                "{job}: accepted by {machine}, {n} waiting job(s) ahead of it"
            ),
        };
        if self.detach {
            follower.close().await;
            return Ok(0);
        }
        let mut progress = JobProgress::new(io.progress_bar, &job);
        let bar = progress.bar.clone();
        let interrupt = tokio::signal::ctrl_c();
        tokio::pin!(interrupt);
        let outcome = loop {
            let event = tokio::select! {
                e = follower.next() => e,
                _ = &mut interrupt => {
                    bar.abandon();
                    let _ = writeln!(
                        io.err,
                        "interrupted: job {job} keeps running on {m}; follow it with \
                         `cellgate job {job} --follow`, cancel it with `cellgate cancel {job}`",
                        m = machine
                    );
                    follower.close().await;
                    return Ok(EXIT_INTERRUPTED);
                }
            };
            let event = match event {
                Ok(Some(e)) => e,
                Ok(None) => break None,
                Err(e) => {
                    bar.abandon();
                    follower.close().await;
                    return Err(e);
                }
            };
            progress.show(io, &event);
            if let Some(outcome) = JobOutcome::of(&event) {
                if self.json {
                    let _ = writeln!(io.out, "{}", render::job_event_json(&event));
                }
                break Some(outcome);
            }
        };
        follower.close().await;
        Ok(outcome.map_or(1, |o| o.exit_code()))
    }
}

/// What a failed or cancelled job left on the CNC, and where its resume starts: `mill-1-x-7
/// was cancelled with 1.2 KiB on the line, 1.0 KiB of it acknowledged by the board: the
/// resume sends from block N120 (line 14), its header first`.
fn resume_context(e: &pb::JobEvent) -> Option<String> {
    let (ended, on_line, acked, next) = match &e.kind {
        Some(Kind::Failed(f)) => ("failed", f.bytes_on_line, f.byte_offset, &f.next_block),
        Some(Kind::Cancelled(c)) => (
            "was cancelled",
            c.bytes_on_line,
            c.byte_offset,
            &c.next_block,
        ),
        _ => return None,
    };
    let next = next.as_ref()?;
    let block = if next.sequence_number.is_empty() {
        format!("the block at line {}", next.line)
    } else {
        format!("block {} (line {})", next.sequence_number, next.line)
    };
    Some(format!(
        "{} {ended} with {} on the line, {} of it acknowledged by the board: the resume \
         sends from {block}, the first block the board did not hold whole, its header first",
        e.job_id,
        render::bytes(on_line),
        render::bytes(acked)
    ))
}

/// A job's progress as `submit` shows it: a bar on a terminal, else a line for each step.
/// Until the first bytes go on the line the job waits for the CNC to ask for it (for
/// seconds, or until an operator starts the read): that is shown as a wait, not as a bar
/// standing at 0 B.
struct JobProgress {
    bar: ProgressBar,
    /// Lines for the steps instead of the bar (stderr is no terminal).
    lines: bool,
    /// When it started, on the gateway's clock (the event's `unix_ms`).
    started_ms: Option<u64>,
    /// Bytes have gone on the line.
    sending: bool,
}

/// The bar while the job waits: no bytes, what it waits for.
const WAIT_TEMPLATE: &str = "{prefix} {spinner} {msg} {elapsed_precise}";
/// The bar once bytes go on the line: acknowledged bytes of the total.
const SEND_TEMPLATE: &str =
    "{prefix} {msg:24} [{wide_bar}] {bytes}/{total_bytes} {elapsed_precise} eta {eta}";

/// What `submit` says while a started job waits for the CNC.
pub const WAITING_FOR_CNC: &str = "waiting for the CNC to ask for it";

impl JobProgress {
    fn new(visible: bool, job: &str) -> JobProgress {
        // Drawn only once styled: a bar drawn at once shows the default style for a moment.
        let progress = JobProgress {
            bar: ProgressBar::hidden(),
            lines: !visible,
            started_ms: None,
            sending: false,
        };
        progress.style(WAIT_TEMPLATE);
        progress.bar.set_prefix(job.to_string());
        if visible {
            progress.bar.set_draw_target(ProgressDrawTarget::stderr());
            progress.bar.enable_steady_tick(Duration::from_millis(200));
        }
        progress
    }

    fn style(&self, template: &str) {
        let style = ProgressStyle::with_template(template)
            .map(|s| s.progress_chars("=> "))
            .unwrap_or_else(|_| ProgressStyle::default_bar());
        self.bar.set_style(style);
    }

    /// Shows one job event: on the bar when there is one; otherwise as a line for each step
    /// (the first bytes on the line are one) but the other progress events.
    fn show(&mut self, io: &mut Io<'_>, event: &pb::JobEvent) {
        let mut line = format!("{}: {}", event.job_id, render::job_kind_text(event));
        match &event.kind {
            Some(Kind::Queued(q)) => self
                .bar
                .set_message(format!("queued, {} ahead", q.queue_position)),
            Some(Kind::Started(s)) => {
                if let Some(total) = s.bytes_total {
                    self.bar.set_length(total);
                }
                self.started_ms = Some(event.unix_ms);
                self.bar.reset_elapsed();
                self.bar.set_message(format!("started: {WAITING_FOR_CNC}"));
                line.push_str(&format!(": {WAITING_FOR_CNC}"));
            }
            Some(Kind::Progress(p)) => {
                if let Some(total) = p.bytes_total {
                    self.bar.set_length(total);
                }
                self.bar.set_position(p.bytes_sent);
                self.bar.set_message(format!(
                    "{} on the line, {} B/s",
                    render::bytes(p.bytes_on_line),
                    p.rate_bps
                ));
                if self.sending || p.bytes_on_line == 0 {
                    return; // no line per progress event
                }
                self.sending = true;
                self.style(SEND_TEMPLATE);
                let after = self
                    .started_ms
                    .map(|t| {
                        let ms = event.unix_ms.saturating_sub(t);
                        format!(" ({}.{} s after the start)", ms / 1000, ms % 1000 / 100)
                    })
                    .unwrap_or_default();
                line = format!(
                    "{}: sending: the CNC asked for it{after}; {}",
                    event.job_id,
                    render::job_kind_text(event)
                );
            }
            Some(Kind::Completed(c)) => {
                self.bar.set_position(c.bytes_sent);
                self.bar.finish_and_clear();
            }
            Some(Kind::Failed(_) | Kind::Cancelled(_)) | None => self.bar.abandon(),
        }
        if self.lines || JobOutcome::of(event).is_some() {
            let _ = writeln!(io.err, "{line}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn event(unix_ms: u64, kind: Kind) -> pb::JobEvent {
        pb::JobEvent {
            job_id: "mill-1-x-1".to_string(),
            unix_ms,
            kind: Some(kind),
            ..Default::default()
        }
    }

    /// Until bytes go on the line the bar says what the job waits for, at no position;
    /// then it counts the acknowledged bytes and says what is on the line.
    #[test]
    fn a_started_job_waits_for_the_cnc_before_its_bar_counts_bytes() {
        let mut progress = JobProgress::new(false, "mill-1-x-1");
        progress.bar = ProgressBar::with_draw_target(Some(0), ProgressDrawTarget::hidden());
        progress.lines = false;
        let (mut out, mut err) = (Vec::new(), Vec::new());
        let mut io = Io {
            out: &mut out,
            err: &mut err,
            progress_bar: true,
        };
        let started = pb::job_event::Started {
            bytes_total: Some(137),
        };
        progress.show(&mut io, &event(1_000, Kind::Started(started)));
        assert_eq!(
            progress.bar.message(),
            "started: waiting for the CNC to ask for it"
        );
        assert_eq!(progress.bar.position(), 0);
        let on_line = pb::job_event::Progress {
            bytes_sent: 0,
            bytes_total: Some(137),
            rate_bps: 28,
            bytes_on_line: 136,
            block: String::new(),
        };
        progress.show(&mut io, &event(5_800, Kind::Progress(on_line)));
        assert!(progress.sending);
        assert_eq!(progress.bar.message(), "136 B on the line, 28 B/s");
        assert!(err.is_empty(), "a bar, no lines");
    }
}
