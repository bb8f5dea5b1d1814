use super::*;
use crate::fuji::frame::{BccCalc, BccCode, BccKind, BccRange, FrameDecoder, ReceiveErrorKind};

/// The module alone, driven by a scripted host.
struct Host {
    plc: Micrex,
    now: Instant,
    frame: FrameSettings,
}

impl Host {
    fn new(cfg: MicrexConfig) -> Host {
        Host {
            frame: cfg.frame.clone(),
            plc: Micrex::new(cfg).unwrap(),
            now: Instant::now(),
        }
    }

    /// Sends `text` framed and returns the reply texts after the processing delay.
    fn ask(&mut self, text: &[u8]) -> Vec<Vec<u8>> {
        let line = self.frame.encode(text);
        self.raw(&line)
    }

    fn raw(&mut self, line: &[u8]) -> Vec<Vec<u8>> {
        self.plc.handle_input(self.now, line);
        let bytes = self.drain();
        let mut d = FrameDecoder::command_set(&self.frame);
        d.decode(&bytes).into_iter().map(|r| r.unwrap()).collect()
    }

    /// Everything the module sends up to its last deadline.
    fn drain(&mut self) -> Vec<u8> {
        let mut out = Vec::new();
        loop {
            while let Some(b) = self.plc.poll_transmit(self.now) {
                out.extend(b);
            }
            match self.plc.poll_timeout() {
                Some(t) => {
                    self.now = self.now.max(t);
                    self.plc.handle_timeout(self.now);
                }
                None => return out,
            }
        }
    }

    fn events(&mut self) -> Vec<MicrexEvent> {
        std::iter::from_fn(|| self.plc.poll_event()).collect()
    }

    fn command(&mut self, c: MicrexCommand) {
        self.plc.handle_command(self.now, c);
    }
}

fn mode1() -> MicrexConfig {
    MicrexConfig::new(OperationMode::One)
}

#[test]
fn the_reply_leaves_after_the_processing_delay() {
    let mut h = Host::new(mode1());
    h.command(MicrexCommand::SetWords {
        station: 0,
        module: Module::M,
        address: 0,
        words: vec![0x12AB],
    });
    h.plc.handle_input(h.now, b":000000010400000200\r");
    assert_eq!(h.plc.poll_transmit(h.now), None);
    let due = h.plc.poll_timeout().unwrap();
    assert_eq!(due, h.now + Duration::from_millis(5));
    h.plc.handle_timeout(due - Duration::from_nanos(1));
    assert_eq!(
        h.plc.poll_transmit(due),
        Some(b":0000000107000002000112AB\r".to_vec())
    );
    assert_eq!(h.plc.poll_timeout(), None);
    assert_eq!(
        h.events(),
        vec![
            MicrexEvent::Request {
                station: 0,
                cmnd: 0,
                mode: 0,
                moln: 1,
                text: vec![0, 0, 0, 1, 4, 0, 0, 2, 0],
            },
            MicrexEvent::Read {
                station: 0,
                module: Module::M,
                address: 0,
                bytes: 2
            },
            MicrexEvent::Replied {
                station: 0,
                sta: 0,
                line_bytes: 26,
            },
        ]
    );
}

