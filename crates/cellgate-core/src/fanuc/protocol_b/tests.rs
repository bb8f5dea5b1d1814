use super::*;
use crate::fanuc::alarm::CncAlarm;
use proptest::prelude::*;

fn host(code: CodeSystem, expansion: bool, notify: bool) -> (ProtocolBHost, Instant) {
    let now = Instant::now();
    let mut h = ProtocolBHost::new(ProtocolBConfig::new(code, expansion, notify), now).unwrap();
    assert_eq!(h.poll_event(), Some(EngineEvent::State(LinkState::Ready)));
    (h, now)
}

fn events(h: &mut ProtocolBHost) -> Vec<EngineEvent> {
    std::iter::from_fn(|| h.poll_event()).collect()
}

/// Everything the host hands out now.
/// The board ends the read with DC3, and no notice follows within the settle time.
fn end_read(h: &mut ProtocolBHost, now: Instant) -> Vec<EngineEvent> {
    h.handle_input(now, &[h.config().code.control(DC3)]);
    let settle = h.poll_timeout().expect("the end of the read settles");
    h.handle_timeout(settle);
    events(h)
}

fn done(evs: &[EngineEvent]) -> bool {
    evs.iter()
        .any(|e| matches!(e, EngineEvent::ProgramDone { .. }))
}

fn drain_tx(h: &mut ProtocolBHost, now: Instant) -> Vec<u8> {
    let mut out = Vec::new();
    while let Some(piece) = h.poll_transmit(now) {
        assert!(!piece.is_empty());
        assert!(piece.len() <= h.config().tx_piece);
        out.extend(piece);
    }
    out
}

fn program(body_len: usize) -> Vec<u8> {
    let mut p = b"%\nO0001\n".to_vec();
    p.extend((0..body_len).map(|i| b"G01X1.;\n"[i % 8]));
    p.push(EOR);
    p
}

fn load(h: &mut ProtocolBHost, now: Instant, prog: &[u8]) {
    h.handle_command(now, EngineCommand::StartProgram { total: None });
    h.handle_command(
        now,
        EngineCommand::ProgramData(Bytes::copy_from_slice(prog)),
    );
    h.handle_command(now, EngineCommand::ProgramEnd);
}

fn punched(evs: &[EngineEvent]) -> Vec<u8> {
    evs.iter()
        .filter_map(|e| match e {
            EngineEvent::Punched { data } => Some(data.to_vec()),
            _ => None,
        })
        .flatten()
        .collect()
}

/// A queued program waits for the CNC's DC1, a paused one for the DC1 after DC3, a
/// finished one for the DC3 that ends the read: status says which.
#[test]
fn says_what_it_waits_for() {
    let (mut h, now) = host(CodeSystem::Ascii, false, true);
    assert_eq!(h.waiting_for(), None);
    h.handle_command(now, EngineCommand::StartProgram { total: None });
    h.handle_command(now, EngineCommand::ProgramData(Bytes::from(program(600))));
    h.handle_command(now, EngineCommand::ProgramEnd);
    assert!(
        h.waiting_for()
            .is_some_and(|w| w.starts_with("DC1: the CNC"))
    );
    h.handle_input(now, &[DC1]);
    assert_eq!(h.waiting_for(), None);
    let _ = h.poll_transmit(now);
    h.handle_input(now, &[DC3]);
    assert!(
        h.waiting_for()
            .is_some_and(|w| w.starts_with("DC1 after DC3"))
    );
    h.handle_input(now, &[DC1]);
    drain_tx(&mut h, now);
    assert!(h.waiting_for().is_some_and(|w| w.contains("ends the read")));
    h.handle_modem(
        now,
        ModemIn {
            dr: false,
            cs: false,
            cd: false,
        },
    );
    assert!(h.waiting_for().is_some_and(|w| w.starts_with("DR")));
}

/// A host at 19200 baud (11 bits a character), notices on.
fn timed_host() -> (ProtocolBHost, Instant, Duration) {
    let ct = Duration::from_nanos(11 * 1_000_000_000 / 19_200);
    let cfg = ProtocolBConfig {
        char_time: ct,
        ..ProtocolBConfig::new(CodeSystem::Ascii, false, true)
    };
    let now = Instant::now();
    let mut h = ProtocolBHost::new(cfg, now).unwrap();
    events(&mut h);
    (h, now, ct)
}

