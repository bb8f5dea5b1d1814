//! The client commands of the `cellgate` binary: their arguments (clap) and what each one
//! does with a connected [`Client`], writing to the given output streams.
//!
//! Exit codes: 0 success; 1 failure at run time (no gateway, no answer, a job that failed or
//! was cancelled); 2 a request the gateway refused (its `ErrorReply` is printed) or bad usage;
//! 130 `submit` interrupted by Ctrl-C (the job keeps running).

use std::future::Future;
use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use prost::Message;

use super::render::{self, WatchPrinter};
use super::{
    Client, ClientError, ClientSecurity, ConnectOptions, Credentials, DEFAULT_ENDPOINT, JobOutcome,
    WatchEvent, parse_byte,
};
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;

pub mod records;

/// Exit code of an interrupted `submit`.
pub const EXIT_INTERRUPTED: u8 = 130;

/// Inline programs above this size get a hint to use the library instead.
const INLINE_HINT: u64 = 16 * 1024 * 1024;

/// Where the gateway is: options every client command takes.
#[derive(Debug, Clone, Args)]
pub struct ConnectArgs {
    /// Zenoh endpoint of the gateway (or of a router it is connected to). The client connects
    /// there only: client mode, no listen endpoint, multicast scouting off.
    #[arg(short = 'e', long = "connect", value_name = "ENDPOINT", default_value = DEFAULT_ENDPOINT, env = "CELLGATE_CONNECT")]
    pub connect: String,
    /// Key prefix the gateway serves under (its bus.prefix).
    #[arg(
        long,
        value_name = "PREFIX",
        default_value = "cellgate",
        env = "CELLGATE_PREFIX"
    )]
    pub prefix: String,
    /// The cell. Default: the only cell whose gateway answers at the endpoint.
    #[arg(long, value_name = "CELL", env = "CELLGATE_CELL")]
    pub cell: Option<String>,
    /// Seconds to wait for the answer to an ordinary request (status, program library).
    #[arg(long, value_name = "SECS", default_value_t = 10)]
    pub timeout: u64,
    /// The CA that signed the gateway's certificate (PEM), for a tls/ endpoint.
    #[arg(long, value_name = "FILE", env = "CELLGATE_TLS_CA")]
    pub tls_ca: Option<PathBuf>,
    /// This client's certificate (PEM), for a gateway that requires client certificates; its
    /// common name is what the gateway's roles name.
    #[arg(
        long,
        value_name = "FILE",
        env = "CELLGATE_TLS_CERT",
        requires = "tls_key"
    )]
    pub tls_cert: Option<PathBuf>,
    /// The private key of --tls-cert (PEM).
    #[arg(
        long,
        value_name = "FILE",
        env = "CELLGATE_TLS_KEY",
        requires = "tls_cert"
    )]
    pub tls_key: Option<PathBuf>,
    /// User name, for a gateway with a users file. The password comes from --password-file
    /// or the environment variable CELLGATE_PASSWORD.
    #[arg(long, value_name = "NAME", env = "CELLGATE_USER")]
    pub user: Option<String>,
    /// A file whose first line is the password of --user.
    #[arg(long, value_name = "FILE", requires = "user")]
    pub password_file: Option<PathBuf>,
    /// Who you are, for the gateway's audit trail (attached to every request; the gateway
    /// records it as your word). Default: --user, else your login name.
    #[arg(long = "as", value_name = "NAME", env = "CELLGATE_AS")]
    pub as_user: Option<String>,
}

/// Where a client command takes the password of `--user` from when no file is given.
pub const PASSWORD_ENV: &str = "CELLGATE_PASSWORD";

impl ConnectArgs {
    /// The options these arguments give; reads the password file, if any.
    pub fn options(&self) -> Result<ConnectOptions, ClientError> {
        let credentials = match &self.user {
            None => None,
            Some(user) => {
                let password = match &self.password_file {
                    Some(path) => std::fs::read_to_string(path)
                        .map_err(|source| ClientError::File {
                            path: path.clone(),
                            op: "read",
                            source,
                        })?
                        .lines()
                        .next()
                        .unwrap_or_default()
                        .to_string(),
                    None => std::env::var(PASSWORD_ENV).unwrap_or_default(),
                };
                if password.is_empty() {
                    return Err(ClientError::Security {
                        what: format!("--user {user}"),
                        reason: format!("no password: give --password-file or set {PASSWORD_ENV}"),
                    });
                }
                Some(Credentials {
                    user: user.clone(),
                    password,
                })
            }
        };
        let user = self
            .as_user
            .clone()
            .or_else(|| self.user.clone())
            .or_else(|| std::env::var("USER").ok())
            .or_else(|| std::env::var("LOGNAME").ok())
            .unwrap_or_default();
        Ok(ConnectOptions {
            origin: Some(pb::RequestOrigin {
                user: user.chars().take(cellgate_core::bounds::MAX_TEXT).collect(),
                via: "cli".to_string(),
            }),
            endpoint: self.connect.clone(),
            prefix: self.prefix.clone(),
            cell: self.cell.clone(),
            timeout: Duration::from_secs(self.timeout.max(1)),
            security: ClientSecurity {
                ca: self.tls_ca.clone(),
                certificate: self.tls_cert.clone(),
                private_key: self.tls_key.clone(),
                credentials,
            },
        })
    }
}

