//! The gateway's listeners against clients that connect and then do nothing useful, with raw
//! sockets: a request head never finished, a kept-alive connection left idle, an SHDR line
//! without an end, an SHDR agent that never pings while observations flow, MTConnect streams
//! nobody reads, `interval=0` streams, and a flood of connections on a gateway with few open
//! files (docs/security.md, "Listeners").

use crate::common;

use std::time::{Duration, Instant};

use cellgate::door::http::BODY_IDLE;
use cellgate::door::{HEAD_TIMEOUT, WRITE_TIMEOUT};
use cellgate::mtconnect::shdr::{IDLE, MAX_LINE};
use cellgate_core::config::CellConfig;
use common::bus::free_port;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use super::gateway::Gateway;

/// A guard against a hang, well past the time the gateway is given: not a time asserted.
const SLACK: Duration = Duration::from_secs(20);

/// The embedded default cell in this process: its console, its MTConnect agent and an SHDR
/// port, each on a free port.
struct Cell {
    gateway: Gateway,
    console: String,
    mtconnect: String,
    shdr: String,
}

impl Cell {
    async fn start() -> Cell {
        let (mtconnect, shdr) = (free_port(), free_port());
        let gateway = Gateway::start(|c, _| {
            let m = c.mtconnect.get_or_insert_with(Default::default);
            m.listen = format!("127.0.0.1:{mtconnect}");
            m.shdr_listen = Some(format!("127.0.0.1:{shdr}"));
        })
        .await;
        Cell {
            console: gateway.url.trim_start_matches("http://").to_string(),
            gateway,
            mtconnect: format!("127.0.0.1:{mtconnect}"),
            shdr: format!("127.0.0.1:{shdr}"),
        }
    }

    async fn stop(self) {
        self.gateway.stop().await;
    }
}

