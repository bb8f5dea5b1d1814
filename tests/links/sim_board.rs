//! The simulated remote-buffer board, driven step by step by a scripted host in virtual time
//! (sans-IO), plus the async handle and the TCP device server end to end.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use cellgate::transport::ModemIn;
use cellgate_core::engine::Engine;
use cellgate_core::fanuc::alarm::CncAlarm;
use cellgate_core::fanuc::message::{Command, Framing, Message};
use cellgate_core::fanuc::packet::{self, Monitor};
use cellgate_core::fanuc::sat::{AlarmCause, BufferStatus, Params, StatusData};
use cellgate_core::fanuc::{CodeSystem, EndCode, Protocol};
use cellgate_core::sim::{
    BoardCommand, BoardConfig, BoardEvent, BoardLinkState, FanucBoard, ReceivedProgram,
};
use sha2::{Digest, Sha256};

fn ms(v: u64) -> Duration {
    Duration::from_millis(v)
}
fn s(v: u64) -> Duration {
    Duration::from_secs(v)
}

/// What the board sent.
#[derive(Debug, Clone, PartialEq)]
enum Out {
    Msg(Message),
    Mon(Monitor),
}

/// A scripted host around a board, with a virtual clock.
struct Rig {
    board: FanucBoard,
    framing: Framing,
    t0: Instant,
    now: Instant,
    out: VecDeque<(Duration, Out)>,
    events: Vec<(Duration, BoardEvent)>,
}

impl Rig {
    fn new(config: BoardConfig) -> Self {
        let t0 = Instant::now();
        let framing = config.framing;
        Rig {
            board: FanucBoard::new(config, t0).unwrap(),
            framing,
            t0,
            now: t0,
            out: VecDeque::new(),
            events: Vec::new(),
        }
    }

    /// A board with Tx = 0 so that answers come at once, and the given changes.
    fn quick(f: impl FnOnce(&mut BoardConfig)) -> Self {
        let mut c = BoardConfig::default();
        c.params.tx = 0;
        f(&mut c);
        Rig::new(c)
    }

    fn at(&self) -> Duration {
        self.now - self.t0
    }

    fn pump(&mut self) {
        let at = self.at();
        while let Some(bytes) = self.board.poll_transmit(self.now) {
            let out = if bytes.len() == packet::MONITOR_LEN && Monitor::is_code(bytes[0]) {
                Out::Mon(Monitor::decode(&bytes.clone().try_into().unwrap()).unwrap())
            } else {
                Out::Msg(self.framing.decode(&bytes).unwrap())
            };
            self.out.push_back((at, out));
        }
        while let Some(e) = self.board.poll_event() {
            self.events.push((at, e));
        }
    }

    /// Runs the board's deadlines up to `d` from now.
    fn advance(&mut self, d: Duration) {
        let target = self.now + d;
        for _ in 0..1_000_000 {
            self.pump();
            match self.board.poll_timeout() {
                Some(t) if t <= target => {
                    self.now = self.now.max(t);
                    self.board.handle_timeout(self.now);
                }
                _ => {
                    self.now = target;
                    self.board.handle_timeout(self.now);
                    self.pump();
                    return;
                }
            }
        }
        panic!(
            "board keeps asking to be woken at {:?}",
            self.board.poll_timeout()
        );
    }

    /// The next thing the board sends within `limit`.
    fn next(&mut self, limit: Duration) -> (Duration, Out) {
        let target = self.now + limit;
        for _ in 0..1_000_000 {
            self.pump();
            if let Some(o) = self.out.pop_front() {
                return o;
            }
            match self.board.poll_timeout() {
                Some(t) if t <= target => {
                    self.now = self.now.max(t);
                    self.board.handle_timeout(self.now);
                }
                next => panic!(
                    "nothing sent within {limit:?} of {:?} (next deadline {:?})",
                    self.at(),
                    next.map(|t| t - self.t0)
                ),
            }
        }
        panic!("board keeps asking to be woken");
    }

    fn next_msg(&mut self, limit: Duration) -> (Duration, Message) {
        match self.next(limit) {
            (t, Out::Msg(m)) => (t, m),
            other => panic!("expected a message, got {other:?}"),
        }
    }

    /// The next message, which must be `cmd`.
    fn expect(&mut self, cmd: Command, limit: Duration) -> (Duration, Message) {
        let (t, m) = self.next_msg(limit);
        assert_eq!(m.command, cmd, "at {t:?}: expected {cmd}, got {m:?}");
        (t, m)
    }

    fn silent_for(&mut self, d: Duration) {
        self.advance(d);
        assert!(self.out.is_empty(), "board sent {:?}", self.out);
    }

    fn send_raw(&mut self, bytes: &[u8]) {
        self.board.handle_input(self.now, bytes);
        self.pump();
    }

    fn send(&mut self, msg: Message) {
        let bytes = self.framing.encode_to_vec(&msg).unwrap();
        self.send_raw(&bytes);
    }

