use super::*;
use cellgate_core::fanuc::g05::{
    AuxFunction, AuxWord, DataFormat, G05Encoder, G05Format, UnitTime,
};
use cellgate_core::sim::{BoardConfigError, G05End, G05Stats};

/// `n` blocks of `f`: travels (k, -k, 2k, ...) for block k = 1..=n, an M code on every
/// tenth block when the format has an auxiliary word; and the per-axis sums.
fn blocks(f: G05Format, n: i32) -> (Vec<u8>, Vec<i64>, Vec<u32>) {
    let mut e = G05Encoder::new(f).unwrap();
    let mut out = Vec::new();
    let mut sums = vec![0i64; usize::from(f.axes)];
    let mut aux = Vec::new();
    for k in 1..=n {
        let travels: Vec<i32> = (0..i32::from(f.axes))
            .map(|a| if a % 2 == 0 { k * (a + 1) } else { -k })
            .collect();
        for (s, t) in sums.iter_mut().zip(&travels) {
            *s += i64::from(*t);
        }
        let m = (f.aux.rax() && k % 10 == 0).then(|| {
            aux.push(k as u32);
            AuxWord::significant(k as u32)
        });
        e.block(&travels, m, &mut out).unwrap();
    }
    (out, sums, aux)
}

fn end(f: G05Format) -> Vec<u8> {
    let mut out = Vec::new();
    f.encode_end(&mut out);
    out
}

fn ended(events: &[(Duration, BoardEvent)]) -> Vec<(Duration, G05End, G05Stats)> {
    events
        .iter()
        .filter_map(|(t, e)| match e {
            BoardEvent::G05Ended { end, stats } => Some((*t, *end, stats.clone())),
            _ => None,
        })
        .collect()
}

fn started(events: &[(Duration, BoardEvent)]) -> Vec<(Duration, u8, u32)> {
    events
        .iter()
        .filter_map(|(t, e)| match e {
            BoardEvent::G05Started { axes, unit_ms } => Some((*t, *axes, *unit_ms)),
            _ => None,
        })
        .collect()
}

fn m_format() -> G05Format {
    G05Format {
        aux: AuxFunction::M,
        ..G05Format::new(3)
    }
}

#[test]
fn protocol_a_binary_blocks_in_dat_are_taken_one_per_unit_time() {
    let f = m_format();
    let mut rig = Rig::quick(|c| {
        c.consume_rate = 1000;
        c.g05 = Some(f);
    });
    rig.init();
    rig.command(BoardCommand::StartReading);
    let (data, sums, aux) = blocks(f, 100);
    // Special format: no CR, so the blocks can travel in a DAT (§9.1 NOTE).
    assert!(!data.contains(&0x0D));
    let mut tape = b"%\nO5\nG05\n".to_vec();
    tape.extend(&data);
    tape.extend(end(f));
    tape.extend_from_slice(b"G01X0\nM30\n%");
    rig.expect(Command::Gtd, s(1));
    let sent_at = rig.at();
    rig.send(Message::with_data(Command::Dat, tape.clone()));
    rig.idle_host(s(3));
    let st = started(&rig.events);
    // The 9 text bytes at 1000 B/s.
    assert_eq!(st, [(sent_at + ms(9), 3, 8)]);
    let en = ended(&rig.events);
    assert_eq!(en.len(), 1, "{en:?}");
    let (at, end, stats) = &en[0];
    assert_eq!(*end, G05End::EndBlock);
    // 100 blocks and the end block, one each 8 ms from G05 on.
    assert_eq!(*at, st[0].0 + ms(8 * 101));
    assert_eq!(stats.blocks, 100);
    assert_eq!(stats.travel, sums);
    assert_eq!(stats.aux, aux);
    assert_eq!(stats.underruns, 0);
    assert_eq!(stats.sessions, 1);
    // The text after the end block is NC text again: the program ends at its EOR.
    let programs = rig.programs();
    assert_eq!(programs.len(), 1);
    assert_eq!(programs[0].len, tape.len() as u64);
    assert_eq!(programs[0].sha256, sha(&tape));
    assert!(rig.alarms().is_empty());
    assert_eq!(rig.board.cnc().g05_stats(), Some(stats));
    let position = |f: fn(&BoardEvent) -> bool| rig.events.iter().position(|(_, e)| f(e));
    assert!(
        position(|e| matches!(e, BoardEvent::G05Ended { .. }))
            < position(|e| matches!(e, BoardEvent::ProgramReceived(_))),
        "the session ends before the program"
    );
}

