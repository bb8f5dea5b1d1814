//! What the plant's systems do to the cell during the soak: MES clients submitting jobs with
//! request ids (retried on any doubt, as a careful MES does) and resuming the ones that
//! failed, DO outputs, tag writes and PLC transfers, library stores and programs posted into the
//! folder, readers of the console and of MTConnect `/sample`. Every job goes into the
//! [`Ledger`], with the exact bytes its CNC must read, for the checks at the end.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sha2::{Digest, Sha256};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_util::sync::CancellationToken;

use crate::client::{Client, ClientError};
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;

/// A job the gateway accepted, and what its CNC must read if it completes.
#[derive(Debug, Clone)]
pub(crate) struct JobEntry {
    pub(crate) machine: String,
    pub(crate) request_id: String,
    /// The program the CNC reads whole when the job completes.
    pub(crate) bytes: Vec<u8>,
    /// Bytes of `bytes` before the first numbered block: what a resume sends first.
    pub(crate) header: usize,
    /// The job this one resumes.
    pub(crate) resume_of: Option<String>,
    /// The latest event read.
    pub(crate) last: Option<pb::JobEvent>,
    /// Terminal events seen that disagree with an earlier terminal one (a job ended twice).
    pub(crate) ended_again: u32,
    pub(crate) resumed: bool,
}

impl JobEntry {
    pub(crate) fn ended(&self) -> bool {
        self.last.as_ref().is_some_and(|e| {
            matches!(
                e.kind,
                Some(Kind::Completed(_) | Kind::Failed(_) | Kind::Cancelled(_))
            )
        })
    }
}

/// Counters of the load that are figures, not invariants.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub(crate) struct LoadFigures {
    pub(crate) submits_refused: u64,
    pub(crate) submit_retries: u64,
    pub(crate) submits_given_up: u64,
    pub(crate) resumes_refused: u64,
    pub(crate) writes_ok: u64,
    pub(crate) writes_failed: u64,
    pub(crate) reads_ok: u64,
    pub(crate) reads_failed: u64,
    pub(crate) folder_posts: u64,
    pub(crate) hostile_requests: u64,
}

/// Every job the soak's clients got accepted, by job id.
#[derive(Debug, Default)]
pub(crate) struct Ledger {
    pub(crate) jobs: HashMap<String, JobEntry>,
    /// Request id → the job id its first acceptance named.
    pub(crate) by_request: HashMap<String, String>,
    /// Request ids answered with another job id than the first time.
    pub(crate) duplicate_acceptances: Vec<(String, String, String)>,
    pub(crate) figures: LoadFigures,
}

pub(crate) type Shared = Arc<Mutex<Ledger>>;

pub(crate) fn lock(l: &Shared) -> MutexGuard<'_, Ledger> {
    l.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Ledger {
    /// Jobs of `machine` not ended yet.
    fn open_on(&self, machine: &str) -> usize {
        self.jobs
            .values()
            .filter(|j| j.machine == machine && !j.ended())
            .count()
    }

    fn accepted(&mut self, job_id: String, entry: JobEntry) {
        match self.by_request.get(&entry.request_id) {
            Some(first) if *first != job_id => {
                self.duplicate_acceptances.push((
                    entry.request_id.clone(),
                    first.clone(),
                    job_id.clone(),
                ));
            }
            Some(_) => return,
            None => {
                self.by_request
                    .insert(entry.request_id.clone(), job_id.clone());
            }
        }
        self.jobs.entry(job_id).or_insert(entry);
    }

    /// Takes `event` as the latest of its job, if the job is the ledger's.
    pub(crate) fn saw(&mut self, event: pb::JobEvent) {
        let Some(j) = self.jobs.get_mut(&event.job_id) else {
            return;
        };
        if j.ended() {
            let same = j.last.as_ref().is_some_and(|l| {
                std::mem::discriminant(&l.kind) == std::mem::discriminant(&event.kind)
            });
            if !same {
                j.ended_again += 1;
            }
            return;
        }
        j.last = Some(event);
    }
}

/// A program of about `size` bytes whose first line names `token`, so that the CNC's record
/// of it is told from every other; returns it and its header's length.
pub(crate) fn program(token: &str, number: u32, size: usize) -> (Vec<u8>, usize) {
    let mut text = format!("%\nO{:04} (SOAK {token})\n", number % 10_000);
    let header = text.len();
    let mut n = 1u32;
    while text.len() + 16 < size {
        text.push_str(&format!(
            "N{n} G01 X{}.{:03} Y{}.{:03} F{}\n",
            n % 997,
            n % 1000,
            (n * 7) % 991,
            (n * 13) % 1000,
            100 + n % 900
        ));
        n += 1;
    }
    text.push_str(&format!("N{n} M30\n%"));
    (text.into_bytes(), header)
}

