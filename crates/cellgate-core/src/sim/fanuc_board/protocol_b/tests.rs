use super::*;
use crate::engine::Engine;
use crate::fanuc::Protocol;
use crate::fanuc::code::{DC4, NAK, SYN};
use crate::fanuc::message::Framing;
use crate::sim::fanuc_board::{BoardCommand, DEFAULT_ER_OFF_TIME, FanucBoard};

/// A board under a scripted host with a virtual clock.
struct Rig {
    board: FanucBoard,
    now: Instant,
    /// Bytes the board sent, oldest first.
    sent: Vec<u8>,
    events: Vec<BoardEvent>,
}

fn config(expansion: bool, code: CodeSystem, notify: bool) -> BoardConfig {
    BoardConfig {
        protocol: if expansion {
            Protocol::ExpansionB
        } else {
            Protocol::B
        },
        framing: Framing::new(code, crate::fanuc::EndCode::Cr),
        notify_alarm_reset: notify,
        consume_rate: 1000,
        ..BoardConfig::default()
    }
}

impl Rig {
    fn new(config: BoardConfig) -> Rig {
        let now = Instant::now();
        let mut rig = Rig {
            board: FanucBoard::new(config, now).unwrap(),
            now,
            sent: Vec::new(),
            events: Vec::new(),
        };
        rig.board.handle_modem(now, ModemIn::ALL_ON);
        rig.pump();
        rig
    }

    /// Takes everything the board wants to send now, and its events.
    fn pump(&mut self) {
        while let Some(b) = self.board.poll_transmit(self.now) {
            self.sent.extend(b);
        }
        self.collect();
    }

    fn collect(&mut self) {
        while let Some(e) = self.board.poll_event() {
            self.events.push(e);
        }
    }

    fn take(&mut self) -> Vec<u8> {
        self.pump();
        std::mem::take(&mut self.sent)
    }

    /// The next piece the board hands out.
    fn poll(&mut self) -> Option<Vec<u8>> {
        let piece = self.board.poll_transmit(self.now);
        self.collect();
        piece
    }

    fn command(&mut self, c: BoardCommand) {
        self.board.handle_command(self.now, c);
        self.collect();
    }

    fn input(&mut self, bytes: &[u8]) {
        self.board.handle_input(self.now, bytes);
        self.collect();
    }

    fn modem(&mut self, m: ModemIn) {
        self.board.handle_modem(self.now, m);
        self.collect();
    }

    /// Advances to `t`, firing every deadline on the way.
    fn run_until(&mut self, t: Instant) {
        while let Some(d) = self.board.poll_timeout() {
            if d > t {
                break;
            }
            self.now = self.now.max(d);
            self.board.handle_timeout(self.now);
            self.pump();
        }
        self.now = self.now.max(t);
        self.board.handle_timeout(self.now);
        self.pump();
    }

    fn advance(&mut self, d: Duration) {
        let t = self.now + d;
        self.run_until(t);
    }

    fn alarms(&self) -> Vec<CncAlarm> {
        self.events
            .iter()
            .filter_map(|e| match e {
                BoardEvent::Alarm { alarm, .. } => Some(*alarm),
                _ => None,
            })
            .collect()
    }

    fn cnc(&self) -> &Cnc {
        self.board.cnc()
    }
}

fn data(n: usize) -> Vec<u8> {
    vec![b'X'; n]
}

const ISO_DC3: u8 = 0x93;
const ISO_NAK: u8 = 0x95;
const ISO_SYN: u8 = 0x96;

#[test]
fn dc1_on_start_then_dc3_at_512_free_and_dc1_at_4096_free() {
    let mut r = Rig::new(config(false, CodeSystem::Iso, true));
    assert_eq!(r.take(), b"");
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
    // 8192 − 7679 = 513 free: still flowing; one more byte: 512 free → DC3 (93h in ISO).
    r.input(&data(7679));
    assert_eq!(r.take(), b"");
    r.input(&data(1));
    assert_eq!(r.take(), [ISO_DC3]);
    assert_eq!(r.cnc().free(), 512);
    // At 1000 B/s, 4096 free 3.584 s later: DC1.
    let dc1_at = r.board.poll_timeout().unwrap();
    assert_eq!(dc1_at - r.now, Duration::from_millis(3584));
    r.run_until(dc1_at - Duration::from_millis(1));
    assert_eq!(r.take(), b"");
    r.run_until(dc1_at);
    assert_eq!(r.take(), [DC1]);
    let c = r.board.flow_counters();
    assert_eq!((c.dc1_sent, c.dc3_sent), (2, 1));
}

