use std::ffi::OsStr;
use std::io::Write as _;

use super::*;

fn watch(dir: &Path, mode: Watch) -> FolderWatch {
    FolderWatch {
        dir: dir.to_path_buf(),
        watch: mode,
        settle_ms: 300,
        poll: Duration::from_millis(50),
        takes: Arc::new(|f: &OsStr| match f.to_str() {
            Some(f) if !cellgate_core::program::folder::is_temporary(f) => Verdict::Take,
            _ => Verdict::Pass,
        }),
    }
}

/// The next report, within 5 s.
/// The next report but the listings, within 5 s.
async fn next(rx: &mut mpsc::Receiver<Seen>) -> Seen {
    loop {
        let seen = tokio::time::timeout(Duration::from_secs(5), rx.recv())
            .await
            .expect("a report within 5 s")
            .expect("the watcher runs");
        if seen != Seen::Listed {
            return seen;
        }
    }
}

/// Nothing reported for `ms`.
async fn quiet(rx: &mut mpsc::Receiver<Seen>, ms: u64) {
    let until = tokio::time::Instant::now() + Duration::from_millis(ms);
    while let Ok(seen) = tokio::time::timeout_at(until, rx.recv()).await {
        assert_eq!(seen, Some(Seen::Listed), "unexpected report");
    }
}

fn program(n: usize) -> Vec<u8> {
    let mut p = b"%\nO0001\n".to_vec();
    for i in 0..n {
        p.extend_from_slice(format!("N{i} G01 X{i}.0\n").as_bytes());
    }
    p.extend_from_slice(b"M30\n%\n");
    p
}

async fn a_slow_writer_is_taken_whole(mode: Watch) {
    let dir = tempfile::tempdir().unwrap();
    let stop = CancellationToken::new();
    let Followed { seen: mut rx, .. } = watch(dir.path(), mode).spawn(stop.clone());
    let whole = program(400);
    let path = dir.path().join("O0001.nc");
    let mut file = std::fs::File::create(&path).unwrap();
    // Written in place in 8 pieces, 120 ms apart: a CAM post that takes about a second.
    for piece in whole.chunks(whole.len().div_ceil(8)) {
        file.write_all(piece).unwrap();
        file.flush().unwrap();
        tokio::time::sleep(Duration::from_millis(120)).await;
    }
    drop(file);
    assert_eq!(
        next(&mut rx).await,
        Seen::Complete {
            file: "O0001.nc".into()
        }
    );
    // What is there when it is reported is all of it.
    assert_eq!(std::fs::read(&path).unwrap(), whole);
    quiet(&mut rx, 600).await;
    stop.cancel();
}

#[tokio::test]
async fn a_slow_writer_is_taken_whole_with_events() {
    a_slow_writer_is_taken_whole(Watch::Auto).await;
}

#[tokio::test]
async fn a_slow_writer_is_taken_whole_when_polling() {
    a_slow_writer_is_taken_whole(Watch::Poll).await;
}

#[tokio::test]
async fn a_file_renamed_into_place_is_taken_and_its_temporary_never() {
    let dir = tempfile::tempdir().unwrap();
    let stop = CancellationToken::new();
    let Followed { seen: mut rx, .. } = watch(dir.path(), Watch::Auto).spawn(stop.clone());
    let temp = dir.path().join("O0002.nc.tmp");
    std::fs::write(&temp, program(50)).unwrap();
    tokio::time::sleep(Duration::from_millis(500)).await;
    std::fs::rename(&temp, dir.path().join("O0002.nc")).unwrap();
    assert_eq!(
        next(&mut rx).await,
        Seen::Complete {
            file: "O0002.nc".into()
        }
    );
    std::fs::remove_file(dir.path().join("O0002.nc")).unwrap();
    assert_eq!(
        next(&mut rx).await,
        Seen::Gone {
            file: "O0002.nc".into()
        }
    );
    quiet(&mut rx, 500).await;
    stop.cancel();
}

