//! Corners of the remote-buffer protocols where a host that is right most of the time still
//! hurts the CNC: each drives a host engine against the simulated board, made as strict as the
//! manual, in plain time ([`Pair`]).

use std::time::{Duration, Instant};

use bytes::Bytes;
use cellgate_core::engine::LineSettings;
use cellgate_core::fanuc::Protocol;
use cellgate_core::fanuc::alarm::CncAlarm;
use cellgate_core::fanuc::error::{AbortReason, LinkAlarm};
use cellgate_core::fanuc::g05::G05Format;
use cellgate_core::fanuc::g05::stream::{Batch, BlockIn, Offered, Stream, StreamSettings};
use cellgate_core::fanuc::host::{Chunk, EngineCommand, EngineEvent, HostEngine};
use cellgate_core::fanuc::message::{Command, Framing};
use cellgate_core::fanuc::packet::Monitor;
use cellgate_core::fanuc::protocol_a::{ProtocolAConfig, ProtocolAHost};
use cellgate_core::fanuc::protocol_b::{ProtocolBConfig, ProtocolBHost};
use cellgate_core::fanuc::sat::Params;
use cellgate_core::fanuc::{CodeSystem, EndCode};
use cellgate_core::sim::{BoardCommand, BoardConfig, BoardEvent, FanucBoard, G05Stats};
use cellgate_core::testkit::Pair;
use sha2::Digest;

const SEC: Duration = Duration::from_secs(1);
const MS: Duration = Duration::from_millis(1);

fn framing() -> Framing {
    Framing::new(CodeSystem::Iso, EndCode::Cr)
}

/// Protocol A / Expansion A host and board on a line of `baud`, the host's settings from
/// its cell file (`params`, n), the board at its power-on values until the host's SET.
fn pair_a(
    protocol: Protocol,
    n: u8,
    params: Params,
    baud: u32,
    board: impl FnOnce(&mut BoardConfig),
) -> Pair<ProtocolAHost, FanucBoard> {
    let now = Instant::now();
    let line = LineSettings::with_baud(baud);
    let host = ProtocolAHost::new(
        ProtocolAConfig::for_link(framing(), params, n, line.char_time()),
        now,
    )
    .unwrap();
    let mut config = BoardConfig {
        protocol,
        framing: framing(),
        autostart: true,
        first_request_delay: 100 * MS,
        ..BoardConfig::default()
    };
    board(&mut config);
    let board = FanucBoard::new(config, now).unwrap();
    Pair::new(host, board, line, now)
}

/// Runs until `b` reports an event `f` picks, or `limit` passes; the events before it are
/// kept in `seen`.
fn until_b<H: HostEngine, T>(
    pair: &mut Pair<H, FanucBoard>,
    limit: Duration,
    seen: &mut Vec<BoardEvent>,
    mut f: impl FnMut(&BoardEvent) -> Option<T>,
) -> Option<T> {
    let end = pair.now + limit;
    loop {
        for e in pair.take_b_events() {
            let hit = f(&e);
            seen.push(e);
            if hit.is_some() {
                return hit;
            }
        }
        if !pair.step(end) {
            return None;
        }
    }
}

fn alarms(events: &[BoardEvent]) -> Vec<(CncAlarm, String)> {
    events
        .iter()
        .filter_map(|e| match e {
            BoardEvent::Alarm { alarm, detail, .. } => Some((*alarm, detail.clone())),
            _ => None,
        })
        .collect()
}