#[test]
fn the_plc_refuses_with_every_sta_code() {
    let mut cfg = mode1();
    cfg.messages = vec![1];
    cfg.files = vec![(40, FileType::Di, 16)];
    let mut h = Host::new(cfg);
    let sta = |h: &mut Host, text: &[u8]| -> u8 {
        let r = h.ask(text);
        assert_eq!(r.len(), 1, "{text:02X?}");
        let t = CommandText::parse(&r[0]).unwrap();
        assert!(
            t.body.is_empty() || t.second == 0,
            "error replies are the header alone"
        );
        t.second
    };
    // 20: a command the module does not have.
    assert_eq!(sta(&mut h, &[0x02, 0, 0, 5, 0]), 0x20);
    assert_eq!(sta(&mut h, &[0x01, 0, 0x07, 5, 0]), 0x20);
    // 24: no such module; a file not defined; P-link modules without the card.
    assert_eq!(sta(&mut h, &[0, 0, 0, 0x30, 4, 0, 0, 2, 0]), 0x24);
    assert_eq!(sta(&mut h, &[0, 0, 0, 0x06, 4, 0, 0, 2, 0]), 0x24);
    assert_eq!(sta(&mut h, &[0, 0, 0, 0x78, 4, 0, 0, 2, 0]), 0x24);
    // 21: odd count for a 16-bit area, 6 bytes of a 32-bit one, zero, over 212, a write
    // whose count is not its data.
    assert_eq!(sta(&mut h, &[0, 0, 0, 5, 4, 0, 0, 3, 0]), 0x21);
    assert_eq!(sta(&mut h, &[0, 0, 0, 0x0A, 4, 0, 0, 6, 0]), 0x21);
    assert_eq!(sta(&mut h, &[0, 0, 0, 5, 4, 0, 0, 0, 0]), 0x21);
    assert_eq!(sta(&mut h, &[0, 0, 0, 0x0E, 4, 0, 0, 216, 0]), 0x21);
    assert_eq!(sta(&mut h, &[1, 0, 0, 5, 6, 0, 0, 4, 0, 1, 2]), 0x21);
    assert_eq!(sta(&mut h, &[0, 0, 0, 5, 3, 0, 0, 2]), 0x21);
    // 32: beyond the module (D has 64 words here).
    assert_eq!(sta(&mut h, &[0, 0, 0, 5, 4, 63, 0, 4, 0]), 0x32);
    assert_eq!(sta(&mut h, &[0, 0, 0, 5, 4, 63, 0, 2, 0]), 0x00);
    // 12: write protection.
    h.command(MicrexCommand::Protect {
        station: 0,
        module: Module::D,
        address: 4,
        words: 1,
    });
    assert_eq!(sta(&mut h, &[1, 0, 0, 5, 8, 3, 0, 4, 0, 0, 1, 0, 2]), 0x12);
    assert_eq!(
        sta(&mut h, &[1, 0, 5, 5, 0]),
        0x12,
        "clear of a protected module"
    );
    assert_eq!(sta(&mut h, &[1, 0, 0, 5, 6, 5, 0, 2, 0, 0, 1]), 0x00);
    h.command(MicrexCommand::Unprotect { station: 0 });
    assert_eq!(sta(&mut h, &[1, 0, 0, 5, 6, 4, 0, 2, 0, 0, 1]), 0x00);
    // 22: interlock, for reads, writes and clears.
    h.command(MicrexCommand::SetInterlock {
        station: 0,
        on: true,
    });
    assert_eq!(sta(&mut h, &[0, 0, 0, 5, 4, 0, 0, 2, 0]), 0x22);
    assert_eq!(sta(&mut h, &[1, 0, 5, 5, 0]), 0x22);
    h.command(MicrexCommand::SetInterlock {
        station: 0,
        on: false,
    });
    // A7: a transfer to a message module that is not registered.
    assert_eq!(sta(&mut h, &[0x90, 0, 0, 2, 1, 9]), 0xA7);
    assert_eq!(sta(&mut h, &[0x90, 0, 0, 1, 1, 9]), 0x00);
    // A DI file: 32-bit, low byte first, attribute 04 in the read reply.
    assert_eq!(
        sta(
            &mut h,
            &[1, 0, 0, 40, 8, 1, 0, 4, 0, 0x78, 0x56, 0x34, 0x12]
        ),
        0
    );
    let r = h.ask(&[0, 0, 0, 40, 4, 1, 0, 4, 0]);
    assert_eq!(
        r[0],
        [0, 0, 0, 40, 9, 1, 0, 4, 0, 4, 0x78, 0x56, 0x34, 0x12]
    );
    let ev = h.events();
    let refused: Vec<u8> = ev
        .iter()
        .filter_map(|e| match e {
            MicrexEvent::Refused { sta, .. } => Some(sta.code()),
            _ => None,
        })
        .collect();
    for code in [0x12, 0x20, 0x21, 0x22, 0x24, 0x32, 0xA7] {
        assert!(refused.contains(&code), "{code:02X} in {refused:02X?}");
    }
}

