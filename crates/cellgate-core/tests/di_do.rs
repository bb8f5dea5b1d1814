//! DI and DO on Protocol A (§4.4.1; protocol notes 6), the host engine against the simulated
//! board in plain time: RDI and SDO answer SAT or GTD in any order, as fast as a client asks,
//! and neither end ever waits for the other.

use std::time::{Duration, Instant};

use cellgate_core::engine::LineSettings;
use cellgate_core::fanuc::Protocol;
use cellgate_core::fanuc::host::{EngineCommand, EngineEvent, LinkState};
use cellgate_core::fanuc::message::Framing;
use cellgate_core::fanuc::protocol_a::{ProtocolAConfig, ProtocolAHost};
use cellgate_core::fanuc::sat::Params;
use cellgate_core::fanuc::{CodeSystem, EndCode};
use cellgate_core::sim::{BoardConfig, BoardEvent, FanucBoard};
use cellgate_core::testkit::Pair;

fn pair(autostart: bool) -> Pair<ProtocolAHost, FanucBoard> {
    let now = Instant::now();
    let line = LineSettings::with_baud(19200);
    let framing = Framing::new(CodeSystem::Iso, EndCode::Cr);
    let host = ProtocolAHost::new(
        ProtocolAConfig::for_link(framing, Params::POWER_ON, 0, line.char_time()),
        now,
    )
    .unwrap();
    let board = FanucBoard::new(
        BoardConfig {
            protocol: Protocol::A,
            framing,
            autostart,
            first_request_delay: Duration::from_millis(100),
            ..BoardConfig::default()
        },
        now,
    )
    .unwrap();
    let mut p = Pair::new(host, board, line, now);
    p.run_for(Duration::from_secs(5));
    p
}

fn alarms(p: &mut Pair<ProtocolAHost, FanucBoard>) -> Vec<String> {
    let mut out: Vec<String> = p
        .take_a_events()
        .into_iter()
        .filter_map(|e| match e {
            EngineEvent::Alarm(a) => Some(format!("host: {a}")),
            EngineEvent::State(LinkState::Initialising) => Some("host: re-initialised".to_string()),
            _ => None,
        })
        .collect();
    out.extend(p.take_b_events().into_iter().filter_map(|e| match e {
        BoardEvent::Alarm { .. } => Some(format!("board: {e:?}")),
        _ => None,
    }));
    out
}

/// The DO images the board output, in order.
fn outputs(events: &[BoardEvent]) -> Vec<u8> {
    events
        .iter()
        .filter_map(|e| match e {
            BoardEvent::DoChanged(v) => Some(*v),
            _ => None,
        })
        .collect()
}

#[test]
fn di_then_do_then_do_at_once_never_stall_the_link() {
    for autostart in [false, true] {
        let mut p = pair(autostart);
        let _ = alarms(&mut p);
        for round in 0..20u64 {
            p.b_events.clear();
            p.command_a(EngineCommand::ReadDi);
            p.run_for(Duration::from_millis(50 * (round % 7)));
            p.command_a(EngineCommand::SetDo(7));
            p.run_for(Duration::from_millis(10 * (round % 5)));
            p.command_a(EngineCommand::SetDo(0));
            // Each SDO takes one SAT or GTD (every Tp = 5 s at least), the RDI one too.
            p.run_for(Duration::from_secs(16));
            let events: Vec<BoardEvent> = p.b_events.iter().map(|(_, e)| e.clone()).collect();
            assert_eq!(
                outputs(&events),
                [7, 0],
                "autostart {autostart}, round {round}"
            );
            let a = alarms(&mut p);
            assert!(a.is_empty(), "autostart {autostart}, round {round}: {a:?}");
        }
    }
}

/// An SDO right after SDI is the answer to the SAT before the RDI (§4.4.1: SDO answers SAT;
/// after SDI the host sends "the response of the command received immediately before"): a
/// host that sends it is served, and one that sends SET after it as well gets SR0947.
#[test]
fn the_board_takes_an_sdo_after_sdi_as_the_sats_answer() {
    use cellgate_core::engine::Engine;
    use cellgate_core::fanuc::message::{Command, Decoder, Message};
    let now = Instant::now();
    let framing = Framing::new(CodeSystem::Iso, EndCode::Cr);
    let mut board = FanucBoard::new(
        BoardConfig {
            protocol: Protocol::A,
            framing,
            first_request_delay: Duration::from_millis(100),
            ..BoardConfig::default()
        },
        now,
    )
    .unwrap();
    let mut decoder = Decoder::new(framing);
    let mut t = now;
    let send = |board: &mut FanucBoard, t: Instant, m: Message| {
        board.handle_input(t, &framing.encode_to_vec(&m).unwrap());
    };
    let mut next = |board: &mut FanucBoard, t: &mut Instant| -> Command {
        for _ in 0..100_000 {
            while let Some(bytes) = board.poll_transmit(*t) {
                decoder.push(&bytes);
                while let Some(msg) = decoder.next_message() {
                    if let Ok(m) = msg {
                        return m.command;
                    }
                }
            }
            *t += Duration::from_millis(10);
            board.handle_timeout(*t);
        }
        panic!("the board said nothing");
    };
    assert_eq!(next(&mut board, &mut t), Command::Syn);
    send(&mut board, t, Message::new(Command::Syn));
    assert_eq!(next(&mut board, &mut t), Command::Rdy);
    send(&mut board, t, Message::new(Command::Rdy));
    assert_eq!(next(&mut board, &mut t), Command::Sat);
    send(&mut board, t, Message::new(Command::Rdi));
    assert_eq!(next(&mut board, &mut t), Command::Sdi);
    send(
        &mut board,
        t,
        Message::with_data(Command::Sdo, b"05".to_vec()),
    );
    // The SAT is answered: the next message is the next SAT, Tp later.
    let before = t;
    assert_eq!(next(&mut board, &mut t), Command::Sat);
    assert!(t - before >= Duration::from_secs(4), "{:?}", t - before);
    assert_eq!(board.cnc().do_image(), 5);
}
