//! The gateway's Protocol B / Expansion B host engine against the simulated remote-buffer
//! board: over the simulated line and over TCP through a device-server double, in virtual
//! time. Downloads with hundreds of DC3 / DC1 cycles, CNC alarms mid-transfer with
//! notification on and off, and punch-out round trips.

use crate::common;

use std::time::Duration;

use cellgate::link::driver::{self, JobSource, LinkCommand, LinkEvent, LinkHandle, ProgramJob};
use cellgate::link::pump::{Pump, PumpError, now};
use cellgate::sim::{BoardHandle, BoardSnapshot};
use cellgate::transport::sim::{self, SimPort};
use cellgate::transport::tcp::{TcpOptions, TcpTransport};
use cellgate::transport::{LineSettings, Transport};
use cellgate_core::engine::Engine;
use cellgate_core::fanuc::alarm::CncAlarm;
use cellgate_core::fanuc::host::{Confirmation, EngineEvent};
use cellgate_core::fanuc::message::Framing;
use cellgate_core::fanuc::protocol_b::{ProtocolBConfig, ProtocolBHost};
use cellgate_core::fanuc::{CodeSystem, EndCode, Protocol};
use cellgate_core::sim::fanuc_board::protocol_b::overrun_allowance;
use cellgate_core::sim::{BoardConfig, BoardEvent, ControlCode};
use common::{nc_program, next_event};
use sha2::{Digest, Sha256};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

const HOUR: Duration = Duration::from_secs(3600);

/// Characters per second at `baud` with 11 bit times a character (protocol notes 2).
fn chars_per_sec(baud: u32) -> u32 {
    baud / 11
}

fn board_config(expansion: bool, code: CodeSystem, notify: bool, consume_rate: u32) -> BoardConfig {
    BoardConfig {
        protocol: if expansion {
            Protocol::ExpansionB
        } else {
            Protocol::B
        },
        framing: Framing::new(code, EndCode::Cr),
        autostart: true,
        consume_rate,
        notify_alarm_reset: notify,
        ..BoardConfig::default()
    }
}

fn host(expansion: bool, code: CodeSystem, notify: bool) -> ProtocolBHost {
    ProtocolBHost::new(ProtocolBConfig::new(code, expansion, notify), now()).unwrap()
}

/// The host link and the board, however they are connected.
struct Rig {
    board: BoardHandle,
    link: LinkHandle,
    token: CancellationToken,
    task: JoinHandle<Result<(), std::sync::Arc<PumpError>>>,
}

impl Rig {
    /// Host and board on one simulated cable.
    fn on_sim_line(
        expansion: bool,
        code: CodeSystem,
        notify: bool,
        baud: u32,
        consume_rate: u32,
    ) -> Rig {
        let (host_end, device_end, _line) = sim::line(LineSettings::with_baud(baud));
        let board = BoardHandle::spawn(
            board_config(expansion, code, notify, consume_rate),
            device_end,
        )
        .unwrap();
        Rig::with_transport(board, host(expansion, code, notify), host_end)
    }

    fn with_transport<T: Transport + 'static>(
        board: BoardHandle,
        host: ProtocolBHost,
        transport: T,
    ) -> Rig {
        let token = CancellationToken::new();
        let (link, task) = driver::spawn("m1", host, transport, token.clone());
        Rig {
            board,
            link,
            token,
            task,
        }
    }

    async fn queue(&self, id: u64, program: &[u8]) {
        self.link
            .send(LinkCommand::Queue(ProgramJob {
                id,
                name: format!("job-{id}"),
                size: Some(program.len() as u64),
                source: JobSource::program(std::io::Cursor::new(program.to_vec())),
                progress_interval: None,
            }))
            .await
            .unwrap();
    }

    /// Sends `program` as job `id` and waits until the CNC has read all of it.
    async fn deliver(
        &self,
        events: &mut cellgate::link::fanout::Receiver<LinkEvent>,
        id: u64,
        program: &[u8],
        programs_before: usize,
    ) -> BoardSnapshot {
        self.queue(id, program).await;
        let bytes = next_event(events, 4 * HOUR, |ev| match ev {
            LinkEvent::JobDone { job, bytes, .. } if *job == id => Some(*bytes),
            LinkEvent::JobFailed { job, reason, .. } if *job == id => {
                panic!("job {id} failed: {reason}")
            }
            _ => None,
        })
        .await;
        assert_eq!(bytes, program.len() as u64);
        let snap = tokio::time::timeout(
            HOUR,
            self.board.wait_for(|s| s.programs.len() > programs_before),
        )
        .await
        .expect("the CNC reads the whole program");
        let got = snap
            .programs
            .get(programs_before)
            .expect("the board stopped before the program was read");
        assert_eq!(got.len, program.len() as u64);
        assert!(
            got.sha256 == <[u8; 32]>::from(Sha256::digest(program)),
            "the CNC read other bytes than the program"
        );
        snap
    }

    async fn stop(self) {
        self.token.cancel();
        let _ = self.task.await.unwrap();
        self.board.shutdown().await.unwrap();
    }
}

