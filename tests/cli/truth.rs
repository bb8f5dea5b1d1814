//! What the client commands say, checked against `cellgate run` on the embedded default cell:
//! `program get` by revision and of a removed program, what `-o` wrote, a job's start before
//! the CNC asks, a punch's true size, and the names a refusal lists.

use std::process::{Child, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use crate::common;

use common::bus::free_port;
use common::cli::{command, run_on};

/// `cellgate run` on the embedded cell, in a directory of its own; killed when dropped.
pub struct Gateway {
    child: Child,
    pub endpoint: String,
    _dir: tempfile::TempDir,
}

impl Gateway {
    /// Starts it and waits until it answers.
    pub fn start() -> Gateway {
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let dir = tempfile::tempdir().unwrap();
        let child = run_on(&endpoint, dir.path())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let g = Gateway {
            child,
            endpoint,
            _dir: dir,
        };
        let deadline = Instant::now() + Duration::from_secs(60);
        while g.run(&["status"]).0 != 0 {
            assert!(Instant::now() < deadline, "cellgate never answered");
            thread::sleep(Duration::from_millis(100));
        }
        g
    }

    /// A client command against it: (exit code, stdout, stderr).
    pub fn run(&self, args: &[&str]) -> (i32, String, String) {
        let out = command(args)
            .env("CELLGATE_CONNECT", &self.endpoint)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .output()
            .unwrap();
        (
            out.status.code().unwrap_or(-1),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    }

    /// [`Self::run`], which must exit 0: (stdout, stderr).
    pub fn ok(&self, args: &[&str]) -> (String, String) {
        let (code, out, err) = self.run(args);
        assert_eq!(code, 0, "{args:?}\nstdout {out}\nstderr {err}");
        (out, err)
    }
}

impl Drop for Gateway {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `program get --revision`, what `-o` wrote, and a removed program's `get` saying how its
/// kept revisions are read.
#[test]
fn program_get_reads_a_revision_says_what_it_wrote_and_what_became_of_a_removed_program() {
    let g = Gateway::start();
    let scratch = tempfile::tempdir().unwrap();
    let v2 = scratch.path().join("v2.nc");
    let text = "%\nO1234\nN10 G01 X1.0 F250\nM30\n%\n";
    std::fs::write(&v2, text).unwrap();
    g.ok(&["program", "put", "O1234", "examples/programs/O1234.nc"]);
    g.ok(&["program", "put", "O1234", v2.to_str().unwrap()]);

    // -o says what it wrote: the name, the size, the revision, the file.
    let copy = scratch.path().join("copy.nc");
    let (out, err) = g.ok(&["program", "get", "O1234", "-o", copy.to_str().unwrap()]);
    assert!(out.is_empty(), "{out}");
    assert_eq!(
        err.trim(),
        format!(
            "wrote O1234 ({} B, revision 2) to {}",
            text.len(),
            copy.display()
        )
    );
    // --revision reads an earlier one, by number or hash.
    let (_, err) = g.ok(&[
        "program",
        "get",
        "O1234",
        "--revision",
        "1",
        "-o",
        copy.to_str().unwrap(),
    ]);
    assert!(err.contains("(137 B, revision 1)"), "{err}");
    let shipped = std::fs::read(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/programs/O1234.nc"),
    )
    .unwrap();
    assert_eq!(std::fs::read(&copy).unwrap(), shipped);
    let (history, _) = g.ok(&["program", "history", "O1234", "--json"]);
    let history: serde_json::Value = serde_json::from_str(&history).unwrap();
    let sha = history["revisions"][1]["sha256"].as_str().unwrap()[..12].to_string();
    let (json, _) = g.ok(&["program", "get", "O1234", "--revision", &sha, "--json"]);
    let json: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(
        (json["revision"].as_u64(), json["size"].as_u64()),
        (Some(1), Some(137))
    );

    // Removed: get says so and how to read what is kept; --revision reads it.
    g.ok(&["program", "rm", "O1234"]);
    let (code, out, err) = g.run(&["program", "get", "O1234"]);
    assert_eq!(code, 2, "{out}{err}");
    assert!(
        err.contains("ERROR_CODE_NOT_FOUND")
            && err.contains("\"O1234\" was removed (its latest revision was 2)")
            && err.contains("`cellgate program get O1234 --revision 2`"),
        "{err}"
    );
    let (out, _) = g.ok(&["program", "get", "O1234", "--revision", "2"]);
    assert!(out.contains("N10 G01 X1.0 F250"), "{out}");
    // The gateway's own answer on the program's key says the same to every client.
    let (code, _, err) = g.run(&["submit", "mill-1", "--library", "O1234"]);
    assert_eq!(code, 2);
    assert!(
        err.contains("was removed (its latest revision was 2)"),
        "{err}"
    );
}

/// A started job says it waits for the CNC until bytes go on the line, and then that the CNC
/// asked; a punch says what the gateway received, not what the board had sent when it took
/// the punch.
#[test]
fn submit_says_it_waits_for_the_cnc_and_a_punch_says_its_true_size() {
    let g = Gateway::start();
    let (out, err) = g.ok(&["submit", "mill-1", "examples/programs/O1234.nc"]);
    let job = out.trim();
    let lines: Vec<&str> = err.lines().collect();
    let at = |needle: &str| {
        lines
            .iter()
            .position(|l| l.contains(needle))
            .unwrap_or_else(|| panic!("no {needle:?} in:\n{err}"))
    };
    let started = at(&format!(
        "{job}: started (137 B): waiting for the CNC to ask for it"
    ));
    let sending = at(&format!("{job}: sending: the CNC asked for it ("));
    let completed = at(&format!("{job}: completed: 136 B sent"));
    assert!(started < sending && sending < completed, "{err}");
    assert!(lines[sending].contains("on the line"), "{err}");

    let (out, _) = g.ok(&["sim", "punch", "lathe-1", "examples/programs/O1234.nc"]);
    assert!(
        out.starts_with("lathe-1 punched O1234: 136 B received of the file's 137 B")
            && out.contains("stored in the library as lathe-1-O1234-"),
        "{out}"
    );
    let (json, _) = g.ok(&[
        "sim",
        "punch",
        "lathe-1",
        "examples/programs/O1234.nc",
        "--json",
    ]);
    let json: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(json["punched"]["size"], 136, "{json}");
}

/// A program, tag or PLC module the cell does not have is refused with the names near it,
/// or those it has when they are few, as a machine it does not have is.
#[test]
fn unknown_programs_tags_and_modules_are_refused_with_the_names_there_are() {
    let g = Gateway::start();
    g.ok(&["program", "put", "O1234", "examples/programs/O1234.nc"]);
    for (args, says) in [
        (
            &["program", "get", "O1243"][..],
            "program O1243: refused by the gateway (ERROR_CODE_NOT_FOUND): the program library \
             has no program \"O1243\"; did you mean O1234?",
        ),
        (
            &["submit", "mill-1", "--library", "O124"],
            "the program library has no program \"O124\"; did you mean O1234?",
        ),
        (
            &["program", "diff", "P77"],
            "has no program \"P77\"; its programs are: O1234",
        ),
        (&["tag", "get", "recipy"], "; did you mean recipe?"),
        (
            &["tag", "get", "nothing-like-it"],
            "; its tags are: door-open, parts, recipe, spindle-temp",
        ),
        (
            &["plc", "read", "plc-1", "TX", "0"],
            "no module \"TX\" in the module table (FFU120B §5-3-3); did you mean TR or TS? \
             Its modules are B, M, K, F, A, D, W9,",
        ),
        (
            &["plc", "read", "plc-1", "Q", "0"],
            "(FFU120B §5-3-3); its modules are B, M, K, F, A, D, W9,",
        ),
    ] {
        let (code, out, err) = g.run(args);
        assert_eq!(code, 2, "{args:?}: {out}{err}");
        assert!(err.contains(says), "{args:?}: {err}");
    }
}

/// (interval, achieved interval, rounds) of each poll group `plc status` shows.
fn poll_groups(status: &str) -> Vec<(u64, u64, u64)> {
    let number_after = |line: &str, word: &str| -> u64 {
        let rest = &line[line.find(word).unwrap() + word.len()..];
        rest.trim_start()
            .split(|c: char| !c.is_ascii_digit())
            .next()
            .unwrap()
            .parse()
            .unwrap()
    };
    status
        .lines()
        .filter(|l| l.contains(": poll group "))
        .map(|l| {
            let rounds = l.rsplit(" in ").next().unwrap();
            (
                number_after(l, " every "),
                number_after(l, "achieved interval "),
                number_after(rounds, ""),
            )
        })
        .collect()
}

/// A tag write reads what it wrote at once; that read is no poll, so the achieved interval
/// `plc status` reports stays the polls' (before, each write made it the time since the last
/// poll or write).
#[test]
fn plc_status_reports_the_polls_interval_not_a_writes_read() {
    let g = Gateway::start();
    // Two rounds of each group first, so that there is an achieved interval.
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let (status, _) = g.ok(&["plc", "status"]);
        let groups = poll_groups(&status);
        if !groups.is_empty() && groups.iter().all(|(_, _, rounds)| *rounds >= 2) {
            break;
        }
        assert!(Instant::now() < deadline, "{status}");
        thread::sleep(Duration::from_millis(200));
    }
    for value in ["41", "42", "43"] {
        g.ok(&["tag", "set", "recipe", value]);
        let (status, _) = g.ok(&["plc", "status"]);
        let slow: Vec<(u64, u64, u64)> = poll_groups(&status)
            .into_iter()
            .filter(|(interval, ..)| *interval >= 1000)
            .collect();
        assert!(!slow.is_empty(), "{status}");
        for (interval, achieved, _) in slow {
            // The polls keep their schedule: within a tenth of the interval of it.
            assert!(achieved * 10 >= interval * 9, "{status}");
        }
    }
}
