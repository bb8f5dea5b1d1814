//! The gateway alone, at scale: N simulated boards in one process (`cellgate sim fanuc
//! --boards N`), a gateway with N `tcp` machines in another (`cellgate run`), and this program
//! as the factory's client on the bus. Everything is measured from outside the gateway:
//!
//! - **CPU**: the gateway's user + system time from `/proc/PID/stat`, idle (links up, no job)
//!   and busy (every machine running one job from the library, one DO put per machine a
//!   second), as a share of one core; the boards' process beside it, to show it kept up;
//! - **memory**: the gateway's resident set (`VmRSS`, and `VmHWM` for the busy peak) per link,
//!   idle, busy, and five seconds after the last job ended ("after": what the jobs gave back);
//! - **throughput**: each job's bytes from its first `progress` event to `completed` over the
//!   time between them (the gateway's timestamps), against the line's characters a second, as
//!   a share of the protocol's efficiency bound (see [`Proto::bound`]); the wait for the
//!   board's first GTD before it is the protocol's;
//! - **DO delay**: the gateway's `cellgate.do.delay` histogram, scraped from its Prometheus
//!   endpoint: from the put's zenoh timestamp (set by this client) to the host engine taking
//!   the SDO request; p50 and p99 are bucket upper bounds. The wait for the board's next SAT
//!   or GTD comes after and belongs to the protocol: "to board" gives put → the board's `do`
//!   event, which includes it.
//!
//! `cargo bench --bench gateway_alone` runs N = 64, 256, 1024 at 19 200 and 86 400 baud for
//! Protocol A, Expansion A (n = 4) and Protocol B (19 200 only: §2.2 allows no more). Pick
//! with `-- --machines 1024 --baud 86400 --protocol exp-a --job-seconds 20`; `--no-do` leaves
//! the DO puts out, and `--undeclared-do` puts them on keys the client did not declare;
//! `--no-history` turns the cell's history off; `--console-pages N` serves the console and
//! opens N pages (each its first load, then its event stream) while the jobs run; `--window N`
//! sets the machines' `transport.window`; `--zenoh-config FILE` gives the gateway's session
//! that zenoh configuration file.
//! `CELLGATE_GATEWAY_BIN=path` measures another gateway binary against the same boards;
//! `--compare path` measures that binary and this build's, one after the other on each case,
//! and prints their rows side by side (build "before" and "after"). Under
//! `cargo test` a smoke pass (4 machines, short jobs) checks that the benchmark still works.

#[path = "../tests/common/mod.rs"]
mod common;

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use cellgate::bus::keys::{CellKeys, MachineLeaf};
use cellgate_core::fanuc::message::MAX_DAT_DATA;
use cellgate_core::fanuc::packet;
use cellgate_core::fanuc::sat::Params;
use cellgate_core::pb;
use futures::StreamExt;
use prost::Message;
use zenoh::Session;

const BIN: &str = env!("CARGO_BIN_EXE_cellgate");

/// The gateway binary measured by default: this build's, or another one named by
/// `CELLGATE_GATEWAY_BIN` (an older build, to compare on the same machine; the boards stay
/// this build's).
fn gateway_bin() -> String {
    std::env::var("CELLGATE_GATEWAY_BIN").unwrap_or_else(|_| BIN.to_string())
}
const PROGRAM: &str = "O1000";

#[derive(Debug, Clone, Copy, PartialEq)]
enum Proto {
    A,
    ExpA,
    B,
}