/// Output streams of a command. `progress_bar` draws the live bar of `submit` on the
/// terminal's stderr (off when stderr is not a terminal, and in tests).
pub struct Io<'a> {
    pub out: &'a mut (dyn Write + Send),
    pub err: &'a mut (dyn Write + Send),
    pub progress_bar: bool,
}

/// A client command: where to connect, and what to do once connected.
pub trait ClientCommand {
    fn connect_args(&self) -> &ConnectArgs;
    /// Runs the command; `Ok` carries the exit code.
    fn run(
        &self,
        client: &Client,
        io: &mut Io<'_>,
    ) -> impl Future<Output = Result<u8, ClientError>>;
}

/// Connects, runs `command`, closes, and returns its exit code; errors are written to
/// `io.err`, prefixed `cellgate:`.
pub async fn run_command(command: &impl ClientCommand, io: &mut Io<'_>) -> u8 {
    let options = match command.connect_args().options() {
        Ok(o) => o,
        Err(e) => return report(io, &e),
    };
    let client = match Client::connect(&options).await {
        Ok(c) => c,
        Err(e) => return report(io, &e),
    };
    let result = command.run(&client, io).await;
    client.close().await;
    match result {
        Ok(code) => code,
        Err(e) => report(io, &e),
    }
}

fn report(io: &mut Io<'_>, e: &ClientError) -> u8 {
    let _ = writeln!(io.err, "cellgate: {e}");
    e.exit_code()
}

/// Runs a client command from the binary: a multi-thread runtime (zenoh's requirement), the
/// process's stdout and stderr.
pub fn execute(command: &impl ClientCommand) -> ExitCode {
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .worker_threads(2)
        .thread_name("cellgate-client")
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("cellgate: cannot start the Tokio runtime: {e}");
            return ExitCode::from(1);
        }
    };
    let mut out = std::io::stdout();
    let mut err = std::io::stderr();
    let progress_bar = err.is_terminal();
    let mut io = Io {
        out: &mut out,
        err: &mut err,
        progress_bar,
    };
    let code = runtime.block_on(run_command(command, &mut io));
    let _ = io.out.flush();
    runtime.shutdown_timeout(Duration::from_secs(1));
    ExitCode::from(code)
}

// ---- submit ----------------------------------------------------------------------------------

/// `cellgate submit`.
#[derive(Debug, Clone, Args)]
#[command(
    override_usage = "cellgate submit [OPTIONS] <MACHINE> <FILE|--library <NAME>|--key <KEY>|--resume <JOB_ID>>"
)]
#[command(group(
    clap::ArgGroup::new("source")
        .required(true)
        .args(["file", "library", "key", "resume"])
))]
pub struct SubmitArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The machine to send the program to (its name in the cell file).
    #[arg(value_name = "MACHINE")]
    pub machine: String,
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
    #[arg(long, value_name = "LINES", default_value_t = 0)]
    pub header_lines: u32,
    /// If the gateway restarts while sending this job, resume it from the first block the
    /// board did not acknowledge whole instead of failing it.
    #[arg(long)]
    pub resume_after_restart: bool,
    /// Fail the job if it has not completed this many seconds after it started (a CNC that
    /// never asks for data): it fails at what the board acknowledged.
    #[arg(long, value_name = "SECS", default_value_t = 0)]
    pub deadline: u32,
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
    /// The `JobRequest` these arguments make (reads FILE).
    pub async fn request(&self, io: &mut Io<'_>) -> Result<pb::JobRequest, ClientError> {
        use pb::job_request::Program;
        let program = if let Some(path) = &self.file {
            let data = tokio::fs::read(path)
                .await
                .map_err(|source| ClientError::File {
                    path: path.clone(),
                    op: "read",
                    source,
                })?;
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
                header_lines: self.header_lines,
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
                .unwrap_or_else(super::new_request_id),
            start_at,
            resume_after_restart: self.resume_after_restart,
            deadline_s: self.deadline,
            revision: self.revision.clone().unwrap_or_default(),
        })
    }
}

impl ClientCommand for SubmitArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        let request = self.request(io).await?;
        let (accepted, mut follower) = client.submit(&self.machine, &request).await?;
        let job = accepted.job_id.clone();
        if self.json {
            let _ = writeln!(io.out, "{}", render::accepted_json(&accepted));
        } else {
            let _ = writeln!(io.out, "{job}");
        }
        let _ = io.out.flush();
        let _ = writeln!(
            io.err,
            "{job}: accepted by {}, {} job(s) ahead",
            self.machine, accepted.queue_position
        );
        if self.detach {
            follower.close().await;
            return Ok(0);
        }
        let bar = progress_bar(io.progress_bar, &job);
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
                        m = self.machine
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
            show_progress(&bar, io, &event);
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

