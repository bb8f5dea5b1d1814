use super::*;
use cellgate_core::pb::job_event::Kind;

#[test]
fn bytes_parse_in_three_notations_and_are_range_checked() {
    assert_eq!(parse_byte("0x5A"), Ok(0x5A));
    assert_eq!(parse_byte("0XfF"), Ok(0xFF));
    assert_eq!(parse_byte("0b1010_0101"), Ok(0xA5));
    assert_eq!(parse_byte("255"), Ok(255));
    assert_eq!(parse_byte("0"), Ok(0));
    assert!(parse_byte("256").unwrap_err().contains("0..=255"));
    assert!(parse_byte("0x100").unwrap_err().contains("0..=255"));
    assert!(parse_byte("0b2").unwrap_err().contains("not a number"));
    assert!(parse_byte("-1").is_err());
    assert!(parse_byte("0x").unwrap_err().contains("no digits"));
    assert!(parse_byte("").is_err());
}

#[test]
fn the_client_session_connects_only_and_never_scouts() {
    let c = client_config("tcp/127.0.0.1:7447", &ClientSecurity::default()).unwrap();
    assert_eq!(c.get_json("mode").unwrap(), "\"client\"");
    assert_eq!(c.get_json("scouting/multicast/enabled").unwrap(), "false");
    assert_eq!(c.get_json("listen/endpoints").unwrap(), "[]");
    assert!(
        c.get_json("connect/endpoints")
            .unwrap()
            .contains("tcp/127.0.0.1:7447")
    );
    assert!(matches!(
        client_config("nonsense", &ClientSecurity::default()),
        Err(ClientError::Endpoint { .. })
    ));
}

#[test]
fn tls_options_go_into_the_session_and_must_fit_the_endpoint() {
    let tls = ClientSecurity {
        ca: Some("/etc/ca.pem".into()),
        certificate: Some("/etc/me.pem".into()),
        private_key: Some("/etc/me-key.pem".into()),
        credentials: Some(Credentials {
            user: "mes".to_string(),
            password: "s3cret".to_string(),
        }),
    };
    let c = client_config("tls/127.0.0.1:7447", &tls).unwrap();
    let t = |k: &str| c.get_json(&format!("transport/link/tls/{k}")).unwrap();
    assert_eq!(t("root_ca_certificate"), "\"/etc/ca.pem\"");
    assert_eq!(t("connect_certificate"), "\"/etc/me.pem\"");
    assert_eq!(t("connect_private_key"), "\"/etc/me-key.pem\"");
    assert_eq!(t("enable_mtls"), "true");
    assert!(!format!("{tls:?}").contains("s3cret"));
    let bad = |endpoint: &str, s: ClientSecurity| {
        let e = client_config(endpoint, &s).unwrap_err();
        assert!(matches!(e, ClientError::Security { .. }), "{e}");
        assert_eq!(e.exit_code(), 2);
        e.to_string()
    };
    assert!(bad("tcp/127.0.0.1:7447", tls.clone()).contains("tls/"));
    assert!(bad("tls/127.0.0.1:7447", ClientSecurity::default()).contains("--tls-ca"));
    let half = ClientSecurity {
        private_key: None,
        ..tls
    };
    assert!(bad("tls/127.0.0.1:7447", half).contains("both"));
}

#[test]
fn refusals_keep_the_gateways_code_and_message() {
    let e = pb::ErrorReply {
        code: pb::ErrorCode::UnknownMachine as i32,
        message: "cell x has no machine \"m\"".to_string(),
        sta: None,
    };
    let err = refusal("status", &e.encode_to_vec(), &encoding::<pb::ErrorReply>());
    assert_eq!(err.refusal(), Some(pb::ErrorCode::UnknownMachine));
    assert_eq!(err.exit_code(), 2);
    let text = err.to_string();
    assert!(text.contains("ERROR_CODE_UNKNOWN_MACHINE"), "{text}");
    assert!(text.contains("no machine"), "{text}");
}

#[test]
fn a_reply_of_another_schema_is_a_bad_reply() {
    let s = pb::MachineStatus::default().encode_to_vec();
    let r = decode::<pb::DiImage>("di", "k", &s, &encoding::<pb::MachineStatus>());
    assert!(matches!(r, Err(ClientError::BadReply { .. })));
}

#[test]
fn outcomes_map_to_exit_codes() {
    let ev = |kind| pb::JobEvent {
        kind: Some(kind),
        ..pb::JobEvent::default()
    };
    let done = ev(Kind::Completed(pb::job_event::Completed::default()));
    let failed = ev(Kind::Failed(pb::job_event::Failed::default()));
    let progress = ev(Kind::Progress(pb::job_event::Progress::default()));
    assert_eq!(JobOutcome::of(&done).unwrap().exit_code(), 0);
    assert_eq!(JobOutcome::of(&failed).unwrap().exit_code(), 1);
    assert!(JobOutcome::of(&progress).is_none());
    assert!(is_end(&done) && !is_end(&progress));
}

#[test]
fn a_job_id_names_its_machine() {
    assert_eq!(machine_of_job("mill-1-tpfqpi-3"), Some("mill-1"));
    assert_eq!(machine_of_job("m-a-b-c-x9-12"), Some("m-a-b-c"));
    assert_eq!(machine_of_job("lathe-1-tpfqpi-"), None);
    assert_eq!(machine_of_job("tpfqpi-3"), None);
    assert_eq!(machine_of_job("mill-1"), None);
    assert_eq!(machine_of_job("-x-1"), None);
}

#[test]
fn a_bad_endpoint_says_what_an_endpoint_looks_like() {
    for bad in ["127.0.0.1:7447", "tcp/", "/127.0.0.1:7447"] {
        let e = client_config(bad, &ClientSecurity::default()).unwrap_err();
        let text = e.to_string();
        assert!(
            text.contains("endpoints look like tcp/127.0.0.1:7447"),
            "{text}"
        );
        assert!(!text.contains("Json5"), "{text}");
        assert_eq!(e.exit_code(), 2);
    }
}

#[test]
fn a_refused_session_without_credentials_names_them() {
    let m = unreachable_message("tcp/127.0.0.1:7447", false);
    assert!(
        m.contains("--user") && m.contains("CELLGATE_PASSWORD"),
        "{m}"
    );
    assert!(!m.contains("nothing accepted"), "{m}");
}
