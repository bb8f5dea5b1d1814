use super::*;

#[test]
fn time_options_become_zenoh_ranges() {
    let p = |since: Option<&str>, until: Option<&str>| {
        time_param(&None, &since.map(String::from), &until.map(String::from))
    };
    assert_eq!(p(None, None).unwrap(), None);
    assert_eq!(p(Some("2h"), None).unwrap().unwrap().1, "[now(-2h)..]");
    assert_eq!(
        p(Some("7d"), Some("1d")).unwrap().unwrap().1,
        "[now(-7d)..now(-1d)]"
    );
    assert_eq!(
        p(Some("2026-12-01T06:00:00Z"), Some("now"))
            .unwrap()
            .unwrap()
            .1,
        "[2026-12-01T06:00:00Z..now()]"
    );
    let e = p(Some("yesterday"), None).unwrap_err();
    assert!(e.to_string().contains("30m, 2h, 7d"), "{e}");
    assert_eq!(
        time_param(&Some("[now(-1h)..]".into()), &None, &None)
            .unwrap()
            .unwrap()
            .1,
        "[now(-1h)..]"
    );
}

#[test]
fn a_diff_reads_like_a_diff() {
    let d = pb::ProgramDiff {
        name: "O1".into(),
        a: Some(pb::ProgramRevision {
            number: 1,
            ..Default::default()
        }),
        b: Some(pb::ProgramRevision {
            number: 2,
            ..Default::default()
        }),
        blocks_changed: 1,
        hunks: vec![pb::DiffHunk {
            a_line: 3,
            b_line: 3,
            lines: vec![
                pb::DiffLine {
                    op: pb::diff_line::Op::Removed as i32,
                    text: "X10".into(),
                    ..Default::default()
                },
                pb::DiffLine {
                    op: pb::diff_line::Op::Added as i32,
                    text: "X12".into(),
                    ..Default::default()
                },
            ],
        }],
        ..Default::default()
    };
    let t = diff_text(&d);
    assert!(t.contains("--- O1 revision 1"), "{t}");
    assert!(t.contains("+++ O1 revision 2"), "{t}");
    assert!(t.contains("\n-X10\n+X12\n"), "{t}");
    assert!(t.contains("1 block(s) changed"), "{t}");
}

#[test]
fn audit_records_say_who_and_whether_the_roles_vouch_for_it() {
    let r = pb::HistoryRecord {
        unix_ms: 0,
        seq: 7,
        machine: "mill-1".into(),
        kind: pb::HistoryKind::Audit as i32,
        record: Some(pb::history_record::Record::Audit(pb::AuditRecord {
            action: "io.do".into(),
            target: "mill-1".into(),
            detail: "DO 0x07 mask 0xff".into(),
            origin: Some(pb::RequestOrigin {
                user: "alice".into(),
                via: "cli".into(),
            }),
            principal: "operator-1".into(),
            ok: true,
            ..Default::default()
        })),
    };
    let t = record_text(&r);
    assert!(t.contains("io.do mill-1 DO 0x07"), "{t}");
    assert!(t.contains("alice (cli) [operator-1]: ok"), "{t}");
    assert!(t.contains("#7"), "{t}");
}

#[test]
fn the_current_bucket_is_shared_over_the_time_that_has_passed() {
    // An hour's bucket ten minutes in: 5 reading, 4 idle, 1 unknown.
    let min = 60_000;
    let u = pb::Utilisation {
        machines: vec![pb::MachineUtilisation {
            machine: "mill-1".into(),
            buckets: vec![pb::UtilisationBucket {
                start_unix_ms: 0,
                end_unix_ms: 60 * min,
                reading_ms: 5 * min,
                idle_ms: 4 * min,
                unknown_ms: min,
                ..Default::default()
            }],
            ..Default::default()
        }],
        ..Default::default()
    };
    let text = utilisation_text(&u);
    let row = text.lines().find(|l| l.starts_with("mill-1")).unwrap();
    let cells: Vec<&str> = row.split_whitespace().collect();
    assert!(
        cells.contains(&"56%"),
        "reading 5 of 9 known minutes: {text}"
    );
    assert!(cells.contains(&"44%"), "idle 4 of 9: {text}");
    assert!(cells.contains(&"10%"), "unknown 1 of 10 passed: {text}");
}
