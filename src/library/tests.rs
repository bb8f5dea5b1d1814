use super::*;
use cellgate_core::pb::RevisionState;

#[test]
fn names_are_one_safe_key_chunk() {
    for ok in ["O1234", "part-7.nc", "a", "X_1+2", &"n".repeat(128)] {
        assert!(validate_name(ok).is_ok(), "{ok}");
    }
    for bad in [
        "",
        ".",
        "..",
        "../etc",
        "a/b",
        ".hidden",
        "-x",
        "a*",
        "**",
        "a$b",
        "a?b",
        "a#b",
        "sp ace",
        "@admin",
        "é",
        &"n".repeat(129),
    ] {
        assert!(validate_name(bad).is_err(), "{bad:?}");
    }
}

#[tokio::test]
async fn store_read_list_remove() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 100);
    assert!(lib.list().await.unwrap().is_empty());
    let e = lib.store("O1", b"%\nO1\n%").await.unwrap();
    assert_eq!(e.size, 6);
    lib.store("O2", b"%\nO2\n%").await.unwrap();
    lib.store("O1", b"%\nO1\nM30\n%").await.unwrap();
    assert_eq!(lib.read("O1").await.unwrap(), b"%\nO1\nM30\n%");
    let names: Vec<_> = lib
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|e| e.name)
        .collect();
    assert_eq!(names, ["O1", "O2"]);
    lib.remove("O1").await.unwrap();
    // Removed, and said so: its revisions are kept.
    assert!(matches!(
        lib.read("O1").await,
        Err(LibraryError::Removed { latest: 2, .. })
    ));
    assert!(matches!(
        lib.remove("O1").await,
        Err(LibraryError::NotFound { .. })
    ));
    assert!(matches!(
        lib.store("big", &[b'x'; 101]).await,
        Err(LibraryError::TooLarge { size: 101, .. })
    ));
    assert!(matches!(
        lib.store("../x", b"x").await,
        Err(LibraryError::InvalidName { .. })
    ));
    // No temporary file is left behind, and stray files are not listed.
    std::fs::write(dir.path().join(".junk"), b"x").unwrap();
    let names: Vec<_> = lib
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|e| e.name)
        .collect();
    assert_eq!(names, ["O2"]);
}

#[tokio::test]
async fn store_new_never_replaces() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 100);
    lib.store_new("m-O1", b"%\nO1\n%").await.unwrap();
    assert!(matches!(
        lib.store_new("m-O1", b"%\nO1\nM30\n%").await,
        Err(LibraryError::Exists { .. })
    ));
    assert_eq!(lib.read("m-O1").await.unwrap(), b"%\nO1\n%");
    // Racing writers: exactly one wins each name, and no temporary file is left.
    let tries = (0..8).map(|i| {
        let lib = lib.clone();
        tokio::spawn(async move { lib.store_new("m-O2", format!("%{i}%").as_bytes()).await })
    });
    let mut won = 0;
    for t in tries {
        if t.await.unwrap().is_ok() {
            won += 1;
        }
    }
    assert_eq!(won, 1);
    let mut files: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n != REVISIONS_DIR)
        .collect();
    files.sort();
    // Each in the file a CAM system would post: NAME.nc.
    assert_eq!(files, ["m-O1.nc", "m-O2.nc"]);
    let temp = std::fs::read_dir(dir.path().join(REVISIONS_DIR).join("objects"))
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .file_name()
                .to_string_lossy()
                .ends_with(".tmp")
        })
        .count();
    assert_eq!(temp, 0);
}

