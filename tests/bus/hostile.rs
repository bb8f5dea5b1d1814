//! The gateway as a hostile or unlucky user runs it: a journal it cannot open or finds
//! damaged, a full disk, a client with a narrow role reaching for more through the gateway, a
//! flood of one kind of request, a G05 producer that opens and walks away, messages past
//! every bound. Each test is named for what it guards.
//!
//! The disk-full tests mount a small tmpfs (as root, as CI runs); where mounting is refused
//! they say so and pass without checking anything else.

use crate::common;

use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

use cellgate::bus::keys::{G05Part, MachineLeaf};
use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use common::bus::{RunningCell, eventually, get, get_err, get_one};
use common::cli::{collect_stderr, wait_with_deadline};
use prost::Message;

const MILL: &str = "mill-1";
const MILL_G05: &str = "mill-2";

/// The embedded default cell on `port`, its library and journal under `dir`.
fn default_cell(port: u16, dir: &Path) -> CellConfig {
    let mut c = CellConfig::embedded_default();
    // Its MTConnect agent would take a fixed port; this test does not look at it.
    c.mtconnect = None;
    c.opcua = None;
    c.bus.listen = vec![format!("tcp/127.0.0.1:{port}")];
    c.bus.connect = Vec::new();
    c.programs.dir = dir.join("programs");
    c
}

fn inline(program: &[u8]) -> pb::JobRequest {
    pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(program.to_vec())),
        ..Default::default()
    }
}

// ---- a journal that cannot be opened --------------------------------------------------------

/// Runs `cellgate run` on a cell whose journal is `journal`: (exit code, stderr, seconds).
fn run_on_journal(dir: &Path, journal: &Path, extra: &str) -> (Option<i32>, String, f64) {
    let port = common::bus::free_port();
    let cell = dir.join("cell.toml");
    std::fs::write(
        &cell,
        format!(
            "cell = \"hostile\"\n[bus]\nlisten = [\"tcp/127.0.0.1:{port}\"]\n\
             [programs]\ndir = \"{}\"\njournal = \"{}\"\n{extra}\n\
             [[machines]]\nname = \"m1\"\nprotocol = \"a\"\ntransport = {{ kind = \"sim\" }}\n",
            dir.join("programs").display(),
            journal.display()
        ),
    )
    .unwrap();
    let started = Instant::now();
    let mut child = common::cli::bin()
        .args(["run", "-c"])
        .arg(&cell)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = collect_stderr(&mut child);
    let status = wait_with_deadline(&mut child, Duration::from_secs(30));
    if status.is_none() {
        let _ = child.kill();
        let _ = child.wait();
    }
    (
        status.and_then(|s| s.code()),
        stderr.join().unwrap(),
        started.elapsed().as_secs_f64(),
    )
}

/// A journal with a job in it, written by a gateway that ran and stopped.
fn journal_of_a_run(dir: &Path) -> std::path::PathBuf {
    let journal = dir.join("journal");
    let j = cellgate::jobs::journal::Journal::open(&journal).unwrap();
    j.store_bytes("1", &[b"%\nO1\n%"]).unwrap();
    let _ = j.next_seq().unwrap();
    drop(j);
    journal.join("jobs.redb")
}

#[test]
fn a_journal_that_cannot_be_opened_stops_the_gateway_at_once_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("a-file"), b"not a directory").unwrap();
    let journal = dir.path().join("a-file/journal");
    let (code, stderr, secs) = run_on_journal(dir.path(), &journal, "");
    assert_eq!(code, Some(1), "{stderr}");
    assert!(secs < 15.0, "took {secs} s");
    assert!(stderr.contains("a-file/journal"), "{stderr}");
    assert!(stderr.contains("Not a directory"), "{stderr}");
}

