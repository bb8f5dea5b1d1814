use super::*;

fn record(seq: u64, machine: &str, state: JobState) -> JobRecord {
    JobRecord {
        seq,
        id: format!("{machine}-x-{seq}"),
        machine: machine.to_string(),
        request_id: String::new(),
        name: "O1".to_string(),
        priority: 0,
        accepted_unix_ms: 1,
        file: seq.to_string(),
        file_len: 7,
        suffix: b"%".to_vec(),
        start: None,
        resume_after_restart: false,
        deadline_s: 0,
        state,
        acked: 0,
        last_event: Vec::new(),
        origin: Default::default(),
    }
}

#[test]
fn records_and_files_survive_reopening_and_go_together() {
    let dir = tempfile::tempdir().unwrap();
    let j = Journal::open(dir.path()).unwrap();
    assert_eq!(j.next_seq().unwrap(), 1);
    assert_eq!(j.next_seq().unwrap(), 2);
    let len = j.store_bytes("1", &[b"%\nO1\n", b"X1\n"]).unwrap();
    assert_eq!(len, 8);
    let mut a = record(1, "m1", JobState::Waiting);
    j.put_job(&a).unwrap();
    j.put_job(&record(2, "m2", JobState::Active)).unwrap();
    a.acked = 5;
    a.state = JobState::Active;
    j.put_job(&a).unwrap();
    let p = PunchedRecord {
        seq: 3,
        machine: "m2".into(),
        o_number: Some("O7".into()),
        unix_ms: 9,
        text: b"%\nO7\n%".to_vec(),
    };
    j.put_punched(&p).unwrap();
    drop(j);

    // A half-written store file from a crash is gone after reopening.
    std::fs::write(dir.path().join("store/.tmp-9"), b"partial").unwrap();
    let j = Journal::open(dir.path()).unwrap();
    assert!(!dir.path().join("store/.tmp-9").exists());
    assert_eq!(j.next_seq().unwrap(), 3);
    let r = j.restore().unwrap();
    assert_eq!(r.jobs["m1"], vec![a.clone()]);
    assert_eq!(r.jobs["m2"][0].state, JobState::Active);
    assert_eq!(r.punched, vec![p]);
    assert_eq!(std::fs::read(j.file_path("1")).unwrap(), b"%\nO1\nX1\n");

    j.remove_jobs(&[a]).unwrap();
    j.remove_punched(3).unwrap();
    let r = j.restore().unwrap();
    assert!(!r.jobs.contains_key("m1"));
    assert!(r.punched.is_empty());
    assert!(!j.file_path("1").exists());
}

/// The acknowledged offset of job `seq` as the database holds it, without the
/// checkpoints held in memory.
fn stored_acked(j: &Journal, seq: u64) -> u64 {
    let tx = j.inner.db().as_ref().unwrap().begin_read().unwrap();
    let table = tx.open_table(JOBS).unwrap();
    let bytes = table.get(seq).unwrap().unwrap();
    serde_json::from_slice::<JobRecord>(bytes.value())
        .unwrap()
        .acked
}

/// Progress checkpoints are held in memory and reach the disk with the next commit, made
/// by a checkpoint itself once the last commit is a second old; a gateway that stops
/// writes what it holds.
#[test]
fn progress_checkpoints_reach_the_disk_at_a_bounded_rate() {
    let dir = tempfile::tempdir().unwrap();
    let j = Journal::open(dir.path()).unwrap();
    let mut a = record(1, "m1", JobState::Active);
    j.put_job(&a).unwrap();
    a.acked = 100;
    j.put_progress(&a).unwrap();
    assert_eq!(
        stored_acked(&j, 1),
        0,
        "just after a commit, progress is held"
    );
    // The commit of another record carries it to disk.
    j.put_job(&record(2, "m2", JobState::Waiting)).unwrap();
    assert_eq!(stored_acked(&j, 1), 100);
    // Past the interval, a checkpoint is a commit of its own.
    j.inner.pending().last_durable -= PROGRESS_DURABLE_EVERY;
    a.acked = 200;
    j.put_progress(&a).unwrap();
    assert_eq!(stored_acked(&j, 1), 200);
    // Held again, then written when the journal closes.
    a.acked = 300;
    j.put_progress(&a).unwrap();
    assert_eq!(stored_acked(&j, 1), 200);
    drop(j);
    let j = Journal::open(dir.path()).unwrap();
    assert_eq!(stored_acked(&j, 1), 300);
    // Restoring reads what was written, held checkpoints included.
    a.acked = 400;
    j.put_progress(&a).unwrap();
    assert_eq!(j.restore().unwrap().jobs["m1"][0].acked, 400);
}

