//! The library's revisions, compare and release, and the cell's history, audit trail and
//! utilisation, as a client meets them on the bus.

use crate::common;

use std::time::Duration;

use cellgate::bus::keys::MachineLeaf;
use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use common::bus::{RunningCell, Sub, follow, get, get_err, get_one};
use prost::Message;
use zenoh::bytes::ZBytes;

const MILL: &str = "mill-1";
/// Takes released revisions only.
const STRICT: &str = "mill-3";

fn cell_config(port: u16, dir: &std::path::Path) -> CellConfig {
    let text = format!(
        r#"
cell = "records"
[bus]
listen = ["tcp/127.0.0.1:{port}"]
[programs]
dir = {:?}
keep_revisions = 3
[[machines]]
name = "mill-1"
protocol = "a"
part_counter = "plc-1/parts"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
[[machines]]
name = "mill-3"
protocol = "a"
accept = "released"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
[[plcs]]
name = "plc-1"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
[[plcs.tags]]
name = "parts"
module = "D"
address = 0
type = "u16"
poll_ms = 100
history = true
[[plcs.sim.tick]]
module = "D"
address = 0
every_ms = 200
add = 1
"#,
        dir.join("programs")
    );
    CellConfig::from_toml_str(&text, "records cell").unwrap_or_else(|e| panic!("{e}"))
}

fn origin(user: &str) -> ZBytes {
    ZBytes::from(
        pb::RequestOrigin {
            user: user.to_string(),
            via: "test".to_string(),
        }
        .encode_to_vec(),
    )
}

/// A get with a payload and the sender's `RequestOrigin` attached.
async fn ask<M: Message + Default>(
    cell: &RunningCell,
    key: &str,
    payload: Vec<u8>,
    user: &str,
) -> Result<M, pb::ErrorReply> {
    let replies = cell
        .client
        .get(key)
        .payload(payload)
        .attachment(origin(user))
        .timeout(Duration::from_secs(30))
        .await
        .unwrap();
    let reply = replies.recv_async().await.expect("an answer");
    match reply.result() {
        Ok(s) => Ok(M::decode(s.payload().to_bytes().as_ref()).unwrap()),
        Err(e) => Err(pb::ErrorReply::decode(e.payload().to_bytes().as_ref()).unwrap()),
    }
}

async fn store(cell: &RunningCell, name: &str, bytes: &[u8], user: &str) -> pb::ProgramInfo {
    let w = pb::ProgramWrite {
        op: Some(pb::program_write::Op::Store(bytes.to_vec())),
        comment: format!("stored by {user}"),
    };
    ask(
        cell,
        &cell.keys.program_write(name),
        w.encode_to_vec(),
        user,
    )
    .await
    .unwrap_or_else(|e| panic!("{e:?}"))
}

async fn release(
    cell: &RunningCell,
    name: &str,
    revision: &str,
    state: pb::RevisionState,
    user: &str,
) -> Result<pb::ProgramRevision, pb::ErrorReply> {
    let r = pb::ProgramRelease {
        revision: revision.to_string(),
        state: state as i32,
        comment: "checked on the machine".to_string(),
    };
    ask(
        cell,
        &cell.keys.program_release(name),
        r.encode_to_vec(),
        user,
    )
    .await
}

