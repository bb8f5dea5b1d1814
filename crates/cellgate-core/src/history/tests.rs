use super::*;

const NOW: u64 = 1_800_000_000_000;
const H: u64 = 3_600_000;

fn no_time(_: &str) -> Result<(u64, u64), String> {
    Err("no time here".to_string())
}

fn parse(store: Store, params: &[(&str, &str)]) -> Result<HistoryQuery, ParamError> {
    HistoryQuery::parse(store, params.iter().copied(), no_time, NOW)
}

#[test]
fn a_query_without_parameters_reads_the_last_day() {
    let q = parse(Store::History, &[]).unwrap();
    assert_eq!((q.from_ms, q.to_ms), (NOW - 24 * H, NOW));
    assert_eq!(q.limit, DEFAULT_LIMIT);
    assert!(q.machines.is_none() && q.kinds.is_none());
}

#[test]
fn parameters_are_read_and_bad_ones_named() {
    let q = HistoryQuery::parse(
        Store::History,
        [
            ("_time", "[x..y]"),
            ("machine", "mill-1, lathe-1"),
            ("kind", "job,alarm"),
            ("limit", "50"),
            ("after", "7"),
        ],
        |v| {
            assert_eq!(v, "[x..y]");
            Ok((10, 20))
        },
        NOW,
    )
    .unwrap();
    assert_eq!((q.from_ms, q.to_ms, q.limit, q.after), (10, 20, 50, 7));
    assert_eq!(q.machines.unwrap().len(), 2);
    assert_eq!(q.kinds.unwrap().len(), 2);

    let e = parse(Store::History, &[("_time", "[now(-1h)..]")]).unwrap_err();
    assert!(e.to_string().contains("no time here"), "{e}");
    let e = parse(Store::History, &[("kind", "jobs")]).unwrap_err();
    assert!(e.to_string().contains("\"jobs\" is not a kind"), "{e}");
    let e = parse(Store::History, &[("kind", "audit")]).unwrap_err();
    assert!(e.to_string().contains("not a kind of this store"), "{e}");
    let e = parse(Store::History, &[("limit", "0")]).unwrap_err();
    assert!(e.to_string().contains("1 to 10000"), "{e}");
    let e = parse(Store::History, &[("limit", "ten")]).unwrap_err();
    assert!(e.to_string().contains("whole number"), "{e}");
    let e = parse(Store::History, &[("bucket", "hour")]).unwrap_err();
    assert!(matches!(e, ParamError::Unknown { .. }), "{e}");
    assert!(parse(Store::Utilisation, &[("bucket", "shift")]).is_ok());
    let e = parse(Store::Utilisation, &[("bucket", "week")]).unwrap_err();
    assert!(e.to_string().contains("hour or shift"), "{e}");
    let e = parse(Store::History, &[("tag", "parts")]).unwrap_err();
    assert!(e.to_string().contains("PLC/NAME"), "{e}");
    assert_eq!(parse(Store::History, &[]).unwrap().order, Order::Oldest);
    assert_eq!(
        parse(Store::Audit, &[("order", "newest")]).unwrap().order,
        Order::Newest
    );
    let e = parse(Store::History, &[("order", "latest")]).unwrap_err();
    assert!(e.to_string().contains("oldest or newest"), "{e}");
    let e = parse(Store::Utilisation, &[("order", "newest")]).unwrap_err();
    assert!(matches!(e, ParamError::Unknown { .. }), "{e}");
    let e = HistoryQuery::parse(Store::History, [("_time", "[b..a]")], |_| Ok((5, 4)), NOW)
        .unwrap_err();
    assert!(e.to_string().contains("empty"), "{e}");
}

fn record(t: u64, seq: u64, machine: &str, kind: HistoryKind) -> pb::HistoryRecord {
    pb::HistoryRecord {
        unix_ms: t,
        seq,
        machine: machine.to_string(),
        kind: kind as i32,
        record: None,
    }
}

#[test]
fn a_query_takes_records_by_time_machine_kind_and_after() {
    let q = parse(Store::History, &[("machine", "m1"), ("kind", "job")]).unwrap();
    assert!(q.takes(&record(NOW - H, 1, "m1", HistoryKind::Job)));
    assert!(!q.takes(&record(NOW - H, 1, "m2", HistoryKind::Job)));
    assert!(!q.takes(&record(NOW - H, 1, "m1", HistoryKind::Alarm)));
    assert!(!q.takes(&record(NOW - 25 * H, 1, "m1", HistoryKind::Job)));
    assert!(!q.takes(&record(NOW + 1, 1, "m1", HistoryKind::Job)));
    let q = parse(Store::History, &[("after", "5")]).unwrap();
    assert!(!q.takes(&record(NOW, 5, "m1", HistoryKind::Job)));
    assert!(q.takes(&record(NOW, 6, "m1", HistoryKind::Job)));
}

#[test]
fn tag_values_come_only_when_asked_for() {
    let mut r = record(NOW, 1, "plc-1", HistoryKind::Tag);
    r.record = Some(pb::history_record::Record::Tag(pb::TagValue {
        plc: "plc-1".to_string(),
        name: "parts".to_string(),
        ..Default::default()
    }));
    assert!(!parse(Store::History, &[]).unwrap().takes(&r));
    assert!(parse(Store::History, &[("kind", "tag")]).unwrap().takes(&r));
    assert!(
        parse(Store::History, &[("tag", "plc-1/parts")])
            .unwrap()
            .takes(&r)
    );
    assert!(
        !parse(Store::History, &[("tag", "plc-1/recipe")])
            .unwrap()
            .takes(&r)
    );
}