#[test]
fn protocol_a_wrong_check_byte_raises_sr0890_and_alm() {
    let f = m_format();
    let mut rig = Rig::quick(|c| {
        c.consume_rate = 0;
        c.g05 = Some(f);
    });
    rig.init();
    rig.command(BoardCommand::StartReading);
    let (mut data, _, _) = blocks(f, 5);
    // Block 3's check byte.
    data[3 * f.block_len() - 1] ^= 0x10;
    let mut tape = b"G05\n".to_vec();
    tape.extend(&data);
    rig.expect(Command::Gtd, s(1));
    rig.send(Message::with_data(Command::Dat, tape));
    loop {
        let (_, m) = rig.next_msg(s(2));
        match m.command {
            Command::Gtd => rig.send_cmd(Command::Eod),
            Command::Alm => break,
            other => panic!("expected ALM, got {other}"),
        }
    }
    rig.send_cmd(Command::Aal);
    assert_eq!(rig.alarms(), [CncAlarm::Sr0890G05CheckSum]);
    assert!(rig.has_event(|e| matches!(e, BoardEvent::CncAlarm)));
    let en = ended(&rig.events);
    assert_eq!(en.len(), 1);
    assert_eq!((en[0].1, en[0].2.blocks), (G05End::CheckSum, 2));
    let detail = rig
        .events
        .iter()
        .find_map(|(_, e)| match e {
            BoardEvent::Alarm { detail, .. } => Some(detail.clone()),
            _ => None,
        })
        .unwrap();
    assert!(detail.contains("G05 block 3"), "{detail}");
    let d = rig.sat(s(10));
    assert_eq!(d.status, Some(BufferStatus::Alarm));
    assert!(!rig.board.cnc().in_binary());
}

#[test]
fn general_format_is_refused_for_protocol_a() {
    for protocol in [Protocol::A, Protocol::ExpansionA] {
        let config = BoardConfig {
            protocol,
            g05: Some(G05Format {
                data_format: DataFormat::General,
                ..G05Format::new(2)
            }),
            ..BoardConfig::default()
        };
        let err = FanucBoard::new(config, Instant::now()).unwrap_err();
        assert!(matches!(err, BoardConfigError::G05(_)), "{err}");
        assert!(err.to_string().contains("§9.1 NOTE"), "{err}");
    }
    let config = BoardConfig {
        protocol: Protocol::B,
        g05: Some(G05Format::new(0)),
        ..BoardConfig::default()
    };
    assert!(FanucBoard::new(config, Instant::now()).is_err());
}

/// A Protocol B board in virtual time: raw bytes in, everything out collected.
struct BRig {
    board: FanucBoard,
    t0: Instant,
    now: Instant,
    sent: Vec<u8>,
    events: Vec<(Duration, BoardEvent)>,
}

impl BRig {
    fn new(f: G05Format, notify: bool) -> Self {
        let t0 = Instant::now();
        let config = BoardConfig {
            protocol: Protocol::B,
            consume_rate: 0,
            notify_alarm_reset: notify,
            g05: Some(f),
            ..BoardConfig::default()
        };
        let mut r = BRig {
            board: FanucBoard::new(config, t0).unwrap(),
            t0,
            now: t0,
            sent: Vec::new(),
            events: Vec::new(),
        };
        r.board.handle_modem(t0, ModemIn::ALL_ON);
        r.board.handle_command(t0, BoardCommand::StartReading);
        r.pump();
        r
    }

    fn pump(&mut self) {
        while let Some(b) = self.board.poll_transmit(self.now) {
            self.sent.extend(b);
        }
        while let Some(e) = self.board.poll_event() {
            self.events.push((self.now - self.t0, e));
        }
    }

    /// Runs every deadline up to `t0 + at`.
    fn run_until(&mut self, at: Duration) {
        let target = self.t0 + at;
        for _ in 0..1_000_000 {
            match self.board.poll_timeout() {
                Some(t) if t <= target => {
                    self.now = self.now.max(t);
                    self.board.handle_timeout(self.now);
                    self.pump();
                }
                _ => {
                    self.now = target;
                    self.board.handle_timeout(self.now);
                    self.pump();
                    return;
                }
            }
        }
        panic!("the board keeps asking to be woken");
    }

    fn input(&mut self, at: Duration, bytes: &[u8]) {
        self.run_until(at);
        self.board.handle_input(self.now, bytes);
        self.pump();
    }

    fn underruns(&self) -> Vec<(Duration, u64, u64)> {
        self.events
            .iter()
            .filter_map(|(t, e)| match e {
                BoardEvent::G05Underruns { new, total } => Some((*t, *new, *total)),
                _ => None,
            })
            .collect()
    }
}

