use super::*;

#[test]
fn link_alarms_know_their_cnc_alarm_numbers() {
    let cases = [
        (LinkAlarm::Line(LineError::Parity), None),
        (LinkAlarm::Line(LineError::Overrun), Some("SR0946")),
        (LinkAlarm::DataSetReadyOff, Some("SR0855")),
        (LinkAlarm::DataSetReadyOffB, Some("SR0855")),
        (LinkAlarm::RetryOver { count: 4, ne: 3 }, Some("SR0945")),
        (
            LinkAlarm::TimeOut {
                waited: Duration::from_secs(10),
            },
            Some("SR0944"),
        ),
        (
            LinkAlarm::BoardAlarm {
                cause: AlarmCause::CommandError,
            },
            Some("SR0947"),
        ),
        (
            LinkAlarm::BoardAlarm {
                cause: AlarmCause::NcAlarm,
            },
            None,
        ),
    ];
    for (alarm, number) in cases {
        assert_eq!(alarm.cnc_alarm().map(CncAlarm::number), number, "{alarm}");
    }
}

#[test]
fn checksum_errors_are_known_by_kind_not_by_text() {
    let checksum = FrameError::Checksum {
        received: 1,
        computed: 2,
    };
    assert!(ProtocolError::Frame { error: checksum }.is_checksum());
    assert!(
        ProtocolError::RtyReceived {
            reason: Some(b'1'),
            count: 1,
            ne: 3
        }
        .is_checksum()
    );
    assert!(
        !ProtocolError::RtyReceived {
            reason: Some(b'3'),
            count: 1,
            ne: 3
        }
        .is_checksum()
    );
    assert!(!ProtocolError::PunchOverflow { dropped: 1 }.is_checksum());
}