fn progress_bar(visible: bool, job: &str) -> ProgressBar {
    if !visible {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr());
    let style = ProgressStyle::with_template(
        "{prefix} {msg:24} [{wide_bar}] {bytes}/{total_bytes} {elapsed_precise} eta {eta}",
    )
    .map(|s| s.progress_chars("=> "))
    .unwrap_or_else(|_| ProgressStyle::default_bar());
    bar.set_style(style);
    bar.set_prefix(job.to_string());
    bar.enable_steady_tick(Duration::from_millis(200));
    bar
}

/// Shows one job event: on the bar when there is one; otherwise as a line for each step but
/// the progress events.
fn show_progress(bar: &ProgressBar, io: &mut Io<'_>, event: &pb::JobEvent) {
    let line = format!("{}: {}", event.job_id, render::job_kind_text(event));
    match &event.kind {
        Some(Kind::Queued(q)) => bar.set_message(format!("queued, {} ahead", q.queue_position)),
        Some(Kind::Started(s)) => {
            if let Some(total) = s.bytes_total {
                bar.set_length(total);
            }
            bar.reset_elapsed();
            bar.set_message("sending");
        }
        Some(Kind::Progress(p)) => {
            if let Some(total) = p.bytes_total {
                bar.set_length(total);
            }
            bar.set_position(p.bytes_sent);
            bar.set_message(format!("sending, {} B/s", p.rate_bps));
            return; // no line per progress event
        }
        Some(Kind::Completed(c)) => {
            bar.set_position(c.bytes_sent);
            bar.finish_and_clear();
        }
        Some(Kind::Failed(_) | Kind::Cancelled(_)) | None => bar.abandon(),
    }
    if bar.is_hidden() || JobOutcome::of(event).is_some() {
        let _ = writeln!(io.err, "{line}");
    }
}

// ---- status ----------------------------------------------------------------------------------

/// `cellgate health`: the probe of containers and service managers.
#[derive(Debug, Clone, Args)]
pub struct HealthArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Healthy when the gateway answers, whatever its links do: for a liveness probe, which
    /// should not restart a gateway because a CNC is switched off.
    #[arg(long)]
    pub gateway_only: bool,
    /// Print JSON (healthy, links, down, alarm) instead of text.
    #[arg(long)]
    pub json: bool,
}

impl ClientCommand for HealthArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    /// Connecting already proved that the gateway answers its admin key; then every link
    /// must have its transport open and its device answering. A machine in alarm has its
    /// link up (the board answers), so it is healthy, but named: an operator's matter, not
    /// the gateway's.
    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        if self.gateway_only {
            if self.json {
                let v = serde_json::json!({ "healthy": true, "gateway": true });
                let _ = writeln!(io.out, "{v}");
            } else {
                let _ = writeln!(io.out, "ok: the gateway answers");
            }
            return Ok(0);
        }
        let statuses = client.status(None).await?;
        let plcs = client.plc_status(None).await?;
        let stations: Vec<&pb::PlcStation> = plcs.iter().flat_map(|p| &p.stations).collect();
        let mut down: Vec<String> = statuses
            .iter()
            .filter_map(|s| {
                let state = pb::LinkState::try_from(s.link_state).unwrap_or_default();
                match state {
                    pb::LinkState::Down
                    | pb::LinkState::Connecting
                    | pb::LinkState::Unspecified => {
                        Some(format!("{} ({})", s.machine, render::link_text(state)))
                    }
                    _ => None,
                }
            })
            .collect();
        // A PLC station counts as a link: the gateway cannot read or write it while down.
        down.extend(
            stations
                .iter()
                .filter(|s| !s.up)
                .map(|s| format!("{} station {} (down)", s.plc, s.station)),
        );
        let alarm: Vec<String> = statuses
            .iter()
            .filter(|s| {
                s.link_state() == pb::LinkState::Alarm
                    || s.sat
                        .as_ref()
                        .is_some_and(|sat| sat.buffer_status() == pb::BufferStatus::Alarm)
            })
            .map(|s| s.machine.clone())
            .collect();
        let links = statuses.len() + stations.len();
        let healthy = down.is_empty();
        if self.json {
            let v = serde_json::json!({
                "healthy": healthy, "gateway": true, "links": links, "down": down,
                "alarm": alarm,
            });
            let _ = writeln!(io.out, "{v}");
        } else if healthy {
            let _ = write!(
                io.out,
                "ok: the gateway answers and its {links} link(s) are up"
            );
            if !alarm.is_empty() {
                let _ = write!(io.out, "; in alarm: {}", alarm.join(", "));
            }
            let _ = writeln!(io.out);
        } else {
            let _ = writeln!(
                io.out,
                "unhealthy: {} of {links} link(s) down: {}",
                down.len(),
                down.join(", ")
            );
        }
        Ok(if healthy { 0 } else { 1 })
    }
}

/// `cellgate status`.
#[derive(Debug, Clone, Args)]
pub struct StatusArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// One machine; default every machine of the cell.
    #[arg(value_name = "MACHINE")]
    pub machine: Option<String>,
    /// Print JSON (an array of MachineStatus, with the .proto's field and enum names).
    #[arg(long)]
    pub json: bool,
}