#[test]
fn protocol_b_underruns_are_counted_and_reported_at_most_once_a_second() {
    let f = G05Format {
        unit_time_ms: UnitTime::Ms1,
        ..G05Format::new(1)
    };
    let mut r = BRig::new(f, true);
    let (data, sums, _) = blocks(f, 100);
    let mut first = b"G05\n".to_vec();
    first.extend(&data);
    // At 0.5 ms: G05 read at once (rate 0), slots at 1.5, 2.5, ... ms.
    r.input(Duration::from_micros(500), &first);
    assert_eq!(started(&r.events).len(), 1);
    // Nothing more until 3.5 s: slots 101..=3500 find no block.
    r.input(Duration::from_micros(3_500_700), &end(f));
    r.run_until(s(4));
    let u = r.underruns();
    // The first at once (slot 101 at 101.5 ms), then one a second.
    assert_eq!(
        u,
        [
            (Duration::from_micros(101_500), 1, 1),
            (Duration::from_micros(1_101_500), 1000, 1001),
            (Duration::from_micros(2_101_500), 1000, 2001),
            (Duration::from_micros(3_101_500), 1000, 3001),
        ]
    );
    let en = ended(&r.events);
    assert_eq!(en.len(), 1, "{en:?}");
    let (at, end, stats) = &en[0];
    assert_eq!(*at, Duration::from_micros(3_501_500));
    assert_eq!(*end, G05End::EndBlock);
    assert_eq!(stats.blocks, 100);
    assert_eq!(stats.underruns, 3400);
    assert_eq!(stats.travel, sums);
    assert_eq!(stats.min_buffered_blocks, Some(0));
    assert!(r.board.cnc().reading(), "reading NC text again");
}

#[test]
fn protocol_b_sr0890_is_posted_as_nak() {
    let f = G05Format {
        data_format: DataFormat::General,
        aux: AuxFunction::S,
        ..G05Format::new(2)
    };
    let mut r = BRig::new(f, true);
    let (mut data, _, _) = blocks(f, 3);
    data[f.block_len() - 1] = data[f.block_len() - 1].wrapping_add(1);
    let mut tape = b"%\nG05\n".to_vec();
    tape.extend(&data);
    r.input(ms(1), &tape);
    r.sent.clear();
    r.run_until(ms(20));
    let alarms: Vec<CncAlarm> = r
        .events
        .iter()
        .filter_map(|(_, e)| match e {
            BoardEvent::Alarm { alarm, .. } => Some(*alarm),
            _ => None,
        })
        .collect();
    assert_eq!(alarms, [CncAlarm::Sr0890G05CheckSum]);
    // Posted as a CNC alarm (§6.1.2): NAK, after a DC3 ending the read.
    assert!(
        r.sent.contains(&0x15) || r.sent.contains(&0x95),
        "{:?}",
        r.sent
    );
    let en = ended(&r.events);
    assert_eq!((en[0].1, en[0].2.blocks), (G05End::CheckSum, 0));
    // At the first slot, 8 ms after G05.
    assert_eq!(en[0].0, ms(9));
    assert_eq!(r.board.cnc().alarm(), Some(AlarmCause::NcAlarm));
}

mod live {
    use super::*;
    use cellgate::sim::BoardHandle;
    use cellgate::sim::server::PacedLine;
    use tokio::io::AsyncWriteExt;

    /// The board's engine runs on tokio's paused clock: the host writes one block a unit
    /// time, half a unit ahead, misses three, then ends.
    #[tokio::test(start_paused = true)]
    async fn board_handle_takes_blocks_in_paused_time() {
        let f = G05Format {
            aux: AuxFunction::Second,
            ..G05Format::new(2)
        };
        let (mut host, line) = tokio::io::duplex(64 * 1024);
        let config = BoardConfig {
            protocol: Protocol::B,
            consume_rate: 0,
            g05: Some(f),
            ..BoardConfig::default()
        };
        let handle = BoardHandle::spawn(config, PacedLine::unpaced(line, "pipe")).unwrap();
        let mut events = handle.subscribe();
        handle.start_reading();
        handle.wait_for(|s| s.reading).await;
        let (data, sums, aux) = blocks(f, 50);
        host.write_all(b"%\nG05\n").await.unwrap();
        handle
            .wait_for(|s| s.g05.as_ref().is_some_and(|g| g.active))
            .await;
        for (k, block) in data.chunks(f.block_len()).enumerate() {
            let wait = if k == 0 { 4 } else { 8 };
            tokio::time::sleep(ms(wait)).await;
            host.write_all(block).await.unwrap();
        }
        // Slots 51, 52 and 53 find nothing; the end block makes slot 54.
        tokio::time::sleep(ms(32)).await;
        host.write_all(&end(f)).await.unwrap();
        host.write_all(b"M30\n%").await.unwrap();
        let snap = handle.wait_for(|s| !s.programs.is_empty()).await;
        let g = snap.g05.unwrap();
        assert!(!g.active);
        assert_eq!(g.end, Some(G05End::EndBlock));
        assert_eq!(g.blocks, 50);
        assert_eq!(g.underruns, 3);
        assert_eq!(g.travel, sums);
        assert_eq!(g.aux, aux);
        assert_eq!(g.min_buffered_blocks, Some(0));
        let mut seen = Vec::new();
        while let Ok(e) = events.try_recv() {
            match e {
                BoardEvent::G05Started { .. } => seen.push("started".to_string()),
                BoardEvent::G05Underruns { new, total } => {
                    seen.push(format!("underruns {new}/{total}"))
                }
                BoardEvent::G05Ended { end, .. } => seen.push(format!("ended {end:?}")),
                _ => {}
            }
        }
        assert_eq!(seen, ["started", "underruns 1/1", "ended EndBlock"]);
        handle.shutdown().await.unwrap();
    }
}