#[tokio::test]
async fn quotas_count_every_kept_revision_once_per_content() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 100).with_quota(Quota {
        bytes: Some(150),
        files: Some(2),
    });
    lib.store("A", &[b'x'; 60]).await.unwrap();
    // A's second revision: both are kept, so both count.
    lib.store("A", &[b'x'; 70]).await.unwrap();
    let e = lib.store("B", &[b'y'; 21]).await.unwrap_err();
    assert!(
        matches!(
            e,
            LibraryError::QuotaExceeded {
                what: "bytes",
                would: 151,
                limit: 150,
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("programs.quota_bytes = 150"), "{e}");
    // The same content as a kept revision takes no more room.
    lib.store("B", &[b'x'; 60]).await.unwrap();
    lib.store("B", &[b'y'; 20]).await.unwrap();
    let e = lib.store_new("C", b"z").await.unwrap_err();
    assert!(
        matches!(
            e,
            LibraryError::QuotaExceeded {
                what: "files",
                would: 3,
                limit: 2,
                ..
            }
        ),
        "{e}"
    );
    // Nothing of the refused stores is left.
    let names: Vec<String> = lib
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|e| e.name)
        .collect();
    assert_eq!(names, ["A", "B"]);
    assert_eq!(
        std::fs::read_dir(dir.path().join(REVISIONS_DIR).join("objects"))
            .unwrap()
            .count(),
        3
    );
}

fn by(user: &str) -> pb::RequestOrigin {
    pb::RequestOrigin {
        user: user.to_string(),
        via: "test".to_string(),
    }
}

async fn store_by(lib: &ProgramLibrary, name: &str, bytes: &[u8], user: &str) -> ProgramEntry {
    lib.store_as(
        name,
        Store {
            bytes: bytes.into(),
            by: by(user),
            comment: format!("by {user}"),
            adopted: None,
        },
    )
    .await
    .unwrap()
}

#[tokio::test]
async fn every_store_makes_a_revision_readable_by_number_or_hash() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000);
    let one = store_by(&lib, "O1", b"%\nO1\nG00X0\n%", "alice").await;
    let r1 = one.latest.clone().unwrap();
    assert_eq!(r1.number, 1);
    assert_eq!(r1.sha256, sha256_hex(b"%\nO1\nG00X0\n%"));
    assert_eq!(r1.by.as_ref().unwrap().user, "alice");
    assert_eq!(r1.state(), RevisionState::Draft);
    let two = store_by(&lib, "O1", b"%\nO1\nG00X1\n%", "bob").await;
    assert_eq!(two.latest.as_ref().unwrap().number, 2);
    // The same bytes again make no revision.
    let again = store_by(&lib, "O1", b"%\nO1\nG00X1\n%", "carol").await;
    assert_eq!(again.latest.as_ref().unwrap().number, 2);
    assert_eq!(
        again.latest.as_ref().unwrap().by.as_ref().unwrap().user,
        "bob"
    );

    let revs = lib.revisions("O1").await.unwrap();
    let numbers: Vec<u32> = revs.revisions.iter().map(|r| r.number).collect();
    assert_eq!(numbers, [2, 1], "newest first");
    assert_eq!(lib.read("O1").await.unwrap(), b"%\nO1\nG00X1\n%");
    let (_, old) = lib.read_revision("O1", "1").await.unwrap();
    assert_eq!(old, b"%\nO1\nG00X0\n%");
    let (by_hash, _) = lib.read_revision("O1", &r1.sha256[..10]).await.unwrap();
    assert_eq!(by_hash.number, 1);
    let e = lib.read_revision("O1", "9").await.unwrap_err();
    assert!(matches!(e, LibraryError::NoRevision { .. }), "{e}");
    assert!(e.to_string().contains("its revisions are 1, 2"), "{e}");
    assert_eq!(e.code(), pb::ErrorCode::NotFound);

    // Across a restart (a new library on the same directory).
    drop(lib);
    let lib = ProgramLibrary::new(dir.path(), 1000);
    let revs = lib.revisions("O1").await.unwrap();
    assert_eq!(revs.revisions.len(), 2);
    let three = store_by(&lib, "O1", b"%\nO1\nG00X2\n%", "dave").await;
    assert_eq!(three.latest.unwrap().number, 3);
}

#[tokio::test]
async fn a_removed_program_keeps_its_revisions_and_numbers_go_on() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000);
    store_by(&lib, "O2", b"%\nA\n%", "a").await;
    lib.remove_by("O2").await.unwrap();
    assert!(matches!(
        lib.read("O2").await,
        Err(LibraryError::Removed { latest: 1, .. })
    ));
    let revs = lib.revisions("O2").await.unwrap();
    assert!(revs.removed);
    assert!(lib.read_revision("O2", "1").await.is_ok());
    // A job cannot take "the latest" of a removed program.
    assert!(matches!(
        lib.revision("O2", "").await,
        Err(LibraryError::Removed { .. })
    ));
    let back = store_by(&lib, "O2", b"%\nA\n%", "a").await;
    assert_eq!(back.latest.unwrap().number, 2);
}