/// Waits until `url` answers 200 (at most a minute).
async fn wait_200(url: &str) {
    for _ in 0..600 {
        if status(url).await == Some(200) {
            return;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("{url} never answered 200");
}

/// The status `url` answers, if it answers.
async fn status(url: &str) -> Option<u16> {
    let http = reqwest::Client::builder()
        .timeout(Duration::from_secs(5))
        .build()
        .ok()?;
    Some(http.get(url).send().await.ok()?.status().as_u16())
}

/// Reads `s` until the gateway closes it; answers what came and whether it closed within
/// `limit`.
async fn read_to_close(s: &mut TcpStream, limit: Duration) -> (Vec<u8>, bool) {
    let mut got = Vec::new();
    let closed = tokio::time::timeout(limit, async {
        let mut buf = [0u8; 8192];
        loop {
            match s.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) => got.extend_from_slice(&buf[..n]),
            }
        }
    })
    .await
    .is_ok();
    (got, closed)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_head_never_finished_is_cut_off_on_the_console_and_the_agent() {
    let cell = Cell::start().await;
    let half = |addr: String| async move {
        let mut s = TcpStream::connect(&addr).await.unwrap();
        // Half a head: the request line and one header, never the blank line.
        s.write_all(format!("GET /probe HTTP/1.1\r\nHost: {addr}\r\n").as_bytes())
            .await
            .unwrap();
        let started = Instant::now();
        let (_, closed) = read_to_close(&mut s, HEAD_TIMEOUT + SLACK).await;
        (addr, closed, started.elapsed())
    };
    let (console, agent) = tokio::join!(half(cell.console.clone()), half(cell.mtconnect.clone()));
    for (addr, closed, after) in [console, agent] {
        assert!(closed, "{addr}: a half head kept its connection {after:?}");
        eprintln!("{addr}: half a head closed after {after:?}");
    }
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_body_that_stops_is_cut_off() {
    let cell = Cell::start().await;
    let addr = cell.console.clone();
    let mut s = TcpStream::connect(&addr).await.unwrap();
    // A whole head that promises 100 bytes, then 9 of them and nothing more.
    s.write_all(
        format!(
            "POST /api/v1/login HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n\
             Content-Length: 100\r\n\r\n{{\"user\":"
        )
        .as_bytes(),
    )
    .await
    .unwrap();
    let started = Instant::now();
    let (got, closed) = read_to_close(&mut s, BODY_IDLE + SLACK).await;
    let after = started.elapsed();
    let answer = String::from_utf8_lossy(&got);
    assert!(
        closed,
        "a body that stopped kept its connection {after:?}: {answer}"
    );
    assert!(after >= BODY_IDLE, "cut off before its time: {after:?}");
    eprintln!("a stopped body: closed after {after:?}, answered {answer:?}");
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_kept_alive_connection_left_idle_is_closed_too() {
    let cell = Cell::start().await;
    let idle = |addr: String, path: &'static str| async move {
        let mut s = TcpStream::connect(&addr).await.unwrap();
        s.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
            .await
            .unwrap();
        // The answer comes, and the connection is kept for a next request that never comes.
        let mut first = vec![0u8; 4096];
        let n = tokio::time::timeout(SLACK, s.read(&mut first))
            .await
            .expect("an answer")
            .unwrap();
        let head = String::from_utf8_lossy(&first[..n]).to_lowercase();
        assert!(head.starts_with("http/1.1 200"), "{addr}: {head}");
        assert!(!head.contains("connection: close"), "{addr}: {head}");
        let started = Instant::now();
        let (_, closed) = read_to_close(&mut s, HEAD_TIMEOUT + SLACK).await;
        (addr, closed, started.elapsed())
    };
    let (console, agent) = tokio::join!(
        idle(cell.console.clone(), "/health"),
        idle(cell.mtconnect.clone(), "/probe")
    );
    for (addr, closed, after) in [console, agent] {
        assert!(
            closed,
            "{addr}: an idle kept-alive connection stayed {after:?}"
        );
        eprintln!("{addr}: idle kept-alive connection closed after {after:?}");
    }
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_shdr_line_without_an_end_is_cut_off_at_its_bound() {
    let cell = Cell::start().await;
    let (before, _) = common::memory_kib("self");
    let s = TcpStream::connect(&cell.shdr).await.unwrap();
    let (mut read, mut write) = s.into_split();
    // What the adapter sends (the state) is read, so that its writes never wait.
    let reader = tokio::spawn(async move {
        let mut buf = vec![0u8; 64 * 1024];
        while let Ok(n) = read.read(&mut buf).await {
            if n == 0 {
                break;
            }
        }
    });
    const TOTAL: usize = 64 << 20;
    let chunk = vec![b'a'; 64 * 1024];
    let mut sent = 0;
    let refused = tokio::time::timeout(SLACK, async {
        while sent < TOTAL {
            match write.write_all(&chunk).await {
                Ok(()) => sent += chunk.len(),
                Err(_) => return true,
            }
        }
        false
    })
    .await
    .unwrap_or(false);
    let (after, _) = common::memory_kib("self");
    eprintln!(
        "SHDR: {sent} bytes without a newline taken before the close (line bound {MAX_LINE}); \
         this process's VmRSS {before} → {after} KiB"
    );
    assert!(
        refused && sent < TOTAL,
        "the adapter took {sent} bytes of one line"
    );
    tokio::time::timeout(SLACK, reader)
        .await
        .expect("the adapter closed the connection")
        .unwrap();
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_shdr_agent_that_never_pings_is_closed_while_observations_flow() {
    // The simulated PLC counts parts every second: an observation a second all along.
    let cell = Cell::start().await;
    let mut s = TcpStream::connect(&cell.shdr).await.unwrap();
    let started = Instant::now();
    let mut late = 0;
    let closed = tokio::time::timeout(IDLE + SLACK, async {
        let mut buf = [0u8; 8192];
        loop {
            match s.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) if started.elapsed() > IDLE / 2 => {
                    late += buf[..n].iter().filter(|b| **b == b'\n').count();
                }
                Ok(_) => {}
            }
        }
    })
    .await
    .is_ok();
    eprintln!(
        "SHDR: a silent agent got {late} lines in its last {:?} and was closed after {:?}",
        started.elapsed().saturating_sub(IDLE / 2),
        started.elapsed()
    );
    assert!(late >= 5, "observations flowed while the agent was silent");
    assert!(
        closed,
        "a silent agent kept its connection {:?}",
        started.elapsed()
    );
    cell.stop().await;
}

/// A connection that asks for `path` and then reads nothing, with a small receive window so
/// that its buffers fill soon.
async fn stalled(addr: &str, path: &str) -> tokio::net::TcpStream {
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(2048).unwrap();
    let mut s = socket.connect(addr.parse().unwrap()).await.unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    s
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streams_nobody_reads_are_dropped_and_their_slots_freed() {
    let cell = Cell::start().await;
    let path = "/sample?interval=0&heartbeat=1";
    let mut held = Vec::new();
    for _ in 0..cellgate::mtconnect::http::MAX_STREAMS {
        held.push(stalled(&cell.mtconnect, path).await);
    }
    let url = format!("http://{}{path}", cell.mtconnect);
    // Every slot held: one more stream is refused.
    let mut refused = false;
    for _ in 0..100 {
        if status(&url).await == Some(503) {
            refused = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(refused, "the stalled streams hold every slot");
    // Their writes wait on clients that never read, and fail: the slots come free while the
    // stalled connections are still open on this side.
    let started = Instant::now();
    let freed = tokio::time::timeout(WRITE_TIMEOUT + 3 * SLACK, async {
        loop {
            let http = reqwest::Client::new();
            if let Ok(r) = http.get(&url).send().await
                && r.status() == 200
            {
                return;
            }
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
    })
    .await
    .is_ok();
    eprintln!(
        "MTConnect: 64 stalled streams; a new stream got 200 after {:?}",
        started.elapsed()
    );
    assert!(freed, "a stream slot never came free");
    // The stalled connections were closed by the agent.
    let (_, closed) = read_to_close(&mut held[0], SLACK).await;
    assert!(closed, "a stalled stream's connection is still open");
    drop(held);
    cell.stop().await;
}

/// The number of parts a stream of `path` sends in `window` (after its first).
async fn parts_in(addr: &str, path: &str, window: Duration) -> usize {
    let mut r = reqwest::get(format!("http://{addr}{path}")).await.unwrap();
    assert_eq!(r.status(), 200, "{path}");
    let ct = r.headers()["content-type"].to_str().unwrap().to_string();
    let boundary = format!(
        "--{}\r\n",
        ct.strip_prefix("multipart/x-mixed-replace;boundary=")
            .unwrap_or_else(|| panic!("{ct}"))
    );
    // The first part comes at once; parts are counted from there.
    let mut body = Vec::new();
    while !String::from_utf8_lossy(&body).contains(&boundary) {
        body.extend_from_slice(&r.chunk().await.unwrap().expect("a first part"));
    }
    let until = Instant::now() + window;
    while let Ok(Ok(Some(c))) = tokio::time::timeout_at(until.into(), r.chunk()).await {
        body.extend_from_slice(&c);
    }
    String::from_utf8_lossy(&body).matches(&boundary).count() - 1
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn interval_zero_streams_no_faster_than_the_floor() {
    // The simulated PLC counts parts every second; `/sample` also has the start's
    // observations to catch up on, a full part at a time.
    let cell = Cell::start().await;
    let window = Duration::from_secs(3);
    let (current, sample) = tokio::join!(
        parts_in(&cell.mtconnect, "/current?interval=0", window),
        parts_in(&cell.mtconnect, "/sample?interval=0&count=1", window)
    );
    let floor = cellgate::mtconnect::http::MIN_INTERVAL;
    let most = (window.as_millis() / floor.as_millis()) as usize + 2;
    eprintln!(
        "interval=0 over {window:?}: /current {current} parts, /sample {sample} parts (at most \
         {most})"
    );
    assert!(current <= most, "/current?interval=0 sent {current} parts");
    assert!(sample <= most, "/sample?interval=0 sent {sample} parts");
    cell.stop().await;
}

/// The open files and VmRSS (KiB) of process `pid`.
fn files_and_rss(pid: u32) -> (usize, u64) {
    let files = std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |d| d.count());
    (files, common::memory_kib(&pid.to_string()).0)
}

/// Whether the gateway's bus answers `cellgate health`.
async fn bus_answers(endpoint: &str) -> bool {
    let (code, out, err) =
        common::cli::cellgate(["health", "-e", endpoint, "--gateway-only"]).await;
    if code != 0 {
        eprintln!("health: {code}\n{out}{err}");
    }
    code == 0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gateway_with_few_open_files_outlives_a_flood_of_connections() {
    use std::os::unix::process::CommandExt as _;
    /// The gateway's limit on open files: each listener may hold 64 connections.
    const FILES: libc::rlim_t = 512;
    /// Connections to each of the console and the agent: together more than it has files.
    const FLOOD: usize = 400;
    // This process opens them: its own soft limit goes up to its hard one.
    let mut own = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit and setrlimit only read or write the struct they are given.
    unsafe {
        libc::getrlimit(libc::RLIMIT_NOFILE, &mut own);
        own.rlim_cur = own.rlim_max;
        libc::setrlimit(libc::RLIMIT_NOFILE, &own);
    }
    assert!(
        own.rlim_cur > 3 * FLOOD as u64,
        "this test needs {} open files",
        3 * FLOOD
    );
    let dir = tempfile::tempdir().unwrap();
    let mut config = CellConfig::embedded_default();
    config.opcua = None;
    let (bus, console, mtconnect) = (free_port(), free_port(), free_port());
    config.bus.listen = vec![format!("tcp/127.0.0.1:{bus}")];
    config.programs.dir = dir.path().join("programs");
    config.console.as_mut().unwrap().listen = format!("127.0.0.1:{console}");
    config.mtconnect.as_mut().unwrap().listen = format!("127.0.0.1:{mtconnect}");
    let file = dir.path().join("cell.toml");
    std::fs::write(&file, config.to_toml_string().unwrap()).unwrap();
    let mut command = common::cli::command(["run", "-c", file.to_str().unwrap()]);
    command
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped());
    // SAFETY: setrlimit is async-signal-safe, and touches nothing of this process's memory.
    unsafe {
        command.pre_exec(|| {
            let limit = libc::rlimit {
                rlim_cur: FILES,
                rlim_max: FILES,
            };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &limit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let mut child = command.spawn().unwrap();
    let stderr = common::cli::collect_stderr(&mut child);
    let child = common::cli::Reaper(child);
    let pid = child.0.id();
    let (console, mtconnect) = (
        format!("127.0.0.1:{console}"),
        format!("127.0.0.1:{mtconnect}"),
    );
    let endpoint = format!("tcp/127.0.0.1:{bus}");
    let _ = tokio_rustls::rustls::crypto::ring::default_provider().install_default();
    wait_200(&format!("http://{console}/health")).await;
    wait_200(&format!("http://{mtconnect}/probe")).await;
    let quiet = files_and_rss(pid);
    // The flood: half a head each, never more.
    let mut flood = Vec::new();
    for addr in [&console, &mtconnect] {
        for _ in 0..FLOOD {
            let connected =
                tokio::time::timeout(Duration::from_secs(1), TcpStream::connect(addr)).await;
            if let Ok(Ok(mut s)) = connected {
                let _ = s
                    .write_all(format!("GET / HTTP/1.1\r\nHost: {addr}\r\n").as_bytes())
                    .await;
                flood.push(s);
            }
        }
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let flooded = files_and_rss(pid);
    // The bus is still served: its sockets are in the reserve the listeners leave.
    assert!(
        bus_answers(&endpoint).await,
        "the bus stopped answering in the flood"
    );
    // Once the heads' time is up, the held connections are closed and a real client is served,
    // though the flood's sockets are still open on this side.
    let started = Instant::now();
    let served = tokio::time::timeout(HEAD_TIMEOUT + 2 * SLACK, async {
        while status(&format!("http://{console}/health")).await != Some(200)
            || status(&format!("http://{mtconnect}/probe")).await != Some(200)
        {
            tokio::time::sleep(Duration::from_millis(500)).await;
        }
    })
    .await
    .is_ok();
    let after = files_and_rss(pid);
    eprintln!(
        "flood of {} connections (limit {FILES} files): open files / VmRSS KiB quiet {quiet:?}, \
         flooded {flooded:?}, after {after:?}; served again after {:?}",
        flood.len(),
        started.elapsed()
    );
    assert!(served, "the console or the agent never served again");
    assert!(bus_answers(&endpoint).await, "the bus stopped answering");
    drop(flood);
    drop(child);
    let log = stderr.join().unwrap();
    assert!(log.contains("connections refused"), "{log}");
    assert!(!log.contains("panicked"), "{log}");
}
