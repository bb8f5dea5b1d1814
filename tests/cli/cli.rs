//! The `cellgate` binary as a user runs it: version, run until a signal, check-config.

use crate::common;

use common::bus::free_port;

use std::net::{TcpListener, TcpStream};
use std::process::{Command, Stdio};
use std::thread::{self};
use std::time::{Duration, Instant};

use common::cli::{collect_stderr, wait_with_deadline};

#[test]
fn version_prints_the_crate_version() {
    let out = common::cli::bin().arg("--version").output().unwrap();
    assert!(out.status.success());
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert_eq!(
        stdout.trim(),
        format!("cellgate {}", env!("CARGO_PKG_VERSION"))
    );
}

/// Starts `cellgate run` on a free loopback port, waits until it runs, sends
/// `signal`, and expects a clean exit 0 within a few seconds.
fn run_then_signal(signal: &str) {
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    // The embedded cell keeps its programs and journal under the working directory.
    let dir = tempfile::tempdir().unwrap();
    let mut child = common::cli::bin()
        .current_dir(dir.path())
        .args([
            "run",
            "--listen",
            &endpoint,
            "--no-multicast-scouting",
            "--console",
            "127.0.0.1:0",
            "--mtconnect",
            "127.0.0.1:0",
            "--opcua",
            "127.0.0.1:0",
        ])
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

    // The port accepts before the cell is served; the signal goes once the gateway says it
    // runs (a signal while it starts is tests/hostile.rs's).
    if !stderr.wait_for("running, listening on", Duration::from_secs(30)) {
        let _ = child.kill();
        panic!("cellgate never said it runs:\n{}", stderr.join().unwrap());
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
    let out = common::cli::bin()
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

/// 7 data bits over a device server: `check-config` says where the parity bit is made, and
/// what to set if the device server passes whole frames (FFU120B §4-3 items 5–6); with
/// `parity_by` set it says nothing more than the summary does, and `parity_by = "gateway"` on
/// an 8-bit line is refused.
#[test]
fn check_config_explains_where_a_7_bit_lines_parity_is_made() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cell.toml");
    let file = |transport_extra: &str, line: &str| {
        format!(
            "cell = \"c\"\n[[plcs]]\nname = \"p\"\nmode = 4\n\
             transport = {{ kind = \"tcp\", address = \"127.0.0.1:4001\"{transport_extra}, \
             line = {{ baud = 9600, {line} }} }}\n"
        )
    };
    let check = |text: String| {
        std::fs::write(&path, text).unwrap();
        let out = common::cli::bin()
            .args(["check-config", path.to_str().unwrap()])
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8(out.stdout).unwrap(),
            String::from_utf8(out.stderr).unwrap(),
        )
    };
    let seven = "data_bits = 7, parity = \"even\", stop_bits = 1";
    let (code, stdout, stderr) = check(file("", seven));
    assert_eq!(code, Some(0), "{stderr}");
    assert!(
        stderr.contains(
            "warning: plcs.p.transport: 7 data bits with even parity over a device server"
        ) && stderr.contains("parity_by = \"gateway\""),
        "{stderr}"
    );
    assert!(
        stdout.contains("parity made and checked by the device server"),
        "{stdout}"
    );
    let (code, stdout, stderr) = check(file(", parity_by = \"gateway\"", seven));
    assert_eq!(code, Some(0), "{stderr}");
    assert!(!stderr.contains("warning"), "{stderr}");
    assert!(
        stdout.contains("parity made and checked by the gateway (the device server passes 8-bit frames, 9600 8N1)"),
        "{stdout}"
    );
    let (code, _, stderr) = check(file(", parity_by = \"gateway\"", "data_bits = 8"));
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains(
            "plcs.p.transport.parity_by = \"gateway\": the gateway carries a parity bit in bit 7"
        ),
        "{stderr}"
    );
}