#[tokio::test]
async fn release_lock_and_unlock_follow_the_rules_and_a_lock_holds() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000);
    store_by(&lib, "O3", b"%\nA\n%", "a").await;
    let r = lib
        .set_state(
            "O3",
            "",
            RevisionState::Released,
            by("qa"),
            "checked".into(),
        )
        .await
        .unwrap();
    assert_eq!(r.state(), RevisionState::Released);
    assert_eq!(r.state_by.as_ref().unwrap().user, "qa");
    assert_eq!(r.state_comment, "checked");
    let r = lib
        .set_state("O3", "1", RevisionState::Locked, by("qa"), String::new())
        .await
        .unwrap();
    assert_eq!(r.state(), RevisionState::Locked);
    // Locked: nothing replaces or removes it.
    let e = lib.store("O3", b"%\nB\n%").await.unwrap_err();
    assert!(matches!(e, LibraryError::Locked { number: 1, .. }), "{e}");
    assert_eq!(e.code(), pb::ErrorCode::Locked);
    let e = lib.remove_by("O3").await.unwrap_err();
    assert!(matches!(e, LibraryError::Locked { .. }), "{e}");
    assert_eq!(lib.read("O3").await.unwrap(), b"%\nA\n%");
    // Unlocking (state draft) leaves it released; again, a draft.
    let r = lib
        .set_state("O3", "1", RevisionState::Draft, by("qa"), String::new())
        .await
        .unwrap();
    assert_eq!(r.state(), RevisionState::Released);
    let r = lib
        .set_state("O3", "1", RevisionState::Draft, by("qa"), String::new())
        .await
        .unwrap();
    assert_eq!(r.state(), RevisionState::Draft);
    lib.store("O3", b"%\nB\n%").await.unwrap();
    let e = lib
        .set_state(
            "O3",
            "",
            RevisionState::Unspecified,
            by("qa"),
            String::new(),
        )
        .await
        .unwrap_err();
    assert!(matches!(e, LibraryError::Transition { .. }), "{e}");
}

#[tokio::test]
async fn retention_keeps_the_latest_the_latest_released_and_locked_ones() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000).with_retention(Retention {
        revisions: 2,
        days: None,
    });
    store_by(&lib, "O4", b"%\n1\n%", "a").await;
    lib.set_state("O4", "1", RevisionState::Released, by("qa"), String::new())
        .await
        .unwrap();
    store_by(&lib, "O4", b"%\n2\n%", "a").await;
    lib.set_state("O4", "2", RevisionState::Locked, by("qa"), String::new())
        .await
        .unwrap();
    lib.set_state("O4", "2", RevisionState::Draft, by("qa"), String::new())
        .await
        .unwrap();
    lib.set_state("O4", "2", RevisionState::Draft, by("qa"), String::new())
        .await
        .unwrap();
    for i in 3..=6 {
        store_by(&lib, "O4", format!("%\n{i}\n%").as_bytes(), "a").await;
    }
    let kept: Vec<u32> = lib
        .revisions("O4")
        .await
        .unwrap()
        .revisions
        .iter()
        .map(|r| r.number)
        .collect();
    // 5 and 6 are the newest two; 1 is the latest released.
    assert_eq!(kept, [6, 5, 1]);
    // The content of dropped revisions is gone, the rest is there.
    let objects = std::fs::read_dir(dir.path().join(REVISIONS_DIR).join("objects"))
        .unwrap()
        .count();
    assert_eq!(objects, 3);
}