pub(crate) fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// Whether `e` says the request was seen and refused for good (no retry makes it go).
fn final_refusal(e: &ClientError) -> bool {
    matches!(
        e.refusal(),
        Some(
            pb::ErrorCode::InvalidRequest
                | pb::ErrorCode::UnknownMachine
                | pb::ErrorCode::NotFound
                | pb::ErrorCode::NotPermitted
                | pb::ErrorCode::NotSupported
        )
    )
}

/// Sends `request` to `machine` until the gateway answers it (the same request id each time:
/// a retry after a lost answer must not queue a second job); the job id, or None.
async fn submit_until_answered(
    client: &Client,
    ledger: &Shared,
    machine: &str,
    request: &pb::JobRequest,
    stop: &CancellationToken,
) -> Option<String> {
    for attempt in 0..20 {
        if attempt > 0 {
            lock(ledger).figures.submit_retries += 1;
            tokio::select! {
                () = stop.cancelled() => {}
                () = tokio::time::sleep(Duration::from_millis(1500)) => {}
            }
        }
        match client.submit(machine, request).await {
            Ok((accepted, follower)) => {
                follower.close().await;
                return Some(accepted.job_id);
            }
            Err(e) if final_refusal(&e) => {
                lock(ledger).figures.submits_refused += 1;
                tracing::debug!(machine, error = %e, "submit refused");
                return None;
            }
            Err(e) => {
                // Full disk, busy, gone for a restart, no reply: the MES tries again later,
                // with the same request id.
                tracing::debug!(machine, error = %e, "submit not answered; trying again");
            }
        }
    }
    lock(ledger).figures.submits_given_up += 1;
    None
}

/// One MES: submits jobs to random machines of `machines`, at most two open on a machine.
pub(crate) async fn mes(
    client: Client,
    id: usize,
    seed: u64,
    machines: Vec<String>,
    ledger: Shared,
    stop: CancellationToken,
) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ (id as u64).wrapping_mul(0x9E37_79B9));
    let mut n = 0u32;
    while !stop.is_cancelled() && !machines.is_empty() {
        let machine = &machines[rng.random_range(0..machines.len())];
        if lock(&ledger).open_on(machine) >= 2 {
            tokio::time::sleep(Duration::from_millis(200)).await;
            continue;
        }
        n += 1;
        let token = format!("M{id}-{n}");
        let (bytes, header) = program(&token, n, rng.random_range(1024..8192));
        let request = pb::JobRequest {
            program: Some(pb::job_request::Program::Inline(bytes.clone())),
            request_id: format!("soak-{id}-{n}"),
            name: token,
            ..Default::default()
        };
        if let Some(job) = submit_until_answered(&client, &ledger, machine, &request, &stop).await {
            lock(&ledger).accepted(
                job,
                JobEntry {
                    machine: machine.clone(),
                    request_id: request.request_id.clone(),
                    bytes,
                    header,
                    resume_of: None,
                    last: None,
                    ended_again: 0,
                    resumed: false,
                },
            );
        }
        let pause = rng.random_range(200..1500);
        tokio::select! {
            () = stop.cancelled() => {}
            () = tokio::time::sleep(Duration::from_millis(pause)) => {}
        }
    }
}

/// Resumes every job that failed or was cancelled with a block to resume from, once, as an
/// operator would, and records what the CNC must then read: the header, then the program from
/// that block.
pub(crate) async fn resumer(client: Client, ledger: Shared, stop: CancellationToken) {
    while !stop.is_cancelled() {
        let due: Vec<(String, JobEntry, u64)> = {
            let mut l = lock(&ledger);
            let mut due = Vec::new();
            for (id, j) in &mut l.jobs {
                let next = match j.last.as_ref().and_then(|e| e.kind.as_ref()) {
                    Some(Kind::Failed(f)) => f.next_block.as_ref(),
                    Some(Kind::Cancelled(c)) => c.next_block.as_ref(),
                    _ => None,
                };
                if let Some(b) = next
                    && !j.resumed
                {
                    j.resumed = true;
                    due.push((id.clone(), j.clone(), b.byte_offset));
                }
            }
            due
        };
        for (id, parent, from) in due {
            let Some(tail) = usize::try_from(from)
                .ok()
                .and_then(|f| parent.bytes.get(f..))
            else {
                continue;
            };
            let mut bytes = Vec::new();
            if from > 0 {
                bytes.extend_from_slice(&parent.bytes[..parent.header]);
            }
            bytes.extend_from_slice(tail);
            let request = pb::JobRequest {
                program: Some(pb::job_request::Program::ResumeJob(id.clone())),
                request_id: format!("resume-{id}"),
                ..Default::default()
            };
            match submit_until_answered(&client, &ledger, &parent.machine, &request, &stop).await {
                Some(job) => lock(&ledger).accepted(
                    job,
                    JobEntry {
                        machine: parent.machine.clone(),
                        request_id: request.request_id.clone(),
                        bytes,
                        header: parent.header,
                        resume_of: Some(id),
                        last: None,
                        ended_again: 0,
                        resumed: false,
                    },
                ),
                None => lock(&ledger).figures.resumes_refused += 1,
            }
        }
        tokio::select! {
            () = stop.cancelled() => {}
            () = tokio::time::sleep(Duration::from_millis(500)) => {}
        }
    }
}