/// Corner 1 (§5.3 1; protocol notes 16): the CNC is reset between the board's GTD and the
/// host's answer while the host has no program (it would answer WAT after its grace). The
/// board sends CAN and waits for the end packet: the host must send it at once, not WAT,
/// which the board takes as an unexpected command (SR0947).
#[test]
fn expansion_a_can_with_no_packet_under_way_gets_the_end_packet_at_once() {
    let mut pair = pair_a(Protocol::ExpansionA, 1, Params::POWER_ON, 38_400, |_| {});
    let mut seen = Vec::new();
    // The link comes up, the host's SET puts n = 1 in force, the CNC starts reading.
    let gtd = until_b(&mut pair, 30 * SEC, &mut seen, |e| {
        matches!(e, BoardEvent::MessageSent(Command::Gtd)).then_some(())
    });
    assert!(gtd.is_some(), "no GTD: {seen:?}");
    assert_eq!(pair.b.packet_n(), 1, "the host's SET did not select n = 1");
    // The host has nothing to send and holds its answer for the WAT grace.
    pair.run_for(100 * MS);
    pair.command_b(BoardCommand::Reset);
    let can = pair
        .take_b_events()
        .into_iter()
        .any(|e| e == BoardEvent::MonitorSent(Monitor::Stop));
    assert!(can, "the board did not send CAN");
    let sent_before = pair.a_sent.len();
    pair.run_for(5 * SEC);
    seen = pair.take_b_events();
    assert_eq!(alarms(&seen), [], "the board raised an alarm: {seen:?}");
    // The end packet (FFh, dummy data, §5.2 2 b) answered the CAN, and then RST got ARS.
    let after = &pair.a_sent[sent_before..];
    assert_eq!(
        after.first(),
        Some(&0xFF),
        "the host's answer to CAN: {after:02X?}"
    );
    assert!(
        seen.contains(&BoardEvent::MessageReceived(Command::Ars)),
        "no ARS after the end packet: {seen:?}"
    );
    let host_events = pair.take_a_events();
    assert!(
        !host_events
            .iter()
            .any(|e| matches!(e, EngineEvent::ProtocolError { .. })),
        "{host_events:?}"
    );
    // The link goes on: a program queued now is read whole.
    let program = b"%\nO0001\nG01X1.\nM30\n%".to_vec();
    pair.command_a(EngineCommand::StartProgram {
        total: Some(program.len() as u64),
    });
    pair.command_a(EngineCommand::ProgramData(Bytes::from(program.clone())));
    pair.command_a(EngineCommand::ProgramEnd);
    let got = until_b(&mut pair, 60 * SEC, &mut seen, |e| match e {
        BoardEvent::ProgramReceived(p) => Some(p.data.to_vec()),
        _ => None,
    });
    assert_eq!(got.as_deref(), Some(&program[..]), "{seen:?}");
}

/// An NC program of about `len` bytes, `%` to `%`.
fn nc_program(len: usize, seed: u32) -> Vec<u8> {
    let mut p = format!("%\nO{:04}\n", seed % 10_000).into_bytes();
    let mut i = 0u32;
    while p.len() + 6 < len {
        p.extend_from_slice(
            format!("N{} G01 X{}.{:03} F100\n", i % 10_000, i, i * 7 % 1000).as_bytes(),
        );
        i += 1;
    }
    p.extend_from_slice(b"M30\n%");
    p
}

/// Feeds `program` to the host as it wants it, until it reports the program done or aborted
/// (or `limit` passes); the host's events and the board's are kept.
fn deliver<H: HostEngine>(
    pair: &mut Pair<H, FanucBoard>,
    program: &[u8],
    limit: Duration,
    host_events: &mut Vec<EngineEvent>,
    board_events: &mut Vec<BoardEvent>,
) -> bool {
    pair.command_a(EngineCommand::StartProgram {
        total: Some(program.len() as u64),
    });
    let mut rest = program;
    let end = pair.now + limit;
    while pair.now < end {
        let want = pair.a.data_wanted().min(rest.len());
        if want > 0 {
            let (piece, tail) = rest.split_at(want);
            pair.command_a(EngineCommand::ProgramData(Bytes::copy_from_slice(piece)));
            rest = tail;
            if rest.is_empty() {
                pair.command_a(EngineCommand::ProgramEnd);
            }
        }
        pair.run_for(20 * MS);
        board_events.extend(pair.take_b_events());
        for e in pair.take_a_events() {
            let over = matches!(
                e,
                EngineEvent::ProgramDone { .. } | EngineEvent::ProgramAborted { .. }
            );
            host_events.push(e);
            if over {
                return true;
            }
        }
    }
    false
}