    fn send_cmd(&mut self, cmd: Command) {
        self.send(Message::new(cmd));
    }

    fn command(&mut self, c: BoardCommand) {
        self.board.handle_command(self.now, c);
        self.pump();
    }

    /// Power-on handshake: SYN ↔ SYN, RDY ↔ RDY.
    fn init(&mut self) {
        self.expect(Command::Syn, s(3));
        self.send_cmd(Command::Syn);
        self.expect(Command::Rdy, s(1));
        self.send_cmd(Command::Rdy);
        assert_eq!(self.board.link_state(), BoardLinkState::Ready);
    }

    /// Waits for a SAT and returns its data part.
    fn sat(&mut self, limit: Duration) -> StatusData {
        let (_, m) = self.expect(Command::Sat, limit);
        StatusData::decode(&m.data).unwrap()
    }

    fn alarms(&self) -> Vec<CncAlarm> {
        self.events
            .iter()
            .filter_map(|(_, e)| match e {
                BoardEvent::Alarm { alarm, .. } => Some(*alarm),
                _ => None,
            })
            .collect()
    }

    fn programs(&self) -> Vec<ReceivedProgram> {
        self.events
            .iter()
            .filter_map(|(_, e)| match e {
                BoardEvent::ProgramReceived(p) => Some(p.clone()),
                _ => None,
            })
            .collect()
    }

    /// A host with nothing to send for `d`: SET for SAT, EOD for GTD.
    fn idle_host(&mut self, d: Duration) {
        let end = self.now + d;
        loop {
            self.pump();
            while let Some((_, out)) = self.out.pop_front() {
                match out {
                    Out::Msg(m) if m.command == Command::Sat => {
                        self.send(Message::new(Command::Set))
                    }
                    Out::Msg(m) if m.command == Command::Gtd => self.send_cmd(Command::Eod),
                    other => panic!("idle host got {other:?}"),
                }
            }
            match self.board.poll_timeout() {
                Some(t) if t <= end => {
                    self.now = self.now.max(t);
                    self.board.handle_timeout(self.now);
                }
                _ => {
                    self.now = end;
                    return;
                }
            }
        }
    }

    fn has_event(&self, pred: impl Fn(&BoardEvent) -> bool) -> bool {
        self.events.iter().any(|(_, e)| pred(e))
    }
}

fn set_with(f: impl FnOnce(&mut StatusData)) -> Message {
    let mut d = StatusData {
        params: Some(Params::POWER_ON),
        packet_n: Some(0),
        conversion: Some((0, 0)),
        ..StatusData::default()
    };
    f(&mut d);
    Message::with_data(Command::Set, d.to_bytes())
}

fn program(lines: usize) -> Vec<u8> {
    let mut p = b"%\nO1234 (SIM)\n".to_vec();
    for i in 0..lines {
        p.extend_from_slice(format!("N{i} G01 X{}.{:03} F200\n", i % 97, i % 1000).as_bytes());
    }
    p.extend_from_slice(b"M30\n%");
    p
}

fn sha(data: &[u8]) -> [u8; 32] {
    Sha256::digest(data).into()
}

// ---- Protocol A ------------------------------------------------------------------------------

#[test]
fn init_handshake_after_first_request_delay() {
    let mut rig = Rig::new(BoardConfig::default());
    let (t, _) = rig.expect(Command::Syn, s(5));
    assert_eq!(t, s(2), "first request ≈2 s after power-on (§4.3 (1))");
    rig.send_cmd(Command::Syn);
    let (t, _) = rig.expect(Command::Rdy, s(1));
    assert_eq!(
        t,
        s(2) + ms(100),
        "RDY waits Tx = 100 ms after reception (§4.3 (4))"
    );
    // Host not ready yet: SYN again later.
    rig.send_cmd(Command::Syn);
    let (t2, _) = rig.expect(Command::Syn, s(5));
    assert_eq!(t2, t + s(2));
    rig.send_cmd(Command::Syn);
    rig.expect(Command::Rdy, s(1));
    rig.send_cmd(Command::Rdy);
    assert_eq!(rig.board.link_state(), BoardLinkState::Ready);
    assert!(rig.has_event(|e| *e == BoardEvent::LinkState(BoardLinkState::Ready)));
}

#[test]
fn no_host_means_syn_again_every_to_without_alarm() {
    let mut rig = Rig::quick(|_| {});
    let (t1, _) = rig.expect(Command::Syn, s(3));
    let (t2, _) = rig.expect(Command::Syn, s(30));
    assert_eq!(t2 - t1, s(20));
    assert!(rig.alarms().is_empty());
}

