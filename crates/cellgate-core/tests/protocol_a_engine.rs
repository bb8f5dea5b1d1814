//! The Protocol A / Expansion Protocol A host engine, driven step by step by a scripted board:
//! the board's messages are built with the crate's own codecs, time moves only when the test
//! says so, and every byte the host transmits is decoded and checked.

use std::time::{Duration, Instant};

use bytes::Bytes;
use cellgate_core::engine::Engine;
use cellgate_core::engine::{LineError, ModemIn};
use cellgate_core::fanuc::alarm::CncAlarm;
use cellgate_core::fanuc::host::{Confirmation, EngineCommand, EngineEvent, HostEngine, LinkState};
use cellgate_core::fanuc::message::{Command, Decoder, Framing, Message};
use cellgate_core::fanuc::packet::{DUMMY_PACKET, END_PACKET, Monitor, decode_data_packet};
use cellgate_core::fanuc::protocol_a::{PAD, ProtocolAConfig, ProtocolAHost};
use cellgate_core::fanuc::sat::{AlarmCause, BufferStatus, Params, StatusData};
use cellgate_core::fanuc::{CodeSystem, EndCode};

const SEC: Duration = Duration::from_secs(1);
const MS: Duration = Duration::from_millis(1);

/// The host engine and the board's end of the line.
struct Bench {
    host: ProtocolAHost,
    now: Instant,
    framing: Framing,
    events: Vec<EngineEvent>,
    /// Pieces the host handed out while `advance` checked its deadlines.
    pending_tx: Vec<Vec<u8>>,
}

/// A SAT data part as a board in operation sends it.
fn board_sat(params: Params, n: u8) -> StatusData {
    StatusData {
        remote: Some(true),
        status: Some(BufferStatus::Operating),
        alarm_cause: Some(AlarmCause::NcAlarm),
        buffered: Some(0),
        params: Some(params),
        boring_unit: Some(0),
        conversion: Some((0, 0)),
        packet_n: Some(n),
    }
}

impl Bench {
    fn new(cfg: ProtocolAConfig) -> Self {
        let now = Instant::now();
        let framing = cfg.framing;
        Bench {
            host: ProtocolAHost::new(cfg, now).unwrap(),
            now,
            framing,
            events: Vec::new(),
            pending_tx: Vec::new(),
        }
    }

    /// Initialised, and the first SET answered, with the board at the host's settings.
    fn ready(cfg: ProtocolAConfig) -> Self {
        let params = cfg.params;
        let n = cfg.packet_n;
        let mut b = Bench::new(cfg);
        b.init();
        let set = b.sat(board_sat(Params::POWER_ON, 0));
        assert_eq!(set.command, Command::Set);
        assert!(!set.data.is_empty());
        let set = b.sat(board_sat(params, n));
        assert_eq!(set, Message::new(Command::Set));
        b.take_events();
        b
    }

    /// Lets `d` pass, waking the host at each deadline it asks for on the way.
    fn advance(&mut self, d: Duration) {
        let target = self.now + d;
        while let Some(t) = self.host.poll_timeout() {
            if t > target {
                break;
            }
            self.now = self.now.max(t);
            self.host.handle_timeout(self.now);
            // A deadline still due after handle_timeout would spin a driver, unless what the
            // host now transmits clears it.
            if self.host.poll_timeout().is_some_and(|a| a <= self.now) {
                let sent = self.drain();
                assert!(
                    !sent.is_empty(),
                    "a deadline stays due with nothing to send"
                );
                self.pending_tx.extend(sent);
                assert!(
                    self.host.poll_timeout().is_none_or(|a| a > self.now),
                    "a deadline stays due"
                );
            }
        }
        self.now = target;
    }

    fn board_bytes(&mut self, bytes: &[u8]) {
        self.host.handle_input(self.now, bytes);
    }

    fn board(&mut self, command: Command) {
        self.board_msg(Message::new(command));
    }

    fn board_data(&mut self, command: Command, data: &[u8]) {
        self.board_msg(Message::with_data(command, data.to_vec()));
    }

    fn board_msg(&mut self, msg: Message) {
        let bytes = self.framing.encode_to_vec(&msg).unwrap();
        self.board_bytes(&bytes);
    }

    fn monitor(&mut self, m: Monitor) {
        self.board_bytes(&m.encode());
    }

    fn command(&mut self, c: EngineCommand) {
        self.host.handle_command(self.now, c);
    }

    fn data(&mut self, bytes: &[u8]) {
        self.command(EngineCommand::ProgramData(Bytes::copy_from_slice(bytes)));
    }

    fn drain(&mut self) -> Vec<Vec<u8>> {
        std::iter::from_fn(|| self.host.poll_transmit(self.now)).collect()
    }

    /// Every piece the host hands out now, in order.
    fn pieces(&mut self) -> Vec<Vec<u8>> {
        let mut v = std::mem::take(&mut self.pending_tx);
        v.extend(self.drain());
        v
    }

    fn tx(&mut self) -> Vec<u8> {
        self.pieces().concat()
    }

    /// The Protocol A messages the host transmits now.
    fn msgs(&mut self) -> Vec<Message> {
        let bytes = self.tx();
        let mut d = Decoder::new(self.framing);
        d.push(&bytes);
        let mut v = Vec::new();
        while let Some(m) = d.next_message() {
            v.push(m.expect("host sent a malformed message"));
        }
        assert_eq!(d.buffered(), 0, "host sent a partial message");
        v
    }

    /// The single message the host answers with now.
    fn answer(&mut self) -> Message {
        let mut v = self.msgs();
        assert_eq!(v.len(), 1, "expected one answer, got {v:?}");
        v.remove(0)
    }

    fn expect(&mut self, command: Command) -> Message {
        let m = self.answer();
        assert_eq!(m.command, command, "answer {m:?}");
        m
    }

    fn expect_silence(&mut self) {
        let t = self.tx();
        assert!(t.is_empty(), "host sent {:?}", String::from_utf8_lossy(&t));
    }

    fn dat(&mut self) -> Vec<u8> {
        self.expect(Command::Dat).data
    }

    /// The next data packet; one per poll_transmit, so that DC3 acts after the current one.
    fn next_packet(&mut self, n: u8) -> Option<(u8, Vec<u8>)> {
        let bytes = if self.pending_tx.is_empty() {
            self.host.poll_transmit(self.now)?
        } else {
            self.pending_tx.remove(0)
        };
        let p = decode_data_packet(&bytes, n).expect("host sent a malformed packet");
        Some((p.no, p.data.to_vec()))
    }

    fn packets(&mut self, n: u8) -> Vec<(u8, Vec<u8>)> {
        std::iter::from_fn(|| self.next_packet(n)).collect()
    }

    fn take_events(&mut self) -> Vec<EngineEvent> {
        while let Some(e) = self.host.poll_event() {
            self.events.push(e);
        }
        std::mem::take(&mut self.events)
    }

    /// SYN/SYN, RDY/RDY.
    fn init(&mut self) {
        self.board(Command::Syn);
        self.expect(Command::Syn);
        self.board(Command::Rdy);
        self.expect(Command::Rdy);
        let ev = self.take_events();
        assert_eq!(ev.last(), Some(&EngineEvent::State(LinkState::Ready)));
    }

    fn sat(&mut self, sd: StatusData) -> Message {
        self.board_data(Command::Sat, &sd.to_bytes());
        self.answer()
    }
}

fn data_sent(events: &[EngineEvent]) -> u64 {
    events
        .iter()
        .map(|e| match e {
            EngineEvent::DataSent { data } => data.len() as u64,
            _ => 0,
        })
        .sum()
}

/// The program bytes the events say went out, in their order.
fn sent_program(events: &[EngineEvent]) -> Vec<u8> {
    let mut out = Vec::new();
    for e in events {
        if let EngineEvent::DataSent { data } = e {
            out.extend_from_slice(data);
        }
    }
    out
}