#[test]
fn a_damaged_journal_is_refused_with_how_to_recover_never_a_crash() {
    type Damage = fn(&Path);
    let damages: [(&str, Damage); 3] = [
        ("header overwritten", |p| {
            let mut b = std::fs::read(p).unwrap();
            b[..16].copy_from_slice(b"not a redb file!");
            std::fs::write(p, b).unwrap();
        }),
        ("truncated to half", |p| {
            let len = std::fs::metadata(p).unwrap().len();
            let f = std::fs::OpenOptions::new().write(true).open(p).unwrap();
            f.set_len(len / 2).unwrap();
        }),
        ("emptied", |p| std::fs::write(p, b"").unwrap()),
    ];
    for (what, damage) in damages {
        let dir = tempfile::tempdir().unwrap();
        let db = journal_of_a_run(dir.path());
        damage(&db);
        let (code, stderr, secs) = run_on_journal(dir.path(), &dir.path().join("journal"), "");
        assert_eq!(
            code,
            Some(1),
            "{what}: a crash (101) or a hang is not an answer: {stderr}"
        );
        assert!(secs < 15.0, "{what}: took {secs} s");
        assert!(stderr.contains("is damaged"), "{what}: {stderr}");
        assert!(stderr.contains("move-aside"), "{what}: {stderr}");
        assert!(!stderr.contains("panicked"), "{what}: {stderr}");
        assert!(
            db.exists(),
            "{what}: the damaged file is left for a person to look at"
        );
    }
}

#[test]
fn a_damaged_journal_is_moved_aside_loudly_when_the_cell_file_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let db = journal_of_a_run(dir.path());
    std::fs::write(&db, b"").unwrap();
    let port = common::bus::free_port();
    let cell = dir.path().join("cell.toml");
    std::fs::write(
        &cell,
        format!(
            "cell = \"hostile\"\n[bus]\nlisten = [\"tcp/127.0.0.1:{port}\"]\n\
             [programs]\ndir = \"{}\"\njournal = \"{}\"\ndamaged_journal = \"move-aside\"\n",
            dir.path().join("programs").display(),
            dir.path().join("journal").display()
        ),
    )
    .unwrap();
    let mut child = common::cli::bin()
        .args(["run", "-c"])
        .arg(&cell)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = collect_stderr(&mut child);
    let health = || {
        common::cli::run([
            "health",
            "-e",
            &format!("tcp/127.0.0.1:{port}"),
            "--gateway-only",
        ])
        .0
    };
    let deadline = Instant::now() + Duration::from_secs(20);
    while health() != 0 {
        assert!(Instant::now() < deadline, "the gateway never answered");
        std::thread::sleep(Duration::from_millis(200));
    }
    let _ = nix_term(&child);
    let status = wait_with_deadline(&mut child, Duration::from_secs(10));
    assert_eq!(status.and_then(|s| s.code()), Some(0));
    let stderr = stderr.join().unwrap();
    assert!(stderr.contains("moved aside"), "{stderr}");
    let names: Vec<String> = std::fs::read_dir(dir.path().join("journal"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        names.iter().any(|n| n.starts_with("jobs.redb.damaged-")),
        "{names:?}"
    );
}

