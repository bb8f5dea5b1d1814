//! `cellgate reload` and SIGHUP against a `cellgate run --config FILE` process: the file read
//! again, what changed applied, a bad file refused with every error (the command's output and
//! the gateway's log), the process never ended by the signal.

use std::process::{Output, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use crate::common;

use common::bus::free_port;
use common::cli::{Reaper, collect_stderr, text};

fn cli(endpoint: &str, args: &[&str]) -> Output {
    common::cli::command(args)
        .args(["--connect", endpoint])
        .output()
        .unwrap()
}

fn machine(name: &str) -> String {
    format!("[[machines]]\nname = \"{name}\"\nprotocol = \"a\"\ntransport = {{ kind = \"sim\" }}\n")
}

#[test]
fn reload_and_sighup_apply_the_file_and_a_bad_one_is_refused_with_every_error() {
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cell.toml");
    let head = format!(
        "cell = \"cli-reload\"\n[bus]\nlisten = [\"{endpoint}\"]\n[programs]\ndir = \"{}\"\n",
        dir.path().join("programs").display()
    );
    std::fs::write(&path, format!("{head}{}", machine("m1"))).unwrap();
    let mut child = common::cli::command(["run", "--config", path.to_str().unwrap()])
        .args(common::cli::ONLY_THE_BUS)
        .current_dir(dir.path())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = collect_stderr(&mut child);
    let gateway = Reaper(child);
    let run = |args: &[&str]| cli(&endpoint, args);
    let deadline = Instant::now() + Duration::from_secs(30);
    while !run(&["status"]).status.success() {
        assert!(Instant::now() < deadline, "cellgate never answered");
        thread::sleep(Duration::from_millis(100));
    }

    // A machine added: taken, and the status shows it and the generation.
    std::fs::write(&path, format!("{head}{}{}", machine("m1"), machine("m2"))).unwrap();
    let o = run(&["reload", "--json"]);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["applied"], true, "{r}");
    // uint64 as a string: the proto3 JSON mapping.
    assert_eq!(r["generation"], "2", "{r}");
    assert_eq!(r["machines_added"], serde_json::json!(["m2"]), "{r}");
    let o = run(&["status"]);
    let out = text(&o);
    assert!(
        out.contains("m2") && out.contains("configuration generation 2"),
        "{out}"
    );
    // The same file again: taken, nothing changed, the same generation.
    let o = run(&["reload", "--json"]);
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (&r["applied"], &r["generation"]),
        (&true.into(), &"2".into()),
        "{r}"
    );
    let o = run(&["reload"]);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    assert!(
        String::from_utf8_lossy(&o.stdout)
            .contains(": nothing changed (configuration generation 2)"),
        "{}",
        text(&o)
    );

    // A bad file: exit 2, every error, and the gateway says so in its log.
    std::fs::write(
        &path,
        format!("{head}{}[history]\nkeep_dayz = 1\n", machine("m1")),
    )
    .unwrap();
    let o = run(&["reload"]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("reload refused (ERROR_CODE_INVALID_REQUEST)")
            && err.contains(&format!("{}:", path.display()))
            && err.contains("keep_dayz"),
        "{err}"
    );
    assert!(
        log.wait_for("reload refused", Duration::from_secs(10)),
        "{}",
        log.so_far()
    );
    assert!(log.so_far().contains("keep_dayz"), "{}", log.so_far());
    let o = run(&["status"]);
    assert!(text(&o).contains("m2"), "the refused file changed the cell");

    // SIGHUP reloads as `cellgate reload` does, and the gateway goes on.
    std::fs::write(&path, format!("{head}{}", machine("m3"))).unwrap();
    // SAFETY: kill sends a signal to the child this test started; nothing is dereferenced.
    let sent = unsafe { libc::kill(gateway.0.id() as libc::pid_t, libc::SIGHUP) };
    assert_eq!(sent, 0);
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let out = text(&run(&["status"]));
        if out.contains("m3") && out.contains("configuration generation 3") {
            break;
        }
        assert!(Instant::now() < deadline, "SIGHUP did not reload: {out}");
        thread::sleep(Duration::from_millis(200));
    }
    drop(gateway);
    let _ = log.join();
}

/// A FIFO or a link to an endless device in the cell file's place: a reload is refused at
/// once, saying what the file is, the gateway answers meanwhile, and SIGTERM stops it.
#[test]
fn a_fifo_or_a_device_in_the_cell_files_place_is_refused_and_sigterm_still_stops_the_gateway() {
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cell.toml");
    let head = format!(
        "cell = \"cli-fifo\"\n[bus]\nlisten = [\"{endpoint}\"]\n[programs]\ndir = \"{}\"\n",
        dir.path().join("programs").display()
    );
    std::fs::write(&path, format!("{head}{}", machine("m1"))).unwrap();
    let mut child = common::cli::command(["run", "--config", path.to_str().unwrap()])
        .args(common::cli::ONLY_THE_BUS)
        .current_dir(dir.path())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = collect_stderr(&mut child);
    let mut gateway = Reaper(child);
    let run = |args: &[&str]| cli(&endpoint, args);
    let deadline = Instant::now() + Duration::from_secs(30);
    while !run(&["status"]).status.success() {
        assert!(Instant::now() < deadline, "cellgate never answered");
        thread::sleep(Duration::from_millis(100));
    }

    // A FIFO nothing writes to: refused for what it is (before, the reload waited for a
    // writer for ever, and every later one behind it).
    std::fs::remove_file(&path).unwrap();
    let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes()).unwrap();
    // SAFETY: mkfifo reads the NUL-terminated path it is given; nothing else is touched.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    for _ in 0..2 {
        let o = run(&["reload"]);
        assert_eq!(o.status.code(), Some(2), "{}", text(&o));
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("a FIFO, not a regular file") && err.contains(&path.display().to_string()),
            "{err}"
        );
        assert!(run(&["status"]).status.success());
    }

    // A link to /dev/zero: refused, not read (before, the gateway grew until memory ran out).
    std::fs::remove_file(&path).unwrap();
    std::os::unix::fs::symlink("/dev/zero", &path).unwrap();
    let o = run(&["reload"]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("a character device"),
        "{}",
        text(&o)
    );

    // A FIFO again, a reload asked for by signal, and then SIGTERM: the gateway stops.
    std::fs::remove_file(&path).unwrap();
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    let pid = gateway.0.id() as libc::pid_t;
    // SAFETY: kill sends signals to the child this test started; nothing is dereferenced.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGHUP) }, 0);
    assert_eq!(unsafe { libc::kill(pid, libc::SIGTERM) }, 0);
    let status = common::cli::wait_with_deadline(&mut gateway.0, Duration::from_secs(20));
    assert!(
        status.is_some(),
        "SIGTERM did not stop the gateway: {}",
        log.so_far()
    );
    let _ = log.join();
}
