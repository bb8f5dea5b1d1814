//! Modes 4 and 5 (FFU120B §5-5; FFU120B notes 9): non-procedure messages both ways, fixed and
//! variable length, against the simulated module and a scripted one.

use super::*;

fn nonproc(mode: OperationMode, fixed: Option<usize>) -> (MasterSettings, MicrexConfig) {
    let mut m = settings(mode);
    m.fixed_length = fixed;
    let mut p = plc(mode, &[0]);
    p.fixed_length = fixed;
    p.receive_message = 5;
    (m, p)
}

#[test]
fn modes_4_and_5_variable_length_messages_both_ways() {
    for mode in [OperationMode::Four, OperationMode::Five] {
        let (m, p) = nonproc(mode, None);
        let mut r = pair(m, p);
        r.command_a(MasterCommand::Send {
            id: 1,
            data: b"HELLO".to_vec(),
        });
        r.command_b(MicrexCommand::QueueTransfer {
            message: 0,
            data: b"BARCODE 42".to_vec(),
        });
        r.settle(Duration::from_secs(1));
        let ev = r.take_a_events();
        assert!(ev.contains(&MasterEvent::Done {
            id: 1,
            station: 0,
            result: Ok(Reply::Sent { bytes: 12 })
        }));
        assert!(ev.contains(&MasterEvent::Received {
            data: b"BARCODE 42".to_vec()
        }));
        // Variable length: start code, transposed text, end code (appendix).
        assert_eq!(r.a_sent, b":48454C4C4F\r");
        assert!(r.take_b_events().contains(&MicrexEvent::TransferReceived {
            station: 0,
            message: 5,
            data: b"HELLO".to_vec()
        }));
        let e = {
            r.command_a(MasterCommand::Send {
                id: 2,
                data: vec![0; 217],
            });
            done(&r.take_a_events()).pop().unwrap().1.unwrap_err()
        };
        assert!(e.to_string().contains("1 to 216"), "{e}");
        assert_eq!(r.a.counters().messages_received, 1);
    }
}

/// EBCDIC (items 13, 14; FFU120B notes 10): a mode-4 message both ways between the host and
/// the simulated module, every character of the frame in EBCDIC, with an add BCC over start,
/// text and end; and the command set in EBCDIC (a read answered).
#[test]
fn an_ebcdic_round_trip() {
    let (mut m, mut p) = nonproc(OperationMode::Four, None);
    for f in [&mut m.frame, &mut p.frame] {
        f.code = crate::fuji::frame::TransmissionCode::Ebcdic;
        f.bcc = BccKind::Set1;
        f.bcc_range = BccRange::StartTextEnd;
    }
    let mut r = pair(m, p);
    r.command_a(MasterCommand::Send {
        id: 1,
        data: b"OK".to_vec(),
    });
    r.command_b(MicrexCommand::QueueTransfer {
        message: 0,
        data: vec![0x00, 0xC1, 0xFF],
    });
    r.settle(Duration::from_secs(1));
    // ':' "4F4B" CR and the BCC "F7" (7A + F4 + C6 + F4 + C2 + 0D = 3F7), all EBCDIC.
    assert_eq!(r.a_sent, [0x7A, 0xF4, 0xC6, 0xF4, 0xC2, 0x0D, 0xC6, 0xF7]);
    assert!(r.take_b_events().contains(&MicrexEvent::TransferReceived {
        station: 0,
        message: 5,
        data: b"OK".to_vec()
    }));
    assert!(r.take_a_events().contains(&MasterEvent::Received {
        data: vec![0x00, 0xC1, 0xFF]
    }));
    assert_eq!(r.a.counters().receive_errors, Default::default());

    let mut m = settings(OperationMode::One);
    m.frame.code = crate::fuji::frame::TransmissionCode::Ebcdic;
    let mut p = plc(OperationMode::One, &[0]);
    p.frame = m.frame.clone();
    let mut r = pair(m, p);
    r.command_a(MasterCommand::Request {
        id: 7,
        station: 0,
        request: Request::read_words(Module::D, 0, 2).unwrap(),
    });
    r.settle(Duration::from_secs(1));
    let d = done(&r.take_a_events());
    assert!(
        matches!(d.as_slice(), [(7, Ok(Reply::Read { .. }))]),
        "{d:?}"
    );
    assert_eq!(r.a_sent.first(), Some(&0x7A), "the start code in EBCDIC");
}

