use super::*;

#[test]
fn addresses() {
    for good in [
        "127.0.0.1:4001",
        "moxa-cell3:950",
        "[::1]:4001",
        "localhost:1",
    ] {
        assert!(check_addr(good).is_ok(), "{good}");
    }
    for bad in [
        "127.0.0.1",
        ":4001",
        "host:",
        "host:0",
        "host:70000",
        "::1:4001",
    ] {
        assert!(
            matches!(check_addr(bad), Err(TransportError::BadAddress { .. })),
            "{bad}"
        );
    }
}

#[test]
fn default_window_is_inside_protocol_b_allowance() {
    assert!(TcpOptions::default().window < 512);
}
