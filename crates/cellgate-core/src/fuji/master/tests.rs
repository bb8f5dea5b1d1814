use std::collections::BTreeMap;

use proptest::prelude::*;

use super::*;
use crate::fuji::command::{FileType, Module, Sta};
use crate::fuji::frame::{BccCalc, BccCode, BccKind, BccRange, FrameSettings};
use crate::sim::micrex::{Micrex, MicrexCommand, MicrexConfig, MicrexEvent};
use crate::testkit::Pair;

const TIMEOUT: Duration = Duration::from_millis(200);

fn line() -> LineSettings {
    LineSettings::with_baud(9600)
}

fn settings(mode: OperationMode) -> MasterSettings {
    MasterSettings {
        line: line(),
        reply_timeout: TIMEOUT,
        probe_interval: Duration::from_secs(5),
        ..MasterSettings::new(mode)
    }
}

fn plc(mode: OperationMode, stations: &[u8]) -> MicrexConfig {
    MicrexConfig {
        line: line(),
        stations: stations.to_vec(),
        ..MicrexConfig::new(mode)
    }
}

fn pair(master: MasterSettings, plc: MicrexConfig) -> Pair<Master, Micrex> {
    Pair::new(
        Master::new(master).unwrap(),
        Micrex::new(plc).unwrap(),
        line(),
        Instant::now(),
    )
}

fn request(id: RequestId, station: u8, request: Request) -> MasterCommand {
    MasterCommand::Request {
        id,
        station,
        request,
    }
}

fn read(id: RequestId, station: u8, module: Module, address: u16, words: usize) -> MasterCommand {
    request(
        id,
        station,
        Request::read_words(module, address, words).unwrap(),
    )
}

/// The Done events among `events`: id → result.
fn done(events: &[MasterEvent]) -> Vec<(RequestId, Result<Reply, MasterError>)> {
    events
        .iter()
        .filter_map(|e| match e {
            MasterEvent::Done { id, result, .. } => Some((*id, result.clone())),
            _ => None,
        })
        .collect()
}

fn words_of(r: &Result<Reply, MasterError>) -> Vec<u32> {
    match r {
        Ok(Reply::Read { words, .. }) => words.clone(),
        other => panic!("not a read reply: {other:?}"),
    }
}

/// A master alone, driven by hand: the test is the scripted module.
struct Solo {
    m: Master,
    now: Instant,
    sent: Vec<Vec<u8>>,
    events: Vec<MasterEvent>,
}

impl Solo {
    fn new(s: MasterSettings) -> Solo {
        Solo {
            m: Master::new(s).unwrap(),
            now: Instant::now(),
            sent: Vec::new(),
            events: Vec::new(),
        }
    }
    fn pump(&mut self) {
        while let Some(b) = self.m.poll_transmit(self.now) {
            self.sent.push(b);
        }
        while let Some(e) = self.m.poll_event() {
            self.events.push(e);
        }
    }
    fn cmd(&mut self, c: MasterCommand) {
        self.m.handle_command(self.now, c);
        self.pump();
    }
    fn input(&mut self, bytes: &[u8]) {
        self.m.handle_input(self.now, bytes);
        self.pump();
    }
    fn advance_to(&mut self, t: Instant) {
        self.now = self.now.max(t);
        self.m.handle_timeout(self.now);
        self.pump();
    }
    fn take_sent(&mut self) -> Vec<Vec<u8>> {
        std::mem::take(&mut self.sent)
    }
    fn take_events(&mut self) -> Vec<MasterEvent> {
        std::mem::take(&mut self.events)
    }
}

#[test]
fn read_goes_out_as_the_section_7_2_sample_and_its_reply_completes_it() {
    let mut s = Solo::new(settings(OperationMode::One));
    assert_eq!(s.m.poll_timeout(), None, "nothing ticks when idle");
    s.cmd(read(7, 0, Module::M, 0, 1));
    assert_eq!(s.take_sent(), vec![b":000000010400000200\r".to_vec()]);
    assert!(s.m.busy());
    // The deadline: request on the line, the module's allowance, the longest reply's line
    // time (":" + 12 bytes × 2 + CR = 26 characters).
    let l = line();
    assert_eq!(
        s.m.poll_timeout(),
        Some(s.now + l.time_for_chars(20) + TIMEOUT + l.time_for_chars(26))
    );
    s.input(b":0000000107000002000112AB\r");
    let ev = s.take_events();
    assert_eq!(
        ev,
        vec![MasterEvent::Done {
            id: 7,
            station: 0,
            result: Ok(Reply::Read {
                module: Module::M,
                address: 0,
                data: vec![0x12, 0xAB],
                words: vec![0x12AB],
            }),
        }]
    );
    assert_eq!(s.m.poll_timeout(), None, "nothing ticks when idle");
    let c = s.m.counters();
    let st = &c.stations[&0];
    assert_eq!(
        (st.requests, st.replies, st.timeouts, st.retries),
        (1, 1, 0, 0)
    );
}