#[test]
fn sat_every_tp_with_status_data() {
    let mut rig = Rig::quick(|_| {});
    rig.init();
    let ready_at = rig.at();
    let (t, m) = rig.expect(Command::Sat, s(10));
    assert_eq!(t - ready_at, s(5), "SAT Tp after the last reception");
    let d = StatusData::decode(&m.data).unwrap();
    assert_eq!(m.data.len(), 56);
    assert_eq!(d.status, Some(BufferStatus::Reset));
    assert_eq!(d.buffered, Some(0));
    assert_eq!(
        d.params,
        Some(Params {
            tx: 0,
            ..Params::POWER_ON
        })
    );
    assert_eq!(d.packet_n, Some(0));
    for _ in 0..3 {
        rig.send(Message::new(Command::Set)); // empty: no change
        let answered = rig.at();
        let (t, _) = rig.expect(Command::Sat, s(10));
        assert_eq!(t - answered, s(5));
    }
}

#[test]
fn set_changes_params_and_n_and_ignores_invalid_fields() {
    let mut rig = Rig::quick(|c| c.protocol = Protocol::ExpansionA);
    rig.init();
    rig.sat(s(10));
    rig.send(set_with(|d| {
        let p = d.params.as_mut().unwrap();
        p.tp = 3;
        p.tw = 2;
        p.nb = 1000;
        p.to = 0; // outside 1..=999: ignored
        d.packet_n = Some(2);
    }));
    let answered = rig.at();
    let (t, m) = rig.expect(Command::Sat, s(10));
    assert_eq!(t - answered, s(3), "the new Tp is in force");
    let d = StatusData::decode(&m.data).unwrap();
    let p = d.params.unwrap();
    assert_eq!((p.tp, p.tw, p.nb, p.to), (3, 2, 1000, 20));
    assert_eq!(d.packet_n, Some(2));
    assert!(rig.has_event(
        |e| matches!(e, BoardEvent::ProtocolError { detail } if detail.contains("To = 0"))
    ));
    // n outside {0, 1, 2, 4} means 0 (§5.2 note).
    rig.send(set_with(|d| {
        d.params = None;
        d.packet_n = Some(3);
    }));
    assert_eq!(rig.board.packet_n(), 0);
}

#[test]
fn protocol_a_board_keeps_n_at_zero() {
    let mut rig = Rig::quick(|_| {});
    rig.init();
    rig.sat(s(10));
    rig.send(set_with(|d| d.packet_n = Some(1)));
    assert_eq!(rig.board.packet_n(), 0);
}

#[test]
fn gtd_only_when_reading_and_free_at_least_nb() {
    let mut rig = Rig::quick(|c| {
        c.buffer_size = 4000;
        c.consume_rate = 100;
        c.params.nb = 1000;
    });
    rig.init();
    // Not reading: only SATs.
    rig.sat(s(10));
    rig.send(Message::new(Command::Set));
    rig.command(BoardCommand::StartReading);
    let (t, _) = rig.expect(Command::Gtd, s(1));
    assert_eq!(t, rig.at(), "GTD as soon as the CNC reads (Tx = 0)");
    // 3500 bytes: free 500 < Nb.
    let mut data = b"%\nO0001\n".to_vec();
    data.resize(3500, b'X');
    rig.send(Message::with_data(Command::Dat, data));
    let stored_at = rig.at();
    rig.silent_for(s(4));
    assert_eq!(rig.board.cnc().buffered(), 3100);
    assert_eq!(
        rig.board.status_data().status,
        Some(BufferStatus::Operating)
    );
    // Free reaches Nb = 1000 once 500 bytes are read: 5 s at 100 B/s (GTD comes before the
    // SAT due at the same moment).
    let (t, _) = rig.expect(Command::Gtd, s(2));
    assert_eq!(t - stored_at, s(5));
    rig.send_cmd(Command::Eod);
    // After EOD: no GTD until the next SAT exchange.
    let d = rig.sat(s(10));
    assert_eq!(d.buffered, Some(2500));
    rig.send(Message::new(Command::Set));
    rig.expect(Command::Gtd, s(1));
}

#[test]
fn dat_consumed_at_rate_and_program_split_at_eor() {
    let mut rig = Rig::quick(|c| c.consume_rate = 1000);
    rig.init();
    rig.command(BoardCommand::StartReading);
    let prog = program(200);
    assert!(prog.len() > 4096);
    let mut tape = b"\n\n".to_vec(); // leader
    tape.extend_from_slice(&prog);
    tape.extend_from_slice(b"\nDATA AFTER EOR IS IGNORED\n");
    let mut sent = 0;
    for chunk in tape.chunks(1500) {
        rig.expect(Command::Gtd, s(10));
        rig.send(Message::with_data(Command::Dat, chunk.to_vec()));
        sent += chunk.len();
    }
    assert_eq!(sent, tape.len());
    // The CNC reads 1000 B/s: the program ends (tape.len() - trailing) / 1000 s after start.
    rig.advance(s(30));
    let programs = rig.programs();
    assert_eq!(programs.len(), 1);
    let p = &programs[0];
    assert_eq!(&p.data[..], &prog[..]);
    assert_eq!(p.len, prog.len() as u64);
    assert_eq!(p.sha256, sha(&prog));
    assert_eq!(p.first_line, "O1234 (SIM)");
    assert!(!rig.board.cnc().reading(), "the CNC stops after EOR");
    assert_eq!(rig.board.cnc().buffered(), 0, "data after EOR is ignored");
    let (when, _) = rig
        .events
        .iter()
        .find(|(_, e)| matches!(e, BoardEvent::ProgramReceived(_)))
        .unwrap();
    // Started reading at init; the whole leader + program is 2 + len bytes at 1000 B/s, but
    // it arrived in pieces: it cannot end before its last byte arrived.
    assert!(*when >= Duration::from_secs_f64((2 + prog.len()) as f64 / 1000.0));
}

