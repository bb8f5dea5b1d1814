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

#[tokio::test]
async fn a_job_that_ends_before_it_starts_keeps_its_size() {
    let dir = tempfile::tempdir().unwrap();
    let stop = tokio_util::sync::CancellationToken::new();
    let config = cellgate_core::config::HistoryConfig::default();
    let (h, writer) = History::open(dir.path(), &config, stop.clone())
        .await
        .unwrap();
    let mut r = Recorder::default();
    r.job(
        &h,
        "m",
        &event(Kind::Queued(pb::job_event::Queued {
            queue_position: 0,
            bytes_total: Some(40_550),
        })),
    );
    r.job(
        &h,
        "m",
        &event(Kind::Cancelled(pb::job_event::Cancelled {
            by: "request".to_string(),
            ..Default::default()
        })),
    );
    let page = loop {
        use cellgate_core::history::{HistoryQuery, Store};
        let q = HistoryQuery::parse(
            Store::History,
            [],
            |_| Err(String::new()),
            pb::now_ms() + 1000,
        )
        .unwrap();
        let page = h.query(crate::history::Log::History, q).await.unwrap();
        if page
            .records
            .iter()
            .any(|r| matches!(r.record, Some(Record::Job(_))))
        {
            break page;
        }
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    };
    let job = page.records.iter().find_map(|r| match &r.record {
        Some(Record::Job(j)) => Some(j),
        _ => None,
    });
    assert_eq!(job.unwrap().bytes_total, 40_550);
    stop.cancel();
    writer.await.unwrap();
}
