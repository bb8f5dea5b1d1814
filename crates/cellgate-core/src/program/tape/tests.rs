use super::*;
use proptest::prelude::*;

/// Every character with an EIA code, as text.
fn eia_text_chars() -> Vec<u8> {
    EIA_CHARACTERS.iter().map(|&(_, c)| c).collect()
}

#[test]
fn every_eia_code_but_blank_has_odd_parity() {
    for &(eia, text) in &EIA_CHARACTERS {
        if eia == EIA_BLANK {
            continue;
        }
        assert!(
            has_odd_parity(eia),
            "{eia:#04x} ({text:#04x}) has even parity"
        );
    }
    for b in [EIA_DELETE, EIA_UPPER_CASE, EIA_LOWER_CASE] {
        assert!(has_odd_parity(b), "{b:#04x}");
    }
    assert!(has_even_parity(EIA_BLANK));
}

#[test]
fn eia_codes_are_distinct() {
    let mut seen = std::collections::HashSet::new();
    for eia in EIA_CHARACTERS.iter().map(|&(e, _)| e).chain(EIA_IGNORED) {
        assert!(seen.insert(eia), "{eia:#04x} twice");
    }
    let mut text = std::collections::HashSet::new();
    for &(_, c) in &EIA_CHARACTERS {
        assert!(c < 0x80 && !c.is_ascii_lowercase());
        assert!(text.insert(c), "{c:#04x} twice");
    }
}

#[test]
fn eia_table_round_trips_both_ways() {
    for c in eia_text_chars() {
        let eia = iso_to_eia(&[c]).unwrap();
        assert_eq!(eia.len(), 1, "{c:#04x}");
        assert_eq!(eia_to_iso(&eia).unwrap(), vec![c], "{c:#04x}");
        // With the ISO parity bit as punched.
        assert_eq!(iso_to_eia(&[CodeSystem::Iso.encode(c)]).unwrap(), eia);
    }
    for &(eia, text) in &EIA_CHARACTERS {
        assert_eq!(eia_to_iso(&[eia]).unwrap(), vec![text]);
        assert_eq!(iso_to_eia(&[text]).unwrap(), vec![eia]);
    }
    for eia in EIA_IGNORED {
        assert_eq!(eia_to_iso(&[eia]).unwrap(), Vec::<u8>::new());
    }
    assert_eq!(iso_to_eia(&[0x00, 0x7F]).unwrap(), [EIA_BLANK, EIA_DELETE]);
}

#[test]
fn eia_codes_of_the_table() {
    assert_eq!(iso_to_eia(b"%").unwrap(), [0x0B]);
    assert_eq!(iso_to_eia(b"\n").unwrap(), [0x80]);
    assert_eq!(
        iso_to_eia(b"0123456789").unwrap(),
        [0x20, 0x01, 0x02, 0x13, 0x04, 0x15, 0x16, 0x07, 0x08, 0x19]
    );
    assert_eq!(
        iso_to_eia(b"gxz.(").unwrap(),
        [0x67, 0x37, 0x29, 0x6B, 0x1A]
    );
    assert_eq!(
        iso_to_eia(b"GXZ.)").unwrap(),
        [0x67, 0x37, 0x29, 0x6B, 0x4A]
    );
    // The ISO EOB of 0000#3 NCR = 0 (LF CR CR) is one EIA EOB.
    assert_eq!(iso_to_eia(b"M30\n\r\r").unwrap(), [0x54, 0x13, 0x20, 0x80]);
    assert_eq!(
        eia_to_iso(&[0x00, 0x0B, 0x80, 0x7C, 0x46, 0x7A, 0x01, 0x7F, 0x80]).unwrap(),
        b"%\nO1\n"
    );
}

#[test]
fn characters_without_eia_code_are_named() {
    for (i, &c) in b"#[]=:*;<>?@!\"$'^_|~{}".iter().enumerate() {
        let text = [b'G', b'1', c];
        assert_eq!(
            iso_to_eia(&text),
            Err(TapeError::NoEiaCode { offset: 2, byte: c }),
            "#{i}"
        );
    }
    let e = iso_to_eia(b"G1#5").unwrap_err();
    assert_eq!(
        e.to_string(),
        "character '#' (0x23) at offset 2 has no EIA code"
    );
    assert_eq!(encode(b"X=1", TapeCode::Eia), iso_to_eia(b"X=1"));
}

#[test]
fn eia_errors() {
    // 0x03 has even parity; 0x0D odd but unassigned.
    assert_eq!(
        eia_to_iso(&[0x0B, 0x03]),
        Err(TapeError::Parity {
            code: TapeCode::Eia,
            offset: 1,
            byte: 0x03
        })
    );
    assert_eq!(
        eia_to_iso(&[0x0B, 0x0D]),
        Err(TapeError::NotEia {
            offset: 1,
            byte: 0x0D
        })
    );
}

#[test]
fn encode_in_each_code() {
    assert_eq!(
        encode(b"%\nO1\n%", TapeCode::Iso).unwrap(),
        [0xA5, 0x0A, 0xCF, 0xB1, 0x0A, 0xA5]
    );
    assert_eq!(encode(b"%\nO1\n%", TapeCode::Ascii).unwrap(), b"%\nO1\n%");
    assert_eq!(
        encode(b"%\nO1\n%", TapeCode::Eia).unwrap(),
        [0x0B, 0x80, 0x46, 0x01, 0x80, 0x0B]
    );
    assert_eq!(
        encode(b"O1\xB1", TapeCode::Ascii),
        Err(TapeError::EightBit {
            offset: 2,
            byte: 0xB1
        })
    );
}