impl Proto {
    fn parse(s: &str) -> Proto {
        match s {
            "a" => Proto::A,
            "exp-a" => Proto::ExpA,
            "b" => Proto::B,
            other => panic!("--protocol takes a, exp-a or b, not {other}"),
        }
    }
    fn label(self) -> &'static str {
        match self {
            Proto::A => "A",
            Proto::ExpA => "Exp. A n=4",
            Proto::B => "B",
        }
    }
    fn sim(self) -> &'static str {
        match self {
            Proto::A => "a",
            Proto::ExpA => "exp-a",
            Proto::B => "b",
        }
    }
    fn cell(self) -> &'static str {
        match self {
            Proto::A => "protocol = \"a\"\n",
            Proto::ExpA => "protocol = \"expansion-a\"\npacket_n = 4\n",
            Proto::B => "protocol = \"b\"\n",
        }
    }
    /// The most a protocol can deliver: data ÷ characters the line's time allows. Framing
    /// only for Expansion A and B (the `link_efficiency` benchmark's upper bound); Protocol A
    /// adds the board's wait Tx = 100 ms before every GTD (§4.3 (4)), which no host can
    /// shorten: one GTD (6 characters) and one DAT of L = min(4096, Nb − No) data bytes
    /// (L + 6) a cycle.
    fn bound(self, chars_per_s: f64) -> f64 {
        match self {
            Proto::B => 1.0,
            Proto::ExpA => packet::data_len(4) as f64 / packet::packet_len(4) as f64,
            Proto::A => {
                let p = Params::POWER_ON;
                let l = (MAX_DAT_DATA as f64).min(f64::from(p.nb - p.no));
                l / (l + 12.0 + 0.1 * chars_per_s)
            }
        }
    }
}

struct Case {
    machines: u16,
    baud: u32,
    proto: Proto,
    job_seconds: f64,
    idle_seconds: u64,
    /// A DO put per machine a second while the jobs run.
    dos: bool,
    /// The DO puts go out on keys the client did not declare.
    undeclared_do: bool,
    /// The cell's history (and audit trail) kept.
    history: bool,
    /// Console pages open while the jobs run (each its event stream); 0: no console.
    console_pages: usize,
    /// The machines' `transport.window`; `None`: the cell file leaves it out.
    window: Option<u32>,
    /// The gateway binary, and what its row calls it.
    gateway: (String, &'static str),
    /// A zenoh configuration file for the gateway's session (`bus.zenoh_config`).
    zenoh_config: Option<String>,
}

/// What the boards' process said, with when this program read it.
#[derive(Default)]
struct SimLog {
    listening: usize,
    /// (board, image) → when the board's DO took that image.
    dos: HashMap<(u64, u64), Instant>,
}

/// A DO put: (board, image) and when it was made.
type Put = ((u64, u64), Instant);

/// Clock ticks a second for `/proc/PID/stat`.
fn ticks_per_second() -> f64 {
    // SAFETY: sysconf has no preconditions.
    let t = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    if t > 0 { t as f64 } else { 100.0 }
}

/// CPU seconds (user + system) process `pid` has used.
fn cpu_of(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    // Fields after the command name in parentheses: state is field 3, utime 14, stime 15.
    let rest = stat.rsplit_once(") ").map(|(_, r)| r).unwrap_or("");
    let f: Vec<f64> = rest
        .split_whitespace()
        .map(|v| v.parse().unwrap_or(0.0))
        .collect();
    if f.len() < 13 {
        return 0.0;
    }
    (f[11] + f[12]) / ticks_per_second()
}

/// (VmRSS, VmHWM) of process `pid`, KiB.
fn memory_of(pid: u32) -> (u64, u64) {
    common::memory_kib(&pid.to_string())
}

/// Kills the child when dropped, so that a failed run leaves no process behind.
struct Reaped(Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start_boards(case: &Case, first: u16, log: Arc<Mutex<SimLog>>) -> Reaped {
    let mut child = Command::new(BIN)
        .args(["sim", "fanuc", "--autostart", "--consume-rate", "0"])
        .args(["--boards", &case.machines.to_string()])
        .args(["--protocol", case.proto.sim()])
        .args(["--baud", &case.baud.to_string()])
        .args(["--first-request-delay-ms", "100"])
        .args(["--listen", &format!("127.0.0.1:{first}")])
        .env("RUST_LOG", "error")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("cellgate sim fanuc");
    let out = child.stdout.take().expect("piped stdout");
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines() {
            let Ok(line) = line else { break };
            let Ok(e) = serde_json::from_str::<serde_json::Value>(&line) else {
                continue;
            };
            let mut log = log.lock().unwrap();
            match e["event"].as_str() {
                Some("listening") => log.listening += 1,
                Some("do") => {
                    let board = e["board"].as_u64().unwrap_or(0);
                    let image = e["image"].as_u64().unwrap_or(0);
                    log.dos.insert((board, image), Instant::now());
                }
                _ => {}
            }
        }
    });
    Reaped(child)
}

