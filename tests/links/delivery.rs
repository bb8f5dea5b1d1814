//! Completed means the CNC has it, and a cut program resumes where the board stopped holding
//! it: the job manager with its journal, the real link and the simulated board, in virtual
//! time.

use crate::common;

use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use cellgate::jobs::journal::Journal;
use cellgate::jobs::source::ProgramInput;
use cellgate::jobs::{self, JobSubmission, JobsSettings};
use cellgate::library::ProgramLibrary;
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;
use common::{nc_program, sim_cell, start};
use sha2::{Digest, Sha256};

const HOUR: Duration = Duration::from_secs(3600);

async fn until_end(
    events: &mut cellgate::link::fanout::Receiver<Arc<pb::JobEvent>>,
    id: &str,
) -> pb::JobEvent {
    tokio::time::timeout(HOUR, async {
        loop {
            let e = events.recv().await.unwrap();
            if e.job_id == id
                && matches!(
                    e.kind,
                    Some(Kind::Completed(_) | Kind::Failed(_) | Kind::Cancelled(_))
                )
            {
                return Arc::unwrap_or_clone(e);
            }
        }
    })
    .await
    .expect("the job never ended")
}

/// A 1 MiB program cut by a CNC alarm: the job fails at what the board acknowledged and names
/// the first block it did not hold whole; resumed, the board receives the header and the
/// program from exactly that block: nothing skipped, no whole block twice. Expansion A
/// acknowledges nothing before the end of a transmission (`mid_acks` false): its job fails at
/// offset 0 and resumes from the start.
async fn resume_after_an_alarm(protocol: &str, packet_n: Option<u8>, baud: u32, mid_acks: bool) {
    let config = sim_cell(protocol, packet_n, baud, 6_000);
    let (cell, token) = start(&config).await;
    let m = cell.machine("m1").unwrap();
    let board = m.board.as_ref().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let library = ProgramLibrary::new(dir.path(), 4 << 20);
    let journal = Journal::open(&dir.path().join(".journal")).unwrap();
    let settings = JobsSettings {
        rules: m.config.program_rules(library.max_size()),
        library,
        journal,
        restored: Vec::new(),
        keep: jobs::KEEP_ENDED,
        accept: Default::default(),
    };
    let (jobs, _task, mut events) =
        jobs::spawn("m1", settings, m.link.clone(), token.child_token());

    // A header (tape start, O-number), then numbered blocks.
    let program = nc_program(1 << 20, 31);
    let header = b"%\nO0031\n";
    assert!(program.starts_with(header));
    let first = jobs
        .submit(JobSubmission {
            input: ProgramInput::Inline(Bytes::from(program.clone())),
            ..JobSubmission::default()
        })
        .await
        .unwrap();
    board.wait_for(|s| s.data_received > 400 * 1024).await;
    board.raise_alarm();
    let failed = until_end(&mut events, &first.job_id).await;
    let Some(Kind::Failed(f)) = failed.kind else {
        panic!("{failed:?}");
    };
    // Protocol B without notification sees the alarm as ER off, a link failure (§6.4 (1)).
    assert!(
        matches!(
            f.code(),
            pb::ErrorCode::CncAlarm | pb::ErrorCode::LinkFailed
        ),
        "{}",
        f.reason
    );
    let next = f.next_block.clone().expect("the block to resume at");
    let block_start = usize::try_from(next.byte_offset).unwrap();
    let block_end = block_start
        + program[block_start..]
            .iter()
            .position(|&b| b == b'\n')
            .unwrap()
        + 1;
    // The block holds the acknowledged offset: every block before it was acknowledged whole
    // (nothing skipped), and it was not (nothing sent twice).
    let acked = usize::try_from(f.byte_offset).unwrap();
    assert!(
        block_start <= acked && acked < block_end,
        "acknowledged {acked}, block {block_start}..{block_end}"
    );
    if mid_acks {
        assert!(acked > 300 * 1024, "acknowledged only {acked}");
        assert!(next.sequence_number.starts_with('N'), "{next:?}");
    } else {
        assert_eq!((acked, block_start), (0, 0));
    }
    assert_eq!(
        next.line,
        1 + program[..block_start]
            .iter()
            .filter(|&&b| b == b'\n')
            .count() as u64
    );

    let programs_before = board.snapshot().programs.len();
    let resumed = jobs
        .submit(JobSubmission {
            input: ProgramInput::Resume(first.job_id.clone()),
            ..JobSubmission::default()
        })
        .await
        .unwrap();
    let done = until_end(&mut events, &resumed.job_id).await;
    assert!(matches!(done.kind, Some(Kind::Completed(_))), "{done:?}");
    let snap = board.wait_for(|s| s.programs.len() > programs_before).await;
    let got = snap.programs.last().unwrap();
    let mut expected = if block_start == 0 {
        Vec::new()
    } else {
        header.to_vec()
    };
    expected.extend_from_slice(&program[block_start..]);
    assert_eq!(got.len, expected.len() as u64);
    assert_eq!(got.sha256, <[u8; 32]>::from(Sha256::digest(&expected)));
    token.cancel();
    cell.join().await;
}

#[tokio::test(start_paused = true)]
async fn a_program_cut_by_a_cnc_alarm_resumes_at_its_next_block_protocol_a() {
    resume_after_an_alarm("a", None, 19_200, true).await;
}

#[tokio::test(start_paused = true)]
async fn a_program_cut_by_a_cnc_alarm_in_expansion_a_resumes_from_its_start() {
    resume_after_an_alarm("expansion-a", Some(2), 86_400, false).await;
}

#[tokio::test(start_paused = true)]
async fn a_program_cut_by_a_cnc_alarm_resumes_at_its_next_block_protocol_b() {
    resume_after_an_alarm("b", None, 19_200, true).await;
}