const PROGRAM: &[u8] = b"%\nO1234(PART)\nG00X1.Y2.\nM30\n%";
const PROGRAM_NCR0: &[u8] = b"%\n\r\rO1234(PART)\n\r\rG00X1.Y2.\n\r\rM30\n\r\r%";

#[test]
fn detects_realistic_programs() {
    for text in [PROGRAM, PROGRAM_NCR0] {
        for code in [TapeCode::Iso, TapeCode::Ascii, TapeCode::Eia] {
            let tape = encode(text, code).unwrap();
            assert_eq!(detect(&tape), code, "{code} {text:?}");
            let (got, decoded) = decode(&tape).unwrap();
            assert_eq!(got, code);
            if code == TapeCode::Eia {
                assert_eq!(decoded, PROGRAM);
            } else {
                assert_eq!(decoded, text);
            }
        }
    }
    // With feed before and after, as spec. no. 1 and 2 punch it (§10).
    let mut eia = vec![0; 10];
    eia.extend(encode(PROGRAM, TapeCode::Eia).unwrap());
    eia.extend([0; 10]);
    assert_eq!(decode(&eia).unwrap(), (TapeCode::Eia, PROGRAM.to_vec()));
    let mut iso = vec![0; 10];
    iso.extend(encode(PROGRAM, TapeCode::Iso).unwrap());
    assert_eq!(decode(&iso).unwrap(), (TapeCode::Iso, PROGRAM.to_vec()));
}

#[test]
fn detects_short_programs() {
    for text in [&b"%"[..], b"%\n%", b"%O1%", b"%\nM30\n%", b"%\nO1\n%"] {
        for code in [TapeCode::Iso, TapeCode::Ascii, TapeCode::Eia] {
            let tape = encode(text, code).unwrap();
            assert_eq!(detect(&tape), code, "{code} {text:?}");
        }
    }
    assert_eq!(detect(b""), TapeCode::Ascii);
    assert_eq!(detect(&[0, 0]), TapeCode::Ascii);
    // All odd parity but no EIA mark: ASCII.
    assert_eq!(detect(b"O1"), TapeCode::Ascii);
    // A text that needs no parity bit: ISO and ASCII give the same bytes.
    assert_eq!(
        detect(&encode(b"G0\n", TapeCode::Iso).unwrap()),
        TapeCode::Ascii
    );
}

#[test]
fn decode_as_a_known_code() {
    let iso = encode(PROGRAM, TapeCode::Iso).unwrap();
    assert_eq!(decode_as(&iso, TapeCode::Iso).unwrap(), PROGRAM);
    assert_eq!(
        decode_as(&iso, TapeCode::Ascii),
        Err(TapeError::EightBit {
            offset: 0,
            byte: 0xA5
        })
    );
    assert_eq!(
        decode_as(b"%\nO1", TapeCode::Iso),
        Err(TapeError::Parity {
            code: TapeCode::Iso,
            offset: 0,
            byte: b'%'
        })
    );
    // Feed and delete are dropped in every code.
    assert_eq!(decode_as(b"\0%\x7f\n", TapeCode::Ascii).unwrap(), b"%\n");
    assert_eq!(decode_as(&[0x00, 0xA5, 0xFF], TapeCode::Iso).unwrap(), b"%");
}

#[test]
fn misfits_are_parity_errors() {
    let mut iso = encode(PROGRAM, TapeCode::Iso).unwrap();
    iso[5] ^= 0x80;
    match decode(&iso) {
        Err(TapeError::Parity {
            code: TapeCode::Iso,
            offset: 5,
            ..
        }) => {}
        other => panic!("{other:?}"),
    }
    let mut eia = encode(PROGRAM, TapeCode::Eia).unwrap();
    eia[4] ^= 0x10;
    match decode(&eia) {
        Err(TapeError::Parity {
            code: TapeCode::Eia,
            offset: 4,
            ..
        }) => {}
        other => panic!("{other:?}"),
    }
}

fn eia_text() -> impl Strategy<Value = Vec<u8>> {
    proptest::collection::vec(proptest::sample::select(eia_text_chars()), 0..200)
}

proptest! {
    #[test]
    fn text_survives_eia(text in eia_text()) {
        let eia = encode(&text, TapeCode::Eia).unwrap();
        prop_assert!(eia.iter().all(|&b| has_odd_parity(b)));
        prop_assert_eq!(eia_to_iso(&eia).unwrap(), text);
    }

    #[test]
    fn text_survives_iso(text in eia_text()) {
        let iso = encode(&text, TapeCode::Iso).unwrap();
        prop_assert!(iso.iter().all(|&b| has_even_parity(b)));
        let (_, back) = decode(&iso).unwrap();
        prop_assert_eq!(back, text);
    }

    #[test]
    fn tapes_with_marks_are_recognised(text in eia_text()) {
        let mut program = b"%\n".to_vec();
        program.extend(&text);
        program.extend(b"\n%");
        for code in [TapeCode::Iso, TapeCode::Eia] {
            let tape = encode(&program, code).unwrap();
            prop_assert_eq!(detect(&tape), code);
        }
    }

    #[test]
    fn garbage_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let code = detect(&bytes);
        if let Ok((got, text)) = decode(&bytes) {
            prop_assert_eq!(got, code);
            prop_assert!(text.iter().all(|&b| b < 0x80));
        }
        let _ = eia_to_iso(&bytes);
        let _ = iso_to_eia(&bytes);
    }
}
