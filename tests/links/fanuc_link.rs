//! A host link against the simulated remote-buffer board, end to end over the simulated line,
//! in virtual time: cell file → transports → Protocol A / Expansion A engines → board and CNC.

use crate::common;

use std::time::Duration;

use cellgate::link::driver::{LinkCommand, LinkEvent};
use cellgate::transport::sim::Dir;
use cellgate_core::fanuc::alarm::CncAlarm;
use cellgate_core::fanuc::sat::AlarmCause;
use common::*;
use sha2::{Digest, Sha256};

const HOUR: Duration = Duration::from_secs(3600);

/// Sends a 1 MiB program and checks that the CNC received it byte-exact.
async fn one_mib(protocol: &str, packet_n: Option<u8>, baud: u32) {
    let config = sim_cell(protocol, packet_n, baud, 1_000_000);
    let (cell, token) = start(&config).await;
    let m = cell.machine("m1").unwrap();
    let mut events = m.link.subscribe();
    let program = nc_program(1 << 20, 7);
    assert!(program.len() > 1_000_000);
    queue(&m.link, 1, program.clone()).await;
    // The block being fed, with each progress event: the last line that ends within the
    // acknowledged bytes.
    let mut blocks = 0;
    let bytes = next_event(&mut events, HOUR, |ev| match ev {
        LinkEvent::JobDone { job: 1, bytes, .. } => Some(*bytes),
        LinkEvent::JobFailed { job: 1, reason, .. } => panic!("job failed: {reason}"),
        LinkEvent::Progress {
            job: 1,
            acked,
            block: Some(block),
            ..
        } => {
            let acked = usize::try_from(*acked).unwrap();
            let upto = program.get(..acked).unwrap();
            let end = upto.iter().rposition(|b| *b == b'\n').unwrap();
            let start = upto.get(..end).unwrap().iter().rposition(|b| *b == b'\n');
            let line = &upto[start.map_or(0, |s| s + 1)..end];
            assert_eq!(block.as_bytes(), line, "at {acked}");
            blocks += 1;
            None
        }
        _ => None,
    })
    .await;
    // Protocol A acknowledges at each exchange after DATs (§4.4.1); Expansion A a run of
    // packets at its end packet, so its block moves with the runs.
    let least = if protocol == "a" { 50 } else { 1 };
    assert!(blocks >= least, "{blocks} progress events named a block");
    assert_eq!(bytes, program.len() as u64);
    let board = m.board.as_ref().unwrap();
    let snap = board.wait_for(|s| !s.programs.is_empty()).await;
    let got = &snap.programs[0];
    assert_eq!(got.len, program.len() as u64);
    assert_eq!(got.sha256, <[u8; 32]>::from(Sha256::digest(&program)));
    assert_eq!(got.first_line, "O0007");
    assert!(snap.alarms.is_empty(), "{:?}", snap.alarms);
    token.cancel();
    cell.join().await;
}

#[tokio::test(start_paused = true)]
async fn one_mib_protocol_a_86400() {
    one_mib("a", None, 86_400).await;
}

#[tokio::test(start_paused = true)]
async fn one_mib_expansion_a_n1_86400() {
    one_mib("expansion-a", Some(1), 86_400).await;
}

#[tokio::test(start_paused = true)]
async fn one_mib_expansion_a_n2_86400() {
    one_mib("expansion-a", Some(2), 86_400).await;
}

#[tokio::test(start_paused = true)]
async fn one_mib_expansion_a_n4_86400() {
    one_mib("expansion-a", Some(4), 86_400).await;
}

async fn wait_ready(events: &mut cellgate::link::fanout::Receiver<LinkEvent>) {
    next_event(events, HOUR, |ev| {
        matches!(
            ev,
            LinkEvent::State {
                state: cellgate_core::fanuc::host::LinkState::Ready
            }
        )
        .then_some(())
    })
    .await;
}

#[tokio::test(start_paused = true)]
async fn do_and_di_round_trip() {
    let config = sim_cell("a", None, 19_200, 2000);
    let (cell, token) = start(&config).await;
    let m = cell.machine("m1").unwrap();
    let board = m.board.as_ref().unwrap();
    let mut events = m.link.subscribe();
    wait_ready(&mut events).await;

    m.link
        .send(LinkCommand::SetDo {
            value: 0xA5,
            mask: 0xFF,
            asked: std::time::SystemTime::now(),
        })
        .await
        .unwrap();
    next_event(&mut events, HOUR, |ev| {
        matches!(ev, LinkEvent::Do { value: 0xA5 }).then_some(())
    })
    .await;
    board.wait_for(|s| s.do_image == 0xA5).await;
    // A masked write changes only the selected bits of the last image.
    m.link
        .send(LinkCommand::SetDo {
            value: 0x00,
            mask: 0x0F,
            asked: std::time::SystemTime::now(),
        })
        .await
        .unwrap();
    board.wait_for(|s| s.do_image == 0xA0).await;

    board.set_di(0x3C);
    m.link.send(LinkCommand::ReadDi).await.unwrap();
    let di = next_event(&mut events, HOUR, |ev| match ev {
        LinkEvent::Di { value } => Some(*value),
        _ => None,
    })
    .await;
    assert_eq!(di, 0x3C);
    token.cancel();
    cell.join().await;
}

