use super::*;

fn rules() -> FolderRules {
    FolderRules {
        extensions: vec!["nc".into(), "tap".into(), "txt".into()],
        settle_ms: 1000,
    }
}

fn stat(size: u64, modified_ms: u64) -> Stat {
    Stat { size, modified_ms }
}

#[test]
fn extensions_are_not_part_of_the_name() {
    let r = rules();
    assert_eq!(r.program_name("O5555.nc"), Ok("O5555"));
    assert_eq!(r.program_name("O5555.NC"), Ok("O5555"));
    assert_eq!(r.program_name("O5555.Tap"), Ok("O5555"));
    assert_eq!(r.program_name("O5555"), Ok("O5555"));
    // Only the last extension, only a listed one.
    assert_eq!(r.program_name("part.v2.nc"), Ok("part.v2"));
    assert_eq!(r.program_name("part.v2"), Ok("part.v2"));
    assert!(r.ends_in_extension("O5555.nc"));
    assert!(!r.ends_in_extension("O5555"));
    // A file that is all extension keeps its name.
    assert_eq!(r.strip(".nc"), ".nc");
}

#[test]
fn temporary_and_hidden_files_are_passed_over() {
    let r = rules();
    for f in [
        ".O5555.nc",
        "O5555.nc.tmp",
        "O5555.TMP",
        "~O5555.nc",
        "O5555.nc~",
        "O5555.nc.part",
        ".O5555.nc.swp",
    ] {
        assert_eq!(r.program_name(f), Err(Skip::Temporary), "{f}");
    }
    assert!(matches!(r.program_name("a b.nc"), Err(Skip::BadName(_))));
    assert!(matches!(r.program_name("-x.nc"), Err(Skip::BadName(_))));
}

#[test]
fn an_old_file_first_seen_is_due_at_once() {
    let mut s = Settle::new(1000);
    s.observe("O1", stat(10, 5_000), 60_000);
    assert_eq!(s.due(60_000), vec![("O1".to_string(), stat(10, 5_000))]);
    // Once per content.
    assert!(s.due(70_000).is_empty());
    assert_eq!(s.next_deadline(), None);
}

#[test]
fn a_growing_file_waits_until_it_is_still() {
    let mut s = Settle::new(1000);
    s.observe("O1", stat(10, 10_000), 10_000);
    assert!(s.due(10_500).is_empty());
    s.observe("O1", stat(20, 10_600), 10_600);
    assert!(s.due(11_500).is_empty(), "changed 900 ms ago");
    assert_eq!(s.next_deadline(), Some(11_600));
    s.observe("O1", stat(20, 10_600), 11_600);
    assert_eq!(s.due(11_600), vec![("O1".to_string(), stat(20, 10_600))]);
}

#[test]
fn a_file_open_for_writing_waits_for_its_close() {
    let mut s = Settle::new(1000);
    s.observe("O1", stat(10, 1_000), 50_000);
    s.writing("O1", 50_000);
    assert!(s.due(90_000).is_empty(), "still open");
    assert_eq!(s.next_deadline(), None);
    assert!(s.is_writing("O1"));
    s.closed("O1");
    assert_eq!(s.due(90_000).len(), 1);
}

#[test]
fn an_empty_file_is_never_due() {
    let mut s = Settle::new(1000);
    s.observe("O1", stat(0, 1_000), 50_000);
    assert!(s.due(90_000).is_empty());
    assert_eq!(s.waiting(), 1);
}

#[test]
fn a_file_modified_in_the_future_waits_its_settle() {
    // A share's clock ahead of ours: still for `settle` by our clock first.
    let mut s = Settle::new(1000);
    s.observe("O1", stat(10, 99_000), 50_000);
    assert!(s.due(50_500).is_empty());
    assert_eq!(s.next_deadline(), Some(51_000));
    assert_eq!(s.due(51_000).len(), 1);
}

#[test]
fn a_changed_file_is_due_again_and_a_failed_take_retries() {
    let mut s = Settle::new(1000);
    s.observe("O1", stat(10, 1_000), 5_000);
    assert_eq!(s.due(5_000).len(), 1);
    s.observe("O1", stat(11, 6_000), 6_000);
    assert_eq!(s.due(7_000).len(), 1);
    s.retry("O1", 7_000);
    assert!(s.due(7_500).is_empty());
    assert_eq!(s.due(8_000).len(), 1);
    s.gone("O1");
    assert_eq!(s.waiting(), 0);
}