fn aborted(events: &[EngineEvent]) -> Vec<(String, bool)> {
    events
        .iter()
        .filter_map(|e| match e {
            EngineEvent::ProgramAborted { reason, cancelled } => {
                Some((reason.to_string(), *cancelled))
            }
            _ => None,
        })
        .collect()
}

fn protocol_errors(events: &[EngineEvent]) -> Vec<String> {
    events
        .iter()
        .filter_map(|e| match e {
            EngineEvent::ProtocolError { error, .. } => Some(error.to_string()),
            _ => None,
        })
        .collect()
}

fn alarms(events: &[EngineEvent]) -> Vec<(Option<CncAlarm>, String)> {
    events
        .iter()
        .filter_map(|e| match e {
            EngineEvent::Alarm(alarm) => Some((alarm.cnc_alarm(), alarm.to_string())),
            _ => None,
        })
        .collect()
}

/// A program of `body` bytes of NC text between tape-start and EOR.
fn nc_program(body: usize) -> Vec<u8> {
    let mut p = b"%\n".to_vec();
    let line = b"N0010G01X12.345Y-6.789F100;\n";
    while p.len() < body + 2 {
        p.extend_from_slice(line);
    }
    p.truncate(body + 2);
    p.push(b'%');
    p
}

// ---------------------------------------------------------------- Protocol A: the exchange

#[test]
fn initialisation_handshake() {
    let mut b = Bench::new(ProtocolAConfig::default());
    assert_eq!(
        b.take_events(),
        [EngineEvent::State(LinkState::Initialising)]
    );
    // Before SYN, any message gets SYN: the host asks the board to initialise.
    b.board_data(Command::Sat, &board_sat(Params::POWER_ON, 0).to_bytes());
    b.expect(Command::Syn);
    b.board(Command::Syn);
    assert_eq!(b.tx(), b"07SYN\r");
    b.board(Command::Rdy);
    b.expect(Command::Rdy);
    assert_eq!(b.take_events(), [EngineEvent::State(LinkState::Ready)]);
    // No deadline while waiting for SYN; supervision once initialised.
    assert!(b.host.poll_timeout().is_some());
}

#[test]
fn set_carries_params_and_n_first_then_empty() {
    let params = Params {
        nb: 3000,
        no: 100,
        ne: 5,
        tp: 3,
        to: 30,
        ti: 0,
        tx: 20,
        tw: 2,
    };
    let cfg = ProtocolAConfig {
        params,
        packet_n: 2,
        conversion: Some((0x3B, 0x0A)),
        ..Default::default()
    };
    let mut b = Bench::new(cfg);
    b.init();
    let set = b.sat(board_sat(Params::POWER_ON, 0));
    assert_eq!(set.command, Command::Set);
    let sd = StatusData::decode(&set.data).unwrap();
    assert_eq!(sd.params, Some(params));
    assert_eq!(sd.packet_n, Some(2));
    assert_eq!(sd.conversion, Some((0x3B, 0x0A)));
    assert_eq!(sd.remote, Some(true), "byte 1 echoes the SAT");
    let ev = b.take_events();
    assert!(matches!(ev[0], EngineEvent::Status(_)));
    // The board took the values: SET with an empty data part.
    let mut now_sat = board_sat(params, 2);
    now_sat.conversion = Some((0x3B, 0x0A));
    assert_eq!(b.sat(now_sat), Message::new(Command::Set));
    assert_eq!(b.host.board_packet_n(), 2);
    // A board that lost them (e.g. power cycled without dropping the line) gets them again.
    let set = b.sat(board_sat(Params::POWER_ON, 0));
    assert_eq!(StatusData::decode(&set.data).unwrap().params, Some(params));
    // An unreadable SAT is still answered, with an empty SET.
    b.board_data(Command::Sat, b"12G4");
    assert_eq!(b.answer(), Message::new(Command::Set));
    assert_eq!(protocol_errors(&b.take_events()).len(), 1);
}

#[test]
fn clear_buffer_answers_the_next_sat_with_clb() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::ClearBuffer);
    b.expect_silence();
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 0)),
        Message::new(Command::Clb)
    );
    assert_eq!(b.sat(board_sat(Params::POWER_ON, 0)).command, Command::Set);
}

#[test]
fn rdi_then_sdi_then_the_answer_owed_to_sat() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::ReadDi);
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 0)),
        Message::new(Command::Rdi)
    );
    b.board_data(Command::Sdi, b"5A");
    assert_eq!(b.answer(), Message::new(Command::Set));
    assert!(b.take_events().contains(&EngineEvent::Di(0x5A)));
}

#[test]
fn rdi_answers_gtd_and_the_gtd_gets_its_dat_after_sdi() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::StartProgram { total: None });
    b.data(b"%\nO1;\n%");
    b.command(EngineCommand::ReadDi);
    b.board(Command::Gtd);
    b.expect(Command::Rdi);
    b.board_data(Command::Sdi, b"03");
    assert_eq!(b.dat(), b"%\nO1;\n%");
    assert!(b.take_events().contains(&EngineEvent::Di(3)));
}

#[test]
fn sdo_answers_sat_and_gtd_never_sdi() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    // SAT → SDO.
    b.command(EngineCommand::SetDo(0x12));
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 0)),
        Message::with_data(Command::Sdo, b"12".to_vec())
    );
    assert!(b.take_events().contains(&EngineEvent::DoSent(0x12)));
    // GTD → SDO; the board asks again and gets its DAT.
    b.command(EngineCommand::StartProgram { total: None });
    b.data(b"%\nO1;\n%");
    b.command(EngineCommand::SetDo(0xA5));
    b.board(Command::Gtd);
    assert_eq!(b.answer(), Message::with_data(Command::Sdo, b"A5".to_vec()));
    b.board(Command::Gtd);
    assert_eq!(b.dat(), b"%\nO1;\n%");
    // SAT → RDI, SDI → the SAT's own answer (SET): boards read an SDO right after SDI two
    // ways (protocol notes 6), so the pending SDO waits for the next SAT.
    b.command(EngineCommand::ReadDi);
    b.command(EngineCommand::SetDo(0x0F));
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 0)),
        Message::new(Command::Rdi)
    );
    b.board_data(Command::Sdi, b"80");
    assert_eq!(b.answer().command, Command::Set);
    b.expect_silence();
    let ev = b.take_events();
    assert!(ev.contains(&EngineEvent::Di(0x80)));
    assert!(!ev.contains(&EngineEvent::DoSent(0x0F)));
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 0)),
        Message::with_data(Command::Sdo, b"0F".to_vec())
    );
    assert!(b.take_events().contains(&EngineEvent::DoSent(0x0F)));
}

#[test]
fn sdi_without_rdi_is_a_reception_error() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.board_data(Command::Sdi, b"00");
    b.expect_silence();
    let errs = protocol_errors(&b.take_events());
    assert!(
        errs[0].contains("SDI") && errs[0].contains("SR0947"),
        "{errs:?}"
    );
}

// ---------------------------------------------------------------- Protocol A: NC data

#[test]
fn a_10_kib_program_in_dats_then_eod() {
    let program = nc_program(10 * 1024);
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::StartProgram {
        total: Some(program.len() as u64),
    });
    assert_eq!(b.host.data_wanted(), 16 * 1024);
    b.data(&program);
    b.command(EngineCommand::ProgramEnd);
    let mut received = Vec::new();
    let mut dats = 0;
    loop {
        b.board(Command::Gtd);
        let m = b.answer();
        match m.command {
            Command::Dat => {
                // min(4096, Nb − No) with the power-on Nb 2000, No 50.
                assert!(m.data.len() <= 1950);
                received.extend_from_slice(&m.data);
                dats += 1;
            }
            Command::Eod => break,
            other => panic!("unexpected {other}"),
        }
    }
    assert_eq!(received, program);
    assert_eq!(dats, program.len().div_ceil(1950));
    let ev = b.take_events();
    assert_eq!(sent_program(&ev), program, "the DATs' data parts, in order");
    assert!(ev.contains(&EngineEvent::State(LinkState::Sending)));
    assert_eq!(ev.last(), Some(&EngineEvent::State(LinkState::Ready)));
    assert!(ev.contains(&EngineEvent::ProgramDone {
        confirmation: Confirmation::Acknowledged
    }));
    // The CNC may still be reading the program: GTDs get EOD (§8.2)...
    b.board(Command::Gtd);
    b.expect(Command::Eod);
    // ...until a SAT shows the buffer empty. Then, nothing queued: a GTD waits, then WAT.
    b.sat(board_sat(Params::POWER_ON, 0));
    b.board(Command::Gtd);
    b.expect_silence();
    b.advance(SEC);
    b.expect(Command::Wat);
}