#[test]
fn every_command_against_the_simulated_plc() {
    let mut cfg = plc(OperationMode::One, &[0]);
    cfg.files = vec![(30, FileType::Si, 64), (31, FileType::Di, 64)];
    cfg.messages = vec![2];
    let mut r = pair(settings(OperationMode::One), cfg);
    let si = Module::file(30, FileType::Si).unwrap();
    let di = Module::file(31, FileType::Di).unwrap();
    let cmds = vec![
        request(
            1,
            0,
            Request::write_words(Module::D, 3, &[0x1234, 0xABCD]).unwrap(),
        ),
        read(2, 0, Module::D, 3, 2),
        request(
            3,
            0,
            Request::write_words(Module::TS, 0, &[0x0000_1500]).unwrap(),
        ),
        read(4, 0, Module::TS, 0, 1),
        request(5, 0, Request::write_words(si, 10, &[0xBEEF]).unwrap()),
        read(6, 0, si, 10, 1),
        request(7, 0, Request::write_words(di, 1, &[0x1234_5678]).unwrap()),
        read(8, 0, di, 1, 1),
        request(9, 0, Request::Clear { module: Module::D }),
        read(10, 0, Module::D, 3, 2),
        request(
            11,
            0,
            Request::Transfer {
                message: 2,
                data: vec![10, 0, 0, 0, 0x78, 0x56, 0x34, 0x12],
            },
        ),
    ];
    for c in cmds {
        r.command_a(c);
    }
    r.settle(Duration::from_secs(10));
    let ev = r.take_a_events();
    let d = done(&ev);
    assert_eq!(d.len(), 11, "{ev:?}");
    assert_eq!(
        d[0].1,
        Ok(Reply::Written {
            module: Module::D,
            address: 3,
            bytes: 4
        })
    );
    assert_eq!(words_of(&d[1].1), vec![0x1234, 0xABCD]);
    assert_eq!(words_of(&d[3].1), vec![0x1500]);
    assert_eq!(words_of(&d[5].1), vec![0xBEEF]);
    assert_eq!(words_of(&d[7].1), vec![0x1234_5678]);
    assert_eq!(d[8].1, Ok(Reply::Cleared { module: Module::D }));
    assert_eq!(words_of(&d[9].1), vec![0, 0]);
    assert_eq!(d[10].1, Ok(Reply::Transferred { message: 2 }));
    // Ids come back in order, and the PLC saw every write, the clear and the transfer.
    assert_eq!(
        d.iter().map(|(id, _)| *id).collect::<Vec<_>>(),
        (1..=11).collect::<Vec<_>>()
    );
    let b = r.take_b_events();
    assert!(b.contains(&MicrexEvent::Cleared {
        station: 0,
        module: Module::D
    }));
    assert!(b.contains(&MicrexEvent::TransferReceived {
        station: 0,
        message: 2,
        data: vec![10, 0, 0, 0, 0x78, 0x56, 0x34, 0x12],
    }));
    assert_eq!(r.b.words(0, di, 1, 1), Some(vec![0x1234_5678]));
    // The SI word went low byte first, the D words high byte first (§5-3-6).
    let sent = String::from_utf8(r.a_sent.clone()).unwrap();
    assert!(sent.contains(":0100001E060A000200EFBE\r"), "{sent}");
    assert!(
        sent.contains(":010000050803000400 1234ABCD\r".replace(' ', "").as_str()),
        "{sent}"
    );
    assert_eq!(r.a.poll_timeout(), None);
}

#[test]
fn every_sta_code_ends_the_request_with_a_typed_error() {
    let mut s = Solo::new(settings(OperationMode::One));
    let codes = [0x12u8, 0x20, 0x21, 0x22, 0x24, 0x32, 0xA7, 0x5A];
    for (i, code) in codes.iter().enumerate() {
        let id = i as u64;
        s.cmd(request(
            id,
            0,
            Request::write_words(Module::D, 1, &[5]).unwrap(),
        ));
        assert_eq!(s.take_sent().len(), 1);
        // Error reply: the header alone, BYTEN 00 (FFU120B notes 2).
        let reply = FrameSettings::default().encode(&[0x01, *code, 0x00, 0x05, 0x00]);
        s.input(&reply);
        let d = done(&s.take_events());
        let Err(MasterError::Sta(e)) = &d[0].1 else {
            panic!("{d:?}");
        };
        assert_eq!(e.sta, Sta::from_code(*code).unwrap());
        assert_eq!((e.station, e.module, e.address), (0, 5, Some(1)));
        assert!(e.to_string().contains("FFU120B §5-3-5"));
    }
    let c = s.m.counters();
    let st = &c.stations[&0];
    assert_eq!(st.replies, 8);
    assert_eq!(st.retries, 0, "STA errors are not retried");
    assert_eq!(st.error_replies.len(), 8);
    assert!(st.error_replies.values().all(|n| *n == 1));
    assert!(matches!(st.last_error, Some(MasterError::Sta(_))));
    assert!(st.up);
}