fn status(link: pb::LinkState, buffer: Option<pb::BufferStatus>) -> pb::MachineStatus {
    pb::MachineStatus {
        link_state: link as i32,
        sat: buffer.map(|b| pb::Sat {
            buffer_status: b as i32,
            ..Default::default()
        }),
        ..Default::default()
    }
}

#[test]
fn activity_follows_the_link_then_the_sat() {
    use pb::{BufferStatus as B, LinkState as L, MachineActivity as A};
    assert_eq!(activity(&status(L::Down, Some(B::Alarm))), A::LinkDown);
    assert_eq!(activity(&status(L::Connecting, None)), A::LinkDown);
    assert_eq!(activity(&status(L::Sending, Some(B::Alarm))), A::Reading);
    assert_eq!(activity(&status(L::Receiving, None)), A::Punching);
    assert_eq!(activity(&status(L::Alarm, None)), A::Alarm);
    assert_eq!(activity(&status(L::Idle, Some(B::Alarm))), A::Alarm);
    assert_eq!(activity(&status(L::Idle, Some(B::Reset))), A::Reset);
    assert_eq!(activity(&status(L::Idle, Some(B::Operating))), A::Idle);
    assert_eq!(activity(&status(L::Idle, None)), A::Idle);
}

#[test]
fn hour_buckets_cover_the_range() {
    let b = buckets(10 * H + 5, 12 * H + 1, Bucket::Hour, &[]);
    assert_eq!(b, [(10 * H, 11 * H), (11 * H, 12 * H), (12 * H, 13 * H)]);
    // Shifts at 06:00, 14:00, 22:00 UTC.
    let day = 20_000 * 24 * H;
    let b = buckets(day + 7 * H, day + 15 * H, Bucket::Shift, &[360, 840, 1320]);
    assert_eq!(
        b,
        [(day + 6 * H, day + 14 * H), (day + 14 * H, day + 22 * H)]
    );
    // The night shift runs into the next day.
    let b = buckets(
        day + 23 * H,
        day + 24 * H + H,
        Bucket::Shift,
        &[360, 840, 1320],
    );
    assert_eq!(b, [(day + 22 * H, day + 30 * H)]);
}

#[test]
fn utilisation_shares_each_bucket_between_the_states() {
    use pb::MachineActivity as A;
    let marks = [
        Mark::Started(0),
        Mark::Activity(0, A::Idle),
        Mark::Activity(H / 2, A::Reading),
        Mark::Activity(H + H / 4, A::Alarm),
        Mark::Activity(H + H / 2, A::Idle),
    ];
    let jobs = [(H / 2 + 10, true), (H + H / 4, false)];
    let b = utilisation(&marks, &jobs, &[], false, &[(0, H), (H, 2 * H)], 2 * H);
    assert_eq!(b[0].idle_ms, H / 2);
    assert_eq!(b[0].reading_ms, H / 2);
    assert_eq!(b[0].jobs_completed, 1);
    assert_eq!(b[1].reading_ms, H / 4);
    assert_eq!(b[1].alarm_ms, H / 4);
    assert_eq!(b[1].idle_ms, H / 2);
    assert_eq!(b[1].jobs_failed, 1);
    for x in &b {
        assert_eq!(x.unknown_ms, 0, "{x:?}");
        assert_eq!(x.parts, None);
    }
}

#[test]
fn time_the_gateway_was_not_running_is_unknown() {
    use pb::MachineActivity as A;
    // Reading from 0; a clean stop at 10 min; started again at 40 min.
    let marks = [
        Mark::Activity(0, A::Reading),
        Mark::Stopped(10 * 60_000),
        Mark::Started(40 * 60_000),
        Mark::Activity(40 * 60_000, A::Idle),
    ];
    let b = utilisation(&marks, &[], &[], false, &[(0, H)], H);
    assert_eq!(b[0].reading_ms, 10 * 60_000);
    assert_eq!(b[0].unknown_ms, 30 * 60_000);
    assert_eq!(b[0].idle_ms, 20 * 60_000);

    // A crash: last alive at 5 min, started at 40: the state holds one alive period after
    // the last sign of life, the rest is unknown.
    let marks = [
        Mark::Activity(0, A::Reading),
        Mark::Alive(5 * 60_000),
        Mark::Started(40 * 60_000),
        Mark::Activity(40 * 60_000, A::Idle),
    ];
    let b = utilisation(&marks, &[], &[], false, &[(0, H)], H);
    assert_eq!(b[0].reading_ms, 6 * 60_000);
    assert_eq!(b[0].unknown_ms, 34 * 60_000);

    // Before the first record, and after now: unknown and not counted.
    let b = utilisation(
        &[Mark::Activity(H / 2, A::Idle)],
        &[],
        &[],
        false,
        &[(0, H)],
        H,
    );
    assert_eq!((b[0].unknown_ms, b[0].idle_ms), (H / 2, H / 2));
    let b = utilisation(
        &[Mark::Activity(0, A::Idle)],
        &[],
        &[],
        false,
        &[(0, H)],
        H / 4,
    );
    assert_eq!((b[0].idle_ms, b[0].unknown_ms), (H / 4, 0));
}

#[test]
fn parts_are_the_counters_rises_and_a_reset_counts_from_zero() {
    let values = [
        (0, 100.0),
        (10, 103.0),
        (20, 103.0),
        (30, 2.0),
        (40, 5.0),
        (50, 9.0),
    ];
    assert_eq!(parts_made(&values, 5, 45), 3.0 + 2.0 + 3.0);
    // The value before the bucket is the base; nothing after the bucket counts.
    assert_eq!(parts_made(&values, 45, 100), 4.0);
    assert_eq!(parts_made(&[], 0, 100), 0.0);
    let b = utilisation(&[], &[], &values, true, &[(0, 100)], 100);
    assert_eq!(b[0].parts, Some(3.0 + 2.0 + 3.0 + 4.0));
}
