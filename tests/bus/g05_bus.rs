//! G05 streams through the bus contract, in real time on loopback: open, batches by put and by
//! get, status, refusals as `ErrorReply`s, and a producer whose liveliness token goes away.

use crate::common;

use std::time::Duration;

use cellgate::bus::keys::{G05Part, MachineLeaf};
use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use cellgate_core::sim::cnc::G05End;
use common::bus::{RunningCell, get_err, get_one};
use prost::Message;

fn cell_config(port: u16, dir: &std::path::Path) -> CellConfig {
    let text = format!(
        r#"
cell = "g05bus"
[bus]
listen = ["tcp/127.0.0.1:{port}"]
[programs]
dir = {:?}
[[machines]]
name = "b1"
protocol = "b"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
[machines.g05]
axes = 3
idle_ms = 1000
[[machines]]
name = "plain"
protocol = "b"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
"#,
        dir.join("programs")
    );
    CellConfig::from_toml_str(&text, "g05 bus cell").unwrap_or_else(|e| panic!("{e}"))
}

fn blocks(n: usize) -> Vec<pb::G05Block> {
    (0..n)
        .map(|i| pb::G05Block {
            travel: vec![3, -2, (i % 5) as i32],
            aux: None,
        })
        .collect()
}

async fn open(cell: &RunningCell, machine: &str, id: &str, token: bool) -> pb::G05Opened {
    let request = pb::G05Open {
        stream_id: id.to_string(),
        producer_token: token,
    };
    get_one(
        &cell.client,
        &cell.keys.leaf(machine, MachineLeaf::G05),
        Some(request.encode_to_vec()),
    )
    .await
}

