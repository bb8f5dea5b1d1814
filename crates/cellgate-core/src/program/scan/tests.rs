use super::*;

fn rules(protocol: Protocol) -> ProgramRules {
    ProgramRules {
        protocol,
        end_code: EndCode::Cr,
        max_size: 1 << 20,
    }
}

#[test]
fn a_plain_program_passes_and_reports_its_number() {
    let r = scan(rules(Protocol::A), b"%\nO1234\nG00X0\nM30\n%\n").unwrap();
    assert!(r.has_eor);
    assert_eq!(r.size, 20);
    assert_eq!(r.o_number.as_deref(), Some("O1234"));
}

#[test]
fn the_tape_start_mark_is_not_eor() {
    let r = scan(rules(Protocol::A), b"%\nO1\nG00X0\n").unwrap();
    assert!(!r.has_eor);
    assert_eq!(eor_suffix(&r), b"%");
    let r = scan(rules(Protocol::A), b"O1\nG00X0").unwrap();
    assert!(!r.has_eor);
    assert_eq!(eor_suffix(&r), b"\n%");
    // Without a tape-start mark, the first % after text is EOR.
    assert!(scan(rules(Protocol::A), b"O1\nG00X0\n%").unwrap().has_eor);
}

#[test]
fn empty_programs_are_refused() {
    for p in [&b""[..], b"\n\n", b"%\n%\n", b"  %"] {
        assert_eq!(
            scan(rules(Protocol::A), p),
            Err(ProgramError::Empty),
            "{p:?}"
        );
    }
}

#[test]
fn eight_bit_bytes_are_refused_with_their_offset() {
    assert_eq!(
        scan(rules(Protocol::B), b"%\nG00\xA5X0\n%"),
        Err(ProgramError::EightBit {
            offset: 5,
            byte: 0xA5
        })
    );
}

#[test]
fn protocol_a_refuses_its_end_code_only() {
    let cr = scan(rules(Protocol::A), b"%\r\nO1\n%");
    assert_eq!(
        cr,
        Err(ProgramError::EndCodeInData {
            offset: 1,
            code: "CR (0Dh)"
        })
    );
    assert!(
        scan(rules(Protocol::ExpansionA), b"%\nO1\r\n%").is_err(),
        "expansion A keeps the rule"
    );
    let etx = ProgramRules {
        end_code: EndCode::Etx,
        ..rules(Protocol::A)
    };
    assert!(
        scan(etx, b"%\r\nO1\n%").is_ok(),
        "CR is data when ETX ends messages"
    );
    assert!(matches!(
        scan(etx, b"%\nO1\x03\n%"),
        Err(ProgramError::EndCodeInData { offset: 4, .. })
    ));
    // DC3 is no control code in Protocol A.
    assert!(scan(rules(Protocol::A), b"%\nO1\x13\n%").is_ok());
}

#[test]
fn protocol_b_refuses_its_control_codes() {
    for (c, name) in [(0x11, "DC1"), (0x13, "DC3"), (0x15, "NAK"), (0x16, "SYN")] {
        let p = [b'%', b'\n', b'G', c, b'\n', b'%'];
        match scan(rules(Protocol::ExpansionB), &p) {
            Err(ProgramError::ControlCodeInData { offset: 3, code }) => {
                assert!(code.starts_with(name))
            }
            other => panic!("{name}: {other:?}"),
        }
    }
    // CR is plain data in Protocol B.
    assert!(scan(rules(Protocol::B), b"%\r\nO1\r\n%").is_ok());
}

#[test]
fn size_is_checked_while_streaming() {
    let small = ProgramRules {
        max_size: 10,
        ..rules(Protocol::A)
    };
    let mut s = Scanner::new(small);
    s.feed(b"%\nO1\n").unwrap();
    assert_eq!(
        s.feed(b"G00X0\n%"),
        Err(ProgramError::TooLarge { size: 12, max: 10 })
    );
}

#[test]
fn pieces_give_the_same_answer_as_the_whole() {
    let program = b"%\nO0042 (PART)\nG01X1\nM30\n%\n";
    let whole = scan(rules(Protocol::A), program).unwrap();
    for split in 0..program.len() {
        let mut s = Scanner::new(rules(Protocol::A));
        s.feed(&program[..split]).unwrap();
        s.feed(&program[split..]).unwrap();
        assert_eq!(s.finish().unwrap(), whole, "split at {split}");
    }
    assert_eq!(whole.o_number.as_deref(), Some("O0042"));
}