/// Where the board's RS is seen, a DAT goes out in pieces of No so that CS off stops the host
/// within No bytes (§4.3 (5)); behind a TCP device server, which carries no modem lines, it
/// goes out whole: one write.
#[test]
fn a_dat_is_handed_out_in_pieces_of_no_only_where_cs_is_seen() {
    for cs_visible in [true, false] {
        let mut b = Bench::ready(ProtocolAConfig {
            cs_visible,
            ..Default::default()
        });
        b.command(EngineCommand::StartProgram { total: None });
        b.data(&nc_program(9000));
        b.board(Command::Gtd);
        let pieces = b.pieces();
        let whole: usize = pieces.iter().map(Vec::len).sum();
        assert!(whole > 1950, "{whole}");
        if cs_visible {
            assert!(pieces.iter().all(|p| p.len() <= 50), "{:?}", pieces.len());
            assert_eq!(pieces.len(), whole.div_ceil(50));
        } else {
            assert_eq!(pieces.len(), 1);
        }
    }
}

#[test]
fn dat_length_follows_the_boards_nb_and_no() {
    let params = Params {
        nb: 4000,
        no: 200,
        ..Params::POWER_ON
    };
    let mut b = Bench::ready(ProtocolAConfig {
        params,
        ..Default::default()
    });
    b.command(EngineCommand::StartProgram { total: None });
    b.data(&nc_program(9000));
    b.board(Command::Gtd);
    assert_eq!(b.dat().len(), 3800);
}

#[test]
fn a_large_program_streams_through_a_bounded_buffer() {
    let cfg = ProtocolAConfig {
        params: Params {
            nb: 4000,
            no: 50,
            ..Params::POWER_ON
        },
        max_buffer: 8192,
        ..Default::default()
    };
    let mut b = Bench::ready(cfg);
    let program = nc_program(2_000_000);
    b.command(EngineCommand::StartProgram {
        total: Some(program.len() as u64),
    });
    let mut fed = 0;
    let mut received = 0usize;
    let mut hash = 0u64;
    let mut expect_hash = 0u64;
    for &x in &program {
        expect_hash = expect_hash.wrapping_mul(31).wrapping_add(u64::from(x));
    }
    loop {
        let want = b.host.data_wanted();
        if want > 0 && fed < program.len() {
            let end = (fed + want).min(program.len());
            b.data(&program[fed..end]);
            fed = end;
            if fed == program.len() {
                b.command(EngineCommand::ProgramEnd);
            }
        }
        assert!(b.host.buffer_usage().program <= 8192);
        b.board(Command::Gtd);
        let m = b.answer();
        match m.command {
            Command::Dat => {
                assert!(m.data.len() <= 3950);
                for &x in &m.data {
                    hash = hash.wrapping_mul(31).wrapping_add(u64::from(x));
                }
                received += m.data.len();
            }
            Command::Eod => break,
            other => panic!("unexpected {other}"),
        }
        b.take_events();
    }
    assert_eq!(received, program.len());
    assert_eq!(hash, expect_hash);
}

#[test]
fn late_data_gets_wat_then_dat() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    // No program queued at all: WAT after the grace (the CNC waits for a job).
    b.board(Command::Gtd);
    b.advance(999 * MS);
    b.expect_silence();
    b.advance(MS);
    b.expect(Command::Wat);
    // A program whose data is late: WAT again.
    b.command(EngineCommand::StartProgram { total: None });
    b.board(Command::Gtd);
    b.advance(SEC);
    b.expect(Command::Wat);
    // Data arriving within the grace is sent at once.
    b.board(Command::Gtd);
    b.advance(300 * MS);
    b.data(&nc_program(4000)[..2500]);
    assert_eq!(b.dat().len(), 1950);
    // Less than a full DAT within the grace: what there is goes when the grace ends.
    b.board(Command::Gtd);
    b.expect_silence();
    b.advance(SEC);
    assert_eq!(b.dat().len(), 550);
    let ev = b.take_events();
    assert_eq!(data_sent(&ev), 2500);
}

#[test]
fn eor_is_appended_and_trailing_data_dropped() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::StartProgram { total: None });
    b.data(b"%\nO1;\nM30;\n");
    b.command(EngineCommand::ProgramEnd);
    b.board(Command::Gtd);
    assert_eq!(b.dat(), b"%\nO1;\nM30;\n%");
    b.board(Command::Gtd);
    b.expect(Command::Eod);
    // After EOR nothing more is taken.
    b.command(EngineCommand::StartProgram { total: None });
    b.data(b"%\nO2;\n%\nafter EOR");
    assert_eq!(b.host.data_wanted(), 0);
    b.sat(board_sat(Params::POWER_ON, 0));
    b.board(Command::Gtd);
    assert_eq!(b.dat(), b"%\nO2;\n%");
}

#[test]
fn end_code_inside_program_data_is_refused() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::StartProgram { total: None });
    b.data(b"%\r\nO1;\r\n%");
    let ab = aborted(&b.take_events());
    assert_eq!(ab.len(), 1);
    assert!(!ab[0].1);
    assert!(
        ab[0].0.contains("end code 0x0d") && ab[0].0.contains("offset 1"),
        "{ab:?}"
    );
    assert_eq!(b.host.data_wanted(), 0);
    // The board had nothing of it: no clean-up, the next GTD just waits.
    b.board(Command::Gtd);
    b.advance(SEC);
    b.expect(Command::Wat);
    // With ETX as end code, CR is fine.
    let mut b = Bench::ready(ProtocolAConfig {
        framing: Framing::new(CodeSystem::Ascii, EndCode::Etx),
        ..Default::default()
    });
    b.command(EngineCommand::StartProgram { total: None });
    b.data(b"%\r\nO1;\r\n%");
    b.board(Command::Gtd);
    assert_eq!(b.dat(), b"%\r\nO1;\r\n%");
}

#[test]
fn cancel_answers_gtd_with_eod_and_sat_with_clb() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::StartProgram { total: None });
    b.data(&nc_program(5000));
    b.board(Command::Gtd);
    b.dat();
    b.command(EngineCommand::Cancel);
    assert_eq!(aborted(&b.take_events()), [("cancelled".to_string(), true)]);
    // A new program waits until the board's buffer has been cleared.
    b.command(EngineCommand::StartProgram { total: None });
    b.data(b"%\nO2;\n%");
    b.board(Command::Gtd);
    b.expect(Command::Eod);
    b.board(Command::Gtd);
    b.expect(Command::Wat);
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 0)),
        Message::new(Command::Clb)
    );
    b.board(Command::Gtd);
    assert_eq!(b.dat(), b"%\nO2;\n%");
    // Nothing reported done for the cancelled one.
    assert!(!b.take_events().contains(&EngineEvent::ProgramDone {
        confirmation: Confirmation::Acknowledged
    }));
}

// ---------------------------------------------------------------- RTY

