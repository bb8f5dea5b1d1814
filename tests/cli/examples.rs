//! The examples as a newcomer first meets them: the Python scripts answer `--help` before
//! their packages are installed (`.ci/run` needs python3, not eclipse-zenoh), and the files the
//! docs use are shipped.

use std::path::{Path, PathBuf};
use std::process::Command;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `python3 SCRIPT ARGS` in examples/python: (exit code, stdout, stderr).
fn python(script: &str, args: &[&str]) -> (i32, String, String) {
    let dir = repo().join("examples/python");
    let out = Command::new("python3")
        .arg(dir.join(script))
        .args(args)
        .current_dir(&dir)
        // Nothing the user has installed or generated may make this pass or fail.
        .env("PYTHONNOUSERSITE", "1")
        .env_remove("PYTHONPATH")
        .output()
        .expect("python3 runs (.ci/run needs it)");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn the_python_examples_answer_help() {
    let (code, out, err) = python("submit.py", &["--help"]);
    assert_eq!(code, 0, "stdout {out}\nstderr {err}");
    assert!(out.contains("--append-eor"), "{out}");
    // A `%` in a help string is a format directive to argparse: it must be written `%%`.
    assert!(out.contains("append % (EOR)"), "{out}");
    let (code, out, err) = python("g05_circle.py", &["--help"]);
    assert_eq!(code, 0, "stdout {out}\nstderr {err}");
    assert!(out.contains("--blocks"), "{out}");
    // The MTConnect follower needs nothing but the standard library.
    let (code, out, err) = python("mtconnect_follow.py", &["--help"]);
    assert_eq!(code, 0, "stdout {out}\nstderr {err}");
    assert!(out.contains("--device"), "{out}");
}

#[test]
fn the_python_examples_say_what_is_missing() {
    // Without eclipse-zenoh (or without the generated classes) the script says what to do
    // instead of a traceback.
    let (code, out, err) = python("submit.py", &["--machine", "mill-1", "O1234.nc"]);
    if code == 0 {
        panic!("submit.py ran without a gateway: {out}{err}");
    }
    assert!(!err.contains("Traceback"), "{err}");
    let has_zenoh = Command::new("python3")
        .args(["-c", "import zenoh"])
        .status()
        .is_ok_and(|s| s.success());
    if !has_zenoh {
        assert!(err.contains("pip install -r requirements.txt"), "{err}");
    }
}

/// The files the README tour and the Python README name exist.
#[test]
fn the_sample_files_the_docs_use_are_shipped() {
    for file in ["examples/programs/O1234.nc", "examples/g05/circle.csv"] {
        let path = repo().join(file);
        assert!(path.is_file(), "{} is missing", path.display());
        let docs = std::fs::read_to_string(repo().join("README.md")).unwrap();
        assert!(docs.contains(file), "README.md does not use {file}");
    }
    let program = std::fs::read(repo().join("examples/programs/O1234.nc")).unwrap();
    assert!(program.starts_with(b"%\nO1234 "), "{program:?}");
    assert!(
        program.trim_ascii_end().ends_with(b"%"),
        "the sample program ends with its EOR"
    );
    let circle =
        std::fs::read_to_string(Path::new(&repo()).join("examples/g05/circle.csv")).unwrap();
    let blocks: Vec<Vec<i32>> = circle
        .lines()
        .filter(|l| !l.trim_start().starts_with('#') && !l.trim().is_empty())
        .map(|l| l.split(',').map(|f| f.trim().parse().unwrap()).collect())
        .collect();
    assert!(blocks.len() >= 1000, "{} blocks", blocks.len());
    for b in &blocks {
        assert_eq!(b.len(), 3, "3 axes: {b:?}");
        assert!(
            b.iter().any(|&t| t != 0),
            "an all-zero block ends binary mode"
        );
        assert!(b.iter().all(|t| (-8192..=8191).contains(t)), "{b:?}");
    }
    // A closed path: the travels add up to zero in X (the circle's start and end).
    let sum_x: i32 = blocks.iter().map(|b| b[0]).sum();
    assert_eq!(sum_x, 0);
}
