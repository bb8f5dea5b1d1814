//! Nothing queued is lost by a restart: a `cellgate run` process with one job being sent and
//! five waiting is stopped (SIGTERM, and `kill -9`), a new one starts on the same cell file,
//! and the five run with their ids in their order, the one that was being sent is reported
//! failed at the offset the board acknowledged, and a submit repeated with its request id
//! queues nothing.

use crate::common;

use std::path::Path;
use std::process::{Child, Stdio};
use std::time::Duration;

use cellgate::client::{Client, ConnectOptions};
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;
use common::bus::free_port;
use common::nc_program;

const MILL: &str = "mill-1";

/// One Protocol A machine on a simulated line at 4800 baud: an 8 KB program takes long
/// enough to stop the gateway in its middle.
fn cell_file(dir: &Path, port: u16) -> std::path::PathBuf {
    let text = format!(
        r#"
cell = "restart"

[bus]
listen = ["tcp/127.0.0.1:{port}"]

[programs]
dir = "{programs}"

[[machines]]
name = "{MILL}"
protocol = "a"
tp = 1
tw = 1

[machines.transport]
kind = "sim"
line = {{ baud = 4800 }}
"#,
        programs = dir.join("programs").display()
    );
    let path = dir.join("cell.toml");
    std::fs::write(&path, text).unwrap();
    path
}

fn start(config: &Path) -> Child {
    common::cli::bin()
        .args(["run", "--config"])
        .arg(config)
        .env("RUST_LOG", "warn")
        .env_remove("OTEL_EXPORTER_OTLP_ENDPOINT")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

async fn connect(port: u16) -> Client {
    let options = ConnectOptions {
        endpoint: format!("tcp/127.0.0.1:{port}"),
        prefix: "cellgate".to_string(),
        cell: Some("restart".to_string()),
        timeout: Duration::from_secs(10),
        ..ConnectOptions::default()
    };
    for _ in 0..120 {
        if let Ok(client) = Client::connect(&options).await {
            return client;
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    panic!("the gateway on port {port} never answered");
}

fn request(program: Vec<u8>, request_id: &str) -> pb::JobRequest {
    pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(program)),
        request_id: request_id.to_string(),
        ..Default::default()
    }
}

fn stop(child: &mut Child, signal: libc::c_int) {
    // SAFETY: kill(2) on the pid of a child this process spawned and has not reaped.
    unsafe {
        libc::kill(child.id() as libc::pid_t, signal);
    }
    for _ in 0..200 {
        if matches!(child.try_wait(), Ok(Some(_))) {
            return;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = child.kill();
    let _ = child.wait();
}

async fn restart_keeps_the_queue(signal: libc::c_int) {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let config = cell_file(dir.path(), port);
    let mut gateway = start(&config);
    let client = connect(port).await;

    let (first, mut follower) = client
        .submit(MILL, &request(nc_program(8 * 1024, 1), "req-1"))
        .await
        .unwrap();
    let mut waiting = Vec::new();
    for i in 2..=6 {
        let (accepted, _) = client
            .submit(MILL, &request(nc_program(300, i), &format!("req-{i}")))
            .await
            .unwrap();
        waiting.push(accepted.job_id);
    }
    // Stop once the board has acknowledged part of the first program.
    loop {
        let e = tokio::time::timeout(Duration::from_secs(60), follower.next())
            .await
            .expect("the first job never made progress")
            .unwrap()
            .unwrap();
        if matches!(e.kind, Some(Kind::Progress(p)) if p.bytes_sent > 0) {
            break;
        }
    }
    follower.close().await;
    client.close().await;
    stop(&mut gateway, signal);

    let mut gateway = start(&config);
    let client = connect(port).await;
    // The job that was being sent: failed at what the board acknowledged.
    let latest = client.job_latest(MILL, &first.job_id).await.unwrap();
    match latest.kind {
        Some(Kind::Failed(f)) => {
            assert!(f.reason.contains("gateway restarted"), "{}", f.reason);
            assert!(f.byte_offset > 0, "acknowledged offset {}", f.byte_offset);
            assert!(f.byte_offset < 8 * 1024);
            assert!(f.next_block.is_some());
        }
        other => panic!("the active job after the restart: {other:?}"),
    }
    // A retried submit of a waiting job queues nothing and answers its id.
    let (again, _) = client
        .submit(MILL, &request(nc_program(300, 2), "req-2"))
        .await
        .unwrap();
    assert_eq!(again.job_id, waiting[0]);
    // The five run, with their ids, in their order.
    let mut completed_at = Vec::new();
    for id in &waiting {
        let mut follower = client.follow(MILL, id).await.unwrap();
        let end = tokio::time::timeout(Duration::from_secs(120), follower.wait_end())
            .await
            .expect("a waiting job never ended")
            .unwrap();
        follower.close().await;
        match end.kind {
            Some(Kind::Completed(_)) => completed_at.push(end.unix_ms),
            other => panic!("job {id}: {other:?}"),
        }
    }
    assert!(
        completed_at.windows(2).all(|w| w[0] < w[1]),
        "completed out of order: {completed_at:?}"
    );
    let queue = client.queue(MILL).await.unwrap();
    assert!(
        queue.active.is_none() && queue.waiting.is_empty(),
        "{queue:?}"
    );
    client.close().await;
    stop(&mut gateway, libc::SIGTERM);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_then_restart_keeps_the_queue() {
    restart_keeps_the_queue(libc::SIGTERM).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_then_restart_keeps_the_queue() {
    restart_keeps_the_queue(libc::SIGKILL).await;
}

/// A write the gateway answered is in the audit trail after a `kill -9` straight after the
/// answer: the answer waits for its record to be committed (the rest of the history may lose
/// its last second).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_straight_after_the_answers_keeps_their_audit_records() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let config = cell_file(dir.path(), port);
    let mut gateway = start(&config);
    let client = connect(port).await;
    let mut accepted = Vec::new();
    for i in 1..=5 {
        let (a, follower) = client
            .submit(MILL, &request(nc_program(300, i), &format!("audited-{i}")))
            .await
            .unwrap();
        follower.close().await;
        accepted.push(a.job_id);
    }
    let stored = client
        .program_put("O77", b"%\nO77\nG00X0\nM30\n%")
        .await
        .unwrap();
    client.close().await;
    stop(&mut gateway, libc::SIGKILL);

    let mut gateway = start(&config);
    let client = connect(port).await;
    let page = client.history(true, &[]).await.unwrap();
    let audited: Vec<(String, String)> = page
        .records
        .iter()
        .filter_map(|r| match &r.record {
            Some(pb::history_record::Record::Audit(a)) if a.ok => {
                Some((a.action.clone(), a.target.clone()))
            }
            _ => None,
        })
        .collect();
    for id in &accepted {
        assert!(
            audited.contains(&("job.submit".to_string(), id.clone())),
            "the submit of {id} is not in the audit trail: {audited:?}"
        );
    }
    assert!(
        audited
            .iter()
            .any(|(action, target)| action == "program.store" && *target == stored.name),
        "the store of {} is not in the audit trail: {audited:?}",
        stored.name
    );
    client.close().await;
    stop(&mut gateway, libc::SIGTERM);
}