/// A CNC that reads at line speed behind a device server that delivered sooner than the
/// nominal rate ends the read before the host's estimate of the EOR's arrival: that DC3
/// ends the read all the same, and the program is done.
#[test]
fn an_end_of_read_a_little_before_the_estimate_ends_the_read() {
    let (mut h, t0, ct) = timed_host();
    let prog = program(4000);
    load(&mut h, t0, &prog);
    h.handle_input(t0, &[DC1]);
    assert_eq!(drain_tx(&mut h, t0), prog);
    let estimate = t0 + ct * prog.len() as u32;
    let early = estimate - ct * 300;
    assert!(done(&end_read(&mut h, early)));
    assert_eq!(h.poll_transmit(early), None);
    // Far before the estimate, a DC3 cannot end the read: the EOR is not there yet.
    let (mut h, t0, ct) = timed_host();
    load(&mut h, t0, &prog);
    h.handle_input(t0, &[DC1]);
    drain_tx(&mut h, t0);
    let too_early = t0 + ct * (prog.len() as u32 / 2);
    h.handle_input(too_early, &[DC3]);
    h.handle_timeout(too_early + Duration::from_secs(1));
    assert!(!done(&events(&mut h)));
}

/// A board that stopped the program with DC3 before (a CNC slower than the line) may stop
/// it again just before the EOR arrives: that DC3 stays flow control, the DC1 after it
/// sends nothing, and only the DC3 after the EOR's arrival ends the read.
#[test]
fn a_board_that_stopped_the_program_is_not_taken_early() {
    let (mut h, t0, ct) = timed_host();
    let prog = program(4000);
    load(&mut h, t0, &prog);
    h.handle_input(t0, &[DC1]);
    let first = h.poll_transmit(t0).unwrap();
    h.handle_input(t0, &[DC3]);
    h.handle_input(t0, &[DC1]);
    let mut sent = first;
    sent.extend(drain_tx(&mut h, t0));
    assert_eq!(sent, prog);
    let estimate = t0 + ct * prog.len() as u32;
    let near = estimate - ct * 300;
    h.handle_input(near, &[DC3]);
    assert_eq!(h.poll_timeout(), None, "no end of read to settle");
    h.handle_input(near, &[DC1]);
    assert!(!done(&events(&mut h)));
    assert!(h.waiting_for().is_some_and(|w| w.contains("ends the read")));
    assert!(done(&end_read(&mut h, estimate + ct)));
}

#[test]
fn default_settings_are_valid_and_overrun_per_protocol() {
    assert!(ProtocolBConfig::default().validate().is_empty());
    let b = ProtocolBConfig::new(CodeSystem::Iso, false, true);
    assert_eq!(b.overrun_allowance, 512);
    let eb = ProtocolBConfig::new(CodeSystem::Iso, true, false);
    assert_eq!(eb.overrun_allowance, 1280);
    assert!(eb.validate().is_empty());
    assert_eq!(
        ProtocolBConfig::for_protocol(Protocol::ExpansionB, CodeSystem::Iso, false),
        Some(eb.clone())
    );
    assert_eq!(
        ProtocolBConfig::for_protocol(Protocol::A, CodeSystem::Iso, false),
        None
    );
    let bad = ProtocolBConfig { tx_piece: 300, ..b };
    assert!(matches!(
        bad.validate().as_slice(),
        [ProtocolBProblem::TxPiece { piece: 300, .. }]
    ));
    assert!(ProtocolBHost::new(bad, Instant::now()).is_err());
}

#[test]
fn nothing_is_sent_before_dc1() {
    let (mut h, now) = host(CodeSystem::Ascii, false, true);
    load(&mut h, now, &program(100));
    assert_eq!(h.poll_transmit(now), None);
    assert!(h.data_wanted() == 0, "EOR is in: the program takes no more");
}

