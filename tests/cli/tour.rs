//! The README's tour of the default cell, walked as a newcomer walks it: `cellgate run` on the
//! embedded cell, then the tour's commands as written (the endpoint comes from
//! `CELLGATE_CONNECT`, the files from the repository's `examples/`), each checked for what
//! the tour says it does. And every `cellgate` command the README and docs/cli.md show is one
//! the binary takes.

use crate::common;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

use common::bus::free_port;
use common::cli::{BIN, command};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `cellgate run` on the default cell, in a directory of its own; stopped with SIGINT, as
/// Ctrl-C stops it.
struct Gateway {
    child: Child,
    endpoint: String,
    dir: tempfile::TempDir,
    /// Every command line run against it, in order.
    ran: std::cell::RefCell<Vec<String>>,
}

impl Gateway {
    /// Starts it and returns it with what it printed once it served.
    fn start() -> (Gateway, String) {
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        Gateway::start_in(tempfile::tempdir().unwrap(), endpoint)
    }

    /// Starts it in `dir` (its library, journal and history there), listening on `endpoint`.
    fn start_in(dir: tempfile::TempDir, endpoint: String) -> (Gateway, String) {
        let mut child = command([
            "run",
            "--listen",
            &endpoint,
            "--console",
            "127.0.0.1:0",
            "--mtconnect",
            "127.0.0.1:0",
            "--opcua",
            "127.0.0.1:0",
        ])
        .current_dir(dir.path())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut text = String::new();
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                // The agent's URL comes last (both web listeners are asked for above).
                let done = line.starts_with("mtconnect: ");
                text.push_str(&line);
                text.push('\n');
                if done {
                    let _ = tx.send(text.clone());
                }
            }
        });
        let printed = rx
            .recv_timeout(Duration::from_secs(60))
            .expect("cellgate run never said what it serves");
        (
            Gateway {
                child,
                endpoint,
                dir,
                ran: Default::default(),
            },
            printed,
        )
    }

    /// A tour command as written, against this gateway: (exit code, stdout, stderr).
    fn run(&self, line: &str) -> (i32, String, String) {
        self.run_in(&repo(), line)
    }

    /// [`Self::run`] in the folder `dir`.
    fn run_in(&self, dir: &Path, line: &str) -> (i32, String, String) {
        self.ran.borrow_mut().push(line.to_string());
        let args: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(args[0], "cellgate", "{line}");
        let out = command(&args[1..])
            .current_dir(dir)
            .env("CELLGATE_CONNECT", &self.endpoint)
            .output()
            .unwrap();
        (
            out.status.code().unwrap_or(-1),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    }

    /// [`Self::run`], which must exit 0; its stdout.
    fn ok(&self, line: &str) -> String {
        let (code, out, err) = self.run(line);
        assert_eq!(code, 0, "{line}\nstdout {out}\nstderr {err}");
        out
    }

    /// Runs `line` until `check` accepts its stdout, for up to `limit`.
    fn until(&self, line: &str, limit: Duration, check: impl Fn(&str) -> bool) -> String {
        let deadline = Instant::now() + limit;
        loop {
            let (code, out, err) = self.run(line);
            if code == 0 && check(&out) {
                return out;
            }
            assert!(
                Instant::now() < deadline,
                "{line} never showed what was expected:\n{out}{err}"
            );
            std::thread::sleep(Duration::from_millis(250));
        }
    }

    fn stop(self) -> Option<i32> {
        self.stop_keeping().0
    }

    /// Stops it as Ctrl-C does; its exit code, its directory and endpoint for a restart.
    fn stop_keeping(mut self) -> (Option<i32>, tempfile::TempDir, String) {
        // SAFETY: kill(2) on the pid of a child this test spawned and has not reaped.
        unsafe {
            libc::kill(self.child.id() as libc::pid_t, libc::SIGINT);
        }
        let code = common::cli::wait_with_deadline(&mut self.child, Duration::from_secs(20))
            .and_then(|s| s.code());
        let dir = std::mem::replace(&mut self.dir, tempfile::tempdir().unwrap());
        (code, dir, std::mem::take(&mut self.endpoint))
    }
}