/// A held checkpoint never overwrites what the job's own later write says, nor brings back
/// a job that was removed.
#[test]
fn a_held_checkpoint_does_not_undo_a_later_write() {
    let dir = tempfile::tempdir().unwrap();
    let j = Journal::open(dir.path()).unwrap();
    let mut a = record(1, "m1", JobState::Active);
    let b = record(2, "m2", JobState::Active);
    j.put_job(&a).unwrap();
    j.put_job(&b).unwrap();
    a.acked = 100;
    j.put_progress(&a).unwrap();
    j.put_progress(&b).unwrap();
    a.state = JobState::Ended;
    a.acked = 120;
    j.put_job(&a).unwrap();
    j.remove_jobs(std::slice::from_ref(&b)).unwrap();
    drop(j);
    let j = Journal::open(dir.path()).unwrap();
    let r = j.restore().unwrap();
    assert_eq!(r.jobs["m1"][0].state, JobState::Ended);
    assert_eq!(r.jobs["m1"][0].acked, 120);
    assert!(!r.jobs.contains_key("m2"));
}

#[test]
fn a_linked_program_keeps_its_version_when_the_library_replaces_it() {
    let dir = tempfile::tempdir().unwrap();
    let j = Journal::open(&dir.path().join("journal")).unwrap();
    let lib = dir.path().join("O1");
    std::fs::write(&lib, b"%\nO1\nold\n%").unwrap();
    assert_eq!(j.store_file("5", &lib).unwrap(), 10);
    // The library replaces by rename: a new inode.
    let tmp = dir.path().join(".O1.tmp");
    std::fs::write(&tmp, b"%\nO1\nnew, longer\n%").unwrap();
    std::fs::rename(&tmp, &lib).unwrap();
    assert_eq!(std::fs::read(j.file_path("5")).unwrap(), b"%\nO1\nold\n%");
}

#[test]
fn a_link_put_in_a_programs_place_is_never_followed_into_the_store() {
    let dir = tempfile::tempdir().unwrap();
    let j = Journal::open(&dir.path().join("journal")).unwrap();
    let secret = dir.path().join("secret.key");
    std::fs::write(&secret, b"-----BEGIN PRIVATE KEY-----").unwrap();
    // The drop folder's entry was a program when looked at; a link is there when it is taken.
    let entry = dir.path().join("O1.nc");
    std::os::unix::fs::symlink(&secret, &entry).unwrap();
    let e = j.store_file("6", &entry).unwrap_err();
    assert!(e.to_string().contains("not a regular file"), "{e}");
    assert!(std::fs::symlink_metadata(j.file_path("6")).is_err());
}

#[test]
fn a_second_gateway_cannot_open_the_same_journal() {
    let dir = tempfile::tempdir().unwrap();
    let _j = Journal::open(dir.path()).unwrap();
    assert!(Journal::open(dir.path()).is_err());
}

#[test]
fn stream_offsets_map_back_to_the_program() {
    let mut r = record(1, "m", JobState::Ended);
    r.file_len = 100;
    r.suffix.clear();
    assert_eq!(r.stream_size(), 100);
    r.start = Some(StartPoint {
        header_end: 10,
        body_start: 60,
    });
    assert_eq!(r.stream_size(), 50);
    assert_eq!(r.program_offset(4), 60);
    assert_eq!(r.program_offset(10), 60);
    assert_eq!(r.program_offset(25), 75);
}

