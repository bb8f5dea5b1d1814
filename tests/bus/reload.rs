//! Reloading the cell file of a running gateway (docs/configuration.md, "Reloading"): a
//! machine added while another sends a long job, a machine's line changed, one removed, a
//! file that does not check and one that needs a restart refused whole, the audit and the
//! bus told. Each test runs `gateway::run_with` on a cell file in a temporary directory, with
//! simulated machines, and speaks to it as `cellgate` does (the client library).

use crate::common;

use std::path::PathBuf;
use std::time::Duration;

use cellgate::bus::keys::CellKeys;
use cellgate::client::{Client, ClientError, ConnectOptions, WatchEvent};
use cellgate::gateway::{self, CellSource, ReloadHandle, Reloads, RunOptions};
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;
use prost::Message as _;

use common::bus::{free_port, wait_token};

const CELL: &str = "rl";

/// m1: Protocol A at 4800 baud, so that a 4 KB program takes about nine seconds.
const M1: &str = r#"
[[machines]]
name = "m1"
protocol = "a"
transport = { kind = "sim", line = { baud = 4800 } }
"#;

const M2: &str = r#"
[[machines]]
name = "m2"
protocol = "a"
transport = { kind = "sim", line = { baud = 19200 } }
"#;

/// A gateway running a cell file it can read again.
struct Running {
    dir: tempfile::TempDir,
    path: PathBuf,
    port: u16,
    keys: CellKeys,
    client: Client,
    reload: ReloadHandle,
    /// What the gateway serves beside the bus (its console's URL).
    ready: gateway::Ready,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<Result<(), gateway::GatewayError>>,
}

fn cell_text(port: u16, dir: &std::path::Path, body: &str) -> String {
    format!(
        "cell = \"{CELL}\"\n[bus]\nlisten = [\"tcp/127.0.0.1:{port}\"]\n[programs]\ndir = \
         \"{}\"\n{body}",
        dir.join("programs").display()
    )
}

impl Running {
    async fn start(body: &str) -> Running {
        let dir = tempfile::tempdir().unwrap();
        let port = free_port();
        let path = dir.path().join("cell.toml");
        std::fs::write(&path, cell_text(port, dir.path(), body)).unwrap();
        let config = gateway::check_cell_file(&path).unwrap();
        let (reload, reloads) = Reloads::new();
        let (ready, started) = tokio::sync::oneshot::channel();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let options = RunOptions {
            ready: Some(ready),
            source: Some(CellSource::file(&path)),
            reloads: Some(reloads),
        };
        let task = tokio::spawn(gateway::run_with(
            config,
            async {
                let _ = stopped.await;
            },
            options,
        ));
        let ready = tokio::time::timeout(Duration::from_secs(30), started)
            .await
            .expect("the gateway did not start in time")
            .expect("the gateway did not start");
        let client = Client::connect(&ConnectOptions {
            endpoint: format!("tcp/127.0.0.1:{port}"),
            cell: Some(CELL.to_string()),
            origin: Some(pb::RequestOrigin {
                user: "tester".to_string(),
                via: "test".to_string(),
            }),
            ..ConnectOptions::default()
        })
        .await
        .unwrap();
        Running {
            keys: CellKeys::new("cellgate", CELL).unwrap(),
            dir,
            path,
            port,
            client,
            reload,
            ready,
            stop,
            task,
        }
    }

    fn write(&self, body: &str) {
        std::fs::write(&self.path, cell_text(self.port, self.dir.path(), body)).unwrap();
    }

    async fn stop(self) {
        self.client.close().await;
        let _ = self.stop.send(());
        self.task.await.unwrap().unwrap();
    }

    /// The admin document as a client connecting now finds it.
    async fn admin(&self) -> serde_json::Value {
        let c = Client::connect(&ConnectOptions {
            endpoint: format!("tcp/127.0.0.1:{}", self.port),
            cell: Some(CELL.to_string()),
            ..ConnectOptions::default()
        })
        .await
        .unwrap();
        let doc = c.admin().clone();
        c.close().await;
        doc
    }

