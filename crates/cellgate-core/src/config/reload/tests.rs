use super::*;

const BASE: &str = r#"
cell = "c1"

[console]
listen = "127.0.0.1:7480"

[[machines]]
name = "m1"
protocol = "a"
transport = { kind = "sim", line = { baud = 19200 } }

[[machines]]
name = "m2"
protocol = "b"
transport = { kind = "sim" }

[[plcs]]
name = "plc-1"
mode = 1
transport = { kind = "sim" }

[[plcs.tags]]
name = "parts"
module = "D"
address = 0
type = "u16"
"#;

fn cell(text: &str) -> CellConfig {
    CellConfig::from_toml_str(text, "t.toml").unwrap()
}

fn changed(text: &str) -> Result<CellChange, RestartNeeded> {
    compare(&cell(BASE), &cell(text))
}

#[test]
fn the_same_file_changes_nothing() {
    let c = changed(BASE).unwrap();
    assert!(c.is_empty());
    assert!(!c.touches_links());
    assert_eq!(c.summary(), "nothing changed");
}

#[test]
fn machines_added_removed_and_changed_are_told_apart() {
    let text = BASE
        .replace("baud = 19200", "baud = 9600")
        .replace("name = \"m2\"", "name = \"m3\"");
    let c = changed(&text).unwrap();
    assert_eq!(c.machines_changed, ["m1"]);
    assert_eq!(c.machines_added, ["m3"]);
    assert_eq!(c.machines_removed, ["m2"]);
    assert!(c.plcs_changed.is_empty() && c.plc_tags.is_empty());
    assert!(c.touches_links());
    assert_eq!(
        c.summary(),
        "machines added: m3; machines removed: m2; machines changed: m1"
    );
}

#[test]
fn a_plc_whose_tags_alone_differ_keeps_its_link() {
    let tags = format!(
        "{BASE}\n[[plcs.tags]]\nname = \"door\"\nmodule = \"M\"\naddress = 0\ntype = \"bit\"\nbit = 0\n"
    );
    let c = changed(&tags).unwrap();
    assert_eq!(c.plc_tags, ["plc-1"]);
    assert!(!c.touches_links(), "{c:?}");
    // A poll group is a tag's poll_ms: the same.
    let poll = BASE.replace("type = \"u16\"", "type = \"u16\"\npoll_ms = 250");
    assert_eq!(changed(&poll).unwrap().plc_tags, ["plc-1"], "{poll}");
    // Its line is the link's own.
    let line = BASE.replace(
        "mode = 1\ntransport = { kind = \"sim\" }",
        "mode = 1\ntransport = { kind = \"sim\", line = { baud = 4800 } }",
    );
    let c = changed(&line).unwrap();
    assert_eq!(c.plcs_changed, ["plc-1"]);
    assert!(c.plc_tags.is_empty());
}

#[test]
fn live_settings_are_named_by_key() {
    let text = format!("{BASE}\n[programs]\nquota_files = 10\n[history]\nkeep_days = 7\n").replace(
        "listen = \"127.0.0.1:7480\"",
        "listen = \"127.0.0.1:7480\"\nsession_idle_minutes = 5",
    );
    let c = changed(&text).unwrap();
    assert_eq!(
        c.settings,
        [
            "programs.quota_files",
            "history.keep_days",
            "console.session_idle_minutes"
        ]
    );
    assert!(!c.touches_links());
}

#[test]
fn what_the_session_holds_needs_a_restart_and_every_key_is_named() {
    let text =
        format!("{BASE}\n[bus]\nlisten = [\"tcp/127.0.0.1:7999\"]\n[programs]\nkeep_jobs = 10\n")
            .replace("baud = 19200", "baud = 9600");
    let e = changed(&text).unwrap_err();
    assert_eq!(e.0.len(), 2, "{e:?}");
    assert!(
        e.0[0].starts_with("bus.listen (the bus listen endpoints"),
        "{e:?}"
    );
    assert!(e.0[1].starts_with("programs.keep_jobs"), "{e:?}");
    let text = e.to_string();
    assert!(text.contains("restart") && text.contains("nothing of this reload was applied"));
}

#[test]
fn roles_are_zenohs_and_need_a_restart() {
    let mut old = cell(BASE);
    let mut new = old.clone();
    new.security.roles.push(crate::config::Role {
        name: "ops".to_string(),
        cert_common_names: Vec::new(),
        usernames: vec!["ann".to_string()],
        permissions: vec![crate::config::Permission::StatusRead],
    });
    let e = compare(&old, &new).unwrap_err();
    assert!(e.0[0].starts_with("security.roles"), "{e:?}");
    // The console's listener too, but not its sessions.
    old.security = new.security.clone();
    let mut console = new.console.clone().unwrap();
    console.sessions_per_user = 2;
    new.console = Some(console.clone());
    assert_eq!(
        compare(&old, &new).unwrap().settings,
        ["console.sessions_per_user"]
    );
    console.listen = "127.0.0.1:7481".to_string();
    new.console = Some(console);
    assert!(compare(&old, &new).unwrap_err().0[0].starts_with("console.listen"));
    new.console = None;
    assert!(compare(&old, &new).unwrap_err().0[0].starts_with("console ("));
}

#[test]
fn the_folders_keys_need_a_restart_where_they_were_once_silently_ignored() {
    for (key, value) in [
        ("settle_ms", "2000"),
        ("poll_ms", "5000"),
        ("watch", "\"poll\""),
        ("extensions", "[\"nc\"]"),
    ] {
        let e = changed(&format!("{BASE}\n[programs]\n{key} = {value}\n")).unwrap_err();
        assert!(
            e.0.iter()
                .any(|k| k.starts_with(&format!("programs.{key} ("))),
            "{e}"
        );
    }
}

/// Every key a reload compares is in the table of docs/configuration.md that says how a
/// reload takes it (by its last part: the table names a section's keys once).
#[test]
fn every_key_a_reload_compares_is_in_the_docs_table() {
    let docs = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/configuration.md"),
    )
    .unwrap();
    let table = docs
        .split("### Each key on a reload")
        .nth(1)
        .and_then(|t| t.split("\n\n").nth(1))
        .expect("the table");
    let base = cell(BASE);
    for (key, takes, differs) in keys(&base, &base) {
        assert!(!differs, "{key}");
        let last = key.rsplit('.').next().unwrap();
        let row = table
            .lines()
            .find(|l| {
                [
                    format!("`{key}`"),
                    format!("`{last}`"),
                    format!("`[{key}]`"),
                    format!("`[[{key}]]`"),
                ]
                .iter()
                .any(|k| l.contains(k.as_str()))
            })
            .unwrap_or_else(|| panic!("{key} is not in the docs' reload table"));
        let said_live = row.contains("applied at once");
        assert_eq!(said_live, takes == Takes::Live, "{key}: {row}");
    }
}
