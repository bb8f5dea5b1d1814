//! The cell on the bus with real links: a gateway session serving a simulated cell of eight
//! machines (Protocol A and Expansion A, each with its simulated board and CNC on a simulated
//! line), and a separate client session that drives it through the public contract only.
//! Real time (zenoh cannot run under paused time), loopback, multicast scouting off.

use crate::common;

use std::time::Duration;

use cellgate::bus::keys::MachineLeaf;
use cellgate_core::config::CellConfig;
use cellgate_core::fanuc::message::Command;
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;
use cellgate_core::sim::fanuc_board::BoardEvent;
use common::bus::{RunningCell, eventually, follow, get, get_err, get_one};
use prost::Message;
use sha2::{Digest, Sha256};

/// Machines of the test cell: (name, protocol, packet n).
const MACHINES: [(&str, &str, Option<u8>); 8] = [
    ("m1", "a", None),
    ("m2", "a", None),
    ("m3", "a", None),
    ("m4", "a", None),
    ("m5", "expansion-a", Some(1)),
    ("m6", "expansion-a", Some(2)),
    ("m7", "expansion-a", Some(4)),
    ("m8", "expansion-a", Some(1)),
];

fn cell_config(port: u16, dir: &std::path::Path) -> CellConfig {
    let mut text = format!(
        "cell = \"e2e\"\n[bus]\nlisten = [\"tcp/127.0.0.1:{port}\"]\n[programs]\ndir = {:?}\n",
        dir.join("programs")
    );
    for (name, protocol, n) in MACHINES {
        let n = n.map(|n| format!("packet_n = {n}\n")).unwrap_or_default();
        // Tp = 1 s so that the first SAT (and with it the CNC's autostart) comes quickly.
        text.push_str(&format!(
            "[[machines]]\nname = \"{name}\"\nprotocol = \"{protocol}\"\ntp = 1\ntw = 1\n{n}\
             transport = {{ kind = \"sim\", line = {{ baud = 86400 }} }}\n\
             sim = {{ consume_rate = 100000 }}\n"
        ));
    }
    CellConfig::from_toml_str(&text, "e2e cell").unwrap_or_else(|e| panic!("{e}"))
}

async fn start() -> RunningCell {
    RunningCell::start(cell_config, false).await
}

