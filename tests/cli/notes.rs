//! docs/protocol-notes.md ends each note with the files that cite it ("Cited by: …"); this
//! checks those lists against the code: every file that cites a note is listed under it, and
//! every file listed cites it. A comment cites a FANUC note as "protocol notes N" and an
//! FFU120B note as "FFU120B notes N" (the page's "How to look up a citation").

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

type Cites = BTreeMap<u32, BTreeSet<String>>;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The numbers after each `marker` in `text` (the N of "protocol notes N").
fn numbers_after<'t>(text: &'t str, marker: &'t str) -> impl Iterator<Item = (usize, u32)> + 't {
    text.match_indices(marker).filter_map(move |(at, _)| {
        let rest = &text[at + marker.len()..];
        let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
        digits.parse().ok().map(|n| (at, n))
    })
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        if p.is_dir() {
            if name != "target" && !name.starts_with('.') {
                rust_files(&p, out);
            }
        } else if name.ends_with(".rs") {
            out.push(p);
        }
    }
}

/// What the code cites: (FANUC notes, FFU120B notes).
fn cited_in_code() -> (Cites, Cites) {
    let root = repo();
    let mut files = Vec::new();
    for d in ["crates", "src", "tests", "benches", "fuzz"] {
        rust_files(&root.join(d), &mut files);
    }
    let (mut fanuc, mut ffu) = (Cites::new(), Cites::new());
    for f in files {
        let text = std::fs::read_to_string(&f).unwrap();
        let rel = f
            .strip_prefix(&root)
            .unwrap()
            .to_string_lossy()
            .into_owned();
        for (_, n) in numbers_after(&text, "FFU120B notes ") {
            ffu.entry(n).or_default().insert(rel.clone());
        }
        for marker in ["protocol notes ", "Protocol notes "] {
            for (_, n) in numbers_after(&text, marker) {
                fanuc.entry(n).or_default().insert(rel.clone());
            }
        }
    }
    (fanuc, ffu)
}

/// Each note's "Cited by" list in one of the page's two lists.
fn listed(section: &str) -> Cites {
    let mut out = Cites::new();
    for note in section.split("\n### ").skip(1) {
        let n: u32 = note
            .split('.')
            .next()
            .and_then(|n| n.trim().parse().ok())
            .unwrap_or_else(|| panic!("a note without its number: {note:.40}"));
        let cited = note
            .split_once("Cited by:")
            .map(|(_, c)| c.split("\n\n").next().unwrap_or_default())
            .unwrap_or_else(|| panic!("note {n} has no \"Cited by\" list"));
        let files = cited
            .split('`')
            .skip(1)
            .step_by(2)
            .map(str::to_string)
            .collect();
        out.insert(n, files);
    }
    out
}

#[test]
fn the_cited_by_lists_of_the_protocol_notes_are_the_code_s() {
    let doc = std::fs::read_to_string(repo().join("docs/protocol-notes.md")).unwrap();
    let (fanuc_part, ffu_part) = doc
        .split_once("## FFU120B protocol notes")
        .expect("the FFU120B list");
    let fanuc_part = fanuc_part
        .split_once("## FANUC protocol notes")
        .expect("the FANUC list")
        .1;
    let (code_fanuc, code_ffu) = cited_in_code();
    let mut wrong = Vec::new();
    for (list, doc_lists, code) in [
        ("FANUC", listed(fanuc_part), code_fanuc),
        ("FFU120B", listed(ffu_part), code_ffu),
    ] {
        let numbers: BTreeSet<u32> = doc_lists.keys().chain(code.keys()).copied().collect();
        for n in numbers {
            let Some(in_doc) = doc_lists.get(&n) else {
                wrong.push(format!("{list} notes {n}: cited by the code, no such note"));
                continue;
            };
            let in_code = code.get(&n).cloned().unwrap_or_default();
            for f in in_code.difference(in_doc) {
                wrong.push(format!("{list} notes {n}: {f} cites it, not listed"));
            }
            for f in in_doc.difference(&in_code) {
                wrong.push(format!("{list} notes {n}: {f} listed, does not cite it"));
            }
        }
    }
    assert!(
        wrong.is_empty(),
        "docs/protocol-notes.md's \"Cited by\" lists drifted from the code:\n{}",
        wrong.join("\n")
    );
}