impl ClientCommand for StatusArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        let statuses = client.status(self.machine.as_deref()).await?;
        if self.json {
            let all: Vec<_> = statuses.iter().map(render::status_json).collect();
            let text = serde_json::to_string_pretty(&all).unwrap_or_default();
            let _ = writeln!(io.out, "{text}");
        } else {
            let _ = write!(io.out, "{}", render::status_table(&statuses));
        }
        // The PLC stations, when no one machine was asked for.
        if self.machine.is_none() && !self.json {
            let plcs = client.plc_status(None).await.unwrap_or_default();
            let _ = write!(
                io.out,
                "{}",
                render::plc_status_text(&plcs, cellgate_core::pb::now_ms())
            );
        }
        if !self.json
            && let Some(line) = render::gateway_line(client.admin(), cellgate_core::pb::now_ms())
        {
            let _ = writeln!(io.out, "{line}");
        }
        if statuses.is_empty() && client.admin().is_null() {
            // A gateway that hides @admin enforces roles: no status may be a refusal.
            let _ = writeln!(
                io.err,
                "note: this gateway enforces roles; status needs status.read"
            );
        }
        Ok(0)
    }
}

// ---- jobs ------------------------------------------------------------------------------------

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
        // Asking for the status first names the cell's machines when MACHINE is none of them.
        let machines: Vec<String> = client
            .status(self.machine.as_deref())
            .await?
            .into_iter()
            .map(|s| s.machine)
            .collect();
        let mut queues = Vec::new();
        for m in &machines {
            queues.push(client.queue(m).await?);
        }
        let ended: Vec<pb::JobEvent> = if self.all {
            client
                .recent_jobs(self.machine.as_deref())
                .await?
                .into_iter()
                .filter(super::is_end)
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
        while !super::is_end(&last) {
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

// ---- watch -----------------------------------------------------------------------------------

/// `cellgate watch`.
#[derive(Debug, Clone, Args)]
pub struct WatchArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// Only this machine's events, or this PLC's (its stations, transfers and tags).
    #[arg(value_name = "MACHINE")]
    pub machine: Option<String>,
    /// PLC tag changes to print as well: `--tags` every tag, `--tags=parts,recipe` those.
    /// Without it tag changes are left out (a counter tag changes every second and would
    /// drown everything else), unless MACHINE is a PLC.
    #[arg(
        long,
        value_name = "NAMES",
        num_args = 0..=1,
        require_equals = true,
        default_missing_value = "*",
        value_delimiter = ','
    )]
    pub tags: Option<Vec<String>>,
    /// One JSON object per line.
    #[arg(long)]
    pub json: bool,
    /// Stop after this many lines (default: until Ctrl-C).
    #[arg(long, value_name = "N")]
    pub count: Option<u64>,
}

impl WatchArgs {
    /// Whether a tag change is printed.
    fn shows_tag(&self, tag: &pb::TagValue, plc_watched: bool) -> bool {
        plc_watched
            || self
                .tags
                .as_ref()
                .is_some_and(|names| names.iter().any(|n| n == "*" || *n == tag.name))
    }
}

impl ClientCommand for WatchArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        // A name that is neither a machine nor a PLC of the cell would print nothing, ever.
        let mut plc_watched = false;
        if let Some(m) = &self.machine {
            match client.status(Some(m)).await {
                Ok(_) => {}
                Err(e) if e.refusal() == Some(pb::ErrorCode::UnknownMachine) => {
                    let plcs: Vec<String> = client
                        .plc_status(None)
                        .await
                        .unwrap_or_default()
                        .into_iter()
                        .map(|p| p.plc)
                        .collect();
                    if !plcs.contains(m) {
                        let machines: Vec<String> = client
                            .status(None)
                            .await
                            .unwrap_or_default()
                            .into_iter()
                            .map(|s| s.machine)
                            .collect();
                        return Err(ClientError::InvalidArgument {
                            what: format!("watch {m}"),
                            reason: format!(
                                "cell {} has no machine or PLC {m:?}; its machines: {}; its \
                                 PLCs: {}",
                                client.cell(),
                                list_or_none(&machines),
                                list_or_none(&plcs)
                            ),
                        });
                    }
                    plc_watched = true;
                }
                Err(e) => return Err(e),
            }
        }
        let mut watch = client.watch().await?;
        let mut printer = WatchPrinter::new();
        let mut printed = 0;
        let interrupt = tokio::signal::ctrl_c();
        tokio::pin!(interrupt);
        while self.count.is_none_or(|n| printed < n) {
            let event = tokio::select! {
                e = watch.next() => e,
                _ = &mut interrupt => break,
            };
            let Some(event) = event else {
                watch.close().await;
                return Err(ClientError::Closed {
                    what: "watch".to_string(),
                });
            };
            if let Some(m) = &self.machine
                && render::watch_machine(&event) != Some(m.as_str())
            {
                continue;
            }
            if let WatchEvent::Tag(t) = &event
                && !self.shows_tag(t, plc_watched)
            {
                continue;
            }
            let now = cellgate_core::pb::now_ms();
            let line = if self.json {
                Some(render::watch_json(&event, now).to_string())
            } else {
                printer.line(&event, now)
            };
            if let Some(line) = line {
                // A closed stdout (`cellgate watch | head`) ends the watch.
                if writeln!(io.out, "{line}")
                    .and_then(|()| io.out.flush())
                    .is_err()
                {
                    break;
                }
                printed += 1;
            }
        }
        watch.close().await;
        Ok(0)
    }
}