impl Drop for Gateway {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn status_of(g: &Gateway, machine: &str) -> serde_json::Value {
    let out = g.ok(&format!("cellgate status {machine} --json"));
    serde_json::from_str::<serde_json::Value>(&out).unwrap()[0].clone()
}

#[test]
fn the_readme_tour_works_as_written() {
    // 1. The gateway says what it serves and where.
    let (g, printed) = Gateway::start();
    assert!(
        printed.contains(&format!("serves cell demo on {}", g.endpoint)),
        "{printed}"
    );
    for (name, takes) in [
        (
            "mill-1",
            "Protocol A, simulated, 19200 baud: programs (submit), DI/DO",
        ),
        ("mill-2", "G05 streams of 3 axes at T = 2 ms"),
        ("lathe-1", "punched programs"),
        ("plc-1", "tags parts, door-open, recipe (writable)"),
    ] {
        let line = printed
            .lines()
            .find(|l| l.trim_start().starts_with(name))
            .unwrap_or_else(|| panic!("{name} missing from:\n{printed}"));
        assert!(line.contains(takes), "{line}");
    }

    // 2. Look at the cell, once its links are up.
    g.until("cellgate status --json", Duration::from_secs(30), |out| {
        let v: serde_json::Value = serde_json::from_str(out).unwrap();
        v.as_array()
            .unwrap()
            .iter()
            .all(|s| s["link_state"] == "LINK_STATE_IDLE")
    });
    let status = g.ok("cellgate status");
    for name in ["mill-1", "mill-2", "lathe-1", "plc-1"] {
        assert!(status.contains(name), "{status}");
    }
    assert!(status.contains("gateway: cellgate "), "{status}");
    assert!(g.ok("cellgate health").starts_with("ok: "));

    // 3. A program, from the shipped file; then from the library.
    let (code, out, err) = g.run("cellgate submit mill-1 examples/programs/O1234.nc");
    assert_eq!(code, 0, "{out}{err}");
    assert!(out.trim().starts_with("mill-1-"), "{out}");
    assert!(
        err.contains("completed: 136 B sent") && err.contains("the 1 B after the EOR % not sent"),
        "{err}"
    );
    assert!(
        err.contains("accepted by mill-1, next in its queue"),
        "{err}"
    );
    assert!(g.ok("cellgate jobs").contains("no job active or waiting"));
    g.ok("cellgate program put O1234 examples/programs/O1234.nc");
    assert!(g.ok("cellgate program ls").contains("O1234 "));
    g.ok("cellgate submit mill-2 --library O1234");

    // 4. DI and DO; then DI and DO in a row, as an operator's script does them, leave every
    // link up and no alarm.
    g.ok("cellgate sim di mill-1 0x0F");
    assert!(
        g.ok("cellgate di mill-1")
            .starts_with("mill-1 DI 0x0F 0b00001111")
    );
    assert_eq!(
        g.ok("cellgate do mill-1 0x03").trim(),
        "mill-1 DO 0x03 0b00000011"
    );
    g.ok("cellgate di mill-1");
    g.ok("cellgate do mill-1 7 --no-wait");
    assert_eq!(
        g.ok("cellgate do mill-1 0").trim(),
        "mill-1 DO 0x00 0b00000000"
    );
    let health = g.ok("cellgate health");
    assert!(!health.contains("in alarm"), "{health}");
    let mill = status_of(&g, "mill-1");
    assert_eq!(mill["counters"]["link_alarms"], 0, "{mill}");
    assert_ne!(
        mill["sat"]["buffer_status"], "BUFFER_STATUS_ALARM",
        "{mill}"
    );

    // 5. A punched program lands in the library.
    g.ok("cellgate sim punch lathe-1 examples/programs/O1234.nc");
    g.until("cellgate program ls", Duration::from_secs(20), |out| {
        out.lines().any(|l| l.starts_with("lathe-1-O1234-"))
    });

    // 6. A G05 stream of the shipped circle.
    let out = g.ok("cellgate g05 mill-2 examples/g05/circle.csv");
    assert!(out.contains("completed: 3000 blocks"), "{out}");

    // 7. Tags and memory.
    assert!(g.ok("cellgate tag get parts").starts_with("plc-1/parts = "));
    assert_eq!(
        g.ok("cellgate tag set recipe 42").trim(),
        "plc-1/recipe = 42 written"
    );
    assert!(
        g.ok("cellgate tag get recipe")
            .starts_with("plc-1/recipe = 42 (good, writable)")
    );
    assert_eq!(
        g.ok("cellgate plc write plc-1 D 10 0x1234 65535").trim(),
        "plc-1: 2 word(s) written to D10"
    );
    let words = g.ok("cellgate plc read plc-1 D 10 --count 2");
    assert!(
        words.contains("D10 = 4660 (0x1234)") && words.contains("D11 = 65535 (0xFFFF)"),
        "{words}"
    );
    g.ok("cellgate plc status");

    // 8. A CNC alarm, played by hand, typed without a pause: `sim alarm` returns once the
    // gateway has seen the alarm, `sim reset` once it has seen the reset, so the job waits
    // for the CNC instead of meeting a board the gateway still thought ready.
    g.ok("cellgate sim auto mill-1 off");
    g.ok("cellgate sim alarm mill-1");
    let job = g.ok("cellgate submit mill-1 examples/programs/O1234.nc --detach");
    let job = job.trim();
    let status = g.ok("cellgate status mill-1");
    assert!(status.lines().nth(1).unwrap().contains("alarm"), "{status}");
    assert!(status.contains(job), "{status}");
    g.ok("cellgate sim reset mill-1");
    let status = g.ok("cellgate status mill-1 --json");
    assert!(
        !status.contains("LINK_STATE_ALARM"),
        "the reset is seen: {status}"
    );
    g.ok("cellgate sim read mill-1");
    let followed = g.ok(&format!("cellgate job {job} --follow"));
    assert!(followed.contains(": completed: 136 B sent"), "{followed}");
    g.ok("cellgate sim auto mill-1 on");
    let health = g.ok("cellgate health");
    assert!(
        health.starts_with("ok: ") && !health.contains("in alarm"),
        "{health}"
    );

    // 9. Revisions: a changed copy stored, its history, the comparison, the release.
    // As written, in a folder of the reader's own.
    let scratch = tempfile::tempdir().unwrap();
    let in_scratch = |line: &str| {
        let (code, out, err) = g.run_in(scratch.path(), line);
        assert_eq!(code, 0, "{line}\nstdout {out}\nstderr {err}");
    };
    in_scratch("cellgate program get O1234 -o O1234.nc");
    let copy = scratch.path().join("O1234.nc");
    let text = std::fs::read_to_string(&copy).unwrap();
    assert!(text.contains("N30 G01 X50.0 F300"), "{text}");
    std::fs::write(
        &copy,
        text.replace("N30 G01 X50.0 F300", "N30 G01 X50.0 F250"),
    )
    .unwrap();
    in_scratch("cellgate program put O1234 O1234.nc --comment feed-F250");
    let revisions = g.ok("cellgate program history O1234");
    let rows: Vec<&str> = revisions.lines().skip(1).collect();
    assert!(
        rows.len() == 2 && rows[0].starts_with("2 ") && rows[0].contains("feed-F250"),
        "{revisions}"
    );
    let (code, diff, _) = g.run("cellgate program diff O1234");
    assert_eq!(code, 1, "they differ: {diff}");
    assert!(
        diff.contains("-N30 G01 X50.0 F300") && diff.contains("+N30 G01 X50.0 F250"),
        "{diff}"
    );
    g.ok("cellgate program release O1234 --comment proven");

    // 10. The history, newest first where asked, the audit and utilisation.
    let history = g.ok("cellgate history --since 1h");
    assert!(history.contains("gateway started"), "{history}");
    // The history commits once a second: step 8's job may be a moment away.
    let jobs = g.until(
        "cellgate history mill-1 --kind job --newest",
        Duration::from_secs(10),
        |out| out.lines().count() >= 2,
    );
    let jobs: Vec<&str> = jobs.lines().collect();
    assert!(
        jobs[0].contains(job) && jobs.iter().all(|l| l.contains(" mill-1 ")),
        "the last job first: {jobs:?}"
    );
    // The audit is written with the history's next commit, once a second.
    g.until(
        "cellgate audit --since 1h",
        Duration::from_secs(10),
        |audit| audit.contains("program.release O1234 revision 2"),
    );
    let (code, utilisation, err) = g.run("cellgate utilisation mill-1 --since 1h");
    assert_eq!(code, 0, "{err}");
    assert!(
        utilisation.lines().nth(1).unwrap().starts_with("mill-1 "),
        "{utilisation}"
    );
    assert!(
        !err.contains("older form"),
        "the tour uses the current form: {err}"
    );

    // Every command of the README's tour was run above as written, in the README's order
    // (the id submit printed in place of JOB_ID): the README and this walk cannot drift.
    let ran = g.ran.borrow().clone();
    let mut at = 0;
    for line in commands_in(&repo().join("README.md")) {
        let line = line.replace("JOB_ID", job);
        match ran[at..].iter().position(|r| *r == line) {
            Some(i) => at += i + 1,
            None => panic!("the README's {line:?} was not run here in its order; ran:\n{ran:#?}"),
        }
    }

    // 11. Ctrl-C stops it cleanly. A job the link had taken fails "gateway restarted"; the
    // one waiting behind it runs after the next start.
    g.ok("cellgate sim auto mill-1 off");
    let taken = g.ok("cellgate submit mill-1 examples/programs/O1234.nc --detach");
    let waiting = g.ok("cellgate submit mill-1 examples/programs/O1234.nc --detach");
    let (taken, waiting) = (taken.trim(), waiting.trim());
    g.until("cellgate jobs", Duration::from_secs(20), |out| {
        out.lines()
            .any(|l| l.contains(taken) && l.contains("active"))
    });
    let (code, dir, endpoint) = g.stop_keeping();
    assert_eq!(code, Some(0));
    let (g, _) = Gateway::start_in(dir, endpoint);
    let followed = g.ok(&format!("cellgate job {waiting} --follow"));
    assert!(followed.contains(": completed: 136 B sent"), "{followed}");
    let (_, failed, _) = g.run(&format!("cellgate job {taken}"));
    assert!(failed.contains("gateway restarted"), "{failed}");
    assert_eq!(g.stop(), Some(0));
}

/// The `cellgate` commands of the shell blocks of `file` (```sh lines, ```console lines after
/// `$ `), comments stripped.
fn commands_in(file: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(file).unwrap();
    let mut out = Vec::new();
    let mut block: Option<String> = None;
    for line in text.lines() {
        if let Some(fence) = line.trim_start().strip_prefix("```") {
            block = match block {
                Some(_) => None,
                None => Some(fence.trim().to_string()),
            };
            continue;
        }
        let command = match block.as_deref() {
            Some("sh" | "bash" | "shell") => line.trim(),
            Some("console") => match line.trim().strip_prefix("$ ") {
                Some(c) => c,
                None => continue,
            },
            _ => continue,
        };
        let command = command.split(" #").next().unwrap().trim();
        if command.starts_with("cellgate ") && !command.contains(['|', '&', '<', '>', '$']) {
            out.push(command.to_string());
        }
    }
    out
}

/// The README, the Python example's and every page of docs/.
fn doc_pages() -> Vec<PathBuf> {
    let mut docs = vec![
        repo().join("README.md"),
        repo().join("examples/python/README.md"),
    ];
    for entry in std::fs::read_dir(repo().join("docs")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "md") {
            docs.push(path);
        }
    }
    docs.sort();
    docs
}

