//! The fault matrix: what a real cell does to a link, and what the gateway must do about it.
//! Each test injects one fault and checks the promise — a job is completed only when the board
//! has every byte, a failed job names the offset the board acknowledged, and the link comes
//! back by itself. Virtual time: hours of line traffic run in seconds.

use crate::common;

use std::time::Duration;

use cellgate::link::driver::LinkEvent;
use cellgate::sim::BoardHandle;
use cellgate::transport::LineSettings;
use cellgate::transport::sim;
use cellgate_core::config::CellConfig;
use cellgate_core::fanuc::error::LinkAlarm;
use cellgate_core::fanuc::host::LinkState;
use cellgate_core::fanuc::message::Framing;
use cellgate_core::sim::fanuc_board::BoardConfig;
use common::device_server::DeviceServer;
use common::{nc_program, next_event, queue, start};

const HOUR: Duration = Duration::from_secs(3600);

fn ready(ev: &LinkEvent) -> Option<()> {
    matches!(
        ev,
        LinkEvent::State {
            state: LinkState::Ready
        }
    )
    .then_some(())
}

/// The board's CNC read `program` whole (compared by digest: no dump of a program on failure).
fn assert_whole(got: &cellgate_core::sim::ReceivedProgram, program: &[u8]) {
    use sha2::{Digest, Sha256};
    assert_eq!(
        got.len,
        program.len() as u64,
        "length of the program the CNC read"
    );
    assert_eq!(
        got.sha256,
        <[u8; 32]>::from(Sha256::digest(program)),
        "digest of the program the CNC read"
    );
}

/// A Protocol A machine behind a device server at `addr`, with short timers (Tp 1 s, To 4 s).
fn tcp_cell(addr: &str, baud: u32) -> CellConfig {
    let text = format!(
        r#"
cell = "faults"
[bus]
listen = []
[[machines]]
name = "m1"
protocol = "a"
tp = 1
to = 4
tw = 1
transport = {{ kind = "tcp", address = "{addr}", line = {{ baud = {baud} }}, reconnect_min_ms = 50, reconnect_max_ms = 500 }}
"#
    );
    CellConfig::from_toml_str(&text, "faults").unwrap_or_else(|e| panic!("{e}"))
}

/// A Protocol A machine behind a device server, whose serial side has a simulated board with
/// the same timers and framing.
async fn machine_behind_device_server(baud: u32) -> (CellConfig, BoardHandle, DeviceServer) {
    let (host_end, device_end, _cable) = sim::line(LineSettings::with_baud(baud));
    let server = DeviceServer::start(host_end).await;
    let config = tcp_cell(&server.addr, baud);
    let m = config.machine("m1").unwrap();
    let board = BoardHandle::spawn(
        BoardConfig {
            framing: Framing::new(m.code, m.effective_end_code()),
            params: m.params(),
            autostart: true,
            consume_rate: 4000,
            ..BoardConfig::default()
        },
        device_end,
    )
    .unwrap();
    (config, board, server)
}

/// The device server's connection goes silent without closing (it lost power and came back,
/// or was swapped): TCP sees nothing wrong. The host's supervision times out (§4.6 1 (6)), the
/// link makes a new connection at once instead of waiting on the dead one, the board
/// re-initialises, and a job then goes through.
#[tokio::test(start_paused = true)]
async fn a_half_open_device_server_connection_is_replaced() {
    let baud = 19_200;
    let (config, board, server) = machine_behind_device_server(baud).await;
    let (cell, token) = start(&config).await;
    let m = cell.machine("m1").unwrap();
    let mut events = m.link.subscribe();
    next_event(&mut events, HOUR, ready).await;
    assert_eq!(server.connections(), 1);

    server.freeze();
    let waited = next_event(&mut events, HOUR, |ev| match ev {
        LinkEvent::Alarm(LinkAlarm::TimeOut { waited }) => Some(*waited),
        _ => None,
    })
    .await;
    assert!(waited <= Duration::from_secs(5), "{waited:?}");
    next_event(&mut events, HOUR, ready).await;
    assert_eq!(
        server.connections(),
        2,
        "a new connection replaced the silent one"
    );

    let program = nc_program(20_000, 3);
    queue(&m.link, 1, program.clone()).await;
    next_event(&mut events, HOUR, |ev| match ev {
        LinkEvent::JobDone { job: 1, bytes, .. } => Some(*bytes),
        LinkEvent::JobFailed { job: 1, reason, .. } => panic!("job failed: {reason}"),
        _ => None,
    })
    .await;
    let snap = board.wait_for(|s| !s.programs.is_empty()).await;
    assert_eq!(snap.programs.len(), 1);
    assert_whole(&snap.programs[0], &program);
    token.cancel();
    cell.join().await;
    server.stop();
}