#[test]
fn consumption_rate_is_applied_to_the_buffer() {
    let mut rig = Rig::quick(|c| c.consume_rate = 200);
    rig.init();
    rig.command(BoardCommand::StartReading);
    rig.expect(Command::Gtd, s(1));
    rig.send(Message::with_data(Command::Dat, vec![b'G'; 3000]));
    rig.advance(s(4));
    assert_eq!(rig.board.cnc().buffered(), 2200);
    rig.advance(ms(2500));
    assert_eq!(rig.board.cnc().buffered(), 1700);
    assert_eq!(rig.board.status_data().buffered, Some(1700));
}

#[test]
fn code_conversion_of_set_bytes_45_to_48() {
    let mut rig = Rig::quick(|c| c.consume_rate = 0);
    rig.init();
    rig.sat(s(10));
    rig.send(set_with(|d| d.conversion = Some((b';', b'\n'))));
    rig.command(BoardCommand::StartReading);
    rig.expect(Command::Gtd, s(1));
    rig.send(Message::with_data(Command::Dat, b"%;O5;G0X1;%".to_vec()));
    rig.advance(ms(1));
    let p = &rig.programs()[0];
    assert_eq!(&p.data[..], b"%\nO5\nG0X1\n%");
}

#[test]
fn rdi_answered_with_sdi_then_the_owed_answer() {
    let mut rig = Rig::quick(|_| {});
    rig.init();
    rig.command(BoardCommand::SetDi(0xA5));
    rig.sat(s(10));
    rig.send_cmd(Command::Rdi);
    let (_, m) = rig.expect(Command::Sdi, s(1));
    assert_eq!(m.data, b"A5");
    // After SDI the host owes the SAT's answer (§4.4.1 SDI); SDO is one (§4.4.1 SDO): the
    // exchange is complete, and the next SAT comes Tp later.
    rig.send(Message::with_data(Command::Sdo, "0F"));
    let answered = rig.at();
    assert_eq!(rig.board.cnc().do_image(), 0x0F);
    let (t, _) = rig.expect(Command::Sat, s(10));
    assert_eq!(t - answered, s(5));
    // RDI in answer to GTD, then DAT for the GTD.
    rig.command(BoardCommand::SetDi(0x3C));
    rig.send(Message::new(Command::Set));
    rig.command(BoardCommand::StartReading);
    rig.expect(Command::Gtd, s(1));
    rig.send_cmd(Command::Rdi);
    let (_, m) = rig.expect(Command::Sdi, s(1));
    assert_eq!(m.data, b"3C");
    rig.send(Message::with_data(Command::Dat, b"%\nO1\n".to_vec()));
    assert!(rig.has_event(|e| matches!(e, BoardEvent::DataReceived { bytes: 5, .. })));
    assert!(rig.alarms().is_empty());
}

#[test]
fn sdo_changes_do_and_a_gtd_answered_by_sdo_is_asked_again() {
    let mut rig = Rig::quick(|_| {});
    rig.init();
    rig.sat(s(10));
    rig.send(Message::with_data(Command::Sdo, "C3"));
    assert_eq!(rig.board.cnc().do_image(), 0xC3);
    assert!(rig.has_event(|e| *e == BoardEvent::DoChanged(0xC3)));
    rig.command(BoardCommand::StartReading);
    rig.expect(Command::Gtd, s(1));
    rig.send(Message::with_data(Command::Sdo, "01"));
    rig.expect(Command::Gtd, s(1));
    assert_eq!(rig.board.cnc().do_image(), 0x01);
}

#[test]
fn wat_makes_the_board_ask_again_after_tw() {
    let mut rig = Rig::quick(|_| {});
    rig.init();
    rig.command(BoardCommand::StartReading);
    rig.expect(Command::Gtd, s(1));
    rig.send_cmd(Command::Wat);
    let wat_at = rig.at();
    let (t, _) = rig.expect(Command::Gtd, s(10));
    assert_eq!(t - wat_at, s(5), "Tw = 5 s");
}