/// Every command the README and the docs show in their examples is one the binary takes,
/// options included (a renamed option or command fails here, not for a reader).
#[test]
fn every_command_the_docs_show_is_one_the_binary_takes() {
    let mut checked = 0;
    for path in doc_pages() {
        let doc = path.display();
        for line in commands_in(&path) {
            let args: Vec<&str> = line.split_whitespace().skip(1).collect();
            // --help after the arguments: clap checks the command and every option before it
            // and then prints help instead of running.
            let out = std::process::Command::new(BIN)
                .args(&args)
                .arg("--help")
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{doc}: `{line}` is not a command the binary takes:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
            checked += 1;
        }
    }
    assert!(checked > 20, "only {checked} commands found");
}

/// The `curl` lines of the shell blocks of `file`, lines continued with `\` joined, comments
/// cut.
fn curl_lines(file: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(file).unwrap();
    let mut out = Vec::new();
    let mut in_sh = false;
    let mut pending: Option<String> = None;
    for line in text.lines() {
        if let Some(fence) = line.trim_start().strip_prefix("```") {
            in_sh = !in_sh && matches!(fence.trim(), "sh" | "bash" | "shell");
            continue;
        }
        if !in_sh {
            continue;
        }
        let line = line.split("  #").next().unwrap().trim();
        let joined = match pending.take() {
            Some(p) => format!("{p} {line}"),
            None if line.starts_with("curl ") => line.to_string(),
            None => continue,
        };
        match joined.strip_suffix('\\') {
            Some(head) => pending = Some(head.trim_end().to_string()),
            None => out.push(joined),
        }
    }
    out
}