#[test]
fn dc1_dc3_flow_stops_within_a_piece_and_resumes_with_the_continuation() {
    for (code, dc3) in [(CodeSystem::Iso, 0x93), (CodeSystem::Ascii, 0x13)] {
        let (mut h, now) = host(code, false, true);
        let prog = program(2000);
        load(&mut h, now, &prog);
        h.handle_input(now, &[0x11]);
        let mut sent = Vec::new();
        // The board stops the host after a few pieces.
        for _ in 0..5 {
            sent.extend(h.poll_transmit(now).unwrap());
        }
        // A piece is on the line when the DC3 arrives: at most that piece overruns.
        let in_flight = h.poll_transmit(now).unwrap();
        sent.extend(&in_flight);
        h.handle_input(now, &[dc3]);
        assert_eq!(h.sent_since_dc3(), 0);
        assert_eq!(h.poll_transmit(now), None);
        let overrun = in_flight.len() as u64 + h.sent_since_dc3();
        let cfg = h.config();
        assert!(overrun <= cfg.tx_piece as u64, "overrun {overrun}");
        assert!(
            overrun < cfg.overrun_allowance as u64 / 4,
            "overrun {overrun}"
        );
        assert!(!h.flowing());
        // DC1: the data immediately after that sent last.
        h.handle_input(now, &[0x11]);
        sent.extend(drain_tx(&mut h, now));
        assert_eq!(sent, prog);
        let mut evs = events(&mut h);
        evs.extend(end_read(&mut h, now));
        let told: Vec<u8> = evs
            .iter()
            .filter_map(|e| match e {
                EngineEvent::DataSent { data } => Some(data.to_vec()),
                _ => None,
            })
            .flatten()
            .collect();
        assert_eq!(told, prog, "the pieces sent, in order");
        assert_eq!(
            evs.iter()
                .filter(|e| matches!(e, EngineEvent::ProgramDone { .. }))
                .count(),
            1
        );
        assert!(evs.contains(&EngineEvent::State(LinkState::Sending)));
        assert_eq!(evs.last(), Some(&EngineEvent::State(LinkState::Ready)));
    }
}

#[test]
fn next_program_waits_for_dc3_and_a_following_dc1() {
    let (mut h, now) = host(CodeSystem::Iso, false, true);
    let first = program(10);
    load(&mut h, now, &first);
    h.handle_input(now, &[0x11]);
    assert_eq!(drain_tx(&mut h, now), first);
    assert!(!done(&events(&mut h)));
    // Flow-control DC1 of the same read: nothing, and the program is not done.
    h.handle_input(now, &[0x11]);
    assert_eq!(h.poll_transmit(now), None);
    assert!(!done(&events(&mut h)));
    // The CNC ends the read with DC3; nothing until a new DC1, which also shows that no
    // reset or alarm followed: the first program is the board's.
    h.handle_input(now, &[0x93]);
    assert_eq!(h.poll_transmit(now), None);
    assert!(!done(&events(&mut h)));
    h.handle_input(now, &[0x11]);
    assert!(done(&events(&mut h)));
    // That DC1 asked for the next program: it goes at once.
    let second = program(20);
    load(&mut h, now, &second);
    assert_eq!(drain_tx(&mut h, now), second);
}

#[test]
fn program_without_eor_gets_one() {
    let (mut h, now) = host(CodeSystem::Ascii, false, true);
    load(&mut h, now, b"%\nO1\nX1\n");
    h.handle_input(now, &[0x11]);
    assert_eq!(drain_tx(&mut h, now), b"%\nO1\nX1\n%");
    assert!(done(&end_read(&mut h, now)));
}

#[test]
fn data_comes_in_bounded_pieces() {
    let (mut h, now) = host(CodeSystem::Ascii, false, true);
    h.handle_command(now, EngineCommand::StartProgram { total: None });
    assert_eq!(h.data_wanted(), 64 * 1024);
    h.handle_command(
        now,
        EngineCommand::ProgramData(Bytes::from(vec![b'X'; 1000])),
    );
    assert_eq!(h.data_wanted(), 64 * 1024 - 1000);
    h.handle_input(now, &[0x11]);
    let sent = drain_tx(&mut h, now);
    assert_eq!(sent.len(), 1000);
    // Late data: the host waits, the board keeps the read open.
    h.handle_command(now, EngineCommand::ProgramData(Bytes::from_static(b"Y%")));
    assert_eq!(drain_tx(&mut h, now), b"Y%");
    assert!(done(&end_read(&mut h, now)));
}