#[test]
fn mode_4_fixed_length_sends_and_receives_bare_data() {
    let (m, p) = nonproc(OperationMode::Four, Some(4));
    let mut r = pair(m, p);
    r.command_a(MasterCommand::Send {
        id: 1,
        data: b":AB\r".to_vec(),
    });
    r.command_b(MicrexCommand::QueueTransfer {
        message: 0,
        data: b"WXYZ".to_vec(),
    });
    r.settle(Duration::from_secs(1));
    assert_eq!(r.a_sent, b":AB\r", "no start code, end code or BCC added");
    let ev = r.take_a_events();
    assert!(ev.contains(&MasterEvent::Received {
        data: b"WXYZ".to_vec()
    }));
    assert!(r.take_b_events().contains(&MicrexEvent::TransferReceived {
        station: 0,
        message: 5,
        data: b":AB\r".to_vec()
    }));
    r.command_a(MasterCommand::Send {
        id: 2,
        data: b"ABC".to_vec(),
    });
    let e = done(&r.take_a_events()).pop().unwrap().1.unwrap_err();
    assert!(e.to_string().contains("exactly 4"), "{e}");
}

/// Fixed length has nothing to find a message's start by (§5-5): a partial message that the
/// line cut short is dropped after a silence of the reply time-out, and the next message is
/// read on its boundary; a message longer than N is N, and the rest starts the next one
/// (appendix). Variable length without transposition refuses data holding the end code.
#[test]
fn modes_4_5_fixed_length_realigns_after_a_silence_and_variable_refuses_the_end_code() {
    let mut st = settings(OperationMode::Five);
    st.fixed_length = Some(4);
    let mut s = Solo::new(st);
    s.input(b"AB");
    s.now += TIMEOUT;
    s.input(b"WXYZ12");
    let got: Vec<_> = s
        .take_events()
        .into_iter()
        .filter_map(|e| match e {
            MasterEvent::Received { data } => Some(data),
            _ => None,
        })
        .collect();
    assert_eq!(got, [b"WXYZ".to_vec()]);
    let c = s.m.counters();
    assert_eq!((c.partial_messages, c.receive_errors.text_form), (1, 1));
    s.input(b"34");
    assert!(s.take_events().contains(&MasterEvent::Received {
        data: b"1234".to_vec()
    }));
    assert_eq!(s.m.counters().messages_received, 2);

    let mut st = settings(OperationMode::Four);
    st.frame.transposition = false;
    let mut s = Solo::new(st);
    s.cmd(MasterCommand::Send {
        id: 1,
        data: b"AB\rC".to_vec(),
    });
    let e = done(&s.take_events()).pop().unwrap().1.unwrap_err();
    assert!(e.to_string().contains("end code"), "{e}");
    assert!(s.take_sent().is_empty());
    s.cmd(MasterCommand::Send {
        id: 2,
        data: b"ABC".to_vec(),
    });
    assert_eq!(s.take_sent(), [b":ABC\r".to_vec()]);
    assert_eq!(s.m.counters().messages_sent, 1);
}

#[test]
fn mode_4_waits_for_cs_and_mode_5_for_a_quiet_line() {
    // Mode 4 (RS-232C): nothing goes while CS is off.
    let mut s = Solo::new(settings(OperationMode::Four));
    s.m.handle_modem(
        s.now,
        ModemIn {
            cs: false,
            ..ModemIn::ALL_ON
        },
    );
    s.cmd(MasterCommand::Send {
        id: 1,
        data: b"A".to_vec(),
    });
    assert!(s.take_sent().is_empty());
    assert_eq!(s.m.poll_timeout(), None, "waiting for CS is no timer");
    s.m.handle_modem(s.now, ModemIn::ALL_ON);
    s.pump();
    assert_eq!(s.take_sent(), vec![b":41\r".to_vec()]);
    // Mode 5 (RS-485): CS does not exist; the host waits for two quiet characters.
    let mut s = Solo::new(settings(OperationMode::Five));
    s.m.handle_modem(
        s.now,
        ModemIn {
            cs: false,
            ..ModemIn::ALL_ON
        },
    );
    s.input(b":4");
    s.cmd(MasterCommand::Send {
        id: 1,
        data: b"A".to_vec(),
    });
    assert!(s.take_sent().is_empty());
    let quiet = s.m.poll_timeout().unwrap();
    assert_eq!(quiet, s.now + line().time_for_chars(2));
    s.advance_to(quiet);
    assert_eq!(s.take_sent(), vec![b":41\r".to_vec()]);
}