/// One fault of the matrix, on a simulated line.
#[derive(Debug, Clone, Copy)]
enum Fault {
    /// Random faults on every byte for the whole run, in the directions given.
    Noise {
        corrupt_ppm: u32,
        drop_ppm: u32,
        /// Bytes spared after each hit (see `Noise::guard`).
        guard: u32,
        host_to_device: bool,
        device_to_host: bool,
    },
    /// The cable is cut a third of the way into the first attempt at each program, and
    /// mended after this long.
    Cut(Duration),
    /// The CNC raises an alarm a third of the way in (it resets itself, as an operator would).
    CncAlarm,
    /// The CNC is reset a third of the way in.
    CncReset,
}

enum JobEnd {
    Progress(u64),
    Done(u64),
    Failed { offset: u64, sent: u64 },
}

/// A machine of the matrix: protocol, packet length n, baud rate, and extra machine keys.
#[derive(Debug, Clone, Copy)]
struct Machine {
    protocol: &'static str,
    packet_n: Option<u8>,
    baud: u32,
    /// Protocol A: Nb and No, which bound the DAT length to Nb − No (§4.5 note 1).
    nb_no: Option<(u16, u16)>,
}

const A: Machine = Machine {
    protocol: "a",
    packet_n: None,
    baud: 19_200,
    nb_no: None,
};
const EXPANSION_A: Machine = Machine {
    protocol: "expansion-a",
    packet_n: Some(1),
    baud: 19_200,
    nb_no: None,
};
const B: Machine = Machine {
    protocol: "b",
    packet_n: None,
    baud: 19_200,
    nb_no: None,
};
const EXPANSION_B: Machine = Machine {
    protocol: "expansion-b",
    packet_n: None,
    baud: 86_400,
    nb_no: None,
};

fn cell_of(machine: Machine) -> CellConfig {
    let mut config = common::sim_cell(
        machine.protocol,
        machine.packet_n,
        machine.baud,
        machine.baud / 20,
    );
    if let Some((nb, no)) = machine.nb_no {
        let m = &mut config.machines[0];
        m.nb = Some(nb);
        m.no = Some(no);
    }
    config
}

/// How a run through a fault went.
#[derive(Debug, Default)]
struct Outcome {
    completed: usize,
    failed: usize,
}