/// Reads the latest event of every job the gateway keeps, every two seconds, into the ledger.
pub(crate) async fn tracker(client: Client, ledger: Shared, stop: CancellationToken) {
    while !stop.is_cancelled() {
        if let Ok(events) = client.recent_jobs(None).await {
            let mut l = lock(&ledger);
            for e in events {
                l.saw(e);
            }
        }
        tokio::select! {
            () = stop.cancelled() => {}
            () = tokio::time::sleep(Duration::from_secs(2)) => {}
        }
    }
}

/// The other writes a cell sees: DO outputs, the PLC's tag and transfers, library stores and
/// files posted into the folder.
pub(crate) async fn writer(
    client: Client,
    a_family: Vec<String>,
    folder: std::path::PathBuf,
    ledger: Shared,
    stop: CancellationToken,
) {
    let mut tick = 0u64;
    while !stop.is_cancelled() {
        tick += 1;
        let mut ok = Vec::new();
        if let Some(m) = a_family.get(tick as usize % a_family.len().max(1)) {
            ok.push(client.put_do(m, (tick % 256) as u8, None).await.is_ok());
        }
        if tick % 2 == 0 {
            ok.push(
                client
                    .tag_set("plc-1/count", (tick % 1000) as f64)
                    .await
                    .is_ok(),
            );
            ok.push(
                client
                    .plc_send("plc-4", 1, format!("SOAK{tick}").into_bytes())
                    .await
                    .is_ok(),
            );
        }
        if tick % 5 == 0 {
            let (bytes, _) = program(&format!("LIB{tick}"), 9000 + (tick % 100) as u32, 2048);
            ok.push(
                client
                    .program_put(&format!("SOAK{}", tick % 20), &bytes)
                    .await
                    .is_ok(),
            );
        }
        if tick % 7 == 0 {
            let (bytes, _) = program(&format!("CAM{tick}"), 8000 + (tick % 100) as u32, 3000);
            let name = folder.join(format!("CAM{}.nc", tick % 10));
            let tmp = folder.join(format!(".CAM{}.tmp", tick % 10));
            // As a CAM post-processor that writes whole and renames.
            if tokio::fs::write(&tmp, &bytes).await.is_ok()
                && tokio::fs::rename(&tmp, &name).await.is_ok()
            {
                lock(&ledger).figures.folder_posts += 1;
            }
        }
        {
            let mut l = lock(&ledger);
            for ok in ok {
                if ok {
                    l.figures.writes_ok += 1;
                } else {
                    l.figures.writes_failed += 1;
                }
            }
        }
        tokio::select! {
            () = stop.cancelled() => {}
            () = tokio::time::sleep(Duration::from_secs(1)) => {}
        }
    }
}

/// One HTTP GET on loopback, its status code; bounded in time and size.
pub(crate) async fn http_get(port: u16, path: &str) -> Option<u16> {
    let run = async {
        let mut s = tokio::net::TcpStream::connect(("127.0.0.1", port))
            .await
            .ok()?;
        let req = format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n");
        s.write_all(req.as_bytes()).await.ok()?;
        let mut head = vec![0u8; 64 * 1024];
        let mut got = 0;
        // Read what comes (the body too, up to the buffer) until the server closes.
        loop {
            if got == head.len() {
                break;
            }
            match s.read(&mut head[got..]).await {
                Ok(0) | Err(_) => break,
                Ok(n) => got += n,
            }
        }
        let text = std::str::from_utf8(&head[..got.min(32)]).ok()?;
        text.split_whitespace().nth(1)?.parse().ok()
    };
    tokio::time::timeout(Duration::from_secs(5), run)
        .await
        .ok()
        .flatten()
}

/// Readers of the console's pages and of MTConnect's `/current` and `/sample`.
pub(crate) async fn readers(console: u16, mtconnect: u16, ledger: Shared, stop: CancellationToken) {
    let pages = [
        (console, "/"),
        (mtconnect, "/current"),
        (mtconnect, "/sample?count=100"),
        (mtconnect, "/probe"),
    ];
    let mut i = 0;
    while !stop.is_cancelled() {
        let (port, path) = pages[i % pages.len()];
        i += 1;
        let ok = http_get(port, path).await.is_some_and(|c| c < 500);
        {
            let mut l = lock(&ledger);
            if ok {
                l.figures.reads_ok += 1;
            } else {
                l.figures.reads_failed += 1;
            }
        }
        tokio::select! {
            () = stop.cancelled() => {}
            () = tokio::time::sleep(Duration::from_millis(500)) => {}
        }
    }
}