#[test]
fn expansion_b_dc3_at_2560_free_ascii() {
    let mut r = Rig::new(config(true, CodeSystem::Ascii, true));
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
    r.input(&data(8192 - 2561));
    assert_eq!(r.take(), b"");
    r.input(&data(1));
    assert_eq!(r.take(), [DC3], "ASCII: DC3 without parity");
}

/// Fills the buffer to the DC3 and hands it out; returns the rig.
fn stopped(expansion: bool) -> Rig {
    // A CNC that reads next to nothing (1 byte a second; the clock stands still here).
    let mut r = Rig::new(BoardConfig {
        consume_rate: 1,
        ..config(expansion, CodeSystem::Iso, true)
    });
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
    r.input(&data(8192 - dc3_free(expansion) - 100));
    r.input(&data(100));
    assert_eq!(r.take(), [ISO_DC3]);
    r
}

#[test]
fn sr0856_only_past_the_allowance_b() {
    let mut r = stopped(false);
    r.input(&data(512));
    assert!(
        r.alarms().is_empty(),
        "512 after DC3 is within the allowance"
    );
    assert_eq!(r.board.flow_counters().max_overrun, 512);
    assert_eq!(r.take(), b"");
    r.input(&data(1));
    assert_eq!(r.alarms(), vec![CncAlarm::Sr0856BufferOverflow]);
    assert!(r.cnc().alarm().is_some());
    // The CNC alarm is posted: DC3 then NAK (§6.1.2 2 (7)).
    assert_eq!(r.take(), [ISO_DC3, ISO_NAK]);
    assert_eq!(r.board.flow_counters().overruns, 1);
}

#[test]
fn sr0856_only_past_2560_in_expansion_b() {
    let mut r = stopped(true);
    r.input(&data(1280));
    r.input(&data(1280));
    assert!(r.alarms().is_empty());
    r.input(&data(1));
    assert_eq!(r.alarms(), vec![CncAlarm::Sr0856BufferOverflow]);
}

#[test]
fn data_after_eor_is_ignored_and_the_read_ends_with_dc3() {
    let mut r = Rig::new(config(false, CodeSystem::Ascii, true));
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
    r.input(b"%\nO0001\nG00X0\nM30\n%\nO0002\nLOST\n");
    assert_eq!(r.take(), b"");
    r.advance(Duration::from_secs(1));
    let programs: Vec<_> = r
        .events
        .iter()
        .filter_map(|e| match e {
            BoardEvent::ProgramReceived(p) => Some(p.clone()),
            _ => None,
        })
        .collect();
    assert_eq!(programs.len(), 1);
    assert_eq!(&programs[0].data[..], b"%\nO0001\nG00X0\nM30\n%");
    assert_eq!(r.take(), [DC3], "end of the read (§6.1.1 1 (7))");
    assert_eq!(r.cnc().buffered(), 0, "data after EOR is ignored (§8.2)");
    r.input(b"MORE");
    assert!(r.events.contains(&BoardEvent::DataIgnored { bytes: 4 }));
    // A new read (next program) starts with DC1.
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
}

#[test]
fn no_flow_control_dc1_once_the_eor_is_buffered() {
    let mut r = Rig::new(config(false, CodeSystem::Ascii, true));
    r.command(BoardCommand::StartReading);
    r.take();
    let mut prog = b"%\nO1\n".to_vec();
    prog.extend(data(7680 - 6));
    prog.push(b'%');
    r.input(&prog);
    assert_eq!(r.take(), [DC3]);
    // 4096 free comes and goes: no DC1 (protocol notes 13); the CNC reads the EOR at
    // 7.68 s and the read ends with DC3.
    r.advance(Duration::from_millis(7679));
    assert_eq!(r.take(), b"");
    r.advance(Duration::from_millis(1));
    assert_eq!(r.take(), [DC3]);
    assert_eq!(r.board.flow_counters().dc1_sent, 1);
}

#[test]
fn autostart_reads_again_after_each_program() {
    let mut r = Rig::new(BoardConfig {
        autostart: true,
        consume_rate: 0,
        ..config(false, CodeSystem::Ascii, true)
    });
    assert_eq!(r.take(), [DC1]);
    r.input(b"%\nO1\n%");
    assert_eq!(r.take(), [DC3, DC1]);
    r.input(b"%\nO2\n%");
    assert_eq!(r.take(), [DC3, DC1]);
    assert_eq!(
        r.events
            .iter()
            .filter(|e| matches!(e, BoardEvent::ProgramReceived(_)))
            .count(),
        2
    );
}