/// Checks the flow control of a download that needed at least `min_cycles` DC3 / DC1 cycles.
fn assert_flow(snap: &BoardSnapshot, expansion: bool, min_cycles: u64) {
    println!(
        "DC1 {} DC3 {}, at most {} characters after one DC3",
        snap.dc1_sent, snap.dc3_sent, snap.max_overrun
    );
    assert!(snap.alarms.is_empty(), "alarms: {:?}", snap.alarms);
    assert_eq!(snap.overruns, 0);
    assert!(
        snap.dc1_sent >= min_cycles && snap.dc3_sent >= min_cycles,
        "only {} DC1 and {} DC3",
        snap.dc1_sent,
        snap.dc3_sent
    );
    // The host stays within its own allowance (§6.3; 1280 in Expansion B, protocol notes 12).
    let host_allowance = if expansion { 1280 } else { 512 };
    assert!(
        snap.max_overrun < host_allowance && snap.max_overrun <= overrun_allowance(expansion),
        "{} characters after a DC3",
        snap.max_overrun
    );
}

/// A 1 MiB program over the simulated line, with the CNC reading at a quarter of the line's
/// rate so that the board stops and resumes the host over and over: each cycle moves about
/// 4/3 of the 3584 (Expansion B: 1536) characters between the DC3 and DC1 levels (§6.3).
async fn one_mib_on_sim_line(expansion: bool, code: CodeSystem, baud: u32) {
    let rig = Rig::on_sim_line(expansion, code, true, baud, chars_per_sec(baud) / 4);
    let mut events = rig.link.subscribe();
    let program = nc_program(1 << 20, 11);
    let snap = rig.deliver(&mut events, 1, &program, 0).await;
    assert_eq!(snap.programs[0].first_line, "O0011");
    assert_flow(&snap, expansion, 200);
    rig.stop().await;
}

#[tokio::test(start_paused = true)]
async fn one_mib_protocol_b_19200_with_hundreds_of_dc3_dc1_cycles() {
    one_mib_on_sim_line(false, CodeSystem::Iso, 19_200).await;
}

#[tokio::test(start_paused = true)]
async fn one_mib_expansion_b_86400_with_hundreds_of_dc3_dc1_cycles() {
    one_mib_on_sim_line(true, CodeSystem::Ascii, 86_400).await;
}

/// An NC program of exactly `len` bytes: `%`, an O number, G01 blocks, `M30`, `%`.
fn program_of_len(len: usize, seed: u32) -> Vec<u8> {
    let mut p = format!("%\nO{:04}\n", seed % 10_000).into_bytes();
    let tail = b"M30\n%";
    let body = len - p.len() - tail.len();
    p.extend(b"G01X1.Y2.\n".iter().cycle().take(body));
    p.extend_from_slice(tail);
    p
}

/// Programs queued back to back: each goes on its own read request (protocol notes 13) and
/// none loses bytes behind another's EOR (§8.2). At 19 200 baud with the CNC reading at half
/// the line's rate, the board's first DC3 of a read goes out when about 15 340 bytes have
/// arrived and the host's overrun is about 80 bytes: the first programs end inside that
/// overrun, so their EOR reaches the board after its DC3, and a flow-control DC1 then would
/// bring the next program in behind the EOR.
#[tokio::test(start_paused = true)]
async fn back_to_back_programs_each_on_its_own_read_request() {
    let baud = 19_200;
    let rig = Rig::on_sim_line(false, CodeSystem::Iso, true, baud, chars_per_sec(baud) / 2);
    let mut events = rig.link.subscribe();
    let programs: Vec<Vec<u8>> = [15_360, 15_380, 15_400, 15_420, 9000]
        .iter()
        .zip(20..)
        .map(|(&len, seed)| program_of_len(len, seed))
        .collect();
    for (i, p) in programs.iter().enumerate() {
        rig.queue(i as u64 + 1, p).await;
    }
    for i in 0..programs.len() as u64 {
        next_event(&mut events, HOUR, |ev| match ev {
            LinkEvent::JobDone { job, .. } if *job == i + 1 => Some(()),
            LinkEvent::JobFailed { job, reason, .. } => panic!("job {job} failed: {reason}"),
            _ => None,
        })
        .await;
    }
    let snap = tokio::time::timeout(
        HOUR,
        rig.board.wait_for(|s| s.programs.len() >= programs.len()),
    )
    .await
    .expect("the CNC reads every program");
    for (got, sent) in snap.programs.iter().zip(&programs) {
        assert!(
            got.sha256 == <[u8; 32]>::from(Sha256::digest(sent)),
            "program {} arrived altered",
            got.first_line
        );
    }
    assert_flow(&snap, false, 5);
    rig.stop().await;
}