#[test]
fn checksum_error_is_answered_with_rty_1() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    let mut bytes = b
        .framing
        .encode_to_vec(&Message::with_data(
            Command::Sat,
            board_sat(Params::POWER_ON, 0).to_bytes(),
        ))
        .unwrap();
    bytes[10] ^= 0x01; // a digit of the data part changes, the checksum does not
    b.board_bytes(&bytes);
    assert_eq!(b.answer(), Message::with_data(Command::Rty, b"1".to_vec()));
    let ev = b.take_events();
    assert!(
        matches!(&ev[0], EngineEvent::ProtocolError { retried: true, error } if error.is_checksum())
    );
    // The board sends it again, correctly.
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 0)),
        Message::new(Command::Set)
    );
}

#[test]
fn rty_received_retransmits_the_last_message() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::StartProgram { total: None });
    b.data(b"%\nO1;\n%");
    b.board(Command::Gtd);
    let first = b.tx();
    b.board_data(Command::Rty, b"1");
    assert_eq!(b.tx(), first);
    // Counted once only.
    b.board(Command::Gtd);
    b.expect(Command::Eod);
    assert_eq!(data_sent(&b.take_events()), 7);
}

#[test]
fn retries_above_ne_are_a_line_error() {
    let params = Params {
        ne: 2,
        ..Params::POWER_ON
    };
    let mut b = Bench::ready(ProtocolAConfig {
        params,
        ..Default::default()
    });
    b.board(Command::Gtd);
    b.advance(SEC);
    let wat = b.tx();
    b.board_data(Command::Rty, b"1");
    assert_eq!(b.tx(), wat);
    b.board_data(Command::Rty, b"1");
    assert_eq!(b.tx(), wat);
    b.board_data(Command::Rty, b"1"); // third: 3 > Ne = 2
    b.expect_silence();
    let ev = b.take_events();
    let al = alarms(&ev);
    assert_eq!(al.len(), 1);
    assert_eq!(al[0].0, Some(CncAlarm::Sr0945RetryOver));
    assert!(ev.contains(&EngineEvent::State(LinkState::Initialising)));
    // Re-initialised: waits for SYN, answers anything else with SYN.
    b.sat(board_sat(params, 0));
    b.init();
}

#[test]
fn rty_answered_by_rty_cannot_loop() {
    // Both sides see each other's RTY damaged: each corrupt frame costs one retry.
    let mut b = Bench::ready(ProtocolAConfig::default()); // Ne = 10
    let mut sent = 0;
    for _ in 0..20 {
        b.board_bytes(b"00RTY1\r"); // checksum error
        match b.msgs().as_slice() {
            [m] if m.command == Command::Rty => sent += 1,
            [] => break,
            other => panic!("{other:?}"),
        }
    }
    assert_eq!(sent, 10);
    let al = alarms(&b.take_events());
    assert_eq!(al[0].0, Some(CncAlarm::Sr0945RetryOver));
}

// ---------------------------------------------------------------- RST / ALM / board alarm

#[test]
fn alm_gets_aal_and_aborts_the_program() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::StartProgram { total: None });
    b.data(&nc_program(5000));
    b.board(Command::Gtd);
    b.dat();
    b.board(Command::Alm);
    b.expect(Command::Aal);
    let ev = b.take_events();
    assert!(ev.contains(&EngineEvent::CncAlarm));
    let ab = aborted(&ev);
    assert_eq!(ab.len(), 1);
    assert!(ab[0].0.starts_with("CNC alarm"));
    // The alarm status the SATs then report is an alarm event once, not every poll.
    let mut sat = board_sat(Params::POWER_ON, 0);
    sat.status = Some(BufferStatus::Alarm);
    sat.alarm_cause = Some(AlarmCause::NcAlarm);
    b.sat(sat);
    b.sat(sat);
    assert_eq!(alarms(&b.take_events()).len(), 1);
}

#[test]
fn rst_gets_ars_and_aborts_the_program() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::StartProgram { total: None });
    b.data(&nc_program(5000));
    b.board(Command::Gtd);
    b.dat();
    b.board(Command::Rst);
    b.expect(Command::Ars);
    let ev = b.take_events();
    assert!(ev.contains(&EngineEvent::CncReset));
    assert!(aborted(&ev)[0].0.starts_with("CNC reset"));
    // A queued program the board has nothing of stays queued through a reset.
    b.command(EngineCommand::StartProgram { total: None });
    b.data(b"%\nO7;\n%");
    b.board(Command::Rst);
    b.expect(Command::Ars);
    assert!(aborted(&b.take_events()).is_empty());
    b.board(Command::Gtd);
    assert_eq!(b.dat(), b"%\nO7;\n%");
}

fn acked(events: &[EngineEvent]) -> Option<u64> {
    events
        .iter()
        .filter_map(|e| match e {
            EngineEvent::Acked { offset } => Some(*offset),
            _ => None,
        })
        .max()
}

fn done(events: &[EngineEvent]) -> bool {
    events
        .iter()
        .any(|e| matches!(e, EngineEvent::ProgramDone { .. }))
}

/// A program is the board's only once its next exchange acknowledges the final DAT: a reset,
/// an alarm or a retry-over right after that DAT fails it at what was acknowledged before.
#[test]
fn a_reset_an_alarm_or_a_retry_over_right_after_the_final_dat_fails_the_program() {
    let params = Params {
        ne: 2,
        ..Params::POWER_ON
    };
    let program = b"%\nO1;\nG01X1;\nM30;\n%";
    let dat1 = &program[..9];
    for after in ["RST", "ALM", "retry over"] {
        let mut b = Bench::ready(ProtocolAConfig {
            params: Params {
                nb: 60,
                no: 51,
                ..params
            },
            ..Default::default()
        });
        b.command(EngineCommand::StartProgram { total: None });
        b.data(program);
        // Two DATs of min(4096, Nb - No) = 9 bytes: the second carries EOR.
        b.board(Command::Gtd);
        assert_eq!(b.dat(), dat1);
        b.board(Command::Gtd);
        assert_eq!(b.dat(), &program[9..18]);
        // The first DAT is acknowledged by the GTD that asked for the second.
        b.board(Command::Gtd);
        assert_eq!(b.dat(), &program[18..]);
        let ev = b.take_events();
        assert_eq!(acked(&ev), Some(18), "{after}");
        assert!(!done(&ev), "{after}");
        match after {
            "RST" => {
                b.board(Command::Rst);
                b.expect(Command::Ars);
            }
            "ALM" => {
                b.board(Command::Alm);
                b.expect(Command::Aal);
            }
            _ => {
                for _ in 0..3 {
                    b.board_data(Command::Rty, b"1");
                    b.drain();
                }
            }
        }
        let ev = b.take_events();
        assert!(!done(&ev), "{after}: not acknowledged, so not delivered");
        assert_eq!(aborted(&ev).len(), 1, "{after}: {ev:?}");
        assert_eq!(
            acked(&ev),
            None,
            "{after}: the final DAT is not acknowledged"
        );
    }
    // The board's next exchange acknowledges it: delivered, then EOD.
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::StartProgram { total: None });
    b.data(program);
    b.board(Command::Gtd);
    assert_eq!(b.dat(), program);
    assert!(!done(&b.take_events()));
    b.board(Command::Gtd);
    b.expect(Command::Eod);
    let ev = b.take_events();
    assert_eq!(acked(&ev), Some(program.len() as u64));
    assert!(ev.contains(&EngineEvent::ProgramDone {
        confirmation: Confirmation::Acknowledged
    }));
    // A reset after that changes nothing of it.
    b.board(Command::Rst);
    b.expect(Command::Ars);
    assert!(aborted(&b.take_events()).is_empty());
}

