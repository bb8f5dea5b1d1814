//! The DNC folder on a running gateway, with real files: programs posted into the library's
//! folder (whole, renamed into place, written slowly, edited, deleted, locked, two files of
//! one name), a machine's drop folder queuing its files as jobs, and the receive folder.

use crate::common;

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use cellgate::bus::keys::MachineLeaf;
use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;
use common::bus::{RunningCell, Sub, follow, get, get_err, get_one};
use prost::Message;

fn cell_config(port: u16, dir: &Path) -> CellConfig {
    let text = format!(
        r#"
cell = "folder"
[bus]
listen = ["tcp/127.0.0.1:{port}"]
[programs]
dir = {:?}
settle_ms = 300
[[machines]]
name = "mill-1"
protocol = "a"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
sim = {{ consume_rate = 4000 }}
drop_dir = {:?}
[[machines]]
name = "lathe-1"
protocol = "b"
code = "iso"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
receive_dir = {:?}
"#,
        dir.join("programs"),
        dir.join("drop-mill-1"),
        dir.join("received-lathe-1"),
    );
    CellConfig::from_toml_str(&text, "folder cell").unwrap_or_else(|e| panic!("{e}"))
}

pub(crate) fn programs(cell: &RunningCell) -> PathBuf {
    cell.dir.path().join("programs")
}

/// What the library said: a change on `…/NAME/changed` (stored or removed), or a folder's
/// refusal on `…/@events`.
#[derive(Debug)]
pub(crate) struct Said {
    pub(crate) kind: &'static str,
    pub(crate) name: String,
    pub(crate) file: String,
    pub(crate) revision: u32,
    pub(crate) size: u64,
    pub(crate) code: pb::ErrorCode,
    pub(crate) error: String,
    pub(crate) by: Option<pb::RequestOrigin>,
}

/// Both of the library's publications, as one stream.
pub(crate) struct Library {
    changed: Sub,
    events: Sub,
}

impl Library {
    pub(crate) async fn follow(cell: &RunningCell) -> Library {
        Library {
            changed: cell.subscribe(cell.keys.program_changed("*")).await,
            events: cell.subscribe(cell.keys.program_events()).await,
        }
    }

    /// The next thing said, within 10 s.
    pub(crate) async fn next(&self) -> Said {
        let wait = async {
            tokio::select! {
                s = self.changed.recv_async() => {
                    let s = s.unwrap();
                    let info = pb::ProgramInfo::decode(s.payload().to_bytes().as_ref()).unwrap();
                    let by = s.attachment().map(|a| {
                        pb::RequestOrigin::decode(a.to_bytes().as_ref()).unwrap()
                    });
                    let latest = info.latest.clone().unwrap_or_default();
                    Said {
                        kind: if latest.removed { "removed" } else { "stored" },
                        name: info.name,
                        file: info.file,
                        revision: latest.number,
                        size: latest.size,
                        code: pb::ErrorCode::Unspecified,
                        error: String::new(),
                        by,
                    }
                }
                s = self.events.recv_async() => {
                    let e = pb::LibraryEvent::decode(s.unwrap().payload().to_bytes().as_ref()).unwrap();
                    Said {
                        kind: match e.kind() {
                            pb::LibraryEventKind::Refused => "refused",
                            _ => "folder",
                        },
                        code: e.code(),
                        name: e.name,
                        file: e.file,
                        revision: 0,
                        size: 0,
                        error: e.error,
                        by: e.by,
                    }
                }
            }
        };
        tokio::time::timeout(Duration::from_secs(10), wait)
            .await
            .expect("the library says something within 10 s")
    }

    /// Nothing said for `ms`.
    pub(crate) async fn quiet(&self, ms: u64) {
        if let Ok(said) = tokio::time::timeout(Duration::from_millis(ms), self.next()).await {
            panic!("unexpected: {said:?}");
        }
    }
}

pub(crate) fn program(o: u32, lines: usize) -> Vec<u8> {
    let mut p = format!("%\nO{o}\n").into_bytes();
    for i in 0..lines {
        p.extend_from_slice(format!("N{i} G01 X{i}.5 F100\n").as_bytes());
    }
    p.extend_from_slice(b"M30\n%\n");
    p
}