fn cell_file(
    case: &Case,
    first: u16,
    (bus_port, prom_port, console_port): (u16, u16, u16),
    dir: &Path,
) -> String {
    let mut text = format!(
        "cell = \"scale\"\n[bus]\nlisten = [\"tcp/127.0.0.1:{bus_port}\"]\n{}\
         [telemetry]\nprometheus = \"127.0.0.1:{prom_port}\"\n\
         [programs]\ndir = {:?}\n",
        case.zenoh_config
            .as_ref()
            .map(|z| format!("zenoh_config = {z:?}\n"))
            .unwrap_or_default(),
        dir.join("programs")
    );
    if !case.history {
        text.push_str("[history]\nenabled = false\n");
    }
    if case.console_pages > 0 {
        text.push_str(&format!(
            "[console]\nlisten = \"127.0.0.1:{console_port}\"\n"
        ));
    }
    let window = case
        .window
        .map(|w| format!(", window = {w}"))
        .unwrap_or_default();
    for i in 0..case.machines {
        text.push_str(&format!(
            "[[machines]]\nname = \"m{i}\"\n{}\
             transport = {{ kind = \"tcp\", address = \"127.0.0.1:{}\", line = {{ baud = {} }}{window} }}\n",
            case.proto.cell(),
            first + i,
            case.baud
        ));
    }
    text
}

/// Machines whose link is up (idle or sending), from one wildcard status get.
async fn links_up(client: &Session, keys: &CellKeys) -> usize {
    let Ok(replies) = client
        .get(keys.leaf("*", MachineLeaf::Status))
        .timeout(Duration::from_secs(10))
        .await
    else {
        return 0;
    };
    let mut up = 0;
    while let Ok(r) = replies.recv_async().await {
        if let Ok(s) = r.result() {
            if let Ok(st) = pb::MachineStatus::decode(s.payload().to_bytes().as_ref()) {
                if matches!(
                    pb::LinkState::try_from(st.link_state),
                    Ok(pb::LinkState::Idle | pb::LinkState::Sending)
                ) {
                    up += 1;
                }
            }
        }
    }
    up
}

/// p50 and p99 of a Prometheus histogram summed over its series, as bucket upper bounds, and
/// the count.
fn histogram_percentiles(metrics: &str, name: &str) -> Option<(f64, f64, u64)> {
    let mut buckets: Vec<(f64, u64)> = Vec::new();
    for line in metrics.lines() {
        let Some(rest) = line.strip_prefix(&format!("{name}_bucket{{")) else {
            continue;
        };
        let le = rest.split("le=\"").nth(1)?.split('"').next()?;
        let le: f64 = if le == "+Inf" {
            f64::INFINITY
        } else {
            le.parse().ok()?
        };
        let count: u64 = line.rsplit(' ').next()?.parse().ok()?;
        match buckets.iter_mut().find(|(b, _)| *b == le) {
            Some((_, c)) => *c += count,
            None => buckets.push((le, count)),
        }
    }
    buckets.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total = buckets.last()?.1;
    if total == 0 {
        return None;
    }
    let at = |p: f64| {
        let want = (total as f64 * p).ceil() as u64;
        buckets
            .iter()
            .find(|(_, c)| *c >= want)
            .map_or(f64::INFINITY, |(b, _)| *b)
    };
    Some((at(0.5), at(0.99), total))
}

async fn scrape(port: u16) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let Ok(mut s) = tokio::net::TcpStream::connect(("127.0.0.1", port)).await else {
        return String::new();
    };
    let _ = s
        .write_all(b"GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        .await;
    let mut body = String::new();
    let _ = s.read_to_string(&mut body).await;
    body
}