#[test]
fn sta_errors_from_the_simulated_plc() {
    let mut r = pair(settings(OperationMode::One), plc(OperationMode::One, &[0]));
    r.command_b(MicrexCommand::Protect {
        station: 0,
        module: Module::D,
        address: 10,
        words: 2,
    });
    r.command_a(request(
        1,
        0,
        Request::write_words(Module::D, 11, &[1]).unwrap(),
    ));
    r.command_a(read(2, 0, Module::file(40, FileType::Si).unwrap(), 0, 1));
    r.command_a(read(3, 0, Module::by_name("W120").unwrap(), 0, 1));
    r.command_a(read(4, 0, Module::D, 63, 2));
    r.command_a(request(
        5,
        0,
        Request::Transfer {
            message: 9,
            data: vec![1],
        },
    ));
    r.settle(Duration::from_secs(5));
    r.command_b(MicrexCommand::SetInterlock {
        station: 0,
        on: true,
    });
    r.command_a(read(6, 0, Module::D, 0, 1));
    r.settle(Duration::from_secs(5));
    r.command_b(MicrexCommand::SetInterlock {
        station: 0,
        on: false,
    });
    r.command_a(read(7, 0, Module::D, 0, 1));
    r.settle(Duration::from_secs(5));
    let d = done(&r.take_a_events());
    let sta = |i: usize| match &d[i].1 {
        Err(MasterError::Sta(e)) => Some(e.sta),
        _ => None,
    };
    assert_eq!(sta(0), Some(Sta::MemoryWrite));
    assert_eq!(sta(1), Some(Sta::ModuleNumber), "undefined file");
    assert_eq!(sta(2), Some(Sta::ModuleNumber), "no P-link card");
    assert_eq!(sta(3), Some(Sta::OverMemorySize));
    assert_eq!(sta(4), Some(Sta::Transfer), "message not registered");
    assert_eq!(sta(5), Some(Sta::Interlock));
    assert!(d[6].1.is_ok());
    let msg = d[5].1.as_ref().unwrap_err().to_string();
    assert!(
        msg.starts_with(
            "module in interlock: only the loader may read or write now (STA 22, FFU120B §5-3-5)"
        ),
        "{msg}"
    );
}

#[test]
fn time_out_then_retries_then_a_typed_error() {
    let mut st = settings(OperationMode::One);
    st.retries = 2;
    st.down_after = 10;
    let mut s = Solo::new(st);
    s.cmd(read(1, 0, Module::D, 0, 1));
    let l = line();
    let per_attempt = l.time_for_chars(20) + TIMEOUT + l.time_for_chars(26);
    for attempt in 1..=3 {
        let sent = s.take_sent();
        assert_eq!(sent.len(), 1, "attempt {attempt}");
        assert_eq!(sent[0], b":000000050400000200\r");
        let deadline = s.m.poll_timeout().unwrap();
        assert_eq!(deadline, s.now + per_attempt);
        // Not a moment early.
        s.advance_to(deadline - Duration::from_nanos(1));
        assert!(s.take_sent().is_empty());
        s.advance_to(deadline);
    }
    assert!(s.take_sent().is_empty());
    let d = done(&s.take_events());
    assert_eq!(
        d,
        vec![(
            1,
            Err(MasterError::TimeOut {
                station: 0,
                request: "read",
                attempts: 3
            })
        )]
    );
    let c = s.m.counters();
    let stc = &c.stations[&0];
    assert_eq!(
        (stc.requests, stc.timeouts, stc.retries, stc.replies),
        (1, 3, 2, 0)
    );
    assert_eq!(s.m.poll_timeout(), None);
}