/// Every `curl` line of the MTConnect and console pages, run as written against the default
/// cell (its ports put in place of 5000 and 7480): each answers 200 with the document the
/// page says. The Prometheus line needs a cell file with `[telemetry] prometheus`; its
/// endpoint is scraped in the telemetry tests.
#[test]
fn the_curl_lines_of_the_docs_answer_as_written() {
    if std::process::Command::new("curl")
        .arg("--version")
        .output()
        .is_err()
    {
        eprintln!("skipped: no curl here (.ci/run installs it)");
        return;
    }
    let (g, printed) = Gateway::start();
    let url_of = |what: &str| {
        printed
            .lines()
            .find_map(|l| l.strip_prefix(what))
            .unwrap_or_else(|| panic!("no {what} in:\n{printed}"))
            .trim()
            .trim_start_matches("http://")
            .trim_end_matches('/')
            .to_string()
    };
    let (agent, console) = (url_of("mtconnect: "), url_of("console: "));
    let work = tempfile::tempdir().unwrap();
    let mut csrf = String::new();
    let mut ran = 0;
    for page in ["mtconnect.md", "console.md"] {
        for line in curl_lines(&repo().join("docs").join(page)) {
            let line = line
                .replace("127.0.0.1:5000", &agent)
                .replace("127.0.0.1:7480", &console)
                .replace("TOKEN", &csrf);
            // A stream ends only when its reader stops: this one stops after 3 s.
            let streams = line.contains(" -sN") || line.contains("interval=");
            let full = format!(
                "{line} -w '\\n%{{http_code}}'{}",
                if streams { " --max-time 3" } else { "" }
            );
            let out = std::process::Command::new("sh")
                .arg("-c")
                .arg(&full)
                .current_dir(work.path())
                .output()
                .unwrap();
            let body = String::from_utf8_lossy(&out.stdout).into_owned();
            let code = out.status.code();
            assert!(
                code == Some(0) || (streams && code == Some(28)),
                "{page}: {line}\nexit {code:?}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
            if streams {
                assert!(body.contains("<MTConnectStreams"), "{page}: {line}\n{body}");
            } else {
                let (doc, status) = body.rsplit_once('\n').unwrap_or(("", &body));
                assert_eq!(status, "200", "{page}: {line}\n{body}");
                assert!(
                    !doc.contains("MTConnectError") && !doc.contains("ERROR_CODE_"),
                    "{page}: {line}\n{doc}"
                );
                if let Ok(v) = serde_json::from_str::<serde_json::Value>(doc)
                    && let Some(token) = v["csrf"].as_str()
                {
                    csrf = token.to_string();
                }
            }
            ran += 1;
        }
    }
    assert!(ran >= 8, "the pages' curl lines were found: {ran}");
    assert_eq!(g.stop(), Some(0));
}

/// Whether `arg` stands for something the reader fills in (`JOB_ID`, `FILE`, `MACHINE`),
/// rather than a value typed as it is (`D`, `O1234`, `mill-1`).
fn placeholder(arg: &str) -> bool {
    arg.len() >= 2 && arg.chars().all(|c| c.is_ascii_uppercase() || c == '_')
}

/// Every command of the docs' examples, run as written against the default cell (its
/// endpoint in place of the docs' own, in a folder holding the example files): none hangs,
/// none panics, none is refused as a command the binary does not take. What a command
/// answers depends on what ran before it (a revision 3 that is not there, a job id of the
/// docs' own day): its exit code is the reader's to read, and is not checked here. Left out:
/// the commands that serve until stopped (`run`, `router`, the site views, the simulators,
/// `watch` without `--count`) and those with a placeholder to fill in.
#[test]
fn every_command_of_the_docs_runs_against_a_gateway() {
    let (g, _) = Gateway::start();
    let work = tempfile::tempdir().unwrap();
    std::os::unix::fs::symlink(repo().join("examples"), work.path().join("examples")).unwrap();
    std::fs::copy(
        repo().join("examples/programs/O1234.nc"),
        work.path().join("O1234.nc"),
    )
    .unwrap();
    let serving = [
        "run",
        "router",
        "console",
        "mtconnect",
        "opcua",
        "historian",
        "acl",
    ];
    let (mut ran, mut ok) = (0, 0);
    let mut failed = Vec::new();
    for path in doc_pages() {
        for line in commands_in(&path) {
            let args: Vec<String> = line
                .split_whitespace()
                .skip(1)
                .map(|a| {
                    if a.starts_with("tcp/") || a.starts_with("tls/") {
                        g.endpoint.clone()
                    } else {
                        a.to_string()
                    }
                })
                .collect();
            let first = args.first().map(String::as_str).unwrap_or_default();
            let second = args.get(1).map(String::as_str).unwrap_or_default();
            if args
                .iter()
                .any(|a| placeholder(a) || a.contains('"') || a.contains('\''))
                || serving.contains(&first)
                || (first == "sim" && matches!(second, "fanuc" | "fuji"))
                || (first == "watch" && !args.iter().any(|a| a == "--count"))
                || args
                    .iter()
                    .any(|a| a == "--config" || a == "-c" && first == "check-config")
            {
                continue;
            }
            let mut child = command(&args)
                .current_dir(work.path())
                .env("CELLGATE_CONNECT", &g.endpoint)
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap();
            let status = common::cli::wait_with_deadline(&mut child, Duration::from_secs(90));
            let mut err = String::new();
            if let Some(mut e) = child.stderr.take() {
                use std::io::Read as _;
                let _ = e.read_to_string(&mut err);
            }
            let doc = path.strip_prefix(repo()).unwrap_or(&path).display();
            match status {
                None => {
                    let _ = child.kill();
                    failed.push(format!("{doc}: `{line}` did not end within 90 s"));
                }
                Some(s) if s.code().is_none() || err.contains("panicked") => {
                    failed.push(format!("{doc}: `{line}` crashed: {s}\n{err}"));
                }
                Some(_) if err.contains("Usage:") => {
                    failed.push(format!("{doc}: `{line}` is refused as a command:\n{err}"));
                }
                Some(s) => {
                    if s.success() {
                        ok += 1;
                    } else {
                        eprintln!(
                            "{doc}: `{line}`: {s}: {}",
                            err.lines().next().unwrap_or_default()
                        );
                    }
                }
            }
            ran += 1;
        }
    }
    eprintln!("{ran} commands of the docs run, {ok} exited 0");
    assert!(failed.is_empty(), "{failed:#?}");
    assert!(ran > 40 && ok * 2 > ran, "{ran} run, {ok} exited 0");
    assert_eq!(g.stop(), Some(0));
}
