use super::*;

#[test]
fn opening_a_missing_port_names_it() {
    let e =
        SerialTransport::open("/dev/cellgate-no-such-port", LineSettings::default()).unwrap_err();
    assert!(e.to_string().contains("/dev/cellgate-no-such-port"), "{e}");
}