/// CAN after the end packet went out: the transmission was stopped before the board was back
/// in Protocol A, so the end of the program is not confirmed; the program fails at the
/// packets past the NAK window (§5.2 2 b, §5.3 1).
#[test]
fn expansion_stop_request_after_the_end_packet_fails_the_program() {
    let mut b = expansion(1);
    start(&mut b, &program_of(600), true);
    b.board(Command::Gtd);
    assert_eq!(numbers(&b.packets(1)), [0x30, 0x31, 0xFF]);
    b.monitor(Monitor::Stop);
    assert!(b.next_packet(1).is_none());
    b.board(Command::Rst);
    b.expect(Command::Ars);
    let ev = b.take_events();
    assert!(!done(&ev));
    assert_eq!(aborted(&ev).len(), 1, "{ev:?}");
    // Three packets are all within the window of ten: none is acknowledged.
    assert_eq!(acked(&ev), None);

    // The board back in Protocol A after the end packet acknowledges the whole program.
    let mut b = expansion(1);
    let program = program_of(600);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    assert_eq!(numbers(&b.packets(1)), [0x30, 0x31, 0xFF]);
    b.sat(board_sat(Params::POWER_ON, 1));
    let ev = b.take_events();
    assert_eq!(acked(&ev), Some(600));
    assert!(done(&ev));
}

/// Expansion A packets get only negative acknowledgements (§5.3): a packet past the NAK window
/// is not known to be held (the NAK may have been lost, the board may have lost the packet
/// boundary), so nothing is acknowledged before the board is back in Protocol A, and a
/// transmission cut in the middle acknowledges nothing.
#[test]
fn expansion_acknowledges_only_at_the_end_of_the_transmission() {
    let program = program_of(256 * 15 + 100);
    let mut b = expansion(1);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    assert_eq!(b.packets(1).len(), 16);
    let ev = b.take_events();
    assert_eq!(acked(&ev), None, "six packets are past the window of ten");
    assert!(!done(&ev));
    b.sat(board_sat(Params::POWER_ON, 1));
    let ev = b.take_events();
    assert_eq!(acked(&ev), Some(program.len() as u64));
    assert!(done(&ev));

    let mut b = expansion(1);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    let _ = b.next_packet(1);
    b.monitor(Monitor::Stop);
    while b.next_packet(1).is_some() {}
    b.board(Command::Rst);
    b.expect(Command::Ars);
    let ev = b.take_events();
    assert_eq!(aborted(&ev).len(), 1, "{ev:?}");
    assert_eq!(acked(&ev), None);
}

/// The next program waits until the CNC has read the last one: every byte behind an EOR is
/// ignored (§8.2), so GTDs get EOD while a SAT shows the buffer still holding data.
#[test]
fn the_next_program_waits_for_the_buffer_to_drain() {
    let mut b = expansion(1);
    start(&mut b, &program_of(600), true);
    b.board(Command::Gtd);
    assert_eq!(numbers(&b.packets(1)), [0x30, 0x31, 0xFF]);
    // The board back in Protocol A asks for more while the CNC still reads: EOD.
    b.board(Command::Gtd);
    b.expect(Command::Eod);
    assert!(done(&b.take_events()));
    start(&mut b, &program_of(300), true);
    let mut holding = board_sat(Params::POWER_ON, 1);
    holding.buffered = Some(120);
    b.sat(holding);
    b.board(Command::Gtd);
    b.expect(Command::Eod);
    // Empty: the CNC has read the EOR.
    b.sat(board_sat(Params::POWER_ON, 1));
    b.board(Command::Gtd);
    assert_eq!(numbers(&b.packets(1)), [0x30, 0xFF]);
}

#[test]
fn sat_alarm_causes_map_to_alarm_numbers() {
    for (cause, alarm) in [
        (
            AlarmCause::ChecksumRetryOver,
            Some(CncAlarm::Sr0945RetryOver),
        ),
        (
            AlarmCause::OverrunRetryOver,
            Some(CncAlarm::Sr0945RetryOver),
        ),
        (
            AlarmCause::CommandError,
            Some(CncAlarm::Sr0947InvalidResponse),
        ),
        (AlarmCause::NcAlarm, None),
    ] {
        let mut b = Bench::ready(ProtocolAConfig::default());
        let mut sat = board_sat(Params::POWER_ON, 0);
        sat.status = Some(BufferStatus::Alarm);
        sat.alarm_cause = Some(cause);
        b.sat(sat);
        b.sat(sat);
        let al = alarms(&b.take_events());
        assert_eq!(al.len(), 1, "{cause:?}");
        assert_eq!(al[0].0, alarm);
        // Out of alarm and into it again: reported again.
        b.sat(board_sat(Params::POWER_ON, 0));
        b.sat(sat);
        assert_eq!(alarms(&b.take_events()).len(), 1);
    }
}

// ---------------------------------------------------------------- errors and supervision

#[test]
fn garbage_and_bad_frames_are_typed_protocol_errors() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.board_bytes(b"00XYZ\r"); // undefined command
    b.board_bytes(b"07S\r"); // truncated
    b.board_bytes(b"junk\r"); // garbage
    b.board(Command::Dat); // a host command from the board
    b.board_data(Command::Sat, &[b'0'; 72]); // longest legal
    b.answer();
    let long = {
        let mut m = b"00SAT".to_vec();
        m.extend_from_slice(&[b'0'; 80]);
        m.push(b'\r');
        let sum = m[2..].iter().fold(0u8, |a, &x| a.wrapping_add(x));
        m[..2].copy_from_slice(format!("{sum:02X}").as_bytes());
        m
    };
    b.board_bytes(&long); // data part too long
    b.expect_silence();
    let errs = protocol_errors(&b.take_events());
    assert_eq!(errs.len(), 5, "{errs:?}");
    assert!(errs[0].contains("undefined command") && errs[0].contains("SR0948"));
    assert!(errs[1].contains("too short"));
    assert!(errs[3].contains("unexpected DAT") && errs[3].contains("SR0947"));
    assert!(errs[4].contains("exceeds 72"));
    // Still working.
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 0)),
        Message::new(Command::Set)
    );
    // A run without end code is dropped once it is longer than any message.
    b.board_bytes(&vec![b'7'; 5000]);
    b.board_bytes(b"\r");
    assert_eq!(protocol_errors(&b.take_events()).len(), 1);
    assert!(b.host.buffer_usage().rx == 0);
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 0)),
        Message::new(Command::Set)
    );
}

#[test]
fn line_errors_reinitialise() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.command(EngineCommand::StartProgram { total: None });
    b.data(&nc_program(5000));
    b.board(Command::Gtd);
    b.dat();
    b.host.handle_line_error(b.now, LineError::Framing);
    let ev = b.take_events();
    assert_eq!(alarms(&ev)[0].0, Some(CncAlarm::Sr0946FramingOverrun));
    assert!(aborted(&ev)[0].0.starts_with("link lost"));
    assert!(ev.contains(&EngineEvent::State(LinkState::Initialising)));
    b.board(Command::Gtd);
    b.expect(Command::Syn);
    b.init();

    // A parity error inside a message (ISO).
    let iso = Framing::new(CodeSystem::Iso, EndCode::Cr);
    let mut b = Bench::ready(ProtocolAConfig {
        framing: iso,
        ..Default::default()
    });
    // 'T' 54h has three bits set: without its parity bit it is a parity error.
    b.board_bytes(&[b'0', b'0', b'G', b'T', b'D', 0x8D]);
    let ev = b.take_events();
    assert!(alarms(&ev)[0].1.contains("parity"));
    assert!(ev.contains(&EngineEvent::State(LinkState::Initialising)));
}

#[test]
fn dr_off_is_line_down_with_sr0855() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    let off = ModemIn {
        dr: false,
        ..ModemIn::ALL_ON
    };
    b.host.handle_modem(b.now, off);
    let ev = b.take_events();
    assert_eq!(alarms(&ev)[0].0, Some(CncAlarm::Sr0855DataSetReadyDown));
    assert!(ev.contains(&EngineEvent::State(LinkState::LineDown)));
    b.board(Command::Syn);
    b.expect_silence();
    assert_eq!(b.host.poll_timeout(), None);
    b.host.handle_modem(b.now, ModemIn::ALL_ON);
    assert_eq!(
        b.take_events(),
        [EngineEvent::State(LinkState::Initialising)]
    );
    b.init();
}

