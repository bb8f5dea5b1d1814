//! `cellgate g05`: a G05 stream fed from a file or standard input.

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;
use prost::Message as _;
use tokio::io::{AsyncBufReadExt as _, AsyncRead};

use super::{ClientCommand, ConnectArgs, EXIT_INTERRUPTED, Io};
use crate::client::{Client, ClientError, render};
use cellgate_core::pb;

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
        let input = self.open_input().await?;
        let (opened, _token) = client
            .g05_open(&self.machine, self.id.as_deref().unwrap_or_default(), true)
            .await?;
        let stream = opened.stream_id.clone();
        let status_sub = client.g05_status(&self.machine, &stream).await?;
        let _ = writeln!(io.err, "{}", opened_line(&self.machine, &opened));
        let mut source = BlockSource {
            lines: tokio::io::BufReader::new(input).lines(),
            file: self.file.display().to_string(),
            line_no: 0,
            eof: false,
            axes: opened.axes as usize,
            aux: opened.aux,
        };
        let mut latest = pb::G05Status {
            credits: opened.credits,
            ..pb::G05Status::default()
        };
        let mut sent = 0u64;
        let mut seq = 0u64;
        let mut pending: Vec<pb::G05Block> = Vec::new();
        let mut last_shown = std::time::Instant::now();
        let interrupt = tokio::signal::ctrl_c();
        tokio::pin!(interrupt);
        let fail = loop {
            if let Err(why) = source.fill(&mut pending, self.batch).await {
                let _ = writeln!(io.err, "cellgate: {why}");
                let _ = client.g05_cancel(&self.machine, &stream).await;
                break Some(2);
            }
            // Credits as the gateway last said, less what was sent since.
            let in_flight = sent.saturating_sub(latest.received);
            let credits = u64::from(latest.credits).saturating_sub(in_flight) as usize;
            let n = pending.len().min(credits);
            if n > 0 || (source.eof && pending.is_empty()) {
                let blocks: Vec<pb::G05Block> = pending.drain(..n).collect();
                let end = source.eof && pending.is_empty();
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
            if is_over(&latest) {
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
        let last = last_status(&status_sub, latest).await;
        let _ = status_sub.undeclare().await;
        if io.progress_bar {
            let _ = writeln!(io.err);
        }
        let Some(last) = last else {
            let _ = writeln!(io.err, "cellgate: stream {stream}: no final status");
            return Ok(1);
        };
        let summary = summary(&stream, &last);
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

impl G05Args {
    /// The file of blocks, or standard input for `-`.
    async fn open_input(&self) -> Result<Box<dyn AsyncRead + Unpin + Send>, ClientError> {
        if self.file.as_os_str() == "-" {
            return Ok(Box::new(tokio::io::stdin()));
        }
        let file =
            tokio::fs::File::open(&self.file)
                .await
                .map_err(|e| ClientError::InvalidArgument {
                    what: format!("file {}", self.file.display()),
                    reason: e.to_string(),
                })?;
        Ok(Box::new(file))
    }
}

/// The CSV lines of a stream's blocks, read a batch at a time.
struct BlockSource {
    lines: tokio::io::Lines<tokio::io::BufReader<Box<dyn AsyncRead + Unpin + Send>>>,
    file: String,
    line_no: u64,
    eof: bool,
    axes: usize,
    aux: bool,
}

impl BlockSource {
    /// Reads blocks into `pending` until it holds `batch` or the input ends; a line that is
    /// not a block, or a failed read, is the error (with the file and line).
    async fn fill(&mut self, pending: &mut Vec<pb::G05Block>, batch: usize) -> Result<(), String> {
        while !self.eof && pending.len() < batch {
            match self.lines.next_line().await {
                Ok(Some(text)) => {
                    self.line_no += 1;
                    match parse_g05_line(&text, self.axes, self.aux) {
                        Ok(Some(b)) => pending.push(b),
                        Ok(None) => {}
                        Err(why) => return Err(format!("{}:{}: {why}", self.file, self.line_no)),
                    }
                }
                Ok(None) => self.eof = true,
                Err(e) => return Err(format!("reading {}: {e}", self.file)),
            }
        }
        Ok(())
    }
}

/// What the gateway opened, in one line.
fn opened_line(machine: &str, opened: &pb::G05Opened) -> String {
    format!(
        "G05 stream {} on {machine}: {} axes{}, T = {} ms, {}-byte blocks; window {} blocks, \
         priming {}; the line runs {} baud, {} needed",
        opened.stream_id,
        opened.axes,
        if opened.aux { " + aux" } else { "" },
        opened.unit_time_ms,
        opened.block_len,
        opened.window,
        opened.prime,
        opened.actual_baud,
        opened.required_baud,
    )
}

fn is_over(status: &pb::G05Status) -> bool {
    matches!(
        status.state(),
        pb::G05State::Completed | pb::G05State::Failed
    )
}

/// The stream's last status: `latest` if it is over, else the next that is (`None` when the
/// gateway says nothing more for ten minutes, or the subscription ends).
async fn last_status(
    status_sub: &zenoh::pubsub::Subscriber<
        zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>,
    >,
    mut latest: pb::G05Status,
) -> Option<pb::G05Status> {
    loop {
        if is_over(&latest) {
            return Some(latest);
        }
        match tokio::time::timeout(Duration::from_secs(600), status_sub.recv_async()).await {
            Ok(Ok(sample)) => {
                if let Ok(st) = pb::G05Status::decode(sample.payload().to_bytes().as_ref()) {
                    latest = st;
                }
            }
            _ => return None,
        }
    }
}

/// How the stream ended, in one line.
fn summary(stream: &str, last: &pb::G05Status) -> String {
    format!(
        "G05 stream {stream} {}: {} blocks, {} underruns (estimated){}",
        render::g05_state_name(last.state()),
        last.received,
        last.underruns,
        if last.last_error.is_empty() {
            String::new()
        } else {
            format!("; last error: {}", last.last_error)
        }
    )
}
