use super::*;

#[test]
fn cell_settings_override_zenoh_defaults() {
    let cfg = BusConfig {
        mode: crate::bus::BusMode::Client,
        listen: vec!["tcp/127.0.0.1:17447".to_string()],
        connect: vec!["tcp/127.0.0.1:7447".to_string()],
        ..BusConfig::default()
    };
    let z = zenoh_config(&cfg).unwrap();
    assert_eq!(z.get_json("mode").unwrap(), "\"client\"");
    assert_eq!(z.get_json("scouting/multicast/enabled").unwrap(), "false");
    assert!(
        z.get_json("listen/endpoints")
            .unwrap()
            .contains("tcp/127.0.0.1:17447")
    );
    assert!(
        z.get_json("connect/endpoints")
            .unwrap()
            .contains("tcp/127.0.0.1:7447")
    );
}

#[test]
fn a_malformed_endpoint_names_the_field() {
    let cfg = BusConfig {
        listen: vec!["not an endpoint".to_string()],
        ..BusConfig::default()
    };
    match zenoh_config(&cfg) {
        Err(BusError::ConfigValue { field, .. }) => assert_eq!(field, "listen"),
        other => panic!("expected ConfigValue, got {other:?}"),
    }
}

#[test]
fn the_json5_file_is_read_then_overridden() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("zenoh.json5");
    std::fs::write(
        &path,
        r#"{ mode: "router", scouting: { multicast: { enabled: true } } }"#,
    )
    .unwrap();
    let cfg = BusConfig {
        zenoh_config: Some(path),
        ..BusConfig::default()
    };
    let z = zenoh_config(&cfg).unwrap();
    assert_eq!(z.get_json("mode").unwrap(), "\"peer\"");
    assert_eq!(z.get_json("scouting/multicast/enabled").unwrap(), "false");
}

#[test]
fn a_missing_json5_file_is_a_config_file_error() {
    let cfg = BusConfig {
        zenoh_config: Some("/nonexistent/zenoh.json5".into()),
        ..BusConfig::default()
    };
    assert!(matches!(
        zenoh_config(&cfg),
        Err(BusError::ConfigFile { .. })
    ));
}

#[test]
fn the_deploy_examples_load() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/zenoh");
    let mut seen = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "json5") {
            zenoh::Config::from_file(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            seen += 1;
        }
    }
    assert!(
        seen >= 2,
        "expected the zenoh examples in {}",
        dir.display()
    );
}