/// A serial device server double: relays between one TCP connection and the host end of a
/// simulated cable, holding at most 1 KiB in each direction, as a real one buffers per port.
async fn device_server(listener: TcpListener, serial: SimPort) {
    let (stream, _) = listener.accept().await.unwrap();
    stream.set_nodelay(true).unwrap();
    let (mut net_rd, mut net_wr) = stream.into_split();
    let (mut ser_rd, mut ser_wr) = tokio::io::split(serial);
    let to_serial = async {
        let mut buf = [0u8; 1024];
        loop {
            match net_rd.read(&mut buf).await {
                Ok(0) | Err(_) => break,
                Ok(n) => {
                    if ser_wr.write_all(&buf[..n]).await.is_err() {
                        break;
                    }
                }
            }
        }
    };
    let to_net = async {
        let mut buf = [0u8; 1024];
        loop {
            match ser_rd.read(&mut buf).await {
                Ok(0) | Err(_) => break,
                Ok(n) => {
                    if net_wr.write_all(&buf[..n]).await.is_err() {
                        break;
                    }
                }
            }
        }
    };
    tokio::join!(to_serial, to_net);
}

/// The same download over the TCP transport to a device server with the board on its
/// serial side. Paused time works with loopback sockets: a write lands in the peer's socket
/// before the writer yields, so the runtime sees it ready before it advances the clock.
async fn over_tcp(expansion: bool, baud: u32, program_len: usize, min_cycles: u64) {
    let line = LineSettings::with_baud(baud);
    let (serial_host_end, device_end, _cable) = sim::line(line);
    let code = CodeSystem::Iso;
    let board = BoardHandle::spawn(
        board_config(expansion, code, true, chars_per_sec(baud) / 4),
        device_end,
    )
    .unwrap();
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let server = tokio::spawn(device_server(listener, serial_host_end));
    // What can still reach the board after its DC3: the host's piece in the driver (64), the
    // transport's window of characters not yet on the serial side (wherever they sit: socket
    // buffers or the device server's 1 KiB; the window bounds them all, since the device
    // server drains at line rate), and the few characters on the wire while the DC3 travels.
    // Protocol B: 64 + 256 + ~20 < 512. Expansion B: 64 + 1024 + ~20 < 1280.
    let window = if expansion { 1024 } else { 256 };
    let transport = TcpTransport::connect(
        addr,
        line,
        TcpOptions {
            window,
            ..TcpOptions::default()
        },
    )
    .await
    .unwrap();
    let rig = Rig::with_transport(board, host(expansion, code, true), transport);
    let mut events = rig.link.subscribe();
    let program = nc_program(program_len, 5);
    let snap = rig.deliver(&mut events, 1, &program, 0).await;
    assert_flow(&snap, expansion, min_cycles);
    rig.stop().await;
    server.abort();
}

#[tokio::test(start_paused = true)]
async fn one_mib_protocol_b_over_tcp_through_a_device_server() {
    over_tcp(false, 19_200, 1 << 20, 200).await;
}

#[tokio::test(start_paused = true)]
async fn one_mib_expansion_b_over_tcp_through_a_device_server() {
    over_tcp(true, 86_400, 1 << 20, 200).await;
}