#[test]
fn notices_with_notification_on_idle_receiving_punching() {
    // Idle: the notice alone (§6.1.2 1).
    let mut r = Rig::new(config(false, CodeSystem::Iso, true));
    r.command(BoardCommand::RaiseAlarm);
    assert_eq!(r.take(), [ISO_NAK]);
    r.command(BoardCommand::Reset);
    assert_eq!(r.take(), [ISO_SYN]);
    // Receiving: DC3 first (§6.1.2 2 (7)).
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
    r.input(b"%\nO1\nG0");
    r.command(BoardCommand::Reset);
    assert_eq!(r.take(), [ISO_DC3, ISO_SYN]);
    assert_eq!(r.cnc().buffered(), 0, "a reset loses the buffer (§8.2)");
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
    r.command(BoardCommand::RaiseAlarm);
    assert_eq!(r.take(), [ISO_DC3, ISO_NAK]);
    r.command(BoardCommand::Reset);
    r.take();
    // Punching: DC4 first (§6.1.2 2 (5)).
    r.command(BoardCommand::Punch(data(100)));
    let out = r.take();
    assert_eq!(out.first(), Some(&DC2));
    assert_eq!(out.last(), Some(&DC4));
    assert_eq!(out.len(), 102);
    r.command(BoardCommand::Punch(data(1000)));
    assert_eq!(r.poll(), Some(vec![DC2]));
    assert_eq!(r.poll(), Some(data(PUNCH_PIECE)));
    r.command(BoardCommand::RaiseAlarm);
    assert_eq!(r.take(), [DC4, ISO_NAK]);
    assert!(r.events.contains(&BoardEvent::PunchInterrupted {
        sent: PUNCH_PIECE,
        bytes: 1000
    }));
}

#[test]
fn notification_off_sends_dc3_and_turns_er_off_for_a_moment() {
    let mut r = Rig::new(BoardConfig {
        er_off_time: Duration::from_millis(500),
        ..config(false, CodeSystem::Ascii, false)
    });
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
    r.input(b"%\nO1\nG0");
    r.command(BoardCommand::RaiseAlarm);
    assert!(
        r.board.modem_out().er,
        "ER stays on until the DC3 is on the line"
    );
    assert_eq!(r.take(), [DC3], "no NAK with notification off");
    assert!(!r.board.modem_out().er, "then ER off (§6.4 (1))");
    r.advance(Duration::from_millis(499));
    assert!(!r.board.modem_out().er);
    r.advance(Duration::from_millis(1));
    assert!(r.board.modem_out().er);
    assert_eq!(r.take(), b"", "the CNC in alarm asks for nothing");
    r.advance(ER_ON_SETTLE);
    assert!(r.events.contains(&BoardEvent::ErSignal { on: false }));
    assert!(r.events.contains(&BoardEvent::ErSignal { on: true }));
    // A reset while idle: DC3, ER off again.
    r.command(BoardCommand::Reset);
    assert_eq!(r.take(), [DC3]);
    assert!(!r.board.modem_out().er);
    // Cycle start meanwhile: the DC1 waits for ER, and for the host to see it.
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), b"");
    r.advance(Duration::from_millis(500));
    assert!(r.board.modem_out().er);
    assert_eq!(r.take(), b"");
    r.advance(ER_ON_SETTLE);
    assert_eq!(r.take(), [DC1]);
}

#[test]
fn punch_out_honours_host_dc3_and_resumes_on_dc1_or_dc2() {
    for resume in [DC1, DC2, 0x11 | 0x80] {
        let mut r = Rig::new(config(false, CodeSystem::Iso, true));
        let tape: Vec<u8> = (0..200u8).collect();
        r.command(BoardCommand::Punch(tape.clone()));
        let mut got = Vec::new();
        assert_eq!(r.poll(), Some(vec![DC2]));
        got.extend(r.poll().unwrap());
        // The host stops the punch-out (DC3 with parity, ISO host).
        r.input(&[ISO_DC3]);
        assert_eq!(r.take(), b"", "stopped at once");
        r.advance(Duration::from_secs(5));
        assert_eq!(r.take(), b"");
        r.input(&[resume]);
        let rest = r.take();
        assert_eq!(rest.last(), Some(&DC4));
        got.extend(&rest[..rest.len() - 1]);
        assert!(got == tape, "punched bytes differ (resume {resume:#04x})");
        assert!(r.events.contains(&BoardEvent::PunchFinished { bytes: 200 }));
        assert!(
            r.events
                .contains(&BoardEvent::ControlReceived(ControlCode::Dc3))
        );
        assert_eq!(r.board.flow_counters().punched, 200);
    }
}