    /// The audit's `cell.reload` records, once there are `n`.
    async fn reload_audits(&self, n: usize) -> Vec<pb::AuditRecord> {
        for _ in 0..100 {
            let page = self.client.history(true, &[]).await.unwrap();
            let audits: Vec<pb::AuditRecord> = page
                .records
                .into_iter()
                .filter_map(|r| match r.record {
                    Some(pb::history_record::Record::Audit(a)) if a.action == "cell.reload" => {
                        Some(a)
                    }
                    _ => None,
                })
                .collect();
            if audits.len() >= n {
                return audits;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        panic!("fewer than {n} cell.reload records in the audit");
    }

    async fn machines(&self) -> Vec<String> {
        let statuses = self.client.status(None).await.unwrap();
        statuses.into_iter().map(|s| s.machine).collect()
    }

    /// Waits until `machine` is sending job `job`.
    async fn until_active(&self, machine: &str, job: &str) {
        for _ in 0..200 {
            let q = self.client.queue(machine).await.unwrap();
            if q.active.is_some_and(|a| a.job_id == job) {
                return;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        panic!("job {job} never became active on {machine}");
    }
}

fn inline(program: &[u8]) -> pb::JobRequest {
    pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(program.to_vec())),
        ..pb::JobRequest::default()
    }
}

fn completed(e: &pb::JobEvent) -> &pb::job_event::Completed {
    match &e.kind {
        Some(Kind::Completed(c)) => c,
        other => panic!("expected completed, got {other:?}"),
    }
}

/// A subscriber to the liveliness token of `machine`: what it saw go and come.
async fn token_watch(
    client: &Client,
    keys: &CellKeys,
    machine: &str,
) -> zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>> {
    client
        .session()
        .liveliness()
        .declare_subscriber(keys.machine(machine))
        .await
        .unwrap()
}

fn withdrawals(
    sub: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
) -> usize {
    let mut n = 0;
    while let Ok(Some(s)) = sub.try_recv() {
        if s.kind() == zenoh::sample::SampleKind::Delete {
            n += 1;
        }
    }
    n
}

/// The machines of the console's overview of the cell, as a browser gets them.
async fn console_machines(url: &str) -> Vec<String> {
    let _ = tokio_rustls::rustls::crypto::ring::default_provider().install_default();
    let http = reqwest::Client::builder()
        .cookie_store(true)
        .build()
        .unwrap();
    // A cell without [security]: the first visit gets a session.
    http.get(format!("{url}api/v1/me")).send().await.unwrap();
    let overview: serde_json::Value = http
        .get(format!("{url}api/v1/cells/{CELL}/overview"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    overview["machines"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["machine"].as_str().unwrap().to_string())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_machine_added_while_another_sends_a_long_job_takes_a_job_and_the_long_one_completes() {
    let g = Running::start(&format!("[console]\nlisten = \"127.0.0.1:0\"\n{M1}")).await;
    let console = g.ready.console.clone().expect("the console serves");
    assert_eq!(console_machines(&console).await, ["m1"]);
    let mut watch = g.client.watch().await.unwrap();
    let published = g
        .client
        .session()
        .declare_subscriber(g.keys.reloads())
        .await
        .unwrap();
    let m1_token = token_watch(&g.client, &g.keys, "m1").await;
    let long = common::nc_program(4000, 1);
    let (accepted, mut long_job) = g.client.submit("m1", &inline(&long)).await.unwrap();
    g.until_active("m1", &accepted.job_id).await;

    g.write(&format!("[console]\nlisten = \"127.0.0.1:0\"\n{M1}{M2}"));
    let r = g.client.reload(false).await.unwrap();
    assert!(r.applied, "{r:?}");
    assert_eq!(r.generation, 2);
    assert_eq!(r.machines_added, ["m2"]);
    assert!(r.machines_removed.is_empty() && r.machines_changed.is_empty() && r.waiting.is_empty());
    assert_eq!(r.file, g.path.display().to_string());

    // The new machine is served and takes a job while m1 still sends its own.
    wait_token(g.client.session(), &g.keys.machine("m2"), true).await;
    let short = common::nc_program(300, 2);
    let (_, mut short_job) = g.client.submit("m2", &inline(&short)).await.unwrap();
    let end = short_job.wait_end().await.unwrap();
    assert_eq!(completed(&end).bytes_sent, short.len() as u64);
    let q = g.client.queue("m1").await.unwrap();
    assert_eq!(
        q.active.map(|a| a.job_id),
        Some(accepted.job_id.clone()),
        "m1's job should still be running when m2's completes"
    );
    // m1's job goes on to its end, every byte acknowledged, its link never down.
    let end = long_job.wait_end().await.unwrap();
    assert_eq!(completed(&end).bytes_sent, long.len() as u64);
    assert_eq!(withdrawals(&m1_token), 0, "m1's link went down");
    assert_eq!(g.machines().await, ["m1", "m2"]);
    assert_eq!(console_machines(&console).await, ["m1", "m2"]);
    // `cellgate watch` saw the reload and the new machine's link come up.
    let (mut reloaded, mut m2_up) = (false, false);
    while !(reloaded && m2_up) {
        let event = tokio::time::timeout(Duration::from_secs(10), watch.next())
            .await
            .expect("watch saw no reload and no m2")
            .unwrap();
        match event {
            WatchEvent::Reload(r) => reloaded = r.applied && r.machines_added == ["m2"],
            WatchEvent::Link { machine, up } if machine == "m2" => m2_up |= up,
            _ => {}
        }
    }
    watch.close().await;

    // The bus was told, the admin document shows the generation, the audit has it.
    let sample = published.recv_async().await.unwrap();
    let told = pb::ReloadResult::decode(sample.payload().to_bytes().as_ref()).unwrap();
    assert!(told.applied && told.machines_added == ["m2"] && told.via == "bus");
    let doc = g.admin().await;
    assert_eq!(doc["generation"], 2);
    assert_eq!(doc["config"]["machines"][1]["name"], "m2");
    assert_eq!(doc["reload"]["machines_added"][0], "m2");
    let audits = g.reload_audits(1).await;
    let a = &audits[0];
    assert!(a.ok, "{a:?}");
    assert_eq!(a.target, g.path.display().to_string());
    assert!(
        a.detail.contains("generation 2") && a.detail.contains("machines added: m2"),
        "{a:?}"
    );
    assert_eq!(a.origin.as_ref().map(|o| o.user.as_str()), Some("tester"));
    g.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_changed_machine_restarts_after_its_job_and_a_removed_one_stops() {
    let g = Running::start(&format!("{M1}{M2}")).await;
    let m1_token = token_watch(&g.client, &g.keys, "m1").await;
    let long = common::nc_program(5000, 3);
    let (accepted, mut long_job) = g.client.submit("m1", &inline(&long)).await.unwrap();
    g.until_active("m1", &accepted.job_id).await;

    // m1's line goes to 9600 baud; m2 leaves the cell.
    g.write(&M1.replace("baud = 4800", "baud = 9600"));
    let r = g.client.reload(false).await.unwrap();
    assert!(r.applied, "{r:?}");
    assert_eq!(r.machines_changed, ["m1"]);
    assert_eq!(r.machines_removed, ["m2"]);
    assert!(r.waiting.contains(&"m1".to_string()), "{r:?}");

    // m1 takes a job while it waits: it runs on the restarted link.
    let next = common::nc_program(500, 4);
    let (queued, mut next_job) = g.client.submit("m1", &inline(&next)).await.unwrap();
    let q = g.client.queue("m1").await.unwrap();
    assert_eq!(q.active.map(|a| a.job_id), Some(accepted.job_id.clone()));
    assert_eq!(q.waiting.len(), 1);
    assert_eq!(q.waiting[0].job_id, queued.job_id);
    // m2 had nothing to send: it goes at once.
    wait_token(g.client.session(), &g.keys.machine("m2"), false).await;
    match g.client.status(Some("m2")).await {
        Err(ClientError::Refused { code, .. }) => assert_eq!(code, pb::ErrorCode::UnknownMachine),
        other => panic!("{other:?}"),
    }
    assert_eq!(g.admin().await["waiting"][0], "m1");

    // Its running job ends whole on the old link; then the link restarts.
    let end = long_job.wait_end().await.unwrap();
    assert_eq!(completed(&end).bytes_sent, long.len() as u64);
    let end = next_job.wait_end().await.unwrap();
    assert_eq!(completed(&end).bytes_sent, next.len() as u64);
    assert!(withdrawals(&m1_token) >= 1, "m1's link did not restart");
    let doc = g.admin().await;
    assert_eq!(
        doc["config"]["machines"][0]["transport"]["line"]["baud"],
        9600
    );
    assert_eq!(doc["waiting"], serde_json::json!([]));
    assert_eq!(g.machines().await, ["m1"]);
    // Its jobs are still found by id after the restart.
    let latest = g.client.job_latest("m1", &accepted.job_id).await.unwrap();
    assert!(matches!(latest.kind, Some(Kind::Completed(_))));
    g.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_removed_machine_takes_no_job_and_a_forced_reload_ends_its_wait_failing_its_job() {
    let g = Running::start(&format!("{M1}{M2}")).await;
    let long = common::nc_program(4000, 5);
    let (accepted, mut long_job) = g.client.submit("m1", &inline(&long)).await.unwrap();
    g.until_active("m1", &accepted.job_id).await;
    g.write(M2);
    let r = g.client.reload(false).await.unwrap();
    assert!(r.applied && r.machines_removed == ["m1"], "{r:?}");
    assert_eq!(r.waiting, ["m1"]);
    // m1 waits for its job and takes no other.
    match g.client.submit("m1", &inline(&long)).await {
        Err(ClientError::Refused { code, message, .. }) => {
            assert_eq!(code, pb::ErrorCode::Unavailable);
            assert!(message.contains("leaving the cell"), "{message}");
        }
        Err(e) => panic!("{e:?}"),
        Ok((a, _)) => panic!("a machine leaving the cell took job {}", a.job_id),
    }
    let q = g.client.queue("m1").await.unwrap();
    assert_eq!(q.active.map(|a| a.job_id), Some(accepted.job_id.clone()));
    // --force ends the wait: the same file, nothing changed, the job fails saying why.
    let r = g.client.reload(true).await.unwrap();
    assert!(r.applied && r.machines_removed.is_empty(), "{r:?}");
    let end = long_job.wait_end().await.unwrap();
    match &end.kind {
        Some(Kind::Failed(f)) => {
            assert!(
                f.reason
                    .contains("removed from the cell by a forced reload"),
                "{f:?}"
            );
            assert!(f.byte_offset < long.len() as u64);
        }
        other => panic!("{other:?}"),
    }
    wait_token(g.client.session(), &g.keys.machine("m1"), false).await;
    assert_eq!(g.machines().await, ["m2"]);
    g.stop().await;
}

/// A reload removes a busy machine and an idle one: only the busy one waits, it stays in the
/// cell as every surface sees it (the admin document) until its job ended, the reload is
/// published again once it left, and its job's id still says how the job ended.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_removed_busy_machine_stays_until_its_job_ended_and_its_job_is_still_found() {
    let m3 = M2.replace("\"m2\"", "\"m3\"");
    let g = Running::start(&format!("{M1}{M2}")).await;
    let published = g
        .client
        .session()
        .declare_subscriber(g.keys.reloads())
        .await
        .unwrap();
    let long = common::nc_program(4000, 7);
    let (accepted, mut long_job) = g.client.submit("m1", &inline(&long)).await.unwrap();
    g.until_active("m1", &accepted.job_id).await;
    g.write(&m3);
    let r = g.client.reload(false).await.unwrap();
    assert!(r.applied, "{r:?}");
    assert_eq!(r.machines_removed, ["m1", "m2"]);
    // m2 had nothing to send: it left at once and does not wait (before, it was listed).
    assert_eq!(r.waiting, ["m1"], "{r:?}");
    // m1 still runs its job: the running cell holds it, as the admin document says.
    let doc = g.admin().await;
    let names: Vec<&str> = doc["config"]["machines"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|m| m["name"].as_str())
        .collect();
    assert!(names.contains(&"m1") && !names.contains(&"m2"), "{names:?}");
    assert_eq!(doc["waiting"], serde_json::json!(["m1"]));
    let end = long_job.wait_end().await.unwrap();
    assert_eq!(completed(&end).bytes_sent, long.len() as u64);
    // Once it left: published again, nothing waiting, gone from the admin document.
    let mut again = None;
    for _ in 0..3 {
        let sample = tokio::time::timeout(Duration::from_secs(20), published.recv_async())
            .await
            .expect("the reload was not published again once m1 left")
            .unwrap();
        let told = pb::ReloadResult::decode(sample.payload().to_bytes().as_ref()).unwrap();
        if told.waiting.is_empty() {
            again = Some(told);
            break;
        }
    }
    let again = again.expect("a publication with nothing waiting");
    assert_eq!((again.generation, again.applied), (2, true));
    wait_token(g.client.session(), &g.keys.machine("m1"), false).await;
    let doc = g.admin().await;
    assert_eq!(doc["config"]["machines"][0]["name"], "m3");
    assert_eq!(doc["config"]["machines"].as_array().unwrap().len(), 1);
    // The job's own id still tells how it ended, from the history.
    let latest = g.client.job_latest("m1", &accepted.job_id).await.unwrap();
    match &latest.kind {
        Some(Kind::Completed(c)) => assert_eq!(c.bytes_sent, long.len() as u64),
        other => panic!("{other:?}"),
    }
    assert_eq!(latest.machine, "m1");
    g.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_file_and_a_change_that_needs_a_restart_are_refused_whole() {
    let g = Running::start(M1).await;
    let published = g
        .client
        .session()
        .declare_subscriber(g.keys.reloads())
        .await
        .unwrap();

    // A file that does not check: every error, with the line or key at fault.
    g.write(&format!(
        "{M1}{}\n[history]\nkeep_dayz = 3\n",
        M2.replace("19200", "12345")
    ));
    let e = g.client.reload(false).await.unwrap_err();
    let ClientError::Refused { code, message, .. } = &e else {
        panic!("{e:?}");
    };
    assert_eq!(*code, pb::ErrorCode::InvalidRequest);
    let file = g.path.display().to_string();
    assert!(
        message.contains(&format!("{file}:")) && message.contains("unknown key `keep_dayz`"),
        "{message}"
    );
    assert!(
        message.contains("machines.m2.transport.line.baud = 12345"),
        "{message}"
    );
    assert_eq!(message.lines().count(), 2, "{message}");

    // A change to the bus endpoints with a machine added: nothing of it is applied.
    let other = free_port();
    std::fs::write(
        &g.path,
        cell_text(other, g.dir.path(), &format!("{M1}{M2}")),
    )
    .unwrap();
    let e = g.client.reload(false).await.unwrap_err();
    let ClientError::Refused { code, message, .. } = &e else {
        panic!("{e:?}");
    };
    assert_eq!(*code, pb::ErrorCode::RestartNeeded);
    assert!(
        message.contains("bus.listen") && message.contains("restart"),
        "{message}"
    );
    assert_eq!(g.machines().await, ["m1"]);

    // The gateway goes on with the cell it had: generation 1, m1 still takes jobs.
    let doc = g.admin().await;
    assert_eq!(doc["generation"], 1);
    assert_eq!(doc["reload"]["restart_needed"], true);
    let program = common::nc_program(300, 6);
    let (_, mut job) = g.client.submit("m1", &inline(&program)).await.unwrap();
    completed(&job.wait_end().await.unwrap());

    // Whoever asked is told, and so are the bus and the audit.
    for _ in 0..2 {
        let sample = published.recv_async().await.unwrap();
        let told = pb::ReloadResult::decode(sample.payload().to_bytes().as_ref()).unwrap();
        assert!(!told.applied && !told.errors.is_empty(), "{told:?}");
        assert_eq!(told.generation, 1);
    }
    let audits = g.reload_audits(2).await;
    assert!(audits.iter().all(|a| !a.ok), "{audits:?}");
    assert!(
        audits
            .iter()
            .any(|a| a.code == pb::ErrorCode::RestartNeeded as i32)
    );
    // A signal's reload is audited too, as the gateway's own.
    g.write(M1);
    let answer = g.reload.reload(false, "signal", None).await.unwrap();
    assert!(answer.result.applied, "{answer:?}");
    // The file the gateway runs: taken, nothing changed, so the generation stays.
    assert_eq!(answer.result.generation, 1);
    let audits = g.reload_audits(3).await;
    assert!(audits.iter().any(|a| a.ok && a.roles.is_empty()));
    g.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn plc_tags_change_in_the_running_link_and_settings_take_effect() {
    let plc = r#"
[[plcs]]
name = "plc-1"
mode = 1
transport = { kind = "sim" }

[[plcs.tags]]
name = "parts"
module = "D"
address = 0
type = "u16"
poll_ms = 100
"#;
    let g = Running::start(&format!("{M1}{plc}")).await;
    let station = g.keys.plc_station("plc-1", 0);
    wait_token(g.client.session(), &station, true).await;
    let stations = g
        .client
        .session()
        .liveliness()
        .declare_subscriber(station.as_str())
        .await
        .unwrap();
    let more = format!(
        "{plc}\n[[plcs.tags]]\nname = \"speed\"\nmodule = \"D\"\naddress = 5\ntype = \
         \"u16\"\npoll_ms = 100\nwritable = true\n"
    );
    g.write(&format!("{M1}{more}\n[history]\nkeep_days = 7\n"));
    let r = g.client.reload(false).await.unwrap();
    assert!(r.applied, "{r:?}");
    assert_eq!(r.plc_tags, ["plc-1"]);
    assert_eq!(r.settings, ["history.keep_days"]);
    assert!(r.plcs_changed.is_empty() && r.machines_changed.is_empty());
    // The new tag is read and written through the running link.
    let mut value = None;
    for _ in 0..100 {
        if let Ok(v) = g.client.tag_get("plc-1/speed").await {
            value = Some(v);
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(value.is_some(), "the new tag is never read");
    g.client.tag_set("plc-1/speed", 42.0).await.unwrap();
    assert_eq!(withdrawals(&stations), 0, "the PLC's station went down");
    assert_eq!(
        g.admin().await["config"]["history"]["keep_days"],
        7,
        "the admin document shows the running settings"
    );
    g.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_embedded_cell_has_no_file_to_reload() {
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let text = cell_text(port, dir.path(), M1);
    let config = cellgate_core::config::CellConfig::from_toml_str(&text, "in memory").unwrap();
    let (reload, reloads) = Reloads::new();
    let (ready, started) = tokio::sync::oneshot::channel();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let task = tokio::spawn(gateway::run_with(
        config,
        async {
            let _ = stopped.await;
        },
        RunOptions {
            ready: Some(ready),
            source: None,
            reloads: Some(reloads),
        },
    ));
    started.await.unwrap();
    let answer = reload.reload(false, "signal", None).await.unwrap();
    assert!(!answer.result.applied);
    assert_eq!(answer.code, pb::ErrorCode::NotSupported);
    assert!(
        answer.message().contains("embedded default cell") && answer.message().contains("--config"),
        "{answer:?}"
    );
    let _ = stop.send(());
    task.await.unwrap().unwrap();
}

/// The gateway's own MTConnect agent follows a reload: a machine added gets a device and a
/// DEVICE_ADDED, one removed leaves the documents with a DEVICE_REMOVED; nothing says a
/// device changed before.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_mtconnect_agent_follows_a_reload() {
    let http_port = free_port();
    let mtconnect = format!("[mtconnect]\nlisten = \"127.0.0.1:{http_port}\"\n");
    let m3 = M2.replace("\"m2\"", "\"m3\"");
    let g = Running::start(&format!("{mtconnect}{M1}{M2}")).await;
    let url = g.ready.mtconnect.clone().expect("the agent serves");
    let _ = tokio_rustls::rustls::crypto::ring::default_provider().install_default();
    let http = reqwest::Client::new();
    let get = |path: &'static str| {
        let (http, url) = (http.clone(), url.trim_end_matches('/').to_string());
        async move {
            http.get(format!("{url}{path}"))
                .send()
                .await
                .unwrap()
                .text()
                .await
                .unwrap()
        }
    };
    let until = |path: &'static str, what: &'static str, check: fn(&str) -> bool| async move {
        for _ in 0..100 {
            let doc = get(path).await;
            if check(&doc) {
                return doc;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        panic!("never: {what}");
    };
    let probe = until("/probe", "m1 and m2 modelled", |d| {
        d.contains("name=\"m1\"") && d.contains("name=\"m2\"")
    })
    .await;
    let uuid_of = |doc: &str, name: &str| {
        let at = doc.find(&format!("name=\"{name}\" uuid=\"")).unwrap();
        let rest = &doc[at + name.len() + 14..];
        rest[..rest.find('"').unwrap()].to_string()
    };
    let m2 = uuid_of(&probe, "m2");
    // The agent asked its gateway at start: the same cell, no change said.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let current = get("/current").await;
    assert!(
        current.contains("<DeviceChanged dataItemId=\"device_changed\"")
            && current.contains(">UNAVAILABLE</DeviceChanged>"),
        "{current}"
    );

    g.write(&format!("{mtconnect}{M1}{m3}"));
    let r = g.client.reload(false).await.unwrap();
    assert!(r.applied, "{r:?}");
    let probe = until("/probe", "m3 in, m2 out", |d| {
        d.contains("name=\"m3\"") && !d.contains("name=\"m2\"")
    })
    .await;
    let m3_uuid = uuid_of(&probe, "m3");
    let current = until("/current", "the agent device says what changed", |d| {
        d.contains("DeviceRemoved") && !d.contains(">UNAVAILABLE</DeviceAdded>")
    })
    .await;
    assert!(
        current.contains(&format!(">{m2}</DeviceRemoved>")),
        "{current}"
    );
    assert!(
        current.contains(&format!(">{m3_uuid}</DeviceAdded>")),
        "{current}"
    );
    assert!(!current.contains("m2_"), "m2 left the documents: {current}");
    // The new device is fed: its link comes up.
    until("/m3/current", "m3 available", |d| {
        d.contains(">AVAILABLE</Availability>")
    })
    .await;
    g.stop().await;
}