fn list_or_none(names: &[String]) -> String {
    if names.is_empty() {
        "none".to_string()
    } else {
        names.join(", ")
    }
}

// ---- DO / DI ---------------------------------------------------------------------------------

fn byte_arg(text: &str) -> Result<u8, String> {
    parse_byte(text)
}

/// `cellgate do`.
#[derive(Debug, Clone, Args)]
pub struct DoArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The machine (Protocol A family only: SDO, §4.4.1).
    #[arg(value_name = "MACHINE")]
    pub machine: String,
    /// The DO bits: 0x.. hex, 0b.. binary or decimal, 0..=255.
    #[arg(value_name = "VALUE", value_parser = byte_arg)]
    pub value: u8,
    /// Which bits to change (same notations); the others keep the last DO image. Default:
    /// all 8.
    #[arg(long, value_name = "MASK", value_parser = byte_arg)]
    pub mask: Option<u8>,
    /// Put the command and return without waiting for SDO to go out (no confirmation).
    #[arg(long)]
    pub no_wait: bool,
    /// Print JSON (machine, do_image, confirmed) instead of text.
    #[arg(long)]
    pub json: bool,
}

impl ClientCommand for DoArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        if self.no_wait {
            client.put_do(&self.machine, self.value, self.mask).await?;
            if self.json {
                let v = serde_json::json!({
                    "machine": self.machine, "value": self.value, "mask": self.mask,
                    "confirmed": false,
                });
                let _ = writeln!(io.out, "{v}");
            }
            let _ = writeln!(io.err, "{}: DO command sent (not confirmed)", self.machine);
            return Ok(0);
        }
        let status = client.set_do(&self.machine, self.value, self.mask).await?;
        let image = status.do_image.unwrap_or(u32::from(self.value));
        if self.json {
            let v = serde_json::json!({
                "machine": self.machine, "do_image": image, "confirmed": true,
            });
            let _ = writeln!(io.out, "{v}");
        } else {
            let _ = writeln!(io.out, "{} DO {}", self.machine, render::byte_image(image));
        }
        Ok(0)
    }
}

/// `cellgate di`.
#[derive(Debug, Clone, Args)]
pub struct DiArgs {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The machine (Protocol A family only: RDI → SDI, §4.4.1). The read waits for the
    /// board's next exchange, up to 2·Tp + 1 s.
    #[arg(value_name = "MACHINE")]
    pub machine: String,
    /// Print JSON (machine, value, unix_ms) instead of text.
    #[arg(long)]
    pub json: bool,
}

impl ClientCommand for DiArgs {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        let di = client.read_di(&self.machine).await?;
        if self.json {
            let _ = writeln!(io.out, "{}", render::di_json(&di));
        } else {
            let _ = write!(io.out, "{}", render::di_text(&di));
        }
        Ok(0)
    }
}

// ---- program library -------------------------------------------------------------------------

/// `cellgate program`.
#[derive(Debug, Clone, Subcommand)]
pub enum ProgramCommand {
    /// Store a program file in the gateway's library under NAME (replacing one of that name).
    Put {
        #[command(flatten)]
        connect: ConnectArgs,
        /// Library name: 1-128 of A-Z a-z 0-9 . _ + -, starting with a letter or digit.
        name: String,
        /// The program file.
        file: PathBuf,
        /// A comment for the revision the store makes.
        #[arg(short = 'c', long, value_name = "TEXT")]
        comment: Option<String>,
        /// Print JSON (a ProgramInfo) of the stored program.
        #[arg(long)]
        json: bool,
    },
    /// Fetch a program of the library.
    Get {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's name in the library (`cellgate program ls` lists them).
        name: String,
        /// Write it to FILE instead of stdout.
        #[arg(short, long, value_name = "FILE")]
        output: Option<PathBuf>,
        /// Print JSON (name, size, text) instead of the program's bytes.
        #[arg(long, conflicts_with = "output")]
        json: bool,
    },
    /// List the library.
    Ls {
        #[command(flatten)]
        connect: ConnectArgs,
        /// Print JSON (an array of name, size, modified_unix_ms).
        #[arg(long)]
        json: bool,
    },
    /// Remove a program from the library.
    Rm {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's name in the library.
        name: String,
        /// Print JSON (name, size, modified_unix_ms) of the removed program.
        #[arg(long)]
        json: bool,
    },
    /// A program's revisions, newest first: number, state, when, by whom, size, hash,
    /// comment.
    History {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's library name.
        name: String,
        /// Print JSON (a ProgramRevisions).
        #[arg(long)]
        json: bool,
    },
    /// Compare two revisions block by block (default: the latest against the one before).
    /// Exit code 0 when they are the same, 1 when they differ.
    Diff {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's library name.
        name: String,
        /// The older revision: a number or a SHA-256 (or its first 8+ hex digits).
        a: Option<String>,
        /// The newer revision (default: the latest).
        b: Option<String>,
        /// Leave out what does not change the machining: sequence, blanks, comments
        /// (repeat or comma-separate).
        #[arg(long, value_name = "WHAT", value_delimiter = ',')]
        ignore: Vec<String>,
        /// Print JSON (a ProgramDiff).
        #[arg(long)]
        json: bool,
    },
    /// Release a revision for production (default: the latest); with --state, set another
    /// state: draft unreleases (or unlocks a locked one). Needs program.release.
    Release {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's library name.
        name: String,
        /// The revision (default: the latest).
        revision: Option<String>,
        /// The state it takes: released, locked or draft.
        #[arg(long, value_name = "STATE", default_value = "released")]
        state: String,
        /// Why, for the record.
        #[arg(short = 'c', long, value_name = "TEXT")]
        comment: Option<String>,
        /// Print JSON (the ProgramRevision as it now is).
        #[arg(long)]
        json: bool,
    },
    /// Lock a revision (default: the latest): while the latest revision is locked nothing
    /// replaces or removes the program. Needs program.release.
    Lock {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program's library name.
        name: String,
        /// The revision (default: the latest).
        revision: Option<String>,
        /// Why, for the record.
        #[arg(short = 'c', long, value_name = "TEXT")]
        comment: Option<String>,
        /// Print JSON (the ProgramRevision as it now is).
        #[arg(long)]
        json: bool,
    },
    /// Store another library program (a punched one) as NAME's next revision.
    Adopt {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The program that gets the new revision (e.g. O1234).
        name: String,
        /// The library program to take the content of (e.g. the punched
        /// lathe-1-O1234-20261201T061500Z).
        from: String,
        /// Its revision (default: the latest).
        #[arg(long, value_name = "REV")]
        revision: Option<String>,
        /// A comment for the new revision.
        #[arg(short = 'c', long, value_name = "TEXT")]
        comment: Option<String>,
        /// Print JSON (the ProgramInfo with its new revision).
        #[arg(long)]
        json: bool,
    },
}