/// Three 6 KB programs back to back to a Protocol B board behind a TCP device server at
/// 19 200 baud. For each k, the gateway and the device server are stopped the moment job k is
/// reported completed, and whatever was still in the device server, the sockets or the
/// transport's window is lost: program k (and every one before it) must be whole on the board
/// all the same. Completed is published only once the board holds the program.
#[tokio::test(start_paused = true)]
async fn completed_means_the_board_has_it_even_if_everything_stops_at_that_moment() {
    let baud = 19_200;
    let line = LineSettings::with_baud(baud);
    let code = CodeSystem::Iso;
    let programs: Vec<Vec<u8>> = (0..3).map(|i| program_of_len(6 * 1024, 40 + i)).collect();
    for k in 1..=programs.len() {
        let (serial_host_end, device_end, _cable) = sim::line(line);
        let board = BoardHandle::spawn(
            board_config(false, code, true, chars_per_sec(baud) / 2),
            device_end,
        )
        .unwrap();
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        let server = tokio::spawn(device_server(listener, serial_host_end));
        let transport = TcpTransport::connect(addr, line, TcpOptions::default())
            .await
            .unwrap();
        let rig = Rig::with_transport(board, host(false, code, true), transport);
        let mut events = rig.link.subscribe();
        for (i, p) in programs.iter().enumerate() {
            rig.queue(i as u64 + 1, p).await;
        }
        let k_id = k as u64;
        next_event(&mut events, HOUR, |ev| match ev {
            LinkEvent::JobDone {
                job, confirmation, ..
            } if *job == k_id => {
                assert_eq!(*confirmation, Confirmation::EndOfRead);
                Some(())
            }
            LinkEvent::JobFailed { job, reason, .. } => panic!("job {job} failed: {reason}"),
            _ => None,
        })
        .await;
        // Everything stops now: bytes still under way are lost.
        server.abort();
        rig.token.cancel();
        tokio::time::sleep(Duration::from_secs(60)).await;
        let snap = rig.board.snapshot();
        assert!(
            snap.programs.len() >= k,
            "job {k} was reported completed, but the CNC has only {} programs whole",
            snap.programs.len()
        );
        for (got, sent) in snap.programs.iter().zip(&programs).take(k) {
            assert!(
                got.sha256 == <[u8; 32]>::from(Sha256::digest(sent)),
                "program {} arrived altered",
                got.first_line
            );
        }
        let _ = rig.task.await;
        rig.board.shutdown().await.unwrap();
    }
}

/// A CNC alarm in the middle of a transfer fails the job at its byte offset; the CNC resets
/// itself (autostart) and the next job arrives whole.
async fn alarm_mid_transfer(notify: bool) {
    let baud = 19_200;
    let rig = Rig::on_sim_line(
        false,
        CodeSystem::Iso,
        notify,
        baud,
        chars_per_sec(baud) / 2,
    );
    let mut events = rig.link.subscribe();
    let program = nc_program(64 * 1024, 3);
    rig.queue(1, &program).await;
    rig.board.wait_for(|s| s.data_received > 16 * 1024).await;
    rig.board.raise_alarm();
    let mut notice = false;
    let mut dr_off = false;
    let offset = next_event(&mut events, HOUR, |ev| match ev {
        LinkEvent::CncAlarm => {
            notice = true;
            None
        }
        LinkEvent::Alarm(a) if a.cnc_alarm() == Some(CncAlarm::Sr0855DataSetReadyDown) => {
            dr_off = true;
            None
        }
        LinkEvent::JobFailed { job: 1, offset, .. } => Some(*offset),
        LinkEvent::JobDone { .. } => panic!("the job cannot complete"),
        _ => None,
    })
    .await;
    assert!(
        offset > 16 * 1024 && offset < program.len() as u64,
        "offset {offset}"
    );
    if notify {
        // DC3 then NAK (§6.1.2 2 (7)).
        assert!(notice && !dr_off, "notice {notice}, DR off {dr_off}");
    } else {
        // DC3 then ER off (§6.4 (1)): the host sees DR off.
        assert!(dr_off && !notice, "notice {notice}, DR off {dr_off}");
    }
    let snap = rig.board.snapshot();
    assert!(snap.programs.is_empty());
    assert!(
        snap.alarms.is_empty(),
        "a CNC alarm, not an SR alarm of the board"
    );
    let next = nc_program(8 * 1024, 4);
    rig.deliver(&mut events, 2, &next, 0).await;
    rig.stop().await;
}

#[tokio::test(start_paused = true)]
async fn cnc_alarm_mid_transfer_fails_the_job_with_notification_on() {
    alarm_mid_transfer(true).await;
}

#[tokio::test(start_paused = true)]
async fn cnc_alarm_mid_transfer_fails_the_job_with_notification_off() {
    alarm_mid_transfer(false).await;
}

