use super::*;
use prost::Message;

#[test]
fn job_request_round_trips_through_the_wire_format() {
    let request = JobRequest {
        program: Some(job_request::Program::Inline(b"%\nO0001\nG00X0\n%".to_vec())),
        name: "O0001".to_string(),
        priority: -3,
        append_eor: true,
        request_id: "r-1".to_string(),
        start_at: Some(BlockStart {
            at: Some(block_start::At::SequenceNumber(1234)),
            header_lines: 0,
        }),
        resume_after_restart: true,
        deadline_s: 30,
        revision: "3".to_string(),
    };
    let bytes = request.encode_to_vec();
    let decoded = JobRequest::decode(bytes.as_slice()).unwrap();
    assert_eq!(decoded, request);
}

#[test]
fn job_event_oneof_survives_decoding() {
    let event = JobEvent {
        job_id: "j1".to_string(),
        machine: "lathe1".to_string(),
        unix_ms: 1_700_000_000_000,
        origin: None,
        kind: Some(job_event::Kind::Failed(job_event::Failed {
            reason: "retry over".to_string(),
            byte_offset: 512,
            alarm_number: "SR0945".to_string(),
            code: ErrorCode::LinkFailed as i32,
            ..job_event::Failed::default()
        })),
    };
    let decoded = JobEvent::decode(event.encode_to_vec().as_slice()).unwrap();
    match decoded.kind {
        Some(job_event::Kind::Failed(f)) => {
            assert_eq!(f.byte_offset, 512);
            assert_eq!(f.alarm_number, "SR0945");
            assert_eq!(f.code(), ErrorCode::LinkFailed);
        }
        other => panic!("decoded kind {other:?}"),
    }
}

#[test]
fn garbage_is_a_decode_error_not_a_panic() {
    assert!(MachineStatus::decode(&[0xFF, 0xFF, 0xFF][..]).is_err());
}
