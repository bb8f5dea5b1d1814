//! What the command line says of what happens in the cell beyond its own request: `watch`
//! prints the library's changes and DO outputs however they were asked for; a followed job
//! whose gateway dies ends at once with a clear message; `do` and `di` say what they wait for.
//! Against `cellgate run` processes and the `cellgate` binary, real time, loopback.

use crate::common;

use std::process::Stdio;
use std::time::{Duration, Instant};

use common::bus::free_port;
use common::cli::{Reaper, bin, cellgate, collect_stderr, run_on, wait_with_deadline};

const PROGRAM: &str = "%\nO7001(BRACKET)\nN10G00X0Y0\nN20G01X25.F150\nN30Y40.\nN40M30\n%\n";

/// `cellgate run` on the embedded default cell (with `extra` arguments), on a free port, in
/// a temporary directory; killed when dropped. Returns once mill-1's link is idle.
struct Run {
    child: Reaper,
    endpoint: String,
    dir: tempfile::TempDir,
}

impl Run {
    async fn start(extra: &[&str]) -> Run {
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let dir = tempfile::tempdir().unwrap();
        let child = run_on(&endpoint, dir.path())
            .args(extra)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.path().join("gateway.log")).unwrap())
            .spawn()
            .unwrap();
        let run = Run {
            child: Reaper(child),
            endpoint,
            dir,
        };
        for _ in 0..120 {
            let (code, out, _) =
                cellgate(["status", "mill-1", "-e", &run.endpoint, "--json"]).await;
            if code == 0 && out.contains("LINK_STATE_IDLE") {
                return run;
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
        panic!(
            "cellgate run on {} never showed mill-1 idle: {}",
            run.endpoint,
            std::fs::read_to_string(run.dir.path().join("gateway.log")).unwrap_or_default()
        );
    }

    async fn cellgate(&self, args: &[&str]) -> (i32, String, String) {
        let mut all: Vec<&str> = args.to_vec();
        all.extend(["-e", self.endpoint.as_str()]);
        cellgate(all).await
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watch_prints_library_changes_and_do_outputs_however_they_were_asked_for() {
    let run = Run::start(&[]).await;
    let mut watch = bin()
        .args(["watch", "--json", "-e", &run.endpoint])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdout = watch.stdout.take().unwrap();
    let _watch = Reaper(watch);
    let lines = std::sync::Arc::new(std::sync::Mutex::new(Vec::<serde_json::Value>::new()));
    let sink = lines.clone();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::BufReader::new(stdout)
            .lines()
            .map_while(Result::ok)
        {
            if let Ok(v) = serde_json::from_str(&line) {
                sink.lock().unwrap().push(v);
            }
        }
    });
    // The watch is subscribed once its standing tokens are printed.
    let seen = |pick: &dyn Fn(&serde_json::Value) -> bool| lines.lock().unwrap().iter().any(pick);
    let started = Instant::now();
    while !seen(&|l| l["event"] == "gateway_up") {
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "watch never started"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    // A store and a removal from the command line (gets on the write key), a DO output (a
    // get on `do`) twice with the same value: nothing a subscriber of those keys would see.
    let file = run.dir.path().join("O7001.nc");
    std::fs::write(&file, PROGRAM).unwrap();
    let (code, _, err) = run
        .cellgate(&["program", "put", "O7001", file.to_str().unwrap()])
        .await;
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = run.cellgate(&["program", "rm", "O7001"]).await;
    assert_eq!(code, 0, "{err}");
    for _ in 0..2 {
        let (code, _, err) = run
            .cellgate(&["do", "mill-1", "0x05", "--mask", "0x0f"])
            .await;
        assert_eq!(code, 0, "{err}");
    }
    let started = Instant::now();
    loop {
        let (stored, removed, outs) = {
            let l = lines.lock().unwrap();
            let changed = |c: &str| {
                l.iter().any(|e| {
                    e["event"] == "program_changed"
                        && e["change"] == c
                        && e["program"]["name"] == "O7001"
                        && e["by"]["via"] == "cli"
                })
            };
            let outs = l
                .iter()
                .filter(|e| {
                    e["event"] == "do_output"
                        && e["machine"] == "mill-1"
                        && e["do_command"]["value"] == 5
                        && e["do_command"]["mask"] == 0x0f
                })
                .count();
            (changed("stored"), changed("removed"), outs)
        };
        if stored && removed && outs == 2 {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "stored {stored}, removed {removed}, DO outputs {outs}: {:#?}",
            lines.lock().unwrap()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }

    // As lines: the same events in words.
    let mut text = bin()
        .args(["watch", "-e", &run.endpoint])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdout = text.stdout.take().unwrap();
    let _text = Reaper(text);
    let out = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
    let sink = out.clone();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::BufReader::new(stdout)
            .lines()
            .map_while(Result::ok)
        {
            let mut o = sink.lock().unwrap();
            o.push_str(&line);
            o.push('\n');
        }
    });
    let started = Instant::now();
    while !out.lock().unwrap().contains("gateway up") {
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "watch never started"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let (code, _, err) = run
        .cellgate(&["program", "put", "O7002", file.to_str().unwrap()])
        .await;
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = run
        .cellgate(&["do", "mill-1", "0x05", "--mask", "0x0f"])
        .await;
    assert_eq!(code, 0, "{err}");
    let started = Instant::now();
    loop {
        let o = out.lock().unwrap().clone();
        if o.contains("library O7002 stored: revision 1, 60 B, by ")
            && o.contains("mill-1 DO output 0x05 0b00000101 mask 0x0F by ")
        {
            break;
        }
        assert!(started.elapsed() < Duration::from_secs(20), "{o}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_submit_whose_gateway_dies_ends_at_once_and_says_so() {
    let mut run = Run::start(&[]).await;
    // The CNC's operator is away: the job is started and waits for the CNC to read.
    let (code, _, err) = run.cellgate(&["sim", "auto", "mill-1", "off"]).await;
    assert_eq!(code, 0, "{err}");
    let file = run.dir.path().join("O7001.nc");
    std::fs::write(&file, PROGRAM).unwrap();
    let mut submit = bin()
        .args([
            "submit",
            "mill-1",
            file.to_str().unwrap(),
            "-e",
            &run.endpoint,
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = collect_stderr(&mut submit);
    let mut submit = Reaper(submit);
    assert!(
        stderr.wait_for("started", Duration::from_secs(20)),
        "{}",
        stderr.so_far()
    );
    // The gateway dies (SIGKILL: no goodbye of its own).
    run.child.0.kill().unwrap();
    let _ = run.child.0.wait();
    let killed = Instant::now();
    let status = tokio::task::spawn_blocking(move || {
        let s = wait_with_deadline(&mut submit.0, Duration::from_secs(30));
        (s, submit)
    })
    .await
    .unwrap()
    .0
    .expect("submit still waits 30 s after its gateway died");
    let took = killed.elapsed();
    let err = stderr.join().unwrap();
    assert_eq!(status.code(), Some(1), "{err}");
    assert!(err.contains("the gateway went away"), "{err}");
    assert!(err.contains("cellgate job mill-1-"), "{err}");
    // At once: not after a silent wait for the job's next event (5 s) and a question
    // nobody answers.
    assert!(took < Duration::from_secs(3), "{took:?}: {err}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn do_and_di_say_what_they_wait_for_when_the_board_is_slow_to_speak() {
    // The default cell's boards poll every Tp = 5 s; a read waits for the board's next
    // exchange, seconds away as often as not.
    let run = Run::start(&[]).await;
    let mut slow = 0;
    for args in [
        ["di", "mill-1"],
        ["di", "mill-1"],
        ["di", "mill-1"],
        ["do", "mill-1"],
    ] {
        let mut args = args.to_vec();
        if args[0] == "do" {
            args.push("0x01");
        }
        let asked = Instant::now();
        let (code, out, err) = run.cellgate(&args).await;
        let took = asked.elapsed();
        assert_eq!(code, 0, "{err}");
        assert!(out.contains("mill-1 D"), "{out}");
        let said = err.contains("mill-1: waiting for the remote buffer")
            && err.contains("next exchange, which comes every Tp = 5 s (up to 11 s)");
        // Said after 1.5 s of waiting, and only then (the command's own start-up aside).
        if took > Duration::from_secs(3) {
            slow += 1;
            assert!(said, "{args:?} took {took:?} without a word: {err:?}");
        }
        if took < Duration::from_millis(1400) {
            assert!(!said, "{args:?} took {took:?}: {err:?}");
        }
    }
    assert!(slow > 0, "no read waited: nothing was checked");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resume_refused_says_what_the_board_had_when_the_job_ended() {
    let run = Run::start(&[]).await;
    // The CNC does not read: the job waits for it, and is cancelled before it asked.
    let (code, _, err) = run.cellgate(&["sim", "auto", "mill-1", "off"]).await;
    assert_eq!(code, 0, "{err}");
    let file = run.dir.path().join("O7001.nc");
    std::fs::write(&file, PROGRAM).unwrap();
    let (code, out, err) = run
        .cellgate(&["submit", "mill-1", file.to_str().unwrap(), "--detach"])
        .await;
    assert_eq!(code, 0, "{err}");
    let job = out.trim().to_string();
    let (code, out, err) = run.cellgate(&["cancel", &job]).await;
    assert_eq!(code, 0, "{out}{err}");
    let (code, _, err) = run.cellgate(&["submit", "--resume", &job]).await;
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("was cancelled before any of it went to the board (0 B on the line: the CNC had not asked for data yet)"),
        "{err}"
    );
}
