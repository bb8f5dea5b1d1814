//! `cellgate sim fanuc --boards N`: N independent boards from one process, on consecutive
//! ports, each event line tagged with its board. Loopback only.

use crate::common;

use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::process::Stdio;
use std::time::{Duration, Instant};

use common::bus::free_ports;

#[test]
fn boards_listen_on_consecutive_ports_and_tag_their_events() {
    let first = free_ports(3);
    let mut child = common::cli::bin()
        .args([
            "sim",
            "fanuc",
            "--boards",
            "3",
            "--protocol",
            "a",
            "--baud",
            "19200",
        ])
        .args(["--listen", &format!("127.0.0.1:{first}")])
        .env("RUST_LOG", "error")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let mut next = || -> serde_json::Value {
        let line = lines.next().expect("an event line").unwrap();
        serde_json::from_str(&line).unwrap()
    };
    let mut listening = Vec::new();
    while listening.len() < 3 {
        let e = next();
        if e["event"] == "listening" {
            listening.push((
                e["board"].as_u64().unwrap(),
                e["addr"].as_str().unwrap().to_string(),
            ));
        }
    }
    listening.sort();
    let want: Vec<(u64, String)> = (0..3u16)
        .map(|i| (u64::from(i), format!("127.0.0.1:{}", first + i)))
        .collect();
    assert_eq!(listening, want);

    // The third board answers on its own port, and says so as board 2.
    let deadline = Instant::now() + Duration::from_secs(10);
    let _host = loop {
        match TcpStream::connect(("127.0.0.1", first + 2)) {
            Ok(s) => break s,
            Err(e) => {
                assert!(Instant::now() < deadline, "board 2 never accepted: {e}");
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    };
    let connected = loop {
        let e = next();
        if e["event"] == "connected" {
            break e;
        }
    };
    assert_eq!(connected["board"], 2);

    // SAFETY: kill(2) on the pid of a child this process spawned and has not reaped.
    unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
    assert!(child.wait().unwrap().success());
}

#[test]
fn boards_past_the_last_port_are_refused() {
    let out = common::cli::bin()
        .args([
            "sim",
            "fanuc",
            "--boards",
            "10",
            "--listen",
            "127.0.0.1:65530",
        ])
        .stdin(Stdio::null())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("10 boards need 10 consecutive ports from 127.0.0.1:65530"),
        "{err}"
    );
}
