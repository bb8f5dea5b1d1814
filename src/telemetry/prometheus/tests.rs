use super::*;

#[test]
fn addresses_are_ip_and_port() {
    assert!(parse_addr("127.0.0.1:9464").is_ok());
    assert!(parse_addr("[::1]:9464").is_ok());
    assert!(parse_addr("localhost:9464").is_err());
    assert!(parse_addr("127.0.0.1").is_err());
    assert!(parse_addr("").is_err());
}