/// The board punches a tape out; the host engine, run by a pump without the link driver,
/// takes its punched pieces only every few seconds, so that it must stop the board with DC3
/// and resume it (DC1 with notification on, DC2 off; protocol notes 11).
async fn punch_round_trip(notify: bool) {
    let baud = 19_200;
    let code = CodeSystem::Iso;
    let (host_end, device_end, _line) = sim::line(LineSettings::with_baud(baud));
    let board = BoardHandle::spawn(board_config(false, code, notify, 0), device_end).unwrap();
    let mut board_events = board.subscribe();
    let cfg = ProtocolBConfig {
        max_buffer: 8192,
        punch_piece: 1024,
        punch_high_water: 8192 - 2 * 512,
        ..ProtocolBConfig::new(code, false, notify)
    };
    let mut pump = Pump::new(ProtocolBHost::new(cfg, now()).unwrap(), host_end);
    let tape: Vec<u8> = nc_program(40 * 1024, 8)
        .into_iter()
        .map(|b| code.encode(b))
        .collect();
    board.punch(tape.clone());
    let mut punched = Vec::new();
    let mut take = tokio::time::interval(Duration::from_secs(6));
    let drive = async {
        loop {
            tokio::select! {
                r = pump.step() => r.unwrap(),
                _ = take.tick() => {
                    while let Some(e) = pump.engine_mut().poll_event() {
                        if let EngineEvent::Punched { data } = e {
                            punched.extend_from_slice(&data);
                        }
                    }
                    if punched.len() >= tape.len() {
                        break;
                    }
                }
            }
        }
    };
    tokio::time::timeout(HOUR, drive)
        .await
        .expect("the punch-out completes");
    assert!(punched == tape, "punched bytes differ from the tape");
    let snap = board.wait_for(|s| s.punched == tape.len() as u64).await;
    assert!(snap.alarms.is_empty());
    let mut stops = 0;
    let mut resumes = 0;
    let mut finished = false;
    while let Ok(e) = board_events.try_recv() {
        match e {
            BoardEvent::ControlReceived(ControlCode::Dc3) => stops += 1,
            BoardEvent::ControlReceived(ControlCode::Dc1) => {
                assert!(notify, "DC2 resumes with notification off");
                resumes += 1;
            }
            BoardEvent::ControlReceived(ControlCode::Dc2) => {
                assert!(!notify, "DC1 resumes with notification on");
                resumes += 1;
            }
            BoardEvent::PunchFinished { bytes } => {
                assert_eq!(bytes, tape.len());
                finished = true;
            }
            _ => {}
        }
    }
    assert!(finished);
    assert!(
        stops >= 2 && resumes >= 2,
        "{stops} stops, {resumes} resumes"
    );
    board.shutdown().await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn punch_out_round_trip_with_host_flow_control_notification_on() {
    punch_round_trip(true).await;
}

#[tokio::test(start_paused = true)]
async fn punch_out_round_trip_with_host_flow_control_notification_off() {
    punch_round_trip(false).await;
}

/// The block being fed moves through a Protocol B job: a CNC reading as fast as the line
/// makes its board send no control code until the end of the read (§6.3), so nothing is
/// acknowledged until then; meanwhile every progress event past the first blocks names the
/// block the line has carried (MTConnect's `block_fed`, the console's "block").
#[tokio::test(start_paused = true)]
async fn the_block_being_fed_moves_through_a_protocol_b_job() {
    for consume_rate in [chars_per_sec(19_200) * 2, chars_per_sec(19_200) / 4] {
        let rig = Rig::on_sim_line(false, CodeSystem::Iso, true, 19_200, consume_rate);
        let mut events = rig.link.subscribe();
        let program = nc_program(16 * 1024, 7);
        rig.queue(1, &program).await;
        let mut named = Vec::new();
        let mut unnamed = Vec::new();
        loop {
            let ev = next_event(&mut events, HOUR, |ev| match ev {
                LinkEvent::Progress { sent, block, .. } => Some(Some((*sent, block.clone()))),
                LinkEvent::JobDone { .. } => Some(None),
                LinkEvent::JobFailed { reason, .. } => panic!("failed: {reason}"),
                _ => None,
            })
            .await;
            match ev {
                Some((sent, Some(block))) => named.push((sent, block)),
                Some((sent, None)) if sent > 2048 => unnamed.push(sent),
                Some(_) => {}
                None => break,
            }
        }
        assert!(
            unnamed.is_empty(),
            "{consume_rate} c/s: progress without a block at {unnamed:?}"
        );
        assert!(named.len() > 10, "{consume_rate} c/s: {named:?}");
        // Each names a line of the program that went out before it was named, and they
        // move on.
        let mut last = 0;
        for (sent, block) in &named {
            let line = format!("{block}\n");
            let end = program
                .windows(line.len())
                .position(|w| w == line.as_bytes())
                .map(|p| p + line.len())
                .unwrap_or_else(|| panic!("{block:?} is no line of the program"));
            assert!(end as u64 <= *sent && end >= last, "{block:?} at {sent}");
            last = end;
        }
        rig.stop().await;
    }
}
