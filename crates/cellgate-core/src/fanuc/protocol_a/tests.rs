use super::*;

#[test]
fn default_settings_are_valid() {
    assert!(ProtocolAConfig::default().validate().is_empty());
    for n in [1, 2, 4] {
        let cfg = ProtocolAConfig {
            packet_n: n,
            ..Default::default()
        };
        assert!(cfg.validate().is_empty());
    }
}

#[test]
fn dummy_interval_must_stay_below_to() {
    let cfg = ProtocolAConfig {
        dummy_interval: Duration::from_secs(10),
        ..Default::default()
    };
    assert_eq!(
        cfg.validate(),
        [ProtocolAProblem::DummyInterval {
            interval: Duration::from_secs(10),
            to: 20
        }]
    );
}

#[test]
fn di_image_parsing() {
    assert_eq!(parse_di(b"5A"), Some(0x5A));
    assert_eq!(parse_di(b"ff000"), Some(0xFF));
    assert_eq!(parse_di(b"5"), None);
    assert_eq!(parse_di(b"G0"), None);
}

#[test]
fn dat_length_is_nb_minus_no_within_4096() {
    let now = Instant::now();
    let mut host = ProtocolAHost::new(ProtocolAConfig::default(), now).unwrap();
    assert_eq!(host.dat_len(), 1950);
    host.sat = Some(StatusData {
        params: Some(Params {
            nb: 4000,
            no: 2,
            ..Params::POWER_ON
        }),
        ..Default::default()
    });
    // No SAT since the link initialised: the DAT fits a board at its power-on values too
    // (protocol notes 19).
    assert_eq!(host.dat_len(), 1950);
    host.sat_seen = true;
    assert_eq!(host.dat_len(), 3998);
    host.sat = Some(StatusData {
        params: Some(Params {
            nb: 10,
            no: 50,
            ..Params::POWER_ON
        }),
        ..Default::default()
    });
    assert_eq!(host.dat_len(), 1);
}

#[test]
fn supervision_is_max_of_two_tp_and_to() {
    let now = Instant::now();
    let mut host = ProtocolAHost::new(ProtocolAConfig::default(), now).unwrap();
    assert_eq!(host.supervision_interval(), Duration::from_secs(20));
    host.sat = Some(StatusData {
        params: Some(Params {
            tp: 30,
            to: 20,
            ..Params::POWER_ON
        }),
        ..Default::default()
    });
    assert_eq!(host.supervision_interval(), Duration::from_secs(60));
}
