//! Protocol B machines on the bus, with real links to simulated boards: programs the CNC
//! punches out (ISO, ASCII, EIA) come out on `P/C/machine/M/punch` and in the library, remote
//! requests punched by the CNC queue library programs, and a CNC alarm in the middle of a
//! download fails the job with its offset and raises an alarm event.
//! Real time (zenoh cannot run under paused time), loopback, multicast scouting off.

use crate::common;

use std::time::Duration;

use cellgate::bus::keys::MachineLeaf;
use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;
use cellgate_core::program::tape::{self, TapeCode};
use common::bus::{RunningCell, Sub, follow, get, get_one};
use prost::Message;
use sha2::{Digest, Sha256};

async fn start() -> RunningCell {
    RunningCell::start(cell_config, false).await
}

/// `lathe-1`: Protocol B, ISO control codes, notification on, 19200 baud.
/// `lathe-2`: Expansion B, ASCII control codes, notification off, 86400 baud.
/// Both CNCs read 1000 bytes/s, slower than either line.
fn cell_config(port: u16, dir: &std::path::Path) -> CellConfig {
    let text = format!(
        r#"
cell = "punch"
[bus]
listen = ["tcp/127.0.0.1:{port}"]
[programs]
dir = {:?}
[[machines]]
name = "lathe-1"
protocol = "b"
code = "iso"
notify_alarm_reset = true
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
sim = {{ consume_rate = 1000 }}
[[machines]]
name = "lathe-2"
protocol = "expansion-b"
code = "ascii"
notify_alarm_reset = false
transport = {{ kind = "sim", line = {{ baud = 86400 }} }}
sim = {{ consume_rate = 1000, buffer_size = 16384 }}
"#,
        dir.join("programs")
    );
    CellConfig::from_toml_str(&text, "punch cell").unwrap_or_else(|e| panic!("{e}"))
}

