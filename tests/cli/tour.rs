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
                let done = line.starts_with("try: ");
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
            },
            printed,
        )
    }

    /// A tour command as written, against this gateway: (exit code, stdout, stderr).
    fn run(&self, line: &str) -> (i32, String, String) {
        let args: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(args[0], "cellgate", "{line}");
        let out = command(&args[1..])
            .current_dir(repo())
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

    // 8. A CNC alarm, played by hand.
    g.ok("cellgate sim auto mill-1 off");
    g.ok("cellgate sim alarm mill-1");
    g.until(
        "cellgate status mill-1 --json",
        Duration::from_secs(30),
        |out| out.contains("LINK_STATE_ALARM"),
    );
    let job = g.ok("cellgate submit mill-1 examples/programs/O1234.nc --detach");
    let job = job.trim();
    let status = g.ok("cellgate status mill-1");
    assert!(status.lines().nth(1).unwrap().contains("alarm"), "{status}");
    assert!(status.contains(job), "{status}");
    g.ok("cellgate sim reset mill-1");
    let status = g.until("cellgate status mill-1", Duration::from_secs(30), |out| {
        out.contains("waiting for CNC")
    });
    assert!(
        !status.lines().nth(1).unwrap().contains("alarm"),
        "the reset ended the alarm: {status}"
    );
    assert!(status.contains(&format!("job {job} waits")), "{status}");
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
    let scratch = tempfile::tempdir().unwrap();
    let copy = scratch.path().join("O1234.nc");
    g.ok(&format!("cellgate program get O1234 -o {}", copy.display()));
    let text = std::fs::read_to_string(&copy).unwrap();
    assert!(text.contains("N30 G01 X50.0 F300"), "{text}");
    std::fs::write(
        &copy,
        text.replace("N30 G01 X50.0 F300", "N30 G01 X50.0 F250"),
    )
    .unwrap();
    g.ok(&format!(
        "cellgate program put O1234 {} --comment feed-F250",
        copy.display()
    ));
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
    let audit = g.ok("cellgate audit --since 1h");
    assert!(
        audit.contains("program.release O1234 revision 2"),
        "{audit}"
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

/// Every command the README and the docs show in their examples is one the binary takes,
/// options included (a renamed option or command fails here, not for a reader).
#[test]
fn every_command_the_docs_show_is_one_the_binary_takes() {
    let mut checked = 0;
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
    for path in docs {
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