#[test]
fn dc3_syn_is_a_cnc_reset_that_aborts_the_program() {
    for (code, dc3, syn) in [
        (CodeSystem::Iso, 0x93, 0x96),
        (CodeSystem::Ascii, 0x13, 0x16),
    ] {
        let (mut h, now) = host(code, false, true);
        load(&mut h, now, &program(500));
        h.handle_input(now, &[0x11]);
        let _ = h.poll_transmit(now).unwrap();
        events(&mut h);
        h.handle_input(now, &[dc3, syn]);
        assert_eq!(h.poll_transmit(now), None);
        assert_eq!(
            events(&mut h),
            vec![
                // The piece sent reached the board before its DC3.
                EngineEvent::Acked { offset: 64 },
                EngineEvent::CncReset,
                EngineEvent::ProgramAborted {
                    reason: AbortReason::ResetNotice,
                    cancelled: false
                },
                EngineEvent::State(LinkState::Ready),
            ]
        );
        // The next program goes on the next read request.
        let next = program(5);
        load(&mut h, now, &next);
        h.handle_input(now, &[0x11]);
        assert_eq!(drain_tx(&mut h, now), next);
    }
}

#[test]
fn dc3_nak_is_a_cnc_alarm_and_a_queued_program_stays() {
    let (mut h, now) = host(CodeSystem::Iso, true, true);
    load(&mut h, now, &program(500));
    h.handle_input(now, &[0x11]);
    let _ = h.poll_transmit(now).unwrap();
    events(&mut h);
    // Parity-less form accepted defensively with ISO.
    h.handle_input(now, &[0x13, 0x15]);
    let evs = events(&mut h);
    assert_eq!(evs.first(), Some(&EngineEvent::Acked { offset: 64 }));
    assert_eq!(evs.get(1), Some(&EngineEvent::CncAlarm));
    assert!(evs.contains(&EngineEvent::ProgramAborted {
        reason: AbortReason::AlarmNotice,
        cancelled: false
    }));
    // Idle notice (§6.1.2 1): a queued, unstarted program stays queued.
    let next = program(5);
    load(&mut h, now, &next);
    h.handle_input(now, &[0x95]);
    assert_eq!(events(&mut h), vec![EngineEvent::CncAlarm]);
    h.handle_input(now, &[0x11]);
    assert_eq!(drain_tx(&mut h, now), next);
}

#[test]
fn punch_out_produces_exactly_the_punched_bytes() {
    let (mut h, now) = host(CodeSystem::Iso, false, true);
    let data: Vec<u8> = b"%\nO0002\nG00X0\n%"
        .iter()
        .map(|&b| CodeSystem::Iso.encode(b))
        .collect();
    // Split anywhere; DC4 with or without bit 7.
    h.handle_input(now, &[0x12]);
    h.handle_input(now, &data[..5]);
    assert_eq!(
        events(&mut h),
        vec![EngineEvent::State(LinkState::Receiving)]
    );
    h.handle_input(now, &data[5..]);
    h.handle_input(now, &[0x14]);
    let evs = events(&mut h);
    assert_eq!(punched(&evs), data);
    assert_eq!(evs.last(), Some(&EngineEvent::State(LinkState::Ready)));
    assert_eq!(h.punch_held(), 0);
    // A punch-out cut by a reset: DC4 then SYN (§6.1.2 2 (5)).
    h.handle_input(now, &[0x12, b'O', b'1', 0x94, 0x96]);
    let evs = events(&mut h);
    assert_eq!(punched(&evs), b"O1");
    assert!(evs.contains(&EngineEvent::CncReset));
    assert_eq!(h.poll_transmit(now), None);
}

#[test]
fn punch_out_flow_control_sends_dc3_then_dc1_or_dc2() {
    for (notify, resume) in [(true, 0x11), (false, 0x12)] {
        let (mut h, now) = host(CodeSystem::Iso, false, notify);
        let high = h.config().punch_high_water;
        h.handle_input(now, &[0x12]);
        h.handle_input(now, &vec![b'A'; high]);
        assert_eq!(h.poll_transmit(now), None);
        assert!(h.modem_out().rs);
        // One more byte not taken: DC3 in the configured code, and RS off (CS of the
        // board).
        h.handle_input(now, b"B");
        assert_eq!(h.poll_transmit(now), Some(vec![0x93]));
        assert!(!h.modem_out().rs);
        // Overrun within the allowance is kept.
        h.handle_input(now, &vec![b'C'; 400]);
        assert_eq!(h.punch_held(), high + 401);
        // Taking the pieces resumes the board.
        let mut got = punched(&events(&mut h));
        assert_eq!(got.len() + h.punch_held(), high + 401);
        assert_eq!(h.poll_transmit(now), Some(vec![resume]));
        assert!(h.modem_out().rs);
        h.handle_input(now, &[0x14]);
        got.extend(punched(&events(&mut h)));
        let mut expected = vec![b'A'; high];
        expected.push(b'B');
        expected.extend([b'C'; 400]);
        assert!(got == expected, "punched data differs");
        assert_eq!(h.poll_transmit(now), None);
    }
}