#[tokio::test(start_paused = true)]
async fn cnc_alarm_and_reset_come_out_as_events() {
    let config = sim_cell("a", None, 19_200, 2000);
    let (cell, token) = start(&config).await;
    let m = cell.machine("m1").unwrap();
    let board = m.board.as_ref().unwrap();
    let mut events = m.link.subscribe();
    wait_ready(&mut events).await;
    board.raise_alarm();
    next_event(&mut events, HOUR, |ev| {
        matches!(ev, LinkEvent::CncAlarm).then_some(())
    })
    .await;
    board.reset();
    next_event(&mut events, HOUR, |ev| {
        matches!(ev, LinkEvent::CncReset).then_some(())
    })
    .await;
    token.cancel();
    cell.join().await;
}

/// Single corrupted characters host → board during a transfer: the board asks again (RTY,
/// Protocol A; NAK, Expansion A) and the program still arrives byte-exact.
async fn recovers_from_corruption(protocol: &str, packet_n: Option<u8>) {
    let config = sim_cell(protocol, packet_n, 19_200, 1_000_000);
    let (cell, token) = start(&config).await;
    let m = cell.machine("m1").unwrap();
    let line = m.line.as_ref().unwrap();
    let mut events = m.link.subscribe();
    let program = nc_program(64 * 1024, 3);
    queue(&m.link, 1, program.clone()).await;
    // Corrupt one character whenever the transfer has made progress, five times over. The
    // next one waits until the last one hit a byte and the transfer moved on twice, so that no
    // frame takes two hits, which could cancel in the 8-bit sum.
    let mut corrupted = 0;
    let mut moved_since = 2;
    let done = loop {
        match events.recv().await.unwrap() {
            LinkEvent::Progress { .. } if corrupted < 5 => {
                if line.counters(Dir::HostToDevice).corrupted == corrupted {
                    moved_since += 1;
                }
                if moved_since > 2 {
                    line.corrupt_next(Dir::HostToDevice, 0x04);
                    corrupted += 1;
                    moved_since = 0;
                }
            }
            LinkEvent::JobDone { job: 1, bytes, .. } => break bytes,
            LinkEvent::JobFailed { reason, .. } => panic!("job failed: {reason}"),
            _ => {}
        }
    };
    assert_eq!(done, program.len() as u64);
    assert!(line.counters(Dir::HostToDevice).corrupted >= 5);
    let board = m.board.as_ref().unwrap();
    let snap = board.wait_for(|s| !s.programs.is_empty()).await;
    assert_eq!(
        snap.programs[0].sha256,
        <[u8; 32]>::from(Sha256::digest(&program))
    );
    assert!(snap.alarms.is_empty(), "{:?}", snap.alarms);
    token.cancel();
    cell.join().await;
}

#[tokio::test(start_paused = true)]
async fn checksum_faults_are_recovered_by_rty() {
    recovers_from_corruption("a", None).await;
}

#[tokio::test(start_paused = true)]
async fn packet_faults_are_recovered_by_nak() {
    recovers_from_corruption("expansion-a", Some(1)).await;
}

#[tokio::test(start_paused = true)]
async fn retry_over_raises_alarm_cause_1_and_sr0945() {
    let config = sim_cell("a", None, 19_200, 2000);
    let (cell, token) = start(&config).await;
    let m = cell.machine("m1").unwrap();
    let line = m.line.as_ref().unwrap();
    let board = m.board.as_ref().unwrap();
    let mut events = m.link.subscribe();
    wait_ready(&mut events).await;
    // Every answer the host sends arrives with one corrupted character until the board gives
    // up: Ne = 10 retries (§4.5), then a reception error with alarm cause 1 (§4.4.2, §4.6 2 (1)).
    // One character is armed each time the board sends SAT or RTY, so the host's answer to it
    // is what gets corrupted.
    use cellgate_core::fanuc::message::Command;
    use cellgate_core::sim::fanuc_board::BoardEvent;
    let mut board_events = board.subscribe();
    let watch = async {
        loop {
            match board_events.recv().await {
                Ok(BoardEvent::MessageSent(Command::Sat | Command::Rty)) => {
                    line.corrupt_next(Dir::HostToDevice, 0x01);
                }
                Ok(BoardEvent::Alarm { alarm, cause, .. }) => return (alarm, cause),
                Ok(_) => {}
                Err(e) => panic!("board events: {e}"),
            }
        }
    };
    let (alarm, cause) = tokio::time::timeout(HOUR, watch)
        .await
        .expect("the board gives up within the hour");
    assert_eq!(alarm, CncAlarm::Sr0945RetryOver);
    assert_eq!(cause, AlarmCause::ChecksumRetryOver);
    // With the line clean again, the host reads the alarm from the next SAT and reports it.
    let reported = next_event(&mut events, HOUR, |ev| match ev {
        LinkEvent::Alarm(a) => a.cnc_alarm(),
        _ => None,
    })
    .await;
    assert_eq!(reported, CncAlarm::Sr0945RetryOver);
    token.cancel();
    cell.join().await;
}