/// Submits one job, asking again while the gateway says it is busy.
async fn submit(client: &Session, key: &str, request: Vec<u8>) {
    loop {
        let replies = client
            .get(key)
            .payload(request.clone())
            .timeout(Duration::from_secs(120))
            .await
            .expect("get");
        let reply = replies.recv_async().await.expect("a reply to a job submit");
        match reply.result() {
            Ok(s) => {
                let accepted = pb::JobAccepted::decode(s.payload().to_bytes().as_ref()).unwrap();
                assert!(!accepted.job_id.is_empty());
                return;
            }
            Err(e) => match pb::ErrorReply::decode(e.payload().to_bytes().as_ref()) {
                Ok(r) if r.code() == pb::ErrorCode::Busy => {
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
                other => panic!("{key}: {other:?} ({:?})", e.payload().to_bytes()),
            },
        }
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() as f64 - 1.0) * p).round() as usize]
}

async fn run(case: &Case) {
    let n = usize::from(case.machines);
    let first = common::bus::free_ports(case.machines);
    let (bus_port, prom_port, console_port) = (
        common::bus::free_port(),
        common::bus::free_port(),
        common::bus::free_port(),
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let chars_per_s = f64::from(case.baud) / 11.0;
    let bound = case.proto.bound(chars_per_s);
    let size = (case.job_seconds * chars_per_s * bound) as usize;
    std::fs::create_dir_all(dir.path().join("programs")).unwrap();
    std::fs::write(
        dir.path().join("programs").join(PROGRAM),
        common::nc_program(size, 1000),
    )
    .unwrap();
    let cell = dir.path().join("cell.toml");
    std::fs::write(
        &cell,
        cell_file(case, first, (bus_port, prom_port, console_port), dir.path()),
    )
    .unwrap();

    let log = Arc::new(Mutex::new(SimLog::default()));
    let boards = start_boards(case, first, log.clone());
    let t0 = Instant::now();
    while log.lock().unwrap().listening < n {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "boards never listened"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let gateway_log = std::fs::File::create(dir.path().join("gateway.log")).unwrap();
    let gateway = Reaped(
        Command::new(&case.gateway.0)
            .args(["run", "--config"])
            .arg(&cell)
            .current_dir(dir.path())
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(gateway_log)
            .spawn()
            .expect("cellgate run"),
    );
    let gpid = gateway.0.id();
    let spid = boards.0.id();
    let gateway_log = dir.path().join("gateway.log");
    let t0 = Instant::now();
    let client = loop {
        match cellgate::bus::open(&common::bus::client_config(bus_port)).await {
            Ok(c) => break c,
            Err(e) => {
                assert!(
                    t0.elapsed() < Duration::from_secs(60)
                        && std::fs::metadata(format!("/proc/{gpid}")).is_ok(),
                    "the gateway never listened ({e}): {}",
                    std::fs::read_to_string(&gateway_log).unwrap_or_default()
                );
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
    };
    let keys = CellKeys::new("cellgate", "scale").unwrap();
    let t0 = Instant::now();
    loop {
        let up = links_up(&client, &keys).await;
        if up == n {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "only {up} of {n} links came up: {}",
            std::fs::read_to_string(&gateway_log).unwrap_or_default()
        );
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    let up_after = t0.elapsed();

    // Idle: every link up, nothing to send.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let (g0, s0, w0) = (cpu_of(gpid), cpu_of(spid), Instant::now());
    tokio::time::sleep(Duration::from_secs(case.idle_seconds)).await;
    let idle_wall = w0.elapsed().as_secs_f64();
    let idle_cpu = (cpu_of(gpid) - g0) / idle_wall;
    let idle_sim = (cpu_of(spid) - s0) / idle_wall;
    let (idle_rss, _) = memory_of(gpid);

    // The console's pages: each loads the overview, then follows the cell's events.
    let console = format!("http://127.0.0.1:{console_port}");
    let mut first_loads = Vec::new();
    let mut pages = Vec::new();
    let events_seen = Arc::new(std::sync::atomic::AtomicU64::new(0));
    for _ in 0..case.console_pages {
        let http = reqwest::Client::builder()
            .cookie_store(true)
            .build()
            .unwrap();
        http.get(format!("{console}/api/v1/me"))
            .send()
            .await
            .unwrap();
        let t = Instant::now();
        for path in [
            "/",
            "/assets/app.js",
            "/api/v1/cells",
            "/api/v1/cells/scale/overview",
        ] {
            let r = http.get(format!("{console}{path}")).send().await.unwrap();
            assert!(r.status().is_success(), "{path}: {}", r.status());
            r.bytes().await.unwrap();
        }
        first_loads.push(t.elapsed());
        let seen = events_seen.clone();
        let url = format!("{console}/api/v1/cells/scale/events");
        pages.push(tokio::spawn(async move {
            let mut r = http.get(url).send().await.unwrap();
            while let Ok(Some(chunk)) = r.chunk().await {
                let n = chunk.windows(6).filter(|w| w == b"event:").count();
                seen.fetch_add(n as u64, std::sync::atomic::Ordering::Relaxed);
            }
        }));
    }

    // Busy: a job per machine, a DO put per machine a second.
    let events = client
        .declare_subscriber(keys.job_events("*", "*"))
        // Room for every event while the submits run: a subscriber that does not keep up
        // holds the gateway's job events back (they are published with QoS block).
        .with(zenoh::handlers::FifoChannel::new(1 << 20))
        .await
        .unwrap();
    let (g0, s0, w0) = (cpu_of(gpid), cpu_of(spid), Instant::now());
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Library(PROGRAM.to_string())),
        ..Default::default()
    }
    .encode_to_vec();
    let submits = futures::stream::iter(0..n)
        .map(|i| {
            let (client, key, request) = (
                client.clone(),
                keys.leaf(&format!("m{i}"), MachineLeaf::Submit),
                request.clone(),
            );
            async move { submit(&client, &key, request).await }
        })
        .buffer_unordered(32)
        .collect::<Vec<()>>();
    submits.await;
    let submitted_in = w0.elapsed();
    let puts: Arc<Mutex<Vec<Put>>> = Arc::default();
    let do_task = (case.dos && case.proto != Proto::B).then(|| {
        let (client, keys, puts) = (client.clone(), keys.clone(), puts.clone());
        let declare_do = !case.undeclared_do;
        tokio::spawn(async move {
            // Declared once, as a client that puts to the same machines again and again
            // would: the gateway then routes each put by the key's id instead of matching
            // its text against every declaration (README, "A thousand links").
            let mut do_keys = Vec::with_capacity(n);
            for i in 0..n {
                let key = keys.leaf(&format!("m{i}"), MachineLeaf::Do);
                do_keys.push(if declare_do {
                    client.declare_keyexpr(key).await.unwrap()
                } else {
                    zenoh::key_expr::KeyExpr::try_from(key).unwrap()
                });
            }
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            for second in 1u64.. {
                tick.tick().await;
                // Spread over the second, as independent clients would.
                let gap = Duration::from_secs(1) / u32::try_from(n).unwrap_or(1);
                for (i, key) in do_keys.iter().enumerate() {
                    let image = (second * 7 + i as u64) % 256;
                    let cmd = pb::DoCommand {
                        value: image as u32,
                        mask: None,
                    };
                    let at = Instant::now();
                    let _ = client
                        .put(key.clone(), cmd.encode_to_vec())
                        .timestamp(client.new_timestamp())
                        .await;
                    puts.lock().unwrap().push(((i as u64, image), at));
                    tokio::time::sleep(gap).await;
                }
            }
        })
    });
    let mut efficiency = Vec::new();
    let mut first_progress: HashMap<String, (u64, u64)> = HashMap::new();
    let mut failed = 0;
    // Completed without a progress event before (too short to measure).
    let mut unmeasured = 0;
    let mut peak_rss = 0;
    let deadline = Instant::now() + Duration::from_secs_f64(case.job_seconds * 4.0 + 60.0);
    while efficiency.len() + failed + unmeasured < n {
        let left = deadline.saturating_duration_since(Instant::now());
        let Ok(Ok(sample)) = tokio::time::timeout(left.min(Duration::from_millis(500)), async {
            events.recv_async().await
        })
        .await
        else {
            peak_rss = peak_rss.max(memory_of(gpid).0);
            assert!(
                Instant::now() < deadline,
                "{} of {n} jobs ended in time",
                efficiency.len() + failed + unmeasured
            );
            continue;
        };
        let Ok(ev) = pb::JobEvent::decode(sample.payload().to_bytes().as_ref()) else {
            continue;
        };
        match ev.kind {
            Some(pb::job_event::Kind::Progress(p)) => {
                first_progress
                    .entry(ev.job_id)
                    .or_insert((p.bytes_sent, ev.unix_ms));
            }
            Some(pb::job_event::Kind::Completed(c)) => {
                // Measured over a second at least: acknowledgements come in steps.
                match first_progress.get(&ev.job_id) {
                    Some(&(b0, t0)) if ev.unix_ms >= t0 + 1000 => {
                        let secs = (ev.unix_ms - t0) as f64 / 1000.0;
                        let bytes = c.bytes_sent.saturating_sub(b0) as f64;
                        efficiency.push(bytes / (secs * chars_per_s) / bound);
                    }
                    _ => unmeasured += 1,
                }
            }
            Some(pb::job_event::Kind::Failed(_) | pb::job_event::Kind::Cancelled(_)) => failed += 1,
            _ => {}
        }
    }
    let busy_wall = w0.elapsed().as_secs_f64();
    let busy_cpu = (cpu_of(gpid) - g0) / busy_wall;
    let busy_sim = (cpu_of(spid) - s0) / busy_wall;
    let (_, hwm) = memory_of(gpid);
    if let Some(t) = do_task {
        t.abort();
    }
    // What the jobs took and gave back: resident a few seconds after the last one ended.
    tokio::time::sleep(Duration::from_secs(5)).await;
    let (after_rss, _) = memory_of(gpid);
    for p in pages {
        p.abort();
    }
    let metrics = scrape(prom_port).await;
    let delay = histogram_percentiles(&metrics, "cellgate_do_delay_seconds");
    let mut to_board: Vec<f64> = {
        let log = log.lock().unwrap();
        puts.lock()
            .unwrap()
            .iter()
            .filter_map(|(k, at)| log.dos.get(k).map(|d| d.duration_since(*at).as_secs_f64()))
            .collect()
    };
    to_board.sort_by(f64::total_cmp);
    efficiency.sort_by(f64::total_cmp);
    drop(client);
    drop(gateway);
    drop(boards);

    let kib = |k: u64| k as f64 / n as f64;
    let ms = |s: f64| s * 1000.0;
    println!(
        "| {n} | {} | {} | {} | {:.1} % | {:.1} % | {:.0} KiB | {:.0} KiB | {:.0} KiB | {:.1} % / {:.1} % | {} | {} | {:.0} % | {:.1} s |",
        case.baud,
        case.proto.label(),
        case.gateway.1,
        100.0 * idle_cpu,
        100.0 * busy_cpu,
        kib(idle_rss),
        kib(hwm.max(peak_rss)),
        kib(after_rss),
        100.0 * percentile(&efficiency, 0.0),
        100.0 * percentile(&efficiency, 0.5),
        match delay {
            Some((p50, p99, count)) => format!("{:.1} / {:.1} ms ({count})", ms(p50), ms(p99)),
            None => "–".to_string(),
        },
        if to_board.is_empty() {
            "–".to_string()
        } else {
            format!(
                "{:.0} / {:.0} ms",
                ms(percentile(&to_board, 0.5)),
                ms(percentile(&to_board, 0.99))
            )
        },
        100.0 * busy_sim,
        up_after.as_secs_f64(),
    );
    println!(
        "  ({n} jobs accepted in {:.1} s; idle boards {:.1} % of a core)",
        submitted_in.as_secs_f64(),
        100.0 * idle_sim
    );
    if failed + unmeasured > 0 {
        println!("  ({failed} of {n} jobs failed, {unmeasured} too short to measure)");
    }
    if case.console_pages > 0 {
        first_loads.sort();
        println!(
            "  ({} console pages: first load (page, script, cells, overview of {n} machines) {:.0} ms median, {:.0} ms slowest; {:.0} events a second per page)",
            case.console_pages,
            ms(first_loads[first_loads.len() / 2].as_secs_f64()),
            ms(first_loads.last().map_or(0.0, Duration::as_secs_f64)),
            events_seen.load(std::sync::atomic::Ordering::Relaxed) as f64
                / busy_wall
                / case.console_pages as f64
        );
    }
    println!("  (history {})", if case.history { "on" } else { "off" });
}

fn list<T>(args: &[String], flag: &str, default: &str, parse: impl Fn(&str) -> T) -> Vec<T> {
    let v = args
        .iter()
        .position(|a| a == flag)
        .and_then(|i| args.get(i + 1))
        .map_or(default, |s| s.as_str());
    v.split(',').map(|s| parse(s.trim())).collect()
}

fn main() {
    // The console's pages are read with reqwest, built without a crypto provider.
    let _ = tokio_rustls::rustls::crypto::ring::default_provider().install_default();
    let args: Vec<String> = std::env::args().collect();
    let full = args.iter().any(|a| a == "--bench");
    let (machines, bauds, protos, job_seconds, idle_seconds) = if full {
        (
            list(&args, "--machines", "64,256,1024", |s| {
                s.parse::<u16>().unwrap()
            }),
            list(&args, "--baud", "19200,86400", |s| {
                s.parse::<u32>().unwrap()
            }),
            list(&args, "--protocol", "a,exp-a,b", Proto::parse),
            list(&args, "--job-seconds", "20", |s| s.parse::<f64>().unwrap())[0],
            5,
        )
    } else {
        (vec![4], vec![19_200], vec![Proto::ExpA, Proto::B], 4.0, 1)
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .expect("tokio runtime");
    println!(
        "| links | baud | protocol | build | CPU idle | CPU busy | RSS/link idle | RSS/link busy | RSS/link after | \
         jobs: min / median of bound | DO delay p50 / p99 | DO to board p50 / p99 | boards' CPU | links up in |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    // `--compare OTHER`: OTHER ("before") then this build ("after") on every case.
    let builds: Vec<(String, &'static str)> = match args
        .iter()
        .position(|a| a == "--compare")
        .and_then(|i| args.get(i + 1))
    {
        Some(other) => {
            let other = std::fs::canonicalize(other)
                .unwrap_or_else(|e| panic!("--compare {other}: {e}"))
                .to_string_lossy()
                .into_owned();
            vec![(other, "before"), (BIN.to_string(), "after")]
        }
        None => vec![(gateway_bin(), "this")],
    };
    for &n in &machines {
        for &baud in &bauds {
            for &proto in &protos {
                if proto == Proto::B && baud > 19_200 {
                    continue;
                }
                for gateway in &builds {
                    let case = Case {
                        machines: n,
                        baud,
                        proto,
                        job_seconds,
                        idle_seconds,
                        dos: !args.iter().any(|a| a == "--no-do"),
                        undeclared_do: args.iter().any(|a| a == "--undeclared-do"),
                        history: !args.iter().any(|a| a == "--no-history"),
                        console_pages: list(&args, "--console-pages", "0", |s| {
                            s.parse::<usize>().unwrap()
                        })[0],
                        window: args
                            .iter()
                            .position(|a| a == "--window")
                            .and_then(|i| args.get(i + 1))
                            .map(|s| s.parse().expect("--window takes a number of bytes")),
                        gateway: gateway.clone(),
                        zenoh_config: args
                            .iter()
                            .position(|a| a == "--zenoh-config")
                            .and_then(|i| args.get(i + 1))
                            .map(|p| {
                                std::fs::canonicalize(p)
                                    .unwrap_or_else(|e| panic!("--zenoh-config {p}: {e}"))
                                    .to_string_lossy()
                                    .into_owned()
                            }),
                    };
                    rt.block_on(run(&case));
                }
            }
        }
    }
}