#[test]
fn cs_off_holds_the_transmission() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    b.host.handle_modem(
        b.now,
        ModemIn {
            cs: false,
            ..ModemIn::ALL_ON
        },
    );
    b.command(EngineCommand::StartProgram { total: None });
    b.data(&nc_program(3000));
    b.board(Command::Gtd);
    b.expect_silence();
    b.host.handle_modem(b.now, ModemIn::ALL_ON);
    // Handed out in pieces of at most No (50) bytes, so that CS off stops it within No.
    let pieces = b.pieces();
    assert!(pieces.len() > 1 && pieces.iter().all(|p| p.len() <= 50));
}

#[test]
fn silence_after_the_hosts_answer_is_a_time_out() {
    let mut b = Bench::ready(ProtocolAConfig::default());
    // Tp = 5 s, To = 20 s: max(2·Tp, To) = 20 s after the last SET.
    b.advance(19 * SEC);
    let ev = b.take_events();
    assert!(ev.is_empty(), "{ev:?}");
    b.sat(board_sat(Params::POWER_ON, 0));
    b.take_events();
    b.advance(19 * SEC);
    assert!(b.take_events().is_empty());
    b.advance(SEC);
    let ev = b.take_events();
    assert_eq!(alarms(&ev)[0].0, Some(CncAlarm::Sr0944TimeOut));
    assert!(ev.contains(&EngineEvent::State(LinkState::Initialising)));
    // Waiting for SYN has no time-out.
    assert_eq!(b.host.poll_timeout(), None);
}

// ---------------------------------------------------------------- Expansion Protocol A (§5.4)

/// Initialised with n selected: the SET carried n, the board's next SAT shows it.
fn expansion(n: u8) -> Bench {
    let b = Bench::ready(ProtocolAConfig {
        packet_n: n,
        ..Default::default()
    });
    assert_eq!(b.host.board_packet_n(), n);
    b
}

/// A program of exactly `len` bytes ending in EOR.
fn program_of(len: usize) -> Vec<u8> {
    let mut p = nc_program(len - 3);
    assert_eq!(p.len(), len);
    p.truncate(len);
    p
}

fn start(b: &mut Bench, program: &[u8], end: bool) {
    b.command(EngineCommand::StartProgram {
        total: Some(program.len() as u64),
    });
    b.data(program);
    if end {
        b.command(EngineCommand::ProgramEnd);
    }
}

fn numbers(packets: &[(u8, Vec<u8>)]) -> Vec<u8> {
    packets.iter().map(|p| p.0).collect()
}

/// The program as the board assembles it from effective packets and the end packet, cut at
/// the second `%`.
fn assemble(packets: &[(u8, Vec<u8>)]) -> Vec<u8> {
    let mut v: Vec<u8> = packets
        .iter()
        .filter(|(no, _)| (0x30..=0x39).contains(no) || *no == END_PACKET)
        .flat_map(|(_, d)| d.clone())
        .collect();
    let second = v
        .iter()
        .enumerate()
        .filter(|(_, b)| **b == b'%')
        .nth(1)
        .unwrap()
        .0;
    assert!(v[second + 1..].iter().all(|&b| b == PAD));
    v.truncate(second + 1);
    v
}

/// §5.4 1) Normal. Reconstructed: board GTD → host sends packets 30h, 31h, 32h … back to
/// back without waiting, the last one as FFh (end packet, padded after EOR) → the board is
/// back in Protocol A and polls with SAT → host SET; the program is done.
#[test]
fn expansion_1_normal() {
    let mut b = expansion(1);
    let program = program_of(900);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    let packets = b.packets(1);
    assert_eq!(numbers(&packets), [0x30, 0x31, 0x32, 0xFF]);
    assert_eq!(assemble(&packets), program);
    let ev = b.take_events();
    assert_eq!(data_sent(&ev), 900);
    assert!(!ev.contains(&EngineEvent::ProgramDone {
        confirmation: Confirmation::Acknowledged
    }));
    b.expect_silence();
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 1)),
        Message::new(Command::Set)
    );
    let ev = b.take_events();
    assert!(ev.contains(&EngineEvent::ProgramDone {
        confirmation: Confirmation::Acknowledged
    }));
    assert_eq!(ev.last(), Some(&EngineEvent::State(LinkState::Ready)));
}

/// A program that fits one packet is a lone packet, numbered FFh (§5.2 2 a).
#[test]
fn expansion_lone_packet() {
    let mut b = expansion(4);
    let program = program_of(1024);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    let packets = b.packets(4);
    assert_eq!(numbers(&packets), [0xFF]);
    assert_eq!(packets[0].1, program);
    // 1025 bytes: one effective packet and an end packet with one byte.
    let mut b = expansion(4);
    let program = program_of(1025);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    let packets = b.packets(4);
    assert_eq!(numbers(&packets), [0x30, 0xFF]);
    assert_eq!(packets[1].1[0], b'%');
}

/// §5.4 2) Stop request. Reconstructed: GTD → 30h, 31h, … → the CNC is reset: board CAN →
/// host finishes the packet it is sending, sends the end packet FFh (dummy data) and goes back
/// to Protocol A → board RST → host ARS. The program is aborted once.
#[test]
fn expansion_2_stop_request() {
    let mut b = expansion(1);
    start(&mut b, &program_of(3000), true);
    b.board(Command::Gtd);
    assert_eq!(b.next_packet(1).unwrap().0, 0x30);
    assert_eq!(b.next_packet(1).unwrap().0, 0x31);
    b.monitor(Monitor::Stop);
    let end = b.next_packet(1).unwrap();
    assert_eq!(end.0, END_PACKET);
    assert!(end.1.iter().all(|&x| x == PAD));
    assert!(b.next_packet(1).is_none());
    let ev = b.take_events();
    assert_eq!(data_sent(&ev), 512);
    let ab = aborted(&ev);
    assert_eq!(ab.len(), 1);
    assert!(ab[0].0.contains("CAN"));
    b.board(Command::Rst);
    b.expect(Command::Ars);
    let ev = b.take_events();
    assert!(ev.contains(&EngineEvent::CncReset));
    assert!(aborted(&ev).is_empty());
    assert!(!ev.contains(&EngineEvent::ProgramDone {
        confirmation: Confirmation::Acknowledged
    }));
}

/// CAN while paused by DC3: the end packet still goes (§5.3 1).
#[test]
fn expansion_stop_request_while_paused() {
    let mut b = expansion(1);
    start(&mut b, &program_of(3000), true);
    b.board(Command::Gtd);
    b.next_packet(1).unwrap();
    b.monitor(Monitor::Pause);
    assert!(b.next_packet(1).is_none());
    b.monitor(Monitor::Stop);
    assert_eq!(b.next_packet(1).unwrap().0, END_PACKET);
    assert!(b.next_packet(1).is_none());
}

/// §5.4 3) Retransmission (i). Reconstructed: GTD → 30h, 31h, 32h, 33h; the board finds a
/// checksum error in 31h and sends NAK 31h while 33h is going → host finishes 33h, then sends
/// 31h, 32h, 33h again and goes on with 34h … FFh.
#[test]
fn expansion_3i_retransmission_of_an_effective_packet() {
    let mut b = expansion(1);
    let program = program_of(256 * 6 + 10);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    let mut seen = Vec::new();
    for _ in 0..4 {
        seen.push(b.next_packet(1).unwrap());
    }
    b.monitor(Monitor::Retransmit(0x31));
    let rest = b.packets(1);
    assert_eq!(numbers(&rest), [0x31, 0x32, 0x33, 0x34, 0x35, 0xFF]);
    assert_eq!(rest[0].1, seen[1].1);
    // The board keeps 30h and what follows the NAK.
    let mut good = vec![seen[0].clone()];
    good.extend(rest);
    assert_eq!(assemble(&good), program);
    // Retransmissions are not counted as sent data; the packets' data without padding.
    assert_eq!(sent_program(&b.take_events()), program);
}