/// Corner 2 (§5.3 3; protocol notes 17): after the board's DC3 only the packet under way may
/// still come, whatever the transport holds between host and line. With a device server that
/// buffers 4 KiB (sixteen packets of n = 1), the host must not run ahead of the line.
#[test]
fn expansion_a_after_dc3_only_the_packet_under_way_reaches_the_board() {
    let mut pair = pair_a(Protocol::ExpansionA, 1, Params::POWER_ON, 38_400, |c| {
        // The CNC reads at half the line's rate: the board stops the host again and again.
        c.consume_rate = 1700;
    });
    pair.a_window = Some(4096);
    let mut seen = Vec::new();
    until_b(&mut pair, 30 * SEC, &mut seen, |e| {
        matches!(e, BoardEvent::ReadingStarted).then_some(())
    })
    .expect("the CNC starts reading");
    let program = nc_program(60_000, 7);
    let mut host_events = Vec::new();
    let over = deliver(&mut pair, &program, 300 * SEC, &mut host_events, &mut seen);
    assert!(over, "the program did not end within 300 s");
    assert_eq!(alarms(&seen), [], "the board raised an alarm");
    let dc3 = seen
        .iter()
        .filter(|e| **e == BoardEvent::MonitorSent(Monitor::Pause))
        .count();
    assert!(
        dc3 >= 5,
        "only {dc3} DC3: the test does not exercise flow control"
    );
    assert!(
        host_events
            .iter()
            .any(|e| matches!(e, EngineEvent::ProgramDone { .. })),
        "{host_events:?}"
    );
    let got = until_b(&mut pair, 120 * SEC, &mut seen, |e| match e {
        BoardEvent::ProgramReceived(p) => Some(p.sha256),
        _ => None,
    });
    let want: [u8; 32] = sha2::Sha256::digest(&program).into();
    assert_eq!(got, Some(want), "the CNC read other bytes than the program");
}

/// Hands a stream's chunks to the host as the link does, one command each.
fn feed_chunks(pair: &mut Pair<ProtocolAHost, FanucBoard>, chunks: Vec<Chunk>) {
    for chunk in chunks {
        pair.command_a(chunk.command());
    }
}

/// Streams `blocks` blocks of 6 axes through `pair` as a producer that honours the credits
/// would, the first batch `first_after` after the host was told of the stream; returns the
/// CNC's G05 totals.
fn g05_stream(
    pair: &mut Pair<ProtocolAHost, FanucBoard>,
    blocks: u64,
    first_after: Duration,
    seen: &mut Vec<BoardEvent>,
) -> G05Stats {
    let format = G05Format::new(6);
    let settings = StreamSettings {
        format,
        before: Bytes::from_static(b"G05\n"),
        after: Bytes::from_static(b"M30\n"),
        window: 1000,
        prime: 62,
        idle: 10 * SEC,
        line: pair.line,
        in_flight: 4096,
    };
    let mut stream = Stream::new(settings, pair.now);
    pair.command_a(EngineCommand::StartProgram { total: None });
    pair.command_a(EngineCommand::Streaming);
    pair.run_for(first_after);
    let (mut seq, mut sent, mut on_line) = (0u64, 0u64, 0u64);
    let end = pair.now + 600 * SEC;
    while pair.now < end {
        let credits = u64::from(stream.credits()).min(blocks - sent);
        if credits > 0 && !stream.is_closing() {
            let batch: Vec<BlockIn> = (0..credits)
                .map(|i| BlockIn {
                    travels: vec![1, 2, 3, -4, ((sent + i) % 7) as i32 - 3, 5],
                    aux: None,
                })
                .collect();
            sent += credits;
            let batch = Batch {
                seq,
                blocks: batch,
                end: sent == blocks,
            };
            seq += 1;
            assert_eq!(stream.offer(pair.now, &batch), Ok(Offered::Accepted));
            let chunks = stream.take_chunks();
            feed_chunks(pair, chunks);
            if stream.is_closing() {
                pair.command_a(EngineCommand::ProgramEnd);
            }
        }
        pair.run_for(20 * MS);
        for e in pair.take_a_events() {
            if let EngineEvent::DataSent { data } = e {
                on_line += data.len() as u64;
            }
        }
        stream.on_sent(pair.now, on_line);
        for e in pair.take_b_events() {
            let ended = match &e {
                BoardEvent::G05Ended { stats, .. } => Some(stats.clone()),
                _ => None,
            };
            seen.push(e);
            if let Some(stats) = ended {
                return stats;
            }
        }
    }
    panic!("the CNC never left binary mode: {seen:?}");
}

