use super::*;

fn event(kind: Kind) -> pb::JobEvent {
    pb::JobEvent {
        job_id: "m-1-1".to_string(),
        machine: "m".to_string(),
        unix_ms: 42,
        origin: Some(pb::JobOrigin {
            program: Some(pb::ProgramRef {
                library: "O1".to_string(),
                revision: 3,
                sha256: "ab".repeat(32),
            }),
            ..Default::default()
        }),
        kind: Some(kind),
    }
}

#[test]
fn a_job_is_recorded_once_it_ended() {
    assert!(job_history(&event(Kind::Queued(Default::default()))).is_none());
    assert!(job_history(&event(Kind::Progress(Default::default()))).is_none());
    let done = job_history(&event(Kind::Completed(pb::job_event::Completed {
        bytes_sent: 100,
        ..Default::default()
    })))
    .unwrap();
    assert_eq!(done.outcome(), pb::JobOutcome::Completed);
    assert_eq!((done.bytes_sent, done.ended_unix_ms), (100, 42));
    assert_eq!(done.origin.unwrap().program.unwrap().revision, 3);
    let failed = job_history(&event(Kind::Failed(pb::job_event::Failed {
        reason: "retry over".to_string(),
        byte_offset: 7,
        alarm_number: "SR0945".to_string(),
        code: pb::ErrorCode::LinkFailed as i32,
        ..Default::default()
    })))
    .unwrap();
    assert_eq!(failed.outcome(), pb::JobOutcome::Failed);
    assert_eq!(failed.alarm_number, "SR0945");
    assert_eq!(failed.code(), pb::ErrorCode::LinkFailed);
    let cancelled = job_history(&event(Kind::Cancelled(pb::job_event::Cancelled {
        by: "bus".to_string(),
        ..Default::default()
    })))
    .unwrap();
    assert_eq!(cancelled.reason, "cancelled by bus");
}