#[test]
fn write_protection_and_memory_per_module() {
    let mut h = Host::new(mode1());
    h.ask(&[1, 0, 0, 5, 8, 2, 0, 4, 0, 0x12, 0x34, 0x56, 0x78]);
    assert_eq!(h.plc.words(0, Module::D, 2, 2), Some(vec![0x1234, 0x5678]));
    assert_eq!(h.plc.words(0, Module::M, 2, 2), Some(vec![0, 0]));
    assert_eq!(h.plc.words(0, Module::D, 63, 2), None);
    h.ask(&[1, 0, 5, 5, 0]);
    assert_eq!(h.plc.words(0, Module::D, 2, 2), Some(vec![0, 0]));
    let ev = h.events();
    assert!(ev.contains(&MicrexEvent::Written {
        station: 0,
        module: Module::D,
        address: 2,
        words: vec![0x1234, 0x5678]
    }));
    assert!(ev.contains(&MicrexEvent::Cleared {
        station: 0,
        module: Module::D
    }));
}

#[test]
fn receive_errors_get_no_reply() {
    let mut cfg = mode1();
    cfg.frame.bcc = BccKind::Set1;
    cfg.frame.bcc_range = BccRange::StartTextEnd;
    let mut h = Host::new(cfg);
    // The appendix request with its BCC AE, then with a wrong one.
    assert_eq!(h.raw(b":000000010400000200\rAE").len(), 1);
    assert!(h.raw(b":000000010400000200\rAF").is_empty());
    // BYTEN that does not count the body; unreadable text; garbage.
    let mut bad = h.frame.encode(&[0, 0, 0, 1, 5, 0, 0, 2, 0]);
    assert!(h.raw(&bad).is_empty());
    bad = b":00000001040000020G\r".to_vec();
    bad.extend(crate::fuji::bcc::hex2(crate::fuji::bcc::sum8(&bad)));
    assert!(h.raw(&bad).is_empty());
    assert!(h.raw(b"xx:").is_empty());
    let c = h.plc.receive_counts();
    assert_eq!((c.bcc, c.text_form, c.start_code), (1, 2, 1), "{c:?}");
    let kinds: Vec<ReceiveErrorKind> = h
        .events()
        .iter()
        .filter_map(|e| match e {
            MicrexEvent::ReceiveError { error } => Some(error.kind()),
            _ => None,
        })
        .collect();
    assert_eq!(
        kinds,
        vec![
            ReceiveErrorKind::Bcc,
            ReceiveErrorKind::TextForm,
            ReceiveErrorKind::TextForm,
            ReceiveErrorKind::StartCode
        ]
    );
}

#[test]
fn several_stations_each_with_its_own_memory_silent_for_others() {
    let mut cfg = MicrexConfig::new(OperationMode::Three);
    cfg.stations = vec![1, 12];
    let mut h = Host::new(cfg);
    // Write to station 12 (RSNO 12h), read both.
    let r = h.ask(&[1, 0x12, 0, 5, 6, 0, 0, 2, 0, 0xAA, 0xBB]);
    assert_eq!(r[0][2], 0x80, "MODE with its MSB in mode 3");
    let r12 = h.ask(&[0, 0x12, 0, 5, 4, 0, 0, 2, 0]);
    let r1 = h.ask(&[0, 0x01, 0, 5, 4, 0, 0, 2, 0]);
    assert_eq!(r12[0][10..], [0xAA, 0xBB]);
    assert_eq!(r1[0][10..], [0, 0]);
    // Station 13, and an RSNO that is not BCD: silence.
    assert!(h.ask(&[0, 0x13, 0, 5, 4, 0, 0, 2, 0]).is_empty());
    assert!(h.ask(&[0, 0x1A, 0, 5, 4, 0, 0, 2, 0]).is_empty());
    // Transfers are refused over RS-485.
    let r = h.ask(&[0x90, 0x01, 0, 1, 1, 5]);
    assert_eq!(r[0][1], 0xA7);
    h.command(MicrexCommand::QueueTransfer {
        message: 1,
        data: vec![1],
    });
    assert!(matches!(
        h.events().last(),
        Some(MicrexEvent::CommandRefused { .. })
    ));
}

