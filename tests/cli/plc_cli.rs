//! `cellgate plc …` and `cellgate tag …` against `cellgate run` on the embedded default cell
//! (its simulated PLC, plc-1).

use std::net::TcpStream;
use std::process::{Output, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use crate::common;

use common::bus::free_port;
use common::cli::text;

fn cli(endpoint: &str, args: &[&str]) -> Output {
    common::cli::bin()
        .args(args)
        .args(["--connect", endpoint])
        .env_remove("CELLGATE_CONFIG")
        .output()
        .unwrap()
}

#[test]
fn plc_and_tag_commands_work_against_the_default_cell() {
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
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
            "off",
            "--opcua",
            "off",
        ])
        .env_remove("OTEL_EXPORTER_OTLP_ENDPOINT")
        .env_remove("CELLGATE_CONFIG")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < deadline, "cellgate never listened");
        thread::sleep(Duration::from_millis(50));
    }
    let run = |args: &[&str]| cli(&endpoint, args);
    // The gateway shows itself (its admin key) once every route is declared.
    while !run(&["status"]).status.success() {
        assert!(Instant::now() < deadline, "cellgate never answered");
        thread::sleep(Duration::from_millis(100));
    }

    // Words written come back in order (16-bit area, high byte first on the wire).
    let o = run(&["plc", "write", "plc-1", "D", "10", "0x1234", "65535"]);
    assert!(o.status.success(), "{}", text(&o));
    let o = run(&["plc", "read", "plc-1", "D", "10", "--count", "2"]);
    assert!(o.status.success(), "{}", text(&o));
    let out = text(&o);
    assert!(out.contains("D10 = 4660 (0x1234)"), "{out}");
    assert!(out.contains("D11 = 65535 (0xFFFF)"), "{out}");

    // Clear, then the words read 0.
    let o = run(&["plc", "clear", "plc-1", "D"]);
    assert!(o.status.success(), "{}", text(&o));
    let o = run(&["plc", "read", "plc-1", "D", "10"]);
    assert!(text(&o).contains("D10 = 0 "), "{}", text(&o));

    // Message 1 is registered in the default cell; message 2 is not: STA A7.
    let o = run(&["plc", "send", "plc-1", "1", "48656C6C6F"]);
    assert!(o.status.success(), "{}", text(&o));
    let o = run(&["plc", "send", "plc-1", "2", "00"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("ERROR_CODE_PLC_TRANSFER"), "{}", text(&o));
    // The refusal is counted under its STA as the manual writes it, and its age is shown.
    let o = run(&["plc", "status", "--json"]);
    assert!(o.status.success(), "{}", text(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let station = &v[0]["stations"][0];
    assert_eq!(station["error_replies"]["A7"], 1, "{station}");
    let now = cellgate_core::pb::unix_ms(std::time::SystemTime::now());
    let at = station["last_error_unix_ms"].as_u64().unwrap();
    assert!(at <= now && now - at < 60_000, "{station}");
    let o = run(&["plc", "status"]);
    assert!(text(&o).contains(" s ago: "), "{}", text(&o));

    // A tag reads what was written as soon as the write is confirmed.
    let o = run(&["tag", "set", "recipe", "42"]);
    assert!(o.status.success(), "{}", text(&o));
    let o = run(&["tag", "get", "recipe"]);
    assert!(text(&o).contains("plc-1/recipe = 42 "), "{}", text(&o));

    // Tags: a writable one is written (scale undone) and reads back; a read-only one is
    // refused by the gateway.
    let o = run(&["tag", "set", "spindle-temp", "-12.5"]);
    assert!(o.status.success(), "{}", text(&o));
    let o = run(&["plc", "read", "plc-1", "D", "2"]);
    assert!(
        text(&o).contains("(0xFF83)"),
        "-125 as a 16-bit word: {}",
        text(&o)
    );
    let o = run(&["tag", "set", "parts", "3"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("read-only"), "{}", text(&o));

    // The part counter moves by itself (the sim's tick): two gets a few seconds apart differ.
    let value = |o: &Output| -> f64 {
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        v["value"].as_f64().unwrap()
    };
    let deadline = Instant::now() + Duration::from_secs(10);
    let first = loop {
        let o = run(&["tag", "get", "parts", "--json"]);
        if o.status.success() && text(&o).contains("\"good\"") {
            break value(&o);
        }
        assert!(Instant::now() < deadline, "{}", text(&o));
        thread::sleep(Duration::from_millis(200));
    };
    thread::sleep(Duration::from_millis(2500));
    let o = run(&["tag", "get", "parts", "--json"]);
    assert!(value(&o) > first, "{}", text(&o));

    let o = run(&["status"]);
    assert!(text(&o).contains("plc-1"), "{}", text(&o));
    // Each poll group's achieved round time is in the PLC's status.
    assert!(
        text(&o).contains("poll group 0 every") && text(&o).contains("achieved interval"),
        "{}",
        text(&o)
    );

    let _ = child.kill();
    let _ = child.wait();
}