/// Corner 3 (§9.2): a G05 stream opened while the CNC waits on a Protocol A board, its first
/// batch coming while the board's GTD is still unanswered. The `G05` block must not go out
/// alone: the CNC takes a block every T from the moment it reads it, so the blocks of the
/// priming level go in the same DAT. 6 axes every 8 ms at 19 200 baud (1.07× §9.2).
#[test]
fn g05_on_protocol_a_primes_even_when_the_gtd_is_already_waiting() {
    let params = Params {
        tx: 0,
        ti: 0,
        ..Params::POWER_ON
    };
    let mut pair = pair_a(Protocol::A, 0, params, 19_200, |c| {
        c.g05 = Some(G05Format::new(6));
    });
    let mut seen = Vec::new();
    until_b(&mut pair, 30 * SEC, &mut seen, |e| {
        matches!(e, BoardEvent::ParamsChanged { .. }).then_some(())
    })
    .expect("the host's SET");
    until_b(&mut pair, 30 * SEC, &mut seen, |e| {
        matches!(e, BoardEvent::MessageSent(Command::Gtd)).then_some(())
    })
    .expect("the CNC asks for data");
    // The producer's first batch comes while the host holds the GTD (its WAT grace).
    let stats = g05_stream(&mut pair, 3000, 200 * MS, &mut seen);
    assert_eq!(stats.blocks, 3000, "{stats:?}");
    assert_eq!(stats.underruns, 0, "the CNC waited: {stats:?}");
}

/// Queues `program` whole on the host (it is short enough for the host's buffer).
fn queue<H: HostEngine>(pair: &mut Pair<H, FanucBoard>, program: &[u8]) {
    pair.command_a(EngineCommand::StartProgram {
        total: Some(program.len() as u64),
    });
    pair.command_a(EngineCommand::ProgramData(Bytes::copy_from_slice(program)));
    pair.command_a(EngineCommand::ProgramEnd);
}

