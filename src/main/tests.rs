use super::*;

#[test]
fn the_command_line_is_consistent() {
    // Catches, among others, two options of one command with the same name (a flattened
    // group of options meeting a command's own).
    use clap::CommandFactory;
    Cli::command().debug_assert();
}

/// Every command below the root, with its path (`program get`).
fn commands() -> Vec<(String, clap::Command)> {
    use clap::CommandFactory;
    let mut out = Vec::new();
    let mut stack = vec![(String::new(), Cli::command())];
    while let Some((path, c)) = stack.pop() {
        for sub in c.get_subcommands() {
            let p = format!("{path} {}", sub.get_name()).trim().to_string();
            stack.push((p, sub.clone()));
        }
        out.push((path, c));
    }
    out
}

#[test]
fn usual_synonyms_point_to_the_subcommand() {
    let args = |line: &str| -> Vec<String> { line.split(' ').map(String::from).collect() };
    assert_eq!(synonym_of(&args("cellgate program delete x")), Some("rm"));
    assert_eq!(synonym_of(&args("cellgate program remove x")), Some("rm"));
    assert_eq!(synonym_of(&args("cellgate program list")), Some("ls"));
    assert_eq!(synonym_of(&args("cellgate -v program list")), Some("ls"));
    // Only where the subcommand exists.
    assert_eq!(synonym_of(&args("cellgate tag delete x")), None);
    assert_eq!(synonym_of(&args("cellgate program frobnicate")), None);
}

#[test]
fn the_removed_machine_flag_names_the_form_commands_have_now() {
    let args = |line: &str| -> Vec<String> { line.split(' ').map(String::from).collect() };
    for (line, path) in [
        ("cellgate submit -m mill-1 O1234.nc", "submit"),
        ("cellgate do --machine mill-1 0x05", "do"),
        ("cellgate -v watch -m mill-1", "watch"),
    ] {
        let e = parse_from(&args(line))
            .err()
            .unwrap_or_else(|| panic!("{line} parsed"));
        let text = e.render().to_string();
        assert!(text.contains("unexpected argument"), "{line}: {text}");
        assert!(
            text.contains(&format!(
                "name the machine first, as every command does: `cellgate {path} MACHINE ...`"
            )),
            "{line}: {text}"
        );
    }
    // Commands that take no machine first get no such tip.
    let e = parse_from(&args("cellgate program ls -m mill-1"))
        .err()
        .unwrap();
    assert!(!e.render().to_string().contains("name the machine first"));
    // history, audit and utilisation keep the older flag working, beside the machine first.
    for line in [
        "cellgate history -m mill-1",
        "cellgate history mill-1,mill-2 --kind job",
        "cellgate audit --machine mill-1",
        "cellgate utilisation mill-1",
    ] {
        assert!(parse_from(&args(line)).is_ok(), "{line}");
    }
}

#[test]
fn every_argument_has_help() {
    let mut missing = Vec::new();
    for (path, c) in commands() {
        for a in c.get_arguments() {
            let id = a.get_id().as_str();
            if id == "help" || id == "version" {
                continue;
            }
            if a.get_help().is_none() && a.get_long_help().is_none() {
                missing.push(format!("{path}: {id}"));
            }
        }
        // An empty default says nothing: say what happens without the option instead.
        let help = c.clone().render_long_help().to_string();
        assert!(!help.contains("[default: ]"), "{path}:\n{help}");
        assert!(!help.contains("[default: \"\"]"), "{path}:\n{help}");
    }
    assert!(missing.is_empty(), "arguments without help: {missing:#?}");
}

/// One convention for output: every client command (one that connects to a gateway)
/// prints JSON with --json.
#[test]
fn every_client_command_has_json() {
    let mut missing = Vec::new();
    for (path, c) in commands() {
        let client = c.get_arguments().any(|a| a.get_id() == "connect")
            && c.get_subcommands().next().is_none()
            && path != "router"
            && path != "run"
            // Servers: they print their URL, and serve JSON over HTTP (or OPC UA).
            && path != "console"
            && path != "mtconnect"
            && path != "opcua";
        if client && !c.get_arguments().any(|a| a.get_id() == "json") {
            missing.push(path);
        }
    }
    assert!(
        missing.is_empty(),
        "client commands without --json: {missing:?}"
    );
}

#[test]
fn the_first_command_to_try_carries_the_credentials_a_secured_cell_needs() {
    let mut config = CellConfig::embedded_default();
    assert!(!serving_text(&config).contains("--user"));
    config.security.users_file = Some(std::path::PathBuf::from("users"));
    let t = serving_text(&config);
    assert!(t.contains("try: cellgate status --user NAME"), "{t}");
    assert!(t.contains("CELLGATE_PASSWORD"), "{t}");
}