impl RunningCell {
    /// Puts a program into the library and waits until the library has it.
    async fn put_program(&self, name: &str, program: &[u8]) {
        self.client
            .put(self.keys.program_write(name), program.to_vec())
            .await
            .unwrap();
        // A put has no reply: read the library back until it has the program.
        for _ in 0..100 {
            if let [Ok((_, bytes, _))] = get(&self.client, &self.keys.program(name), None)
                .await
                .as_slice()
                && bytes == program
            {
                return;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        panic!("program {name} never showed in the library");
    }
}

async fn next<M: Message + Default>(sub: &Sub, what: &str) -> M {
    let sample = tokio::time::timeout(Duration::from_secs(30), sub.recv_async())
        .await
        .unwrap_or_else(|_| panic!("no {what} within 30 s"))
        .unwrap();
    M::decode(sample.payload().to_bytes().as_ref()).unwrap()
}

const PART: &[u8] = b"%\nO1234(SHAFT 7)\nG00X10.Y2.5\nG01Z-1.F100\nM30\n%";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn punched_programs_round_trip_in_iso_ascii_and_eia() {
    let cell = start().await;
    let punched = cell
        .subscribe(cell.keys.leaf("lathe-1", MachineLeaf::Punch))
        .await;
    let cases = [
        (TapeCode::Iso, pb::CodeSystem::Iso),
        (TapeCode::Ascii, pb::CodeSystem::Ascii),
        (TapeCode::Eia, pb::CodeSystem::Eia),
    ];
    let mut names = Vec::new();
    for (code, expected) in cases {
        let tape = tape::encode(PART, code).unwrap();
        if code != TapeCode::Ascii {
            assert_ne!(tape.as_slice(), PART, "{code}: the tape is encoded");
        }
        cell.board("lathe-1").punch(tape);
        let p: pb::PunchedProgram = next(&punched, "punched program").await;
        assert_eq!(p.machine, "lathe-1");
        assert_eq!(p.code_system(), expected, "{code}");
        assert_eq!(p.o_number, "O1234", "{code}");
        assert_eq!(p.name, "SHAFT 7", "{code}");
        assert_eq!(
            String::from_utf8_lossy(&p.program),
            String::from_utf8_lossy(PART),
            "{code}: the text is the program as written"
        );
        assert!(p.request.is_none());
        assert!(
            p.library_name.starts_with("lathe-1-O1234-"),
            "{code}: {}",
            p.library_name
        );
        // Stored under that name, never over an earlier punch of the same program.
        let stored = get(&cell.client, &cell.keys.program(&p.library_name), None).await;
        match stored.as_slice() {
            [Ok((_, bytes, _))] => assert_eq!(bytes, PART),
            other => panic!("{}: {other:?}", p.library_name),
        }
        assert!(!names.contains(&p.library_name), "{names:?}");
        names.push(p.library_name);
    }
    let status: pb::MachineStatus = get_one(
        &cell.client,
        &cell.keys.leaf("lathe-1", MachineLeaf::Status),
        None,
    )
    .await;
    assert_eq!(status.counters.unwrap().programs_punched, 3);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_punched_program_is_compared_with_the_library_and_adopted_as_a_revision() {
    let cell = start().await;
    let punched = cell
        .subscribe(cell.keys.leaf("lathe-1", MachineLeaf::Punch))
        .await;
    // Nothing in the library yet: no comparison.
    cell.board("lathe-1")
        .punch(tape::encode(PART, TapeCode::Iso).unwrap());
    let p: pb::PunchedProgram = next(&punched, "punched program").await;
    assert!(p.comparison.is_none(), "{:?}", p.comparison);
    // The library's O1234 has the same blocks (blanks aside): the same.
    let spaced = b"%\nO1234(SHAFT 7)\nG00 X10. Y2.5\nG01 Z-1. F100\nM30\n%";
    cell.put_program("O1234", spaced).await;
    cell.board("lathe-1")
        .punch(tape::encode(PART, TapeCode::Iso).unwrap());
    let p: pb::PunchedProgram = next(&punched, "punched program").await;
    let c = p.comparison.expect("compared");
    assert_eq!((c.library_name.as_str(), c.revision), ("O1234", 1));
    assert!(c.same, "{c:?}");
    // The operator changed a feed at the machine: one block changed.
    let edited = b"%\nO1234(SHAFT 7)\nG00X10.Y2.5\nG01Z-1.F80\nM30\n%";
    cell.board("lathe-1")
        .punch(tape::encode(edited, TapeCode::Iso).unwrap());
    let p: pb::PunchedProgram = next(&punched, "punched program").await;
    let c = p.comparison.expect("compared");
    assert!(!c.same);
    assert_eq!(
        (c.blocks_changed, c.blocks_added, c.blocks_removed),
        (1, 0, 0),
        "{c:?}"
    );
    // One request makes it O1234's next revision, saying where it came from.
    let adopt = pb::ProgramWrite {
        op: Some(pb::program_write::Op::Adopt(pb::program_write::Adopt {
            from: p.library_name.clone(),
            revision: String::new(),
        })),
        comment: "feed as proven on the machine".to_string(),
    };
    let info: pb::ProgramInfo = get_one(
        &cell.client,
        &cell.keys.program_write("O1234"),
        Some(adopt.encode_to_vec()),
    )
    .await;
    let r = info.latest.unwrap();
    assert_eq!(r.number, 2);
    assert_eq!(r.adopted_from, p.library_name);
    assert_eq!(r.comment, "feed as proven on the machine");
    let now = get(&cell.client, &cell.keys.program("O1234"), None).await;
    assert_eq!(now[0].as_ref().unwrap().1, edited);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_punch_of_two_programs_comes_out_as_two() {
    let cell = start().await;
    let punched = cell
        .subscribe(cell.keys.leaf("lathe-2", MachineLeaf::Punch))
        .await;
    let second = b"%\nO55\nG00X0\nM30\n%";
    let mut tape = tape::encode(PART, TapeCode::Ascii).unwrap();
    tape.extend_from_slice(&tape::encode(second, TapeCode::Ascii).unwrap());
    cell.board("lathe-2").punch(tape);
    let a: pb::PunchedProgram = next(&punched, "first program").await;
    let b: pb::PunchedProgram = next(&punched, "second program").await;
    assert_eq!((a.o_number.as_str(), b.o_number.as_str()), ("O1234", "O55"));
    assert_eq!(b.program, second);
    assert!(
        b.library_name.starts_with("lathe-2-O55-"),
        "{}",
        b.library_name
    );
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_remote_request_queues_the_library_program() {
    let cell = start().await;
    let program = common::nc_program(6 * 1024, 12);
    cell.put_program("O0012", &program).await;
    let punched = cell
        .subscribe(cell.keys.leaf("lathe-1", MachineLeaf::Punch))
        .await;
    let jobs = cell.subscribe(cell.keys.job_events("lathe-1", "*")).await;
    // The operator calls O12 from the CNC: `(PRG=12)`, punched in ISO.
    let request = tape::encode(b"%\n(PRG=12)\n%", TapeCode::Iso).unwrap();
    cell.board("lathe-1").punch(request);
    let p: pb::PunchedProgram = next(&punched, "punched request").await;
    let r = p.request.expect("a request");
    assert_eq!(r.program, "O12");
    assert_eq!(
        r.library_name, "O0012",
        "found under FANUC's 4-digit spelling"
    );
    assert!(r.error.is_empty(), "{}", r.error);
    assert!(!r.job_id.is_empty());
    assert!(p.library_name.is_empty(), "a request is not stored");
    // The job runs to the end, and the CNC gets the program byte for byte.
    let seen = follow(&jobs, &r.job_id, Duration::from_secs(60)).await;
    match seen.last() {
        Some(Kind::Completed(c)) => assert_eq!(c.bytes_sent, program.len() as u64),
        other => panic!("the requested job ended with {other:?}"),
    }
    let snap = cell
        .board("lathe-1")
        .wait_for(|s| !s.programs.is_empty())
        .await;
    assert_eq!(
        snap.programs[0].sha256,
        <[u8; 32]>::from(Sha256::digest(&program))
    );
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_for_a_missing_program_raises_an_alarm() {
    let cell = start().await;
    let punched = cell
        .subscribe(cell.keys.leaf("lathe-1", MachineLeaf::Punch))
        .await;
    let alarms = cell
        .subscribe(cell.keys.leaf("lathe-1", MachineLeaf::Alarm))
        .await;
    let request = tape::encode(b"%\n(REQ O9999)\n%", TapeCode::Eia).unwrap();
    cell.board("lathe-1").punch(request);
    let p: pb::PunchedProgram = next(&punched, "punched request").await;
    let r = p.request.expect("a request");
    assert_eq!(r.program, "O9999");
    assert!(r.job_id.is_empty());
    assert!(r.error.contains("O9999"), "{}", r.error);
    let alarm: pb::AlarmEvent = next(&alarms, "alarm").await;
    assert_eq!(alarm.kind(), pb::AlarmKind::RemoteRequest);
    assert!(alarm.message.contains("O9999"), "{}", alarm.message);
    let queue: pb::JobQueue = get_one(
        &cell.client,
        &cell.keys.leaf("lathe-1", MachineLeaf::Job),
        None,
    )
    .await;
    assert!(
        queue.active.is_none() && queue.waiting.is_empty(),
        "nothing was queued: {queue:?}"
    );
    cell.stop().await;
}

/// A CNC alarm in the middle of a download: with notification on (NAK) and off (ER off, seen
/// as DR off: SR0855).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cnc_alarm_mid_transfer_fails_the_job_with_its_offset() {
    let cell = start().await;
    for (machine, kind) in [
        ("lathe-1", pb::AlarmKind::CncAlarm),
        ("lathe-2", pb::AlarmKind::LinkAlarm),
    ] {
        let alarms = cell
            .subscribe(cell.keys.leaf(machine, MachineLeaf::Alarm))
            .await;
        // 200 KiB at 1000 bytes/s: minutes, so the alarm comes in the middle.
        let program = common::nc_program(200 * 1024, 3);
        let (job, events) = cell.submit(machine, &program).await;
        // Wait for the transfer to be well under way.
        tokio::time::timeout(Duration::from_secs(30), async {
            loop {
                let ev: pb::JobEvent = next(&events, "job event").await;
                if let Some(Kind::Progress(p)) = ev.kind
                    && p.bytes_sent > 4096
                {
                    return;
                }
            }
        })
        .await
        .expect("the transfer got under way");
        cell.board(machine).raise_alarm();
        let seen = follow(&events, &job, Duration::from_secs(60)).await;
        match seen.last() {
            Some(Kind::Failed(f)) => {
                assert!(
                    f.byte_offset > 4096 && f.byte_offset < program.len() as u64,
                    "{machine}: offset {} of {}",
                    f.byte_offset,
                    program.len()
                );
            }
            other => panic!("{machine}: the job ended with {other:?}"),
        }
        let alarm: pb::AlarmEvent = next(&alarms, "alarm").await;
        assert_eq!(alarm.kind(), kind, "{machine}: {alarm:?}");
        // The CNC is reset so the next case starts clean.
        cell.board(machine).reset();
    }
    cell.stop().await;
}