async fn last_status(sub: &common::bus::Sub) -> pb::G05Status {
    tokio::time::timeout(Duration::from_secs(60), async {
        loop {
            let s = sub.recv_async().await.unwrap();
            let st = pb::G05Status::decode(s.payload().to_bytes().as_ref()).unwrap();
            if st.state() == pb::G05State::Completed || st.state() == pb::G05State::Failed {
                return st;
            }
        }
    })
    .await
    .expect("the stream never ended")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_through_the_contract() {
    let cell = RunningCell::start(cell_config, false).await;
    let opened = open(&cell, "b1", "s1", false).await;
    assert_eq!(
        (opened.stream_id.as_str(), opened.axes, opened.block_len),
        ("s1", 3, 7)
    );
    assert_eq!(opened.required_baud, 9625);
    let status_key = cell.keys.g05("b1", "s1", G05Part::Status);
    let sub = cell.subscribe(status_key.clone()).await;
    let blocks_key = cell.keys.g05("b1", "s1", G05Part::Blocks);

    // One stream at a time; a machine without G05; a bad batch by get.
    let busy = get_err(
        &cell.client,
        &cell.keys.leaf("b1", MachineLeaf::G05),
        Some(pb::G05Open::default().encode_to_vec()),
    )
    .await;
    assert_eq!(busy.code(), pb::ErrorCode::Busy, "{}", busy.message);
    let none = get_err(
        &cell.client,
        &cell.keys.leaf("plain", MachineLeaf::G05),
        Some(pb::G05Open::default().encode_to_vec()),
    )
    .await;
    assert_eq!(none.code(), pb::ErrorCode::NotSupported, "{}", none.message);
    let far = pb::G05Batch {
        seq: 0,
        blocks: vec![pb::G05Block {
            travel: vec![1, 20_000, 0],
            aux: None,
        }],
        end: false,
    };
    let e = get_err(&cell.client, &blocks_key, Some(far.encode_to_vec())).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);
    assert!(
        e.message.contains("20000") && e.message.contains("axis 2"),
        "{}",
        e.message
    );

    // Batches by get (answered with the status) and by put.
    let first = pb::G05Batch {
        seq: 0,
        blocks: blocks(300),
        end: false,
    };
    let st: pb::G05Status = get_one(&cell.client, &blocks_key, Some(first.encode_to_vec())).await;
    assert_eq!((st.received, st.next_seq, st.refused), (300, 1, 1));
    for seq in 1..4 {
        let b = pb::G05Batch {
            seq,
            blocks: blocks(200),
            end: seq == 3,
        };
        cell.client
            .put(blocks_key.as_str(), b.encode_to_vec())
            .await
            .unwrap();
    }
    let last = last_status(&sub).await;
    assert_eq!(last.state(), pb::G05State::Completed, "{last:?}");
    assert_eq!(last.end_reason(), pb::G05EndReason::Producer);
    assert_eq!(last.received, 900);
    let g = cell
        .board("b1")
        .wait_for(|s| s.g05.as_ref().is_some_and(|g| g.end.is_some()))
        .await
        .g05
        .unwrap();
    assert_eq!((g.blocks, g.end), (900, Some(G05End::EndBlock)));
    assert_eq!(g.travel, [2700, -1800, 900 / 5 * (1 + 2 + 3 + 4)]);

    // The last status still answers a get; the machine status shows it.
    let again: pb::G05Status = get_one(&cell.client, &status_key, None).await;
    assert_eq!(again.state(), pb::G05State::Completed);
    let ms: pb::MachineStatus = get_one(
        &cell.client,
        &cell.keys.leaf("b1", MachineLeaf::Status),
        None,
    )
    .await;
    let g = ms.g05.unwrap();
    assert_eq!(g.stream_id, "s1");
    // Over: nothing is estimated in the CNC's buffer any more (it was left as it stood).
    assert_eq!(g.cnc_buffer, 0, "{g:?}");
    assert_eq!(last.cnc_buffer, 0, "{last:?}");
    // The history keeps the stream's last status.
    let mut kept = None;
    for _ in 0..50 {
        let page: pb::HistoryPage = get_one(
            &cell.client,
            &format!("{}?kind=g05", cell.keys.history()),
            None,
        )
        .await;
        kept = page.records.into_iter().find_map(|r| match r.record {
            Some(pb::history_record::Record::G05(g)) => Some((r.machine, g)),
            _ => None,
        });
        if kept.is_some() {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    let (machine, g) = kept.expect("the stream is in the history");
    assert_eq!(machine, "b1");
    assert_eq!((g.stream_id.as_str(), g.received), ("s1", 900));
    assert_eq!(g.state(), pb::G05State::Completed);
    cell.stop().await;
}

/// The producer's liveliness token goes away mid-stream: the gateway ends binary mode with the
/// end block and says why.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_producer_that_goes_away_ends_the_stream_cleanly() {
    let cell = RunningCell::start(cell_config, false).await;
    open(&cell, "b1", "lost", true).await;
    let token = cell
        .client
        .liveliness()
        .declare_token(cell.keys.g05("b1", "lost", G05Part::Producer))
        .await
        .unwrap();
    let sub = cell
        .subscribe(cell.keys.g05("b1", "lost", G05Part::Status))
        .await;
    let blocks_key = cell.keys.g05("b1", "lost", G05Part::Blocks);
    for seq in 0..3 {
        let b = pb::G05Batch {
            seq,
            blocks: blocks(250),
            end: false,
        };
        let st: pb::G05Status = get_one(&cell.client, &blocks_key, Some(b.encode_to_vec())).await;
        assert_eq!(st.next_seq, seq + 1);
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    token.undeclare().await.unwrap();
    let last = last_status(&sub).await;
    assert_eq!(
        last.end_reason(),
        pb::G05EndReason::ProducerLost,
        "{last:?}"
    );
    assert_eq!(last.state(), pb::G05State::Completed, "{last:?}");
    let g = cell
        .board("b1")
        .wait_for(|s| s.g05.as_ref().is_some_and(|g| g.end.is_some()))
        .await
        .g05
        .unwrap();
    assert_eq!((g.blocks, g.end), (750, Some(G05End::EndBlock)));
    cell.stop().await;
}

/// A producer that sends one batch and falls silent: the CNC runs dry, which raises an
/// `AlarmEvent` (kind G05) saying the stream starves it, and after `idle_ms` the stream ends
/// with `PRODUCER_IDLE`, which raises another. Both are the machine's alarms, not only fields
/// of the stream's status.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn starvation_and_an_idle_end_raise_alarm_events() {
    let cell = RunningCell::start(cell_config, false).await;
    let alarms = cell
        .subscribe(cell.keys.leaf("b1", MachineLeaf::Alarm))
        .await;
    open(&cell, "b1", "dry", false).await;
    let sub = cell
        .subscribe(cell.keys.g05("b1", "dry", G05Part::Status))
        .await;
    let blocks_key = cell.keys.g05("b1", "dry", G05Part::Blocks);
    let b = pb::G05Batch {
        seq: 0,
        blocks: blocks(300),
        end: false,
    };
    let st: pb::G05Status = get_one(&cell.client, &blocks_key, Some(b.encode_to_vec())).await;
    assert_eq!(st.received, 300);
    let last = last_status(&sub).await;
    assert_eq!(
        last.end_reason(),
        pb::G05EndReason::ProducerIdle,
        "{last:?}"
    );
    assert!(last.underruns > 0, "{last:?}");
    let mut seen = Vec::new();
    let got = tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            let s = alarms.recv_async().await.unwrap();
            let a = pb::AlarmEvent::decode(s.payload().to_bytes().as_ref()).unwrap();
            if a.kind() == pb::AlarmKind::G05 {
                seen.push(a.message.clone());
            }
            if seen.iter().any(|m| m.contains("starving"))
                && seen.iter().any(|m| m.contains("ended"))
            {
                return;
            }
        }
    })
    .await;
    assert!(got.is_ok(), "G05 alarms seen: {seen:?}");
    assert!(
        seen[0].contains("starving") && seen[0].contains("stream dry"),
        "{seen:?}"
    );
    let ms: pb::MachineStatus = get_one(
        &cell.client,
        &cell.keys.leaf("b1", MachineLeaf::Status),
        None,
    )
    .await;
    let last_alarm = ms.last_alarm.expect("the machine's last alarm");
    assert_eq!(last_alarm.kind(), pb::AlarmKind::G05);
    cell.stop().await;
}