#[test]
fn rs_stays_on_without_rs_flow() {
    let cfg = ProtocolBConfig {
        rs_flow: false,
        ..ProtocolBConfig::new(CodeSystem::Ascii, false, true)
    };
    let now = Instant::now();
    let mut h = ProtocolBHost::new(cfg, now).unwrap();
    let high = h.config().punch_high_water;
    h.handle_input(now, &[0x12]);
    h.handle_input(now, &vec![b'A'; high + 1]);
    assert_eq!(h.poll_transmit(now), Some(vec![0x13]));
    assert!(h.modem_out().rs);
}

#[test]
fn punch_overflow_is_dropped_and_reported() {
    let (mut h, now) = host(CodeSystem::Ascii, false, true);
    let max = h.config().max_buffer;
    h.handle_input(now, &[0x12]);
    h.handle_input(now, &vec![b'A'; max + 10]);
    assert_eq!(h.punch_held(), max);
    let evs = events(&mut h);
    assert!(evs.iter().any(|e| matches!(
        e,
        EngineEvent::ProtocolError {
            error: ProtocolError::PunchOverflow { dropped: 10 },
            ..
        }
    )));
}

#[test]
fn cancel_aborts_and_the_next_program_waits_for_a_new_read() {
    let (mut h, now) = host(CodeSystem::Ascii, false, true);
    load(&mut h, now, &program(500));
    h.handle_input(now, &[0x11]);
    let _ = h.poll_transmit(now).unwrap();
    events(&mut h);
    h.handle_command(now, EngineCommand::Cancel);
    assert_eq!(h.poll_transmit(now), None);
    assert!(events(&mut h).contains(&EngineEvent::ProgramAborted {
        reason: AbortReason::Cancelled,
        cancelled: true
    }));
    load(&mut h, now, &program(5));
    assert_eq!(h.poll_transmit(now), None);
    h.handle_input(now, &[0x13, 0x11]);
    assert_eq!(drain_tx(&mut h, now), program(5));
}

#[test]
fn do_di_and_clb_do_not_exist_in_protocol_b() {
    let (mut h, now) = host(CodeSystem::Ascii, false, true);
    for c in [
        EngineCommand::SetDo(1),
        EngineCommand::ReadDi,
        EngineCommand::ClearBuffer,
    ] {
        h.handle_command(now, c);
        let evs = events(&mut h);
        assert!(matches!(
            evs.as_slice(),
            [EngineEvent::ProtocolError {
                error: ProtocolError::NotInProtocolB { .. },
                retried: false
            }]
        ));
    }
    assert_eq!(h.poll_transmit(now), None);
}

#[test]
fn dr_off_raises_sr0855_and_aborts() {
    let (mut h, now) = host(CodeSystem::Iso, false, true);
    load(&mut h, now, &program(500));
    h.handle_input(now, &[0x11]);
    let _ = h.poll_transmit(now).unwrap();
    events(&mut h);
    let down = ModemIn {
        dr: false,
        ..ModemIn::ALL_ON
    };
    h.handle_modem(now, down);
    let evs = events(&mut h);
    assert!(matches!(
        evs.first(),
        Some(EngineEvent::Alarm(a)) if a.cnc_alarm() == Some(CncAlarm::Sr0855DataSetReadyDown)
    ));
    assert!(evs.contains(&EngineEvent::ProgramAborted {
        reason: AbortReason::Link(LinkAlarm::DataSetReadyOffB),
        cancelled: false
    }));
    assert_eq!(evs.last(), Some(&EngineEvent::State(LinkState::LineDown)));
    h.handle_input(now, &[0x11]);
    assert_eq!(h.poll_transmit(now), None);
    h.handle_modem(now, ModemIn::ALL_ON);
    assert_eq!(events(&mut h), vec![EngineEvent::State(LinkState::Ready)]);
}