#[tokio::test]
async fn a_program_is_adopted_from_another_and_says_where_from() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000);
    store_by(&lib, "O5", b"%\nOLD\n%", "a").await;
    lib.store_new("lathe-1-O5-20261201T000000Z", b"%\nPUNCHED\n%")
        .await
        .unwrap();
    let e = lib
        .adopt(
            "O5",
            "lathe-1-O5-20261201T000000Z",
            "",
            by("op"),
            String::new(),
        )
        .await
        .unwrap();
    let r = e.latest.unwrap();
    assert_eq!(r.number, 2);
    assert_eq!(r.adopted_from, "lathe-1-O5-20261201T000000Z");
    assert_eq!(r.adopted_revision, 1);
    assert!(r.comment.contains("adopted from"), "{}", r.comment);
    assert_eq!(lib.read("O5").await.unwrap(), b"%\nPUNCHED\n%");
}

fn folder(file: &str) -> FolderFile {
    FolderFile {
        file: file.to_string(),
        by: pb::RequestOrigin {
            user: "cam".to_string(),
            via: "folder".to_string(),
        },
    }
}

#[tokio::test]
async fn files_of_the_folder_become_revisions_under_their_name_without_extension() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000);
    lib.create_dir().await.unwrap();
    std::fs::write(dir.path().join("O6.nc"), b"%\nHAND\n%").unwrap();
    let Taken::Revision(e) = lib.take_file(folder("O6.nc")).await.unwrap() else {
        panic!("not taken");
    };
    assert_eq!(e.name, "O6");
    assert_eq!(e.file, "O6.nc");
    let r = e.latest.unwrap();
    assert_eq!((r.number, r.by.unwrap().user), (1, "cam".to_string()));
    assert_eq!(r.comment, "from the folder: O6.nc");
    // The same content again (the gateway's own write, a touch) is no revision.
    assert_eq!(
        lib.take_file(folder("O6.nc")).await.unwrap(),
        Taken::Unchanged
    );
    // Edited: the next revision; a job sends it.
    std::fs::write(dir.path().join("O6.nc"), b"%\nHAND 2\n%").unwrap();
    assert!(matches!(
        lib.take_file(folder("O6.nc")).await.unwrap(),
        Taken::Revision(_)
    ));
    assert_eq!(lib.read("O6").await.unwrap(), b"%\nHAND 2\n%");
    // A store through the bus writes the file the folder has, not a second one.
    lib.store("O6", b"%\nBUS\n%").await.unwrap();
    assert_eq!(
        std::fs::read(dir.path().join("O6.nc")).unwrap(),
        b"%\nBUS\n%"
    );
    assert!(!dir.path().join("O6").exists());
    // The listing gives the revision's size and the file.
    let listed = lib.list().await.unwrap();
    assert_eq!(listed.len(), 1);
    assert_eq!((listed[0].size, listed[0].file.as_str()), (7, "O6.nc"));
    // A name that ends in an extension is never a program of its own.
    assert!(matches!(
        lib.store("O7.nc", b"%\n%").await,
        Err(LibraryError::InvalidName { .. })
    ));
}

#[tokio::test]
async fn a_locked_program_is_not_replaced_or_removed_from_the_folder() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000);
    // A store writes O8.nc, the file a CAM system would post.
    lib.store("O8", b"%\nLOCKED\n%").await.unwrap();
    lib.set_state("O8", "", RevisionState::Locked, by("lead"), String::new())
        .await
        .unwrap();
    std::fs::write(dir.path().join("O8.nc"), b"%\nEDITED\n%").unwrap();
    let e = lib.take_file(folder("O8.nc")).await.unwrap_err();
    assert!(matches!(e, LibraryError::Locked { number: 1, .. }), "{e}");
    // The file is left as written; the library keeps sending the locked revision.
    assert_eq!(
        std::fs::read(dir.path().join("O8.nc")).unwrap(),
        b"%\nEDITED\n%"
    );
    assert_eq!(lib.read("O8").await.unwrap(), b"%\nLOCKED\n%");
    let listed = lib.list().await.unwrap();
    assert!(listed[0].note.contains("locked"), "{}", listed[0].note);
    std::fs::remove_file(dir.path().join("O8.nc")).unwrap();
    assert!(matches!(
        lib.file_gone("O8.nc").await,
        Err(LibraryError::Locked { .. })
    ));
    assert_eq!(lib.read("O8").await.unwrap(), b"%\nLOCKED\n%");
    assert_eq!(
        lib.list().await.unwrap().len(),
        1,
        "still listed without a file"
    );
}