#[test]
fn fault_hooks_silence_corrupt_and_cut_replies() {
    let mut cfg = mode1();
    cfg.frame.bcc = BccKind::Set2;
    cfg.frame.bcc_range = BccRange::TextEnd;
    cfg.frame.bcc_calc = BccCalc::Crc16;
    cfg.frame.bcc_code = BccCode::Binary;
    let mut h = Host::new(cfg);
    let read = [0, 0, 0, 5, 4, 0, 0, 2, 0];
    h.command(MicrexCommand::SetSilent {
        station: 0,
        on: true,
    });
    assert!(h.ask(&read).is_empty());
    h.command(MicrexCommand::SetSilent {
        station: 0,
        on: false,
    });
    assert_eq!(h.ask(&read).len(), 1);
    // A corrupted BCC: the host's decoder refuses the reply.
    h.command(MicrexCommand::CorruptNextBcc { station: 0 });
    h.plc.handle_input(h.now, &h.frame.encode(&read));
    let bytes = h.drain();
    let mut d = FrameDecoder::command_set(&h.frame);
    let out = d.decode(&bytes);
    assert!(matches!(out[..], [Err(ReceiveError::Bcc(_))]), "{out:?}");
    // Only the next reply.
    assert_eq!(h.ask(&read).len(), 1);
    // Cut short: no whole text.
    h.command(MicrexCommand::DropReplyBytes {
        station: 0,
        count: 2,
    });
    assert!(h.ask(&read).is_empty());
    let faults = h
        .events()
        .iter()
        .filter(|e| matches!(e, MicrexEvent::Fault { .. }))
        .count();
    assert_eq!(faults, 3);
    // Hooks for a station that is not simulated are refused.
    h.command(MicrexCommand::SetSilent {
        station: 9,
        on: true,
    });
    assert!(matches!(
        h.events()[..],
        [MicrexEvent::CommandRefused { .. }]
    ));
}

#[test]
fn plc_transfers_wait_for_the_reply_in_progress() {
    let mut h = Host::new(mode1());
    h.plc
        .handle_input(h.now, &h.frame.encode(&[0, 0, 0, 5, 4, 0, 0, 2, 0]));
    h.command(MicrexCommand::QueueTransfer {
        message: 7,
        data: vec![0x34, 0x12],
    });
    // The reply first, then the transfer, which nobody answers.
    assert_eq!(h.plc.poll_transmit(h.now), None);
    let bytes = h.drain();
    let text = String::from_utf8(bytes).unwrap();
    assert_eq!(
        text,
        ":00000005070000020001 0000\r:90000007023412\r".replace(' ', "")
    );
    assert!(h.events().contains(&MicrexEvent::TransferSent {
        message: 7,
        bytes: 16
    }));
    assert_eq!(h.plc.poll_timeout(), None);
}

#[test]
fn start_code_none_forgets_a_partial_text_after_a_silence() {
    let mut cfg = mode1();
    cfg.frame.start_code = StartCode::None;
    let mut h = Host::new(cfg);
    let line = h.frame.encode(&[0, 0, 0, 5, 4, 0, 0, 2, 0]);
    h.plc.handle_input(h.now, &line[..5]);
    h.now += Duration::from_millis(100);
    assert_eq!(h.raw(&line).len(), 1);
}

/// The messages the module stored in its receive message number.
fn stored(h: &mut Host, message: u8) -> Vec<Vec<u8>> {
    h.events()
        .into_iter()
        .filter_map(|e| match e {
            MicrexEvent::TransferReceived {
                message: m, data, ..
            } if m == message => Some(data),
            _ => None,
        })
        .collect()
}

/// Fixed length N without transposition: every N bytes are a message, whatever they hold
/// (appendix), and bytes beyond N start the next one.
#[test]
fn non_procedure_fixed_length_messages_arrive_whole() {
    let mut cfg = MicrexConfig::new(OperationMode::Five);
    cfg.fixed_length = Some(3);
    cfg.frame.transposition = false;
    cfg.receive_message = 9;
    let mut h = Host::new(cfg);
    h.plc.handle_input(h.now, b"AB");
    h.plc.handle_input(h.now, b"CDEFG");
    assert_eq!(stored(&mut h, 9), vec![b"ABC".to_vec(), b"DEF".to_vec()]);
}