/// Three programs, one after another, through `fault`. A program whose job fails is run again
/// (up to `attempts` times) after the operator resets the CNC — what a person does after a
/// failed download. Checks the promise: a completed job's program reached the CNC whole; the
/// CNC read exactly the completed programs, each once, in order, and nothing else; a failed
/// job's offset is no more than the board received.
async fn through(machine: Machine, fault: Fault, attempts: usize) -> Outcome {
    use cellgate::transport::sim::{Dir, Noise};
    let name = machine.protocol;
    let config = cell_of(machine);
    let (cell, token) = start(&config).await;
    let m = cell.machine("m1").unwrap();
    let board = m.board.as_ref().unwrap();
    let line = m.line.as_ref().unwrap().clone();
    let mut events = m.link.subscribe();
    next_event(&mut events, HOUR, ready).await;
    if let Fault::Noise {
        corrupt_ppm,
        drop_ppm,
        guard,
        host_to_device,
        device_to_host,
    } = fault
    {
        for (dir, on, seed) in [
            (Dir::HostToDevice, host_to_device, 7),
            (Dir::DeviceToHost, device_to_host, 11),
        ] {
            if on {
                line.set_noise(
                    dir,
                    Noise {
                        corrupt_ppm,
                        drop_ppm,
                        guard,
                        seed,
                    },
                );
            }
        }
    }

    let programs: Vec<Vec<u8>> = (0..3).map(|i| nc_program(24 * 1024, 100 + i)).collect();
    let mut completed: Vec<&[u8]> = Vec::new();
    let mut outcome = Outcome::default();
    let mut id = 0;
    // What happened, for the failure messages.
    let mut log: Vec<String> = Vec::new();
    for program in &programs {
        let len = program.len() as u64;
        let mut injected = matches!(fault, Fault::Noise { .. });
        for _ in 0..attempts {
            id += 1;
            let received_before = board.snapshot().data_received;
            queue(&m.link, id, program.clone()).await;
            let end = loop {
                let ev = tokio::time::timeout(HOUR, async {
                    loop {
                        match events.recv().await {
                            Ok(LinkEvent::Progress { job, sent, .. }) if job == id => {
                                return JobEnd::Progress(sent);
                            }
                            Ok(LinkEvent::JobDone { job, bytes, .. }) if job == id => {
                                return JobEnd::Done(bytes);
                            }
                            Ok(LinkEvent::JobFailed {
                                job, offset, sent, ..
                            }) if job == id => return JobEnd::Failed { offset, sent },
                            Ok(_) => {}
                            Err(e) => panic!("{name} under {fault:?}: link events: {e}"),
                        }
                    }
                })
                .await
                .unwrap_or_else(|_| {
                    panic!("{name} under {fault:?}: job {id} neither ended nor moved for an hour; {log:#?}")
                });
                match ev {
                    // Injected once the first third has gone out (Expansion A acknowledges
                    // only at the end of a transmission, so what was sent is the measure).
                    JobEnd::Progress(sent) if !injected && sent > len / 3 => {
                        injected = true;
                        log.push(format!("job {id}: {fault:?} at {sent} bytes sent"));
                        match fault {
                            Fault::Cut(down) => {
                                line.cut();
                                let line = line.clone();
                                tokio::spawn(async move {
                                    tokio::time::sleep(down).await;
                                    line.restore();
                                });
                            }
                            Fault::CncAlarm => board.raise_alarm(),
                            Fault::CncReset => board.reset(),
                            Fault::Noise { .. } => {}
                        }
                    }
                    JobEnd::Progress(_) => {}
                    JobEnd::Done(bytes) => break Ok(bytes),
                    JobEnd::Failed { offset, sent } => break Err((offset, sent)),
                }
            };
            match end {
                Ok(bytes) => {
                    log.push(format!("job {id} ({len} bytes) completed"));
                    assert_eq!(bytes, len);
                    completed.push(program);
                    outcome.completed += 1;
                    break;
                }
                Err((offset, sent)) => {
                    log.push(format!(
                        "job {id} ({len} bytes) failed at {offset}, {sent} sent"
                    ));
                    outcome.failed += 1;
                    let received = board.snapshot().data_received - received_before;
                    assert!(
                        offset <= sent && offset <= len && offset <= received,
                        "{name} under {fault:?}: job {id} failed at offset {offset}, \
                         {sent} sent, the board received {received}"
                    );
                    // What a person does after a failed download, once the link is back: reset
                    // the CNC, so that the part-read program is dropped, and run it again.
                    tokio::time::timeout(HOUR, async {
                        while m.link.state() != Some(LinkState::Ready) {
                            tokio::time::sleep(Duration::from_millis(100)).await;
                        }
                    })
                    .await
                    .unwrap_or_else(|_| panic!("{name} under {fault:?}: the link never came back: {:?}, host in {:?}, host out {:?}, board out {:?}, cut {}", m.link.state(), line.modem_in(cellgate::transport::sim::End::Host), line.modem_out(cellgate::transport::sim::End::Host), line.modem_out(cellgate::transport::sim::End::Device), line.is_cut()));
                    board.reset();
                    tokio::time::sleep(Duration::from_secs(3)).await;
                }
            }
        }
    }
    let snap = tokio::time::timeout(
        HOUR,
        board.wait_for(|s| s.programs.len() >= completed.len()),
    )
    .await
    .unwrap_or_else(|_| {
        let read: Vec<u64> = board.snapshot().programs.iter().map(|p| p.len).collect();
        panic!("{name} under {fault:?}: the CNC read programs of {read:?} bytes; {log:#?}")
    });
    let read: Vec<(u64, [u8; 32])> = snap.programs.iter().map(|p| (p.len, p.sha256)).collect();
    let expected: Vec<(u64, [u8; 32])> = completed
        .iter()
        .map(|p| {
            use sha2::{Digest, Sha256};
            (p.len() as u64, <[u8; 32]>::from(Sha256::digest(p)))
        })
        .collect();
    assert!(
        read == expected,
        "{name} under {fault:?}: the CNC read programs of {:?} bytes, not exactly the \
         completed ones in order; {log:#?}",
        read.iter().map(|r| r.0).collect::<Vec<_>>()
    );
    token.cancel();
    cell.join().await;
    outcome
}

