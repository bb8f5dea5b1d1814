//! The cargo commands the docs give for a test or a benchmark name one that exists: the test
//! binaries were merged once and the commands in the docs kept the old names, which cargo
//! answers with "no test target named …".

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The stems of the `.rs` files in `dir`, and the names of its folders holding a `main.rs`.
fn targets_in(dir: &Path) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() && p.join("main.rs").exists() {
            names.insert(e.file_name().to_string_lossy().into_owned());
        } else if p.extension().is_some_and(|x| x == "rs") {
            names.insert(p.file_stem().unwrap().to_string_lossy().into_owned());
        }
    }
    names
}

fn markdown(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            markdown(&p, out);
        } else if p.extension().is_some_and(|x| x == "md") {
            out.push(p);
        }
    }
}

/// Each `flag NAME` in `text`, with its line.
fn named_after<'t>(text: &'t str, flag: &'t str) -> impl Iterator<Item = (usize, String)> + 't {
    text.lines().enumerate().flat_map(move |(i, line)| {
        line.match_indices(flag)
            .filter_map(move |(at, _)| {
                let name: String = line[at + flag.len()..]
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect();
                (!name.is_empty()).then_some((i + 1, name))
            })
            .collect::<Vec<_>>()
    })
}

#[test]
fn every_test_and_bench_the_docs_name_exists() {
    let root = repo();
    let mut tests = targets_in(&root.join("tests"));
    tests.remove("common");
    tests.extend(targets_in(&root.join("crates/cellgate-core/tests")));
    let benches = targets_in(&root.join("benches"));
    let mut pages = vec![root.join("README.md")];
    markdown(&root.join("docs"), &mut pages);
    let mut wrong = Vec::new();
    let mut seen = 0;
    for page in &pages {
        let text = std::fs::read_to_string(page).unwrap();
        let name = page.strip_prefix(&root).unwrap().display().to_string();
        for (line, test) in named_after(&text, "--test ") {
            seen += 1;
            if !tests.contains(&test) {
                wrong.push(format!("{name}:{line}: --test {test}"));
            }
        }
        for (line, bench) in named_after(&text, "--bench ") {
            seen += 1;
            if !benches.contains(&bench) {
                wrong.push(format!("{name}:{line}: --bench {bench}"));
            }
        }
    }
    // The docs do give such commands: a check that found none would pass for nothing.
    assert!(seen > 10, "only {seen} commands found");
    assert!(
        wrong.is_empty(),
        "no such test or bench target (tests: {tests:?}; benches: {benches:?}):\n{}",
        wrong.join("\n")
    );
}