#[test]
fn a_corrupted_bcc_is_retried_at_once_and_counted() {
    let frame = FrameSettings {
        bcc: BccKind::Set1,
        bcc_range: BccRange::StartTextEnd,
        bcc_calc: BccCalc::Add,
        bcc_code: BccCode::TransmissionCode,
        ..FrameSettings::default()
    };
    // Scripted: the appendix's request, a reply with a wrong BCC, then a good one.
    let mut st = settings(OperationMode::One);
    st.frame = frame.clone();
    let mut s = Solo::new(st);
    s.cmd(read(1, 0, Module::M, 0, 1));
    assert_eq!(s.take_sent(), vec![b":000000010400000200\rAE".to_vec()]);
    let good = frame.encode(&[0, 0, 0, 1, 7, 0, 0, 2, 0, 1, 0x12, 0xAB]);
    let mut bad = good.clone();
    let n = bad.len();
    bad[n - 1] = if bad[n - 1] == b'0' { b'1' } else { b'0' };
    s.input(&bad);
    assert_eq!(s.take_sent().len(), 1, "sent again at once");
    assert!(done(&s.events).is_empty());
    s.input(&good);
    let d = done(&s.take_events());
    assert_eq!(words_of(&d[0].1), vec![0x12AB]);
    let c = s.m.counters();
    assert_eq!(c.stations[&0].bcc_errors, 1);
    assert_eq!(c.stations[&0].retries, 1);
    assert_eq!(c.stations[&0].timeouts, 0);
    assert_eq!(c.receive_errors.bcc, 1);

    // Against the simulated PLC's fault hook.
    let mut m = settings(OperationMode::One);
    m.frame = frame.clone();
    let mut p = plc(OperationMode::One, &[0]);
    p.frame = frame;
    let mut r = pair(m, p);
    r.command_b(MicrexCommand::CorruptNextBcc { station: 0 });
    r.command_a(read(2, 0, Module::D, 0, 1));
    r.settle(Duration::from_secs(5));
    let d = done(&r.take_a_events());
    assert!(d[0].1.is_ok(), "{d:?}");
    let c = r.a.counters();
    assert_eq!((c.stations[&0].bcc_errors, c.stations[&0].retries), (1, 1));
}

#[test]
fn a_reply_cut_short_is_a_time_out_and_retried() {
    let mut r = pair(settings(OperationMode::One), plc(OperationMode::One, &[0]));
    r.command_b(MicrexCommand::DropReplyBytes {
        station: 0,
        count: 3,
    });
    r.command_a(read(1, 0, Module::D, 0, 1));
    r.settle(Duration::from_secs(5));
    let d = done(&r.take_a_events());
    assert!(d[0].1.is_ok(), "{d:?}");
    let c = r.a.counters();
    assert_eq!((c.stations[&0].timeouts, c.stations[&0].retries), (1, 1));
}

/// Polls every station in `stations` on `r` for `span`: a station's next read goes out when
/// its last one ended (a station reported down is asked again 100 ms later). Returns the
/// good replies per station.
fn poll_loop(r: &mut Pair<Master, Micrex>, stations: &[u8], span: Duration) -> BTreeMap<u8, u64> {
    let end = r.now + span;
    let mut due: BTreeMap<u8, Option<Instant>> =
        stations.iter().map(|s| (*s, Some(r.now))).collect();
    let mut ok: BTreeMap<u8, u64> = stations.iter().map(|s| (*s, 0)).collect();
    let mut id = 0;
    loop {
        for (s, d) in due.iter_mut() {
            if d.is_some_and(|t| t <= r.now) {
                id += 1;
                *d = None;
                r.a.handle_command(r.now, read(id, *s, Module::D, 0, 1));
            }
        }
        r.pump();
        for (_, e) in std::mem::take(&mut r.a_events) {
            if let MasterEvent::Done {
                station, result, ..
            } = e
            {
                let pause = match &result {
                    Ok(_) => {
                        *ok.entry(station).or_default() += 1;
                        Duration::ZERO
                    }
                    Err(MasterError::StationDown { .. }) => Duration::from_millis(100),
                    Err(_) => Duration::ZERO,
                };
                due.insert(station, Some(r.now + pause));
            }
        }
        if due.values().any(|d| d.is_some_and(|t| t <= r.now)) {
            continue;
        }
        if r.now >= end {
            return ok;
        }
        let limit = due
            .values()
            .flatten()
            .copied()
            .chain([end])
            .min()
            .unwrap_or(end);
        if !r.step(limit) {
            r.now = limit;
        }
    }
}

#[test]
fn multi_drop_dead_station_costs_the_others_only_its_own_time_outs() {
    let span = Duration::from_secs(60);
    // Three live stations alone on the line: their pace.
    let mut alone = pair(
        settings(OperationMode::Three),
        plc(OperationMode::Three, &[1, 2, 3]),
    );
    let base = poll_loop(&mut alone, &[1, 2, 3], span);
    // The same three with station 4 on the line, silent.
    let mut with_dead = pair(
        settings(OperationMode::Three),
        plc(OperationMode::Three, &[1, 2, 3, 4]),
    );
    with_dead.command_b(MicrexCommand::SetSilent {
        station: 4,
        on: true,
    });
    let got = poll_loop(&mut with_dead, &[1, 2, 3, 4], span);
    for s in [1, 2, 3] {
        assert!(base[&s] > 300, "station {s} alone: {} replies", base[&s]);
        assert!(
            got[&s] * 100 >= base[&s] * 90,
            "station {s}: {} replies with a dead neighbour, {} without",
            got[&s],
            base[&s]
        );
    }
    assert_eq!(got[&4], 0);
    let c = with_dead.a.counters();
    let dead = &c.stations[&4];
    assert!(!dead.up);
    // Three time-outs to mark it down, then one probe every 5 s.
    assert!(
        (3 + 10..=3 + 13).contains(&dead.timeouts),
        "dead station: {} time-outs",
        dead.timeouts
    );
    assert!(dead.refused_down > 100);
    // Without the down mark, each round would wait out three time-outs: a much slower line.
    let mut st = settings(OperationMode::Three);
    st.down_after = u32::MAX;
    let mut naive = Pair::new(
        Master::new(st).unwrap(),
        Micrex::new(plc(OperationMode::Three, &[1, 2, 3, 4])).unwrap(),
        line(),
        Instant::now(),
    );
    naive.command_b(MicrexCommand::SetSilent {
        station: 4,
        on: true,
    });
    let slow = poll_loop(&mut naive, &[1, 2, 3, 4], span);
    assert!(slow[&1] * 2 < got[&1], "naive {} vs {}", slow[&1], got[&1]);
}