#[test]
fn cs_off_pauses_sending() {
    let (mut h, now) = host(CodeSystem::Ascii, false, true);
    let prog = program(100);
    load(&mut h, now, &prog);
    h.handle_input(now, &[0x11]);
    let mut sent = h.poll_transmit(now).unwrap();
    h.handle_modem(
        now,
        ModemIn {
            cs: false,
            ..ModemIn::ALL_ON
        },
    );
    assert_eq!(h.poll_transmit(now), None);
    h.handle_modem(now, ModemIn::ALL_ON);
    sent.extend(drain_tx(&mut h, now));
    assert_eq!(sent, prog);
}

#[test]
fn garbage_is_reported_and_ignored() {
    let (mut h, now) = host(CodeSystem::Iso, false, true);
    h.handle_input(now, b"hello");
    let evs = events(&mut h);
    assert!(matches!(
        evs.as_slice(),
        [EngineEvent::ProtocolError {
            error: ProtocolError::NotControlCodes {
                count: 5,
                first: 0x68
            },
            ..
        }]
    ));
    h.handle_line_error(now, LineError::Parity);
    assert_eq!(events(&mut h).len(), 1);
}

#[test]
fn punched_pieces_end_at_each_programs_eor() {
    let (mut h, now) = host(CodeSystem::Ascii, false, true);
    h.handle_input(now, b"\x12\n%\nO1\nX1\n%\nO2\nX2\n%\x14");
    let pieces: Vec<Vec<u8>> = events(&mut h)
        .into_iter()
        .filter_map(|e| match e {
            EngineEvent::Punched { data } => Some(data.to_vec()),
            _ => None,
        })
        .collect();
    assert_eq!(
        pieces,
        vec![b"\n%\nO1\nX1\n%".to_vec(), b"\nO2\nX2\n%".to_vec()]
    );
}

#[test]
fn a_line_error_while_punching_marks_the_punch_out_damaged_where_it_fell() {
    let (mut h, now) = host(CodeSystem::Ascii, false, true);
    h.handle_input(now, b"\x12\n%\nO1\nX1");
    h.handle_line_error(now, LineError::Parity);
    h.handle_input(now, b"\n%\x14");
    let evs: Vec<EngineEvent> = events(&mut h)
        .into_iter()
        .filter(|e| !matches!(e, EngineEvent::State(_)))
        .collect();
    assert!(
        matches!(
            evs.as_slice(),
            [
                EngineEvent::Punched { data: before },
                EngineEvent::PunchDamaged {
                    cause: PunchDamage::Line(LineError::Parity)
                },
                EngineEvent::ProtocolError { .. },
                EngineEvent::Punched { data: after },
            ] if before.as_ref() == b"\n%\nO1\nX1" && after.as_ref() == b"\n%"
        ),
        "{evs:?}"
    );
    // Outside a punch-out a line error damages nothing.
    h.handle_line_error(now, LineError::Framing);
    assert!(
        !events(&mut h)
            .iter()
            .any(|e| matches!(e, EngineEvent::PunchDamaged { .. }))
    );
}

#[test]
fn notices_are_reported_with_notification_off_too() {
    let (mut h, now) = host(CodeSystem::Ascii, false, false);
    h.handle_input(now, &[0x13, 0x16, 0x15]);
    assert_eq!(
        events(&mut h),
        vec![EngineEvent::CncReset, EngineEvent::CncAlarm]
    );
}

#[test]
fn a_dc3_not_sent_yet_is_dropped_rather_than_resumed() {
    let (mut h, now) = host(CodeSystem::Ascii, false, false);
    let high = h.config().punch_high_water;
    h.handle_modem(
        now,
        ModemIn {
            cs: false,
            ..ModemIn::ALL_ON
        },
    );
    h.handle_input(now, &[0x12]);
    h.handle_input(now, &vec![b'A'; high + 1]);
    // CS off: the DC3 waits; the data is taken meanwhile.
    assert_eq!(h.poll_transmit(now), None);
    events(&mut h);
    h.handle_modem(now, ModemIn::ALL_ON);
    assert_eq!(h.poll_transmit(now), None);
    assert!(h.punch_held() <= high / 2);
}