#[tokio::test]
async fn files_there_at_start_are_taken_at_once_and_an_edit_again() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("O0003");
    std::fs::write(&path, program(5)).unwrap();
    let old = std::time::SystemTime::now() - Duration::from_secs(60);
    std::fs::File::options()
        .write(true)
        .open(&path)
        .unwrap()
        .set_modified(old)
        .unwrap();
    let stop = CancellationToken::new();
    let started = std::time::Instant::now();
    let Followed { seen: mut rx, .. } = watch(dir.path(), Watch::Auto).spawn(stop.clone());
    assert_eq!(
        next(&mut rx).await,
        Seen::Complete {
            file: "O0003".into()
        }
    );
    assert!(
        started.elapsed() < Duration::from_millis(300),
        "not waited for"
    );
    std::fs::write(&path, program(6)).unwrap();
    // Taken before, rewritten: said to be changing, then complete again.
    assert_eq!(
        next(&mut rx).await,
        Seen::Changing {
            file: "O0003".into()
        }
    );
    assert_eq!(
        next(&mut rx).await,
        Seen::Complete {
            file: "O0003".into()
        }
    );
    stop.cancel();
}

#[tokio::test]
async fn an_unreadable_folder_is_said_and_followed_once_it_is_there() {
    let parent = tempfile::tempdir().unwrap();
    let dir = parent.path().join("share");
    let stop = CancellationToken::new();
    let Followed { seen: mut rx, .. } = watch(&dir, Watch::Auto).spawn(stop.clone());
    assert!(matches!(next(&mut rx).await, Seen::Unreadable { .. }));
    std::fs::create_dir(&dir).unwrap();
    std::fs::write(dir.join("O0004.tap"), program(3)).unwrap();
    assert_eq!(next(&mut rx).await, Seen::Readable);
    assert_eq!(
        next(&mut rx).await,
        Seen::Complete {
            file: "O0004.tap".into()
        }
    );
    stop.cancel();
}

#[tokio::test]
async fn watch_off_takes_what_is_there_at_start_then_ends() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("O0005"), program(3)).unwrap();
    let stop = CancellationToken::new();
    let Followed {
        seen: mut rx, task, ..
    } = watch(dir.path(), Watch::Off).spawn(stop.clone());
    // Fresh: taken once still for settle_ms; a file posted later is not looked for.
    assert_eq!(
        next(&mut rx).await,
        Seen::Complete {
            file: "O0005".into()
        }
    );
    tokio::time::timeout(Duration::from_secs(5), task)
        .await
        .unwrap()
        .unwrap();
    std::fs::write(dir.path().join("O0006"), program(3)).unwrap();
    while let Some(seen) = rx.recv().await {
        assert_eq!(seen, Seen::Listed);
    }
}

#[tokio::test]
async fn a_folder_named_relative_to_the_working_directory_is_followed_by_its_events() {
    // Tests run in the package's directory: a folder under target/, named relative to it.
    std::fs::create_dir_all("target").unwrap();
    let dir = tempfile::tempdir_in("target").unwrap();
    let relative = Path::new("target").join(dir.path().file_name().unwrap());
    let stop = CancellationToken::new();
    let mut w = watch(&relative, Watch::Auto);
    // No listing within the test: only the events can report the file.
    w.poll = Duration::from_secs(600);
    let Followed { seen: mut rx, .. } = w.spawn(stop.clone());
    tokio::time::sleep(Duration::from_millis(200)).await;
    std::fs::write(relative.join("O0007.nc"), program(3)).unwrap();
    assert_eq!(
        next(&mut rx).await,
        Seen::Complete {
            file: "O0007.nc".into()
        }
    );
    stop.cancel();
}

/// A watch that refuses names with a space, as the library refuses names that give no
/// program.
fn refusing(dir: &Path, mode: Watch) -> FolderWatch {
    let mut w = watch(dir, mode);
    w.takes = Arc::new(|f: &OsStr| match f.to_str() {
        None => Verdict::Refuse("not UTF-8".to_string()),
        Some(f) if cellgate_core::program::folder::is_temporary(f) => Verdict::Pass,
        Some(f) if f.contains(' ') => Verdict::Refuse("a space".to_string()),
        Some(_) => Verdict::Take,
    });
    w
}

