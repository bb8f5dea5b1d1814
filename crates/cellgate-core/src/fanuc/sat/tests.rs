use super::*;

#[test]
fn power_on_values_are_valid_and_match_sat_defaults() {
    assert!(Params::POWER_ON.validate().is_empty());
    // §4.4.2 default column: Nb 07D0, No 0032, Ne 000A, Tp 0005, To 0014, Ti 000A, Tx 0064, Tw 0005.
    let mut v = Vec::new();
    StatusData {
        params: Some(Params::POWER_ON),
        ..Default::default()
    }
    .encode(&mut v);
    assert_eq!(&v[8..40], b"07D00032000A00050014000A00640005");
    assert_eq!(v.len(), STATUS_DATA_LEN);
}

#[test]
fn range_errors_name_the_bound() {
    let p = Params {
        tw: 12,
        nb: 10,
        ..Params::POWER_ON
    };
    let errs = p.validate();
    let text: Vec<String> = errs.iter().map(|e| e.to_string()).collect();
    assert!(text.contains(&"tw = 12: must be within 0..=5 (tp = 5) (§4.5)".to_string()));
    assert!(text.contains(&"nb = 10: must be within 51..=4000 (1 + no) (§4.5)".to_string()));
}

#[test]
fn decode_round_trip_and_short_parts() {
    let d = StatusData {
        remote: Some(true),
        status: Some(BufferStatus::Operating),
        alarm_cause: Some(AlarmCause::OverrunRetryOver),
        buffered: Some(0x1234),
        params: Some(Params::POWER_ON),
        boring_unit: Some(4),
        conversion: Some((0x3B, 0x0A)),
        packet_n: Some(2),
    };
    let bytes = d.to_bytes();
    assert_eq!(StatusData::decode(&bytes), Ok(d));
    // A 20-byte SAT: params incomplete, so unknown.
    let short = StatusData::decode(&bytes[..20]).unwrap();
    assert_eq!(short.buffered, Some(0x1234));
    assert_eq!(short.params, None);
    assert_eq!(short.packet_n, None);
    assert_eq!(StatusData::decode(b""), Ok(StatusData::default()));
}

#[test]
fn decode_rejects_garbage_without_panicking() {
    assert_eq!(
        StatusData::decode(b"12G4"),
        Err(StatusDataError::NotHex {
            position: 3,
            byte: b'G'
        })
    );
    assert!(matches!(
        StatusData::decode(&[b'0'; 73]),
        Err(StatusDataError::TooLong { len: 73 })
    ));
}

#[test]
fn packet_n_outside_set_means_zero() {
    assert_eq!(effective_packet_n(3), 0);
    assert_eq!(effective_packet_n(4), 4);
}
