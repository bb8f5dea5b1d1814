//! The command line against a `cellgate run` process (the binary on both ends), and what a
//! person meets first: health, conventions, job lists, what status and job ends say.

use super::*;

// ---------------------------------------------------------------------------------------------
// The binary against a `cellgate run` process
// ---------------------------------------------------------------------------------------------

/// A `cellgate run` process on the embedded default cell, on a free loopback port, in a
/// temporary directory (its program library goes there). Stopped with SIGTERM on drop.
struct RunProcess {
    child: std::process::Child,
    endpoint: String,
    _dir: tempfile::TempDir,
}

impl RunProcess {
    async fn start() -> RunProcess {
        let port = free_port();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let dir = tempfile::tempdir().unwrap();
        let child = common::cli::run_on(&endpoint, dir.path())
            .env(
                "RUST_LOG",
                std::env::var("CELLGATE_TEST_RUST_LOG").unwrap_or("warn".into()),
            )
            .env_remove("CELLGATE_CONFIG")
            .env_remove("OTEL_EXPORTER_OTLP_ENDPOINT")
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            // CELLGATE_TEST_LOG=FILE keeps the gateway's log for a failing test.
            .stderr(match std::env::var_os("CELLGATE_TEST_LOG") {
                Some(f) => std::fs::File::create(f).unwrap().into(),
                None => std::process::Stdio::null(),
            })
            .spawn()
            .unwrap();
        let run = RunProcess {
            child,
            endpoint,
            _dir: dir,
        };
        // Up once mill-1 and mill-2 are initialised (status says idle).
        for _ in 0..120 {
            let (code, out, _) = cellgate(&["status", "-e", &run.endpoint, "--json"]).await;
            if code == 0 {
                let json: serde_json::Value = serde_json::from_str(&out).unwrap();
                let idle = json
                    .as_array()
                    .unwrap()
                    .iter()
                    .filter(|s| {
                        (s["machine"] == MILL_A || s["machine"] == MILL_X)
                            && s["link_state"] == "LINK_STATE_IDLE"
                    })
                    .count();
                if idle == 2 {
                    return run;
                }
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
        panic!(
            "cellgate run on {} never showed two idle links",
            run.endpoint
        );
    }
}

impl Drop for RunProcess {
    fn drop(&mut self) {
        let pid = self.child.id() as libc::pid_t;
        // SAFETY: kill(2) on the pid of a child this process spawned and has not reaped.
        unsafe {
            libc::kill(pid, libc::SIGTERM);
        }
        for _ in 0..100 {
            if matches!(self.child.try_wait(), Ok(Some(_))) {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_binary_against_cellgate_run() {
    let run = RunProcess::start().await;
    let ep = run.endpoint.as_str();
    let files = tempfile::tempdir().unwrap();
    let program = nc_program(4000, 77);
    let file = write_file(files.path(), "O0077.nc", &program);

    // The cell is found without --cell: the embedded default is "demo".
    let (code, out, err) = cellgate(&["status", "-e", ep]).await;
    assert_eq!(code, 0, "{err}");
    let rows: Vec<&str> = out.lines().skip(1).collect();
    assert!(rows.iter().any(|r| r.starts_with("mill-1 ")), "{out}");
    assert!(rows.iter().any(|r| r.starts_with("mill-2 ")), "{out}");

    for machine in [MILL_A, MILL_X] {
        let (code, out, err) =
            cellgate(&["submit", "-e", ep, machine, file.to_str().unwrap()]).await;
        assert_eq!(code, 0, "{machine}: stdout {out:?}\nstderr {err}");
        let job = out.trim();
        assert!(job.starts_with(&format!("{machine}-")), "{out:?}");
        assert!(
            err.contains(&format!(
                "{job}: completed: {}",
                cellgate::client::render::bytes(program.len() as u64)
            )),
            "{err}"
        );
    }
    let (code, out, err) = cellgate(&["status", "-e", ep, "--cell", "demo", "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let json: serde_json::Value = serde_json::from_str(&out).unwrap();
    for s in json.as_array().unwrap() {
        if s["machine"] == MILL_A || s["machine"] == MILL_X {
            assert_eq!(s["counters"]["jobs_completed"], 1, "{s}");
            assert_eq!(s["counters"]["nc_bytes_sent"], program.len(), "{s}");
        }
    }

    // A refused submit: exit 2 with the gateway's message.
    let (code, _, err) = cellgate(&["submit", "-e", ep, "nosuch", file.to_str().unwrap()]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("no machine \"nosuch\""), "{err}");
    drop(run);
}

/// A circle of `n` blocks in XY (Z still), as the CSV `cellgate g05` reads: relative travels.
fn circle_csv(n: usize, radius: f64) -> (String, [i64; 3]) {
    let mut csv = String::from("# X, Y, Z travels of a circle\n");
    let (mut px, mut py) = (radius.round() as i64, 0i64);
    let mut sums = [0i64; 3];
    for i in 1..=n {
        let a = std::f64::consts::TAU * i as f64 / n as f64;
        let (x, y) = (
            (radius * a.cos()).round() as i64,
            (radius * a.sin()).round() as i64,
        );
        let (dx, mut dy) = (x - px, y - py);
        // Never an all-zero block: that would end binary mode.
        if dx == 0 && dy == 0 {
            dy = 1;
        }
        csv.push_str(&format!("{dx},{dy},0\n"));
        sums[0] += dx;
        sums[1] += dy;
        (px, py) = (px + dx, py + dy);
    }
    (csv, sums)
}

/// `cellgate g05` streams a CSV (from a file, or piped in) to the embedded default cell's
/// G05 machine and exits 0 once the stream ended cleanly; a bad line and a machine without
/// G05 exit 2.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_g05_command_streams_a_csv_against_cellgate_run() {
    let run = RunProcess::start().await;
    let ep = run.endpoint.as_str();
    let files = tempfile::tempdir().unwrap();
    let (csv, _) = circle_csv(1500, 3000.0);
    let file = write_file(files.path(), "circle.csv", csv.as_bytes());
    let (code, out, err) =
        cellgate(&["g05", "-e", ep, MILL_X, file.to_str().unwrap(), "--json"]).await;
    assert_eq!(code, 0, "stdout {out:?}\nstderr {err}");
    let last: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(last["state"], "completed", "{out}");
    assert_eq!(last["received"], 1500, "{out}");
    assert_eq!(last["end_reason"], "Producer", "{out}");
    assert!(err.contains("3 axes, T = 2 ms"), "{err}");

    // Piped in on standard input.
    let mut child = tokio::process::Command::new(BIN)
        .args(["g05", "-e", ep, MILL_X, "-"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    {
        use tokio::io::AsyncWriteExt;
        let mut stdin = child.stdin.take().unwrap();
        stdin.write_all(csv.as_bytes()).await.unwrap();
    }
    let piped = child.wait_with_output().await.unwrap();
    // Without --json the last status is a line of text.
    let summary = String::from_utf8_lossy(&piped.stdout);
    assert!(
        summary.starts_with("G05 stream ") && summary.contains("completed: 1500 blocks"),
        "{summary}"
    );
    assert_eq!(
        piped.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&piped.stderr)
    );

    let bad = write_file(files.path(), "bad.csv", b"1,2,3\n4,x,6\n");
    let (code, _, err) = cellgate(&["g05", "-e", ep, MILL_X, bad.to_str().unwrap()]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("bad.csv:2") && err.contains("\"x\""), "{err}");

    let (code, _, err) = cellgate(&["g05", "-e", ep, MILL_A, file.to_str().unwrap()]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("[machines.g05]"), "{err}");
}

/// Resident memory of process `pid`, bytes (Linux: `VmRSS` of /proc/PID/status).
fn rss_of(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap();
    kb * 1024
}

/// The bound on what a flood may add to the gateway's resident memory.
const FLOOD_RSS_BOUND: u64 = 96 * 1024 * 1024;

/// One client floods `cellgate run` with 10 000 job submits and 10 000 DO puts in a few
/// seconds: the gateway answers what it can and refuses the rest (`QUEUE_FULL`, `BUSY`), its
/// memory stays within a bound, and every machine still serves afterwards.
#[cfg(target_os = "linux")]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_requests_leaves_the_gateway_bounded_and_serving() {
    use bus::keys::MachineLeaf;
    use prost::Message;
    let run = RunProcess::start().await;
    let pid = run.child.id();
    let before = rss_of(pid);
    let client = bus::open(&common::bus::client_config(
        run.endpoint.rsplit(':').next().unwrap().parse().unwrap(),
    ))
    .await
    .unwrap();
    let keys = CellKeys::new("cellgate", "demo").unwrap();
    let program = nc_program(2000, 5);
    let started = std::time::Instant::now();
    let mut pending = Vec::new();
    for i in 0..10_000u32 {
        let machine = if i % 2 == 0 { MILL_A } else { MILL_X };
        let request = pb::JobRequest {
            program: Some(pb::job_request::Program::Inline(program.clone())),
            request_id: format!("flood-{i}"),
            ..Default::default()
        };
        let replies = client
            .get(keys.leaf(machine, MachineLeaf::Submit))
            .payload(request.encode_to_vec())
            .timeout(Duration::from_secs(60))
            .await
            .unwrap();
        pending.push(replies);
    }
    for i in 0..10_000u32 {
        let machine = if i % 2 == 0 { MILL_A } else { MILL_X };
        let cmd = pb::DoCommand {
            value: i % 256,
            mask: None,
        };
        client
            .put(keys.leaf(machine, MachineLeaf::Do), cmd.encode_to_vec())
            .await
            .unwrap();
    }
    let sent_in = started.elapsed();
    let (mut accepted, mut refused, mut lost) = (0, std::collections::BTreeMap::new(), 0);
    for replies in pending {
        match replies.recv_async().await {
            Ok(r) => match r.result() {
                Ok(_) => accepted += 1,
                Err(e) => {
                    let code = pb::ErrorReply::decode(e.payload().to_bytes().as_ref())
                        .map(|e| e.code())
                        .unwrap_or(pb::ErrorCode::Unspecified);
                    *refused.entry(format!("{code:?}")).or_insert(0) += 1;
                }
            },
            Err(_) => lost += 1,
        }
    }
    let peak = rss_of(pid);
    eprintln!(
        "flood: sent in {sent_in:?}; {accepted} accepted, refused {refused:?}, {lost} without \
         answer; RSS {} MiB before, {} MiB after",
        before >> 20,
        peak >> 20
    );
    // Each machine takes 256 waiting jobs and the one being sent, plus one for each job that
    // ended while the flood lasted (its slot was free again); the rest are refused.
    let (_, out, _) = cellgate(&["status", "-e", &run.endpoint, "--json"]).await;
    let ended: u64 = serde_json::from_str::<serde_json::Value>(&out)
        .unwrap()
        .as_array()
        .unwrap()
        .iter()
        .map(|s| {
            let c = &s["counters"];
            c["jobs_completed"].as_u64().unwrap_or(0) + c["jobs_failed"].as_u64().unwrap_or(0)
        })
        .sum();
    assert!(
        accepted > 0 && accepted as u64 <= 2 * 257 + ended,
        "{accepted} accepted, {ended} ended"
    );
    assert_eq!(lost, 0, "every submit is answered");
    assert!(
        peak.saturating_sub(before) < FLOOD_RSS_BOUND,
        "RSS grew from {before} to {peak} bytes"
    );
    // Still serving: status answers for every machine, and DO output works.
    let (code, out, err) = cellgate(&["status", "-e", &run.endpoint, "--json"]).await;
    assert_eq!(code, 0, "{err}");
    assert_eq!(
        serde_json::from_str::<serde_json::Value>(&out)
            .unwrap()
            .as_array()
            .unwrap()
            .len(),
        3
    );
    // The flood's last puts may still wait at the link (at most 16 DO images wait there, older
    // ones give way to newer): once the image has settled, a DO must go out and be confirmed.
    let mut last = None;
    for _ in 0..60 {
        let (_, out, _) = cellgate(&["status", "-e", &run.endpoint, "--json", MILL_A]).await;
        let image = serde_json::from_str::<serde_json::Value>(&out)
            .ok()
            .map(|v| v[0]["do_image"].to_string());
        if image.is_some() && image == last {
            break;
        }
        last = image;
        tokio::time::sleep(Duration::from_millis(1000)).await;
    }
    let (code, _, err) = cellgate(&["do", "-e", &run.endpoint, MILL_A, "0x5A"]).await;
    assert_eq!(code, 0, "{err}");
    client.close().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_says_what_is_down_and_fails_when_the_gateway_is_gone() {
    // The embedded default cell, its links initialised: healthy.
    // Three CNCs and the PLC's station, once the station has answered its first poll.
    let run = RunProcess::start().await;
    let healthy = healthy_within(&run.endpoint, 30).await;
    assert!(healthy.is_ok(), "{healthy:?}");
    let (code, out, err) = cellgate(&["health", "-e", &run.endpoint]).await;
    assert_eq!(code, 0, "{out}{err}");
    assert!(out.contains("its 4 link(s) are up"), "{out}");
    drop(run);

    // A machine behind a device server that is not there: its link stays down.
    let dir = tempfile::tempdir().unwrap();
    let nobody = free_port();
    let cell = dir.path().join("cell.toml");
    std::fs::write(
        &cell,
        format!(
            r#"cell = "demo"
[bus]
multicast_scouting = false
[programs]
dir = "{programs}"
[[machines]]
name = "mill-1"
protocol = "a"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
[[machines]]
name = "mill-9"
protocol = "a"
transport = {{ kind = "tcp", address = "127.0.0.1:{nobody}", line = {{ baud = 19200 }} }}
[[plcs]]
name = "plc-9"
mode = 1
transport = {{ kind = "tcp", address = "127.0.0.1:{nobody}", line = {{ baud = 19200 }} }}
[[plcs.tags]]
name = "parts"
module = "D"
address = 0
type = "u16"
poll_ms = 200
"#,
            programs = dir.path().join("programs").display()
        ),
    )
    .unwrap();
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let mut child = common::cli::bin()
        .args(["run", "--config", cell.to_str().unwrap(), "-l", &endpoint])
        .env("RUST_LOG", "error")
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut last = (0, String::new(), String::new());
    for _ in 0..60 {
        last = cellgate(&["health", "-e", &endpoint]).await;
        // Until mill-1 is initialised, it is down too.
        if last.0 == 1 && last.1.contains("2 of 3") && !last.1.contains("mill-1") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    let (code, out, err) = last;
    assert_eq!(code, 1, "{out}{err}");
    assert!(
        out.contains("2 of 3 link(s) down: mill-9 (down), plc-9 station 0 (down)"),
        "{out}"
    );
    // A liveness probe does not care about the links.
    let (code, out, err) = cellgate(&["health", "-e", &endpoint, "--gateway-only"]).await;
    assert_eq!(code, 0, "{out}{err}");

    // Stopped: nothing answers.
    // SAFETY: kill(2) on the pid of a child this process spawned and has not reaped.
    unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
    assert!(child.wait().unwrap().success());
    let (code, _, err) = cellgate(&["health", "-e", &endpoint, "--gateway-only"]).await;
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("cannot connect"), "{err}");
}

/// Spawns `cellgate` with `args`, its output thrown away, stopped (SIGTERM) when dropped.
struct Spawned(std::process::Child);

impl Spawned {
    fn new(args: &[&str], dir: &std::path::Path) -> Spawned {
        Spawned(
            common::cli::bin()
                .args(args)
                .current_dir(dir)
                .env("RUST_LOG", "error")
                .env_remove("CELLGATE_CONFIG")
                .stdin(std::process::Stdio::null())
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::null())
                .spawn()
                .unwrap(),
        )
    }

    /// SIGTERM, then the exit status (killed after 10 s).
    fn stop(&mut self) -> std::process::ExitStatus {
        // SAFETY: kill(2) on the pid of a child this process spawned and has not reaped.
        unsafe { libc::kill(self.0.id() as libc::pid_t, libc::SIGTERM) };
        for _ in 0..200 {
            if let Ok(Some(status)) = self.0.try_wait() {
                return status;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.0.kill();
        self.0.wait().unwrap()
    }
}

impl Drop for Spawned {
    fn drop(&mut self) {
        if matches!(self.0.try_wait(), Ok(None)) {
            self.stop();
        }
    }
}

/// Polls `cellgate health` through `endpoint` until it exits 0 (at most `secs`).
async fn healthy_within(endpoint: &str, secs: u64) -> Result<Duration, String> {
    let started = std::time::Instant::now();
    let mut last = String::new();
    while started.elapsed() < Duration::from_secs(secs) {
        let (code, out, err) = cellgate(&["health", "-e", endpoint]).await;
        if code == 0 {
            return Ok(started.elapsed());
        }
        last = format!("{out}{err}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    Err(last)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gateway_serves_again_after_its_router_restarts() {
    let dir = tempfile::tempdir().unwrap();
    let router_ep = format!("tcp/127.0.0.1:{}", free_port());
    let gateway_ep = format!("tcp/127.0.0.1:{}", free_port());
    let mut router = Spawned::new(&["router", "-l", &router_ep], dir.path());
    tokio::time::sleep(Duration::from_millis(500)).await;
    // A peer connected to the router: it keeps retrying the router when it goes away.
    let _gateway = Spawned::new(
        &[
            "run",
            "--mode",
            "peer",
            "-l",
            &gateway_ep,
            "-e",
            &router_ep,
            "--console",
            "off",
            "--mtconnect",
            "off",
            "--opcua",
            "off",
        ],
        dir.path(),
    );
    healthy_within(&router_ep, 60).await.unwrap();
    let (code, out, err) = cellgate(&["status", "-e", &router_ep, "mill-1"]).await;
    assert_eq!(code, 0, "{out}{err}");

    assert!(router.stop().success(), "the router stops cleanly");
    let (code, _, _) = cellgate(&["health", "-e", &router_ep, "--timeout", "2"]).await;
    assert_eq!(code, 1, "no router, no answer through it");
    let _router = Spawned::new(&["router", "-l", &router_ep], dir.path());
    let back = healthy_within(&router_ep, 30).await.unwrap();
    eprintln!("serving through the new router after {back:?}");
    // A job goes through the new router end to end.
    let program = nc_program(1500, 42);
    let file = write_file(dir.path(), "O0042.nc", &program);
    let (code, out, err) =
        cellgate(&["submit", "-e", &router_ep, "mill-1", file.to_str().unwrap()]).await;
    assert_eq!(code, 0, "{out}{err}");
}

/// What status and a job's end say is what happened: the bytes after a program's EOR are
/// named as not sent, the line counters are there, a job the CNC never asks for shows as
/// waiting for the CNC (not an idle link), and cancelled it says it never started.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_and_job_ends_say_what_happened() {
    let gw = start_gateway().await;
    let files = tempfile::tempdir().unwrap();
    // A program file as editors write it: a line end after the EOR.
    let program = b"%\nO0042\nN10 G00 X0 Y0\nN20 M30\n%\n";
    let file = write_file(files.path(), "O0042.nc", program);
    let mut args = submit_args(&gw, MILL_A);
    args.file = Some(file);
    let (code, _, err) = run(&args).await;
    assert_eq!(code, 0, "{err}");
    let sent = cellgate::client::render::bytes(program.len() as u64 - 1);
    assert!(
        err.contains(&format!("completed: {sent} sent"))
            && err.contains("the 1 B after the EOR % not sent"),
        "{err}"
    );

    let client = gw.client().await;
    let s = &client.status(Some(MILL_A)).await.unwrap()[0];
    let c = s.counters.unwrap();
    assert!(
        c.bytes_sent.is_some_and(|b| b > program.len() as u64),
        "{c:?}"
    );
    assert!(c.bytes_received.is_some_and(|b| b > 0), "{c:?}");
    assert!(c.frames.is_some_and(|f| f > 0), "{c:?}");

    // The operator stops starting reads: the next job waits for the CNC.
    let board = gw.board(MILL_A);
    board.command(cellgate_core::sim::BoardCommand::SetAutostart(false));
    board.command(cellgate_core::sim::BoardCommand::StopReading);
    tokio::time::timeout(Duration::from_secs(10), board.wait_for(|s| !s.reading))
        .await
        .unwrap();
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(program.to_vec())),
        ..pb::JobRequest::default()
    };
    let (accepted, follower) = client.submit(MILL_A, &request).await.unwrap();
    let job = accepted.job_id.clone();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    loop {
        let s = client.status(Some(MILL_A)).await.unwrap().remove(0);
        if s.current_job_id == job && !s.waiting_for.is_empty() {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the job never showed as waiting: {s:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let status = StatusArgs {
        connect: gw.connect(),
        machine: Some(MILL_A.to_string()),
        json: false,
    };
    let (code, out, err) = run(&status).await;
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("waiting for CNC"), "{out}");
    assert!(
        out.contains(&format!("job {job} waits")) && out.contains("for the CNC to read it"),
        "{out}"
    );

    // The older form, machine first, still works.
    let cancel = CancelArgs {
        connect: gw.connect(),
        job_id: MILL_A.to_string(),
        legacy_job_id: Some(job.clone()),
        json: false,
    };
    let (code, _, err) = run(&cancel).await;
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains("cancelled by request before the CNC read any of it: nothing was sent"),
        "{err}"
    );
    assert!(!err.contains("resumes"), "{err}");
    follower.close().await;
    // Nothing to resume: it says why.
    let mut resume = submit_args(&gw, MILL_A);
    resume.resume = Some(job.clone());
    let (code, _, err) = run(&resume).await;
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("before any of it went to the board (0 B on the line"),
        "{err}"
    );
    // The job id names its machine, as for `cancel` and `job`: no MACHINE needed.
    let (code, _, err) = cellgate(&["submit", "-e", &gw.endpoint, "--resume", &job]).await;
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("before any of it went to the board (0 B on the line"),
        "{err}"
    );
    client.close().await;
    gw.stop().await;
}

/// One convention for the command line on `cellgate run`: an unknown machine fails at once
/// naming the cell's, a bad endpoint says what one looks like, `watch` is not drowned by a
/// counter tag unless asked, and the usual synonyms point to the subcommand.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_command_line_follows_one_convention() {
    let run = RunProcess::start().await;
    let ep = run.endpoint.as_str();

    let started = std::time::Instant::now();
    let (code, _, err) = cellgate(&["watch", "-e", ep, "mill-9"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(started.elapsed() < Duration::from_secs(15), "watch waited");
    assert!(
        err.contains("no machine or PLC \"mill-9\"")
            && err.contains("lathe-1, mill-1, mill-2")
            && err.contains("plc-1"),
        "{err}"
    );

    // Without --tags, the part counter (a change a second) stays out of the watch.
    let child = tokio::process::Command::new(BIN)
        .args(["watch", "-e", ep])
        .env_remove("CELLGATE_CONNECT")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let pid = child.id().unwrap() as libc::pid_t;
    let killer = tokio::spawn(async move {
        tokio::time::sleep(Duration::from_secs(4)).await;
        // SAFETY: kill(2) on the pid of a child this test spawned and has not reaped.
        unsafe {
            libc::kill(pid, libc::SIGINT);
        }
    });
    let out = child.wait_with_output().await.unwrap();
    killer.await.unwrap();
    let lines = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(lines.contains("mill-1 link up"), "{lines}");
    assert!(!lines.contains("plc-1/parts"), "{lines}");
    // Asked for, it is there; and watching the PLC shows its tags.
    let (code, out, err) = cellgate(&["watch", "-e", ep, "--tags=parts", "--count", "7"]).await;
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("plc-1/parts = "), "{out}");
    assert!(!out.contains("plc-1/door-open"), "{out}");
    let (code, out, err) = cellgate(&["watch", "-e", ep, "plc-1", "--count", "2"]).await;
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("plc-1 station 0 up"), "{out}");
    assert!(!out.contains("mill-1"), "{out}");

    let (code, _, err) = cellgate(&["status", "-e", "127.0.0.1:7447"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("endpoints look like tcp/127.0.0.1:7447"),
        "{err}"
    );
    assert!(!err.contains("Json5") && !err.contains(".cargo"), "{err}");

    for (line, meant) in [
        ("program delete O1", "'rm'"),
        ("program remove O1", "'rm'"),
        ("program list", "'ls'"),
    ] {
        let args: Vec<&str> = line.split(' ').collect();
        let (code, _, err) = cellgate(&args).await;
        assert_eq!(code, 2, "{err}");
        assert!(err.contains(meant), "{line}: {err}");
    }
    let (code, _, err) = cellgate(&["cancel", "-e", ep, "mill-1"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("not a job id"), "{err}");
    drop(run);
}

/// `jobs` shows a machine's queue in run order (and with --all the jobs that ended), `job`
/// a job's latest event or, following it, its events to its end; `status` names the
/// gateway's version and uptime.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_and_job_show_the_queue_and_a_jobs_events() {
    let gw = start_gateway().await;
    let ep = gw.endpoint.clone();
    let files = tempfile::tempdir().unwrap();
    // About 20 s at 19200 baud: the second job waits behind it.
    let long = write_file(files.path(), "long.nc", &nc_program(40_000, 7));
    let short = write_file(files.path(), "short.nc", &nc_program(600, 8));
    let submit = |file: &Path| {
        let ep = ep.clone();
        let file = file.to_str().unwrap().to_string();
        async move {
            let (code, out, err) =
                cellgate(&["submit", "-e", &ep, MILL_A, &file, "--detach"]).await;
            assert_eq!(code, 0, "{err}");
            out.trim().to_string()
        }
    };
    let first = submit(&long).await;
    let second = submit(&short).await;

    let (code, out, err) = cellgate(&["jobs", "-e", &ep, MILL_A]).await;
    assert_eq!(code, 0, "{err}");
    let rows: Vec<&str> = out.lines().skip(1).collect();
    assert!(
        rows[0].contains(&first) && rows[0].contains("active"),
        "{out}"
    );
    assert!(
        rows[1].contains(&second) && rows[1].contains("waiting, 0 ahead"),
        "{out}"
    );
    let (code, out, err) = cellgate(&["job", "-e", &ep, &second]).await;
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains(&format!("{second} on {MILL_A}: queued")),
        "{out}"
    );
    let (code, _, err) = cellgate(&["jobs", "-e", &ep, "mill-9"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("mill-1, mill-2"), "{err}");

    // The first is cancelled; following the second shows it run to its end, exit 0.
    let (code, _, err) = cellgate(&["cancel", "-e", &ep, &first]).await;
    assert_eq!(code, 0, "{err}");
    let (code, out, err) = cellgate(&["job", "-e", &ep, &second, "--follow"]).await;
    assert_eq!(code, 0, "{err}");
    let steps: Vec<&str> = out.lines().collect();
    assert!(steps.last().unwrap().contains(": completed: "), "{out}");
    assert!(
        !out.contains(" sent 0 B"),
        "no progress lines as text: {out}"
    );

    let (code, out, err) = cellgate(&["jobs", "-e", &ep, MILL_A, "--all", "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v[0]["active"], serde_json::Value::Null, "{v}");
    let ended: Vec<&str> = v[0]["ended"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["job_id"].as_str().unwrap())
        .collect();
    assert_eq!(ended, [first.as_str(), second.as_str()], "{v}");

    let (code, out, err) = cellgate(&["status", "-e", &ep]).await;
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains(&format!(
            "gateway: cellgate {}, cell {CELL}, up ",
            env!("CARGO_PKG_VERSION")
        )),
        "{out}"
    );
    gw.stop().await;
}

/// The simulation controls drive simulated machines only, and each what it can: a machine
/// without a simulated board, a punch on Protocol A and a cycle start in alarm are refused,
/// saying why.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn simulation_controls_refuse_what_the_machine_cannot_take() {
    // mill-2 as if it were a real machine: no simulated board to drive.
    let gw = start_gateway_with(|links| {
        for l in links.iter_mut().filter(|l| l.config.name == MILL_X) {
            l.sim = None;
        }
    })
    .await;
    let ep = gw.endpoint.clone();
    let (code, _, err) = cellgate(&["sim", "alarm", "-e", &ep, MILL_X]).await;
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("ERROR_CODE_NOT_SUPPORTED") && err.contains("not simulated"),
        "{err}"
    );
    let (code, _, err) = cellgate(&["sim", "reset", "-e", &ep, "mill-9"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("ERROR_CODE_UNKNOWN_MACHINE"), "{err}");
    let (code, out, err) = cellgate(&["sim", "state", "-e", &ep, "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let all: serde_json::Value = serde_json::from_str(&out).unwrap();
    let names: Vec<&str> = all
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["machine"].as_str().unwrap())
        .collect();
    assert!(names.contains(&MILL_A) && !names.contains(&MILL_X), "{out}");

    let files = tempfile::tempdir().unwrap();
    let program = write_file(files.path(), "p.nc", b"%\nO0001\nM30\n%\n");
    let (code, _, err) =
        cellgate(&["sim", "punch", "-e", &ep, MILL_A, program.to_str().unwrap()]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("Protocol B function"), "{err}");

    let (code, _, err) = cellgate(&["sim", "auto", "-e", &ep, MILL_A, "off"]).await;
    assert_eq!(code, 0, "{err}");
    let (code, out, err) = cellgate(&["sim", "alarm", "-e", &ep, MILL_A, "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let state: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(state["alarm"], true, "{out}");
    assert_eq!(state["autostart"], false, "{out}");
    let (code, _, err) = cellgate(&["sim", "read", "-e", &ep, MILL_A]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("reset it first"), "{err}");
    let (code, out, err) = cellgate(&["sim", "reset", "-e", &ep, MILL_A]).await;
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("no alarm"), "{out}");
    assert!(!gw.board(MILL_A).snapshot().alarm);
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_user_in_the_environment_records_still_name_who_ran_the_command() {
    let gw = start_gateway().await;
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("O7777.nc");
    std::fs::write(&file, b"%\nO7777\nG00X0\nM30\n%\n").unwrap();
    let ep = gw.endpoint.clone();
    let out = tokio::task::spawn_blocking(move || {
        common::cli::command(["program", "put", "-e", &ep, "O7777"])
            .arg(&file)
            .env_remove("USER")
            .env_remove("LOGNAME")
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(out.status.success(), "{}", common::cli::text(&out));
    let (code, json, err) =
        cellgate(&["program", "history", "-e", &gw.endpoint, "O7777", "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    let by = &v["revisions"][0]["by"];
    assert_eq!(by["via"], "cli", "{v}");
    assert!(
        by["user"].as_str().is_some_and(|u| !u.is_empty()),
        "the record names somebody: {v}"
    );
    gw.stop().await;
}