async fn links_fifos_and_refused_names_are_reported_once(mode: Watch) {
    use std::os::unix::ffi::OsStrExt as _;
    let parent = tempfile::tempdir().unwrap();
    let dir = parent.path().join("folder");
    std::fs::create_dir(&dir).unwrap();
    std::fs::write(parent.path().join("outside.nc"), program(3)).unwrap();
    let stop = CancellationToken::new();
    let Followed { seen: mut rx, .. } = refusing(&dir, mode).spawn(stop.clone());
    tokio::time::sleep(Duration::from_millis(100)).await;
    std::os::unix::fs::symlink(parent.path().join("outside.nc"), dir.join("O0010.nc")).unwrap();
    let fifo =
        std::ffi::CString::new(dir.join("O0011.nc").into_os_string().into_encoded_bytes()).unwrap();
    assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o644) }, 0);
    std::fs::write(dir.join("O 12.nc"), program(3)).unwrap();
    std::fs::write(dir.join(OsStr::from_bytes(b"O13\xFF.nc")), program(3)).unwrap();
    std::fs::create_dir(dir.join("O0014")).unwrap();
    let mut said = BTreeMap::new();
    while said.len() < 4 {
        match next(&mut rx).await {
            Seen::Refused { file, why } => {
                assert!(said.insert(file.clone(), why).is_none(), "{file:?} twice");
            }
            other => panic!("unexpected: {other:?}"),
        }
    }
    assert!(
        said[OsStr::new("O0010.nc")].contains("symbolic link"),
        "{said:?}"
    );
    assert!(said[OsStr::new("O0011.nc")].contains("FIFO"), "{said:?}");
    assert_eq!(said[OsStr::new("O 12.nc")], "a space");
    assert_eq!(said[OsStr::from_bytes(b"O13\xFF.nc")], "not UTF-8");
    // Listed again and again (polling every 50 ms), written to: said once. A directory is
    // passed over.
    std::fs::write(dir.join("O 12.nc"), program(4)).unwrap();
    quiet(&mut rx, 600).await;
    // The link replaced by a regular file: taken as any file is.
    std::fs::remove_file(dir.join("O0010.nc")).unwrap();
    std::fs::write(dir.join("O0010.nc"), program(5)).unwrap();
    assert_eq!(
        next(&mut rx).await,
        Seen::Complete {
            file: "O0010.nc".into()
        }
    );
    stop.cancel();
}

#[tokio::test]
async fn links_fifos_and_refused_names_are_reported_once_with_events() {
    links_fifos_and_refused_names_are_reported_once(Watch::Auto).await;
}

#[tokio::test]
async fn links_fifos_and_refused_names_are_reported_once_when_polling() {
    links_fifos_and_refused_names_are_reported_once(Watch::Poll).await;
}

#[tokio::test]
async fn a_folder_removed_and_made_again_is_followed_by_its_events() {
    let parent = tempfile::tempdir().unwrap();
    let dir = parent.path().join("folder");
    std::fs::create_dir(&dir).unwrap();
    let stop = CancellationToken::new();
    let mut w = watch(&dir, Watch::Auto);
    // No listing within the test but those the watcher makes itself.
    w.poll = Duration::from_secs(600);
    let Followed { seen: mut rx, .. } = w.spawn(stop.clone());
    tokio::time::sleep(Duration::from_millis(200)).await;
    std::fs::write(dir.join("O0020.nc"), program(3)).unwrap();
    assert_eq!(
        next(&mut rx).await,
        Seen::Complete {
            file: "O0020.nc".into()
        }
    );
    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::create_dir(&dir).unwrap();
    // The file went with the folder; one posted into the new folder is seen by its events.
    let mut gone = false;
    loop {
        match next(&mut rx).await {
            Seen::Gone { file } if file == "O0020.nc" => gone = true,
            Seen::Unreadable { .. } | Seen::Readable => {}
            other => panic!("unexpected: {other:?}"),
        }
        if gone {
            break;
        }
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    std::fs::write(dir.join("O0021.nc"), program(3)).unwrap();
    loop {
        match next(&mut rx).await {
            Seen::Complete { file } => {
                assert_eq!(file, "O0021.nc");
                break;
            }
            Seen::Unreadable { .. } | Seen::Readable => {}
            other => panic!("unexpected: {other:?}"),
        }
    }
    stop.cancel();
}