/// One bit hit in about one byte in a thousand, both ways, at most one hit per frame: every
/// hit is a checksum error the protocol must catch and recover from (RTY, NAK). Two hits in
/// one frame can cancel in an 8-bit sum, which no host can notice: that limit of the
/// protocols is in README.
const CHECKSUM_NOISE: Fault = Fault::Noise {
    corrupt_ppm: 1_000,
    drop_ppm: 0,
    guard: 300,
    host_to_device: true,
    device_to_host: true,
};

/// Protocol A with DATs of Nb − No = 250 bytes, so that a frame fits the noise's guard.
const A_SHORT_DATS: Machine = Machine {
    nb_no: Some((300, 50)),
    ..A
};

#[tokio::test(start_paused = true)]
async fn protocol_a_under_checksum_errors_both_ways() {
    let o = through(A_SHORT_DATS, CHECKSUM_NOISE, 12).await;
    assert_eq!(o.completed, 3, "{o:?}");
}

#[tokio::test(start_paused = true)]
async fn expansion_a_under_checksum_errors_both_ways() {
    let o = through(EXPANSION_A, CHECKSUM_NOISE, 12).await;
    assert_eq!(o.completed, 3, "{o:?}");
}

#[tokio::test(start_paused = true)]
async fn protocol_a_under_dropped_bytes_both_ways() {
    let drops = Fault::Noise {
        corrupt_ppm: 0,
        drop_ppm: 200,
        guard: 0,
        host_to_device: true,
        device_to_host: true,
    };
    let o = through(A, drops, 12).await;
    assert_eq!(o.completed, 3, "{o:?}");
}

/// A lost byte shifts every later packet of the transmission on a board that frames packets by
/// length, as the simulated one does: the transmission ends (SR0945, CAN) and the program is
/// run again. At this rate most attempts go through.
#[tokio::test(start_paused = true)]
async fn expansion_a_under_dropped_bytes_both_ways() {
    let drops = Fault::Noise {
        corrupt_ppm: 0,
        drop_ppm: 20,
        guard: 0,
        host_to_device: true,
        device_to_host: true,
    };
    let o = through(EXPANSION_A, drops, 12).await;
    assert_eq!(o.completed, 3, "{o:?}");
}

/// Protocol B carries no checksum (§6): a data byte lost on its way to the CNC cannot be
/// noticed by any host, so for B the drops hit what the board sends (DC1, DC3 and the
/// notices).
const DROPS_FROM_THE_BOARD: Fault = Fault::Noise {
    corrupt_ppm: 0,
    drop_ppm: 2_000,
    guard: 0,
    host_to_device: false,
    device_to_host: true,
};

#[tokio::test(start_paused = true)]
async fn protocol_b_under_dropped_control_codes() {
    let o = through(B, DROPS_FROM_THE_BOARD, 12).await;
    assert_eq!(o.completed, 3, "{o:?}");
}