impl ClientCommand for ProgramCommand {
    fn connect_args(&self) -> &ConnectArgs {
        match self {
            ProgramCommand::Put { connect, .. }
            | ProgramCommand::Get { connect, .. }
            | ProgramCommand::Ls { connect, .. }
            | ProgramCommand::Rm { connect, .. }
            | ProgramCommand::History { connect, .. }
            | ProgramCommand::Diff { connect, .. }
            | ProgramCommand::Release { connect, .. }
            | ProgramCommand::Lock { connect, .. }
            | ProgramCommand::Adopt { connect, .. } => connect,
        }
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        match self {
            ProgramCommand::Put {
                name,
                file,
                comment,
                json,
                ..
            } => {
                let data = tokio::fs::read(file)
                    .await
                    .map_err(|source| ClientError::File {
                        path: file.clone(),
                        op: "read",
                        source,
                    })?;
                let info = client
                    .program_put_with(name, &data, comment.clone().unwrap_or_default())
                    .await?;
                if *json {
                    let _ = writeln!(io.out, "{}", render::program_json(&info));
                }
                let rev = info
                    .latest
                    .as_ref()
                    .map(|r| format!(", revision {}", r.number))
                    .unwrap_or_default();
                let _ = writeln!(io.err, "{}: stored, {} bytes{rev}", info.name, info.size);
            }
            ProgramCommand::History { name, json, .. } => {
                return records::program_history(client, io, name, *json).await;
            }
            ProgramCommand::Diff {
                name,
                a,
                b,
                ignore,
                json,
                ..
            } => {
                return records::program_diff(
                    client,
                    io,
                    name,
                    a.as_deref(),
                    b.as_deref(),
                    ignore,
                    *json,
                )
                .await;
            }
            ProgramCommand::Release {
                name,
                revision,
                state,
                comment,
                json,
                ..
            } => {
                let state = match state.as_str() {
                    "released" => pb::RevisionState::Released,
                    "locked" => pb::RevisionState::Locked,
                    "draft" => pb::RevisionState::Draft,
                    other => {
                        return Err(ClientError::InvalidArgument {
                            what: format!("--state {other}"),
                            reason: "released, locked or draft".to_string(),
                        });
                    }
                };
                return records::program_state(
                    client,
                    io,
                    name,
                    revision.as_deref(),
                    state,
                    comment.as_deref(),
                    *json,
                )
                .await;
            }
            ProgramCommand::Lock {
                name,
                revision,
                comment,
                json,
                ..
            } => {
                return records::program_state(
                    client,
                    io,
                    name,
                    revision.as_deref(),
                    pb::RevisionState::Locked,
                    comment.as_deref(),
                    *json,
                )
                .await;
            }
            ProgramCommand::Adopt {
                name,
                from,
                revision,
                comment,
                json,
                ..
            } => {
                return records::program_adopt(
                    client,
                    io,
                    name,
                    from,
                    revision.as_deref(),
                    comment.as_deref(),
                    *json,
                )
                .await;
            }
            ProgramCommand::Get {
                name, output, json, ..
            } => {
                let data = client.program_get(name).await?;
                if *json {
                    let v = serde_json::json!({
                        "name": name,
                        "size": data.len(),
                        "text": String::from_utf8_lossy(&data),
                    });
                    let _ = writeln!(io.out, "{v}");
                    return Ok(0);
                }
                match output {
                    Some(path) => {
                        tokio::fs::write(path, &data)
                            .await
                            .map_err(|source| ClientError::File {
                                path: path.clone(),
                                op: "write",
                                source,
                            })?
                    }
                    None => {
                        let _ = io.out.write_all(&data);
                    }
                }
            }
            ProgramCommand::Ls { json, .. } => {
                let list = client.program_list().await?;
                if *json {
                    let all: Vec<_> = list.iter().map(render::program_json).collect();
                    let text = serde_json::to_string_pretty(&all).unwrap_or_default();
                    let _ = writeln!(io.out, "{text}");
                } else {
                    let _ = write!(io.out, "{}", render::program_table(&list));
                    if list.is_empty() && client.admin().is_null() {
                        // A gateway that hides @admin enforces roles: an empty answer may be
                        // a refusal.
                        let _ = writeln!(
                            io.err,
                            "note: this gateway enforces roles; listing the library needs \
                             program.read"
                        );
                    }
                }
            }
            ProgramCommand::Rm { name, json, .. } => {
                let info = client.program_remove(name).await?;
                if *json {
                    let _ = writeln!(io.out, "{}", render::program_json(&info));
                }
                let _ = writeln!(io.err, "{name}: removed");
            }
        }
        Ok(0)
    }
}

