//! `cellgate g05`: a G05 stream fed from a file or standard input.

use super::*;

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