#[test]
fn cs_off_pauses_every_transmission() {
    let mut r = Rig::new(config(false, CodeSystem::Ascii, true));
    r.command(BoardCommand::Punch(data(100)));
    assert_eq!(r.poll(), Some(vec![DC2]));
    assert_eq!(r.poll(), Some(data(PUNCH_PIECE)));
    let cs_off = ModemIn {
        cs: false,
        ..ModemIn::ALL_ON
    };
    r.modem(cs_off);
    assert_eq!(r.take(), b"");
    r.advance(Duration::from_secs(1));
    assert_eq!(r.take(), b"");
    r.modem(ModemIn::ALL_ON);
    let rest = r.take();
    assert_eq!(rest.len(), 100 - PUNCH_PIECE + 1);
    assert_eq!(rest.last(), Some(&DC4));
}

#[test]
fn reset_during_punch_sends_dc4_then_syn_and_cs_holds_them() {
    let mut r = Rig::new(config(false, CodeSystem::Ascii, true));
    r.command(BoardCommand::Punch(data(1000)));
    assert_eq!(r.poll(), Some(vec![DC2]));
    assert_eq!(r.poll(), Some(data(PUNCH_PIECE)));
    r.modem(ModemIn {
        cs: false,
        ..ModemIn::ALL_ON
    });
    r.command(BoardCommand::Reset);
    assert_eq!(r.take(), b"");
    r.modem(ModemIn::ALL_ON);
    assert_eq!(r.take(), [DC4, SYN]);
    assert!(r.events.contains(&BoardEvent::PunchInterrupted {
        sent: PUNCH_PIECE,
        bytes: 1000
    }));
}

#[test]
fn punch_during_a_read_stops_the_host_first_and_resumes_after() {
    let mut r = Rig::new(config(false, CodeSystem::Ascii, true));
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
    r.input(b"%\nO1\nG0");
    r.command(BoardCommand::Punch(b"%\nO9\n%".to_vec()));
    assert_eq!(r.take(), b"\x13\x12%\nO9\n%\x14\x11");
    let before = r.cnc().buffered();
    r.input(b"G1");
    assert_eq!(r.cnc().buffered(), before + 2);
}

#[test]
fn a_late_host_dc3_after_the_punch_is_not_program_data() {
    let mut r = Rig::new(BoardConfig {
        consume_rate: 1,
        ..config(false, CodeSystem::Iso, true)
    });
    r.command(BoardCommand::StartReading);
    r.input(&data(7680));
    assert_eq!(r.take(), [DC1, ISO_DC3]);
    // Stopped already: no DC3 before the DC2; not 4096 free: no DC1 after the DC4.
    r.command(BoardCommand::Punch(b"AB".to_vec()));
    assert_eq!(r.take(), b"\x12AB\x14");
    r.input(&[ISO_DC3]);
    assert_eq!(r.cnc().buffered(), 7680);
    assert!(
        r.events
            .contains(&BoardEvent::ControlReceived(ControlCode::Dc3))
    );
    // Other bytes are the data part (overrun after the DC3, within the allowance).
    r.input(b"G1");
    assert_eq!(r.cnc().buffered(), 7682);
    assert!(r.alarms().is_empty());
}

#[test]
fn dr_off_raises_sr0855_while_reading() {
    let mut r = Rig::new(config(false, CodeSystem::Ascii, true));
    // Idle: no alarm.
    r.modem(ModemIn {
        dr: false,
        cd: false,
        cs: false,
    });
    assert!(r.alarms().is_empty());
    r.modem(ModemIn::ALL_ON);
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
    // Protocol B is RS-232-C: CD off counts too.
    r.modem(ModemIn {
        cd: false,
        ..ModemIn::ALL_ON
    });
    assert_eq!(r.alarms(), vec![CncAlarm::Sr0855DataSetReadyDown]);
    assert_eq!(r.take(), b"", "nothing goes to a host that is not there");
    assert_eq!(r.board.link_state(), BoardLinkState::LineDown);
    r.modem(ModemIn::ALL_ON);
    assert_eq!(r.board.link_state(), BoardLinkState::Ready);
    r.command(BoardCommand::Reset);
    assert_eq!(r.take(), [SYN]);
}

