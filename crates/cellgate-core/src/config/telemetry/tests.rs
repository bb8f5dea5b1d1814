use super::*;

#[test]
fn credentials_are_redacted_and_nothing_else() {
    assert_eq!(
        redact_credentials("http://user:secret@127.0.0.1:4317/v1"),
        "http://***@127.0.0.1:4317/v1"
    );
    assert_eq!(
        redact_credentials("http://127.0.0.1:4317"),
        "http://127.0.0.1:4317"
    );
    assert_eq!(redact_credentials("grpc://a@b@host"), "grpc://***@host");
    assert_eq!(
        redact_credentials("http://host/path?x=a@b"),
        "http://host/path?x=a@b"
    );
}