proptest! {
    /// A board that stops and resumes the host at random: nothing goes out while stopped,
    /// at most one piece is on its way when DC3 arrives, and the board gets exactly the
    /// program.
    #[test]
    fn random_dc1_dc3_flow_delivers_the_program_exactly(
        steps in proptest::collection::vec((any::<bool>(), 0usize..4), 1..200),
        iso in any::<bool>(),
    ) {
        let code = if iso { CodeSystem::Iso } else { CodeSystem::Ascii };
        let (mut h, now) = host(code, false, true);
        let prog = program(3000);
        load(&mut h, now, &prog);
        let mut sent = Vec::new();
        let mut stopped = true;
        for (dc1, polls) in steps {
            h.handle_input(now, &[code.control(if dc1 { DC1 } else { DC3 })]);
            stopped = !dc1;
            for _ in 0..polls {
                match h.poll_transmit(now) {
                    Some(out) => {
                        prop_assert!(!stopped, "data after DC3");
                        prop_assert!(out.len() <= 64);
                        sent.extend(out);
                    }
                    None => break,
                }
            }
            prop_assert!(prog.starts_with(&sent));
        }
        if stopped {
            h.handle_input(now, &[0x11]);
        }
        sent.extend(drain_tx(&mut h, now));
        prop_assert!(sent == prog, "the board got other bytes than the program");
    }

    #[test]
    fn arbitrary_input_never_panics_and_stays_bounded(
        chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..200), 0..60),
        take_events in any::<bool>(),
        expansion in any::<bool>(),
    ) {
        let now = Instant::now();
        let cfg = ProtocolBConfig {
            max_buffer: 4096,
            punch_piece: 512,
            punch_high_water: 4096 - 2 * 1280,
            ..ProtocolBConfig::new(CodeSystem::Iso, expansion, true)
        };
        let mut h = ProtocolBHost::new(cfg, now).unwrap();
        let mut sent = Vec::new();
        let prog = program(3000);
        for (i, chunk) in chunks.iter().enumerate() {
            if i % 7 == 0 {
                load(&mut h, now, &prog);
            }
            h.handle_input(now, chunk);
            if let Some(out) = h.poll_transmit(now) {
                prop_assert!(out.len() <= 64);
                sent.extend(out);
            }
            if take_events {
                events(&mut h);
            }
            prop_assert!(h.punch_held() <= 4096);
            prop_assert!(h.program_buffered() <= prog.len());
        }
    }
}

/// A line faster than its nominal rate: the DC3 that ends the read comes before the host's
/// estimate of the EOR's arrival, after the board had stopped the program before, and the
/// next read's DC1 follows at once. No DC3 comes after that DC1, so by the EOR's latest
/// arrival the host takes the read as ended and the DC1 as the next read's (protocol notes
/// 20); a second DC3 with no DC1 between ends the read at once.
#[test]
fn a_read_that_ended_early_on_a_fast_line_still_ends() {
    let (mut h, t0, ct) = timed_host();
    let prog = program(4000);
    load(&mut h, t0, &prog);
    h.handle_input(t0, &[DC1]);
    let first = h.poll_transmit(t0).unwrap();
    h.handle_input(t0, &[DC3]);
    h.handle_input(t0, &[DC1]);
    let mut sent = first;
    sent.extend(drain_tx(&mut h, t0));
    assert_eq!(sent, prog);
    let estimate = t0 + ct * prog.len() as u32;
    let early = estimate - ct * 600;
    h.handle_input(early, &[DC3]);
    h.handle_input(early, &[DC1]);
    assert!(
        !done(&events(&mut h)),
        "not before the EOR has surely arrived"
    );
    let next = program(1000);
    let deadline = h.poll_timeout().expect("a deadline for the next read");
    assert!(deadline > estimate, "{deadline:?} {estimate:?}");
    h.handle_timeout(deadline);
    assert!(done(&events(&mut h)));
    // The next program goes on that DC1.
    load(&mut h, deadline, &next);
    assert_eq!(drain_tx(&mut h, deadline), next);

    // Two DC3s with no DC1 between: the second ends the read.
    let (mut h, t0, ct) = timed_host();
    load(&mut h, t0, &prog);
    h.handle_input(t0, &[DC1]);
    assert!(h.poll_transmit(t0).is_some());
    h.handle_input(t0, &[DC3]);
    h.handle_input(t0, &[DC1]);
    drain_tx(&mut h, t0);
    let early = t0 + ct * (prog.len() as u32 - 600);
    h.handle_input(early, &[DC3]);
    assert!(done(&end_read(&mut h, early + ct * 10)));
}