#[test]
fn a_station_marked_down_fails_fast_is_probed_and_comes_back() {
    let mut r = pair(
        settings(OperationMode::Three),
        plc(OperationMode::Three, &[5]),
    );
    r.command_b(MicrexCommand::SetSilent {
        station: 5,
        on: true,
    });
    r.command_a(read(1, 5, Module::D, 0, 1));
    r.settle(Duration::from_secs(5));
    let ev = r.take_a_events();
    assert!(ev.contains(&MasterEvent::StationDown {
        station: 5,
        timeouts: 3
    }));
    assert!(matches!(
        done(&ev)[0].1,
        Err(MasterError::TimeOut { attempts: 3, .. })
    ));
    assert!(r.a.is_down(5));
    // Down: refused at once, nothing on the line.
    let before = r.a_sent.len();
    r.command_a(read(2, 5, Module::D, 0, 1));
    assert!(matches!(
        done(&r.take_a_events())[0].1,
        Err(MasterError::StationDown { station: 5, .. })
    ));
    assert_eq!(r.a_sent.len(), before);
    // After the probe interval one request goes out, once; the station answers again.
    r.command_b(MicrexCommand::SetSilent {
        station: 5,
        on: false,
    });
    r.run_for(Duration::from_secs(5));
    r.command_a(read(3, 5, Module::D, 0, 1));
    r.settle(Duration::from_secs(1));
    let ev = r.take_a_events();
    assert!(
        ev.contains(&MasterEvent::StationUp { station: 5 }),
        "{ev:?}"
    );
    assert!(done(&ev)[0].1.is_ok());
    assert!(!r.a.is_down(5));
    // A probe that fails costs one attempt and re-arms the interval.
    r.command_b(MicrexCommand::SetSilent {
        station: 5,
        on: true,
    });
    for id in 10..13 {
        r.command_a(read(id, 5, Module::D, 0, 1));
        r.settle(Duration::from_secs(2));
    }
    r.take_a_events();
    r.run_for(Duration::from_secs(5));
    let t = r.a.counters().stations[&5].timeouts;
    r.command_a(read(20, 5, Module::D, 0, 1));
    r.settle(Duration::from_secs(2));
    assert_eq!(
        r.a.counters().stations[&5].timeouts,
        t + 1,
        "a probe is one attempt"
    );
}

#[test]
fn transfers_both_ways_in_mode_1() {
    let mut cfg = plc(OperationMode::One, &[0]);
    cfg.messages = vec![3];
    let mut r = pair(settings(OperationMode::One), cfg);
    // PLC → PC while idle.
    r.command_b(MicrexCommand::QueueTransfer {
        message: 1,
        data: vec![0x34, 0x12],
    });
    r.settle(Duration::from_secs(1));
    assert_eq!(
        r.take_a_events(),
        vec![MasterEvent::Transfer {
            message: 1,
            data: vec![0x34, 0x12]
        }]
    );
    assert_eq!(r.b_sent, b":90000001023412\r");
    // PC → PLC.
    r.command_a(request(
        1,
        0,
        Request::Transfer {
            message: 3,
            data: vec![1, 2, 3],
        },
    ));
    r.settle(Duration::from_secs(1));
    assert_eq!(
        done(&r.take_a_events()),
        vec![(1, Ok(Reply::Transferred { message: 3 }))]
    );
    // A PLC transfer arriving while a request waits for its reply is reported, and the
    // reply still completes the request.
    r.command_a(read(2, 0, Module::D, 0, 1));
    r.inject_to_a(&FrameSettings::default().encode(&[0x90, 0, 0, 4, 1, 0x55]));
    r.settle(Duration::from_secs(1));
    let ev = r.take_a_events();
    assert_eq!(
        ev[0],
        MasterEvent::Transfer {
            message: 4,
            data: vec![0x55]
        }
    );
    assert!(done(&ev)[0].1.is_ok());
    // A PLC transfer with the message number of our transfer is not taken for its answer.
    r.command_a(request(
        3,
        0,
        Request::Transfer {
            message: 3,
            data: vec![9],
        },
    ));
    r.inject_to_a(&FrameSettings::default().encode(&[0x90, 0, 0, 3, 1, 0x66]));
    r.settle(Duration::from_secs(1));
    let ev = r.take_a_events();
    assert!(ev.contains(&MasterEvent::Transfer {
        message: 3,
        data: vec![0x66]
    }));
    assert_eq!(done(&ev), vec![(3, Ok(Reply::Transferred { message: 3 }))]);
    assert_eq!(r.a.counters().transfers_received, 3);
}

