use super::*;

fn refused(user: &str, action: &str, target: &str) -> pb::AuditRecord {
    pb::AuditRecord {
        action: action.to_string(),
        target: target.to_string(),
        origin: Some(pb::RequestOrigin {
            user: user.to_string(),
            via: "console".to_string(),
        }),
        code: pb::ErrorCode::NotPermitted as i32,
        error: "your roles do not allow program.write".to_string(),
        ..Default::default()
    }
}

const T0: u64 = 1_700_000_000_000 - 1_700_000_000_000 % WINDOW_MS;

#[test]
fn a_flood_of_one_kind_is_the_first_at_once_and_one_count_after_the_minute() {
    let mut r = Refusals::default();
    let first = r.refuse("", refused("vera", "program.store", "X0"), T0 + 5);
    assert_eq!(first.len(), 1, "the first is recorded at once");
    assert_eq!(first[0].1.target, "X0");
    assert_eq!(first[0].1.count, 1);
    for i in 1..300 {
        assert!(
            r.refuse(
                "",
                refused("vera", "program.store", &format!("X{i}")),
                T0 + 10 + i
            )
            .is_empty()
        );
    }
    assert_eq!(r.deadline(), Some(T0 + WINDOW_MS));
    assert!(
        r.flush(T0 + WINDOW_MS - 1).is_empty(),
        "not before the minute is over"
    );
    let summary = r.flush(T0 + WINDOW_MS);
    assert_eq!(summary.len(), 1);
    let s = &summary[0].1;
    assert_eq!(s.count, 299);
    assert_eq!(s.action, "program.store");
    assert_eq!(s.origin.as_ref().unwrap().user, "vera");
    assert!(s.detail.starts_with("299 more like it"), "{}", s.detail);
    assert!(s.detail.contains("X1"), "{}", s.detail);
    assert_eq!(r.deadline(), None);
}

#[test]
fn kinds_are_apart_by_sender_action_and_code_and_bounded() {
    let mut r = Refusals::default();
    assert_eq!(
        r.refuse("", refused("vera", "program.store", "a"), T0)
            .len(),
        1
    );
    assert_eq!(r.refuse("", refused("vera", "io.do", "a"), T0).len(), 1);
    assert_eq!(r.refuse("", refused("olga", "io.do", "a"), T0).len(), 1);
    assert_eq!(
        r.refuse("mill-1", refused("olga", "io.do", "a"), T0).len(),
        1
    );
    let mut other = refused("olga", "io.do", "a");
    other.code = pb::ErrorCode::InvalidRequest as i32;
    assert_eq!(r.refuse("mill-1", other, T0).len(), 1);
    // A sender that claims a new name each time: past the bound, one kind of many.
    let mut written = 5;
    for i in 0..1000 {
        written += r
            .refuse("", refused(&format!("u{i}"), "io.do", "a"), T0 + 1)
            .len();
    }
    assert_eq!(written, MAX_KINDS);
    let summary = r.flush(T0 + WINDOW_MS);
    assert_eq!(summary.len(), 1);
    assert_eq!(summary[0].1.action, "(many)");
    assert_eq!(summary[0].1.count, 1000 - (MAX_KINDS as u32 - 5));
}

#[test]
fn a_new_minute_hands_out_the_last_ones_summaries_first() {
    let mut r = Refusals::default();
    r.refuse("", refused("vera", "io.do", "a"), T0);
    r.refuse("", refused("vera", "io.do", "b"), T0 + 1);
    let out = r.refuse("", refused("vera", "io.do", "c"), T0 + WINDOW_MS + 3);
    assert_eq!(out.len(), 2);
    assert_eq!(out[0].1.count, 1);
    assert!(out[0].1.detail.starts_with("1 more"));
    assert_eq!(out[1].1.target, "c");
}
