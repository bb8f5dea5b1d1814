use super::*;

#[test]
fn rust_log_overrides_the_cell_file() {
    let f = filter("info", Some("cellgate=trace")).unwrap();
    assert_eq!(f.to_string(), "opcua_types::xml=error,cellgate=trace");
    let f = filter("warn,cellgate=debug", None).unwrap();
    assert!(f.to_string().contains("cellgate=debug"), "{f}");
    // An empty RUST_LOG is treated as unset.
    let f = filter("warn", Some("  ")).unwrap();
    assert_eq!(f.to_string(), "opcua_types::xml=error,warn");
    // The NodeSets' old schemas are quiet, unless the filter names the stack's types.
    let f = filter("info", Some("opcua_types=debug")).unwrap();
    assert_eq!(f.to_string(), "opcua_types=debug");
}

#[test]
fn a_bad_filter_names_where_it_came_from() {
    match filter("info", Some("cellgate=loud")) {
        Err(TelemetryError::Filter { origin, .. }) => assert_eq!(origin, RUST_LOG),
        other => panic!("expected a filter error, got {other:?}"),
    }
    match filter("cellgate=loud", None) {
        Err(TelemetryError::Filter { origin, .. }) => {
            assert_eq!(origin, "telemetry.log_filter")
        }
        other => panic!("expected a filter error, got {other:?}"),
    }
}

#[test]
fn otlp_is_off_unless_an_endpoint_is_given() {
    let cfg = TelemetryConfig::default();
    assert_eq!(otlp_endpoint(&cfg, None), None);
    assert_eq!(otlp_endpoint(&cfg, Some("")), None);
    assert_eq!(
        otlp_endpoint(&cfg, Some("http://127.0.0.1:4317")).as_deref(),
        Some("http://127.0.0.1:4317")
    );
    let cfg = TelemetryConfig {
        otlp_endpoint: Some("http://127.0.0.1:14317".to_string()),
        ..TelemetryConfig::default()
    };
    assert_eq!(
        otlp_endpoint(&cfg, Some("http://127.0.0.1:4317")).as_deref(),
        Some("http://127.0.0.1:14317")
    );
}

#[test]
fn a_guard_without_exporter_shuts_down_quietly() {
    let mut guard = TelemetryGuard::default();
    assert!(!guard.exporting());
    guard.shutdown().unwrap();
    guard.shutdown().unwrap();
}