#[test]
fn clb_clears_the_buffer() {
    let mut rig = Rig::quick(|c| {
        c.consume_rate = 1;
        c.buffer_size = 5000;
    });
    rig.init();
    rig.command(BoardCommand::StartReading);
    rig.expect(Command::Gtd, s(1));
    rig.send(Message::with_data(Command::Dat, vec![b'X'; 4000]));
    let d = rig.sat(s(10));
    assert_eq!(d.buffered, Some(4000 - 5));
    rig.send_cmd(Command::Clb);
    assert_eq!(rig.board.cnc().buffered(), 0);
    assert!(rig.has_event(|e| *e == BoardEvent::BufferCleared));
}

#[test]
fn alm_and_rst_are_sent_when_the_board_can_transmit() {
    let mut rig = Rig::quick(|_| {});
    rig.init();
    rig.command(BoardCommand::StartReading);
    rig.expect(Command::Gtd, s(1));
    rig.command(BoardCommand::RaiseAlarm);
    // The GTD is outstanding: ALM only after its answer.
    rig.silent_for(s(1));
    rig.send(Message::with_data(Command::Dat, b"%\nO1\nG0".to_vec()));
    rig.expect(Command::Alm, s(1));
    rig.send_cmd(Command::Aal);
    let d = rig.sat(s(10));
    assert_eq!(d.status, Some(BufferStatus::Alarm));
    assert_eq!(d.alarm_cause, Some(AlarmCause::NcAlarm));
    rig.send(Message::new(Command::Set));
    rig.command(BoardCommand::Reset);
    rig.expect(Command::Rst, s(1));
    rig.send_cmd(Command::Ars);
    let d = rig.sat(s(10));
    assert_eq!(d.status, Some(BufferStatus::Reset));
    assert_eq!(d.buffered, Some(0), "reset loses buffered data (§8.2)");
}

#[test]
fn checksum_error_gets_rty_and_the_retransmission_is_taken() {
    let mut rig = Rig::quick(|_| {});
    rig.init();
    rig.sat(s(10));
    let mut bad = rig
        .framing
        .encode_to_vec(&Message::with_data(Command::Sdo, "5A"))
        .unwrap();
    bad[0] = if bad[0] == b'0' { b'1' } else { b'0' };
    rig.send_raw(&bad);
    let (_, m) = rig.expect(Command::Rty, s(1));
    assert_eq!(m.data, b"1", "reason 1: checksum error (§4.4.2 6)");
    rig.send(Message::with_data(Command::Sdo, "5A"));
    assert_eq!(rig.board.cnc().do_image(), 0x5A);
    rig.sat(s(10));
    assert!(rig.alarms().is_empty());
}

#[test]
fn rty_retransmits_and_retry_over_raises_sr0945_with_cause_1() {
    let mut rig = Rig::quick(|c| c.params.ne = 2);
    rig.init();
    let first = rig.sat(s(10));
    for _ in 0..2 {
        rig.send(Message::with_data(Command::Rty, "1"));
        let again = rig.sat(s(1));
        assert_eq!(again, first, "RTY: the same message again");
    }
    rig.send(Message::with_data(Command::Rty, "1"));
    assert_eq!(rig.alarms(), vec![CncAlarm::Sr0945RetryOver]);
    let failed_at = rig.at();
    let (t, m) = rig.expect(Command::Sat, s(10));
    assert_eq!(t - failed_at, s(5), "back to SAT polling (§4.6 2)");
    let d = StatusData::decode(&m.data).unwrap();
    assert_eq!(d.status, Some(BufferStatus::Alarm));
    assert_eq!(d.alarm_cause, Some(AlarmCause::ChecksumRetryOver));
}

#[test]
fn host_silence_raises_sr0944_and_reinitialises() {
    let mut rig = Rig::quick(|_| {});
    rig.init();
    let (sat_at, _) = rig.expect(Command::Sat, s(10));
    let (syn_at, _) = rig.expect(Command::Syn, s(30));
    assert_eq!(rig.alarms(), vec![CncAlarm::Sr0944TimeOut]);
    assert_eq!(
        syn_at - sat_at,
        s(20) + s(2),
        "To, then the first-request delay"
    );
    assert!(rig.has_event(|e| *e == BoardEvent::LinkState(BoardLinkState::Initialising)));
    rig.send_cmd(Command::Syn);
    rig.expect(Command::Rdy, s(1));
    rig.send_cmd(Command::Rdy);
    let d = rig.sat(s(10));
    assert_eq!(d.status, Some(BufferStatus::Alarm));
}

#[test]
fn unexpected_and_undefined_commands_are_command_errors() {
    let mut rig = Rig::quick(|_| {});
    rig.init();
    rig.sat(s(10));
    rig.send_cmd(Command::Eod); // not an answer to SAT
    assert_eq!(rig.alarms(), vec![CncAlarm::Sr0947InvalidResponse]);
    let d = rig.sat(s(10));
    assert_eq!(d.alarm_cause, Some(AlarmCause::CommandError));
    // An undefined command with a valid checksum.
    let body = b"XYZ\r";
    let sum = body.iter().fold(0u8, |a, &b| a.wrapping_add(b));
    let mut frame = format!("{sum:02X}").into_bytes();
    frame.extend_from_slice(body);
    rig.send_raw(&frame);
    assert_eq!(
        rig.alarms(),
        vec![CncAlarm::Sr0947InvalidResponse, CncAlarm::Sr0948BadCommand]
    );
    rig.sat(s(10));
}