#[test]
fn framing_error_while_reading_is_sr0946_and_ignored_when_idle() {
    let mut r = Rig::new(config(false, CodeSystem::Ascii, true));
    r.board.handle_line_error(r.now, LineError::Framing);
    r.collect();
    assert!(r.alarms().is_empty());
    r.command(BoardCommand::StartReading);
    assert_eq!(r.take(), [DC1]);
    r.board.handle_line_error(r.now, LineError::Parity);
    r.collect();
    assert!(r.alarms().is_empty());
    r.board.handle_line_error(r.now, LineError::Overrun);
    r.collect();
    assert_eq!(r.alarms(), vec![CncAlarm::Sr0946FramingOverrun]);
    assert_eq!(r.take(), [DC3, NAK]);
}

#[test]
fn a_second_notice_while_er_is_off_adds_nothing() {
    let mut r = Rig::new(config(false, CodeSystem::Ascii, false));
    r.command(BoardCommand::RaiseAlarm);
    assert_eq!(r.take(), [DC3]);
    r.command(BoardCommand::Reset);
    assert_eq!(r.take(), b"");
    r.advance(DEFAULT_ER_OFF_TIME + ER_ON_SETTLE);
    assert!(r.board.modem_out().er);
    assert_eq!(r.take(), b"");
    assert!(r.cnc().alarm().is_none(), "the reset itself took effect");
}

#[test]
fn autostart_resets_an_alarm_after_the_delay() {
    let mut r = Rig::new(BoardConfig {
        autostart: true,
        first_request_delay: Duration::from_secs(2),
        ..config(false, CodeSystem::Ascii, true)
    });
    assert_eq!(r.take(), [DC1]);
    r.command(BoardCommand::RaiseAlarm);
    assert_eq!(r.take(), [DC3, NAK]);
    r.advance(Duration::from_millis(1999));
    assert_eq!(r.take(), b"");
    r.advance(Duration::from_millis(1));
    assert_eq!(r.take(), [SYN]);
    // Cycle start again, as late after the reset.
    r.advance(Duration::from_millis(1999));
    assert_eq!(r.take(), b"");
    r.advance(Duration::from_millis(1));
    assert_eq!(r.take(), [DC1]);
}

#[test]
fn what_the_host_still_sends_after_a_reset_is_not_the_next_program() {
    let mut r = Rig::new(BoardConfig {
        autostart: true,
        consume_rate: 0,
        first_request_delay: Duration::from_secs(1),
        ..config(false, CodeSystem::Ascii, true)
    });
    assert_eq!(r.take(), [DC1]);
    r.input(b"%\nO1\nN1 G00 X1\n");
    r.command(BoardCommand::Reset);
    assert_eq!(r.take(), [DC3, SYN]);
    // The rest of the program was on the line already: the CNC is in reset, not reading.
    r.advance(Duration::from_millis(100));
    r.input(b"N2 G00 X2\nN3 M30\n");
    r.advance(Duration::from_millis(900));
    assert_eq!(r.take(), [DC1]);
    // The next program is read whole, from its own tape start.
    r.input(b"%\nO2\nN1 G00 X5\n%");
    let programs: Vec<_> = r
        .events
        .iter()
        .filter_map(|e| match e {
            BoardEvent::ProgramReceived(p) => Some(p.data.to_vec()),
            _ => None,
        })
        .collect();
    assert_eq!(programs, [b"%\nO2\nN1 G00 X5\n%".to_vec()]);
}

#[test]
fn arbitrary_input_never_panics() {
    let mut r = Rig::new(BoardConfig {
        autostart: true,
        ..config(true, CodeSystem::Iso, true)
    });
    let mut x: u32 = 7;
    for i in 0..2000 {
        x = x.wrapping_mul(1_103_515_245).wrapping_add(12_345);
        let len = (x >> 16) as usize % 300;
        let bytes: Vec<u8> = (0..len).map(|j| (x >> (j % 24)) as u8).collect();
        r.input(&bytes);
        if i % 97 == 0 {
            r.command(BoardCommand::Punch(bytes.clone()));
        }
        if i % 131 == 0 {
            r.command(BoardCommand::Reset);
        }
        r.advance(Duration::from_millis(u64::from(x % 50)));
        r.sent.clear();
        r.events.clear();
    }
}