/// §5.4 3) Retransmission (ii). Reconstructed: GTD → 30h, 31h, FFh; the end packet arrives
/// damaged and the board sends NAK with "the before packet No. + 1", 32h → host sends the end
/// packet again → board back in Protocol A.
#[test]
fn expansion_3ii_retransmission_of_the_end_packet() {
    let mut b = expansion(1);
    let program = program_of(600);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    let packets = b.packets(1);
    assert_eq!(numbers(&packets), [0x30, 0x31, 0xFF]);
    b.monitor(Monitor::Retransmit(0x32));
    let again = b.packets(1);
    assert_eq!(numbers(&again), [0xFF]);
    assert_eq!(again[0].1, packets[2].1);
    b.sat(board_sat(Params::POWER_ON, 1));
    assert!(b.take_events().contains(&EngineEvent::ProgramDone {
        confirmation: Confirmation::Acknowledged
    }));
}

/// §5.4 3) Retransmission (iii). Reconstructed: GTD → a lone packet FFh arrives damaged; the
/// board sends NAK with packet No. 0 (§5.2 2 b note) → host sends the lone packet again. Both
/// readings of "No. 0" (30h, the ASCII digit, and 00h) are accepted.
#[test]
fn expansion_3iii_retransmission_of_a_lone_packet() {
    for nak in [0x30, 0x00] {
        let mut b = expansion(2);
        let program = program_of(300);
        start(&mut b, &program, true);
        b.board(Command::Gtd);
        let first = b.packets(2);
        assert_eq!(numbers(&first), [0xFF]);
        b.monitor(Monitor::Retransmit(nak));
        assert_eq!(b.packets(2), first);
        assert_eq!(data_sent(&b.take_events()), 300);
    }
}

/// A NAK for a packet the host no longer keeps ends the transmission: end packet, program
/// aborted, clean-up with EOD and CLB as after a cancel.
#[test]
fn expansion_nak_for_an_unknown_packet() {
    let mut b = expansion(1);
    start(&mut b, &program_of(5000), true);
    b.board(Command::Gtd);
    for _ in 0..12 {
        b.next_packet(1).unwrap();
    }
    // 30h..39h, 30h, 31h sent: 30h is the 11th, the first 30h is gone; 3Ah never existed.
    b.monitor(Monitor::Retransmit(0x3A));
    assert_eq!(b.next_packet(1).unwrap().0, END_PACKET);
    assert!(aborted(&b.take_events())[0].0.contains("3Ah"));
    b.board(Command::Gtd);
    b.expect(Command::Eod);
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 1)),
        Message::new(Command::Clb)
    );
}

/// §5.4 4) Interruption → Restart. Reconstructed: GTD → 30h, 31h; the board's buffer fills:
/// DC3 while 31h is going → host finishes 31h and waits; DC1 → host goes on with 32h … FFh.
#[test]
fn expansion_4_interruption_then_restart() {
    let mut b = expansion(1);
    let program = program_of(1200);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    let mut all = vec![b.next_packet(1).unwrap(), b.next_packet(1).unwrap()];
    b.monitor(Monitor::Pause);
    assert!(b.next_packet(1).is_none());
    // No dummy packets and no time-out while paused, however long.
    b.advance(120 * SEC);
    assert!(b.next_packet(1).is_none());
    assert!(alarms(&b.take_events()).is_empty());
    b.monitor(Monitor::Resume);
    let rest = b.packets(1);
    assert_eq!(numbers(&rest), [0x32, 0x33, 0xFF]);
    all.extend(rest);
    assert_eq!(assemble(&all), program);
}

/// §5.4 5) Interruption → Start. Reconstructed: the board sends GTD and, before the first
/// packet, DC3 (its buffer cannot take a packet yet) → host does not start; DC1 → host starts
/// with packet 30h.
#[test]
fn expansion_5_interruption_then_start() {
    let mut b = expansion(1);
    let program = program_of(700);
    start(&mut b, &program, true);
    let mut gtd = b
        .framing
        .encode_to_vec(&Message::new(Command::Gtd))
        .unwrap();
    gtd.extend_from_slice(&Monitor::Pause.encode());
    b.board_bytes(&gtd);
    assert!(b.next_packet(1).is_none());
    b.advance(30 * SEC);
    assert!(b.next_packet(1).is_none());
    b.monitor(Monitor::Resume);
    let packets = b.packets(1);
    assert_eq!(numbers(&packets), [0x30, 0x31, 0xFF]);
    assert_eq!(assemble(&packets), program);
}

/// §5.4 6) Interruption → Retransmission. Reconstructed: GTD → 30h, 31h, 32h; DC3 → host
/// finishes 32h and waits; the board then finds 31h damaged and sends NAK 31h, which ends the
/// pause ("wait until the next monitor packet") → host resends 31h, 32h and goes on.
#[test]
fn expansion_6_interruption_then_retransmission() {
    let mut b = expansion(1);
    let program = program_of(1100);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    let sent: Vec<_> = (0..3).map(|_| b.next_packet(1).unwrap()).collect();
    b.monitor(Monitor::Pause);
    assert!(b.next_packet(1).is_none());
    b.monitor(Monitor::Retransmit(0x31));
    let rest = b.packets(1);
    assert_eq!(numbers(&rest), [0x31, 0x32, 0x33, 0xFF]);
    let mut good = vec![sent[0].clone()];
    good.extend(rest);
    assert_eq!(assemble(&good), program);
}

/// §5.4 7) Time-out detection. Reconstructed: the board supervises To from GTD to the first
/// packet and then between packets (§5.4 note). The host's data is late (the program streams
/// from the bus): after 30h nothing is ready, so the host sends an invalid packet (20h, dummy
/// data) every dummy_interval; the board ignores them and its To does not expire. When the data
/// comes, 31h follows, numbered as if no dummy had gone.
#[test]
fn expansion_7_dummy_packets_keep_the_link_alive() {
    let mut b = expansion(1);
    let program = program_of(700);
    b.command(EngineCommand::StartProgram { total: None });
    b.data(&program[..300]);
    b.board(Command::Gtd);
    assert_eq!(b.next_packet(1).unwrap().0, 0x30);
    let mut events = b.take_events();
    assert!(b.next_packet(1).is_none());
    b.advance(4999 * MS);
    assert!(b.next_packet(1).is_none());
    b.advance(MS);
    let dummy = b.next_packet(1).unwrap();
    assert_eq!(dummy.0, DUMMY_PACKET);
    assert!(dummy.1.iter().all(|&x| x == PAD));
    assert!(b.next_packet(1).is_none());
    b.advance(5 * SEC);
    assert_eq!(b.next_packet(1).unwrap().0, DUMMY_PACKET);
    // Every gap stays below the board's To (20 s), for as long as the data is late.
    b.advance(60 * SEC);
    let dummies = b.packets(1);
    assert!(dummies.iter().all(|p| p.0 == DUMMY_PACKET));
    events.extend(b.take_events());
    assert!(alarms(&events).is_empty());
    b.data(&program[300..]);
    b.command(EngineCommand::ProgramEnd);
    let rest = b.packets(1);
    assert_eq!(numbers(&rest), [0x31, 0xFF]);
    events.extend(b.take_events());
    assert_eq!(data_sent(&events), 700);
}

/// A GTD with less than one packet of data: WAT after the grace, as in Protocol A; the
/// transmission starts at a later GTD.
#[test]
fn expansion_wat_when_no_packet_is_ready() {
    let mut b = expansion(1);
    b.command(EngineCommand::StartProgram { total: None });
    b.data(&program_of(700)[..100]);
    b.board(Command::Gtd);
    b.advance(SEC);
    b.expect(Command::Wat);
}