/// Corner 4 (§4.4.1 EOD): the final DAT of a program is acknowledged by a SAT (the board's
/// buffer is too full for another GTD), so the EOD "the transmission has been completed" is
/// still owed when the CNC has read the program through its EOR and a SAT has shown the
/// buffer empty. The next read's first GTD must get the next program, not that stale EOD,
/// which makes the board wait a Tp (or two) before it asks again.
#[test]
fn protocol_a_a_new_reads_first_gtd_gets_data_not_a_stale_eod() {
    let mut pair = pair_a(Protocol::A, 0, Params::POWER_ON, 19_200, |c| {
        c.autostart = false;
        // The buffer holds Nb bytes: a GTD only when it is empty.
        c.buffer_size = 2000;
        c.consume_rate = 100;
    });
    let mut seen = Vec::new();
    until_b(&mut pair, 30 * SEC, &mut seen, |e| {
        matches!(e, BoardEvent::MessageReceived(Command::Set)).then_some(())
    })
    .expect("the host's SET");
    let first = nc_program(1500, 1);
    queue(&mut pair, &first);
    pair.command_b(BoardCommand::StartReading);
    until_b(&mut pair, 60 * SEC, &mut seen, |e| {
        matches!(e, BoardEvent::ProgramReceived(_)).then_some(())
    })
    .expect("the CNC reads the first program");
    assert!(
        pair.take_a_events()
            .iter()
            .any(|e| matches!(e, EngineEvent::ProgramDone { .. })),
        "the first program is done"
    );
    // A SAT shows the buffer empty; then the next program is queued and the CNC reads again.
    until_b(&mut pair, 30 * SEC, &mut seen, |e| {
        matches!(e, BoardEvent::MessageReceived(Command::Set)).then_some(())
    })
    .expect("a SAT exchange after the read");
    let second = nc_program(1500, 2);
    queue(&mut pair, &second);
    pair.command_b(BoardCommand::StartReading);
    let started = pair.now;
    let answer = until_b(&mut pair, 30 * SEC, &mut seen, |e| match e {
        BoardEvent::MessageReceived(c @ (Command::Dat | Command::Eod | Command::Wat)) => Some(*c),
        _ => None,
    });
    assert_eq!(
        answer,
        Some(Command::Dat),
        "the new read's first GTD got {answer:?}"
    );
    assert!(
        pair.now - started < SEC,
        "the data came {:?} after the read started",
        pair.now - started
    );
}

/// A cell file's settings different from the board's power-on values (Tx, and n for
/// Expansion A), so that a test sees whether the SET took.
fn cell_params() -> Params {
    Params {
        tx: 20,
        tp: 2,
        tw: 1,
        ..Params::POWER_ON
    }
}

/// Corner 5 (§4.4.1 SAT, §4.5; protocol notes 19): the CNC is already reading when the link
/// comes up (the gateway started or restarted under it). The board asks with GTD and never
/// polls with SAT, so the SET that carries the cell file's parameters and n never goes. The
/// host answers the first GTDs with EOD, after which the board polls with SAT, and the SET
/// puts the parameters in force before any program goes.
#[test]
fn a_cnc_reading_at_connect_still_gets_the_cell_files_parameters() {
    let mut pair = pair_a(Protocol::ExpansionA, 1, cell_params(), 38_400, |c| {
        c.reading_at_power_on = true;
    });
    pair.run_for(60 * SEC);
    let seen = pair.take_b_events();
    assert!(
        seen.contains(&BoardEvent::MessageSent(Command::Gtd)),
        "the board never asked: {seen:?}"
    );
    assert_eq!(
        pair.b.params(),
        cell_params(),
        "the cell file's parameters are not applied"
    );
    assert_eq!(pair.b.packet_n(), 1, "n is not applied");
    // A program queued now goes as Expansion A packets and arrives whole.
    let program = nc_program(3000, 3);
    queue(&mut pair, &program);
    let mut seen = Vec::new();
    let got = until_b(&mut pair, 60 * SEC, &mut seen, |e| match e {
        BoardEvent::ProgramReceived(p) => Some(p.data.to_vec()),
        _ => None,
    });
    assert_eq!(got.as_deref(), Some(&program[..]));
    // It went in packets of 256 bytes, not in DATs.
    assert!(
        seen.iter()
            .any(|e| matches!(e, BoardEvent::DataReceived { bytes: 256, .. })),
        "{seen:?}"
    );
    assert!(!seen.contains(&BoardEvent::MessageReceived(Command::Dat)));
    assert_eq!(alarms(&seen), []);
}