#[tokio::test(start_paused = true)]
async fn expansion_b_under_dropped_control_codes() {
    let o = through(EXPANSION_B, DROPS_FROM_THE_BOARD, 12).await;
    assert_eq!(o.completed, 3, "{o:?}");
}

/// Each program's first attempt is hit; the second goes through.
async fn every_protocol(fault: Fault) {
    let n4 = Machine {
        packet_n: Some(4),
        baud: 86_400,
        ..EXPANSION_A
    };
    for machine in [A, n4, B, EXPANSION_B] {
        let o = through(machine, fault, 2).await;
        assert_eq!(
            (o.completed, o.failed),
            (3, 3),
            "{}: each first attempt fails, each second completes",
            machine.protocol
        );
    }
}

#[tokio::test(start_paused = true)]
async fn every_protocol_through_a_line_cut() {
    every_protocol(Fault::Cut(Duration::from_secs(5))).await;
}

#[tokio::test(start_paused = true)]
async fn every_protocol_through_a_cnc_alarm() {
    every_protocol(Fault::CncAlarm).await;
}

#[tokio::test(start_paused = true)]
async fn every_protocol_through_a_cnc_reset() {
    every_protocol(Fault::CncReset).await;
}

/// A job whose machine cannot take it (here, its cable is cut for good) fails at its
/// deadline, at what the board acknowledged, and says what the link was waiting for; the
/// link reports that wait as it starts.
#[tokio::test(start_paused = true)]
async fn a_stuck_job_fails_at_its_deadline_saying_what_the_link_waited_for() {
    use bytes::Bytes;
    use cellgate::jobs::journal::Journal;
    use cellgate::jobs::source::ProgramInput;
    use cellgate::jobs::{self, JobSubmission, JobsSettings};
    use cellgate::library::ProgramLibrary;
    use cellgate_core::pb;

    let config = common::sim_cell("b", None, 19_200, 2_000);
    let (cell, token) = start(&config).await;
    let m = cell.machine("m1").unwrap();
    let mut link_events = m.link.subscribe();
    next_event(&mut link_events, HOUR, ready).await;
    m.line.as_ref().unwrap().cut();
    let dir = tempfile::tempdir().unwrap();
    let library = ProgramLibrary::new(dir.path(), 1 << 20);
    let settings = JobsSettings {
        rules: m.config.program_rules(library.max_size()),
        library,
        journal: Journal::open(&dir.path().join(".journal")).unwrap(),
        restored: Vec::new(),
        keep: jobs::KEEP_ENDED,
        accept: Default::default(),
    };
    let (jobs, _task, mut events) =
        jobs::spawn("m1", settings, m.link.clone(), token.child_token());
    let started = tokio::time::Instant::now();
    let accepted = jobs
        .submit(JobSubmission {
            input: ProgramInput::Inline(Bytes::from(nc_program(4000, 9))),
            deadline_s: 30,
            ..JobSubmission::default()
        })
        .await
        .unwrap();
    // The job starts waiting for the CNC's DC1, then the cut shows as DR off.
    let waited = next_event(&mut link_events, HOUR, |ev| match ev {
        LinkEvent::Waiting { what: Some(w), .. } if w.starts_with("DR") => Some(*w),
        _ => None,
    })
    .await;
    assert!(waited.contains("line is down"), "{waited}");
    let failed = tokio::time::timeout(HOUR, async {
        loop {
            let e = events.recv().await.unwrap();
            if e.job_id == accepted.job_id
                && let Some(pb::job_event::Kind::Failed(f)) = &e.kind
            {
                return f.clone();
            }
        }
    })
    .await
    .expect("the job never failed");
    let took = started.elapsed();
    assert!(
        took >= Duration::from_secs(30) && took < Duration::from_secs(32),
        "{took:?}"
    );
    assert_eq!(failed.code(), pb::ErrorCode::DeadlineExceeded);
    assert_eq!(failed.byte_offset, 0);
    assert!(
        failed.reason.contains("deadline of 30 s") && failed.reason.contains("DR"),
        "{}",
        failed.reason
    );
    token.cancel();
    cell.join().await;
}
