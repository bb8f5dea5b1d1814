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

/// Without code transposition (item 14 "no") a fixed-length message is its N bytes as they
/// are, whatever they hold (appendix: start code, end code and BCC are data).
#[test]
fn mode_4_fixed_length_without_transposition_sends_and_receives_bare_data() {
    let (mut m, mut p) = nonproc(OperationMode::Four, Some(4));
    m.frame.transposition = false;
    p.frame.transposition = false;
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
    st.frame.transposition = false;
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

/// Fixed length with code transposition on, the module's initial value (§4-3 items 14–15,
/// §5-5; FFU120B notes 9): N data bytes travel as 2N hex characters, with no start code, end
/// code or BCC. Item 14's example, one byte 12h as the two characters "1" "2", and the
/// appendix's three cases: fewer characters than a message wait for the rest, exactly a
/// message is one message, more start the next one.
#[test]
fn fixed_length_with_transposition_is_2n_hex_characters_both_ways() {
    let mut st = settings(OperationMode::Four);
    st.fixed_length = Some(4);
    let mut s = Solo::new(st);
    s.cmd(MasterCommand::Send {
        id: 1,
        data: vec![0x12, 0x34, 0xAB, 0xFF],
    });
    assert_eq!(s.take_sent().concat(), b"1234ABFF");
    assert!(done(&s.take_events()).contains(&(1, Ok(Reply::Sent { bytes: 8 }))));
    let received = |s: &mut Solo| -> Vec<Vec<u8>> {
        s.take_events()
            .into_iter()
            .filter_map(|e| match e {
                MasterEvent::Received { data } => Some(data),
                _ => None,
            })
            .collect()
    };
    // Reception data < fixed length: the module (and the host) waits for the rest.
    s.input(b"1234AB");
    assert!(received(&mut s).is_empty());
    // = fixed length: one message of N bytes, not two of N characters.
    s.input(b"FF");
    assert_eq!(received(&mut s), [vec![0x12, 0x34, 0xAB, 0xFF]]);
    // > fixed length: N bytes, and the rest starts the next message.
    s.input(b"00010203040506070");
    assert_eq!(received(&mut s), [vec![0, 1, 2, 3], vec![4, 5, 6, 7]]);
    s.input(b"8090A");
    assert!(received(&mut s).is_empty(), "6 of 8 characters");
    s.input(b"0B");
    assert_eq!(received(&mut s), [vec![0x08, 0x09, 0x0A, 0x0B]]);
    // A character that is not a hex digit spoils its own message only (text form, §5-6);
    // the next one is read on its boundary.
    s.input(b"12G4ABFF0000002A");
    assert_eq!(received(&mut s), [vec![0, 0, 0, 0x2A]]);
    let c = s.m.counters();
    assert_eq!((c.messages_received, c.receive_errors.text_form), (5, 1));
    // Exactly N bytes of data are taken from a client, as before.
    s.cmd(MasterCommand::Send {
        id: 2,
        data: vec![1; 8],
    });
    let e = done(&s.take_events()).pop().unwrap().1.unwrap_err();
    assert!(e.to_string().contains("exactly 4"), "{e}");
}

/// The same against the simulated module, in ASCII and in EBCDIC (item 13: the hex
/// characters are the code's own): what the host sends arrives as one N-byte message in the
/// module's receive message number, and what the PLC sends reaches the host as one message.
#[test]
fn fixed_length_with_transposition_against_the_simulated_module() {
    for code in [
        crate::fuji::frame::TransmissionCode::Ascii,
        crate::fuji::frame::TransmissionCode::Ebcdic,
    ] {
        let (mut m, mut p) = nonproc(OperationMode::Four, Some(12));
        m.frame.code = code;
        p.frame.code = code;
        let mut r = pair(m, p);
        r.command_a(MasterCommand::Send {
            id: 1,
            data: b"LOT-00000007".to_vec(),
        });
        r.command_b(MicrexCommand::QueueTransfer {
            message: 0,
            data: b"SCAN-0000042".to_vec(),
        });
        r.settle(Duration::from_secs(1));
        assert_eq!(r.a_sent.len(), 24, "{code:?}: 2N characters");
        let hex: Vec<u8> = hex::encode_upper(b"LOT-00000007")
            .bytes()
            .map(|c| code.encode_char(c))
            .collect();
        assert_eq!(r.a_sent, hex, "{code:?}");
        let module: Vec<_> = r
            .take_b_events()
            .into_iter()
            .filter(|e| matches!(e, MicrexEvent::TransferReceived { .. }))
            .collect();
        assert_eq!(
            module,
            [MicrexEvent::TransferReceived {
                station: 0,
                message: 5,
                data: b"LOT-00000007".to_vec()
            }],
            "{code:?}"
        );
        let host: Vec<_> = r
            .take_a_events()
            .into_iter()
            .filter(|e| matches!(e, MasterEvent::Received { .. }))
            .collect();
        assert_eq!(
            host,
            [MasterEvent::Received {
                data: b"SCAN-0000042".to_vec()
            }],
            "{code:?}"
        );
    }
}

/// The messages among `events`.
fn messages(events: Vec<MasterEvent>) -> Vec<Vec<u8>> {
    events
        .into_iter()
        .filter_map(|e| match e {
            MasterEvent::Received { data } => Some(data),
            _ => None,
        })
        .collect()
}

/// A character that came with a parity (or framing) error, reported by the serial driver or
/// found by the gateway's own check, ends its message as a receive error (§5-6: "receiving
/// ends to error"), even when what remains of the message would read well; the next message
/// arrives as usual. Outside a message (before a start code) it spoils nothing.
#[test]
fn a_character_error_ends_its_message_and_the_next_one_arrives() {
    // Variable length: ":4142" + a lost character + "43" would be a good 3-byte text.
    let mut s = Solo::new(settings(OperationMode::Four));
    s.input(b":4142");
    s.m.handle_line_error(s.now, LineError::Parity);
    s.input(b"43\r:44\r");
    assert_eq!(messages(s.take_events()), [b"D".to_vec()]);
    s.m.handle_line_error(s.now, LineError::Framing);
    s.input(b":45\r");
    assert_eq!(messages(s.take_events()), [b"E".to_vec()]);
    let c = s.m.counters();
    assert_eq!(
        (c.receive_errors.character, c.receive_errors.total()),
        (1, 1)
    );
    assert_eq!((c.line_errors.parity, c.line_errors.framing), (1, 1));

    // Fixed length 2 with transposition: the lost character keeps its place, so the next
    // message is read on its boundary.
    let mut st = settings(OperationMode::Five);
    st.fixed_length = Some(2);
    let mut s = Solo::new(st);
    s.input(b"41");
    s.m.handle_line_error(s.now, LineError::Parity);
    s.input(b"24344");
    assert_eq!(messages(s.take_events()), [b"CD".to_vec()]);
    // The lost character was the message's last: it ends there.
    s.input(b"414");
    s.m.handle_line_error(s.now, LineError::Parity);
    s.input(b"4546");
    assert_eq!(messages(s.take_events()), [b"EF".to_vec()]);
    assert_eq!(s.m.counters().receive_errors.character, 2);
}

/// In the command set a reply with a character error is a corrupted reply: the request goes
/// again at once, as for a BCC error, and the good reply completes it.
#[test]
fn a_reply_with_a_character_error_is_sent_again() {
    let mut s = Solo::new(settings(OperationMode::One));
    s.cmd(read(1, 0, Module::D, 0, 1));
    let first = s.take_sent().concat();
    let reply = b":0000000507000002000112AB\r";
    s.input(&reply[..9]);
    s.m.handle_line_error(s.now, LineError::Parity);
    s.input(&reply[10..]);
    assert_eq!(s.take_sent().concat(), first, "sent again");
    assert!(done(&s.take_events()).is_empty());
    s.input(reply);
    let d = done(&s.take_events());
    assert_eq!(words_of(&d[0].1), [0x12AB]);
    let c = s.m.counters();
    assert_eq!(c.stations[&0].corrupted_replies, 1);
    assert_eq!(c.receive_errors.character, 1);
}