/// Corner 5, where nothing gets the SAT: a board that asks again at once after EOD (nothing
/// in §4.4.1 makes it poll with SAT instead) and a CNC that keeps reading. The host says so
/// (an alarm naming what the operator should do, and the link's status), refuses a G05
/// stream that the board's unknown parameters might starve, and still delivers an ordinary
/// program within what a board at its power-on values takes.
#[test]
fn where_no_sat_comes_the_host_says_so_and_refuses_a_g05_stream() {
    let mut pair = pair_a(Protocol::ExpansionA, 1, cell_params(), 38_400, |c| {
        c.reading_at_power_on = true;
        c.eod_holds_gtd = false;
        c.g05 = Some(G05Format::new(3));
    });
    pair.run_for(60 * SEC);
    let host_events = pair.take_a_events();
    let alarm = host_events.iter().find_map(|e| match e {
        EngineEvent::Alarm(a @ LinkAlarm::ParamsNotApplied { .. }) => Some(a.to_string()),
        _ => None,
    });
    let alarm = alarm.unwrap_or_else(|| panic!("no alarm: {host_events:?}"));
    assert!(alarm.contains("reset the CNC"), "{alarm}");
    assert!(
        pair.a.waiting_for().is_some_and(|w| w.contains("SAT")),
        "{:?}",
        pair.a.waiting_for()
    );
    // A G05 stream is refused, not sent under parameters nobody set.
    pair.command_a(EngineCommand::StartProgram { total: None });
    pair.command_a(EngineCommand::Streaming);
    pair.command_a(EngineCommand::Primed {
        text: Bytes::from_static(b"G05\n"),
        blocks: Bytes::from(vec![0x02; 7 * 100]),
    });
    pair.run_for(30 * SEC);
    let events = pair.take_a_events();
    assert!(
        events.iter().any(|e| matches!(
            e,
            EngineEvent::ProgramAborted {
                reason: AbortReason::ParamsNotApplied,
                ..
            }
        )),
        "{events:?}"
    );
    let seen = pair.take_b_events();
    assert!(
        !seen
            .iter()
            .any(|e| matches!(e, BoardEvent::G05Started { .. })),
        "the CNC entered binary mode: {seen:?}"
    );
    // An ordinary program still goes, in DATs a board at its power-on values takes.
    let program = nc_program(5000, 4);
    queue(&mut pair, &program);
    let mut seen = Vec::new();
    let got = until_b(&mut pair, 120 * SEC, &mut seen, |e| match e {
        BoardEvent::ProgramReceived(p) => Some(p.data.to_vec()),
        _ => None,
    });
    assert_eq!(got.as_deref(), Some(&program[..]), "{seen:?}");
    assert_eq!(alarms(&seen), []);
}

