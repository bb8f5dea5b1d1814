use super::*;
use cellgate_core::history::{HistoryQuery, Store};

fn config() -> HistoryConfig {
    HistoryConfig {
        tag_values: 5,
        ..HistoryConfig::default()
    }
}

async fn open(dir: &Path, stop: &CancellationToken) -> (History, tokio::task::JoinHandle<()>) {
    History::open(dir, &config(), stop.clone()).await.unwrap()
}

fn query(store: Store, params: &[(&str, &str)]) -> HistoryQuery {
    let now = pb::now_ms() + 1000;
    HistoryQuery::parse(store, params.iter().copied(), |_| Err(String::new()), now).unwrap()
}

fn alarm(machine: &str, n: u32) -> Record {
    Record::Alarm(pb::AlarmEvent {
        machine: machine.to_string(),
        kind: pb::AlarmKind::CncAlarm as i32,
        alarm_number: format!("SR{n:04}"),
        ..Default::default()
    })
}

/// Waits until the writer committed everything recorded so far (a commit a second).
async fn flushed(h: &History, log: Log, n: usize, q: &[(&str, &str)]) -> pb::HistoryPage {
    let store = if log == Log::Audit {
        Store::Audit
    } else {
        Store::History
    };
    for _ in 0..100 {
        let page = h.query(log, query(store, q)).await.unwrap();
        if page.records.len() >= n {
            return page;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("the records never reached the store");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn records_survive_a_restart_and_keep_their_order() {
    let dir = tempfile::tempdir().unwrap();
    let stop = CancellationToken::new();
    let (h, writer) = open(dir.path(), &stop).await;
    for i in 0..20 {
        h.event("m1", HistoryKind::Alarm, alarm("m1", 800 + i));
    }
    let page = flushed(&h, Log::History, 20, &[("kind", "alarm")]).await;
    assert_eq!(page.records.len(), 20);
    assert!(
        page.records
            .windows(2)
            .all(|w| w[0].seq < w[1].seq && w[0].unix_ms <= w[1].unix_ms)
    );
    stop.cancel();
    writer.await.unwrap();
    drop(h);

    let stop = CancellationToken::new();
    let (h, writer) = open(dir.path(), &stop).await;
    h.event("m1", HistoryKind::Alarm, alarm("m1", 999));
    let page = flushed(&h, Log::History, 21, &[("kind", "alarm")]).await;
    assert_eq!(page.records.len(), 21);
    // Numbering goes on from where it was: no number is reused.
    assert!(page.records[20].seq > page.records[19].seq);
    // The gateway's starts and its stop are there too.
    let g = h
        .query(Log::History, query(Store::History, &[("kind", "gateway")]))
        .await
        .unwrap();
    let events: Vec<i32> = g
        .records
        .iter()
        .filter_map(|r| match &r.record {
            Some(Record::Gateway(g)) => Some(g.event),
            _ => None,
        })
        .collect();
    use pb::gateway_record::Event;
    assert_eq!(
        events,
        [
            Event::Started as i32,
            Event::Stopped as i32,
            Event::Started as i32
        ]
    );
    stop.cancel();
    writer.await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queries_filter_by_machine_and_kind_and_page() {
    let dir = tempfile::tempdir().unwrap();
    let stop = CancellationToken::new();
    let (h, writer) = open(dir.path(), &stop).await;
    for i in 0..30 {
        let m = if i % 3 == 0 { "m1" } else { "m2" };
        h.event(m, HistoryKind::Alarm, alarm(m, i));
        h.event(
            m,
            HistoryKind::Link,
            Record::Link(pb::LinkState::Idle as i32),
        );
    }
    flushed(&h, Log::History, 60, &[("kind", "alarm,link")]).await;
    let m1 = h
        .query(Log::History, query(Store::History, &[("machine", "m1")]))
        .await
        .unwrap();
    assert_eq!(m1.records.len(), 20);
    assert!(m1.records.iter().all(|r| r.machine == "m1"));
    let m1_alarms = h
        .query(
            Log::History,
            query(Store::History, &[("machine", "m1"), ("kind", "alarm")]),
        )
        .await
        .unwrap();
    assert_eq!(m1_alarms.records.len(), 10);
    // Paging: 7 at a time through the 30 alarms, nothing twice, nothing left out.
    let mut seen = Vec::new();
    let mut after = String::new();
    loop {
        let mut p = vec![("kind", "alarm"), ("limit", "7")];
        if !after.is_empty() {
            p.push(("after", after.as_str()));
        }
        let page = h
            .query(Log::History, query(Store::History, &p))
            .await
            .unwrap();
        seen.extend(page.records.iter().map(|r| r.seq));
        if !page.more {
            break;
        }
        after = page.next_after.to_string();
    }
    assert_eq!(seen.len(), 30);
    let mut sorted = seen.clone();
    sorted.sort_unstable();
    sorted.dedup();
    assert_eq!(sorted, seen);
    // A record number the store does not have is an error, not an empty page.
    let e = h
        .query(Log::History, query(Store::History, &[("after", "999999")]))
        .await
        .unwrap_err();
    // Newest first, through the index (a kind) and in time order (no selector): the same
    // records in the reverse order, paged on from each page's last record.
    for selector in [vec![("kind", "alarm")], vec![]] {
        let all = h
            .query(Log::History, query(Store::History, &selector))
            .await
            .unwrap();
        let mut newest = Vec::new();
        let mut after = String::new();
        loop {
            let mut p = selector.clone();
            p.extend([("order", "newest"), ("limit", "7")]);
            if !after.is_empty() {
                p.push(("after", after.as_str()));
            }
            let page = h
                .query(Log::History, query(Store::History, &p))
                .await
                .unwrap();
            assert!(page.records.len() <= 7);
            newest.extend(page.records.iter().map(|r| r.seq));
            if !page.more {
                break;
            }
            after = page.next_after.to_string();
        }
        let mut oldest: Vec<u64> = all.records.iter().map(|r| r.seq).collect();
        oldest.reverse();
        assert_eq!(newest, oldest, "{selector:?}");
    }
    assert!(matches!(e, HistoryError::NoSuchRecord(999_999)), "{e}");
    stop.cancel();
    writer.await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tag_keeps_its_latest_values_only() {
    let dir = tempfile::tempdir().unwrap();
    let stop = CancellationToken::new();
    let (h, writer) = open(dir.path(), &stop).await;
    for v in 0..12 {
        h.event(
            "plc-1",
            HistoryKind::Tag,
            Record::Tag(pb::TagValue {
                plc: "plc-1".into(),
                name: "parts".into(),
                value: Some(f64::from(v)),
                ..Default::default()
            }),
        );
        // Another tag is not trimmed by this one's bound.
        if v < 3 {
            h.event(
                "plc-1",
                HistoryKind::Tag,
                Record::Tag(pb::TagValue {
                    plc: "plc-1".into(),
                    name: "door".into(),
                    value: Some(1.0),
                    ..Default::default()
                }),
            );
        }
    }
    let page = flushed(&h, Log::History, 5, &[("tag", "plc-1/parts")]).await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let page2 = h
        .query(
            Log::History,
            query(Store::History, &[("tag", "plc-1/parts")]),
        )
        .await
        .unwrap();
    let values: Vec<f64> = page2
        .records
        .iter()
        .filter_map(|r| match &r.record {
            Some(Record::Tag(t)) => t.value,
            _ => None,
        })
        .collect();
    assert_eq!(values, [7.0, 8.0, 9.0, 10.0, 11.0], "{page:?}");
    let door = h
        .query(
            Log::History,
            query(Store::History, &[("tag", "plc-1/door")]),
        )
        .await
        .unwrap();
    assert_eq!(door.records.len(), 3);
    stop.cancel();
    writer.await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn audit_records_are_a_log_of_their_own() {
    let dir = tempfile::tempdir().unwrap();
    let stop = CancellationToken::new();
    let (h, writer) = open(dir.path(), &stop).await;
    h.audit(
        "mill-1",
        pb::AuditRecord {
            action: "io.do".into(),
            ok: true,
            ..Default::default()
        },
    );
    let page = flushed(&h, Log::Audit, 1, &[]).await;
    assert_eq!(page.records[0].kind, HistoryKind::Audit as i32);
    let history = h
        .query(
            Log::History,
            query(Store::History, &[("machine", "mill-1")]),
        )
        .await
        .unwrap();
    assert!(history.records.is_empty());
    stop.cancel();
    writer.await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_damaged_store_is_moved_aside_and_a_new_one_started() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("history.redb"), b"not a database at all").unwrap();
    let stop = CancellationToken::new();
    let (h, writer) = open(dir.path(), &stop).await;
    let aside: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains("damaged"))
        .collect();
    assert_eq!(aside.len(), 1, "{aside:?}");
    h.event("m1", HistoryKind::Alarm, alarm("m1", 1));
    flushed(&h, Log::History, 1, &[("kind", "alarm")]).await;
    stop.cancel();
    writer.await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_disabled_history_records_nothing_and_says_so() {
    let h = History::disabled();
    h.event("m1", HistoryKind::Alarm, alarm("m1", 1));
    let e = h
        .query(Log::History, query(Store::History, &[]))
        .await
        .unwrap_err();
    assert!(matches!(e, HistoryError::Disabled));
    assert_eq!(e.code(), pb::ErrorCode::Unavailable);
}
