//! The console's pages in a real browser (Debian's chromium, driven over chromium-driver's
//! WebDriver), against a gateway serving the default cell: the overview shows every
//! machine; a program uploaded, released and sent from the pages reaches the simulated CNC
//! and its progress bar reaches the end; an alarm raised at the simulated CNC shows without a
//! reload; a tag's trend moves; the top bar links to the MTConnect agent; a read-only user
//! sees no control to send a program and a request forged from the page is refused and
//! audited; nothing is fetched from another
//! origin; the site console (`cellgate console -e ROUTER`) shows the cells of two gateways;
//! and the first load of an overview of 64 machines is timed (a figure, printed). Screenshots of the pages are written to `target/console-screenshots/`, and to
//! `docs/console/` when `CELLGATE_UPDATE_SCREENSHOTS=1`.
//!
//! Without `chromedriver` and `chromium` on the PATH (`.ci/run` installs Debian's), each test
//! says so and checks nothing else.

use crate::common;

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use cellgate_core::config::CellConfig;
use common::bus::free_port;
use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::{Value, json};

use super::gateway::Gateway;

/// chromium-driver running for one test; killed when dropped.
struct Driver {
    child: Child,
    url: String,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn found(program: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {program}")])
        .stdout(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// chromium-driver and a headless chromium session, or `None` (said on stderr) where the
/// machine has no browser.
async fn browser() -> Option<(Driver, Client)> {
    let browser = ["chromium", "chromium-browser", "google-chrome"]
        .into_iter()
        .find(|b| found(b));
    if !found("chromedriver") || browser.is_none() {
        eprintln!(
            "SKIPPED: no chromium and chromedriver here (apt-get install chromium chromium-driver; \
             .ci/run does): the console's pages were not checked in a browser"
        );
        return None;
    }
    let port = free_port();
    let child = Command::new("chromedriver")
        .arg(format!("--port={port}"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("chromedriver starts");
    let driver = Driver {
        child,
        url: format!("http://127.0.0.1:{port}"),
    };
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".to_string(),
        json!({"args": [
            "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
            "--window-size=1280,900", "--no-first-run", "--disable-extensions",
            "--disable-background-networking", "--disable-sync", "--disable-component-update"
        ]}),
    );
    let connector = hyper_util::client::legacy::connect::HttpConnector::new();
    let started = Instant::now();
    loop {
        match ClientBuilder::new(connector.clone())
            .capabilities(caps.clone())
            .connect(&driver.url)
            .await
        {
            Ok(c) => return Some((driver, c)),
            Err(e) if started.elapsed() < Duration::from_secs(20) => {
                let _ = e;
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(e) => panic!("no WebDriver session: {e}"),
        }
    }
}

fn provider() {
    let _ = tokio_rustls::rustls::crypto::ring::default_provider().install_default();
}

/// Waits for `css` to match an element.
async fn wait_css(c: &Client, css: &str) -> fantoccini::elements::Element {
    c.wait()
        .at_most(Duration::from_secs(30))
        .for_element(Locator::Css(css))
        .await
        .unwrap_or_else(|e| panic!("no {css} within 30 s: {e}"))
}

/// Waits until the script (an expression) is truthy.
async fn wait_js(c: &Client, what: &str, expr: &str) -> Value {
    let started = Instant::now();
    loop {
        let v = c
            .execute(&format!("return ({expr});"), vec![])
            .await
            .unwrap_or(Value::Null);
        if !matches!(v, Value::Null | Value::Bool(false)) && v != json!("") && v != json!(0) {
            return v;
        }
        if started.elapsed() > Duration::from_secs(60) {
            panic!("never: {what} ({expr})");
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// Writes the page as a PNG under target/, and under docs/console/ when asked to.
async fn screenshot(c: &Client, name: &str) {
    let png = c.screenshot().await.unwrap();
    let target = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("console-screenshots");
    std::fs::create_dir_all(&target).unwrap();
    std::fs::write(target.join(format!("{name}.png")), &png).unwrap();
    if std::env::var("CELLGATE_UPDATE_SCREENSHOTS").as_deref() == Ok("1") {
        let docs = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/console");
        std::fs::create_dir_all(&docs).unwrap();
        std::fs::write(docs.join(format!("{name}.png")), &png).unwrap();
    }
}

/// Every resource the page loaded came from its own origin.
async fn only_own_origin(c: &Client, base: &str) {
    let urls = c
        .execute(
            "return performance.getEntriesByType('resource').map(e => e.name)\
             .concat([location.href]);",
            vec![],
        )
        .await
        .unwrap();
    for u in urls.as_array().unwrap() {
        let u = u.as_str().unwrap();
        assert!(
            u.starts_with(base),
            "a request left the console's origin: {u}"
        );
    }
}

const PROGRAM: &str = "%\nO7001(BRACKET)\nN10G00X0Y0\nN20G01X25.F150\nN30Y40.\nN40M30\n%\n";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_program_goes_from_upload_to_the_cnc_and_the_cell_shows_it_live() {
    provider();
    let Some((_driver, c)) = browser().await else {
        return;
    };
    let mtconnect = format!("127.0.0.1:{}", free_port());
    let agent = mtconnect.clone();
    let gw = Gateway::start(move |c, _| {
        c.mtconnect = Some(cellgate_core::config::MtconnectConfig {
            listen: agent,
            ..Default::default()
        });
    })
    .await;
    c.goto(&format!("{}/#/", gw.url)).await.unwrap();

    // The top bar links to the cell's MTConnect agent.
    let link = wait_css(&c, "#mtconnect").await;
    assert_eq!(
        link.attr("href").await.unwrap().as_deref(),
        Some(format!("http://{mtconnect}/current").as_str())
    );

    // Every machine and the PLC have a tile.
    for m in ["mill-1", "mill-2", "lathe-1"] {
        wait_css(
            &c,
            &format!("article[data-tile=\"machine\"][data-name=\"{m}\"]"),
        )
        .await;
    }
    wait_css(&c, "article[data-tile=\"plc\"][data-name=\"plc-1\"]").await;
    wait_js(
        &c,
        "mill-1's link is up",
        "(document.querySelector('[data-tile=machine][data-name=\"mill-1\"] [data-field=link]')||{}).textContent?.toLowerCase().includes('idle')",
    )
    .await;
    screenshot(&c, "overview").await;

    // Upload a program from the page.
    let file = gw.dir.join("O7001.nc");
    std::fs::write(&file, PROGRAM).unwrap();
    c.goto(&format!("{}/#/cell/demo/programs", gw.url))
        .await
        .unwrap();
    wait_css(&c, "#upload-name")
        .await
        .send_keys("O7001")
        .await
        .unwrap();
    c.find(Locator::Css("#upload-file"))
        .await
        .unwrap()
        .send_keys(file.to_str().unwrap())
        .await
        .unwrap();
    c.find(Locator::Css("#upload-comment"))
        .await
        .unwrap()
        .send_keys("first article")
        .await
        .unwrap();
    c.find(Locator::Css("#upload-submit"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    wait_css(&c, "tr[data-program=\"O7001\"]").await;
    screenshot(&c, "programs").await;

    // Release revision 1, and send it to mill-1.
    c.goto(&format!("{}/#/cell/demo/programs/O7001", gw.url))
        .await
        .unwrap();
    wait_css(&c, "button[data-action=\"release\"][data-rev=\"1\"]")
        .await
        .click()
        .await
        .unwrap();
    wait_js(
        &c,
        "revision 1 shows released",
        "(document.querySelector('tr[data-rev=\"1\"] [data-field=state]')||{}).textContent?.includes('released')",
    )
    .await;
    screenshot(&c, "program").await;
    c.execute(
        "const s = document.querySelector('#send-machine'); s.value = 'mill-1'; \
         s.dispatchEvent(new Event('change')); return true;",
        vec![],
    )
    .await
    .unwrap();
    c.find(Locator::Css("#send-submit"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();

    // On the overview, mill-1's progress bar runs to its end.
    c.goto(&format!("{}/#/", gw.url)).await.unwrap();
    wait_js(
        &c,
        "mill-1's progress bar reached the end",
        "(() => { const p = document.querySelector('[data-tile=machine][data-name=\"mill-1\"] progress[data-field=progress]'); \
           return p && p.max > 1 && p.value === p.max; })()",
    )
    .await;
    // The simulated CNC has every byte of it, through its EOR.
    let http = reqwest::Client::builder()
        .cookie_store(true)
        .build()
        .unwrap();
    http.get(format!("{}/api/v1/me", gw.url))
        .send()
        .await
        .unwrap();
    let job: Value = http
        .get(format!("{}/api/v1/cells/demo/machines/mill-1", gw.url))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let latest = &job["jobs"][0];
    assert!(latest["completed"].is_object(), "{job}");
    assert_eq!(latest["origin"]["program"]["revision"], 1, "{job}");

    // An alarm raised at the simulated CNC shows on the tile without a reload.
    let session = cellgate::bus::open(&common::bus::client_config(
        gw.endpoint.rsplit(':').next().unwrap().parse().unwrap(),
    ))
    .await
    .unwrap();
    let keys = cellgate::bus::keys::CellKeys::new("cellgate", "demo").unwrap();
    // Its simulated operator would reset it at once: keep it in alarm for the pictures.
    let off = cellgate_core::pb::SimAutostart { on: false };
    let replies = session
        .get(keys.sim("mill-1", cellgate::bus::keys::SimLeaf::Autostart))
        .payload(prost::Message::encode_to_vec(&off))
        .encoding(cellgate::bus::payload::encoding::<
            cellgate_core::pb::SimAutostart,
        >())
        .timeout(Duration::from_secs(10))
        .await
        .unwrap();
    while replies.recv_async().await.is_ok() {}
    let replies = session
        .get(keys.sim("mill-1", cellgate::bus::keys::SimLeaf::Alarm))
        .timeout(Duration::from_secs(10))
        .await
        .unwrap();
    while replies.recv_async().await.is_ok() {}
    wait_js(
        &c,
        "the alarm shows on mill-1's tile",
        "(document.querySelector('[data-tile=machine][data-name=\"mill-1\"] [data-field=alarm]')||{}).textContent && \
         document.querySelector('#health [data-field=alarms]')",
    )
    .await;
    // The notices of the earlier pages would hide the tiles in the picture.
    c.execute(
        "document.querySelectorAll('#notices .alert').forEach((a) => a.remove()); return true;",
        vec![],
    )
    .await
    .unwrap();
    screenshot(&c, "overview-alarm").await;

    // The machine page: the job with its revision, the alarm.
    c.goto(&format!("{}/#/cell/demo/machine/mill-1", gw.url))
        .await
        .unwrap();
    wait_css(&c, "tr[data-job]").await;
    // The utilisation chart's axis gives times of day, not durations.
    let hour = wait_js(
        &c,
        "an hour label on the utilisation chart",
        "(document.querySelector('svg.util text.hour')||{}).textContent",
    )
    .await;
    let hour = hour.as_str().unwrap_or_default().to_string();
    assert!(
        hour.len() == 5 && hour.ends_with(":00") && hour[..2].parse::<u8>().is_ok_and(|h| h < 24),
        "{hour:?}"
    );
    screenshot(&c, "machine").await;

    // A tag's trend moves: the simulated sequence program counts parts every second.
    c.goto(&format!("{}/#/cell/demo/plc/plc-1", gw.url))
        .await
        .unwrap();
    wait_css(&c, "tr[data-tag=\"parts\"] svg.trend polyline").await;
    let points = "(document.querySelector('tr[data-tag=\"parts\"] svg.trend polyline')||{}).getAttribute?.('points') || ''";
    let first = wait_js(&c, "the trend has points", points).await;
    let started = Instant::now();
    loop {
        let now = c
            .execute(&format!("return ({points});"), vec![])
            .await
            .unwrap();
        if now != first {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "the trend of parts never moved"
        );
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
    // A trend says what it covers: door-open keeps no history, so only what came since
    // the page opened.
    wait_js(
        &c,
        "door-open's trend says it covers the time since the page opened",
        "((document.querySelector('tr[data-tag=\"door-open\"] [data-field=\"trend-span\"]')||{}).textContent||'').includes('since ')",
    )
    .await;
    screenshot(&c, "plc").await;

    // History: the job, the alarm.
    c.goto(&format!("{}/#/cell/demo/history", gw.url))
        .await
        .unwrap();
    wait_css(&c, "#history-table tr[data-seq]").await;
    // Newest first: what just happened is at the top of the page.
    let seqs = c
        .execute(
            "return [...document.querySelectorAll('#history-table tr[data-seq]')].map((r) => Number(r.dataset.seq));",
            vec![],
        )
        .await
        .unwrap();
    let seqs: Vec<u64> = serde_json::from_value(seqs).unwrap();
    assert!(seqs.len() > 1, "{seqs:?}");
    assert!(
        seqs.windows(2).all(|w| w[0] > w[1]),
        "newest first: {seqs:?}"
    );
    screenshot(&c, "history").await;

    only_own_origin(&c, &gw.url).await;
    c.close().await.unwrap();
    session.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_read_only_user_sees_no_send_control_and_a_forged_request_is_refused_and_audited() {
    provider();
    let Some((_driver, c)) = browser().await else {
        return;
    };
    let gw = Gateway::start(|config, dir| {
        let users = dir.join("users");
        std::fs::write(&users, "olga:tulips\nerik:hammer\n").unwrap();
        let text = format!(
            r#"
cell = "demo"
[security]
users_file = {users:?}
[[security.roles]]
name = "viewer"
usernames = ["olga"]
permissions = ["status.read", "program.read"]
[[security.roles]]
name = "engineer"
usernames = ["erik"]
permissions = ["status.read", "program.write", "job.submit", "audit.read"]
"#
        );
        config.security = CellConfig::from_toml_str(&text, "security")
            .unwrap()
            .security;
    })
    .await;
    // Erik puts a program in the library, through the API.
    let erik = reqwest::Client::builder()
        .cookie_store(true)
        .build()
        .unwrap();
    let me: Value = erik
        .post(format!("{}/api/v1/login", gw.url))
        .json(&json!({"user": "erik", "password": "hammer"}))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let put = erik
        .put(format!("{}/api/v1/cells/demo/programs/O7001", gw.url))
        .header("X-CSRF-Token", me["csrf"].as_str().unwrap())
        .body(PROGRAM)
        .send()
        .await
        .unwrap();
    assert_eq!(put.status(), 200);

    // Olga logs in on the page.
    c.goto(&format!("{}/#/", gw.url)).await.unwrap();
    wait_css(&c, "#login-user")
        .await
        .send_keys("olga")
        .await
        .unwrap();
    c.find(Locator::Css("#login-password"))
        .await
        .unwrap()
        .send_keys("tulips")
        .await
        .unwrap();
    c.find(Locator::Css("#login-submit"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    wait_css(&c, "article[data-tile=\"machine\"][data-name=\"mill-1\"]").await;
    c.goto(&format!("{}/#/cell/demo/programs/O7001", gw.url))
        .await
        .unwrap();
    wait_css(&c, "tr[data-rev=\"1\"]").await;
    // She sees the program, and no control to send it, release it or upload one.
    for hidden in [
        "#send-submit",
        "button[data-action=\"release\"]",
        "#upload-submit",
    ] {
        assert!(
            c.find(Locator::Css(hidden)).await.is_err(),
            "{hidden} is shown to a read-only user"
        );
    }
    // A submit forged from her page, with her own session's token, is refused...
    let forged = c
        .execute_async(
            "const done = arguments[arguments.length - 1];
             fetch('/api/v1/me').then(r => r.json()).then(me =>
               fetch('/api/v1/cells/demo/machines/mill-1/submit', {method: 'POST',
                 headers: {'Content-Type': 'application/json', 'X-CSRF-Token': me.csrf},
                 body: JSON.stringify({library: 'O7001'})}))
             .then(r => r.json().then(b => done([r.status, b])))
             .catch(e => done([0, String(e)]));",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(forged[0], 403, "{forged}");
    assert_eq!(forged[1]["code"], "ERROR_CODE_NOT_PERMITTED", "{forged}");
    // ...and noted in the cell's audit trail, with her name.
    let mut noted = false;
    for _ in 0..50 {
        let page: Value = erik
            .get(format!("{}/api/v1/cells/demo/audit", gw.url))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        noted = page["records"].as_array().unwrap().iter().any(|r| {
            r["audit"]["action"] == "audit.note" && r["audit"]["origin"]["user"] == "olga"
        });
        if noted {
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert!(noted, "the forged submit is not in the audit trail");
    // Nothing was queued on mill-1.
    let m: Value = erik
        .get(format!("{}/api/v1/cells/demo/machines/mill-1", gw.url))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert!(m["jobs"].as_array().unwrap().is_empty(), "{m}");
    c.close().await.unwrap();
    gw.stop().await;
}

/// The time from navigation start to every machine's tile in the DOM, in ms, as the page's
/// own clock (`performance.now()`) saw it.
async fn tiles_seen(c: &Client, tiles: usize) -> f64 {
    let at = c
        .execute_async(
            "const [want, done] = [arguments[0], arguments[arguments.length - 1]];
             (function tick() {
               const n = document.querySelectorAll('article[data-tile=machine]').length;
               if (n >= want) done(performance.now()); else setTimeout(tick, 5);
             })();",
            vec![json!(tiles)],
        )
        .await
        .unwrap();
    at.as_f64().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_overview_of_64_machines_loads_and_the_figure_is_printed() {
    provider();
    let Some((_driver, c)) = browser().await else {
        return;
    };
    const MACHINES: usize = 64;
    let gw = Gateway::start(|config, _| {
        let mill = config.machines[0].clone();
        config.machines = (0..MACHINES)
            .map(|i| {
                let mut m = mill.clone();
                m.name = format!("m{i:02}");
                m
            })
            .collect();
    })
    .await;
    // The first visit, then a reload (scripts in the browser's cache).
    c.goto(&format!("{}/#/", gw.url)).await.unwrap();
    let first = tiles_seen(&c, MACHINES).await;
    c.refresh().await.unwrap();
    let again = tiles_seen(&c, MACHINES).await;
    let shown = c
        .execute(
            "return document.querySelectorAll('article[data-tile=machine]').length;",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(shown, json!(MACHINES), "one tile per machine");
    // A figure, not a bound: the gateway here is a debug build sharing the machine with the
    // browser and the other tests (docs/performance.md has the release figures).
    eprintln!(
        "FIGURE console first load, overview of {MACHINES} machines (debug gateway, headless \
         chromium): {first:.0} ms; reloaded {again:.0} ms"
    );
    only_own_origin(&c, &gw.url).await;
    c.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_site_console_shows_two_gateways_cells_in_the_browser() {
    provider();
    let Some((_driver, c)) = browser().await else {
        return;
    };
    // A router, and the gateways of cells "north" and "south" connected to it.
    let router_port = free_port();
    let router = cellgate::bus::open(&cellgate::bus::BusConfig {
        mode: cellgate::bus::BusMode::Router,
        listen: vec![format!("tcp/127.0.0.1:{router_port}")],
        ..cellgate::bus::BusConfig::default()
    })
    .await
    .unwrap();
    let mut gateways = Vec::new();
    for cell in ["north", "south"] {
        gateways.push(
            Gateway::start(|c, _| {
                c.cell = cell.to_string();
                c.bus.connect = vec![format!("tcp/127.0.0.1:{router_port}")];
            })
            .await,
        );
    }
    // The site console: `cellgate console -e ROUTER`.
    let site = common::bus::SiteConsole::start(router_port);
    let url = site.url.clone();
    let http = reqwest::Client::new();
    for _ in 0..300 {
        if let Ok(r) = http.get(format!("{url}/health")).send().await
            && r.status() == 200
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // The cells are found as their gateways answer on the router: reload until both show.
    let started = Instant::now();
    loop {
        c.goto(&format!("{url}/#/")).await.unwrap();
        let both = c
            .wait()
            .at_most(Duration::from_secs(5))
            .for_element(Locator::Css(
                "section[data-cell=\"south\"] article[data-tile=\"machine\"]",
            ))
            .await
            .is_ok()
            && c.find(Locator::Css(
                "section[data-cell=\"north\"] article[data-tile=\"machine\"]",
            ))
            .await
            .is_ok();
        if both {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the site console never showed both cells"
        );
    }
    for cell in ["north", "south"] {
        for m in ["mill-1", "mill-2", "lathe-1"] {
            wait_css(
                &c,
                &format!(
                    "section[data-cell=\"{cell}\"] article[data-tile=\"machine\"][data-name=\"{m}\"]"
                ),
            )
            .await;
        }
    }
    wait_js(
        &c,
        "every link of both cells is up",
        "(document.querySelector('#health')||{}).textContent?.includes('All 6 machine links up')",
    )
    .await;
    screenshot(&c, "site").await;
    only_own_origin(&c, &url).await;
    c.close().await.unwrap();
    site.stop().await;
    for gw in gateways {
        gw.stop().await;
    }
    router.close().await.unwrap();
}

/// The state at a glance, without a contradiction: at rest no tile shows an alarm label, the
/// machine count is said once, G05 shows only on the machine that takes G05 streams, and a
/// console without users offers no "Log out". With mill-1 in alarm the banner still says
/// every link is up and names the alarm on a line of its own, the tile holds the alarm's
/// whole text, and the machine page says it; after a reset, none of it. Right after a short
/// job ends, the machine page shows its end at once: out of the queue (no "ACTIVE" left
/// behind), in the recent jobs as completed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_overview_tells_links_from_alarms_and_a_job_s_end_shows_at_once() {
    use cellgate::bus::keys::SimLeaf;
    use cellgate::client::{Client as BusClient, ConnectOptions};
    use cellgate_core::pb;

    provider();
    let Some((_driver, c)) = browser().await else {
        return;
    };
    let gw = Gateway::start(|_, _| {}).await;
    let bus = BusClient::connect(&ConnectOptions {
        endpoint: gw.endpoint.clone(),
        ..ConnectOptions::default()
    })
    .await
    .unwrap();
    let no = None::<&pb::SimAutostart>;

    c.goto(&format!("{}/#/", gw.url)).await.unwrap();
    wait_js(
        &c,
        "every link is up",
        "(document.querySelector('#health [data-field=links]')||{}).textContent?.includes('All 3 machine links up')",
    )
    .await;
    let at_rest = c
        .execute(
            "const shown = (el) => el && el.offsetParent !== null;
             const tiles = [...document.querySelectorAll('article[data-tile=machine]')];
             return {
               alarmLabels: tiles.filter((t) => shown(t.querySelector('.alarm-row'))).map((t) => t.dataset.name),
               g05: tiles.filter((t) => shown(t.querySelector('.g05-row'))).map((t) => t.dataset.name),
               counts: [...document.querySelectorAll('main *')].filter((e) => shown(e) && e.children.length === 0 && /^3 machines$/.test(e.textContent.trim())).length,
               alarmsLine: !!document.querySelector('#health [data-field=alarms]'),
               logout: !!document.querySelector('#logout') || [...document.querySelectorAll('#user button')].some((b) => b.textContent.includes('Log out')),
               noLogin: document.querySelector('#no-login')?.textContent,
             };",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(at_rest["alarmLabels"], json!([]), "{at_rest}");
    assert_eq!(at_rest["g05"], json!(["mill-2"]), "{at_rest}");
    assert_eq!(at_rest["counts"], 1, "the machine count once: {at_rest}");
    assert_eq!(at_rest["alarmsLine"], false, "{at_rest}");
    assert_eq!(at_rest["logout"], false, "{at_rest}");
    assert_eq!(at_rest["noLogin"], "No login", "{at_rest}");

    // mill-1 in alarm, its operator away (autostart off) so that it stays.
    bus.sim_control(
        "mill-1",
        SimLeaf::Autostart,
        Some(&pb::SimAutostart { on: false }),
    )
    .await
    .unwrap();
    bus.sim_control("mill-1", SimLeaf::Alarm, no).await.unwrap();
    wait_js(
        &c,
        "the banner names the alarm apart from the links",
        "(document.querySelector('#health [data-field=alarms]')||{}).textContent?.includes('1 machine in alarm: mill-1')",
    )
    .await;
    let banner = c
        .execute(
            "return document.querySelector('#health [data-field=links]').textContent;",
            vec![],
        )
        .await
        .unwrap();
    assert!(
        banner.as_str().unwrap().contains("All 3 machine links up"),
        "a machine in alarm has its link up: {banner}"
    );
    let message = bus
        .status(Some("mill-1"))
        .await
        .unwrap()
        .remove(0)
        .last_alarm
        .expect("mill-1's alarm in its status")
        .message;
    let tile = wait_js(
        &c,
        "the tile holds the alarm",
        "(() => { const r = document.querySelector('[data-tile=machine][data-name=\"mill-1\"] .alarm-row');
           if (!r || r.hidden || !r.textContent.includes('In alarm')) return null;
           const t = r.querySelector('[data-field=alarm]');
           return { text: r.textContent, title: r.title, clipped: t.scrollWidth > t.clientWidth + 1 || r.scrollWidth > r.clientWidth + 1 }; })()",
    )
    .await;
    assert!(
        tile["text"].as_str().unwrap().contains(&message),
        "the whole alarm text {message:?}: {tile}"
    );
    assert!(tile["title"].as_str().unwrap().contains(&message), "{tile}");
    assert_eq!(tile["clipped"], false, "{tile}");
    c.goto(&format!("{}/#/cell/demo/machine/mill-1", gw.url))
        .await
        .unwrap();
    wait_js(
        &c,
        "the machine page says the alarm and its cause",
        "(document.querySelector('.page-head [data-field=alarm]')||{}).textContent?.includes('In alarm') && \
         [...document.querySelectorAll('dt')].some((d) => d.textContent === 'Alarm cause')",
    )
    .await;

    // After a reset: no alarm anywhere, and no alarm cause on the machine page.
    bus.sim_control("mill-1", SimLeaf::Reset, no).await.unwrap();
    wait_js(
        &c,
        "the machine page shows no alarm after the reset",
        "!document.querySelector('.page-head [data-field=alarm]') && \
         (document.querySelector('.page-head [data-field=link]')||{}).textContent === 'IDLE' && \
         ![...document.querySelectorAll('dt')].some((d) => d.textContent === 'Alarm cause')",
    )
    .await;
    c.goto(&format!("{}/#/", gw.url)).await.unwrap();
    wait_js(
        &c,
        "the overview shows no alarm after the reset",
        "(() => { const r = document.querySelector('[data-tile=machine][data-name=\"mill-1\"] .alarm-row');
           return r && r.hidden && !document.querySelector('#health [data-field=alarms]')
             && document.querySelector('#health').classList.contains('ok'); })()",
    )
    .await;

    // A short job: it waits for the CNC to read (the operator is away), then is read at once.
    bus.program_put("O7001", PROGRAM.as_bytes()).await.unwrap();
    bus.program_release("O7001", "1", pb::RevisionState::Released, String::new())
        .await
        .unwrap();
    c.goto(&format!("{}/#/cell/demo/machine/mill-1", gw.url))
        .await
        .unwrap();
    wait_css(&c, "#sec-queue").await;
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Library("O7001".to_string())),
        request_id: cellgate::client::new_request_id(),
        ..Default::default()
    };
    let (accepted, follower) = bus.submit("mill-1", &request).await.unwrap();
    follower.close().await;
    let job = accepted.job_id;
    wait_css(&c, &format!("tr.active[data-job=\"{job}\"]")).await;
    // The page's own clock: when the job's end reached the browser (on a stream of its own),
    // and when the page stopped showing the job as active and showed it completed.
    c.execute(
        "const id = arguments[0];
         const rec = window.__rec = { t0: null, gone: null, done: null, open: false };
         const es = new EventSource('/api/v1/cells/demo/events?machine=mill-1');
         es.onopen = () => { rec.open = true; };
         es.addEventListener('job', (e) => {
           const ev = JSON.parse(e.data);
           if (ev.job_id === id && ev.completed && rec.t0 === null) rec.t0 = performance.now();
         });
         const check = () => {
           const now = performance.now();
           const active = document.querySelector(`#sec-queue ~ * tr[data-job=\"${id}\"], [data-field=active-job]`);
           if (!active && rec.gone === null) rec.gone = now;
           if (document.querySelector(`tr[data-job=\"${id}\"][data-state=completed]`) && rec.done === null) rec.done = now;
         };
         new MutationObserver(check).observe(document.querySelector('main'), { subtree: true, childList: true, characterData: true });
         return true;",
        vec![json!(job)],
    )
    .await
    .unwrap();
    wait_js(&c, "the recorder's stream is open", "window.__rec.open").await;
    bus.sim_control("mill-1", SimLeaf::Read, no).await.unwrap();
    let rec = wait_js(
        &c,
        "the job ended on the page",
        "window.__rec.t0 !== null && window.__rec.gone !== null && window.__rec.done !== null && window.__rec",
    )
    .await;
    let after = |k: &str| rec[k].as_f64().unwrap() - rec["t0"].as_f64().unwrap();
    // One render after the event (at most 4 a second), not the page's re-read 600 ms later.
    assert!(
        after("gone") < 450.0,
        "the queue showed the ended job as active {:.0} ms on: {rec}",
        after("gone")
    );
    assert!(
        after("done") < 450.0,
        "the recent jobs showed the job completed {:.0} ms on: {rec}",
        after("done")
    );
    let page = c
        .execute("return document.querySelector('main').innerText;", vec![])
        .await
        .unwrap();
    assert!(!page.as_str().unwrap().contains("ACTIVE"), "{page}");

    // The compare view pairs a changed block with its new text on one row.
    bus.program_put(
        "O7001",
        PROGRAM
            .replace("N20G01X25.F150", "N20G01X30.F120")
            .as_bytes(),
    )
    .await
    .unwrap();
    c.goto(&format!("{}/#/cell/demo/programs/O7001", gw.url))
        .await
        .unwrap();
    wait_css(&c, "tr[data-rev=\"2\"]").await;
    c.find(Locator::Css("#diff-show"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let row = wait_js(
        &c,
        "the changed block on one row",
        "(() => { const rows = [...document.querySelectorAll('#diff-result tr[data-op]')].filter((r) => r.dataset.op !== 'equal');
           return rows.length && rows.map((r) => [r.dataset.op, r.querySelector('td.a').textContent, r.querySelector('td.b').textContent]); })()",
    )
    .await;
    assert_eq!(row.as_array().unwrap().len(), 1, "{row}");
    assert_eq!(row[0][0], "changed", "{row}");
    assert!(
        row[0][1].as_str().unwrap().contains("N20G01X25.F150"),
        "{row}"
    );
    assert!(
        row[0][2].as_str().unwrap().contains("N20G01X30.F120"),
        "{row}"
    );

    // Pages that do not stream say so, not "off".
    c.goto(&format!("{}/#/cell/demo/programs", gw.url))
        .await
        .unwrap();
    wait_css(&c, "tr[data-program=\"O7001\"]").await;
    let conn = c
        .execute(
            "return [document.querySelector('#conn .conn-text').textContent, document.querySelector('#conn').title];",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(conn[0], "Not live", "{conn}");
    assert!(
        conn[1]
            .as_str()
            .unwrap()
            .contains("does not update by itself"),
        "{conn}"
    );
    only_own_origin(&c, &gw.url).await;
    c.close().await.unwrap();
    bus.close().await;
    gw.stop().await;
}