/// Corner 6 (§6.1.1 (7), §6.3; protocol notes 13, 20): Expansion B through a device server
/// whose UART runs 15 % above the nominal rate. The CNC read the program slowly (the board
/// stopped the host with DC3 again and again), then at line speed at its end, so the DC3
/// that ends the read came before the host's estimate of when its EOR reached the board.
/// The program must still end, and the next one go at the next read's DC1.
#[test]
fn expansion_b_ends_a_program_on_a_line_running_fast() {
    let now = Instant::now();
    let nominal = LineSettings::with_baud(86_400);
    let mut config = ProtocolBConfig::new(CodeSystem::Iso, true, true);
    config.char_time = nominal.char_time();
    let host = ProtocolBHost::new(config, now).unwrap();
    let board = FanucBoard::new(
        BoardConfig {
            protocol: Protocol::ExpansionB,
            framing: framing(),
            autostart: true,
            first_request_delay: 100 * MS,
            consume_rate: 86_400 / 11 / 4,
            ..BoardConfig::default()
        },
        now,
    )
    .unwrap();
    // The device server's UART: 15 % fast; the host paces at the nominal rate through a
    // window of 1 KiB.
    let mut pair = Pair::new(host, board, LineSettings::with_baud(99_360), now);
    pair.a_window = Some(1024);
    pair.run_for(SEC);
    let programs = [nc_program(200_000, 1), nc_program(3000, 2)];
    let mut seen = Vec::new();
    for (i, program) in programs.iter().enumerate() {
        let mut host_events = Vec::new();
        pair.command_a(EngineCommand::StartProgram {
            total: Some(program.len() as u64),
        });
        let mut rest = &program[..];
        let mut sent = 0u64;
        let mut fast = false;
        let end = pair.now + 120 * SEC;
        let done = loop {
            assert!(
                pair.now < end,
                "program {i} did not end within 120 s; the host waits for {:?}",
                pair.a.waiting_for()
            );
            let want = pair.a.data_wanted().min(rest.len());
            if want > 0 {
                let (piece, tail) = rest.split_at(want);
                pair.command_a(EngineCommand::ProgramData(Bytes::copy_from_slice(piece)));
                rest = tail;
                if rest.is_empty() {
                    pair.command_a(EngineCommand::ProgramEnd);
                }
            }
            pair.run_for(10 * MS);
            seen.extend(pair.take_b_events());
            let mut over = None;
            for e in pair.take_a_events() {
                match &e {
                    EngineEvent::DataSent { data } => {
                        sent += data.len() as u64;
                        // The last few KiB: the CNC now reads as fast as they come.
                        if !fast && sent + 4096 >= program.len() as u64 {
                            fast = true;
                            pair.command_b(BoardCommand::SetConsumeRate(0));
                        }
                    }
                    EngineEvent::ProgramDone { .. } => over = Some(true),
                    EngineEvent::ProgramAborted { .. } => over = Some(false),
                    _ => {}
                }
                host_events.push(e);
            }
            if let Some(done) = over {
                break done;
            }
        };
        assert!(done, "program {i}: {host_events:?}");
        pair.command_b(BoardCommand::SetConsumeRate(86_400 / 11 / 4));
    }
    pair.run_for(60 * SEC);
    seen.extend(pair.take_b_events());
    let received: Vec<[u8; 32]> = seen
        .iter()
        .filter_map(|e| match e {
            BoardEvent::ProgramReceived(p) => Some(p.sha256),
            _ => None,
        })
        .collect();
    let want: Vec<[u8; 32]> = programs
        .iter()
        .map(|p| sha2::Sha256::digest(p).into())
        .collect();
    assert_eq!(received, want, "the CNC did not read both programs whole");
    assert_eq!(alarms(&seen), []);
    let dc3 = pair.b.flow_counters();
    assert!(
        dc3.dc3_sent > 20,
        "the test does not exercise flow control: {dc3:?}"
    );
}

/// Streams `blocks` blocks of `format` through `pair` from a CNC already waiting for data:
/// the producer's first batch is the priming level exactly, and only once the DAT carrying
/// the `G05` block has gone does it top the window up, so that the next DAT is a full one.
/// Returns the CNC's totals and the stream's own figures.
fn g05_from_a_waiting_cnc(
    pair: &mut Pair<ProtocolAHost, FanucBoard>,
    format: G05Format,
    prime: u32,
    blocks: u64,
) -> (G05Stats, cellgate_core::fanuc::g05::stream::StreamFigures) {
    let settings = StreamSettings {
        format,
        before: Bytes::from_static(b"G05\n"),
        after: Bytes::from_static(b"M30\n"),
        window: 1000,
        prime,
        idle: 10 * SEC,
        line: pair.line,
        in_flight: 4096,
    };
    let mut stream = Stream::new(settings, pair.now);
    pair.command_a(EngineCommand::StartProgram { total: None });
    pair.command_a(EngineCommand::Streaming);
    let block = |i: u64| BlockIn {
        travels: vec![1, 2, 3, -4, (i % 7) as i32 - 3, 5],
        aux: None,
    };
    let first = Batch {
        seq: 0,
        blocks: (0..u64::from(prime)).map(block).collect(),
        end: false,
    };
    assert_eq!(stream.offer(pair.now, &first), Ok(Offered::Accepted));
    feed_chunks(pair, stream.take_chunks());
    let (mut seq, mut sent, mut on_line) = (1u64, u64::from(prime), 0u64);
    let end = pair.now + 600 * SEC;
    let mut seen = Vec::new();
    while pair.now < end {
        let credits = u64::from(stream.credits()).min(blocks - sent);
        if on_line > 0 && credits > 0 && !stream.is_closing() {
            let batch = Batch {
                seq,
                blocks: (sent..sent + credits).map(block).collect(),
                end: sent + credits == blocks,
            };
            sent += credits;
            seq += 1;
            assert_eq!(stream.offer(pair.now, &batch), Ok(Offered::Accepted));
            feed_chunks(pair, stream.take_chunks());
            if stream.is_closing() {
                pair.command_a(EngineCommand::ProgramEnd);
            }
        }
        pair.run_for(MS);
        for e in pair.take_a_events() {
            if let EngineEvent::DataSent { data } = e {
                on_line += data.len() as u64;
                stream.on_sent(pair.now, on_line);
            }
        }
        stream.tick(pair.now);
        for e in pair.take_b_events() {
            if let BoardEvent::G05Ended { stats, .. } = &e {
                return (stats.clone(), stream.figures());
            }
            seen.push(e);
        }
    }
    panic!("the CNC never left binary mode: {seen:?}");
}

