use std::io::Write as _;

use super::*;

fn watch(dir: &Path, mode: Watch) -> FolderWatch {
    FolderWatch {
        dir: dir.to_path_buf(),
        watch: mode,
        settle_ms: 300,
        poll: Duration::from_millis(50),
        takes: Arc::new(|f: &str| !cellgate_core::program::folder::is_temporary(f)),
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