#[test]
fn check_config_on_a_missing_file_exits_2() {
    let out = common::cli::bin()
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
    let out = common::cli::bin()
        .args(["run", "--config", path.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn a_usage_error_exits_2() {
    let out = common::cli::bin().arg("no-such-command").output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let out = common::cli::bin()
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
    let mut child = common::cli::run_on(&format!("tcp/127.0.0.1:{port}"), dir.path())
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

#[test]
fn logs_to_a_pipe_carry_no_terminal_colours() {
    // The site console on an endpoint where nothing listens: it logs, then gives up.
    let out = common::cli::command([
        "console",
        "-e",
        "tcp/127.0.0.1:1",
        "--listen",
        "127.0.0.1:0",
    ])
    .env("RUST_LOG", "info")
    .output()
    .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.is_empty(), "it logged something");
    assert!(!err.contains('\u{1b}'), "{err}");
}

/// A bus port or the console's in use: one line saying which and what to change, exit 1,
/// and nothing created (no journal, history or library index beside the cell file).
#[test]
fn run_on_an_address_in_use_says_so_in_one_line_and_creates_nothing() {
    let taken = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let free = free_port();
    for (listen, console, expected) in [
        (
            port,
            free,
            format!(
                "cellgate: cannot listen on tcp/127.0.0.1:{port}: the address is in use \
                 (another gateway?) — choose another with [bus] listen or --listen"
            ),
        ),
        (
            free,
            port,
            format!(
                "cellgate: cannot listen on 127.0.0.1:{port} for the console: the address is \
                 in use (another gateway?) — choose another with [console] listen or --console"
            ),
        ),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cell.toml");
        std::fs::write(
            &path,
            format!(
                "cell = \"taken\"\n[bus]\nlisten = [\"tcp/127.0.0.1:{listen}\"]\n\
                 [programs]\ndir = \"programs\"\n[console]\nlisten = \"127.0.0.1:{console}\"\n\
                 [[machines]]\nname = \"m1\"\nprotocol = \"a\"\n\
                 transport = {{ kind = \"sim\" }}\n"
            ),
        )
        .unwrap();
        let out = common::cli::bin()
            .current_dir(dir.path())
            .args([
                "run",
                "--config",
                "cell.toml",
                "--mtconnect",
                "off",
                "--opcua",
                "off",
            ])
            .env("RUST_LOG", "info")
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{stderr}");
        assert_eq!(stderr.trim_end(), expected);
        let left: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(left, ["cell.toml"], "the run left files behind");
    }
    drop(taken);
}

/// `check-config` shows every section that changes what the gateway serves: the console, the
/// MTConnect agent, and each PLC tag with where it lives and who may write it.
#[test]
fn check_config_shows_the_console_the_agent_and_every_tag() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cell.toml");
    std::fs::write(
        &path,
        "cell = \"c\"\n[console]\nlisten = \"127.0.0.1:7481\"\nsession_idle_minutes = 15\n\
         [mtconnect]\nshdr_listen = \"127.0.0.1:7878\"\n\
         [[plcs]]\nname = \"plc-1\"\nmode = 1\ntransport = { kind = \"sim\" }\n\
         [[plcs.tags]]\nname = \"parts\"\nmodule = \"D\"\naddress = 0\ntype = \"u16\"\n\
         [[plcs.tags]]\nname = \"door\"\nmodule = \"M\"\naddress = 2\ntype = \"bit\"\nbit = 3\n\
         poll_ms = 200\nwritable = true\n",
    )
    .unwrap();
    let (code, out, err) = common::cli::run(["check-config", path.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    for line in [
        "    tags: 2",
        "      parts: D0 u16, station 00, read every 1000 ms, read-only",
        "      door: M2 bit 3, station 00, read every 200 ms, writable",
        "console: on 127.0.0.1:7481 (HTTP), sessions end after 15 min idle and 12 h at most, 16 per user",
        "mtconnect: agent on 127.0.0.1:5000 (HTTP), 131072 observations kept, SHDR adapter on 127.0.0.1:7878",
    ] {
        assert!(out.lines().any(|l| l == line), "no {line:?} in:\n{out}");
    }
    // Without the sections, the summary says so.
    std::fs::write(&path, "cell = \"c\"\n").unwrap();
    let (_, out, _) = common::cli::run(["check-config", path.to_str().unwrap()]);
    assert!(
        out.contains("console: none (no [console])")
            && out.contains("mtconnect: none (no [mtconnect])"),
        "{out}"
    );
}
