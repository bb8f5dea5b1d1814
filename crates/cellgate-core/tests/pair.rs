//! A host engine and the simulated board on one line in plain time ([`Pair`]): for each of
//! the four remote-buffer protocols a program goes down and the board's CNC holds every byte
//! of it, once, in order, before the host reports it done.

use std::time::{Duration, Instant};

use bytes::Bytes;
use cellgate_core::engine::LineSettings;
use cellgate_core::fanuc::Protocol;
use cellgate_core::fanuc::host::{EngineCommand, EngineEvent, HostEngine};
use cellgate_core::fanuc::message::Framing;
use cellgate_core::fanuc::protocol_a::{ProtocolAConfig, ProtocolAHost};
use cellgate_core::fanuc::protocol_b::{ProtocolBConfig, ProtocolBHost};
use cellgate_core::fanuc::sat::Params;
use cellgate_core::fanuc::{CodeSystem, EndCode};
use cellgate_core::sim::{BoardConfig, BoardEvent, FanucBoard};
use cellgate_core::testkit::Pair;

fn program(lines: usize) -> Vec<u8> {
    let mut p = b"%\nO0042 (PAIR)\n".to_vec();
    for i in 0..lines {
        p.extend_from_slice(
            format!("N{:04} G01 X{}.{:03} F100\n", i + 1, i, i * 7 % 1000).as_bytes(),
        );
    }
    p.extend_from_slice(b"M30\n%");
    p
}

fn board(protocol: Protocol, packet_n: u8, now: Instant) -> FanucBoard {
    FanucBoard::new(
        BoardConfig {
            protocol,
            framing: Framing::new(CodeSystem::Iso, EndCode::Cr),
            params: Params::POWER_ON,
            packet_n,
            autostart: true,
            first_request_delay: Duration::from_millis(100),
            consume_rate: 4000,
            ..BoardConfig::default()
        },
        now,
    )
    .unwrap()
}

/// Runs `program` from host to board: feeds the host what it wants, until it reports the
/// program done; returns the host's events.
fn send<H: HostEngine>(pair: &mut Pair<H, FanucBoard>, program: &[u8]) -> Vec<EngineEvent> {
    pair.run_for(Duration::from_secs(2));
    pair.command_a(EngineCommand::StartProgram {
        total: Some(program.len() as u64),
    });
    let mut rest = program;
    let mut events = Vec::new();
    let deadline = pair.now + Duration::from_secs(120);
    while pair.now < deadline {
        let want = pair.a.data_wanted().min(rest.len());
        if want > 0 {
            let (piece, tail) = rest.split_at(want);
            pair.command_a(EngineCommand::ProgramData(Bytes::copy_from_slice(piece)));
            rest = tail;
            if rest.is_empty() {
                pair.command_a(EngineCommand::ProgramEnd);
            }
        }
        pair.run_for(Duration::from_millis(20));
        let new = pair.take_a_events();
        let done = new
            .iter()
            .any(|e| matches!(e, EngineEvent::ProgramDone { .. }));
        events.extend(new);
        if done {
            return events;
        }
    }
    panic!("the program was not done within 120 s of line time: {events:?}");
}

fn received(pair: &mut Pair<impl HostEngine, FanucBoard>) -> Vec<Vec<u8>> {
    pair.run_for(Duration::from_secs(30));
    pair.take_b_events()
        .into_iter()
        .filter_map(|e| match e {
            BoardEvent::ProgramReceived(p) => Some(p.data.to_vec()),
            _ => None,
        })
        .collect()
}

fn line() -> LineSettings {
    LineSettings::with_baud(19200)
}

#[test]
fn protocol_a_and_expansion_a_deliver_a_program_whole() {
    for (protocol, n) in [(Protocol::A, 0), (Protocol::ExpansionA, 2)] {
        let now = Instant::now();
        let mut config = ProtocolAConfig::for_link(
            Framing::new(CodeSystem::Iso, EndCode::Cr),
            Params::POWER_ON,
            n,
            line().char_time(),
        );
        config.packet_n = n;
        let host = ProtocolAHost::new(config, now).unwrap();
        let mut pair = Pair::new(host, board(protocol, n, now), line(), now);
        let p = program(300);
        let events = send(&mut pair, &p);
        assert!(
            !events
                .iter()
                .any(|e| matches!(e, EngineEvent::ProgramAborted { .. })),
            "{protocol:?}: {events:?}"
        );
        assert_eq!(received(&mut pair), [p], "{protocol:?}");
    }
}

#[test]
fn protocol_b_and_expansion_b_deliver_a_program_whole() {
    for protocol in [Protocol::B, Protocol::ExpansionB] {
        let now = Instant::now();
        let config = ProtocolBConfig::for_protocol(protocol, CodeSystem::Iso, false).unwrap();
        let host = ProtocolBHost::new(config, now).unwrap();
        let mut pair = Pair::new(host, board(protocol, 0, now), line(), now);
        let p = program(300);
        let events = send(&mut pair, &p);
        assert!(
            !events
                .iter()
                .any(|e| matches!(e, EngineEvent::ProgramAborted { .. })),
            "{protocol:?}: {events:?}"
        );
        assert_eq!(received(&mut pair), [p], "{protocol:?}");
    }
}
