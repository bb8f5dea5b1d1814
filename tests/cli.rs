//! The `cellgate` binary as a user runs it: version, run until a signal, check-config.

mod common;

use common::bus::free_port;

use std::io::Read;
use std::net::{TcpListener, TcpStream};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_cellgate");

/// Collects a child's stderr on a thread so the pipe never fills up.
fn collect_stderr(child: &mut Child) -> JoinHandle<String> {
    let mut stderr = child.stderr.take().unwrap();
    thread::spawn(move || {
        let mut text = String::new();
        let _ = stderr.read_to_string(&mut text);
        text
    })
}

fn wait_with_deadline(child: &mut Child, limit: Duration) -> Option<ExitStatus> {
    let deadline = Instant::now() + limit;
    while Instant::now() < deadline {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(status);
        }
        thread::sleep(Duration::from_millis(20));
    }
    None
}

#[test]
fn version_prints_the_crate_version() {
    let out = Command::new(BIN).arg("--version").output().unwrap();
    assert!(out.status.success());
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert_eq!(
        stdout.trim(),
        format!("cellgate {}", env!("CARGO_PKG_VERSION"))
    );
}

/// Starts `cellgate run` on a free loopback port, waits until the port accepts, sends
/// `signal`, and expects a clean exit 0 within a few seconds.
fn run_then_signal(signal: &str) {
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    // The embedded cell keeps its programs and journal under the working directory.
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(BIN)
        .current_dir(dir.path())
        .args(["run", "--listen", &endpoint, "--no-multicast-scouting"])
        .env("RUST_LOG", "info")
        .env_remove("OTEL_EXPORTER_OTLP_ENDPOINT")
        .env_remove("CELLGATE_CONFIG")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = collect_stderr(&mut child);

    let deadline = Instant::now() + Duration::from_secs(30);
    let mut up = false;
    while Instant::now() < deadline {
        if TcpStream::connect(("127.0.0.1", port)).is_ok() {
            up = true;
            break;
        }
        if let Some(status) = child.try_wait().unwrap() {
            panic!(
                "cellgate exited early with {status}:\n{}",
                stderr.join().unwrap()
            );
        }
        thread::sleep(Duration::from_millis(50));
    }
    if !up {
        let _ = child.kill();
        panic!(
            "cellgate never listened on {endpoint}:\n{}",
            stderr.join().unwrap()
        );
    }

    let killed = Command::new("kill")
        .args([&format!("-{signal}"), &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());

    let status = wait_with_deadline(&mut child, Duration::from_secs(10));
    if status.is_none() {
        let _ = child.kill();
        let _ = child.wait();
    }
    let log = stderr.join().unwrap();
    let status = status.unwrap_or_else(|| panic!("cellgate did not stop on SIG{signal}:\n{log}"));
    assert_eq!(status.code(), Some(0), "exit status {status}:\n{log}");
    assert!(log.contains("running, listening on"), "{log}");
    assert!(log.contains(&endpoint), "{log}");
    assert!(log.contains("cellgate stopped"), "{log}");
}

#[test]
fn run_stops_cleanly_on_sigterm() {
    run_then_signal("TERM");
}

#[test]
fn run_stops_cleanly_on_sigint() {
    run_then_signal("INT");
}

#[test]
fn check_config_rejects_a_bad_file_with_exit_code_2() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad-cell.toml");
    std::fs::write(&path, "cell = \n[bus\nlisten = 7\n").unwrap();
    let out = Command::new(BIN)
        .args(["check-config", path.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(!stderr.trim().is_empty());
    // Each error starts with the file it is about (an error may continue on further
    // lines, e.g. a TOML snippet).
    let first = stderr.lines().next().unwrap();
    assert!(
        first.starts_with(path.to_str().unwrap()),
        "error without the file name: {stderr}"
    );
    assert!(out.stdout.is_empty());
}

#[test]
fn check_config_on_a_missing_file_exits_2() {
    let out = Command::new(BIN)
        .args(["check-config", "/nonexistent/cell.toml"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn run_with_a_bad_file_exits_2_without_starting() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cell.toml");
    std::fs::write(&path, "this is not a cell file").unwrap();
    let out = Command::new(BIN)
        .args(["run", "--config", path.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn a_usage_error_exits_2() {
    let out = Command::new(BIN).arg("no-such-command").output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let out = Command::new(BIN)
        .args(["run", "--mode", "satellite"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn run_on_an_endpoint_in_use_exits_1() {
    let taken = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    // Its programs directory and journal go in a directory of its own.
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(BIN)
        .current_dir(dir.path())
        .args(["run", "--listen", &format!("tcp/127.0.0.1:{port}")])
        .env_remove("OTEL_EXPORTER_OTLP_ENDPOINT")
        .env_remove("CELLGATE_CONFIG")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = collect_stderr(&mut child);
    let status = wait_with_deadline(&mut child, Duration::from_secs(30));
    if status.is_none() {
        let _ = child.kill();
        let _ = child.wait();
    }
    let log = stderr.join().unwrap();
    let status = status.unwrap_or_else(|| panic!("cellgate kept running on a taken port:\n{log}"));
    assert_eq!(status.code(), Some(1), "{log}");
    drop(taken);
}