/// Cancel during a transmission: the current packet is finished, the end packet follows (even
/// when paused), then EOD at the next GTD and CLB at the next SAT.
#[test]
fn expansion_cancel() {
    let mut b = expansion(1);
    start(&mut b, &program_of(3000), true);
    b.board(Command::Gtd);
    b.next_packet(1).unwrap();
    b.monitor(Monitor::Pause);
    b.command(EngineCommand::Cancel);
    assert_eq!(aborted(&b.take_events()), [("cancelled".to_string(), true)]);
    let end = b.next_packet(1).unwrap();
    assert_eq!(end.0, END_PACKET);
    assert!(end.1.iter().all(|&x| x == PAD));
    assert!(b.next_packet(1).is_none());
    b.board(Command::Gtd);
    b.expect(Command::Eod);
    assert_eq!(
        b.sat(board_sat(Params::POWER_ON, 1)),
        Message::new(Command::Clb)
    );
    assert!(!b.take_events().contains(&EngineEvent::ProgramDone {
        confirmation: Confirmation::Acknowledged
    }));
}

/// Monitor packets with and without parity, split off a stream that also carries messages.
#[test]
fn expansion_monitor_packets_split_from_the_stream() {
    let mut b = expansion(1);
    start(&mut b, &program_of(3000), true);
    b.board(Command::Gtd);
    b.next_packet(1).unwrap();
    // DC3 without parity, checksum of 13h + 20h = 33h, delivered byte by byte.
    for byte in [0x13, 0x20, b'3', b'3', 0x0D] {
        b.board_bytes(&[byte]);
    }
    assert!(b.next_packet(1).is_none());
    // NAK with parity (95h + 30h = C5h).
    b.board_bytes(&[0x95, 0x30, b'C', b'5', 0x0D]);
    assert_eq!(b.next_packet(1).unwrap().0, 0x30);
    // A damaged monitor packet is a protocol error and changes nothing.
    b.board_bytes(&[0x13, 0x20, b'0', b'0', 0x0D]);
    assert_eq!(b.next_packet(1).unwrap().0, 0x31);
    assert!(protocol_errors(&b.take_events())[0].contains("monitor"));
    // Protocol A messages other than SYN/RST/ALM during the packets are ignored.
    b.board(Command::Sat);
    assert!(protocol_errors(&b.take_events())[0].contains("unexpected SAT"));
}

/// Expansion A over an ISO link with ETX: messages carry parity and end with ETX, monitor
/// packets still end with CR.
#[test]
fn expansion_over_iso_etx() {
    let mut b = Bench::ready(ProtocolAConfig {
        framing: Framing::new(CodeSystem::Iso, EndCode::Etx),
        packet_n: 1,
        ..Default::default()
    });
    let program = program_of(600);
    start(&mut b, &program, true);
    b.board(Command::Gtd);
    b.next_packet(1).unwrap();
    b.monitor(Monitor::Retransmit(0x30));
    let rest = b.packets(1);
    assert_eq!(numbers(&rest), [0x30, 0x31, 0xFF]);
    assert_eq!(assemble(&rest), program);
    b.sat(board_sat(Params::POWER_ON, 1));
    assert!(b.take_events().contains(&EngineEvent::ProgramDone {
        confirmation: Confirmation::Acknowledged
    }));
}

#[test]
fn invalid_settings_are_refused_with_every_problem() {
    let cfg = ProtocolAConfig {
        packet_n: 3,
        wat_grace: 15 * SEC,
        max_buffer: 100,
        params: Params {
            tw: 9,
            ..Params::POWER_ON
        },
        ..Default::default()
    };
    let err = ProtocolAHost::new(cfg, Instant::now()).unwrap_err();
    assert_eq!(err.problems.len(), 4, "{err}");
    let text = err.to_string();
    assert!(
        text.contains("packet_n = 3") && text.contains("tw = 9"),
        "{text}"
    );
}

// ---------------------------------------------------------------- robustness

mod fuzz {
    use super::*;
    use proptest::prelude::*;

    #[derive(Debug, Clone)]
    enum Op {
        Bytes(Vec<u8>),
        Msg(Command, Vec<u8>),
        Monitor(u8, u8),
        Advance(u32),
        Command(u8, Vec<u8>),
        LineError(u8),
        Modem(bool, bool),
        Poll(u8),
    }

    fn op() -> impl Strategy<Value = Op> {
        prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..300).prop_map(Op::Bytes),
            (
                proptest::sample::select(Command::ALL.to_vec()),
                proptest::collection::vec(0x20u8..0x7f, 0..80)
            )
                .prop_map(|(c, d)| Op::Msg(c, d)),
            (0u8..4, any::<u8>()).prop_map(|(c, n)| Op::Monitor(c, n)),
            (0u32..30_000).prop_map(Op::Advance),
            (0u8..7, proptest::collection::vec(any::<u8>(), 0..3000))
                .prop_map(|(c, d)| Op::Command(c, d)),
            (0u8..3).prop_map(Op::LineError),
            (any::<bool>(), any::<bool>()).prop_map(|(dr, cs)| Op::Modem(dr, cs)),
            (0u8..5).prop_map(Op::Poll),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]

        #[test]
        fn arbitrary_input_never_panics_and_stays_bounded(
            ops in proptest::collection::vec(op(), 1..120),
            iso in any::<bool>(),
            n in proptest::sample::select(vec![0u8, 1, 2, 4]),
        ) {
            let framing = Framing::new(
                if iso { CodeSystem::Iso } else { CodeSystem::Ascii },
                EndCode::Cr,
            );
            let mut b = Bench::new(ProtocolAConfig { framing, packet_n: n, max_buffer: 8192, ..Default::default() });
            b.init();
            for op in ops {
                match op {
                    Op::Bytes(bytes) => b.board_bytes(&bytes),
                    Op::Msg(c, d) => {
                        if let Ok(bytes) = framing.encode_to_vec(&Message::with_data(c, d)) {
                            b.board_bytes(&bytes);
                        }
                    }
                    Op::Monitor(c, no) => {
                        let m = [Monitor::Stop, Monitor::Retransmit(no), Monitor::Pause, Monitor::Resume];
                        b.monitor(m[usize::from(c)]);
                    }
                    Op::Advance(ms) => b.advance(Duration::from_millis(u64::from(ms))),
                    Op::Command(c, d) => {
                        let cmd = match c {
                            0 => EngineCommand::StartProgram { total: None },
                            1 | 2 => EngineCommand::ProgramData(Bytes::from(d)),
                            3 => EngineCommand::ProgramEnd,
                            4 => EngineCommand::Cancel,
                            5 => EngineCommand::SetDo(d.first().copied().unwrap_or(0)),
                            _ => EngineCommand::ReadDi,
                        };
                        b.command(cmd);
                    }
                    Op::LineError(e) => {
                        let e = [LineError::Parity, LineError::Framing, LineError::Overrun][usize::from(e)];
                        b.host.handle_line_error(b.now, e);
                    }
                    Op::Modem(dr, cs) => b.host.handle_modem(b.now, ModemIn { dr, cs, cd: true }),
                    Op::Poll(k) => {
                        for _ in 0..k {
                            let _ = b.host.poll_transmit(b.now);
                        }
                    }
                }
                let u = b.host.buffer_usage();
                prop_assert!(u.rx <= cellgate_core::fanuc::message::MAX_FRAME + 5, "{u:?}");
                prop_assert!(u.tx <= 4 * cellgate_core::fanuc::message::MAX_FRAME, "{u:?}");
                prop_assert!(u.program <= 8192 + 3000, "{u:?}");
                prop_assert!(u.packets <= 2 * 10 * 1028, "{u:?}");
                b.take_events();
                if let Some(t) = b.host.poll_timeout() {
                    // Deadlines are never in the past after the host has acted on them.
                    b.host.handle_timeout(b.now.max(t));
                    while b.host.poll_transmit(b.now.max(t)).is_some() {}
                    prop_assert!(b.host.poll_timeout().is_none_or(|t2| t2 > b.now.max(t)));
                    b.now = b.now.max(t);
                }
            }
        }
    }
}