#[tokio::test]
async fn a_deleted_file_removes_its_program_and_posting_it_again_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000);
    lib.create_dir().await.unwrap();
    std::fs::write(dir.path().join("O9.tap"), b"%\nONE\n%").unwrap();
    lib.take_file(folder("O9.tap")).await.unwrap();
    std::fs::remove_file(dir.path().join("O9.tap")).unwrap();
    let Taken::Removed(e) = lib.file_gone("O9.tap").await.unwrap() else {
        panic!("not removed");
    };
    assert!(e.latest.unwrap().removed);
    assert!(matches!(
        lib.read("O9").await,
        Err(LibraryError::Removed { latest: 1, .. })
    ));
    assert_eq!(lib.file_gone("O9.tap").await.unwrap(), Taken::Nothing);
    std::fs::write(dir.path().join("O9.tap"), b"%\nTWO\n%").unwrap();
    let Taken::Revision(e) = lib.take_file(folder("O9.tap")).await.unwrap() else {
        panic!("not taken");
    };
    assert_eq!(e.latest.unwrap().number, 2);
    // Deleted while the gateway was stopped: found missing at the next start.
    std::fs::remove_file(dir.path().join("O9.tap")).unwrap();
    assert_eq!(lib.files_missing().await.unwrap(), vec!["O9".to_string()]);
}

#[tokio::test]
async fn two_files_giving_one_name_are_a_conflict_and_neither_is_taken() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000);
    lib.create_dir().await.unwrap();
    std::fs::write(dir.path().join("O10.nc"), b"%\nA\n%").unwrap();
    std::fs::write(dir.path().join("O10.TAP"), b"%\nB\n%").unwrap();
    for f in ["O10.nc", "O10.TAP"] {
        let e = lib.take_file(folder(f)).await.unwrap_err();
        assert!(matches!(&e, LibraryError::Conflict { .. }), "{e}");
        assert_eq!(e.code(), pb::ErrorCode::Conflict);
    }
    assert!(matches!(
        lib.read("O10").await,
        Err(LibraryError::NotFound { .. })
    ));
    let listed = lib.list().await.unwrap();
    assert!(listed[0].note.contains("O10.TAP"), "{}", listed[0].note);
    assert!(matches!(
        lib.store("O10", b"%\nC\n%").await,
        Err(LibraryError::Conflict { .. })
    ));
    // One goes: the other stands.
    std::fs::remove_file(dir.path().join("O10.TAP")).unwrap();
    assert_eq!(lib.file_gone("O10.TAP").await.unwrap(), Taken::Nothing);
    assert_eq!(lib.file_of("O10").await.unwrap().as_deref(), Some("O10.nc"));
    assert!(matches!(
        lib.take_file(folder("O10.nc")).await.unwrap(),
        Taken::Revision(_)
    ));
}

#[tokio::test]
async fn temporary_files_of_an_earlier_run_are_removed_at_start() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 100);
    lib.store("KEEP", b"%\nO1\n%").await.unwrap();
    // What a crash between write and rename leaves, from another process id.
    let stale = dir.path().join(".O1234.999999999.3.tmp");
    std::fs::write(&stale, b"half a prog").unwrap();
    // A hidden file that is not a temporary file of the library stays.
    let other = dir.path().join(".keepme");
    std::fs::write(&other, b"").unwrap();
    lib.create_dir().await.unwrap();
    assert!(!stale.exists());
    assert!(other.exists());
    assert_eq!(lib.read("KEEP").await.unwrap(), b"%\nO1\n%");
}

