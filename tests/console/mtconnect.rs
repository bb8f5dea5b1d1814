//! The MTConnect agent against a simulated cell (the embedded default cell, run in this
//! process): a job shows PROGRAM and EXECUTION change, an alarm raised at a simulated CNC
//! shows as a Fault with its native code and clears on reset, sequence numbers run without
//! gaps, `/sample` streams with heartbeats, errors come as MTConnectError documents with the
//! standard's codes, every kind of document is valid against the MTConnect 2.5 schemas, the
//! SHDR adapter sends the state and each observation and answers `* PING`, a site agent
//! serves the cells of two gateways, and the Python follower of docs/mtconnect.md reads it.
//!
//! Schema validation uses `xmllint` (Debian's libxml2-utils; `.ci/run` installs it); where it
//! is missing, the validating test says it was skipped. libxml2 implements XSD 1.0 and the
//! Devices and Assets schemas use XSD 1.1's `notNamespace="##targetNamespace"` on a wildcard:
//! the test reads it as XSD 1.0's `namespace="##other"`, which allows the same elements.

use crate::common;

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use cellgate::bus;
use cellgate::bus::keys::SimLeaf;
use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use common::bus::free_port;

use super::gateway::{Gateway, Surface};

/// A gateway of the embedded default cell in this process, with its agent on a free port.
async fn start(edit: impl FnOnce(&mut CellConfig)) -> Gateway {
    Gateway::serving(Surface::Agent, None, |c, _| edit(c)).await
}

/// The ring provider for rustls, as the gateway uses it (reqwest is built without one).
fn provider() {
    let _ = tokio_rustls::rustls::crypto::ring::default_provider().install_default();
}

async fn get(url: &str) -> (u16, String) {
    provider();
    let r = reqwest::get(url).await.unwrap();
    let status = r.status().as_u16();
    (status, r.text().await.unwrap())
}