#[test]
fn requests_that_cannot_be_right_are_refused_before_sending() {
    let refused = |mode: OperationMode, c: MasterCommand| -> MasterError {
        let mut s = Solo::new(settings(mode));
        s.cmd(c);
        assert!(s.take_sent().is_empty());
        match done(&s.take_events()).pop() {
            Some((_, Err(e))) => e,
            other => panic!("{other:?}"),
        }
    };
    let transfer = || {
        request(
            1,
            1,
            Request::Transfer {
                message: 1,
                data: vec![1],
            },
        )
    };
    let e = refused(OperationMode::Three, transfer());
    assert!(e.to_string().contains("mode 3"), "{e}");
    let e = refused(OperationMode::One, read(1, 5, Module::D, 0, 1));
    assert!(e.to_string().contains("station other than 00"), "{e}");
    let e = refused(OperationMode::Three, read(1, 100, Module::D, 0, 1));
    assert!(matches!(
        e,
        MasterError::Refused(CommandError::Station { station: 100 })
    ));
    let e = refused(OperationMode::Four, read(1, 0, Module::D, 0, 1));
    assert!(e.to_string().contains("mode 4"), "{e}");
    let e = refused(
        OperationMode::One,
        MasterCommand::Send {
            id: 1,
            data: vec![1],
        },
    );
    assert!(e.to_string().contains("non-procedure"), "{e}");
    let e = refused(
        OperationMode::One,
        request(
            1,
            0,
            Request::Read {
                module: Module::D,
                address: 0,
                bytes: 3,
            },
        ),
    );
    assert!(e.to_string().contains("STA 21"), "{e}");
    // The queue is bounded.
    let mut st = settings(OperationMode::Three);
    st.queue_limit = 2;
    let mut s = Solo::new(st);
    for id in 0..4 {
        s.cmd(read(id, 1, Module::D, 0, 1));
    }
    // One on the line, two waiting, the fourth refused.
    assert_eq!(s.m.queued(), 2);
    assert_eq!(
        done(&s.take_events()),
        vec![(3, Err(MasterError::QueueFull { limit: 2 }))]
    );
    // At most 31 stations on a line.
    let mut st = settings(OperationMode::Three);
    st.queue_limit = 100;
    let mut s = Solo::new(st);
    for station in 0..32 {
        s.cmd(read(u64::from(station), station, Module::D, 0, 1));
    }
    assert_eq!(
        done(&s.take_events()),
        vec![(31, Err(MasterError::TooManyStations { station: 31 }))]
    );
}

#[test]
fn invalid_settings_are_reported_together() {
    let mut st = settings(OperationMode::One);
    st.frame.bcc = BccKind::Set1;
    st.frame.bcc_code = BccCode::Binary;
    st.reply_timeout = Duration::ZERO;
    st.fixed_length = Some(4);
    let e = Master::new(st).unwrap_err();
    assert_eq!(e.problems.len(), 3, "{e}");
    assert!(e.to_string().contains("F1"), "{e}");
    let mut st = settings(OperationMode::Four);
    st.fixed_length = Some(217);
    assert!(Master::new(st).is_err());
    assert_eq!(
        OperationMode::try_from(6).unwrap_err(),
        "mode 6: the MODE dial takes 1 to 5 (FFU120B §4-2)"
    );
}

#[test]
fn multi_drop_replies_carry_the_mode_msb_and_only_the_addressed_station_answers() {
    let mut r = pair(
        settings(OperationMode::Two),
        plc(OperationMode::Two, &[7, 12]),
    );
    r.command_b(MicrexCommand::SetWords {
        station: 12,
        module: Module::D,
        address: 0,
        words: vec![0x0C0C],
    });
    r.command_a(read(1, 7, Module::D, 0, 1));
    r.command_a(read(2, 12, Module::D, 0, 1));
    r.settle(Duration::from_secs(2));
    let d = done(&r.take_a_events());
    assert_eq!(words_of(&d[0].1), vec![0]);
    assert_eq!(words_of(&d[1].1), vec![0x0C0C]);
    // RSNO 12 travels as BCD 12h; the replies' MODE is 80h.
    let sent = String::from_utf8(r.a_sent.clone()).unwrap();
    assert!(sent.contains(":001200050400000200\r"), "{sent}");
    let back = String::from_utf8(r.b_sent.clone()).unwrap();
    assert!(back.contains(":00008005070000020001"), "{back}");
}