#[tokio::test]
async fn the_gateways_own_files_are_never_listed_served_replaced_or_removed() {
    let dir = tempfile::tempdir().unwrap();
    // A journal in the library's folder, as a cell file moved under a running gateway has it.
    let journal = dir.path().join("jobs.redb");
    std::fs::write(&journal, b"live journal").unwrap();
    let lib = ProgramLibrary::new(dir.path(), 100)
        .with_owned(vec![dir.path().to_path_buf(), journal.clone()]);
    lib.store("O1", b"%\nO1\n%").await.unwrap();
    let names: Vec<String> = lib
        .list()
        .await
        .unwrap()
        .into_iter()
        .map(|e| e.name)
        .collect();
    assert_eq!(names, ["O1"]);
    assert!(matches!(
        lib.read("jobs.redb").await,
        Err(LibraryError::InvalidName { .. })
    ));
    assert!(matches!(
        lib.remove("jobs.redb").await,
        Err(LibraryError::InvalidName { .. })
    ));
    assert!(matches!(
        lib.store("jobs.redb", b"%\nO2\n%").await,
        Err(LibraryError::InvalidName { .. })
    ));
    assert_eq!(std::fs::read(&journal).unwrap(), b"live journal");
}

#[tokio::test]
async fn links_and_fifos_in_the_folder_are_never_taken_opened_or_served() {
    let dir = tempfile::tempdir().unwrap();
    let programs = dir.path().join("programs");
    let lib = ProgramLibrary::new(&programs, 1000);
    lib.create_dir().await.unwrap();
    // Outside the folder: what a link there would leak, and a program a link would send.
    std::fs::write(dir.path().join("key.pem"), b"%\nSECRET\n%").unwrap();
    std::os::unix::fs::symlink(dir.path().join("key.pem"), programs.join("KEY2")).unwrap();
    std::os::unix::fs::symlink(dir.path().join("key.pem"), programs.join("O8.nc")).unwrap();
    let fifo = std::ffi::CString::new(programs.join("O9.nc").into_os_string().into_encoded_bytes())
        .unwrap();
    assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o644) }, 0);

    for file in ["KEY2", "O8.nc", "O9.nc"] {
        match lib.take_file(folder(file)).await {
            // A link or FIFO is no program's file: refused by its own name, or not found.
            Err(LibraryError::NotTaken { file: f, why }) => {
                assert_eq!(f, file);
                assert!(
                    why.contains("symbolic link") || why.contains("FIFO"),
                    "{why}"
                );
            }
            Ok(Taken::Nothing) => {}
            other => panic!("{file}: {other:?}"),
        }
    }
    // The plain name is opened as it is: refused, never read.
    assert!(matches!(
        lib.take_file(folder("KEY2")).await,
        Err(LibraryError::NotTaken { .. })
    ));
    for name in ["KEY2", "O8", "O9"] {
        assert!(matches!(
            lib.read(name).await,
            Err(LibraryError::NotFound { .. })
        ));
        assert!(lib.open(name).await.is_err(), "{name} opened");
        assert_eq!(lib.file_of(name).await.unwrap(), None, "{name}");
    }
    assert!(
        std::fs::read_dir(programs.join(".revisions/objects"))
            .unwrap()
            .next()
            .is_none()
    );
    // The listing says what each is, with no program name.
    let listed = lib.list().await.unwrap();
    for (file, what) in [
        ("KEY2", "symbolic link"),
        ("O8.nc", "symbolic link"),
        ("O9.nc", "FIFO"),
    ] {
        let e = listed
            .iter()
            .find(|e| e.file == file)
            .unwrap_or_else(|| panic!("{file} not listed: {listed:?}"));
        assert_eq!(e.name, "");
        assert!(e.note.contains(what), "{}", e.note);
        assert!(e.latest.is_none());
    }
    // A store through the bus replaces the link itself, never what it names.
    lib.store("O8", b"%\nBUS\n%").await.unwrap();
    assert_eq!(
        std::fs::read(dir.path().join("key.pem")).unwrap(),
        b"%\nSECRET\n%"
    );
    assert_eq!(lib.read("O8").await.unwrap(), b"%\nBUS\n%");
}