/// GETs `base + path` until `done` holds of its body (at most a minute: a guard against a
/// hang, not a time the test asserts), and returns that body.
async fn wait_for(base: &str, path: &str, done: impl Fn(&str) -> bool) -> String {
    let mut last = String::new();
    for _ in 0..600 {
        if let Ok(r) = reqwest::get(format!("{base}{path}")).await
            && r.status() == 200
        {
            last = r.text().await.unwrap_or_default();
            if done(&last) {
                return last;
            }
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("{base}{path} never showed what was awaited; last:\n{last}");
}

/// The observations of a Streams document: (element, dataItemId, sequence, attributes, text).
fn observations(doc: &str) -> Vec<(String, String, u64, String, String)> {
    let mut out = Vec::new();
    let mut rest = doc;
    while let Some(i) = rest.find(" dataItemId=\"") {
        let start = rest[..i].rfind('<').unwrap();
        let element = rest[start + 1..i].to_string();
        let tag_end = rest[i..].find('>').unwrap() + i;
        let attrs = rest[i..tag_end].to_string();
        let id = attr(&attrs, "dataItemId").unwrap();
        let seq = attr(&attrs, "sequence").unwrap().parse().unwrap();
        let text = if rest[..tag_end].ends_with('/') {
            String::new()
        } else {
            let close = rest[tag_end..].find("</").unwrap() + tag_end;
            rest[tag_end + 1..close].to_string()
        };
        out.push((element, id, seq, attrs, text));
        rest = &rest[tag_end..];
    }
    out
}

fn attr(tag: &str, name: &str) -> Option<String> {
    let key = format!(" {name}=\"");
    let i = tag.find(&key)? + key.len();
    Some(tag[i..].split('"').next()?.to_string())
}

fn header(doc: &str, name: &str) -> u64 {
    let h = &doc[doc.find("<Header").unwrap()..];
    attr(&h[..h.find('>').unwrap()], name)
        .unwrap()
        .parse()
        .unwrap()
}

/// The value `/current` shows for data item `id`.
fn value_of(doc: &str, id: &str) -> Option<(String, String, String)> {
    observations(doc)
        .into_iter()
        .find(|o| o.1 == id)
        .map(|o| (o.0, o.3, o.4))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_shows_program_and_execution_and_sequences_have_no_gaps() {
    let gw = start(|_| {}).await;
    let url = gw.url.clone();
    // The link is up and idle: READY.
    wait_for(&url, "/current", |d| {
        value_of(d, "mill-1_execution").is_some_and(|v| v.2 == "READY")
    })
    .await;
    let client = gw.client().await;
    let mut program = b"%\nO4321\n".to_vec();
    for n in 1..=300 {
        program.extend_from_slice(format!("N{n} G01 X{n}.0 Y{n}.5 F200\n").as_bytes());
    }
    program.extend_from_slice(b"M30\n%\n");
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(program)),
        ..Default::default()
    };
    let (accepted, mut follower) = client.submit("mill-1", &request).await.unwrap();
    let end = tokio::time::timeout(Duration::from_secs(120), follower.wait_end())
        .await
        .expect("the job ends")
        .unwrap();
    assert!(
        matches!(end.kind, Some(pb::job_event::Kind::Completed(_))),
        "{end:?}"
    );
    follower.close().await;
    // The whole program is in the remote buffer and the CNC read it: PROGRAM_COMPLETED.
    let current = wait_for(&url, "/current", |d| {
        value_of(d, "mill-1_execution").is_some_and(|v| v.2 == "PROGRAM_COMPLETED")
    })
    .await;
    // An inline job's program is named by its O-number.
    assert_eq!(value_of(&current, "mill-1_program").unwrap().2, "O4321");
    // The block being fed ends at the program's last block.
    assert_eq!(value_of(&current, "mill-1_block_fed").unwrap().2, "M30");

    // Every observation since the start, in pages of 50, numbered without a gap (up to the
    // last one the current document saw; more may have come since); the execution went
    // through ACTIVE while the CNC read the program.
    let first = header(&current, "firstSequence");
    let last = header(&current, "lastSequence");
    let mut from = first;
    let mut seqs = Vec::new();
    let mut executions = Vec::new();
    let mut blocks = Vec::new();
    while from <= last {
        let count = 50.min(last + 1 - from);
        let (status, page) = get(&format!("{url}/sample?from={from}&count={count}")).await;
        assert_eq!(status, 200, "{page}");
        for o in observations(&page) {
            if o.1 == "mill-1_execution" {
                executions.push(o.4.clone());
            }
            if o.1 == "mill-1_block_fed" && o.4 != "UNAVAILABLE" {
                blocks.push((o.2, o.4.clone()));
            }
            seqs.push(o.2);
        }
        let next = header(&page, "nextSequence");
        assert!(next > from, "{page}");
        from = next;
    }
    // A document groups observations by component: in sequence order once sorted.
    seqs.sort_unstable();
    let expected: Vec<u64> = (first..from).collect();
    assert_eq!(seqs, expected, "sequences without gaps");
    // The blocks went by in the program's order: their sequence numbers rise.
    blocks.sort_unstable();
    let numbers: Vec<u32> = blocks
        .iter()
        .filter_map(|(_, b)| b.strip_prefix('N')?.split(' ').next()?.parse().ok())
        .collect();
    assert!(
        numbers.len() >= 3 && numbers.windows(2).all(|w| w[0] < w[1]),
        "{blocks:?}"
    );
    let active = executions.iter().position(|e| e == "ACTIVE");
    let done = executions.iter().rposition(|e| e == "PROGRAM_COMPLETED");
    assert!(
        active.is_some() && done > active,
        "{} → {executions:?}",
        accepted.job_id
    );
    client.close().await;
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_alarm_is_a_fault_with_its_native_code_and_a_reset_clears_it() {
    let gw = start(|_| {}).await;
    let url = gw.url.clone();
    wait_for(&url, "/current", |d| {
        value_of(d, "mill-1_system").is_some_and(|v| v.0 == "Normal")
            && value_of(d, "lathe-1_system").is_some_and(|v| v.0 == "Normal")
    })
    .await;
    let client = gw.client().await;
    let off = pb::SimAutostart { on: false };
    for m in ["mill-1", "lathe-1"] {
        // The operator resets the alarm, not the simulated CNC by itself.
        client
            .sim_control(m, SimLeaf::Autostart, Some(&off))
            .await
            .unwrap();
        client
            .sim_control::<pb::SimDi>(m, SimLeaf::Alarm, None)
            .await
            .unwrap();
    }
    // Protocol A's ALM and Protocol B's NAK carry no alarm number: cellgate's own codes.
    let current = wait_for(&url, "/current", |d| {
        value_of(d, "mill-1_system").is_some_and(|v| v.0 == "Fault")
            && value_of(d, "lathe-1_system").is_some_and(|v| v.0 == "Fault")
    })
    .await;
    let (_, attrs, _) = value_of(&current, "mill-1_system").unwrap();
    assert_eq!(
        attr(&attrs, "nativeCode").as_deref(),
        Some("CG-ALM"),
        "{attrs}"
    );
    let (_, attrs, _) = value_of(&current, "lathe-1_system").unwrap();
    assert_eq!(
        attr(&attrs, "nativeCode").as_deref(),
        Some("CG-NAK"),
        "{attrs}"
    );
    assert_eq!(
        value_of(&current, "mill-1_execution").unwrap().2,
        "INTERRUPTED"
    );
    for m in ["mill-1", "lathe-1"] {
        client
            .sim_control::<pb::SimDi>(m, SimLeaf::Reset, None)
            .await
            .unwrap();
    }
    let current = wait_for(&url, "/current", |d| {
        value_of(d, "mill-1_system").is_some_and(|v| v.0 == "Normal")
            && value_of(d, "lathe-1_system").is_some_and(|v| v.0 == "Normal")
    })
    .await;
    assert!(!current.contains("<Fault"), "{current}");
    client.close().await;
    gw.stop().await;
}

/// The parts of a multipart stream read so far, and the boundary.
fn parts(body: &str, boundary: &str) -> Vec<String> {
    body.split(&format!("--{boundary}\r\n"))
        .filter_map(|p| {
            let (head, rest) = p.split_once("\r\n\r\n")?;
            let len: usize = head
                .lines()
                .find_map(|l| l.strip_prefix("Content-length: "))?
                .trim()
                .parse()
                .ok()?;
            (rest.len() >= len).then(|| rest[..len].to_string())
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sample_streams_parts_and_heartbeats() {
    let gw = start(|_| {}).await;
    // PROGRAM does not change on an idle cell: after the first part, only heartbeats.
    let path = "//DataItem[@type=\"PROGRAM\"]";
    let url = format!(
        "{}/sample?interval=50&heartbeat=200&path={}",
        gw.url,
        form_urlencoded::byte_serialize(path.as_bytes()).collect::<String>()
    );
    let mut r = reqwest::get(&url).await.unwrap();
    assert_eq!(r.status(), 200);
    let ct = r.headers()["content-type"].to_str().unwrap().to_string();
    let boundary = ct
        .strip_prefix("multipart/x-mixed-replace;boundary=")
        .unwrap_or_else(|| panic!("{ct}"))
        .to_string();
    let mut body = String::new();
    let got = tokio::time::timeout(Duration::from_secs(60), async {
        loop {
            let chunk = r.chunk().await.unwrap().expect("the stream goes on");
            body.push_str(std::str::from_utf8(&chunk).unwrap());
            if parts(&body, &boundary).len() >= 4 {
                return parts(&body, &boundary);
            }
        }
    })
    .await
    .expect("parts keep coming");
    // The first part holds every PROGRAM's state; the heartbeats none, and each tells where
    // the next starts.
    assert_eq!(observations(&got[0]).len(), 3, "{}", got[0]);
    for p in &got[1..] {
        assert!(p.contains("<MTConnectStreams"), "{p}");
        assert!(observations(p).is_empty(), "a heartbeat holds nothing: {p}");
        assert!(header(p, "nextSequence") >= header(&got[0], "nextSequence"));
    }
    drop(r);
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn errors_are_mtconnect_error_documents_with_the_standard_codes() {
    let gw = start(|_| {}).await;
    let u = &gw.url;
    let cases = [
        ("/nosuch/probe", 404, "NO_DEVICE"),
        ("/sample?from=999999999", 400, "OUT_OF_RANGE"),
        ("/sample?count=0", 400, "OUT_OF_RANGE"),
        ("/current?at=999999999", 400, "OUT_OF_RANGE"),
        ("/sample?from=abc", 400, "INVALID_REQUEST"),
        ("/probe?from=1", 400, "INVALID_REQUEST"),
        (
            "/current?path=//DataItem[@type=%22NOPE%22]",
            400,
            "INVALID_PATH",
        ),
        ("/current?path=//DataItem[type", 400, "INVALID_PATH"),
        ("/a/b/c/d", 404, "INVALID_URI"),
        ("/asset/x1", 404, "ASSET_NOT_FOUND"),
        // What a hostile or broken client sends is answered, never a panic.
        ("/%FF/probe", 404, "INVALID_URI"),
        ("/sample?count=-9223372036854775808", 400, "OUT_OF_RANGE"),
        ("/sample?interval=99999999999", 400, "OUT_OF_RANGE"),
        ("/current?at=1&interval=10", 400, "INVALID_REQUEST"),
        ("/current?path=%2F%2F%5B%5B%5B", 400, "INVALID_PATH"),
    ];
    for (path, status, code) in cases {
        let (s, body) = get(&format!("{u}{path}")).await;
        assert_eq!(s, status, "{path}: {body}");
        assert!(body.contains("<MTConnectError"), "{path}: {body}");
        assert!(
            body.contains(&format!("errorCode=\"{code}\"")),
            "{path}: {body}"
        );
    }
    let r = reqwest::Client::new()
        .post(format!("{u}/probe"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 405);
    assert!(
        r.text()
            .await
            .unwrap()
            .contains("errorCode=\"UNSUPPORTED\"")
    );
    // In JSON when asked so.
    let (s, body) = get(&format!("{u}/nosuch/current?format=json")).await;
    assert_eq!(s, 404);
    let v: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(
        v["MTConnectError"]["Errors"]["Error"][0]["errorCode"],
        "NO_DEVICE"
    );
    // Laid out for reading when asked: the same document, a line an element.
    let (s, compact) = get(&format!("{u}/probe")).await;
    assert_eq!(s, 200);
    let (s, laid) = get(&format!("{u}/probe?pretty=true")).await;
    assert_eq!(s, 200);
    assert_eq!(compact.lines().count(), 1, "compact by default");
    assert!(laid.contains("\n  <Header "), "{laid}");
    let squeeze = |d: &str| d.lines().map(str::trim).collect::<String>();
    assert_eq!(
        squeeze(&laid).replace(|c: char| c.is_ascii_digit(), ""),
        squeeze(&compact).replace(|c: char| c.is_ascii_digit(), "")
    );
    let (s, laid) = get(&format!("{u}/current?format=json&pretty=true")).await;
    assert_eq!(s, 200);
    assert!(
        laid.contains("\n  \"MTConnectStreams\": {") || laid.starts_with("{\n"),
        "{laid}"
    );
    serde_json::from_str::<serde_json::Value>(&laid).unwrap();
    let (s, body) = get(&format!("{u}/probe?pretty=yes")).await;
    assert_eq!(s, 400);
    assert!(
        body.contains("INVALID_REQUEST") && body.contains("pretty"),
        "{body}"
    );
    gw.stop().await;
}

/// Where the schemas are, as shipped beside the repository.
fn schemas() -> Option<std::path::PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/mtconnect");
    dir.join("MTConnectStreams_2.5.xsd").exists().then_some(dir)
}

/// Validates `doc` against `kind`'s schema with xmllint; `Err` with its output.
fn validate(work: &Path, schemas: &Path, kind: &str, name: &str, doc: &str) -> Result<(), String> {
    let xsd = work.join(format!("MTConnect{kind}_2.5.xsd"));
    if !xsd.exists() {
        let text =
            std::fs::read_to_string(schemas.join(format!("MTConnect{kind}_2.5.xsd"))).unwrap();
        // XSD 1.1's notNamespace, which libxml2 cannot load, as XSD 1.0's ##other.
        let text = text.replace("notNamespace='##targetNamespace'", "namespace='##other'");
        std::fs::write(&xsd, text).unwrap();
        std::fs::copy(schemas.join("xlink.xsd"), work.join("xlink.xsd")).unwrap();
    }
    let file = work.join(format!("{name}.xml"));
    std::fs::write(&file, doc).unwrap();
    let out = Command::new("xmllint")
        .args(["--noout", "--schema"])
        .arg(&xsd)
        .arg(&file)
        .output()
        .unwrap();
    if out.status.success() {
        Ok(())
    } else {
        Err(String::from_utf8_lossy(&out.stderr).into_owned())
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_kind_of_document_is_valid_against_the_2_5_schemas() {
    let found = Command::new("sh")
        .args(["-c", "command -v xmllint"])
        .output()
        .is_ok_and(|o| o.status.success());
    let Some(schemas) = schemas().filter(|_| found) else {
        eprintln!(
            "SKIPPED: no xmllint or no schemas here (apt-get install libxml2-utils; .ci/run \
             does): the documents were not validated"
        );
        return;
    };
    let gw = start(|_| {}).await;
    let u = gw.url.clone();
    // A fault in the documents too.
    let client = gw.client().await;
    client
        .sim_control(
            "mill-1",
            SimLeaf::Autostart,
            Some(&pb::SimAutostart { on: false }),
        )
        .await
        .unwrap();
    client
        .sim_control::<pb::SimDi>("mill-1", SimLeaf::Alarm, None)
        .await
        .unwrap();
    // The default cell's spindle-temp is a TEMPERATURE sample in CELSIUS: in the documents
    // validated, with its value.
    let current = wait_for(&u, "/current", |d| {
        d.contains("<Fault") && d.contains("<Temperature") && d.contains("<Samples>")
    })
    .await;
    // A File asset too: a program the Protocol B lathe punches out.
    let punch = pb::SimPunch {
        program: b"%\nO5555(BRACKET)\nG00X0Y0\nM30\n%\n".to_vec(),
    };
    client
        .sim_control("lathe-1", SimLeaf::Punch, Some(&punch))
        .await
        .unwrap();
    let assets = wait_for(&u, "/assets", |d| d.contains("<File ")).await;
    let work = tempfile::tempdir().unwrap();
    let mut docs = vec![
        ("Devices", "probe", get(&format!("{u}/probe")).await.1),
        (
            "Devices",
            "device-probe",
            get(&format!("{u}/plc-1/probe")).await.1,
        ),
        ("Streams", "current", current),
        (
            "Streams",
            "sample",
            get(&format!("{u}/sample?count=1000")).await.1,
        ),
        (
            "Streams",
            "current-at",
            get(&format!("{u}/current?at=5")).await.1,
        ),
        ("Assets", "assets", assets),
        (
            "Assets",
            "no-assets",
            get(&format!("{u}/mill-1/assets")).await.1,
        ),
        ("Error", "error", get(&format!("{u}/nosuch/probe")).await.1),
        (
            "Error",
            "out-of-range",
            get(&format!("{u}/sample?from=0")).await.1,
        ),
    ];
    // A part of a stream, too.
    let mut r = reqwest::get(format!("{u}/sample?interval=10&count=5"))
        .await
        .unwrap();
    let ct = r.headers()["content-type"].to_str().unwrap().to_string();
    let boundary = ct.split("boundary=").nth(1).unwrap().to_string();
    let mut body = String::new();
    while parts(&body, &boundary).is_empty() {
        body.push_str(std::str::from_utf8(&r.chunk().await.unwrap().unwrap()).unwrap());
    }
    docs.push(("Streams", "stream-part", parts(&body, &boundary).remove(0)));
    drop(r);
    let mut failed = Vec::new();
    for (kind, name, doc) in &docs {
        if let Err(e) = validate(work.path(), &schemas, kind, name, doc) {
            failed.push(format!("{name}: {e}"));
        }
    }
    assert!(failed.is_empty(), "{failed:#?}");
    client.close().await;
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_shdr_adapter_sends_the_state_and_answers_ping() {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let port = free_port();
    let gw = start(|c| {
        c.mtconnect.as_mut().unwrap().shdr_listen = Some(format!("127.0.0.1:{port}"));
    })
    .await;
    wait_for(&gw.url, "/current", |d| {
        value_of(d, "mill-1_execution").is_some_and(|v| v.2 == "READY")
    })
    .await;
    let stream = tokio::net::TcpStream::connect(gw.shdr.as_deref().unwrap())
        .await
        .unwrap();
    let (read, mut write) = stream.into_split();
    let mut lines = BufReader::new(read).lines();
    write.write_all(b"* PING\n").await.unwrap();
    let mut seen = Vec::new();
    let pong = tokio::time::timeout(Duration::from_secs(30), async {
        while let Some(l) = lines.next_line().await.unwrap() {
            if l.starts_with("* PONG") {
                return l;
            }
            seen.push(l);
        }
        panic!("the adapter hung up");
    })
    .await
    .expect("an answer to * PING");
    assert_eq!(pong, "* PONG 10000");
    // The state first: `TIMESTAMP|DEVICE:ID|VALUE`, conditions with their level.
    assert!(
        seen.iter()
            .any(|l| l.ends_with("|mill-1:mill-1_execution|READY")),
        "{seen:#?}"
    );
    assert!(
        seen.iter()
            .any(|l| l.contains("|mill-1:mill-1_system|NORMAL|")),
        "{seen:#?}"
    );
    // Then each observation as it is made: an alarm at the simulated CNC.
    let client = gw.client().await;
    client
        .sim_control::<pb::SimDi>("mill-1", SimLeaf::Alarm, None)
        .await
        .unwrap();
    let fault = tokio::time::timeout(Duration::from_secs(30), async {
        while let Some(l) = lines.next_line().await.unwrap() {
            if l.contains("|mill-1:mill-1_system|FAULT|") {
                return l;
            }
        }
        panic!("the adapter hung up");
    })
    .await
    .expect("the fault comes as a line");
    assert!(fault.contains("|FAULT|CG-ALM|||"), "{fault}");
    client.close().await;
    drop(write);
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_site_agent_serves_the_cells_of_two_gateways() {
    let router_port = free_port();
    let router = bus::open(&bus::BusConfig {
        mode: bus::BusMode::Router,
        listen: vec![format!("tcp/127.0.0.1:{router_port}")],
        ..bus::BusConfig::default()
    })
    .await
    .unwrap();
    let mut gateways = Vec::new();
    for cell in ["north", "south"] {
        let gw = start(|c| {
            c.cell = cell.to_string();
            c.bus.connect = vec![format!("tcp/127.0.0.1:{router_port}")];
        })
        .await;
        gateways.push(gw);
    }
    let port = free_port();
    let args = cellgate::mtconnect::SiteArgs {
        connect: common::bus::connect_args(format!("tcp/127.0.0.1:{router_port}"), None),
        listen: format!("127.0.0.1:{port}"),
        shdr: None,
        buffer_size: 4096,
    };
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let site = tokio::spawn(async move {
        cellgate::mtconnect::site(&args, async {
            let _ = stopped.await;
        })
        .await
    });
    let url = format!("http://127.0.0.1:{port}");
    // The first cell's machines by their names, the second's qualified by their cell; both
    // cells' adapters established.
    let current = wait_for(&url, "/current", |d| {
        d.matches(">ESTABLISHED<").count() == 2 && d.matches(">READY<").count() == 6
    })
    .await;
    let probe = get(&format!("{url}/probe")).await.1;
    for name in ["mill-1", "lathe-1", "plc-1"] {
        let qualified = [format!("north.{name}"), format!("south.{name}")];
        let plain = probe.contains(&format!(" name=\"{name}\" uuid="));
        let one_qualified = qualified
            .iter()
            .filter(|q| probe.contains(&format!(" name=\"{q}\" uuid=")))
            .count();
        assert!(plain && one_qualified == 1, "{name}: {probe}");
    }
    assert!(current.contains("componentId=\"cell_north\""), "{current}");
    assert!(current.contains("componentId=\"cell_south\""), "{current}");
    // A gateway gone: its devices UNAVAILABLE, its adapter closed.
    let south = gateways.pop().unwrap();
    south.stop().await;
    wait_for(&url, "/current", |d| {
        d.matches(">ESTABLISHED<").count() == 1
    })
    .await;
    let _ = stop.send(());
    site.await.unwrap().unwrap();
    for gw in gateways {
        gw.stop().await;
    }
    router.close().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_python_follower_and_json_read_the_agent() {
    let gw = start(|_| {}).await;
    wait_for(&gw.url, "/current", |d| {
        value_of(d, "mill-1_execution").is_some_and(|v| v.2 == "READY")
    })
    .await;
    // The example of docs/mtconnect.md, with python3 alone.
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/python/mtconnect_follow.py");
    let url = gw.url.clone();
    let out = tokio::task::spawn_blocking(move || {
        Command::new("python3")
            .arg(script)
            .args([url.as_str(), "--once"])
            .output()
            .expect("python3 runs (.ci/run needs it)")
    })
    .await
    .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.lines()
            .any(|l| l.contains("mill-1_execution") && l.ends_with("READY")),
        "{text}"
    );
    // JSON: the same document's structure.
    let (s, body) = get(&format!("{}/mill-1/current?format=json", gw.url)).await;
    assert_eq!(s, 200, "{body}");
    let v: serde_json::Value = serde_json::from_str(&body).unwrap();
    let streams = &v["MTConnectStreams"]["Streams"]["DeviceStream"];
    assert_eq!(streams.as_array().unwrap().len(), 1, "{v}");
    assert_eq!(streams[0]["name"], "mill-1");
    let path = streams[0]["ComponentStream"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["component"] == "Path")
        .unwrap();
    assert_eq!(path["Events"]["Execution"][0]["value"], "READY", "{path}");
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_punched_program_is_a_file_asset_of_its_machine() {
    let gw = start(|_| {}).await;
    let u = gw.url.clone();
    wait_for(&u, "/current", |d| {
        value_of(d, "lathe-1_execution").is_some_and(|v| v.2 == "READY")
    })
    .await;
    let (s, none) = get(&format!("{u}/assets")).await;
    assert_eq!(s, 200, "{none}");
    assert!(none.contains("assetCount=\"0\""), "{none}");
    let client = gw.client().await;
    let program = b"%\nO5556\nG00X0Y0\nG01X10.F100\nM30\n%\n".to_vec();
    client
        .sim_control(
            "lathe-1",
            SimLeaf::Punch,
            Some(&pb::SimPunch {
                program: program.clone(),
            }),
        )
        .await
        .unwrap();
    let assets = wait_for(&u, "/lathe-1/assets", |d| d.contains("<File ")).await;
    let file = &assets[assets.find("<File ").unwrap()..];
    let file = &file[..file.find('>').unwrap()];
    let id = attr(file, "assetId").unwrap();
    assert!(id.starts_with("demo.lathe-1."), "{file}");
    assert_eq!(
        attr(file, "applicationType").as_deref(),
        Some("PRODUCTION_PROGRAM")
    );
    assert!(
        attr(file, "size").unwrap().parse::<u64>().unwrap() > 0,
        "{file}"
    );
    assert!(
        assets.contains("<FileLocation href=\"cellgate/demo/program/"),
        "{assets}"
    );
    // The machine's ASSET_CHANGED names it; /asset/ID answers it; another is not found.
    let current = get(&format!("{u}/lathe-1/current")).await.1;
    let (element, attrs, value) = value_of(&current, "lathe-1_asset_chg").unwrap();
    assert_eq!(
        (element.as_str(), value.as_str()),
        ("AssetChanged", id.as_str())
    );
    assert_eq!(attr(&attrs, "assetType").as_deref(), Some("File"));
    let (s, one) = get(&format!("{u}/asset/{id}")).await;
    assert_eq!(s, 200, "{one}");
    assert!(one.contains(&format!("assetId=\"{id}\"")), "{one}");
    let (s, _) = get(&format!("{u}/asset/demo.lathe-1.nope")).await;
    assert_eq!(s, 404);
    // Not another machine's.
    let mill = get(&format!("{u}/mill-1/assets")).await.1;
    assert!(!mill.contains("<File "), "{mill}");
    client.close().await;
    gw.stop().await;
}

/// A gateway stopped while a job is taken fails it when it starts again ("gateway
/// restarted"): its agent, new with it, shows the machine INTERRUPTED, not READY, until a
/// newer job starts.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_failed_by_a_restart_shows_interrupted_after_it() {
    let dir = tempfile::tempdir().unwrap();
    let programs = dir.path().join("programs");
    let p = programs.clone();
    let gw = start(move |c| c.programs.dir = p).await;
    let client = gw.client().await;
    // A program that takes seconds at 19200 baud: the gateway stops while it is sent.
    let mut text = b"%\nO1\n".to_vec();
    for n in 0..1500 {
        text.extend_from_slice(format!("N{n} G01 X{n} Y1\n").as_bytes());
    }
    text.extend_from_slice(b"M30\n%\n");
    let job = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(text)),
        ..Default::default()
    };
    let (accepted, mut follower) = client.submit("mill-1", &job).await.unwrap();
    loop {
        match tokio::time::timeout(Duration::from_secs(30), follower.next()).await {
            Ok(Ok(Some(e))) => {
                if matches!(&e.kind, Some(pb::job_event::Kind::Progress(p)) if p.bytes_sent > 0) {
                    break;
                }
            }
            other => panic!("the job never progressed: {other:?}"),
        }
    }
    follower.close().await;
    client.close().await;
    gw.stop().await;
    let p = programs.clone();
    let gw = start(move |c| c.programs.dir = p).await;
    let current = wait_for(&gw.url, "/current", |d| {
        value_of(d, "mill-1_execution").is_some_and(|v| v.2 != "UNAVAILABLE")
    })
    .await;
    assert_eq!(
        value_of(&current, "mill-1_execution").unwrap().2,
        "INTERRUPTED",
        "{current}"
    );
    let client = gw.client().await;
    let latest = client.job_latest("mill-1", &accepted.job_id).await.unwrap();
    assert!(
        matches!(latest.kind, Some(pb::job_event::Kind::Failed(_))),
        "{latest:?}"
    );
    client.close().await;
    gw.stop().await;
}
