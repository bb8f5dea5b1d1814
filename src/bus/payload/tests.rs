use super::*;
use cellgate_core::fanuc::sat::Params;

#[test]
fn encodings_name_the_message() {
    let e = encoding::<pb::JobEvent>();
    assert_eq!(e.to_string(), "application/protobuf;cellgate.v1.JobEvent");
    assert_eq!(schema_of(&e).as_deref(), Some("cellgate.v1.JobEvent"));
}

#[test]
fn sat_fields_carry_over() {
    let s = StatusData {
        remote: Some(true),
        status: Some(BufferStatus::Alarm),
        alarm_cause: Some(AlarmCause::OverrunRetryOver),
        buffered: Some(1234),
        params: Some(Params::POWER_ON),
        packet_n: Some(2),
        ..StatusData::default()
    };
    let p = sat(&s);
    assert_eq!(p.remote, Some(true));
    assert_eq!(p.buffer_status(), pb::BufferStatus::Alarm);
    assert_eq!(p.buffer_status_digit, Some(3));
    assert_eq!(p.alarm_cause(), pb::AlarmCause::OverrunRetryOver);
    assert_eq!(p.alarm_cause_digit, Some(0xA));
    assert_eq!(p.bytes_buffered, Some(1234));
    assert_eq!(p.params.unwrap().to, 20);
    assert_eq!(p.packet_n, Some(2));
    let empty = sat(&StatusData::default());
    assert_eq!(empty.buffer_status(), pb::BufferStatus::Unknown);
    assert_eq!(empty.params, None);
}