/// Reads the audit until `check` holds of its records (5 s at most).
pub(crate) async fn audit_until(cell: &RunningCell, check: impl Fn(&[pb::AuditRecord]) -> bool) {
    let mut records = Vec::new();
    for _ in 0..50 {
        let page: pb::HistoryPage = get_one(&cell.client, &cell.keys.audit(), None).await;
        records = page
            .records
            .into_iter()
            .filter_map(|r| match r.record {
                Some(pb::history_record::Record::Audit(a)) => Some(a),
                _ => None,
            })
            .collect();
        if check(&records) {
            return;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("the audit never showed it: {records:#?}");
}

/// The library's listing.
async fn listed(cell: &RunningCell) -> Vec<pb::ProgramInfo> {
    get(&cell.client, &cell.keys.any_program(), None)
        .await
        .into_iter()
        .filter_map(|r| r.ok())
        .map(|(_, bytes, _)| pb::ProgramInfo::decode(bytes.as_slice()).unwrap())
        .collect()
}

pub(crate) async fn read(cell: &RunningCell, name: &str) -> Vec<u8> {
    match get(&cell.client, &cell.keys.program(name), None)
        .await
        .as_slice()
    {
        [Ok((_, bytes, _))] => bytes.clone(),
        other => panic!("{name}: {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn programs_posted_into_the_folder_are_revisions_while_the_gateway_runs() {
    let cell = RunningCell::start(cell_config, false).await;
    let library = Library::follow(&cell).await;
    let dir = programs(&cell);

    // Posted whole: program O5555 (the extension is not part of the name), at once.
    let v1 = program(5555, 20);
    std::fs::write(dir.join("O5555.nc"), &v1).unwrap();
    let e = library.next().await;
    assert_eq!(e.kind, "stored");
    assert_eq!((e.name.as_str(), e.file.as_str()), ("O5555", "O5555.nc"));
    let by = e.by.unwrap();
    assert_eq!(by.via, "folder");
    // The file's owner: whoever runs the test wrote it.
    let me = nix::unistd::User::from_uid(nix::unistd::getuid())
        .unwrap()
        .unwrap();
    assert_eq!(by.user, me.name);
    assert_eq!(e.revision, 1);
    assert_eq!(read(&cell, "O5555").await, v1);

    // A job names it as the library has it.
    let events_m = cell.subscribe(cell.keys.job_events("mill-1", "*")).await;
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Library("O5555".to_string())),
        ..Default::default()
    };
    let accepted: pb::JobAccepted = get_one(
        &cell.client,
        &cell.keys.leaf("mill-1", MachineLeaf::Submit),
        Some(request.encode_to_vec()),
    )
    .await;
    let kinds = follow(&events_m, &accepted.job_id, Duration::from_secs(60)).await;
    assert!(
        matches!(kinds.last(), Some(Kind::Completed(_))),
        "{kinds:?}"
    );

    // Written to a temporary name and renamed into place: the temporary is never taken.
    let v2 = program(5556, 30);
    std::fs::write(dir.join("O5556.nc.tmp"), &v2).unwrap();
    tokio::time::sleep(Duration::from_millis(700)).await;
    std::fs::rename(dir.join("O5556.nc.tmp"), dir.join("O5556.nc")).unwrap();
    let e = library.next().await;
    assert_eq!((e.name.as_str(), e.kind), ("O5556", "stored"));
    assert_eq!(read(&cell, "O5556").await, v2);

    // Written in place over about 1.5 s: one revision, of the whole file.
    let v3 = program(5557, 2000);
    let mut f = std::fs::File::create(dir.join("O5557")).unwrap();
    for piece in v3.chunks(v3.len().div_ceil(10)) {
        f.write_all(piece).unwrap();
        f.flush().unwrap();
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
    drop(f);
    let e = library.next().await;
    assert_eq!((e.name.as_str(), e.kind), ("O5557", "stored"));
    assert_eq!(e.size, v3.len() as u64);
    assert_eq!(read(&cell, "O5557").await, v3);
    library.quiet(800).await;

    // Edited in place: while the writer has it open, the listing says the file is not yet
    // complete (its latest revision still the first); then the next revision, and the
    // listing gives the revision's size and the file, without the note.
    let v1b = program(5555, 25);
    let mut f = std::fs::File::create(dir.join("O5555.nc")).unwrap();
    f.write_all(&v1b[..v1b.len() / 2]).unwrap();
    f.flush().unwrap();
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        let o5555 = listed(&cell).await.into_iter().find(|p| p.name == "O5555");
        let note = o5555.map(|p| p.note).unwrap_or_default();
        if note.contains("not yet complete") && note.contains("O5555.nc") {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no note while the file is rewritten: {note:?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    f.write_all(&v1b[v1b.len() / 2..]).unwrap();
    drop(f);
    let e = library.next().await;
    assert_eq!((e.name.as_str(), e.revision), ("O5555", 2));
    assert_eq!(read(&cell, "O5555").await, v1b);
    let listed_now = listed(&cell).await;
    let o5555 = listed_now.iter().find(|p| p.name == "O5555").unwrap();
    assert_eq!(
        (o5555.size, o5555.file.as_str(), o5555.note.as_str()),
        (v1b.len() as u64, "O5555.nc", "")
    );

    // Deleted: the program is removed, its revisions kept.
    std::fs::remove_file(dir.join("O5556.nc")).unwrap();
    let e = library.next().await;
    assert_eq!((e.name.as_str(), e.kind), ("O5556", "removed"));
    let err = get_err(&cell.client, &cell.keys.program("O5556"), None).await;
    assert_eq!(err.code(), pb::ErrorCode::NotFound);
    let kept: pb::ProgramRevisions =
        get_one(&cell.client, &cell.keys.program_revisions("O5556"), None).await;
    assert!(kept.removed);

    // Locked: an edit is refused, the file left as written, the locked revision served.
    let release = pb::ProgramRelease {
        state: pb::RevisionState::Locked as i32,
        ..Default::default()
    };
    let _: pb::ProgramRevision = get_one(
        &cell.client,
        &cell.keys.program_release("O5555"),
        Some(release.encode_to_vec()),
    )
    .await;
    let edit = program(5555, 3);
    std::fs::write(dir.join("O5555.nc"), &edit).unwrap();
    let e = library.next().await;
    assert_eq!(e.kind, "refused", "{e:?}");
    assert_eq!(e.code, pb::ErrorCode::Locked);
    assert!(e.error.contains("locked"), "{}", e.error);
    assert_eq!(std::fs::read(dir.join("O5555.nc")).unwrap(), edit);
    assert_eq!(read(&cell, "O5555").await, v1b);

    // Two files of one name: neither taken, said.
    std::fs::write(dir.join("O5558.nc"), program(5558, 1)).unwrap();
    std::fs::write(dir.join("O5558.tap"), program(5558, 2)).unwrap();
    let e = library.next().await;
    assert_eq!((e.kind, e.code), ("refused", pb::ErrorCode::Conflict));
    let e = library.next().await;
    assert_eq!(e.code, pb::ErrorCode::Conflict);
    // One removed: the other is taken.
    std::fs::remove_file(dir.join("O5558.tap")).unwrap();
    let e = library.next().await;
    assert_eq!(
        (e.name.as_str(), e.file.as_str(), e.kind),
        ("O5558", "O5558.nc", "stored")
    );

    // Every one of them in the audit, the folder as the origin (the history is written a
    // moment later).
    audit_until(&cell, |records| {
        let from_folder: Vec<&pb::AuditRecord> = records
            .iter()
            .filter(|a| a.key.starts_with("folder:"))
            .collect();
        from_folder.iter().any(|a| {
            // A deletion names no user: the folder does not say who deleted it.
            a.action == "program.remove"
                && a.target == "O5556"
                && a.ok
                && a.origin
                    .as_ref()
                    .is_some_and(|o| o.user.is_empty() && o.via == "folder")
        }) && from_folder.iter().any(|a| {
            a.action == "program.store"
                && a.target == "O5555"
                && !a.ok
                && a.code == pb::ErrorCode::Locked as i32
        }) && from_folder
            .iter()
            .filter(|a| a.action == "program.store" && a.ok)
            .count()
            >= 5
    })
    .await;
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drop_folder_queues_its_files_to_the_machine_and_says_what_it_refused() {
    let cell = RunningCell::start(cell_config, false).await;
    let drop_dir = cell.dir.path().join("drop-mill-1");
    let events = cell.subscribe(cell.keys.job_events("mill-1", "*")).await;
    std::fs::create_dir_all(&drop_dir).unwrap();
    let part = program(7001, 40);
    std::fs::write(drop_dir.join("O7001.nc"), &part).unwrap();
    let sample = tokio::time::timeout(Duration::from_secs(10), events.recv_async())
        .await
        .expect("a job from the drop folder")
        .unwrap();
    let queued = pb::JobEvent::decode(sample.payload().to_bytes().as_ref()).unwrap();
    let kinds = follow(&events, &queued.job_id, Duration::from_secs(60)).await;
    assert!(
        matches!(kinds.last(), Some(Kind::Completed(_))),
        "{kinds:?}"
    );
    // Moved aside once queued: never sent twice.
    common::bus::eventually("the file is in sent/", || {
        drop_dir.join("sent/O7001.nc").is_file() && !drop_dir.join("O7001.nc").exists()
    })
    .await;
    assert_eq!(std::fs::read(drop_dir.join("sent/O7001.nc")).unwrap(), part);

    // A file that is no program for this machine (no end of record): refused, said beside it.
    std::fs::write(drop_dir.join("broken.nc"), b"O7002\nG01 X1\n").unwrap();
    common::bus::eventually("the file is in refused/", || {
        drop_dir.join("refused/broken.nc").is_file()
    })
    .await;
    let why = std::fs::read_to_string(drop_dir.join("refused/broken.nc.why.txt")).unwrap();
    assert!(why.contains("mill-1"), "{why}");

    let job = queued.job_id.clone();
    audit_until(&cell, move |records| {
        let submits: Vec<&pb::AuditRecord> = records
            .iter()
            .filter(|a| a.action == "job.submit")
            .collect();
        submits.iter().any(|a| a.ok && a.detail.contains(&job))
            && submits.iter().any(|a| !a.ok && a.target == "broken.nc")
            && submits.iter().all(|a| {
                a.origin
                    .as_ref()
                    .is_some_and(|o| o.via.starts_with("drop folder"))
            })
    })
    .await;
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_punched_program_is_written_into_the_receive_folder_too() {
    let cell = RunningCell::start(cell_config, false).await;
    let punched = cell
        .subscribe(cell.keys.leaf("lathe-1", MachineLeaf::Punch))
        .await;
    let part = b"%\nO1234(SHAFT 7)\nG00X10.Y2.5\nM30\n%".to_vec();
    cell.board("lathe-1").punch(part.clone());
    let sample = tokio::time::timeout(Duration::from_secs(30), punched.recv_async())
        .await
        .expect("a punched program")
        .unwrap();
    let p = pb::PunchedProgram::decode(sample.payload().to_bytes().as_ref()).unwrap();
    let file = cell
        .dir
        .path()
        .join("received-lathe-1")
        .join(&p.library_name);
    assert_eq!(std::fs::read(&file).unwrap(), part);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_of_the_same_bytes_again_says_nothing_and_the_folder_adds_no_word() {
    let cell = RunningCell::start(cell_config, false).await;
    let library = Library::follow(&cell).await;
    let write = |op| pb::ProgramWrite {
        op: Some(op),
        ..Default::default()
    };
    let part = program(42, 3);
    for _ in 0..2 {
        let _: pb::ProgramInfo = get_one(
            &cell.client,
            &cell.keys.program_write("O42"),
            Some(write(pb::program_write::Op::Store(part.clone())).encode_to_vec()),
        )
        .await;
    }
    let e = library.next().await;
    assert_eq!((e.name.as_str(), e.kind), ("O42", "stored"));
    assert_eq!(e.revision, 1);
    // The same bytes again made no revision, so no event; the folder's own look at the file
    // the store wrote makes none either.
    library.quiet(1500).await;
    let _: pb::ProgramInfo = get_one(
        &cell.client,
        &cell.keys.program_write("O42"),
        Some(write(pb::program_write::Op::Remove(pb::program_write::Remove {})).encode_to_vec()),
    )
    .await;
    let e = library.next().await;
    assert_eq!((e.name.as_str(), e.kind), ("O42", "removed"));
    library.quiet(1500).await;
    cell.stop().await;
}

/// The files of the library's folder, hidden ones aside, sorted.
fn files_in(dir: &Path) -> Vec<String> {
    let mut files: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|f| !f.starts_with('.'))
        .collect();
    files.sort();
    files
}

/// One program, one file: a store from the bus writes `NAME.nc`, the name a CAM system
/// posts, so that its post is the next revision rather than a conflict; a post under another
/// extension, or beside the plain file an earlier version wrote, takes the copy's place.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_post_after_a_store_from_the_bus_is_the_next_revision_not_a_conflict() {
    let cell = RunningCell::start(cell_config, false).await;
    let library = Library::follow(&cell).await;
    let dir = programs(&cell);
    let store = |bytes: Vec<u8>| {
        pb::ProgramWrite {
            op: Some(pb::program_write::Op::Store(bytes)),
            ..Default::default()
        }
        .encode_to_vec()
    };

    // Stored through the bus (as `cellgate program put O1234 FILE` does).
    let info: pb::ProgramInfo = get_one(
        &cell.client,
        &cell.keys.program_write("O1234"),
        Some(store(program(1234, 3))),
    )
    .await;
    assert_eq!(info.file, "O1234.nc");
    assert_eq!(files_in(&dir), ["O1234.nc"]);
    let e = library.next().await;
    assert_eq!((e.name.as_str(), e.revision), ("O1234", 1));

    // The CAM system posts O1234.nc: the next revision, the same file.
    let posted = program(1234, 5);
    std::fs::write(dir.join("O1234.nc"), &posted).unwrap();
    let e = library.next().await;
    assert_eq!(
        (e.kind, e.name.as_str(), e.file.as_str(), e.revision),
        ("stored", "O1234", "O1234.nc", 2),
        "{e:?}"
    );
    assert_eq!(read(&cell, "O1234").await, posted);

    // Posted as O1234.tap: it takes the place of the copy of revision 2.
    let tap = program(1234, 7);
    std::fs::write(dir.join("O1234.tap"), &tap).unwrap();
    let e = library.next().await;
    assert_eq!(
        (e.kind, e.file.as_str(), e.revision),
        ("stored", "O1234.tap", 3),
        "{e:?}"
    );
    assert_eq!(read(&cell, "O1234").await, tap);
    assert_eq!(files_in(&dir), ["O1234.tap"]);
    // The copy's removal removes nothing more.
    library.quiet(1500).await;

    // A plain file (as an earlier version's store wrote it), then the CAM's O77.nc.
    std::fs::write(dir.join("O77"), program(77, 1)).unwrap();
    let e = library.next().await;
    assert_eq!((e.file.as_str(), e.revision), ("O77", 1), "{e:?}");
    std::fs::write(dir.join("O77.nc"), program(77, 2)).unwrap();
    let e = library.next().await;
    assert_eq!(
        (e.kind, e.file.as_str(), e.revision),
        ("stored", "O77.nc", 2),
        "{e:?}"
    );
    assert_eq!(files_in(&dir), ["O1234.tap", "O77.nc"]);

    // A store writes the file the program has.
    let _: pb::ProgramInfo = get_one(
        &cell.client,
        &cell.keys.program_write("O1234"),
        Some(store(program(1234, 9))),
    )
    .await;
    assert_eq!(
        std::fs::read(dir.join("O1234.tap")).unwrap(),
        program(1234, 9)
    );
    assert_eq!(files_in(&dir), ["O1234.tap", "O77.nc"]);
    cell.stop().await;
}

/// `cellgate watch` shows what the folder refused, as docs/library.md says: its events key is
/// a verbatim chunk that `P/C/**` does not take in, so the watch follows it by name.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watch_shows_a_file_the_folder_refused() {
    let cell = RunningCell::start(cell_config, false).await;
    let client = cellgate::client::Client::attach(
        cell.client.clone(),
        "cellgate",
        "folder",
        serde_json::Value::Null,
        Duration::from_secs(10),
    )
    .unwrap();
    let mut watch = client.watch().await.unwrap();
    let dir = programs(&cell);
    std::fs::write(dir.join("O5558.nc"), program(5558, 1)).unwrap();
    std::fs::write(dir.join("O5558.tap"), program(5558, 2)).unwrap();
    let refused = loop {
        let e = tokio::time::timeout(Duration::from_secs(20), watch.next())
            .await
            .expect("watch showed no refusal")
            .expect("the session closed");
        if let cellgate::client::WatchEvent::Library(e) = e {
            break e;
        }
    };
    assert_eq!(refused.kind(), pb::LibraryEventKind::Refused);
    assert_eq!(refused.code(), pb::ErrorCode::Conflict);
    let line = cellgate::client::render::WatchPrinter::new()
        .line(&cellgate::client::WatchEvent::Library(refused.clone()), 0)
        .unwrap();
    assert!(line.contains("not taken"), "{line}");
    watch.close().await;
    cell.stop().await;
}