// ---- cancel ----------------------------------------------------------------------------------

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
    match super::machine_of_job(first) {
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

// ---- g05 -------------------------------------------------------------------------------------

/// `cellgate g05`.
#[derive(Debug, Clone, Args)]
pub struct G05Args {
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// The machine to stream to (its cell file has a `[machines.g05]` table).
    #[arg(value_name = "MACHINE")]
    pub machine: String,
    /// CSV of blocks, one a line: one integer travel per axis (least input increments), then
    /// the auxiliary value when the machine's blocks carry one (empty: none). `#` starts a
    /// comment. `-` reads standard input, so another program can pipe blocks in.
    #[arg(value_name = "FILE")]
    pub file: PathBuf,
    /// The stream's id (default: the gateway names it).
    #[arg(long, value_name = "ID")]
    pub id: Option<String>,
    /// Blocks per batch at most.
    #[arg(long, value_name = "N", default_value_t = 200)]
    pub batch: usize,
    /// Print the stream's last status as JSON instead of a line of text.
    #[arg(long)]
    pub json: bool,
}

/// One CSV line as a block: `axes` travels, then an optional auxiliary value when `aux`.
/// `None` for a blank or comment line.
pub fn parse_g05_line(line: &str, axes: usize, aux: bool) -> Result<Option<pb::G05Block>, String> {
    let line = line.split('#').next().unwrap_or("").trim();
    if line.is_empty() {
        return Ok(None);
    }
    let fields: Vec<&str> = line
        .split(|c: char| c == ',' || c == ';' || c.is_whitespace())
        .filter(|f| !f.is_empty())
        .collect();
    let max = axes + usize::from(aux);
    if fields.len() < axes || fields.len() > max {
        return Err(format!(
            "{} fields; a block has {axes} travels{}",
            fields.len(),
            if aux {
                " and an optional auxiliary value"
            } else {
                ""
            }
        ));
    }
    let mut travel = Vec::with_capacity(axes);
    for f in &fields[..axes] {
        travel.push(
            f.parse::<i32>()
                .map_err(|_| format!("travel {f:?} is not an integer"))?,
        );
    }
    let aux = match fields.get(axes) {
        Some(f) => Some(
            f.parse::<u32>()
                .map_err(|_| format!("auxiliary value {f:?} is not a non-negative integer"))?,
        ),
        None => None,
    };
    Ok(Some(pb::G05Block { travel, aux }))
}

impl ClientCommand for G05Args {
    fn connect_args(&self) -> &ConnectArgs {
        &self.connect
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        use tokio::io::AsyncBufReadExt;
        let input: Box<dyn tokio::io::AsyncRead + Unpin + Send> = if self.file.as_os_str() == "-" {
            Box::new(tokio::io::stdin())
        } else {
            Box::new(tokio::fs::File::open(&self.file).await.map_err(|e| {
                ClientError::InvalidArgument {
                    what: format!("file {}", self.file.display()),
                    reason: e.to_string(),
                }
            })?)
        };
        let mut lines = tokio::io::BufReader::new(input).lines();
        let (opened, _token) = client
            .g05_open(&self.machine, self.id.as_deref().unwrap_or_default(), true)
            .await?;
        let stream = opened.stream_id.clone();
        let status_sub = client.g05_status(&self.machine, &stream).await?;
        let _ = writeln!(
            io.err,
            "G05 stream {stream} on {}: {} axes{}, T = {} ms, {}-byte blocks; window {} blocks, \
             priming {}; the line runs {} baud, {} needed",
            self.machine,
            opened.axes,
            if opened.aux { " + aux" } else { "" },
            opened.unit_time_ms,
            opened.block_len,
            opened.window,
            opened.prime,
            opened.actual_baud,
            opened.required_baud,
        );
        let axes = opened.axes as usize;
        let mut latest = pb::G05Status {
            credits: opened.credits,
            ..pb::G05Status::default()
        };
        let mut sent = 0u64;
        let mut seq = 0u64;
        let mut line_no = 0u64;
        let mut pending: Vec<pb::G05Block> = Vec::new();
        let mut eof = false;
        let mut last_shown = std::time::Instant::now();
        let interrupt = tokio::signal::ctrl_c();
        tokio::pin!(interrupt);
        let fail = loop {
            // Fill a batch from the file.
            while !eof && pending.len() < self.batch {
                match lines.next_line().await {
                    Ok(Some(text)) => {
                        line_no += 1;
                        match parse_g05_line(&text, axes, opened.aux) {
                            Ok(Some(b)) => pending.push(b),
                            Ok(None) => {}
                            Err(why) => {
                                let _ = writeln!(
                                    io.err,
                                    "cellgate: {}:{line_no}: {why}",
                                    self.file.display()
                                );
                                let _ = client.g05_cancel(&self.machine, &stream).await;
                                break;
                            }
                        }
                    }
                    Ok(None) => eof = true,
                    Err(e) => {
                        let _ = writeln!(io.err, "cellgate: reading {}: {e}", self.file.display());
                        let _ = client.g05_cancel(&self.machine, &stream).await;
                        break;
                    }
                }
            }
            if !eof && pending.len() < self.batch {
                // A bad line: the stream was cancelled above.
                break Some(2);
            }
            // Credits as the gateway last said, less what was sent since.
            let in_flight = sent.saturating_sub(latest.received);
            let credits = u64::from(latest.credits).saturating_sub(in_flight) as usize;
            let n = pending.len().min(credits);
            if n > 0 || (eof && pending.is_empty()) {
                let blocks: Vec<pb::G05Block> = pending.drain(..n).collect();
                let end = eof && pending.is_empty();
                sent += blocks.len() as u64;
                // Acknowledged: a refused batch (a travel out of range) ends the stream here
                // with the reason, instead of leaving it open.
                let batch = pb::G05Batch { seq, blocks, end };
                match client.g05_batch_acked(&self.machine, &stream, &batch).await {
                    Ok(status) => latest = status,
                    Err(e) => {
                        let _ = writeln!(io.err, "cellgate: {e}");
                        let _ = client.g05_cancel(&self.machine, &stream).await;
                        let _ = writeln!(io.err, "stream {stream} cancelled (end block sent)");
                        let _ = status_sub.undeclare().await;
                        return Ok(e.exit_code());
                    }
                }
                seq += 1;
                if end {
                    break None;
                }
                continue;
            }
            // No credits: wait for the next status.
            tokio::select! {
                s = status_sub.recv_async() => match s {
                    Ok(sample) => {
                        if let Ok(st) = pb::G05Status::decode(sample.payload().to_bytes().as_ref()) {
                            latest = st;
                        }
                    }
                    Err(_) => break Some(1),
                },
                _ = &mut interrupt => {
                    let _ = client.g05_cancel(&self.machine, &stream).await;
                    let _ = writeln!(io.err, "interrupted: stream {stream} cancelled (end block sent)");
                    break Some(EXIT_INTERRUPTED);
                }
            }
            if latest.state() == pb::G05State::Completed || latest.state() == pb::G05State::Failed {
                break Some(1);
            }
            if io.progress_bar && last_shown.elapsed() >= Duration::from_millis(500) {
                last_shown = std::time::Instant::now();
                let _ = write!(
                    io.err,
                    "\r{sent} blocks sent, {} on the line, credits {}, CNC buffer ~{}, underruns {}   ",
                    latest.on_line, latest.credits, latest.cnc_buffer, latest.underruns
                );
            }
        };
        // Wait for the stream's last status.
        let last = loop {
            if latest.state() == pb::G05State::Completed || latest.state() == pb::G05State::Failed {
                break Some(latest.clone());
            }
            match tokio::time::timeout(Duration::from_secs(600), status_sub.recv_async()).await {
                Ok(Ok(sample)) => {
                    if let Ok(st) = pb::G05Status::decode(sample.payload().to_bytes().as_ref()) {
                        latest = st;
                    }
                }
                _ => break None,
            }
        };
        let _ = status_sub.undeclare().await;
        if io.progress_bar {
            let _ = writeln!(io.err);
        }
        let Some(last) = last else {
            let _ = writeln!(io.err, "cellgate: stream {stream}: no final status");
            return Ok(1);
        };
        let summary = format!(
            "G05 stream {stream} {}: {} blocks, {} underruns (estimated){}",
            render::g05_state_name(last.state()),
            last.received,
            last.underruns,
            if last.last_error.is_empty() {
                String::new()
            } else {
                format!("; last error: {}", last.last_error)
            }
        );
        if self.json {
            let _ = serde_json::to_writer(&mut *io.out, &render::g05_json(&last));
            let _ = writeln!(io.out);
            let _ = writeln!(io.err, "{summary}");
        } else {
            let _ = writeln!(io.out, "{summary}");
        }
        let clean = last.state() == pb::G05State::Completed
            && last.end_reason() == pb::G05EndReason::Producer;
        Ok(match fail {
            Some(code) => code,
            None if clean => 0,
            None => 1,
        })
    }
}