#[tokio::test]
async fn an_extension_in_any_case_is_a_programs_file() {
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000);
    lib.create_dir().await.unwrap();
    std::fs::write(dir.path().join("O2006.Nc"), b"%\nO2006\n%").unwrap();
    std::fs::write(dir.path().join("O2007.tAp"), b"%\nO2007\n%").unwrap();
    for (file, name) in [("O2006.Nc", "O2006"), ("O2007.tAp", "O2007")] {
        let Taken::Revision(e) = lib.take_file(folder(file)).await.unwrap() else {
            panic!("{file} not taken");
        };
        assert_eq!((e.name.as_str(), e.file.as_str()), (name, file));
        assert_eq!(lib.file_of(name).await.unwrap().as_deref(), Some(file));
    }
    // A second spelling of the same name beside the file of its latest revision takes that
    // file's place, as another extension does: one program, one file.
    std::fs::write(dir.path().join("O2006.nC"), b"%\nO2006 B\n%").unwrap();
    assert!(matches!(
        lib.take_file(folder("O2006.nC")).await,
        Ok(Taken::Revision(_))
    ));
    assert!(!dir.path().join("O2006.Nc").exists());
    // Two spellings that both differ from it are a conflict, as two extensions are.
    std::fs::write(dir.path().join("O2006.NC"), b"%\nO2006 C\n%").unwrap();
    std::fs::write(dir.path().join("O2006.nc"), b"%\nO2006 D\n%").unwrap();
    assert!(matches!(
        lib.take_file(folder("O2006.NC")).await,
        Err(LibraryError::Conflict { .. })
    ));
    let listed = lib.list().await.unwrap();
    assert!(
        listed
            .iter()
            .all(|e| !e.note.contains("still being written")),
        "{listed:?}"
    );
}

#[tokio::test]
async fn names_that_give_no_program_are_listed_with_why_and_hidden_ones_are_not() {
    use std::os::unix::ffi::OsStrExt as _;
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 1000);
    lib.create_dir().await.unwrap();
    let long = format!("{}.nc", "A".repeat(200));
    let files: Vec<&[u8]> = vec![
        b"O 1.nc",
        b"-O2.nc",
        b"O3\n.nc",
        b"O4\xFF.nc",
        long.as_bytes(),
        b".hidden",
        b"O5.nc.tmp",
        b"~O6",
    ];
    for f in &files {
        std::fs::write(dir.path().join(std::ffi::OsStr::from_bytes(f)), b"%\n%").unwrap();
    }
    let listed = lib.list().await.unwrap();
    let shown: Vec<(&str, &str)> = listed
        .iter()
        .map(|e| (e.file.as_str(), e.note.as_str()))
        .collect();
    for (file, why) in [
        ("O 1.nc", "use only letters"),
        ("-O2.nc", "start with a letter or a digit"),
        ("O3\\n.nc", "use only letters"),
        ("O4\\xFF.nc", "not UTF-8"),
        (long.as_str(), "longer than 128"),
    ] {
        assert!(
            shown.iter().any(|(f, n)| *f == file && n.contains(why)),
            "{file}: {shown:?}"
        );
    }
    assert_eq!(
        listed.len(),
        5,
        "hidden and temporary files are not listed: {shown:?}"
    );
    assert!(listed.iter().all(|e| e.name.is_empty()));
    use crate::library::folder::Verdict;
    assert_eq!(
        lib.verdict(std::ffi::OsStr::new("O5.nc.tmp")),
        Verdict::Pass
    );
    assert!(matches!(
        lib.verdict(std::ffi::OsStr::from_bytes(b"O4\xFF.nc")),
        Verdict::Refuse(_)
    ));
}

