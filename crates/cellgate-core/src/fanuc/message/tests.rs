use super::*;
use proptest::prelude::*;

const ASCII_CR: Framing = Framing {
    code: CodeSystem::Ascii,
    end: EndCode::Cr,
};
const ISO_CR: Framing = Framing {
    code: CodeSystem::Iso,
    end: EndCode::Cr,
};

#[test]
fn syn_example_of_protocol_notes() {
    // S+Y+N+CR = 0x53+0x59+0x4E+0x0D = 0x107 → "07".
    let bytes = ASCII_CR.encode_to_vec(&Message::new(Command::Syn)).unwrap();
    assert_eq!(bytes, b"07SYN\r");
    assert_eq!(ASCII_CR.decode(&bytes), Ok(Message::new(Command::Syn)));
}

#[test]
fn iso_carries_parity_and_sums_transmitted_bytes() {
    let bytes = ISO_CR.encode_to_vec(&Message::new(Command::Syn)).unwrap();
    // S 53h (4 ones) → 53h, Y 59h (4) → 59h, N 4Eh (4) → 4Eh, CR → 8Dh: 53+59+4E+8D = 187h.
    assert_eq!(&bytes[2..], &[0x53, 0x59, 0x4E, 0x8D]);
    assert_eq!(&bytes[..2], &[with_parity(b'8'), with_parity(b'7')]);
    assert_eq!(ISO_CR.decode(&bytes), Ok(Message::new(Command::Syn)));
}

fn with_parity(b: u8) -> u8 {
    CodeSystem::Iso.encode(b)
}

#[test]
fn etx_end_code() {
    let f = Framing::new(CodeSystem::Ascii, EndCode::Etx);
    let bytes = f
        .encode_to_vec(&Message::with_data(Command::Sdo, "A5"))
        .unwrap();
    assert_eq!(*bytes.last().unwrap(), 0x03);
    assert_eq!(f.decode(&bytes).unwrap().data, b"A5");
}

#[test]
fn dat_data_is_passed_as_is_in_iso() {
    let data = vec![0x25, 0x0A, 0xB0, 0x31]; // NC data with and without parity bits
    let bytes = ISO_CR
        .encode_to_vec(&Message::with_data(Command::Dat, data.clone()))
        .unwrap();
    assert_eq!(&bytes[5..9], &data[..]);
    assert_eq!(ISO_CR.decode(&bytes).unwrap().data, data);
}

#[test]
fn refuses_end_code_in_data_and_long_parts() {
    let err = ASCII_CR
        .encode_to_vec(&Message::with_data(Command::Dat, b"G01\rX1".to_vec()))
        .unwrap_err();
    assert_eq!(
        err,
        EncodeError::EndCodeInData {
            command: Command::Dat,
            end: 0x0D,
            offset: 3
        }
    );
    assert!(matches!(
        ASCII_CR.encode_to_vec(&Message::with_data(Command::Sat, vec![b'0'; 73])),
        Err(EncodeError::DataTooLong { max: 72, .. })
    ));
    assert!(
        ASCII_CR
            .encode_to_vec(&Message::with_data(Command::Dat, vec![b'X'; 4096]))
            .is_ok()
    );
}

#[test]
fn decode_errors() {
    assert_eq!(ASCII_CR.decode(b""), Err(FrameError::TooShort { len: 0 }));
    assert_eq!(
        ASCII_CR.decode(b"07SY\r"),
        Err(FrameError::TooShort { len: 4 })
    );
    assert_eq!(
        ASCII_CR.decode(b"08SYN\r"),
        Err(FrameError::Checksum {
            received: 0x08,
            computed: 0x07
        })
    );
    assert_eq!(
        ASCII_CR.decode(b"0aSYN\r"),
        Err(FrameError::ChecksumDigits { field: *b"0a" })
    );
    assert!(matches!(
        ASCII_CR.decode(b"00XYZ\r"),
        Err(FrameError::UnknownCommand { .. })
    ));
    // ISO: a CR without parity inside the control part.
    assert!(matches!(
        ISO_CR.decode(&[0x30, 0x30, 0x53, 0x59, 0x4F, 0x8D]),
        Err(FrameError::Parity { position: 4, .. })
    ));
}

#[test]
fn decoder_handles_partial_and_multiple_frames() {
    let mut d = Decoder::new(ASCII_CR);
    assert!(d.next_message().is_none());
    d.push(b"07S");
    assert!(d.next_message().is_none());
    d.push(b"YN\r07SY");
    assert_eq!(d.next_message(), Some(Ok(Message::new(Command::Syn))));
    assert!(d.next_message().is_none());
    d.push(b"N\r");
    assert_eq!(d.next_message(), Some(Ok(Message::new(Command::Syn))));
    assert_eq!(d.buffered(), 0);
}

#[test]
fn decoder_resyncs_after_garbage() {
    let mut d = Decoder::new(ASCII_CR);
    d.push(b"\x00\xffgarbage\r07SYN\r");
    assert!(matches!(d.next_message(), Some(Err(_))));
    assert_eq!(d.next_message(), Some(Ok(Message::new(Command::Syn))));
    // An oversize run: reported once, then dropped up to the next end code.
    d.push(&vec![b'x'; MAX_FRAME + 1]);
    assert_eq!(
        d.next_message(),
        Some(Err(FrameError::Oversize {
            dropped: MAX_FRAME + 1
        }))
    );
    d.push(b"more junk\r07SYN\r");
    assert_eq!(d.next_message(), Some(Ok(Message::new(Command::Syn))));
}

fn command() -> impl Strategy<Value = Command> {
    proptest::sample::select(Command::ALL.to_vec())
}

proptest! {
    #[test]
    fn round_trip(cmd in command(), data in proptest::collection::vec(0x20u8..0x7f, 0..72),
                  iso in any::<bool>(), etx in any::<bool>()) {
        let f = Framing::new(
            if iso { CodeSystem::Iso } else { CodeSystem::Ascii },
            if etx { EndCode::Etx } else { EndCode::Cr },
        );
        let msg = Message::with_data(cmd, data);
        let bytes = f.encode_to_vec(&msg).unwrap();
        let mut d = Decoder::new(f);
        d.push(&bytes);
        prop_assert_eq!(d.next_message(), Some(Ok(msg)));
    }

    #[test]
    fn decoder_never_panics(chunks in proptest::collection::vec(
        proptest::collection::vec(any::<u8>(), 0..600), 0..20), iso in any::<bool>()) {
        let code = if iso { CodeSystem::Iso } else { CodeSystem::Ascii };
        let mut d = Decoder::new(Framing::new(code, EndCode::Cr));
        for c in chunks {
            d.push(&c);
            while d.next_message().is_some() {}
            prop_assert!(d.buffered() <= MAX_FRAME);
        }
    }

    #[test]
    fn single_byte_corruption_is_detected(data in proptest::collection::vec(0x20u8..0x7f, 0..72),
                                          pos in any::<prop::sample::Index>(), flip in 1u8..=255) {
        let msg = Message::with_data(Command::Sat, data);
        let mut bytes = ASCII_CR.encode_to_vec(&msg).unwrap();
        let i = pos.index(bytes.len() - 1); // keep the end code
        bytes[i] ^= flip;
        if bytes[i] != 0x0D {
            prop_assert!(ASCII_CR.decode(&bytes).is_err());
        }
    }
}
