use super::*;

const LIMITS: Limits = Limits {
    max_inline: 1000,
    max_program: 5000,
};

#[test]
fn a_message_over_its_size_is_refused_before_it_is_decoded() {
    let big = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(vec![b'x'; 10_000])),
        ..Default::default()
    };
    let e = decode::<pb::JobRequest>(&big.encode_to_vec(), &LIMITS).unwrap_err();
    assert!(
        matches!(
            e,
            BoundError::TooLarge {
                message: "JobRequest",
                ..
            }
        ),
        "{e}"
    );
    // Garbage of the same size is refused for its size too: nothing is decoded.
    let e = decode::<pb::G05Batch>(&vec![0xFF; 2 << 20], &LIMITS).unwrap_err();
    assert!(matches!(e, BoundError::TooLarge { .. }), "{e}");
}

#[test]
fn fields_past_their_bounds_are_refused_by_name() {
    let long_name = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(b"%\n%".to_vec())),
        name: "n".repeat(MAX_TEXT + 1),
        ..Default::default()
    };
    let e = decode::<pb::JobRequest>(&long_name.encode_to_vec(), &LIMITS).unwrap_err();
    assert_eq!(
        e,
        BoundError::Field {
            message: "JobRequest",
            field: "name",
            len: MAX_TEXT + 1,
            max: MAX_TEXT
        }
    );
    let ok = pb::JobRequest {
        name: "n".repeat(MAX_TEXT),
        ..long_name
    };
    assert!(decode::<pb::JobRequest>(&ok.encode_to_vec(), &LIMITS).is_ok());
    let words = pb::PlcWrite {
        words: vec![1; MAX_PLC_WORDS + 1],
        clear: false,
    };
    assert!(matches!(
        decode::<pb::PlcWrite>(&words.encode_to_vec(), &LIMITS),
        Err(BoundError::Field { field: "words", .. })
    ));
    let block = pb::G05Block {
        travel: vec![1; MAX_G05_AXES + 1],
        aux: None,
    };
    let batch = pb::G05Batch {
        seq: 0,
        blocks: vec![block],
        end: false,
    };
    assert!(matches!(
        decode::<pb::G05Batch>(&batch.encode_to_vec(), &LIMITS),
        Err(BoundError::Field {
            field: "blocks.travel",
            ..
        })
    ));
}

#[test]
fn revisions_comments_and_origins_are_bounded() {
    let release = pb::ProgramRelease {
        revision: "1".repeat(MAX_REVISION + 1),
        ..Default::default()
    };
    assert!(matches!(
        decode::<pb::ProgramRelease>(&release.encode_to_vec(), &LIMITS),
        Err(BoundError::Field {
            field: "revision",
            ..
        })
    ));
    let comment = pb::ProgramWrite {
        op: Some(pb::program_write::Op::Store(b"%\n%".to_vec())),
        comment: "c".repeat(MAX_COMMENT + 1),
    };
    assert!(matches!(
        decode::<pb::ProgramWrite>(&comment.encode_to_vec(), &LIMITS),
        Err(BoundError::Field {
            field: "comment",
            ..
        })
    ));
    let adopt = pb::ProgramWrite {
        op: Some(pb::program_write::Op::Adopt(pb::program_write::Adopt {
            from: "p".repeat(NAME_MAX + 1),
            revision: String::new(),
        })),
        comment: String::new(),
    };
    assert!(matches!(
        decode::<pb::ProgramWrite>(&adopt.encode_to_vec(), &LIMITS),
        Err(BoundError::Field {
            field: "adopt.from",
            ..
        })
    ));
    let origin = pb::RequestOrigin {
        user: "u".repeat(MAX_TEXT + 1),
        via: String::new(),
    };
    assert!(matches!(
        decode::<pb::RequestOrigin>(&origin.encode_to_vec(), &LIMITS),
        Err(BoundError::Field { field: "user", .. })
    ));
    let job = pb::JobRequest {
        program: Some(pb::job_request::Program::Library("O1".to_string())),
        revision: "9".repeat(MAX_REVISION + 1),
        ..Default::default()
    };
    assert!(matches!(
        decode::<pb::JobRequest>(&job.encode_to_vec(), &LIMITS),
        Err(BoundError::Field {
            field: "revision",
            ..
        })
    ));
}

#[test]
fn the_largest_valid_messages_fit_their_sizes() {
    let inline = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(vec![b'x'; 1000])),
        name: "n".repeat(MAX_TEXT),
        request_id: "r".repeat(MAX_TEXT),
        ..Default::default()
    };
    assert!(decode::<pb::JobRequest>(&inline.encode_to_vec(), &LIMITS).is_ok());
    let block = pb::G05Block {
        travel: vec![i32::MIN; MAX_G05_AXES],
        aux: Some(u32::MAX),
    };
    let batch = pb::G05Batch {
        seq: u64::MAX,
        blocks: vec![block; MAX_G05_BLOCKS],
        end: true,
    };
    assert!(decode::<pb::G05Batch>(&batch.encode_to_vec(), &LIMITS).is_ok());
    let words = pb::PlcWrite {
        words: vec![u32::MAX; MAX_PLC_WORDS],
        clear: true,
    };
    assert!(decode::<pb::PlcWrite>(&words.encode_to_vec(), &LIMITS).is_ok());
    let t = pb::PlcTransfer {
        plc: "p".repeat(MAX_TEXT),
        message: u32::MAX,
        data: vec![0xFF; MAX_TRANSFER_BYTES],
        from_plc: true,
        unix_ms: u64::MAX,
    };
    assert!(decode::<pb::PlcTransfer>(&t.encode_to_vec(), &LIMITS).is_ok());
    // The largest non-procedure message fits; one byte more is refused by its field check.
    let mut m = pb::PlcMessage {
        plc: "p".repeat(MAX_TEXT),
        data: vec![0xFF; crate::fuji::frame::MAX_NON_PROCEDURE_TEXT],
        from_plc: true,
        receive_message: u32::MAX,
        unix_ms: u64::MAX,
    };
    assert!(decode::<pb::PlcMessage>(&m.encode_to_vec(), &LIMITS).is_ok());
    m.data.push(0);
    assert!(decode::<pb::PlcMessage>(&m.encode_to_vec(), &LIMITS).is_err());
}
