use super::*;

const CELL: &str = r#"
cell = "c1"
[bus]
listen = []
[[machines]]
name = "m1"
protocol = "a"
transport = { kind = "sim" }
"#;

fn file(text: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cell.toml");
    std::fs::write(&path, text).unwrap();
    (dir, path)
}

#[test]
fn a_file_is_checked_as_check_config_checks_it_every_error_naming_the_file() {
    let (_dir, path) = file(CELL);
    assert_eq!(check_cell_file(&path).unwrap().machines.len(), 1);
    let (_dir, path) = file(&format!(
        "{}\nnb = 999\n[history]\nkeep_dayz = 1\n",
        CELL.replace("protocol = \"a\"", "protocol = \"a\"\ntp = 500")
    ));
    let errors = check_cell_file(&path).unwrap_err();
    let origin = path.display().to_string();
    assert!(errors.len() >= 2, "{errors:?}");
    assert!(errors.iter().all(|e| e.starts_with(&origin)), "{errors:?}");
    assert!(errors.iter().any(|e| e.contains("keep_dayz")), "{errors:?}");
    let missing = check_cell_file(Path::new("/nonexistent/cell.toml")).unwrap_err();
    assert!(
        missing[0].contains("cannot read the cell file"),
        "{missing:?}"
    );
}

#[test]
fn the_command_line_options_are_written_over_the_file_again_and_checked() {
    let (_dir, path) = file(CELL);
    let source = CellSource::file(&path).with_adjust(|c| c.bus.prefix = "plant/a".to_string());
    assert_eq!(source.load().unwrap().bus.prefix, "plant/a");
    let bad = CellSource::file(&path).with_adjust(|c| c.bus.prefix = "a/*".to_string());
    let errors = bad.load().unwrap_err();
    assert!(
        errors[0].contains("(with command-line options)") && errors[0].contains("bus.prefix"),
        "{errors:?}"
    );
}

#[test]
fn the_embedded_cell_has_no_file() {
    let errors = CellSource::embedded().load().unwrap_err();
    assert!(errors[0].contains("embedded default cell"), "{errors:?}");
    assert!(CellSource::embedded().path().is_none());
}
