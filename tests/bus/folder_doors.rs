//! The library's folder against a hostile or careless writer, on a running gateway with a
//! real folder: symbolic links and a FIFO posted there, the folder removed and made again,
//! extensions in any case, names that give no program, and a large sparse file.

use crate::common;

use std::os::unix::ffi::OsStrExt as _;
use std::path::Path;

use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use common::bus::{RunningCell, get, get_err, get_one};
use prost::Message;

use super::folder::{Library, Said, audit_until, program, programs, read};

/// A cell whose library's folder is listed every 200 ms as well as followed by its events,
/// so that a file said twice would be said within the test.
fn cell_config(port: u16, dir: &Path) -> CellConfig {
    let text = format!(
        r#"
cell = "doors"
[bus]
listen = ["tcp/127.0.0.1:{port}"]
[programs]
dir = {:?}
settle_ms = 300
watch = "poll"
poll_ms = 200
[[machines]]
name = "mill-1"
protocol = "a"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
sim = {{ consume_rate = 4000 }}
drop_dir = {:?}
"#,
        dir.join("programs"),
        dir.join("drop-mill-1"),
    );
    CellConfig::from_toml_str(&text, "doors cell").unwrap_or_else(|e| panic!("{e}"))
}

/// What the library says until `n` refusals were said (other things said are kept too).
async fn refusals(library: &Library, n: usize) -> Vec<Said> {
    let mut said = Vec::new();
    while said.iter().filter(|s: &&Said| s.kind == "refused").count() < n {
        said.push(library.next().await);
    }
    said
}

async fn listing(cell: &RunningCell) -> Vec<pb::ProgramInfo> {
    get(&cell.client, &cell.keys.any_program(), None)
        .await
        .into_iter()
        .map(|r| r.unwrap_or_else(|e| panic!("{e:?}")))
        .map(|(_, bytes, _)| pb::ProgramInfo::decode(bytes.as_slice()).unwrap())
        .collect()
}