#[tokio::test]
async fn a_folder_made_again_takes_stores_and_forgets_the_revisions_gone_with_it() {
    let dir = tempfile::tempdir().unwrap();
    let programs = dir.path().join("programs");
    let lib = ProgramLibrary::new(&programs, 1000);
    lib.create_dir().await.unwrap();
    lib.store("O1", b"%\nONE\n%").await.unwrap();
    std::fs::remove_dir_all(&programs).unwrap();
    // Gone with the folder: not served, not listed, nothing made meanwhile.
    assert!(matches!(
        lib.revisions("O1").await,
        Err(LibraryError::NotFound { .. })
    ));
    assert!(matches!(
        lib.read("O1").await,
        Err(LibraryError::NotFound { .. })
    ));
    assert!(lib.list().await.unwrap().is_empty());
    assert!(
        !programs.exists(),
        "the library made the folder again by itself"
    );
    std::fs::create_dir(&programs).unwrap();
    // Stores work again, in a new index of the new folder.
    let e = lib.store("O2", b"%\nTWO\n%").await.unwrap();
    assert_eq!(e.latest.unwrap().number, 1);
    assert_eq!(lib.read("O2").await.unwrap(), b"%\nTWO\n%");
    assert!(programs.join(".revisions/index.redb").is_file());
    assert!(matches!(
        lib.revisions("O1").await,
        Err(LibraryError::NotFound { .. })
    ));
    std::fs::write(programs.join("O3.nc"), b"%\nTHREE\n%").unwrap();
    assert!(matches!(
        lib.take_file(folder("O3.nc")).await.unwrap(),
        Taken::Revision(_)
    ));
    // Only the content removed by hand: the revision is said to have lost it, never served.
    lib.store("O2", b"%\nTWO B\n%").await.unwrap();
    std::fs::remove_dir_all(programs.join(".revisions/objects")).unwrap();
    for rev in ["1", "2"] {
        assert!(
            matches!(
                lib.read_revision("O2", rev).await,
                Err(LibraryError::ContentMissing { .. })
            ),
            "revision {rev}"
        );
        assert!(matches!(
            lib.revision("O2", rev).await,
            Err(LibraryError::ContentMissing { .. })
        ));
    }
    // And the next store makes the objects' directory again.
    lib.store("O4", b"%\nFOUR\n%").await.unwrap();
    assert_eq!(lib.read("O4").await.unwrap(), b"%\nFOUR\n%");
}

#[tokio::test]
async fn a_folder_file_is_copied_in_pieces_and_a_sparse_one_stays_sparse() {
    use std::io::{Seek as _, Write as _};
    use std::os::unix::fs::MetadataExt as _;
    let dir = tempfile::tempdir().unwrap();
    let lib = ProgramLibrary::new(dir.path(), 64 * 1024 * 1024);
    lib.create_dir().await.unwrap();
    // 48 MiB, of which a few bytes at each end are written.
    let path = dir.path().join("BIG.nc");
    let mut f = std::fs::File::create(&path).unwrap();
    f.write_all(b"%\nBIG\n").unwrap();
    f.set_len(48 * 1024 * 1024).unwrap();
    f.seek(std::io::SeekFrom::End(-3)).unwrap();
    f.write_all(b"\n%\n").unwrap();
    drop(f);
    let Taken::Revision(e) = lib.take_file(folder("BIG.nc")).await.unwrap() else {
        panic!("not taken");
    };
    let r = e.latest.unwrap();
    assert_eq!(r.size, 48 * 1024 * 1024);
    assert_eq!(r.sha256, sha256_file(&path).unwrap());
    let object = dir.path().join(".revisions/objects").join(&r.sha256);
    let meta = std::fs::metadata(&object).unwrap();
    assert_eq!(meta.len(), 48 * 1024 * 1024);
    // What it holds, not its size: a copy written whole would take 48 MiB of disk.
    assert!(
        meta.blocks() * 512 < 1024 * 1024,
        "{} bytes on disk",
        meta.blocks() * 512
    );
    assert_eq!(sha256_file(&object).unwrap(), r.sha256);
    // No temporary file is left.
    let names: Vec<String> = std::fs::read_dir(dir.path().join(".revisions/objects"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, vec![r.sha256.clone()]);
    // Over programs.max_size by its size: refused before it is read, nothing copied.
    drop(lib);
    let small = ProgramLibrary::new(dir.path(), 1024 * 1024);
    std::fs::write(dir.path().join("BIG.nc"), b"%\nEDIT\n").unwrap();
    std::fs::File::options()
        .write(true)
        .open(&path)
        .unwrap()
        .set_len(8 << 20)
        .unwrap();
    assert!(matches!(
        small.take_file(folder("BIG.nc")).await,
        Err(LibraryError::TooLarge { size, .. }) if size == 8 << 20
    ));
    let after = std::fs::read_dir(dir.path().join(".revisions/objects"))
        .unwrap()
        .count();
    assert_eq!(after, 1);
}