#[test]
fn late_reply_after_a_time_out_is_counted_not_taken() {
    let mut st = settings(OperationMode::One);
    st.down_after = 10;
    let mut s = Solo::new(st);
    s.cmd(read(1, 0, Module::D, 0, 1));
    s.cmd(read(2, 0, Module::M, 0, 1));
    let d = s.m.poll_timeout().unwrap();
    s.advance_to(d);
    s.advance_to(s.m.poll_timeout().unwrap());
    s.advance_to(s.m.poll_timeout().unwrap());
    assert!(matches!(
        done(&s.take_events())[0].1,
        Err(MasterError::TimeOut { .. })
    ));
    // Request 2 is on the line; request 1's reply comes late.
    s.input(&FrameSettings::default().encode(&[0, 0, 0, 5, 7, 0, 0, 2, 0, 1, 0, 1]));
    assert!(done(&s.events).is_empty());
    assert_eq!(s.m.counters().unexpected_texts, 1);
    s.input(&FrameSettings::default().encode(&[0, 0, 0, 1, 7, 0, 0, 2, 0, 1, 0, 2]));
    assert_eq!(words_of(&done(&s.take_events())[0].1), vec![2]);
}

#[test]
fn receive_errors_are_counted_by_kind() {
    let mut s = Solo::new(settings(OperationMode::One));
    s.input(b"junk:0000\rGG:00\r");
    s.input(&[b':'; 600]);
    s.input(&[b'0'; 600]);
    s.input(b"\r:0000000102AB\r");
    let c = s.m.counters().receive_errors;
    // "junk" and "GG": two runs without a start code; repeated start codes are no error.
    assert_eq!(c.start_code, 2);
    assert!(c.text_form >= 2, "{c:?}");
    assert!(c.too_long >= 1 || c.buffer_full >= 1, "{c:?}");
    // Nothing was waiting, so nothing was retried or sent.
    assert!(s.take_sent().is_empty());
    let json = serde_json::to_string(&s.m.counters()).unwrap();
    assert!(json.contains("\"text_form\""), "{json}");
}

#[test]
fn counters_serialise_with_the_last_error_as_text() {
    let mut s = Solo::new(settings(OperationMode::One));
    s.cmd(read(1, 0, Module::D, 0, 1));
    s.input(&FrameSettings::default().encode(&[0, 0x32, 0, 5, 0]));
    let json = serde_json::to_value(s.m.counters()).unwrap();
    let st = &json["stations"]["0"];
    assert_eq!(st["error_replies"]["50"], 1, "{json}");
    assert!(
        st["last_error"].as_str().unwrap().contains("STA 32"),
        "{json}"
    );
}

#[test]
fn every_bcc_kind_and_code_works_against_the_simulated_plc() {
    let mut checked = 0;
    for frame in crate::fuji::frame::tests::every_valid_setting() {
        // Every BCC option with the usual codes, and every start/end code with one BCC.
        let usual = frame.start_code == crate::fuji::frame::StartCode::Colon
            && frame.end_code == crate::fuji::frame::EndCode::Cr;
        let one_bcc = frame.bcc == BccKind::Set2
            && frame.bcc_range == BccRange::TextEnd
            && frame.bcc_calc == BccCalc::Crc16;
        if !(usual || one_bcc) {
            continue;
        }
        let mut m = settings(OperationMode::One);
        m.frame = frame.clone();
        let mut p = plc(OperationMode::One, &[0]);
        p.frame = frame.clone();
        let mut r = pair(m, p);
        r.command_a(request(
            1,
            0,
            Request::write_words(Module::D, 0, &[0x0D0A, 0x3A03]).unwrap(),
        ));
        r.command_a(read(2, 0, Module::D, 0, 2));
        r.settle(Duration::from_secs(2));
        let d = done(&r.take_a_events());
        assert_eq!(d.len(), 2, "{frame:?}");
        assert!(d[0].1.is_ok(), "{frame:?}: {:?}", d[0].1);
        assert_eq!(words_of(&d[1].1), vec![0x0D0A, 0x3A03], "{frame:?}");
        assert_eq!(r.a.counters().receive_errors.total(), 0, "{frame:?}");
        checked += 1;
    }
    assert!(checked > 100, "{checked}");
}

#[test]
fn line_errors_are_counted() {
    let mut s = Solo::new(settings(OperationMode::One));
    s.m.handle_line_error(s.now, LineError::Parity);
    s.m.handle_line_error(s.now, LineError::Framing);
    s.m.handle_line_error(s.now, LineError::Overrun);
    let c = s.m.counters().line_errors;
    assert_eq!((c.parity, c.framing, c.overrun), (1, 1, 1));
}

