//! `cellgate sim fuji` as a TCP device server, with `cellgate run` polling it through a
//! `kind = "tcp"` PLC and `cellgate plc …` / `cellgate tag …` talking to it over the bus.
//! Loopback only.

use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::process::Stdio;
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use serde_json::Value;

use crate::common;

use common::bus::free_port;
use common::cli::{Reaper, text};

/// The simulator's JSON event lines, collected by a thread.
#[derive(Clone, Default)]
struct Events(Arc<Mutex<Vec<Value>>>);

impl Events {
    fn all(&self) -> Vec<Value> {
        self.0.lock().unwrap().clone()
    }

    /// Waits up to 20 s for an event that `pred` accepts.
    fn wait_for(&self, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            if let Some(v) = self.all().into_iter().find(|v| pred(v)) {
                return v;
            }
            assert!(
                Instant::now() < deadline,
                "no {what} event; got: {:#?}",
                self.all()
            );
            thread::sleep(Duration::from_millis(20));
        }
    }
}

#[test]
fn the_gateway_polls_writes_and_is_refused_through_sim_fuji() {
    let sim_port = free_port();
    let mut sim = common::cli::bin()
        .args([
            "sim",
            "fuji",
            "--listen",
            &format!("127.0.0.1:{sim_port}"),
            "--mode",
            "3",
            "--stations",
            "1,2",
            "--baud",
            "19200",
            "--parity",
            "odd",
            "--stop-bits",
            "1",
            "--bcc",
            "set1",
            "--bcc-range",
            "start+text+end",
            "--bcc-calc",
            "eor",
        ])
        .env_remove("OTEL_EXPORTER_OTLP_ENDPOINT")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let stdout = sim.stdout.take().unwrap();
    let _sim = Reaper(sim);
    let events = Events::default();
    {
        let events = events.clone();
        thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                let v: Value = serde_json::from_str(&line)
                    .unwrap_or_else(|e| panic!("not a JSON line: {line:?}: {e}"));
                events.0.lock().unwrap().push(v);
            }
        });
    }
    let listening = events.wait_for("listening", |v| v["event"] == "listening");
    assert_eq!(listening["mode"], 3);
    assert_eq!(listening["stations"], serde_json::json!([1, 2]));

    let bus_port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{bus_port}");
    let dir = tempfile::tempdir().unwrap();
    let cell = dir.path().join("cell.toml");
    std::fs::write(
        &cell,
        format!(
            r#"cell = "fuji-tcp"

[[plcs]]
name = "line-1"
mode = 3
stations = [1, 2]
bcc = "set1"
bcc_range = "start+text+end"
bcc_calc = "eor"
timeout_ms = 500
transport = {{ kind = "tcp", address = "127.0.0.1:{sim_port}", line = {{ baud = 19200, parity = "odd", stop_bits = 1 }} }}

[[plcs.tags]]
name = "count"
station = 2
module = "D"
address = 10
type = "u16"
poll_ms = 200
"#
        ),
    )
    .unwrap();
    let gateway = common::cli::bin()
        .current_dir(dir.path())
        .args([
            "run",
            "--config",
            cell.to_str().unwrap(),
            "--listen",
            &endpoint,
            "--no-multicast-scouting",
        ])
        .env_remove("OTEL_EXPORTER_OTLP_ENDPOINT")
        .env_remove("CELLGATE_CONFIG")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let _gateway = Reaper(gateway);
    let deadline = Instant::now() + Duration::from_secs(30);
    while TcpStream::connect(("127.0.0.1", bus_port)).is_err() {
        assert!(Instant::now() < deadline, "cellgate never listened");
        thread::sleep(Duration::from_millis(50));
    }
    let run = |args: &[&str]| {
        common::cli::bin()
            .args(args)
            .args(["--connect", &endpoint])
            .env_remove("CELLGATE_CONFIG")
            .output()
            .unwrap()
    };

    // The gateway connected and polls the tag: requests to station 2 and their replies.
    events.wait_for("connected", |v| v["event"] == "connected");
    let poll = events.wait_for("request to station 2", |v| {
        v["event"] == "request" && v["station"] == 2 && v["moln"] == "05"
    });
    assert_eq!(poll["cmnd"], "00", "{poll}");
    events.wait_for("reply from station 2", |v| {
        v["event"] == "reply" && v["station"] == 2 && v["sta"] == "00"
    });

    // A write through the bus reaches station 2's D10, in order.
    let o = run(&[
        "plc",
        "write",
        "line-1",
        "D",
        "10",
        "0x1234",
        "7",
        "--station",
        "2",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let written = events.wait_for("written", |v| v["event"] == "written");
    assert_eq!(written["station"], 2, "{written}");
    assert_eq!(written["module"], "D", "{written}");
    assert_eq!(written["address"], 10, "{written}");
    assert_eq!(
        written["words"],
        serde_json::json!([0x1234, 7]),
        "{written}"
    );
    let o = run(&[
        "plc",
        "read",
        "line-1",
        "D",
        "10",
        "--count",
        "2",
        "--station",
        "2",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("D10 = 4660 (0x1234)"), "{}", text(&o));
    assert!(text(&o).contains("D11 = 7 (0x0007)"), "{}", text(&o));
    // Station 1 has its own memory.
    let o = run(&["plc", "read", "line-1", "D", "10", "--station", "1"]);
    assert!(text(&o).contains("D10 = 0 "), "{}", text(&o));

    // The tag follows the write.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let o = run(&["tag", "get", "count"]);
        if text(&o).contains("= 4660") {
            break;
        }
        assert!(Instant::now() < deadline, "{}", text(&o));
        thread::sleep(Duration::from_millis(200));
    }

    // An address beyond the module: the sim refuses it with STA 32, typed on the bus.
    let o = run(&["plc", "read", "line-1", "D", "65000", "--station", "1"]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("ERROR_CODE_PLC_OVER_MEMORY"),
        "{}",
        text(&o)
    );
    let refused = events.wait_for("refused", |v| v["event"] == "refused");
    assert_eq!(refused["sta"], "32", "{refused}");
    assert_eq!(refused["station"], 1, "{refused}");
    events.wait_for("error reply", |v| v["event"] == "reply" && v["sta"] == "32");
}
