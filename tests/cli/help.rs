//! The binary's help as a user reads it: the main commands end with examples that the
//! binary takes, a usage line marks an argument optional exactly where its Arguments entry
//! does, and no option states two defaults.

use std::collections::BTreeMap;

use crate::common;

/// `cellgate ARGS --help`: its stdout, which must be there.
fn help(path: &[&str]) -> String {
    let out = common::cli::command(path.iter().copied().chain(["--help"]))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{path:?} --help: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// The lines of a help section (`Usage:`, `Arguments:`, `Commands:`, `Examples:`) up to
/// the next blank line; the `Usage:` heading's own line included.
fn section<'h>(help: &'h str, heading: &str) -> Vec<&'h str> {
    let mut lines = help.lines().skip_while(|l| !l.starts_with(heading));
    let Some(first) = lines.next() else {
        return Vec::new();
    };
    let mut out = vec![first.trim_start_matches(heading)];
    out.extend(lines.take_while(|l| !l.trim().is_empty()));
    out
}

/// Every command below the root, by its path (`["program", "get"]`), help aside.
fn commands() -> BTreeMap<Vec<String>, String> {
    let mut all = BTreeMap::new();
    let mut todo: Vec<Vec<String>> = vec![Vec::new()];
    while let Some(path) = todo.pop() {
        let args: Vec<&str> = path.iter().map(String::as_str).collect();
        let text = help(&args);
        for line in section(&text, "Commands:").iter().skip(1) {
            let Some(name) = line.split_whitespace().next() else {
                continue;
            };
            if name != "help" {
                let mut sub = path.clone();
                sub.push(name.to_string());
                todo.push(sub);
            }
        }
        all.insert(path, text);
    }
    all
}

#[test]
fn the_main_commands_end_with_examples_the_binary_takes() {
    let mut checked = 0;
    for command in [
        "submit", "program", "status", "watch", "history", "plc", "reload", "g05",
    ] {
        let text = help(&[command]);
        let examples = section(&text, "Examples:");
        assert!(
            examples.len() > 2,
            "`cellgate {command} --help` has no examples:\n{text}"
        );
        for line in &examples[1..] {
            let typed = line.split("  #").next().unwrap().trim();
            let args: Vec<&str> = typed.split_whitespace().collect();
            assert_eq!(args.first(), Some(&"cellgate"), "{command}: {line}");
            assert_eq!(args.get(1), Some(&command), "{command}: {line}");
            // --help after the arguments: clap checks each of them, then prints help.
            help(&args[1..]);
            checked += 1;
        }
    }
    assert!(checked >= 24, "{checked}");
}

#[test]
fn a_usage_marks_an_argument_optional_where_its_entry_does() {
    for (path, text) in commands() {
        let usage = section(&text, "Usage:").join("\n");
        for entry in section(&text, "Arguments:").iter().skip(1) {
            let Some(arg) = entry.split_whitespace().next() else {
                continue;
            };
            let arg = arg.trim_end_matches("...");
            let name = arg.trim_matches(['<', '>', '[', ']']);
            if arg.starts_with('[') {
                // Optional alone, or one of a group of which one is required (`<FILE|--key>`).
                assert!(
                    usage.contains(&format!("[{name}]")) || usage.contains(&format!("<{name}|")),
                    "cellgate {}: {arg} is optional but its usage has no [{name}]:\n{usage}",
                    path.join(" ")
                );
            } else {
                assert!(
                    !usage.contains(&format!("[{name}]")),
                    "cellgate {}: {arg} is required but its usage shows [{name}]:\n{usage}",
                    path.join(" ")
                );
            }
        }
    }
}

#[test]
fn no_option_states_two_defaults() {
    for (path, text) in commands() {
        for line in text.lines().filter(|l| l.contains("[default: ")) {
            let said = line
                .split("[default: ")
                .next()
                .unwrap()
                .to_ascii_lowercase();
            assert!(
                !said.contains("default"),
                "cellgate {}: {}",
                path.join(" "),
                line.trim()
            );
        }
    }
}