proptest! {
    #[test]
    fn arbitrary_input_never_panics_and_every_request_ends_once(
        chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..300), 0..10),
        mode in 1u8..=5,
        binary in any::<bool>(),
    ) {
        let mode = OperationMode::from_dial(mode).unwrap();
        let mut st = settings(mode);
        st.frame.transposition = !binary;
        let mut s = Solo::new(st);
        let command_set = mode.is_command_set();
        for id in 0..3 {
            if command_set {
                s.cmd(read(id, 0, Module::D, 0, 1));
            } else {
                s.cmd(MasterCommand::Send { id, data: vec![1, 2] });
            }
        }
        for c in &chunks {
            s.input(c);
            if let Some(t) = s.m.poll_timeout() {
                s.advance_to(t);
            }
        }
        for _ in 0..20 {
            match s.m.poll_timeout() {
                Some(t) => s.advance_to(t),
                None => break,
            }
        }
        let d = done(&s.events);
        let mut ids: Vec<_> = d.iter().map(|(id, _)| *id).collect();
        ids.sort_unstable();
        prop_assert_eq!(ids, vec![0, 1, 2]);
        prop_assert_eq!(s.m.poll_timeout(), None);
    }
}

#[test]
fn an_echo_of_the_request_on_a_two_wire_line_is_not_a_reply() {
    let mut s = Solo::new(settings(OperationMode::Three));
    s.cmd(read(1, 12, Module::D, 0, 1));
    let sent = s.take_sent();
    // Its own request, heard back: RSNO 12h would read as STA 12 if taken for a reply.
    s.input(&sent[0]);
    assert!(done(&s.events).is_empty());
    assert_eq!(s.m.counters().unexpected_texts, 1);
    s.input(&FrameSettings::default().encode(&[0, 0, 0x80, 5, 7, 0, 0, 2, 0, 1, 0, 9]));
    assert_eq!(words_of(&done(&s.take_events())[0].1), vec![9]);
}

#[test]
fn a_plc_transfer_on_the_line_pushes_the_reply_deadline_back() {
    let mut s = Solo::new(settings(OperationMode::One));
    s.cmd(read(1, 0, Module::D, 0, 1));
    let before = s.m.poll_timeout().unwrap();
    let transfer = FrameSettings::default().encode(&[0x90, 0, 0, 1, 4, 1, 2, 3, 4]);
    s.input(&transfer);
    assert_eq!(
        s.m.poll_timeout(),
        Some(before + line().time_for_chars(transfer.len() as u64))
    );
}

#[test]
fn time_settings_are_bounded() {
    let mut st = settings(OperationMode::One);
    st.probe_interval = Duration::from_secs(365 * 24 * 3600);
    let e = Master::new(st).unwrap_err();
    assert!(matches!(
        e.problems[..],
        [MasterProblem::TooLong {
            name: "probe_interval",
            ..
        }]
    ));
}

#[test]
fn a_line_that_goes_down_marks_its_stations_down_until_they_answer_again() {
    let mut s = Solo::new(settings(OperationMode::One));
    s.cmd(read(1, 0, Module::M, 0, 1));
    s.input(b":0000000107000002000112AB\r");
    s.take_events();
    s.take_sent();
    // The device server goes away: DR, CS and CD off.
    let down = ModemIn {
        dr: false,
        cs: false,
        cd: false,
    };
    s.m.handle_modem(s.now, down);
    s.pump();
    assert_eq!(
        s.take_events(),
        vec![MasterEvent::StationDown {
            station: 0,
            timeouts: 0
        }]
    );
    assert!(s.m.is_down(0));
    // Back: the next request goes out as a probe, its reply marks the station up.
    s.m.handle_modem(s.now, ModemIn::ALL_ON);
    s.cmd(read(2, 0, Module::M, 0, 1));
    assert_eq!(s.take_sent(), vec![b":000000010400000200\r".to_vec()]);
    s.input(b":0000000107000002000112AB\r");
    let ev = s.take_events();
    assert!(
        ev.contains(&MasterEvent::StationUp { station: 0 }),
        "{ev:?}"
    );
    assert!(!s.m.is_down(0));
}

#[test]
fn a_station_first_asked_over_a_line_that_is_down_starts_down() {
    let mut s = Solo::new(settings(OperationMode::One));
    s.m.handle_modem(
        s.now,
        ModemIn {
            dr: false,
            cs: false,
            cd: false,
        },
    );
    s.cmd(read(1, 0, Module::M, 0, 1));
    assert!(s.m.is_down(0));
    assert!(s.take_events().contains(&MasterEvent::StationDown {
        station: 0,
        timeouts: 0
    }));
}

mod messages;
