//! `cellgate plc …` and `cellgate tag …` against `cellgate run` on the embedded default cell
//! (its simulated PLC, plc-1).

use std::net::{TcpListener, TcpStream};
use std::process::{Command, Output, Stdio};
use std::thread;
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_cellgate");

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn cli(endpoint: &str, args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .args(["--connect", endpoint])
        .env_remove("CELLGATE_CONFIG")
        .output()
        .unwrap()
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

#[test]
fn plc_and_tag_commands_work_against_the_default_cell() {
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(BIN)
        .current_dir(dir.path())
        .args(["run", "--listen", &endpoint, "--no-multicast-scouting"])
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

    let _ = child.kill();
    let _ = child.wait();
}