#[test]
fn dr_off_raises_sr0855_and_the_board_waits_for_dr() {
    let mut rig = Rig::quick(|_| {});
    rig.init();
    let off = ModemIn {
        dr: false,
        ..ModemIn::ALL_ON
    };
    rig.board.handle_modem(rig.now, off);
    rig.pump();
    assert_eq!(rig.alarms(), vec![CncAlarm::Sr0855DataSetReadyDown]);
    assert_eq!(rig.board.link_state(), BoardLinkState::LineDown);
    rig.silent_for(s(60));
    rig.board.handle_modem(rig.now, ModemIn::ALL_ON);
    let on_at = rig.at();
    let (t, _) = rig.expect(Command::Syn, s(5));
    assert_eq!(t - on_at, s(2));
}

#[test]
fn iso_etx_framing() {
    let mut rig = Rig::quick(|c| {
        c.framing = Framing::new(CodeSystem::Iso, EndCode::Etx);
        c.consume_rate = 0;
    });
    rig.init();
    rig.command(BoardCommand::StartReading);
    rig.expect(Command::Gtd, s(1));
    rig.send(Message::with_data(Command::Dat, b"\xA5\nO7\n\xA5".to_vec()));
    rig.advance(ms(1));
    assert_eq!(rig.programs()[0].first_line, "O7");
}

#[test]
fn autostart_reads_and_resets_itself_after_an_alarm() {
    let mut rig = Rig::quick(|c| {
        c.autostart = true;
        c.consume_rate = 0;
    });
    rig.init();
    // The first SAT comes before any reading, so that the host can select n.
    rig.sat(s(10));
    rig.send(Message::new(Command::Set));
    rig.expect(Command::Gtd, s(1));
    rig.send(Message::with_data(Command::Dat, program(3)));
    // The CNC read the program and started reading again.
    rig.expect(Command::Gtd, s(1));
    assert_eq!(rig.programs().len(), 1);
    rig.send_cmd(Command::Sat); // wrong answer: SR0947
    let d = rig.sat(s(10));
    assert_eq!(d.status, Some(BufferStatus::Alarm));
    rig.send(Message::new(Command::Set));
    rig.expect(Command::Rst, s(1));
    rig.send_cmd(Command::Ars);
    rig.expect(Command::Gtd, s(1));
}

// ---- Expansion A ----------------------------------------------------------------------------

/// Builds the packets of `data` for n: 30h, 31h, ... and FFh for the last.
fn packets(data: &[u8], n: u8) -> Vec<Vec<u8>> {
    let len = packet::data_len(n);
    let chunks: Vec<&[u8]> = data.chunks(len).collect();
    chunks
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let mut d = c.to_vec();
            d.resize(len, b' ');
            let no = if i + 1 == chunks.len() {
                packet::END_PACKET
            } else {
                position_no(i)
            };
            let mut out = Vec::new();
            packet::encode_data_packet(no, &d, &mut out);
            out
        })
        .collect()
}

fn position_no(i: usize) -> u8 {
    packet::FIRST_PACKET + (i % 10) as u8
}

/// What the host saw during a packet transfer.
#[derive(Debug, Default)]
struct Transfer {
    monitors: Vec<Monitor>,
    sent: usize,
}

/// A host sending packets back to back, one packet time each, reacting to monitor packets one
/// packet late (the packet on the line when a monitor packet arrives is finished first).
/// `spoil(i, attempt)` corrupts a packet on the line.
fn send_packets(
    rig: &mut Rig,
    pkts: &[Vec<u8>],
    packet_time: Duration,
    spoil: impl Fn(usize, usize) -> bool,
) -> Transfer {
    let mut t = Transfer::default();
    let mut attempts = vec![0usize; pkts.len()];
    let mut i = 0;
    let mut paused = false;
    let mut late: Vec<Monitor> = Vec::new();
    let mut stopped = false;
    for _ in 0..100_000 {
        if i >= pkts.len() && late.is_empty() && rig.out.is_empty() {
            // Everything sent: give the board a moment for a last NAK.
            rig.advance(packet_time * 2);
            if rig.out.iter().all(|(_, o)| !matches!(o, Out::Mon(_))) {
                return t;
            }
        }
        if i < pkts.len() && !paused {
            let mut p = pkts[i].clone();
            if spoil(i, attempts[i]) {
                p[3] ^= 0x40;
            }
            attempts[i] += 1;
            rig.send_raw(&p);
            t.sent += 1;
            i += 1;
            rig.advance(packet_time);
        } else {
            rig.advance(packet_time);
        }
        let mut now_seen = Vec::new();
        while let Some((_, Out::Mon(m))) = rig.out.front().cloned() {
            rig.out.pop_front();
            now_seen.push(m);
        }
        // Monitor packets seen during the previous packet take effect now; while paused there
        // is no packet on the line, so they take effect at once.
        let effective: Vec<Monitor> = if paused {
            late.drain(..).chain(now_seen.drain(..)).collect()
        } else {
            std::mem::replace(&mut late, now_seen)
        };
        for m in effective {
            t.monitors.push(m);
            match m {
                Monitor::Pause => paused = true,
                Monitor::Resume => paused = false,
                Monitor::Retransmit(no) => {
                    i = (0..i)
                        .rev()
                        .find(|&j| position_no(j) == no)
                        .expect("NAK number sent");
                }
                Monitor::Stop => {
                    if !stopped {
                        stopped = true;
                        // Finish with the end packet (dummy data).
                        let mut end = Vec::new();
                        let len = pkts[0].len() - 4;
                        packet::encode_data_packet(packet::END_PACKET, &vec![0u8; len], &mut end);
                        rig.send_raw(&end);
                        t.sent += 1;
                        i = pkts.len();
                        paused = false;
                    }
                }
            }
        }
    }
    panic!("transfer did not end: {t:?}");
}