fn nix_term(child: &std::process::Child) -> std::io::Result<()> {
    let pid = i32::try_from(child.id()).unwrap_or(0);
    // SAFETY: kill(2) with a pid of our own child and SIGTERM.
    if unsafe { libc::kill(pid, libc::SIGTERM) } == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

// ---- a full disk ---------------------------------------------------------------------------

/// A tmpfs of `mb` MiB mounted on a fresh directory, unmounted when dropped; `None` (said on
/// stderr) where mounting is refused.
struct SmallDisk {
    dir: tempfile::TempDir,
}

impl SmallDisk {
    fn mount(mb: u32) -> Option<SmallDisk> {
        let dir = tempfile::tempdir().ok()?;
        let ok = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mb}m"), "tmpfs"])
            .arg(dir.path())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if !ok {
            eprintln!("disk-full test skipped: cannot mount a tmpfs here (not root?)");
            return None;
        }
        Some(SmallDisk { dir })
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Fills the disk to within `left` bytes; returns the filler's path.
    fn fill(&self, left: u64) -> std::path::PathBuf {
        let filler = self.path().join("filler");
        let stat = nix_statvfs(self.path());
        let free = stat.saturating_sub(left);
        let _ = std::fs::write(&filler, vec![0u8; usize::try_from(free).unwrap_or(0)]);
        filler
    }
}

fn nix_statvfs(p: &Path) -> u64 {
    use std::os::unix::ffi::OsStrExt as _;
    let c = std::ffi::CString::new(p.as_os_str().as_bytes()).unwrap();
    // SAFETY: statvfs(3) on a NUL-terminated path into a zeroed struct.
    let mut s: libc::statvfs = unsafe { std::mem::zeroed() };
    if unsafe { libc::statvfs(c.as_ptr(), &mut s) } != 0 {
        return 0;
    }
    s.f_bavail as u64 * s.f_frsize as u64
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg(self.dir.path())
            .status();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_on_a_full_disk_is_refused_and_the_earlier_version_stays_whole() {
    let Some(disk) = SmallDisk::mount(4) else {
        return;
    };
    let root = disk.path().to_path_buf();
    let cell = RunningCell::start(
        |port, dir| {
            let mut c = default_cell(port, dir);
            c.programs.dir = root.join("programs");
            c.programs.journal = Some(dir.join("journal"));
            c
        },
        false,
    )
    .await;
    let key = cell.keys.program_write("O1");
    let write = |bytes: Vec<u8>| {
        pb::ProgramWrite {
            op: Some(pb::program_write::Op::Store(bytes)),
            comment: String::new(),
        }
        .encode_to_vec()
    };
    let first = b"%\nO1\nG00X0\nM30\n%".to_vec();
    let _: pb::ProgramInfo = get_one(&cell.client, &key, Some(write(first.clone()))).await;
    let filler = disk.fill(64 * 1024);
    let big = common::nc_program(1 << 20, 7);
    let e = get_err(&cell.client, &key, Some(write(big))).await;
    assert_eq!(e.code(), pb::ErrorCode::StorageFull, "{}", e.message);
    assert!(e.message.contains("unchanged"), "{}", e.message);
    // The earlier version is whole, and no temporary file is left behind.
    assert_eq!(std::fs::read(root.join("programs/O1.nc")).unwrap(), first);
    let leftovers: Vec<_> = std::fs::read_dir(root.join("programs"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n != ".revisions" && n != ".history")
        .collect();
    assert_eq!(leftovers, ["O1.nc"]);
    // Nor half a revision: the store holds the first program's content only.
    let objects: Vec<_> = std::fs::read_dir(root.join("programs/.revisions/objects"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(objects.len(), 1, "{objects:?}");
    let revisions: pb::ProgramRevisions =
        get_one(&cell.client, &cell.keys.program_revisions("O1"), None).await;
    assert_eq!(revisions.revisions.len(), 1);
    // Space back: the same store goes through.
    std::fs::remove_file(filler).unwrap();
    let info: pb::ProgramInfo = get_one(
        &cell.client,
        &key,
        Some(write(common::nc_program(1 << 20, 7))),
    )
    .await;
    assert!(info.size > 1_000_000);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_journal_refuses_submits_on_a_full_disk_and_writes_again_once_space_is_back() {
    let Some(disk) = SmallDisk::mount(4) else {
        return;
    };
    let root = disk.path().to_path_buf();
    let cell = RunningCell::start(
        |port, dir| {
            let mut c = default_cell(port, dir);
            c.programs.journal = Some(root.join("journal"));
            c
        },
        false,
    )
    .await;
    let submit = cell.keys.leaf(MILL, MachineLeaf::Submit);
    let filler = disk.fill(16 * 1024);
    let mut codes = Vec::new();
    for i in 0..4 {
        let req = inline(&common::nc_program(200 * 1024, i));
        let e = get_err(&cell.client, &submit, Some(req.encode_to_vec())).await;
        codes.push(e.code());
    }
    assert!(
        codes.iter().all(|c| *c == pb::ErrorCode::StorageFull),
        "{codes:?}"
    );
    std::fs::remove_file(filler).unwrap();
    // Without a restart: the journal opens its file again and takes the job.
    let accepted: pb::JobAccepted = get_one(
        &cell.client,
        &submit,
        Some(inline(b"%\nO2\nG00X0\nM30\n%").encode_to_vec()),
    )
    .await;
    assert!(!accepted.job_id.is_empty());
    let status: pb::MachineStatus = get_one(
        &cell.client,
        &cell.keys.leaf(MILL, MachineLeaf::Status),
        None,
    )
    .await;
    assert_eq!(
        status.storage_fault, "",
        "the fault is gone once the journal writes"
    );
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_history_holds_its_records_through_a_full_disk_and_writes_them_once_space_is_back() {
    let Some(disk) = SmallDisk::mount(4) else {
        return;
    };
    let root = disk.path().to_path_buf();
    let cell = RunningCell::start(
        |port, dir| {
            let mut c = default_cell(port, dir);
            c.history.dir = Some(root.join("history"));
            c
        },
        false,
    )
    .await;
    let filler = disk.fill(0);
    // Writes the audit trail records while the store cannot take them.
    let key = cell.keys.leaf(MILL, MachineLeaf::Do);
    for value in 1..=5u32 {
        let cmd = pb::DoCommand { value, mask: None };
        cell.client
            .put(key.as_str(), cmd.encode_to_vec())
            .await
            .unwrap();
    }
    // Commits fail at least twice (one a second), so that the store met the full disk.
    tokio::time::sleep(Duration::from_millis(2500)).await;
    // Now that the audit trail is known not to take records, no write is taken: it would go
    // unaudited if the gateway were killed before the disk had room.
    let cmd = pb::DoCommand {
        value: 9,
        mask: None,
    };
    let e = get_err(&cell.client, &key, Some(cmd.encode_to_vec())).await;
    assert_eq!(e.code(), pb::ErrorCode::StorageFull, "{}", e.message);
    assert!(
        e.message.contains("audit trail cannot be written"),
        "{}",
        e.message
    );
    std::fs::remove_file(filler).unwrap();
    // Without a restart: the store is opened again, the records held in memory are written
    // and read back (redb refuses every transaction after an I/O error until reopened).
    let outputs = |page: &pb::HistoryPage| {
        page.records
            .iter()
            .filter(|r| {
                matches!(&r.record, Some(pb::history_record::Record::Audit(a))
                    if a.action == "io.do" && a.ok)
            })
            .count()
    };
    let mut last = Vec::new();
    for _ in 0..50 {
        last = get(&cell.client, &cell.keys.audit(), None).await;
        if let Some(Ok((_, bytes, _))) = last.first()
            && outputs(&pb::HistoryPage::decode(bytes.as_slice()).unwrap()) == 5
        {
            cell.stop().await;
            return;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    panic!("the five DO outputs are not in the audit trail 10 s after the disk had room: {last:?}");
}

// ---- no borrowed authority -----------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_cannot_have_the_gateway_fetch_what_the_client_may_not_read() {
    let cell = RunningCell::start(default_cell, false).await;
    let submit = cell.keys.leaf(MILL, MachineLeaf::Submit);
    for key in [
        cell.keys.admin(),
        cell.keys.plc_mem("plc-1", 0, "D", Some(0)),
        cell.keys.leaf(MILL, MachineLeaf::Di),
        "cam/programs/O1".to_string(),
        "@/*/router".to_string(),
    ] {
        let req = pb::JobRequest {
            program: Some(pb::job_request::Program::Key(key.clone())),
            ..Default::default()
        };
        let e = get_err(&cell.client, &submit, Some(req.encode_to_vec())).await;
        assert_eq!(
            e.code(),
            pb::ErrorCode::NotPermitted,
            "{key}: {}",
            e.message
        );
    }
    let queue: pb::JobQueue =
        get_one(&cell.client, &cell.keys.leaf(MILL, MachineLeaf::Job), None).await;
    assert!(queue.active.is_none() && queue.waiting.is_empty());
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_read_key_never_writes_whatever_the_payload() {
    let cell = RunningCell::start(default_cell, false).await;
    // The queue key takes no JobRequest.
    let e = get_err(
        &cell.client,
        &cell.keys.leaf(MILL, MachineLeaf::Job),
        Some(inline(b"%\nO1\n%").encode_to_vec()),
    )
    .await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{}", e.message);
    // The program key takes no ProgramWrite.
    let w = pb::ProgramWrite {
        op: Some(pb::program_write::Op::Store(b"%\nO1\n%".to_vec())),
        comment: String::new(),
    };
    let e = get_err(
        &cell.client,
        &cell.keys.program("O1"),
        Some(w.encode_to_vec()),
    )
    .await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{}", e.message);
    let e = get_err(&cell.client, &cell.keys.program("O1"), None).await;
    assert_eq!(e.code(), pb::ErrorCode::NotFound, "nothing was stored");
    // A tag's key takes no TagWrite; its own write key does.
    let tag = cell.keys.plc_tag("plc-1", "recipe");
    let before: pb::TagValue = get_one(&cell.client, &tag, None).await;
    let write = pb::TagWrite { value: 77.0 }.encode_to_vec();
    let e = get_err(&cell.client, &tag, Some(write.clone())).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{}", e.message);
    let after: pb::TagValue = get_one(&cell.client, &tag, None).await;
    assert_eq!(after.value, before.value, "the read key wrote nothing");
    let _: pb::TagWritten = get_one(
        &cell.client,
        &cell.keys.plc_tag_set("plc-1", "recipe"),
        Some(write),
    )
    .await;
    // Memory: the read key refuses a PlcWrite.
    let pw = pb::PlcWrite {
        words: vec![1],
        clear: false,
    };
    let e = get_err(
        &cell.client,
        &cell.keys.plc_mem("plc-1", 0, "D", Some(100)),
        Some(pw.encode_to_vec()),
    )
    .await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{}", e.message);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_put_of_another_encoding_is_refused_with_a_word_and_one_without_is_taken() {
    let cell = RunningCell::start(default_cell, false).await;
    let tag = cell.keys.plc_tag("plc-1", "recipe");
    let set = cell.keys.plc_tag_set("plc-1", "recipe");
    let write = |v: f64| pb::TagWrite { value: v }.encode_to_vec();
    // Another encoding: not read, and said (before, passed over without a word).
    cell.client
        .put(&set, write(13.0))
        .encoding(zenoh::bytes::Encoding::TEXT_PLAIN)
        .await
        .unwrap();
    let mut tries = 0;
    let refused = loop {
        tries += 1;
        assert!(tries < 100, "the refused put is nowhere in the audit");
        let page: pb::HistoryPage = get_one(&cell.client, &cell.keys.audit(), None).await;
        let found = page.records.into_iter().find_map(|r| match r.record {
            Some(pb::history_record::Record::Audit(a)) if a.action == "plc.tag" => Some(a),
            _ => None,
        });
        if let Some(a) = found {
            break a;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert!(!refused.ok, "{refused:?}");
    assert_eq!(refused.code(), pb::ErrorCode::InvalidRequest);
    assert!(
        refused.error.contains("text/plain") && refused.error.contains("cellgate.v1.TagWrite"),
        "{}",
        refused.error
    );
    let now: pb::TagValue = get_one(&cell.client, &tag, None).await;
    assert_ne!(now.value, Some(13.0), "the refused put wrote");
    // No encoding said: read as the key's message, as a DO put is.
    cell.client.put(&set, write(21.0)).await.unwrap();
    let mut value = None;
    for _ in 0..100 {
        let v: pb::TagValue = get_one(&cell.client, &tag, None).await;
        value = v.value;
        if value == Some(21.0) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(value, Some(21.0), "a put without an encoding was not taken");
    // The same on a machine's write key: a DO put of another encoding outputs nothing.
    let board = cell.board(MILL);
    let before = board.do_image();
    let command = pb::DoCommand {
        value: u32::from(!before),
        mask: None,
    };
    cell.client
        .put(
            cell.keys.leaf(MILL, MachineLeaf::Do),
            command.encode_to_vec(),
        )
        .encoding(zenoh::bytes::Encoding::TEXT_PLAIN)
        .await
        .unwrap();
    let mut refused = None;
    for _ in 0..100 {
        let page: pb::HistoryPage = get_one(&cell.client, &cell.keys.audit(), None).await;
        refused = page.records.into_iter().find_map(|r| match r.record {
            Some(pb::history_record::Record::Audit(a)) if a.action == "io.do" => Some(a),
            _ => None,
        });
        if refused.is_some() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let refused = refused.expect("the refused DO put is nowhere in the audit");
    assert!(!refused.ok, "{refused:?}");
    assert!(
        refused.error.contains("text/plain") && refused.error.contains("cellgate.v1.DoCommand"),
        "{}",
        refused.error
    );
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(board.do_image(), before, "the refused DO put was output");
    cell.stop().await;
}

// ---- fair shares -------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_reads_leaves_submits_and_program_stores_their_slots() {
    let cell = RunningCell::start(default_cell, false).await;
    let di = cell.keys.leaf(MILL, MachineLeaf::Di);
    let mut rdi = cell.board(MILL).subscribe();
    let flood: Vec<_> = (0..400)
        .map(|_| {
            let (c, k) = (cell.client.clone(), di.clone());
            // Longer than a DI read may wait for the board (2·Tp + 1 s).
            tokio::spawn(async move { get_within(&c, &k, Duration::from_secs(30)).await })
        })
        .collect();
    // While the reads wait for the board, the MES submits and stores.
    tokio::time::sleep(Duration::from_millis(100)).await;
    let accepted: pb::JobAccepted = get_one(
        &cell.client,
        &cell.keys.leaf(MILL, MachineLeaf::Submit),
        Some(inline(b"%\nO1\nG00X0\nM30\n%").encode_to_vec()),
    )
    .await;
    assert!(!accepted.job_id.is_empty());
    let w = pb::ProgramWrite {
        op: Some(pb::program_write::Op::Store(b"%\nO5\n%".to_vec())),
        comment: String::new(),
    };
    let _: pb::ProgramInfo = get_one(
        &cell.client,
        &cell.keys.program_write("O5"),
        Some(w.encode_to_vec()),
    )
    .await;
    let mut answered = 0;
    let mut busy = 0;
    for f in flood {
        for r in f.await.unwrap() {
            match r {
                Ok(_) => answered += 1,
                Err((bytes, encoding)) => {
                    // BUSY from a full pool; zenoh's own time-out for a read still waiting
                    // for its turn when the client gave up.
                    if encoding.contains("ErrorReply") {
                        let e = pb::ErrorReply::decode(bytes.as_slice()).unwrap();
                        assert_eq!(e.code(), pb::ErrorCode::Busy, "{}", e.message);
                    }
                    busy += 1;
                }
            }
        }
    }
    assert!(answered > 0, "{answered} answered, {busy} busy");
    // The reads that were served shared their RDIs: far fewer than one each.
    let mut rdis = 0;
    while let Ok(e) = rdi.try_recv() {
        if matches!(
            e,
            cellgate_core::sim::BoardEvent::MessageReceived(
                cellgate_core::fanuc::message::Command::Rdi
            )
        ) {
            rdis += 1;
        }
    }
    assert!(rdis * 4 < answered, "{rdis} RDIs for {answered} answers");
    cell.stop().await;
}

/// Every reply to a get without payload on `key` within `timeout`: `Ok(())` for an answer,
/// the error's payload and encoding otherwise.
async fn get_within(
    client: &zenoh::Session,
    key: &str,
    timeout: Duration,
) -> Vec<Result<(), (Vec<u8>, String)>> {
    let replies = client.get(key).timeout(timeout).await.unwrap();
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        out.push(match reply.result() {
            Ok(_) => Ok(()),
            Err(e) => Err((
                e.payload().to_bytes().into_owned(),
                e.encoding().to_string(),
            )),
        });
    }
    out
}

// ---- G05 -----------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_get_without_payload_on_blocks_is_a_status_query_never_a_batch() {
    let cell = RunningCell::start(default_cell, false).await;
    let open = pb::G05Open {
        stream_id: "probe".to_string(),
        producer_token: false,
    };
    let _: pb::G05Opened = get_one(
        &cell.client,
        &cell.keys.leaf(MILL_G05, MachineLeaf::G05),
        Some(open.encode_to_vec()),
    )
    .await;
    let blocks = cell.keys.g05(MILL_G05, "probe", G05Part::Blocks);
    let status: pb::G05Status = get_one(&cell.client, &blocks, None).await;
    assert_eq!(status.next_seq, 0, "the status query took no batch number");
    let batch = pb::G05Batch {
        seq: 0,
        blocks: (0..10)
            .map(|i| pb::G05Block {
                travel: vec![i, -i, 1],
                aux: None,
            })
            .collect(),
        end: true,
    };
    let status: pb::G05Status = get_one(&cell.client, &blocks, Some(batch.encode_to_vec())).await;
    assert_eq!(
        (status.repeats, status.next_seq),
        (0, 1),
        "batch 0 was taken as new"
    );
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_nobody_feeds_ends_and_frees_its_machine() {
    let cell = RunningCell::start(default_cell, false).await;
    let open = pb::G05Open {
        stream_id: "orphan".to_string(),
        producer_token: false,
    };
    let _: pb::G05Opened = get_one(
        &cell.client,
        &cell.keys.leaf(MILL_G05, MachineLeaf::G05),
        Some(open.encode_to_vec()),
    )
    .await;
    let status_key = cell.keys.g05(MILL_G05, "orphan", G05Part::Status);
    let mut ended = None;
    for _ in 0..100 {
        let s: pb::G05Status = get_one(&cell.client, &status_key, None).await;
        if matches!(s.state(), pb::G05State::Completed | pb::G05State::Failed) {
            ended = Some(s);
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let ended = ended.expect("the stream ends within its idle time");
    assert_eq!(ended.end_reason(), pb::G05EndReason::NoBatch);
    // The machine takes jobs again.
    let (job, events) = cell.submit(MILL_G05, b"%\nO7\nG00X0\nM30\n%").await;
    let kinds = common::bus::follow(&events, &job, Duration::from_secs(60)).await;
    assert!(
        matches!(kinds.last(), Some(pb::job_event::Kind::Completed(_))),
        "{kinds:?}"
    );
    cell.stop().await;
}

// ---- bounds before work --------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversized_fields_and_messages_are_refused_before_any_work() {
    let cell = RunningCell::start(default_cell, false).await;
    let submit = cell.keys.leaf(MILL, MachineLeaf::Submit);
    let mut long_name = inline(b"%\nO1\n%");
    long_name.name = "n".repeat(1 << 20);
    let e = get_err(&cell.client, &submit, Some(long_name.encode_to_vec())).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);
    assert!(e.message.contains("JobRequest.name"), "{}", e.message);
    // Over max_inline by far: refused for its size, not decoded.
    let huge = vec![0xFFu8; 20 << 20];
    let e = get_err(&cell.client, &submit, Some(huge)).await;
    assert!(e.message.contains("nothing was decoded"), "{}", e.message);
    // A G05 batch far past any window.
    let open = pb::G05Open {
        stream_id: "big".to_string(),
        producer_token: false,
    };
    let _: pb::G05Opened = get_one(
        &cell.client,
        &cell.keys.leaf(MILL_G05, MachineLeaf::G05),
        Some(open.encode_to_vec()),
    )
    .await;
    let e = get_err(
        &cell.client,
        &cell.keys.g05(MILL_G05, "big", G05Part::Blocks),
        Some(vec![0x12; 8 << 20]),
    )
    .await;
    assert!(e.message.contains("nothing was decoded"), "{}", e.message);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_stores_never_break_the_library_quota() {
    let cell = RunningCell::start(
        |port, dir| {
            let mut c = default_cell(port, dir);
            c.programs.quota_files = Some(10);
            c
        },
        false,
    )
    .await;
    let stores: Vec<_> = (0..60)
        .map(|i| {
            let c = cell.client.clone();
            let key = cell.keys.program_write(&format!("Q{i}"));
            let w = pb::ProgramWrite {
                op: Some(pb::program_write::Op::Store(b"%\nO1\n%".to_vec())),
                comment: String::new(),
            };
            tokio::spawn(async move { get(&c, &key, Some(w.encode_to_vec())).await })
        })
        .collect();
    let mut stored = 0;
    for s in stores {
        if let Some(Ok(_)) = s.await.unwrap().into_iter().next() {
            stored += 1;
        }
    }
    let list = get(&cell.client, &cell.keys.any_program(), None).await;
    assert!(
        stored <= 10 && list.len() <= 10,
        "{stored} stored, {} listed",
        list.len()
    );
    eventually("ten stored", || stored == 10).await;
    cell.stop().await;
}

// ---- the smaller ones ----------------------------------------------------------------------

#[test]
fn credentials_of_the_otlp_endpoint_never_reach_admin() {
    let mut c = CellConfig::embedded_default();
    c.telemetry.otlp_endpoint = Some("http://user:s3cret@127.0.0.1:4317".to_string());
    let doc = cellgate::gateway::admin_document(&c, "zid").to_string();
    assert!(!doc.contains("s3cret"), "{doc}");
    assert!(doc.contains("***@127.0.0.1:4317"), "{doc}");
}

#[test]
fn check_config_warns_of_a_listener_beyond_loopback_without_security() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("open.toml");
    std::fs::write(
        &file,
        "cell = \"open\"\n[bus]\nlisten = [\"tcp/0.0.0.0:7447\"]\n",
    )
    .unwrap();
    let (code, _, stderr) =
        common::cli::run([std::ffi::OsStr::new("check-config"), file.as_os_str()]);
    assert_eq!(code, 0, "a warning, not an error: {stderr}");
    assert!(
        stderr.contains("warning") && stderr.contains("no [security]"),
        "{stderr}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_is_checked_before_its_bytes_are_sent_and_the_check_writes_nothing() {
    let cell = RunningCell::start(
        |port, dir| {
            let mut c = default_cell(port, dir);
            c.programs.max_size = 1000;
            c
        },
        false,
    )
    .await;
    let check = |size| {
        pb::ProgramWrite {
            op: Some(pb::program_write::Op::Check(pb::program_write::Check {
                size,
            })),
            comment: String::new(),
        }
        .encode_to_vec()
    };
    let key = cell.keys.program_write("O42");
    let info: pb::ProgramInfo = get_one(&cell.client, &key, Some(check(500))).await;
    assert_eq!(info.name, "O42");
    assert_eq!(info.size, 0, "a new program: nothing stands yet");
    let e = get_err(&cell.client, &key, Some(check(5000))).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{}", e.message);
    assert!(e.message.contains("max_size"), "{}", e.message);
    // Nothing was written.
    let e = get_err(&cell.client, &cell.keys.program("O42"), None).await;
    assert_eq!(e.code(), pb::ErrorCode::NotFound);
    cell.stop().await;
}
