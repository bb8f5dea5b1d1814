//! The console's API as the pages (and any other client) use it, against a running gateway:
//! sessions and CSRF, roles that bound what a browser user may do (a forged request is refused
//! and audited), the pages' live events, and the site view of several cells behind a router.

use crate::common;

use std::time::Duration;

use cellgate::bus;
use cellgate_core::config::CellConfig;
use common::bus::free_port;
use serde_json::{Value, json};

pub(crate) use super::gateway::Gateway;

/// The ring provider for rustls, as the gateway uses it (reqwest is built without one).
fn provider() {
    let _ = tokio_rustls::rustls::crypto::ring::default_provider().install_default();
}

/// Waits until `url` answers 200.
async fn wait_http(url: &str) {
    provider();
    let http = reqwest::Client::new();
    for _ in 0..300 {
        if let Ok(r) = http.get(url).send().await
            && r.status() == 200
        {
            return;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("{url} never answered 200");
}

/// A browser: a cookie jar and the CSRF token of its session.
struct Browser {
    http: reqwest::Client,
    jar: std::sync::Arc<reqwest::cookie::Jar>,
    base: String,
    csrf: String,
}

impl Browser {
    fn new(base: &str) -> Browser {
        provider();
        let jar = std::sync::Arc::new(reqwest::cookie::Jar::default());
        Browser {
            http: reqwest::Client::builder()
                .cookie_provider(jar.clone())
                .build()
                .unwrap(),
            jar,
            base: base.to_string(),
            csrf: String::new(),
        }
    }

    async fn me(&mut self) -> (u16, Value) {
        let r = self
            .http
            .get(format!("{}/api/v1/me", self.base))
            .send()
            .await
            .unwrap();
        let status = r.status().as_u16();
        let v: Value = r.json().await.unwrap();
        if let Some(c) = v["csrf"].as_str() {
            self.csrf = c.to_string();
        }
        (status, v)
    }

    async fn login(&mut self, user: &str, password: &str) -> (u16, Value) {
        let r = self
            .http
            .post(format!("{}/api/v1/login", self.base))
            .json(&json!({"user": user, "password": password}))
            .send()
            .await
            .unwrap();
        let status = r.status().as_u16();
        let v: Value = r.json().await.unwrap();
        if let Some(c) = v["csrf"].as_str() {
            self.csrf = c.to_string();
        }
        (status, v)
    }

    async fn get(&self, path: &str) -> (u16, Value) {
        let r = self
            .http
            .get(format!("{}{path}", self.base))
            .send()
            .await
            .unwrap();
        let status = r.status().as_u16();
        let text = r.text().await.unwrap();
        (
            status,
            serde_json::from_str(&text).unwrap_or(Value::String(text)),
        )
    }

    async fn send(
        &self,
        method: reqwest::Method,
        path: &str,
        body: Option<Value>,
        raw: Option<Vec<u8>>,
        csrf: bool,
    ) -> (u16, Value) {
        let mut req = self.http.request(method, format!("{}{path}", self.base));
        if csrf {
            req = req.header("X-CSRF-Token", &self.csrf);
        }
        if let Some(b) = body {
            req = req.json(&b);
        }
        if let Some(b) = raw {
            req = req.body(b);
        }
        let r = req.send().await.unwrap();
        let status = r.status().as_u16();
        let text = r.text().await.unwrap();
        (
            status,
            serde_json::from_str(&text).unwrap_or(Value::String(text)),
        )
    }

    async fn post(&self, path: &str, body: Value) -> (u16, Value) {
        self.send(reqwest::Method::POST, path, Some(body), None, true)
            .await
    }
}

const PROGRAM: &[u8] = b"%\nO5001\nG00X0Y0\nG01X10F100\nM30\n%\n";

/// Waits for the audit trail to hold a record `check` takes.
async fn audited(b: &Browser, check: impl Fn(&Value) -> bool) -> Value {
    for _ in 0..100 {
        let (status, page) = b.get("/api/v1/cells/demo/audit?_time=[now(-10m)..]").await;
        assert_eq!(status, 200, "{page}");
        if let Some(r) = page["records"]
            .as_array()
            .and_then(|rs| rs.iter().find(|r| check(&r["audit"])))
        {
            return r.clone();
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("never audited");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_open_console_serves_anyone_but_every_write_needs_the_session_token() {
    let gw = Gateway::start(|_, _| {}).await;
    let mut b = Browser::new(&gw.url);
    let (status, me) = b.me().await;
    assert_eq!(status, 200, "{me}");
    assert_eq!(me["secured"], false);
    assert!(
        me["permissions"]
            .as_array()
            .unwrap()
            .iter()
            .any(|p| p == "job.submit")
    );
    // The pages themselves, all from this origin.
    let (status, index) = b.get("/").await;
    assert_eq!(status, 200);
    assert!(index.as_str().unwrap().contains("<html"), "{index}");
    let (_, cells) = b.get("/api/v1/cells").await;
    assert_eq!(cells[0]["cell"], "demo");
    assert_eq!(cells[0]["machines"], json!(["mill-1", "mill-2", "lathe-1"]));
    let (status, overview) = b.get("/api/v1/cells/demo/overview").await;
    assert_eq!(status, 200, "{overview}");
    assert_eq!(overview["machines"].as_array().unwrap().len(), 3);
    assert_eq!(overview["plcs"][0]["plc"], "plc-1");

    // No token, no write: a page of another site cannot make this browser act.
    let (status, e) = b
        .send(
            reqwest::Method::PUT,
            "/api/v1/cells/demo/programs/O5001",
            None,
            Some(PROGRAM.to_vec()),
            false,
        )
        .await;
    assert_eq!(status, 403, "{e}");
    assert_eq!(e["code"], "ERROR_CODE_NOT_PERMITTED");
    // With it, the store goes through and says its revision.
    let (status, info) = b
        .send(
            reqwest::Method::PUT,
            "/api/v1/cells/demo/programs/O5001?comment=first%20cut",
            None,
            Some(PROGRAM.to_vec()),
            true,
        )
        .await;
    assert_eq!(status, 200, "{info}");
    assert_eq!(info["latest"]["number"], 1);
    assert_eq!(info["latest"]["comment"], "first cut");
    assert_eq!(info["latest"]["by"]["via"], "console");

    // Live events: a job submitted through the console shows on the page's stream.
    let mut events = b
        .http
        .get(format!(
            "{}/api/v1/cells/demo/events?machine=mill-1",
            gw.url
        ))
        .send()
        .await
        .unwrap();
    let (status, accepted) = b
        .post(
            "/api/v1/cells/demo/machines/mill-1/submit",
            json!({"library": "O5001"}),
        )
        .await;
    assert_eq!(status, 200, "{accepted}");
    let job = accepted["job_id"].as_str().unwrap().to_string();
    assert_eq!(accepted["program"]["revision"], 1);
    let mut seen = String::new();
    let done = tokio::time::timeout(Duration::from_secs(60), async {
        while let Some(chunk) = events.chunk().await.unwrap() {
            seen.push_str(&String::from_utf8_lossy(&chunk));
            if seen.contains("\"completed\"") && seen.contains(&job) {
                return;
            }
        }
    })
    .await;
    assert!(done.is_ok(), "no completed event for {job}: {seen}");
    assert!(seen.contains("event: job"), "{seen}");
    assert!(
        !seen.contains("\"machine\":\"mill-2\""),
        "only mill-1's events: {seen}"
    );

    // The machine page: its job among the recent ones, with the revision it sent.
    let (_, m) = b.get("/api/v1/cells/demo/machines/mill-1").await;
    assert!(
        m["jobs"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e["job_id"] == job.as_str()),
        "{m}"
    );
    // The history as CSV for a spreadsheet: one column per field, by its path; the record
    // in words; no column holds JSON.
    let r = b
        .http
        .get(format!(
            "{}/api/v1/cells/demo/audit?_time=[now(-10m)..]&format=csv",
            gw.url
        ))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let csv = r.text().await.unwrap();
    let mut lines = csv.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(
        head[..6],
        ["unix_ms", "utc", "seq", "machine", "kind", "text"]
    );
    for column in ["audit.action", "audit.target", "audit.origin.via"] {
        assert!(head.contains(&column), "{column} missing: {head:?}");
    }
    let store = lines
        .find(|l| l.split(',').any(|f| f == "program.store"))
        .unwrap_or_else(|| panic!("no store in:\n{csv}"));
    let fields: Vec<&str> = store.split(',').collect();
    assert!(
        fields.contains(&"O5001") && fields.contains(&"console"),
        "{store}"
    );
    assert!(
        !csv.lines().any(|l| l.contains("{\"") || l.contains("\"{")),
        "JSON in a column:\n{csv}"
    );

    // Bad input gets a clear refusal, in the API's shape.
    let (status, e) = b.get("/api/v1/cells/demo/machines/mill-9").await;
    assert_eq!(status, 404, "{e}");
    let (status, e) = b.get("/api/v1/cells/nosuch/overview").await;
    assert_eq!(status, 404, "{e}");
    let (status, e) = b
        .post(
            "/api/v1/cells/demo/programs/O5001/release",
            json!({"state": "bogus"}),
        )
        .await;
    assert_eq!(status, 400, "{e}");
    gw.stop().await;
}

/// A cell whose console takes logins from a users file: an operator who may output DO and
/// read, an engineer who keeps and releases programs and submits jobs.
fn secured(config: &mut CellConfig, dir: &std::path::Path) {
    let users = dir.join("users");
    std::fs::write(&users, "olga:tulips\nerik:hammer\n").unwrap();
    let text = format!(
        r#"
cell = "demo"
[security]
users_file = {users:?}
[[security.roles]]
name = "operator"
usernames = ["olga"]
permissions = ["status.read", "io.do"]
[[security.roles]]
name = "engineer"
usernames = ["erik"]
permissions = ["status.read", "program.write", "program.release", "job.submit", "audit.read"]
"#
    );
    let security = CellConfig::from_toml_str(&text, "security")
        .unwrap()
        .security;
    config.security = security;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_user_may_do_what_their_roles_allow_and_a_forged_request_is_refused_and_audited() {
    let gw = Gateway::start(secured).await;
    let mut olga = Browser::new(&gw.url);
    let (status, _) = olga.me().await;
    assert_eq!(status, 401, "a login is needed");
    let (status, e) = olga.get("/api/v1/cells/demo/overview").await;
    assert_eq!(status, 401, "{e}");
    let (status, e) = olga.login("olga", "wrong").await;
    assert_eq!(status, 401, "{e}");
    let (status, me) = olga.login("olga", "tulips").await;
    assert_eq!(status, 200, "{me}");
    assert_eq!(me["permissions"], json!(["status.read", "io.do"]));
    let (status, _) = olga.get("/api/v1/cells/demo/overview").await;
    assert_eq!(status, 200);

    let mut erik = Browser::new(&gw.url);
    erik.login("erik", "hammer").await;
    let (status, info) = erik
        .send(
            reqwest::Method::PUT,
            "/api/v1/cells/demo/programs/O5001",
            None,
            Some(PROGRAM.to_vec()),
            true,
        )
        .await;
    assert_eq!(status, 200, "{info}");

    // Olga's page shows no submit control; she forges the request with her own valid token.
    let (status, e) = olga
        .post(
            "/api/v1/cells/demo/machines/mill-1/submit",
            json!({"library": "O5001"}),
        )
        .await;
    assert_eq!(status, 403, "{e}");
    assert!(e["message"].as_str().unwrap().contains("job.submit"), "{e}");
    // The gateway never saw it; the console noted it in the cell's audit trail, with her name.
    let note = audited(&erik, |a| {
        a["action"] == "audit.note"
            && a["origin"]["user"] == "olga"
            && a["detail"]
                .as_str()
                .is_some_and(|d| d.contains("job.submit"))
    })
    .await;
    assert!(
        note["audit"]["detail"]
            .as_str()
            .unwrap()
            .contains("job.submit"),
        "{note}"
    );
    assert_eq!(note["audit"]["ok"], false);
    // Nothing was queued.
    let (_, m) = olga.get("/api/v1/cells/demo/machines/mill-1").await;
    assert!(
        m["queue"]["waiting"]
            .as_array()
            .is_none_or(|w| w.is_empty()),
        "{m}"
    );

    // What her role allows goes through, and the audit names her, through the console (once
    // mill-1's link is up: DO needs it).
    for _ in 0..100 {
        let (_, o) = olga.get("/api/v1/cells/demo/overview").await;
        if o["machines"]
            .as_array()
            .unwrap()
            .iter()
            .any(|m| m["machine"] == "mill-1" && m["link_state"] == "LINK_STATE_IDLE")
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let (status, s) = olga
        .post("/api/v1/cells/demo/machines/mill-1/do", json!({"value": 6}))
        .await;
    assert_eq!(status, 200, "{s}");
    audited(&erik, |a| {
        a["action"] == "io.do" && a["origin"]["user"] == "olga" && a["origin"]["via"] == "console"
    })
    .await;
    // Erik's release, and his submit.
    let (status, r) = erik
        .post(
            "/api/v1/cells/demo/programs/O5001/release",
            json!({"state": "REVISION_STATE_RELEASED", "comment": "proven"}),
        )
        .await;
    assert_eq!(status, 200, "{r}");
    assert_eq!(r["state"], "REVISION_STATE_RELEASED");
    assert_eq!(r["state_by"]["user"], "erik");
    let (status, a) = erik
        .post(
            "/api/v1/cells/demo/machines/mill-1/submit",
            json!({"library": "O5001"}),
        )
        .await;
    assert_eq!(status, 200, "{a}");
    // Olga may not read the audit trail.
    let (status, _) = olga.get("/api/v1/cells/demo/audit").await;
    assert_eq!(status, 403);
    // Logged out, the session is gone.
    olga.send(reqwest::Method::POST, "/api/v1/logout", None, None, true)
        .await;
    let (status, _) = olga.get("/api/v1/cells/demo/overview").await;
    assert_eq!(status, 401);
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_site_console_shows_every_cell_behind_a_router() {
    // A router, and two gateways of cells "north" and "south" connected to it.
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
        let gw = Gateway::start(|c, _| {
            c.cell = cell.to_string();
            c.bus.connect = vec![format!("tcp/127.0.0.1:{router_port}")];
        })
        .await;
        gateways.push(gw);
    }
    let site = common::bus::SiteConsole::start(router_port);
    let url = site.url.clone();
    wait_http(&format!("{url}/health")).await;
    let mut b = Browser::new(&url);
    b.me().await;
    let mut names = Vec::new();
    for _ in 0..100 {
        let (_, cells) = b.get("/api/v1/cells").await;
        names = cells
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["cell"].as_str().unwrap().to_string())
            .collect();
        if names.len() == 2 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert_eq!(names, ["north", "south"]);
    for cell in ["north", "south"] {
        let (status, o) = b.get(&format!("/api/v1/cells/{cell}/overview")).await;
        assert_eq!(status, 200, "{o}");
        assert_eq!(o["machines"].as_array().unwrap().len(), 3, "{o}");
    }
    site.stop().await;
    for gw in gateways {
        let _ = &gw.endpoint;
        gw.stop().await;
    }
    router.close().await.unwrap();
}

#[test]
fn a_console_beyond_loopback_needs_security_or_a_word_of_consent() {
    let text = r#"
cell = "c"
[console]
listen = "0.0.0.0:7480"
"#;
    let e = CellConfig::from_toml_str(text, "cell.toml").unwrap_err();
    assert!(e.to_string().contains("console.listen"), "{e}");
    let ok =
        CellConfig::from_toml_str(&format!("{text}allow_remote = true\n"), "cell.toml").unwrap();
    assert!(
        ok.warnings().iter().any(|w| w.contains("console.listen")),
        "{:?}",
        ok.warnings()
    );
}

/// The overview of a cell of more machines than one get's default FIFO holds (256): the
/// console, in the gateway's own session, takes every machine's status. (It once hung the
/// status route for good: the route blocked its thread on the full FIFO while the task that
/// would drain it waited on the same thread.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_overview_of_a_cell_of_300_machines_answers_and_the_status_route_lives_on() {
    const MACHINES: usize = 300;
    let gw = Gateway::start(|config, _| {
        let mill = config.machines[0].clone();
        config.machines = (0..MACHINES)
            .map(|i| {
                let mut m = mill.clone();
                m.name = format!("m{i:03}");
                m
            })
            .collect();
    })
    .await;
    let mut b = Browser::new(&gw.url);
    b.me().await;
    for _ in 0..3 {
        let (status, o) = b.get("/api/v1/cells/demo/overview").await;
        assert_eq!(status, 200, "{o}");
        assert_eq!(o["machines"].as_array().unwrap().len(), MACHINES);
    }
    gw.stop().await;
}

/// What the pages need to show each machine as it is: the machines that take G05 streams
/// (the others show no G05 at all), and the icon a browser asks for, served from the binary
/// rather than answered 404.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_cells_say_which_machines_take_g05_and_the_favicon_is_served() {
    let gw = Gateway::start(|_, _| {}).await;
    let mut b = Browser::new(&gw.url);
    b.me().await;
    let (_, cells) = b.get("/api/v1/cells").await;
    // mill-2 alone has a g05 table in the default cell.
    assert_eq!(cells[0]["g05"], json!(["mill-2"]), "{cells}");

    for (path, kind) in [
        ("/favicon.ico", "image/x-icon"),
        ("/assets/favicon.svg", "image/svg+xml"),
    ] {
        let r = b
            .http
            .get(format!("{}{path}", gw.url))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200, "{path}");
        assert_eq!(
            r.headers()[reqwest::header::CONTENT_TYPE].to_str().unwrap(),
            kind,
            "{path}"
        );
        let body = r.bytes().await.unwrap();
        if path.ends_with(".ico") {
            // An ICO directory of one image, a PNG.
            assert_eq!(&body[..4], &[0, 0, 1, 0], "{path}");
            assert!(body.windows(3).any(|w| w == b"PNG"), "{path}");
        } else {
            assert!(body.starts_with(b"<svg"), "{path}");
        }
    }
    // The page names its icon, on its own origin.
    let (_, index) = b.get("/").await;
    assert!(
        index
            .as_str()
            .unwrap()
            .contains(r#"<link rel="icon" href="/assets/favicon.svg""#),
        "{index}"
    );
    gw.stop().await;
}

#[path = "door.rs"]
mod door;

/// lathe-1's punched O5557 as its machine page gives it, and whether the list is the
/// history's.
async fn punched_o5557(b: &Browser) -> (Value, Value) {
    for _ in 0..100 {
        let (status, page) = b.get("/api/v1/cells/demo/machines/lathe-1").await;
        assert_eq!(status, 200, "{page}");
        let list = page["punched"].as_array().cloned().unwrap_or_default();
        if let Some(p) = list.into_iter().find(|p| p["o_number"] == "O5557") {
            return (p, page["punched_recorded"].clone());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("lathe-1's punched O5557 never on its page");
}

/// A punched program and its comparison with the library are on the machine's page after the
/// gateway restarted: the history keeps them (the text stays in the library).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn punched_programs_and_their_comparisons_outlive_a_restart() {
    use cellgate::bus::keys::SimLeaf;
    use cellgate::client::{Client, ConnectOptions};
    use cellgate_core::pb;

    let dir = tempfile::tempdir().unwrap();
    let gw = Gateway::start_in(dir.path(), |_, _| {}).await;
    let client = Client::connect(&ConnectOptions {
        endpoint: gw.endpoint.clone(),
        ..ConnectOptions::default()
    })
    .await
    .unwrap();
    client
        .program_put("O5557", b"%\nO5557\nG00X0Y0\nG01X10.F100\nM30\n%\n")
        .await
        .unwrap();
    // The operator changed the feed at the machine.
    client
        .sim_control(
            "lathe-1",
            SimLeaf::Punch,
            Some(&pb::SimPunch {
                program: b"%\nO5557\nG00X0Y0\nG01X10.F200\nM30\n%\n".to_vec(),
            }),
        )
        .await
        .unwrap();
    client.close().await;
    let mut b = Browser::new(&gw.url);
    b.me().await;
    let (before, recorded) = punched_o5557(&b).await;
    assert_eq!(recorded, true);
    assert_eq!(before["comparison"]["library_name"], "O5557", "{before}");
    assert_eq!(before["comparison"]["blocks_changed"], 1, "{before}");
    gw.stop().await;

    let gw = Gateway::start_in(dir.path(), |_, _| {}).await;
    let mut b = Browser::new(&gw.url);
    b.me().await;
    let (after, _) = punched_o5557(&b).await;
    assert_eq!(after["comparison"], before["comparison"], "{after}");
    assert_eq!(after["library_name"], before["library_name"], "{after}");
    gw.stop().await;
}