/// An Expansion A board with n = 1 selected by SET, reading, with the GTD sent.
fn expansion_rig(consume_rate: u32) -> Rig {
    let mut rig = Rig::quick(|c| {
        c.protocol = Protocol::ExpansionA;
        c.consume_rate = consume_rate;
    });
    rig.init();
    rig.sat(s(10));
    rig.send(set_with(|d| d.packet_n = Some(1)));
    rig.command(BoardCommand::StartReading);
    rig.expect(Command::Gtd, s(1));
    rig
}

/// One 260-byte packet at 9600 baud, 11 bits a character.
const PACKET_TIME: Duration = Duration::from_micros(260 * 11 * 1_000_000 / 9600);

#[test]
fn expansion_a_packets_with_dc3_dc1_flow_control() {
    let mut rig = expansion_rig(150);
    let prog = program(1500);
    assert!(prog.len() > 3 * 8192);
    let pkts = packets(&prog, 1);
    let t = send_packets(&mut rig, &pkts, PACKET_TIME, |_, _| false);
    let pauses = t.monitors.iter().filter(|m| **m == Monitor::Pause).count();
    let resumes = t.monitors.iter().filter(|m| **m == Monitor::Resume).count();
    assert!(pauses >= 2, "{:?}", t.monitors);
    assert_eq!(pauses, resumes + usize::from(pauses > resumes));
    assert!(rig.alarms().is_empty(), "{:?}", rig.alarms());
    assert_eq!(t.sent, pkts.len());
    // Back to Protocol A after the end packet: SAT / GTD, answered by an idle host.
    rig.idle_host(s(300));
    let p = &rig.programs()[0];
    assert_eq!(p.sha256, sha(&prog));
    assert_eq!(&p.data[..], &prog[..]);
    // Never more than the buffer.
    let max = rig
        .events
        .iter()
        .filter_map(|(_, e)| match e {
            BoardEvent::DataReceived { buffered, .. } => Some(*buffered),
            _ => None,
        })
        .max()
        .unwrap();
    assert!(max <= 8192);
}

#[test]
fn expansion_a_nak_on_a_corrupted_packet() {
    let mut rig = expansion_rig(0);
    let prog = program(60);
    let pkts = packets(&prog, 1);
    assert!(pkts.len() >= 4);
    let t = send_packets(&mut rig, &pkts, PACKET_TIME, |i, attempt| {
        i == 2 && attempt == 0
    });
    assert_eq!(t.monitors, vec![Monitor::Retransmit(0x32)]);
    // Packet 2 was resent, and packet 3 (in flight when the NAK came) resent after it.
    assert_eq!(t.sent, pkts.len() + 2);
    rig.advance(s(1));
    let p = &rig.programs()[0];
    assert_eq!(p.sha256, sha(&prog));
    assert!(rig.alarms().is_empty());
}

#[test]
fn expansion_a_corrupted_end_packet_is_asked_as_previous_plus_one() {
    let mut rig = expansion_rig(0);
    let prog = program(20);
    let pkts = packets(&prog, 1);
    let last = pkts.len() - 1;
    let t = send_packets(&mut rig, &pkts, PACKET_TIME, |i, attempt| {
        i == last && attempt == 0
    });
    assert_eq!(t.monitors, vec![Monitor::Retransmit(position_no(last))]);
    rig.advance(s(1));
    assert_eq!(rig.programs()[0].sha256, sha(&prog));
}

