use super::*;

#[test]
fn keys_are_read_back_by_cell_name_and_kind() {
    let (cell, name, kind, key) =
        classify("cellgate", "cellgate/demo/machine/mill-1/job/mill-1-7-3").unwrap();
    assert_eq!(
        (cell.as_str(), name.as_str(), kind),
        ("demo", "mill-1", Kind::Job)
    );
    assert_eq!(key, "demo/mill-1/job/mill-1-7-3");
    let (_, name, kind, _) = classify("cellgate", "cellgate/demo/plc/plc-1/tag/parts").unwrap();
    assert_eq!((name.as_str(), kind), ("plc-1", Kind::Tag));
    assert!(classify("cellgate", "cellgate/demo/machine/mill-1/g05/s1/blocks").is_none());
    assert!(classify("other", "cellgate/demo/machine/mill-1/status").is_none());
}

#[test]
fn ends_and_alarms_are_urgent_progress_is_not() {
    let progress = pb::JobEvent {
        kind: Some(pb::job_event::Kind::Progress(Default::default())),
        ..Default::default()
    };
    assert!(!urgent(Kind::Job, &progress.encode_to_vec()));
    let done = pb::JobEvent {
        kind: Some(pb::job_event::Kind::Completed(Default::default())),
        ..Default::default()
    };
    assert!(urgent(Kind::Job, &done.encode_to_vec()));
    assert!(urgent(Kind::Alarm, b""));
    assert!(!urgent(Kind::Status, b""));
}