/// Waits for the history (or audit) to hold what `check` looks for: records are written
/// once a second.
async fn records(
    cell: &RunningCell,
    key: &str,
    check: impl Fn(&pb::HistoryPage) -> bool,
) -> pb::HistoryPage {
    for _ in 0..100 {
        let page: pb::HistoryPage = get_one(&cell.client, key, None).await;
        if check(&page) {
            return page;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let page: pb::HistoryPage = get_one(&cell.client, key, None).await;
    panic!("the records never showed: {page:#?}");
}

const V1: &[u8] = b"%\nO100(FLANGE)\nN10G00X0Y0\nN20G01X10F100\nN30M30\n%\n";
const V2: &[u8] = b"%\nO100(FLANGE REV B)\nN100 G00 X0 Y0\nN200 G01 X12 F100\nN300 M30\n%\n";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn revisions_are_kept_compared_and_read_back() {
    let cell = RunningCell::start(cell_config, false).await;
    let one = store(&cell, "O100", V1, "alice").await;
    assert_eq!(one.latest.as_ref().unwrap().number, 1);
    let two = store(&cell, "O100", V2, "bob").await;
    let r2 = two.latest.unwrap();
    assert_eq!(r2.number, 2);
    assert_eq!(r2.by.unwrap().user, "bob");
    assert_eq!(r2.comment, "stored by bob");

    let revs: pb::ProgramRevisions =
        get_one(&cell.client, &cell.keys.program_revisions("O100"), None).await;
    let numbers: Vec<u32> = revs.revisions.iter().map(|r| r.number).collect();
    assert_eq!(numbers, [2, 1]);

    // Any revision by number or hash.
    let old = get(&cell.client, &cell.keys.program_revision("O100", "1"), None).await;
    assert_eq!(old[0].as_ref().unwrap().1, V1);
    let by_hash = get(
        &cell.client,
        &cell
            .keys
            .program_revision("O100", &revs.revisions[1].sha256),
        None,
    )
    .await;
    assert_eq!(by_hash[0].as_ref().unwrap().1, V1);
    let e = get_err(&cell.client, &cell.keys.program_revision("O100", "7"), None).await;
    assert_eq!(e.code(), pb::ErrorCode::NotFound);

    // The latest against the one before, as it is: every block between the `%`s differs.
    let d: pb::ProgramDiff = get_one(&cell.client, &cell.keys.program_diff("O100"), None).await;
    assert!(!d.same);
    assert_eq!((d.a.unwrap().number, d.b.unwrap().number), (1, 2));
    assert_eq!(d.blocks_changed, 4, "{:?}", d.hunks);
    // Renumbered and spaced out, but only X10 → X12 and the comment changed.
    let key = format!(
        "{}?a=1;b=2;ignore=sequence,blanks",
        cell.keys.program_diff("O100")
    );
    let d: pb::ProgramDiff = get_one(&cell.client, &key, None).await;
    assert_eq!(d.blocks_changed, 2, "{:#?}", d.hunks);
    let key = format!(
        "{}?ignore=sequence,blanks,comments",
        cell.keys.program_diff("O100")
    );
    let d: pb::ProgramDiff = get_one(&cell.client, &key, None).await;
    assert_eq!(
        (d.blocks_changed, d.blocks_added, d.blocks_removed),
        (1, 0, 0)
    );
    let changed: Vec<&str> = d.hunks[0]
        .lines
        .iter()
        .filter(|l| l.changed)
        .map(|l| l.text.as_str())
        .collect();
    assert_eq!(changed, ["N20G01X10F100", "N200 G01 X12 F100"]);

    // Bad options and programs that are not text get clear refusals.
    let e = get_err(
        &cell.client,
        &format!("{}?ignore=spaces", cell.keys.program_diff("O100")),
        None,
    )
    .await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);
    assert!(e.message.contains("spaces"), "{}", e.message);
    store(&cell, "BIN", b"%\x00\x01\x02%", "alice").await;
    store(&cell, "BIN", b"%\x00\x01\x03%", "alice").await;
    let e = get_err(&cell.client, &cell.keys.program_diff("BIN"), None).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);
    assert!(e.message.contains("not NC program text"), "{}", e.message);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_machine_that_takes_released_revisions_refuses_a_draft_and_jobs_record_theirs() {
    let cell = RunningCell::start(cell_config, false).await;
    store(&cell, "O200", b"%\nO200\nG00X1\n%\n", "alice").await;
    let submit = |machine: &str, revision: &str| {
        pb::JobRequest {
            program: Some(pb::job_request::Program::Library("O200".into())),
            revision: revision.to_string(),
            name: machine.to_string(),
            ..Default::default()
        }
        .encode_to_vec()
    };
    let key = cell.keys.leaf(STRICT, MachineLeaf::Submit);
    let e = ask::<pb::JobAccepted>(&cell, &key, submit(STRICT, ""), "mes")
        .await
        .unwrap_err();
    assert_eq!(e.code(), pb::ErrorCode::NotReleased);
    assert!(e.message.contains("revision 1 is a draft"), "{}", e.message);
    let queue: pb::JobQueue = get_one(
        &cell.client,
        &cell.keys.leaf(STRICT, MachineLeaf::Job),
        None,
    )
    .await;
    assert!(queue.active.is_none() && queue.waiting.is_empty());

    // Released: taken, and the job says which revision it sends.
    let r = release(&cell, "O200", "1", pb::RevisionState::Released, "qa")
        .await
        .unwrap();
    assert_eq!(r.state(), pb::RevisionState::Released);
    assert_eq!(r.state_by.unwrap().user, "qa");
    store(&cell, "O200", b"%\nO200\nG00X2\n%\n", "alice").await;
    // The latest (2) is a draft; revision 1 by number is released.
    let e = ask::<pb::JobAccepted>(&cell, &key, submit(STRICT, ""), "mes")
        .await
        .unwrap_err();
    assert!(
        e.message.contains("latest released revision is 1"),
        "{}",
        e.message
    );
    let events: Sub = cell.subscribe(cell.keys.job_events(STRICT, "*")).await;
    let accepted: pb::JobAccepted = ask(&cell, &key, submit(STRICT, "1"), "mes").await.unwrap();
    let program = accepted.program.clone().unwrap();
    assert_eq!((program.library.as_str(), program.revision), ("O200", 1));
    let ends = follow(&events, &accepted.job_id, Duration::from_secs(60)).await;
    assert!(
        matches!(ends.last(), Some(pb::job_event::Kind::Completed(_))),
        "{ends:?}"
    );
    let sent = cell.board(STRICT).programs();
    // The CNC takes the program through its EOR.
    assert_eq!(sent.last().unwrap().data.as_ref(), b"%\nO200\nG00X1\n%");

    // The history has the job with its revision and who submitted it.
    let page = records(&cell, &format!("{}?kind=job", cell.keys.history()), |p| {
        !p.records.is_empty()
    })
    .await;
    let Some(pb::history_record::Record::Job(j)) = &page.records[0].record else {
        panic!("{page:?}");
    };
    let origin = j.origin.clone().unwrap();
    assert_eq!(origin.program.unwrap().revision, 1);
    assert_eq!(origin.submitted_by.unwrap().user, "mes");
    assert_eq!(j.outcome(), pb::JobOutcome::Completed);
    assert!(origin.started_unix_ms >= origin.queued_unix_ms);
    assert!(j.ended_unix_ms >= origin.started_unix_ms);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_locked_revision_holds_until_it_is_unlocked() {
    let cell = RunningCell::start(cell_config, false).await;
    store(&cell, "O300", b"%\nO300\n%\n", "alice").await;
    release(&cell, "O300", "", pb::RevisionState::Locked, "qa")
        .await
        .unwrap();
    let w = pb::ProgramWrite {
        op: Some(pb::program_write::Op::Store(b"%\nO300 NEW\n%\n".to_vec())),
        comment: String::new(),
    };
    let e = ask::<pb::ProgramInfo>(
        &cell,
        &cell.keys.program_write("O300"),
        w.encode_to_vec(),
        "alice",
    )
    .await
    .unwrap_err();
    assert_eq!(e.code(), pb::ErrorCode::Locked);
    let e = release(&cell, "O300", "9", pb::RevisionState::Released, "qa")
        .await
        .unwrap_err();
    assert_eq!(e.code(), pb::ErrorCode::NotFound);
    // Unlocked, it can be replaced again.
    release(&cell, "O300", "", pb::RevisionState::Draft, "qa")
        .await
        .unwrap();
    store(&cell, "O300", b"%\nO300 NEW\n%\n", "alice").await;
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_audit_records_every_write_with_who_asked_and_what_came_of_it() {
    let cell = RunningCell::start(cell_config, false).await;
    store(&cell, "O400", b"%\nO400\n%\n", "alice").await;
    // A DO put, a refused submit (no program), a tag write.
    cell.client
        .put(
            cell.keys.leaf(MILL, MachineLeaf::Do),
            pb::DoCommand {
                value: 5,
                mask: None,
            }
            .encode_to_vec(),
        )
        .attachment(origin("operator"))
        .await
        .unwrap();
    let e = ask::<pb::JobAccepted>(
        &cell,
        &cell.keys.leaf(MILL, MachineLeaf::Submit),
        pb::JobRequest::default().encode_to_vec(),
        "mes",
    )
    .await
    .unwrap_err();
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);
    let page = records(&cell, &cell.keys.audit(), |p| p.records.len() >= 3).await;
    let audits: Vec<pb::AuditRecord> = page
        .records
        .iter()
        .filter_map(|r| match &r.record {
            Some(pb::history_record::Record::Audit(a)) => Some(a.clone()),
            _ => None,
        })
        .collect();
    let find = |action: &str| {
        audits
            .iter()
            .find(|a| a.action == action)
            .unwrap_or_else(|| panic!("no {action} in {audits:#?}"))
    };
    let stored = find("program.store");
    assert!(stored.ok);
    assert_eq!(stored.origin.as_ref().unwrap().user, "alice");
    assert_eq!(stored.target, "O400");
    assert!(stored.detail.contains("revision 1"), "{}", stored.detail);
    let out = find("io.do");
    assert_eq!(out.origin.as_ref().unwrap().user, "operator");
    assert!(out.detail.contains("0x05"), "{}", out.detail);
    let refused = find("job.submit");
    assert!(!refused.ok);
    assert_eq!(refused.code(), pb::ErrorCode::InvalidRequest);
    assert_eq!(refused.origin.as_ref().unwrap().user, "mes");
    // No roles here: none are named, and no principal is claimed for anyone.
    assert!(refused.roles.is_empty() && refused.principal.is_empty());
    // The audit is a log of its own, by machine too.
    let by_machine = records(
        &cell,
        &format!("{}?machine={MILL}", cell.keys.audit()),
        |p| !p.records.is_empty(),
    )
    .await;
    assert!(by_machine.records.iter().all(|r| r.machine == MILL));
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_consoles_summary_note_keeps_the_count_it_stands_for() {
    let cell = RunningCell::start(cell_config, false).await;
    // What a console sends when a minute of refusals is over: one record standing for many.
    let note = pb::AuditRecord {
        action: "console.job.submit".to_string(),
        detail: "599 more like it in the minute after the first".to_string(),
        origin: Some(pb::RequestOrigin {
            user: "olga".to_string(),
            via: "console".to_string(),
        }),
        count: 599,
        error: "olga may not submit jobs".to_string(),
        ..Default::default()
    };
    ask::<pb::AuditRecord>(
        &cell,
        &cell.keys.audit_note(),
        note.encode_to_vec(),
        "console",
    )
    .await
    .unwrap_or_else(|e| panic!("{e:?}"));
    let page = records(&cell, &cell.keys.audit(), |p| {
        p.records.iter().any(|r| {
            matches!(&r.record, Some(pb::history_record::Record::Audit(a)) if a.action == "audit.note")
        })
    })
    .await;
    let kept = page
        .records
        .iter()
        .find_map(|r| match &r.record {
            Some(pb::history_record::Record::Audit(a)) if a.action == "audit.note" => Some(a),
            _ => None,
        })
        .unwrap();
    assert!(kept.detail.contains("599 more"), "{kept:?}");
    assert_eq!(kept.count, 599, "the count its text speaks of: {kept:?}");
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_audit_says_the_values_a_control_and_a_memory_write_set() {
    let cell = RunningCell::start(cell_config, false).await;
    let _: pb::SimState = ask(
        &cell,
        &cell.keys.sim(MILL, cellgate::bus::keys::SimLeaf::Di),
        pb::SimDi { value: 0x81 }.encode_to_vec(),
        "tester",
    )
    .await
    .unwrap_or_else(|e| panic!("{e:?}"));
    let _: pb::PlcWritten = ask(
        &cell,
        &cell.keys.plc_mem_write("plc-1", 0, "D", Some(4)),
        pb::PlcWrite {
            words: vec![7, 0x1234],
            clear: false,
        }
        .encode_to_vec(),
        "tester",
    )
    .await
    .unwrap_or_else(|e| panic!("{e:?}"));
    let page = records(&cell, &cell.keys.audit(), |p| p.records.len() >= 2).await;
    let detail = |action: &str| {
        page.records
            .iter()
            .find_map(|r| match &r.record {
                Some(pb::history_record::Record::Audit(a)) if a.action == action => {
                    Some(a.detail.clone())
                }
                _ => None,
            })
            .unwrap_or_else(|| panic!("no {action} in {page:#?}"))
    };
    assert_eq!(detail("sim.di"), "DI 0x81");
    assert_eq!(detail("plc.mem.write"), "2 word(s): 0x0007 0x1234");
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn history_is_read_by_time_range_kind_machine_and_tag() {
    let cell = RunningCell::start(cell_config, false).await;
    // The link came up: its state changes are there, for mill-1 only when asked.
    let page = records(
        &cell,
        &format!("{}?machine={MILL};kind=link,cnc", cell.keys.history()),
        |p| p.records.len() >= 2,
    )
    .await;
    assert!(page.records.iter().all(|r| r.machine == MILL));
    assert!(page.records.windows(2).all(|w| w[0].seq < w[1].seq));
    // A range in the past holds none of it.
    let past = get_one::<pb::HistoryPage>(
        &cell.client,
        &format!("{}?_time=[..now(-1h)];machine={MILL}", cell.keys.history()),
        None,
    )
    .await;
    assert!(past.records.is_empty(), "{past:?}");
    // Tag values come when asked for, and only the tags that keep history.
    let tags = records(
        &cell,
        &format!("{}?tag=plc-1/parts;_time=[now(-5m)..]", cell.keys.history()),
        |p| p.records.len() >= 3,
    )
    .await;
    assert!(
        tags.records
            .iter()
            .all(|r| r.kind() == pb::HistoryKind::Tag)
    );
    let plain: pb::HistoryPage = get_one(&cell.client, &cell.keys.history(), None).await;
    assert!(
        plain
            .records
            .iter()
            .all(|r| r.kind() != pb::HistoryKind::Tag)
    );
    // Paging goes on where it stopped.
    let first: pb::HistoryPage = get_one(
        &cell.client,
        &format!("{}?tag=plc-1/parts;limit=2", cell.keys.history()),
        None,
    )
    .await;
    assert!(first.more);
    let next: pb::HistoryPage = get_one(
        &cell.client,
        &format!(
            "{}?tag=plc-1/parts;limit=2;after={}",
            cell.keys.history(),
            first.next_after
        ),
        None,
    )
    .await;
    assert!(next.records[0].seq > first.records[1].seq);
    // Newest first, and on to older records from the page's last.
    let newest: pb::HistoryPage = get_one(
        &cell.client,
        &format!(
            "{}?tag=plc-1/parts;limit=2;order=newest",
            cell.keys.history()
        ),
        None,
    )
    .await;
    assert!(newest.more && newest.records[0].seq > newest.records[1].seq);
    assert!(newest.records[0].seq >= next.records[1].seq);
    let older: pb::HistoryPage = get_one(
        &cell.client,
        &format!(
            "{}?tag=plc-1/parts;limit=2;order=newest;after={}",
            cell.keys.history(),
            newest.next_after
        ),
        None,
    )
    .await;
    assert!(older.records[0].seq < newest.records[1].seq, "{older:?}");
    // What cannot be read is refused, naming it.
    for (params, needle) in [
        ("_time=[yesterday..]", "_time"),
        ("kind=jobs", "\"jobs\" is not a kind"),
        ("limit=0", "limit"),
        ("order=latest", "oldest or newest"),
        ("colour=red", "unknown parameter \"colour\""),
    ] {
        let e = get_err(
            &cell.client,
            &format!("{}?{params}", cell.keys.history()),
            None,
        )
        .await;
        assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{params}");
        assert!(e.message.contains(needle), "{params}: {}", e.message);
    }
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn utilisation_shares_the_time_and_counts_parts() {
    let cell = RunningCell::start(cell_config, false).await;
    let (job, events) = cell
        .submit(
            MILL,
            &[b"%\nO1\n".as_slice(), &[b'X'; 3000], b"\n%\n"].concat(),
        )
        .await;
    follow(&events, &job, Duration::from_secs(60)).await;
    // Parts counted while the link ran; wait for a few commits.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let key = format!(
        "{}?_time=[now(-10m)..];machine={MILL}",
        cell.keys.utilisation()
    );
    let u = {
        let mut u: pb::Utilisation = get_one(&cell.client, &key, None).await;
        for _ in 0..50 {
            let b = &u.machines[0].buckets;
            if b.iter().map(|b| b.reading_ms).sum::<u64>() > 0
                && b.iter().filter_map(|b| b.parts).sum::<f64>() > 0.0
            {
                break;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
            u = get_one(&cell.client, &key, None).await;
        }
        u
    };
    assert_eq!(u.machines.len(), 1);
    let m = &u.machines[0];
    assert_eq!(m.part_counter, "plc-1/parts");
    let sum = |f: fn(&pb::UtilisationBucket) -> u64| m.buckets.iter().map(f).sum::<u64>();
    assert!(sum(|b| b.reading_ms) > 0, "{m:#?}");
    assert!(sum(|b| b.idle_ms) > 0, "{m:#?}");
    assert_eq!(
        m.buckets.iter().map(|b| b.jobs_completed).sum::<u32>(),
        1,
        "{m:#?}"
    );
    assert!(m.buckets.iter().filter_map(|b| b.parts).sum::<f64>() > 0.0);
    // Every bucket adds up to its length, up to now.
    for b in &m.buckets {
        let total = b.reading_ms
            + b.idle_ms
            + b.alarm_ms
            + b.reset_ms
            + b.punching_ms
            + b.link_down_ms
            + b.unknown_ms;
        assert!(total <= b.end_unix_ms - b.start_unix_ms, "{b:?}");
    }
    let e = get_err(
        &cell.client,
        &format!("{}?machine=nosuch", cell.keys.utilisation()),
        None,
    )
    .await;
    assert_eq!(e.code(), pb::ErrorCode::UnknownMachine);
    let e = get_err(
        &cell.client,
        &format!("{}?_time=[now(-200d)..]", cell.keys.utilisation()),
        None,
    )
    .await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_put_or_delete_on_a_read_key_is_logged_counted_and_audited_never_silent() {
    use cellgate::bus::route_misdirected::METRIC;
    use cellgate::telemetry::metrics::events;
    let cell = RunningCell::start(cell_config, false).await;
    let program_before = events(METRIC, &[("key", "program")]);
    let tag_before = events(METRIC, &[("key", "plc.tag")]);
    // A client of the old contract: a put of a program on its read key, a delete on a tag's.
    cell.client
        .put(cell.keys.program("O777"), V1.to_vec())
        .attachment(origin("mallory"))
        .await
        .unwrap();
    cell.client
        .delete(cell.keys.plc_tag("plc-1", "parts"))
        .await
        .unwrap();
    common::bus::eventually("both are counted", || {
        events(METRIC, &[("key", "program")]) > program_before
            && events(METRIC, &[("key", "plc.tag")]) > tag_before
    })
    .await;
    let misdirected = |p: &pb::HistoryPage, key: &str| {
        p.records.iter().find_map(|r| match &r.record {
            Some(pb::history_record::Record::Audit(a))
                if a.action == "bus.misdirected" && a.target == key =>
            {
                Some(a.clone())
            }
            _ => None,
        })
    };
    let key = cell.keys.program("O777");
    let page = records(&cell, &cell.keys.audit(), |p| {
        misdirected(p, &key).is_some()
    })
    .await;
    let a = misdirected(&page, &key).unwrap();
    assert!(!a.ok);
    assert_eq!(a.code, pb::ErrorCode::InvalidRequest as i32);
    assert!(a.error.contains(&cell.keys.program_write("O777")), "{a:?}");
    assert_eq!(a.origin.unwrap().user, "mallory");
    // And nothing was stored.
    let e = get_err(&cell.client, &key, None).await;
    assert_eq!(e.code(), pb::ErrorCode::NotFound);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_question_about_a_name_the_cell_lacks_is_refused_not_answered_empty() {
    let cell = RunningCell::start(cell_config, false).await;
    let history = cell.keys.history();
    let audit = cell.keys.audit();
    for (key, code) in [
        (
            format!("{history}?machine=mill-9"),
            pb::ErrorCode::UnknownMachine,
        ),
        (
            format!("{audit}?machine=mill-9"),
            pb::ErrorCode::UnknownMachine,
        ),
        (format!("{history}?tag=plc-1/nope"), pb::ErrorCode::NotFound),
    ] {
        let e = get_err(&cell.client, &key, None).await;
        assert_eq!(e.code(), code, "{key}: {}", e.message);
        assert!(e.message.contains("it has: "), "{}", e.message);
    }
    // Known names, a PLC's among them, are answered.
    for key in [
        format!("{history}?machine={MILL}"),
        format!("{history}?machine=plc-1"),
        format!("{history}?tag=plc-1/parts"),
    ] {
        let _: pb::HistoryPage = get_one(&cell.client, &key, None).await;
    }
    cell.stop().await;
}