#[test]
fn expansion_a_can_on_reset_mid_transfer() {
    let mut rig = expansion_rig(100);
    let prog = program(300);
    let pkts = packets(&prog, 1);
    // Three packets, then the operator resets the CNC.
    for p in &pkts[..3] {
        rig.send_raw(p);
        rig.advance(PACKET_TIME);
    }
    rig.command(BoardCommand::Reset);
    assert_eq!(rig.next(ms(1)).1, Out::Mon(Monitor::Stop));
    // The packet on the line is finished, then the end packet with dummy data.
    rig.send_raw(&pkts[3]);
    rig.advance(PACKET_TIME);
    let mut end = Vec::new();
    packet::encode_data_packet(packet::END_PACKET, &[b'%'; 256], &mut end);
    rig.send_raw(&end);
    // Back to Protocol A: RST.
    rig.expect(Command::Rst, s(1));
    rig.send_cmd(Command::Ars);
    assert_eq!(rig.board.cnc().buffered(), 0);
    assert!(
        rig.programs().is_empty(),
        "the end packet's data was ignored"
    );
    let d = rig.sat(s(10));
    assert_eq!(d.status, Some(BufferStatus::Reset));
}

#[test]
fn expansion_a_time_out_between_packets() {
    let mut rig = expansion_rig(0);
    let pkts = packets(&program(30), 1);
    rig.send_raw(&pkts[0]);
    let last = rig.at();
    let (t, _) = rig.expect(Command::Syn, s(30));
    assert_eq!(rig.alarms(), vec![CncAlarm::Sr0944TimeOut]);
    assert_eq!(t - last, s(22));
}

#[test]
fn expansion_a_gtd_may_still_be_answered_by_protocol_a_messages() {
    let mut rig = expansion_rig(0);
    rig.send_cmd(Command::Wat);
    rig.expect(Command::Gtd, s(6));
    rig.send_cmd(Command::Eod);
    rig.sat(s(10));
    assert!(rig.alarms().is_empty());
}

// ---- garbage ------------------------------------------------------------------------------

mod garbage {
    use super::*;
    use proptest::prelude::*;

    #[derive(Debug, Clone)]
    enum Step {
        Bytes(Vec<u8>),
        Frame(u8, Vec<u8>),
        Wait(u16),
        Cmd(u8),
        Modem(bool),
    }

    fn step() -> impl Strategy<Value = Step> {
        prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..700).prop_map(Step::Bytes),
            (0u8..17, proptest::collection::vec(0x20u8..0x7f, 0..60))
                .prop_map(|(c, d)| Step::Frame(c, d)),
            any::<u16>().prop_map(Step::Wait),
            (0u8..6).prop_map(Step::Cmd),
            any::<bool>().prop_map(Step::Modem),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        #[test]
        fn garbage_never_panics(steps in proptest::collection::vec(step(), 1..60),
                                expansion in any::<bool>(), iso in any::<bool>()) {
            let mut rig = Rig::quick(|c| {
                c.protocol = if expansion { Protocol::ExpansionA } else { Protocol::A };
                c.packet_n = if expansion { 1 } else { 0 };
                c.consume_rate = 500;
                c.framing = Framing::new(if iso { CodeSystem::Iso } else { CodeSystem::Ascii }, EndCode::Cr);
            });
            rig.init();
            for st in steps {
                match st {
                    Step::Bytes(b) => rig.board.handle_input(rig.now, &b),
                    Step::Frame(c, d) => {
                        let cmd = Command::ALL[usize::from(c) % Command::ALL.len()];
                        if let Ok(bytes) = rig.framing.encode_to_vec(&Message::with_data(cmd, d)) {
                            rig.board.handle_input(rig.now, &bytes);
                        }
                    }
                    Step::Wait(ms) => {
                        let target = rig.now + Duration::from_millis(u64::from(ms) * 4);
                        for _ in 0..10_000 {
                            match rig.board.poll_timeout() {
                                Some(t) if t <= target => {
                                    rig.now = rig.now.max(t);
                                    rig.board.handle_timeout(rig.now);
                                    while rig.board.poll_transmit(rig.now).is_some() {}
                                }
                                _ => break,
                            }
                        }
                        rig.now = target;
                    }
                    Step::Cmd(c) => rig.board.handle_command(rig.now, match c {
                        0 => BoardCommand::StartReading,
                        1 => BoardCommand::StopReading,
                        2 => BoardCommand::RaiseAlarm,
                        3 => BoardCommand::Reset,
                        4 => BoardCommand::SetDi(c),
                        _ => BoardCommand::SetConsumeRate(0),
                    }),
                    Step::Modem(dr) => rig.board.handle_modem(rig.now, ModemIn { dr, ..ModemIn::ALL_ON }),
                }
                while rig.board.poll_transmit(rig.now).is_some() {}
                while rig.board.poll_event().is_some() {}
                prop_assert!(rig.board.cnc().buffered() <= rig.board.cnc().capacity());
            }
        }
    }
}

// ---- async: the handle and the TCP device server ---------------------------------------------
mod live;

// ---- the gateway's own host engine against the board ------------------------------------------
mod cell;

// ---- G05 binary input operation (§9) ----------------------------------------------------------
mod g05;