/// With code transposition on (the initial value, §4-3 items 14–15) the module takes 2N hex
/// characters as one N-byte message, and sends N bytes as 2N characters; a character that is
/// not a hex digit is a text form error (§5-6) of that message alone.
#[test]
fn non_procedure_fixed_length_with_transposition_is_2n_characters() {
    let mut cfg = MicrexConfig::new(OperationMode::Four);
    cfg.fixed_length = Some(3);
    cfg.receive_message = 9;
    let mut h = Host::new(cfg);
    h.plc.handle_input(h.now, b"AB");
    h.plc.handle_input(h.now, b"CDEF");
    assert_eq!(stored(&mut h, 9), vec![vec![0xAB, 0xCD, 0xEF]]);
    h.plc.handle_input(h.now, b"1Z3456414243");
    assert_eq!(stored(&mut h, 9), vec![b"ABC".to_vec()]);
    assert_eq!(h.plc.receive_counts().text_form, 1);
    h.command(MicrexCommand::QueueTransfer {
        message: 0,
        data: vec![0x12, 0x00, 0xFE],
    });
    assert_eq!(h.drain(), b"1200FE");
}

#[test]
fn invalid_configurations_are_refused() {
    let mut c = mode1();
    c.stations = vec![100];
    assert!(matches!(
        Micrex::new(c),
        Err(MicrexConfigError::Station { station: 100 })
    ));
    let mut c = mode1();
    c.stations = (0..32).collect();
    assert!(Micrex::new(c).is_err());
    let mut c = mode1();
    c.files = vec![(29, FileType::Si, 10)];
    assert!(matches!(
        Micrex::new(c),
        Err(MicrexConfigError::File { n: 29 })
    ));
    let mut c = mode1();
    c.fixed_length = Some(4);
    assert!(Micrex::new(c).is_err());
    let mut c = mode1();
    c.frame.bcc = BccKind::Set1;
    c.frame.bcc_calc = BccCalc::Crc16;
    let e = Micrex::new(c).unwrap_err().to_string();
    assert!(e.contains("F2"), "{e}");
}

#[test]
fn a_host_that_does_not_wait_fills_the_buffer() {
    let mut h = Host::new(mode1());
    let line = h.frame.encode(&[0, 0, 0, 5, 4, 0, 0, 2, 0]);
    for _ in 0..MAX_PENDING + 3 {
        h.plc.handle_input(h.now, &line);
    }
    assert_eq!(h.plc.receive_counts().buffer_full, 3);
    let bytes = h.drain();
    let mut d = FrameDecoder::command_set(&h.frame);
    assert_eq!(d.decode(&bytes).len(), MAX_PENDING);
}

/// A character the module's UART received with a parity error ends its text as a receiving
/// error (§5-6): that message is not stored (a request gets no reply), the next one is.
#[test]
fn a_character_error_ends_the_modules_text_and_the_next_one_is_stored() {
    let mut cfg = MicrexConfig::new(OperationMode::Four);
    cfg.receive_message = 9;
    let mut h = Host::new(cfg);
    h.plc.handle_input(h.now, b":4142");
    h.plc.handle_line_error(h.now, LineError::Parity);
    h.plc.handle_input(h.now, b"43\r:44\r");
    assert_eq!(stored(&mut h, 9), vec![b"D".to_vec()]);
    assert_eq!(h.plc.receive_counts().character, 1);

    let mut h = Host::new(mode1());
    let line = h.frame.encode(&[0, 0, 0, 5, 4, 0, 0, 2, 0]);
    h.plc.handle_input(h.now, &line[..6]);
    h.plc.handle_line_error(h.now, LineError::Framing);
    h.plc.handle_input(h.now, &line[7..]);
    assert!(h.drain().is_empty(), "no reply to a text received in error");
    assert_eq!(h.raw(&line).len(), 1, "the next request is answered");
}