fn program(size: usize, seed: u32) -> Vec<u8> {
    common::nc_program(size, seed)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_jobs_on_every_machine_are_delivered_byte_exact() {
    let cell = start().await;
    let programs: Vec<Vec<u8>> = (0..MACHINES.len())
        .map(|i| program(12 * 1024 + 997 * i, i as u32 + 1))
        .collect();
    let runs = MACHINES.iter().zip(&programs).map(|((name, _, _), p)| {
        let cell = &cell;
        async move {
            let (job, events) = cell.submit(name, p).await;
            let seen = follow(&events, &job, Duration::from_secs(60)).await;
            (name, p, seen)
        }
    });
    for (name, p, seen) in futures::future::join_all(runs).await {
        match seen.last() {
            Some(Kind::Completed(c)) => assert_eq!(c.bytes_sent, p.len() as u64, "{name}"),
            other => panic!("{name}: job ended with {other:?}"),
        }
        assert!(
            seen.iter().any(|k| matches!(k, Kind::Progress(_))),
            "{name}: no progress event in {seen:?}"
        );
        let board = cell.board(name);
        let snap = board.wait_for(|s| !s.programs.is_empty()).await;
        assert_eq!(snap.programs.len(), 1, "{name}");
        assert_eq!(
            snap.programs[0].sha256,
            <[u8; 32]>::from(Sha256::digest(p)),
            "{name}: the CNC received other bytes"
        );
    }
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn routes_started_after_the_links_still_see_them_up() {
    // `RunningCell::start` waits for every machine's liveliness token: they must appear although the
    // links reported Ready before the routes subscribed to their events.
    let cell = RunningCell::start(cell_config, true).await;
    let status: pb::MachineStatus = get_one(
        &cell.client,
        &cell.keys.leaf("m3", MachineLeaf::Status),
        None,
    )
    .await;
    assert_eq!(status.link_state(), pb::LinkState::Idle);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_in_the_middle_ends_with_eod_then_clb() {
    let cell = start().await;
    let board = cell.board("m1");
    // 200 KiB at 86400 baud takes half a minute: long enough to cancel in the middle.
    let (job, events) = cell.submit("m1", &program(200 * 1024, 9)).await;
    let mut board_events = board.subscribe();
    // Wait for the transfer to be under way.
    tokio::time::timeout(Duration::from_secs(30), async {
        loop {
            let sample = events.recv_async().await.unwrap();
            let ev = pb::JobEvent::decode(sample.payload().to_bytes().as_ref()).unwrap();
            if ev.job_id == job && matches!(ev.kind, Some(Kind::Progress(_))) {
                return;
            }
        }
    })
    .await
    .expect("the job made progress");
    cell.client
        .delete(cell.keys.job_events("m1", &job))
        .await
        .unwrap();
    let seen = follow(&events, &job, Duration::from_secs(30)).await;
    let Some(Kind::Cancelled(c)) = seen.last() else {
        panic!("job ended with {seen:?}");
    };
    assert!(c.byte_offset > 0 && c.byte_offset < 200 * 1024, "{c:?}");
    // Protocol A: the next GTD gets EOD, the next SAT gets CLB (buffer clear).
    let order = tokio::time::timeout(Duration::from_secs(30), async {
        let mut order = Vec::new();
        loop {
            match board_events.recv().await {
                Ok(BoardEvent::MessageReceived(c @ (Command::Eod | Command::Clb))) => {
                    order.push(c);
                    if c == Command::Clb {
                        return order;
                    }
                }
                Ok(_) => {}
                Err(e) => panic!("board events: {e}"),
            }
        }
    })
    .await
    .expect("the board saw EOD and CLB");
    assert_eq!(order.first(), Some(&Command::Eod), "{order:?}");
    assert!(
        board.programs().is_empty(),
        "a cancelled program was completed"
    );
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn do_di_alarm_and_status_through_the_bus() {
    let cell = start().await;
    let board = cell.board("m5");

    let command = pb::DoCommand {
        value: 0x5A,
        mask: None,
    };
    cell.client
        .put(
            cell.keys.leaf("m5", MachineLeaf::Do),
            command.encode_to_vec(),
        )
        .await
        .unwrap();
    eventually("the DO image reaches the simulated board", || {
        board.do_image() == 0x5A
    })
    .await;

    board.set_di(0x81);
    let di: pb::DiImage = get_one(&cell.client, &cell.keys.leaf("m5", MachineLeaf::Di), None).await;
    assert_eq!(di.value, 0x81);

    let alarms = cell
        .client
        .declare_subscriber(cell.keys.leaf("m5", MachineLeaf::Alarm))
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(200)).await;
    board.raise_alarm();
    let alarm = tokio::time::timeout(Duration::from_secs(10), alarms.recv_async())
        .await
        .expect("an alarm event")
        .unwrap();
    let alarm = pb::AlarmEvent::decode(alarm.payload().to_bytes().as_ref()).unwrap();
    assert_eq!(alarm.kind(), pb::AlarmKind::CncAlarm);
    assert_eq!(alarm.machine, "m5");

    let status: pb::MachineStatus = get_one(
        &cell.client,
        &cell.keys.leaf("m5", MachineLeaf::Status),
        None,
    )
    .await;
    assert_eq!(status.machine, "m5");
    assert_eq!(status.protocol(), pb::Protocol::ExpansionA);
    assert_eq!(status.do_image, Some(0x5A));
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_get_an_error_reply_and_nothing_is_queued() {
    let cell = start().await;
    let job_key = cell.keys.leaf("m2", MachineLeaf::Submit);
    let bad = |bytes: &[u8]| {
        pb::JobRequest {
            program: Some(pb::job_request::Program::Inline(bytes.to_vec())),
            name: String::new(),
            priority: 0,
            append_eor: false,
            ..Default::default()
        }
        .encode_to_vec()
    };
    let cases: [(&str, Vec<u8>); 4] = [
        ("empty program", bad(b"")),
        ("missing EOR", bad(b"%\nO1\nG01 X1\n")),
        ("end code in the data", bad(b"%\nO1\r\nG01 X1\n%")),
        ("not 7-bit", bad(b"%\nO1\nG01 X\xB5\n%")),
    ];
    for (what, request) in cases {
        let err = get_err(&cell.client, &job_key, Some(request)).await;
        assert!(!err.message.is_empty(), "{what}: {err:?}");
    }
    let unknown = get_err(
        &cell.client,
        &cell.keys.leaf("no-such-machine", MachineLeaf::Submit),
        Some(bad(b"%\nO1\n%")),
    )
    .await;
    assert!(unknown.message.contains("no-such-machine"), "{unknown:?}");
    // Nothing was queued: the queue is empty and the CNC received nothing.
    let replies = get(&cell.client, &cell.keys.leaf("m2", MachineLeaf::Job), None).await;
    let queue = match replies.as_slice() {
        [Ok((_, bytes, _))] => pb::JobQueue::decode(bytes.as_slice()).unwrap(),
        other => panic!("queue get: {other:?}"),
    };
    assert!(
        queue.active.is_none() && queue.waiting.is_empty(),
        "{queue:?}"
    );
    assert!(cell.board("m2").programs().is_empty());
    cell.stop().await;
}

/// A CNC alarm is one fact on every surface: a SAT showing the remote buffer in alarm status
/// (§4.4.2 1) is the CNC's alarm (kind, code), not a link alarm, and is not counted as one;
/// a Protocol B NAK's alarm (§6.4) stays until a reset, though the link goes idle after it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cnc_alarm_is_the_cncs_whichever_message_reports_it_and_stays_until_a_reset() {
    fn config(port: u16, dir: &std::path::Path) -> CellConfig {
        let text = format!(
            "cell = \"alarms\"\n[bus]\nlisten = [\"tcp/127.0.0.1:{port}\"]\n[programs]\n\
             dir = {:?}\n\
             [[machines]]\nname = \"a1\"\nprotocol = \"expansion-a\"\ntp = 1\ntw = 1\n\
             transport = {{ kind = \"sim\", line = {{ baud = 86400 }} }}\n\
             [[machines]]\nname = \"b1\"\nprotocol = \"b\"\nnotify_alarm_reset = true\n\
             transport = {{ kind = \"sim\", line = {{ baud = 19200 }} }}\n",
            dir.join("programs")
        );
        CellConfig::from_toml_str(&text, "alarm cell").unwrap_or_else(|e| panic!("{e}"))
    }
    let cell = RunningCell::start(config, false).await;
    let status = |m: &'static str| {
        let (client, key) = (cell.client.clone(), cell.keys.leaf(m, MachineLeaf::Status));
        async move { get_one::<pb::MachineStatus>(&client, &key, None).await }
    };
    // Expansion A: the board's next SATs show alarm status, cause NC alarm.
    cell.board("a1").raise_alarm();
    let mut s = status("a1").await;
    for _ in 0..100 {
        if s.last_alarm.as_ref().is_some_and(|a| a.code == "CG-SAT-NC") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
        s = status("a1").await;
    }
    let a = s.last_alarm.clone().expect("an alarm");
    assert_eq!(a.code, "CG-SAT-NC", "{a:?}");
    assert_eq!(a.kind(), pb::AlarmKind::CncAlarm, "{a:?}");
    assert_eq!(s.link_state(), pb::LinkState::Alarm);
    assert_eq!(
        s.counters.as_ref().map_or(0, |c| c.link_alarms),
        0,
        "a CNC alarm is no link alarm"
    );
    // Protocol B: the NAK's alarm stays while the link idles, until the CNC is reset (the
    // simulated operator resets nothing by himself here).
    cell.board("b1")
        .command(cellgate_core::sim::fanuc_board::BoardCommand::SetAutostart(
            false,
        ));
    cell.board("b1").raise_alarm();
    let mut s = status("b1").await;
    for _ in 0..100 {
        if s.last_alarm.as_ref().is_some_and(|a| a.code == "CG-NAK") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        s = status("b1").await;
    }
    assert_eq!(
        s.last_alarm.as_ref().map(|a| a.code.as_str()),
        Some("CG-NAK")
    );
    tokio::time::sleep(Duration::from_secs(2)).await;
    let s = status("b1").await;
    assert_eq!(s.link_state(), pb::LinkState::Alarm, "{s:?}");
    cell.board("b1").reset();
    let mut s = status("b1").await;
    for _ in 0..100 {
        if s.link_state() != pb::LinkState::Alarm {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        s = status("b1").await;
    }
    assert_ne!(s.link_state(), pb::LinkState::Alarm, "{s:?}");
    cell.stop().await;
}