fn mkfifo(path: &Path) {
    let c = std::ffi::CString::new(path.as_os_str().as_bytes()).unwrap();
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0, "mkfifo");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn links_and_a_fifo_in_the_folder_are_refused_visibly_and_never_read() {
    let cell = RunningCell::start(cell_config, false).await;
    let library = Library::follow(&cell).await;
    let dir = programs(&cell);
    let outside = cell.dir.path().join("outside");
    std::fs::create_dir(&outside).unwrap();
    let secret = b"-----BEGIN PRIVATE KEY-----\nMC4CAQAwBQYDK2VwBCIEIK\n".to_vec();
    std::fs::write(outside.join("key.pem"), &secret).unwrap();
    std::fs::write(outside.join("O7100.nc"), program(7100, 3)).unwrap();
    // The target belongs to someone else, where the test may say so: the link's owner (the
    // test's user) is who is credited, never the target's.
    let me = nix::unistd::User::from_uid(nix::unistd::getuid())
        .unwrap()
        .unwrap();
    if nix::unistd::getuid().is_root() {
        std::os::unix::fs::chown(outside.join("key.pem"), Some(65534), Some(65534)).unwrap();
    }

    std::os::unix::fs::symlink(outside.join("key.pem"), dir.join("KEY2")).unwrap();
    std::os::unix::fs::symlink(outside.join("O7100.nc"), dir.join("O7100.nc")).unwrap();
    mkfifo(&dir.join("O7101.nc"));
    let said = refusals(&library, 3).await;
    let refused: Vec<&Said> = said.iter().filter(|s| s.kind == "refused").collect();
    assert!(said.iter().all(|s| s.kind == "refused"), "{said:?}");
    for (file, what) in [
        ("KEY2", "symbolic link"),
        ("O7100.nc", "symbolic link"),
        ("O7101.nc", "FIFO"),
    ] {
        let e = refused
            .iter()
            .find(|s| s.file == file)
            .unwrap_or_else(|| panic!("{file} not said: {said:?}"));
        assert_eq!(e.code, pb::ErrorCode::InvalidRequest, "{e:?}");
        assert!(e.error.contains(what), "{}", e.error);
        assert_eq!(e.by.as_ref().unwrap().user, me.name, "{e:?}");
    }
    // Said once, though the folder is listed every 200 ms.
    library.quiet(1000).await;

    // Never served, never sent: the library has no such program.
    for name in ["KEY2", "O7100", "O7101"] {
        let err = get_err(&cell.client, &cell.keys.program(name), None).await;
        assert_eq!(err.code(), pb::ErrorCode::NotFound, "{name}: {err:?}");
    }
    assert!(
        std::fs::read_dir(dir.join(".revisions/objects"))
            .unwrap()
            .next()
            .is_none(),
        "content copied in"
    );
    let listed = listing(&cell).await;
    for (file, what) in [
        ("KEY2", "symbolic link"),
        ("O7100.nc", "symbolic link"),
        ("O7101.nc", "FIFO"),
    ] {
        let e = listed
            .iter()
            .find(|p| p.file == file)
            .unwrap_or_else(|| panic!("{file} not listed: {listed:?}"));
        assert!(e.name.is_empty() && e.note.contains(what), "{e:?}");
    }
    // Audited as refused stores from the folder, by the links' owner. Refusals of one kind
    // are gathered per minute: the first is recorded at once, the rest with the minute's
    // summary.
    audit_until(&cell, |records| {
        records.iter().any(|a| {
            a.action == "program.store"
                && ["KEY2", "O7100", "O7101"].contains(&a.target.as_str())
                && !a.ok
                && a.code == pb::ErrorCode::InvalidRequest as i32
                && a.key.starts_with("folder:")
                && a.origin.as_ref().is_some_and(|o| o.user == me.name)
        })
    })
    .await;

    // The watcher and the library go on: a regular file is taken, the FIFO never opened.
    let part = program(7102, 3);
    std::fs::write(dir.join("O7102.nc"), &part).unwrap();
    let e = library.next().await;
    assert_eq!((e.kind, e.name.as_str()), ("stored", "O7102"), "{e:?}");
    assert_eq!(read(&cell, "O7102").await, part);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_folder_removed_and_made_again_stores_again_without_a_restart() {
    let cell = RunningCell::start(cell_config, false).await;
    let library = Library::follow(&cell).await;
    let dir = programs(&cell);
    let store = |name: &str, bytes: Vec<u8>| {
        let write = pb::ProgramWrite {
            op: Some(pb::program_write::Op::Store(bytes)),
            ..Default::default()
        };
        (cell.keys.program_write(name), write.encode_to_vec())
    };
    let (key, payload) = store("O7200", program(7200, 3));
    let _: pb::ProgramInfo = get_one(&cell.client, &key, Some(payload)).await;
    let kept: pb::ProgramRevisions =
        get_one(&cell.client, &cell.keys.program_revisions("O7200"), None).await;
    assert_eq!(kept.revisions.len(), 1);

    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::create_dir(&dir).unwrap();
    // Its revisions went with the folder, content and all: not listed as if they were there.
    let err = get_err(&cell.client, &cell.keys.program_revisions("O7200"), None).await;
    assert_eq!(err.code(), pb::ErrorCode::NotFound, "{err:?}");
    // A store works, without a restart.
    let part = program(7201, 4);
    let (key, payload) = store("O7201", part.clone());
    let info: pb::ProgramInfo = get_one(&cell.client, &key, Some(payload)).await;
    assert_eq!(info.latest.unwrap().number, 1);
    assert_eq!(read(&cell, "O7201").await, part);
    assert!(dir.join(".revisions/index.redb").is_file());
    // And the new folder is followed: a posted file becomes a revision.
    let posted = program(7202, 5);
    std::fs::write(dir.join("O7202.nc"), &posted).unwrap();
    loop {
        let e = library.next().await;
        if e.name == "O7202" {
            assert_eq!(e.kind, "stored", "{e:?}");
            break;
        }
    }
    assert_eq!(read(&cell, "O7202").await, posted);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn extensions_in_any_case_are_taken_and_names_that_give_no_program_are_said() {
    let cell = RunningCell::start(cell_config, false).await;
    let library = Library::follow(&cell).await;
    let dir = programs(&cell);
    for (file, o) in [("O2006.Nc", 2006), ("O2007.nC", 2007)] {
        std::fs::write(dir.join(file), program(o, 2)).unwrap();
        let e = library.next().await;
        assert_eq!(
            (e.kind, e.name.as_str(), e.file.as_str()),
            ("stored", format!("O{o}").as_str(), file),
            "{e:?}"
        );
    }
    assert_eq!(read(&cell, "O2006").await, program(2006, 2));

    let long = format!("{}.nc", "B".repeat(200));
    let bad: Vec<(Vec<u8>, &str, &str)> = vec![
        (b"O 1.nc".to_vec(), "O 1.nc", "use only letters"),
        (
            b"-O2.nc".to_vec(),
            "-O2.nc",
            "start with a letter or a digit",
        ),
        (b"O3\n.nc".to_vec(), "O3\\n.nc", "use only letters"),
        (b"O4\xFF.nc".to_vec(), "O4\\xFF.nc", "not UTF-8"),
        (long.clone().into_bytes(), long.as_str(), "longer than 128"),
    ];
    for (raw, _, _) in &bad {
        std::fs::write(dir.join(std::ffi::OsStr::from_bytes(raw)), b"%\nO1\n%\n").unwrap();
    }
    // Hidden and temporary files stay unsaid, as documented.
    std::fs::write(dir.join(".x"), b"%\n%\n").unwrap();
    std::fs::write(dir.join("O5.nc.tmp"), b"%\n%\n").unwrap();
    std::fs::write(dir.join("~O6"), b"%\n%\n").unwrap();
    let said = refusals(&library, bad.len()).await;
    assert_eq!(said.len(), bad.len(), "{said:?}");
    for (_, shown, why) in &bad {
        let e = said
            .iter()
            .find(|s| s.file == *shown)
            .unwrap_or_else(|| panic!("{shown} not said: {said:?}"));
        assert_eq!(e.code, pb::ErrorCode::InvalidRequest);
        assert!(e.error.contains(why), "{}", e.error);
    }
    library.quiet(1000).await;
    let listed = listing(&cell).await;
    for (_, shown, why) in &bad {
        assert!(
            listed
                .iter()
                .any(|p| p.name.is_empty() && p.file == *shown && p.note.contains(why)),
            "{shown}: {listed:?}"
        );
    }
    // Nothing says the taken ones are still being written; hidden files are not listed.
    assert!(
        listed
            .iter()
            .all(|p| !p.note.contains("still being written")),
        "{listed:?}"
    );
    assert_eq!(listed.len(), 2 + bad.len(), "{listed:?}");
    // Audited (the first at once, the rest of the minute's with its summary).
    audit_until(&cell, |records| {
        records.iter().any(|a| {
            a.action == "program.store"
                && !a.ok
                && a.key.starts_with("folder:")
                && bad.iter().any(|(_, shown, _)| a.target == *shown)
        })
    })
    .await;
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_large_sparse_file_is_copied_for_what_it_holds() {
    use std::io::{Seek as _, Write as _};
    use std::os::unix::fs::MetadataExt as _;
    let cell = RunningCell::start(cell_config, false).await;
    let library = Library::follow(&cell).await;
    let dir = programs(&cell);
    // 100 MiB (programs.max_size is 512 MiB), of which a few bytes are written: posted under
    // a temporary name and renamed, so it is whole when it appears.
    let temp = dir.join("O7300.nc.tmp");
    let mut f = std::fs::File::create(&temp).unwrap();
    f.write_all(b"%\nO7300\n").unwrap();
    f.set_len(100 << 20).unwrap();
    f.seek(std::io::SeekFrom::End(-6)).unwrap();
    f.write_all(b"\nM30\n%").unwrap();
    drop(f);
    std::fs::rename(&temp, dir.join("O7300.nc")).unwrap();
    let e = library.next().await;
    assert_eq!((e.kind, e.name.as_str()), ("stored", "O7300"), "{e:?}");
    assert_eq!(e.size, 100 << 20);
    let kept: pb::ProgramRevisions =
        get_one(&cell.client, &cell.keys.program_revisions("O7300"), None).await;
    let object = dir
        .join(".revisions/objects")
        .join(&kept.revisions[0].sha256);
    let meta = std::fs::metadata(&object).unwrap();
    assert_eq!(meta.len(), 100 << 20);
    // Its copy holds what the file holds: written whole, it would take 100 MiB of disk.
    assert!(
        meta.blocks() * 512 < 4 << 20,
        "{} bytes on disk",
        meta.blocks() * 512
    );
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_link_in_a_drop_folder_is_refused_not_sent() {
    let cell = RunningCell::start(cell_config, false).await;
    let drop_dir = cell.dir.path().join("drop-mill-1");
    let events = cell.subscribe(cell.keys.job_events("mill-1", "*")).await;
    std::fs::create_dir_all(&drop_dir).unwrap();
    let outside = cell.dir.path().join("O7400.nc");
    std::fs::write(&outside, program(7400, 3)).unwrap();
    std::os::unix::fs::symlink(&outside, drop_dir.join("O7400.nc")).unwrap();
    common::bus::eventually("the link is in refused/", || {
        std::fs::symlink_metadata(drop_dir.join("refused/O7400.nc"))
            .is_ok_and(|m| m.file_type().is_symlink())
    })
    .await;
    let why = std::fs::read_to_string(drop_dir.join("refused/O7400.nc.why.txt")).unwrap();
    assert!(why.contains("symbolic link"), "{why}");
    // What it named is untouched, and no job was made of it.
    assert_eq!(std::fs::read(&outside).unwrap(), program(7400, 3));
    assert!(events.try_recv().unwrap().is_none(), "a job was made of it");
    cell.stop().await;
}