/// Corner 6 (§9.2, §4.4.2 3): G05 opened on Protocol A while the CNC waits, 6 axes every
/// 4 ms at 38 400 baud (1.07× §9.2). The board uses a DAT only once all of it has arrived,
/// so the CNC starts with the blocks of the first DAT and needs the next DAT whole before
/// they run out: the `prime_ms` default, 500 ms of blocks, followed by a full DAT of 1950
/// bytes (562 ms with the GTD that asks for it) ran it dry. The priming level in force covers
/// that exchange, and the CNC never waits. Either way the stream's estimate counts no more
/// underruns than the CNC did.
#[test]
fn g05_on_protocol_a_from_a_waiting_cnc_is_primed_for_the_next_dat() {
    let params = Params {
        tx: 0,
        ti: 0,
        ..Params::POWER_ON
    };
    let line = LineSettings::with_baud(38_400);
    let g05: cellgate_core::config::G05Config =
        toml::from_str("axes = 6\nunit_time_ms = 4").unwrap();
    let refill = cellgate_core::config::Refill::of(Protocol::A, params, 0, &line);
    assert_eq!(refill.map(|r| r.data), Some(1950));
    assert_eq!(g05.standing_start(refill), None, "this line keeps up");
    let primes = [
        (g05.prime_blocks(), "the prime_ms default"),
        (g05.prime_blocks_on(refill), "the priming in force"),
    ];
    assert_eq!(primes[0].0, 125);
    let mut counted = Vec::new();
    for (prime, what) in primes {
        let mut pair = pair_a(Protocol::A, 0, params, 38_400, |c| {
            c.g05 = Some(g05.format());
        });
        let mut seen = Vec::new();
        until_b(&mut pair, 30 * SEC, &mut seen, |e| {
            matches!(e, BoardEvent::ParamsChanged { .. }).then_some(())
        })
        .expect("the host's SET");
        until_b(&mut pair, 30 * SEC, &mut seen, |e| {
            matches!(e, BoardEvent::MessageSent(Command::Gtd)).then_some(())
        })
        .expect("the CNC asks for data");
        let (stats, figures) = g05_from_a_waiting_cnc(&mut pair, g05.format(), prime, 6000);
        assert_eq!(stats.blocks, 6000, "{what}: {stats:?}");
        assert!(
            figures.underruns <= stats.underruns,
            "{what}: the estimate said {} where the CNC counted {}",
            figures.underruns,
            stats.underruns
        );
        counted.push(stats.underruns);
    }
    assert!(
        counted[0] > 0,
        "500 ms of blocks ran the CNC dry: {counted:?}"
    );
    assert_eq!(counted[1], 0, "primed for the next DAT: {counted:?}");
}