/// A journal with one waiting job, closed; the path of its database file.
fn journal_with_a_job(dir: &Path) -> PathBuf {
    let j = Journal::open(dir).unwrap();
    j.store_bytes("1", &[b"%\nO1\nX1\n"]).unwrap();
    j.put_job(&record(1, "m1", JobState::Waiting)).unwrap();
    let path = j.path().to_path_buf();
    drop(j);
    path
}

fn damage_of(dir: &Path) -> Option<String> {
    match Journal::open_and_restore(dir, DamagedJournal::Refuse) {
        Err(JournalError::Damaged { cause, .. }) => Some(cause),
        Err(other) => panic!("not reported as damaged: {other}"),
        Ok(_) => None,
    }
}

#[test]
fn a_damaged_journal_is_refused_never_a_panic_and_never_an_empty_start() {
    type Damage = fn(&Path);
    let damages: [(&str, Damage); 4] = [
        ("emptied", |p| std::fs::write(p, b"").unwrap()),
        ("header overwritten", |p| {
            let mut bytes = std::fs::read(p).unwrap();
            bytes[..16].copy_from_slice(b"not a redb file!");
            std::fs::write(p, bytes).unwrap();
        }),
        ("truncated to half", |p| {
            let len = std::fs::metadata(p).unwrap().len();
            std::fs::OpenOptions::new()
                .write(true)
                .open(p)
                .unwrap()
                .set_len(len / 2)
                .unwrap();
        }),
        ("garbage", |p| std::fs::write(p, vec![0xA5; 8192]).unwrap()),
    ];
    for (what, damage) in damages {
        let dir = tempfile::tempdir().unwrap();
        let path = journal_with_a_job(dir.path());
        damage(&path);
        let cause = damage_of(dir.path());
        assert!(cause.is_some(), "{what}: opened as if whole");
        // Refusing leaves everything where it was, for a person to look at.
        assert!(
            path.exists() && dir.path().join("store/1").exists(),
            "{what}"
        );
        let message = Journal::open_and_restore(dir.path(), DamagedJournal::Refuse)
            .err()
            .unwrap()
            .to_string();
        assert!(
            message.contains("is damaged") && message.contains("move-aside"),
            "{what}: {message}"
        );
    }
}

#[test]
fn a_damaged_journal_is_moved_aside_with_its_store_when_the_cell_file_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let path = journal_with_a_job(dir.path());
    std::fs::write(&path, b"").unwrap();
    let (j, restored) = Journal::open_and_restore(dir.path(), DamagedJournal::MoveAside).unwrap();
    assert!(restored.jobs.is_empty());
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        names.iter().any(|n| n.starts_with("jobs.redb.damaged-")),
        "{names:?}"
    );
    let store_aside = names
        .iter()
        .find(|n| n.starts_with("store.damaged-"))
        .unwrap();
    assert!(dir.path().join(store_aside).join("1").exists());
    // The new journal works.
    assert_eq!(j.next_seq().unwrap(), 1);
}

#[test]
fn a_whole_journal_opens_with_its_jobs() {
    let dir = tempfile::tempdir().unwrap();
    journal_with_a_job(dir.path());
    let (_, restored) = Journal::open_and_restore(dir.path(), DamagedJournal::Refuse).unwrap();
    assert_eq!(restored.jobs["m1"].len(), 1);
}

#[test]
fn a_journal_under_a_regular_file_is_an_error_naming_the_path() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("file"), b"x").unwrap();
    let e = Journal::open(&dir.path().join("file/journal")).unwrap_err();
    assert!(matches!(e, JournalError::Io { .. }), "{e}");
    assert!(e.to_string().contains("file/journal"), "{e}");
}
