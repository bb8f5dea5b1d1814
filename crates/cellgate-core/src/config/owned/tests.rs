use super::*;

#[test]
fn the_folder_itself_and_visible_entries_are_listed_hidden_ones_are_not() {
    let dir = Path::new("/srv/cell/programs");
    for (path, listed) in [
        ("/srv/cell/programs", true),
        ("/srv/cell/programs/", true),
        ("/srv/cell/programs/.", true),
        ("/srv/cell/./programs", true),
        ("/srv/cell/programs/jobs", true),
        ("/srv/cell/programs/jobs/deeper", true),
        ("/srv/cell/programs/.journal", false),
        ("/srv/cell/programs/.history/x", false),
        ("/srv/cell/programs/../jobs", false),
        ("/srv/cell/programs2", false),
        ("/srv/cell", false),
    ] {
        assert_eq!(listed_in(dir, Path::new(path)), listed, "{path}");
    }
}

#[test]
fn relative_and_absolute_paths_compare_alike() {
    let cwd = std::env::current_dir().unwrap();
    assert!(listed_in(Path::new("lib"), &cwd.join("lib")));
    assert!(listed_in(&cwd.join("lib"), Path::new("./lib/j")));
    assert!(!listed_in(Path::new("lib"), Path::new("jobs")));
}

#[test]
fn owned_files_and_the_folders_that_hold_them_are_owned() {
    let dir = Path::new("/lib");
    let owned = [
        PathBuf::from("/lib"),
        PathBuf::from("/lib/jobs.redb"),
        PathBuf::from("/keys/ca.pem"),
    ];
    assert!(is_owned(&owned, dir, Path::new("/lib/jobs.redb")));
    assert!(
        !is_owned(&owned, dir, Path::new("/lib/O1000")),
        "the folder itself owns no program"
    );
    let owned = [PathBuf::from("/lib/journal")];
    assert!(is_owned(&owned, dir, Path::new("/lib/journal")));
    assert!(!is_owned(&owned, dir, Path::new("/lib/O1000")));
}
