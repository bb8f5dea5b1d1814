use super::*;
use crate::program::name::check_name as validate_name;
use crate::program::tape::encode;
use proptest::prelude::*;

const P1: &[u8] = b"%\nO1234(PART)\nG00X1.Y2.\nM30\n%";
const P2: &[u8] = b"%\n:0012 ( SECOND  )\nG01Z-1.F100\nM30\n%";
const P3: &[u8] = b"%\n(NO NUMBER)\nG28U0W0\nM30\n%";

const CODES: [TapeCode; 3] = [TapeCode::Iso, TapeCode::Ascii, TapeCode::Eia];

/// A punch-out of `programs` in `code` with feed around and LF between, as a CNC sends it.
fn punch(code: TapeCode, programs: &[&[u8]]) -> Vec<u8> {
    let mut text = Vec::new();
    for p in programs {
        text.extend(*p);
        text.push(b'\n');
    }
    let mut out = vec![0; 5];
    out.extend(encode(&text, code).unwrap());
    out.extend([0; 5]);
    out
}

fn texts(results: Vec<Result<PunchedText, PunchError>>) -> Vec<Vec<u8>> {
    results.into_iter().map(|r| r.unwrap().text).collect()
}

fn eia_safe(p: &[u8]) -> Vec<u8> {
    // ':' has no EIA code: EIA punches the program number as O.
    p.iter()
        .map(|&b| if b == b':' { b'O' } else { b })
        .collect()
}

#[test]
fn splits_several_programs_in_one_punch() {
    for code in CODES {
        let (p1, p2, p3) = (eia_safe(P1), eia_safe(P2), eia_safe(P3));
        let programs: [&[u8]; 3] = if code == TapeCode::Eia {
            [&p1, &p2, &p3]
        } else {
            [P1, P2, P3]
        };
        let mut asm = PunchAssembler::new(1 << 20);
        let out = asm.feed(&punch(code, &programs));
        let got: Vec<PunchedText> = out.into_iter().map(Result::unwrap).collect();
        assert_eq!(got.len(), 3, "{code}");
        for (g, want) in got.iter().zip(programs) {
            assert_eq!(g.code, code);
            assert_eq!(g.text, want, "{code}");
        }
        assert_eq!(got[0].o_number.as_deref(), Some("O1234"));
        assert_eq!(got[0].comment.as_deref(), Some("PART"));
        assert_eq!(got[1].o_number.as_deref(), Some("O0012"));
        assert_eq!(got[1].comment.as_deref(), Some("SECOND"));
        assert_eq!(got[2].o_number, None);
        assert_eq!(got[2].comment.as_deref(), Some("NO NUMBER"));
        assert_eq!(asm.pending(), 0);
        assert_eq!(asm.finish(), None);
    }
}

#[test]
fn punched_names_are_recognised_for_their_machine_only() {
    let name = |o: Option<&str>| library_name("lathe-1", o, 1_795_000_000_000, |_| false).unwrap();
    let plain = name(Some("O1234"));
    assert!(is_punched_name("lathe-1", &plain));
    assert!(is_punched_name("lathe-1", &format!("{plain}-7")));
    assert!(is_punched_name("lathe-1", &name(None)));
    assert!(!is_punched_name("lathe-2", &plain));
    // A machine whose name starts another's takes only its own.
    assert!(!is_punched_name("lathe", &plain));
    assert!(is_punched_name(
        "lathe",
        &library_name("lathe", Some("O1"), 0, |_| false).unwrap()
    ));
    for other in [
        "lathe-1",
        "lathe-1-O1234",
        "O1234",
        "lathe-1-O1-2026112T061500Z",
        "lathe-1-x",
    ] {
        assert!(!is_punched_name("lathe-1", other), "{other}");
    }
}

#[test]
fn damage_marks_the_program_it_falls_in_and_no_other() {
    let tape = punch(TapeCode::Ascii, &[P1, P2, P3]);
    // The characters as punched carry a parity bit.
    let plain: Vec<u8> = tape.iter().map(|b| b & 0x7F).collect();
    let second = plain.windows(3).position(|w| w == b"SEC").unwrap();
    let mut asm = PunchAssembler::new(1 << 20);
    let mut got = asm.feed(&tape[..second + 3]);
    asm.damaged("parity error in a received character during the punch-out");
    got.extend(asm.feed(&tape[second + 3..]));
    let got: Vec<PunchedText> = got.into_iter().map(Result::unwrap).collect();
    assert_eq!(got.len(), 3);
    assert_eq!(got[0].damage, None);
    assert_eq!(
        got[1].damage.as_deref(),
        Some("parity error in a received character during the punch-out")
    );
    assert_eq!(got[2].damage, None, "the damage ends with its program");

    // Between programs: the next program may have lost its tape-start, it is suspect.
    let mut asm = PunchAssembler::new(1 << 20);
    let mut got = asm.feed(&punch(TapeCode::Ascii, &[P1]));
    asm.damaged("framing error");
    got.extend(asm.feed(&punch(TapeCode::Ascii, &[P2, P3])));
    let got: Vec<PunchedText> = got.into_iter().map(Result::unwrap).collect();
    assert_eq!(got.len(), 3);
    assert_eq!(got[0].damage, None);
    assert_eq!(got[1].damage.as_deref(), Some("framing error"));
    assert_eq!(got[2].damage, None);
}

#[test]
fn each_code_and_eob_setting_gives_the_same_text() {
    let ncr0 = b"%\n\r\rO1234(PART)\n\r\rG00X1.Y2.\n\r\rM30\n\r\r%";
    for (code, text) in [
        (TapeCode::Iso, &ncr0[..]),
        (TapeCode::Iso, P1),
        (TapeCode::Ascii, &ncr0[..]),
        (TapeCode::Eia, P1),
    ] {
        let mut asm = PunchAssembler::new(1000);
        let got = texts(asm.feed(&encode(text, code).unwrap()));
        assert_eq!(got, [P1.to_vec()], "{code}");
    }
}

#[test]
fn programs_split_across_pieces_at_every_boundary() {
    for code in CODES {
        let whole = punch(code, &[&eia_safe(P1), &eia_safe(P2)]);
        let want = texts(PunchAssembler::new(1000).feed(&whole));
        assert_eq!(want.len(), 2);
        for cut in 0..=whole.len() {
            let mut asm = PunchAssembler::new(1000);
            let mut got = texts(asm.feed(&whole[..cut]));
            got.extend(texts(asm.feed(&whole[cut..])));
            assert_eq!(got, want, "{code} cut at {cut}");
        }
        let mut asm = PunchAssembler::new(1000);
        let got: Vec<Vec<u8>> = whole.iter().flat_map(|b| texts(asm.feed(&[*b]))).collect();
        assert_eq!(got, want, "{code} byte by byte");
    }
}

#[test]
fn eia_v_is_no_eor() {
    // 25h is `V` in EIA and `%` in ASCII.
    let text = b"%\nO1(V)\nG01V5.\nM30\n%";
    let mut asm = PunchAssembler::new(1000);
    assert_eq!(
        texts(asm.feed(&punch(TapeCode::Eia, &[text]))),
        [text.to_vec()]
    );
}

#[test]
fn eia_v_between_programs_is_no_tape_start() {
    let tape = encode(b"%\nO1\nM30\n%\nV1\n%\nO2\nM30\n%", TapeCode::Eia).unwrap();
    let mut asm = PunchAssembler::new(1000);
    let out = asm.feed(&tape);
    assert_eq!(out.len(), 3, "{out:?}");
    assert_eq!(
        out[1],
        Err(PunchError::OutsideProgram { offset: 11, len: 3 })
    );
    assert_eq!(out[2].as_ref().unwrap().text, b"%\nO2\nM30\n%");
    // After an ISO byte, 25h is `%` again.
    let mut asm = PunchAssembler::new(1000);
    let mut tape = encode(b"%\nO1\n%", TapeCode::Eia).unwrap();
    tape.extend(b"\n%\nO2\n%");
    let out = texts(asm.feed(&tape));
    assert_eq!(out, [b"%\nO1\n%".to_vec(), b"%\nO2\n%".to_vec()]);
}

#[test]
fn garbage_between_programs_is_skipped_and_reported() {
    let mut tape = b"%\nO1\nM30\n%\nGARBAGE\n%\nO2\nM30\n%\n".to_vec();
    let mut asm = PunchAssembler::new(1000);
    let out = asm.feed(&tape);
    assert_eq!(out.len(), 3, "{out:?}");
    assert_eq!(out[0].as_ref().unwrap().o_number.as_deref(), Some("O1"));
    assert_eq!(
        out[1],
        Err(PunchError::OutsideProgram { offset: 11, len: 8 })
    );
    assert_eq!(out[2].as_ref().unwrap().text, b"%\nO2\nM30\n%");
    // Garbage before the first program, and at the end of the punch-out.
    tape.splice(0..0, b"xx".iter().copied());
    tape.extend(b"TRAILING");
    let mut asm = PunchAssembler::new(1000);
    let out = asm.feed(&tape);
    assert_eq!(
        out[0],
        Err(PunchError::OutsideProgram { offset: 0, len: 2 })
    );
    assert_eq!(out.len(), 4);
    assert_eq!(
        asm.finish(),
        Some(PunchError::OutsideProgram {
            offset: tape.len() as u64 - 8,
            len: 8
        })
    );
}

#[test]
fn blanks_and_repeated_tape_starts_are_not_garbage() {
    let tape = b"\0\0\r\n \t%%\n%\nO7\n%\n\r\r\0\x7f%\n%";
    let mut asm = PunchAssembler::new(1000);
    let out = asm.feed(tape);
    assert_eq!(texts(out), [b"%\nO7\n%".to_vec()]);
    assert_eq!(asm.finish(), None);
}

#[test]
fn oversize_program_is_refused_and_resyncs() {
    let mut big = b"%\nO9(BIG)\n".to_vec();
    big.extend(std::iter::repeat_n(b"G01X1.\n".as_slice(), 100).flatten());
    big.extend(b"%\n");
    big.extend(P1);
    for code in [TapeCode::Iso, TapeCode::Eia] {
        let tape = encode(&big, code).unwrap();
        let mut asm = PunchAssembler::new(200);
        let mut out = Vec::new();
        for piece in tape.chunks(7) {
            out.extend(asm.feed(piece));
            assert!(asm.pending() <= 200);
        }
        assert_eq!(out.len(), 2, "{code}");
        assert_eq!(
            out[0],
            Err(PunchError::TooLarge {
                offset: 0,
                max: 200
            })
        );
        assert_eq!(out[1].as_ref().unwrap().text, P1);
    }
    // Exactly at the limit is fine; one byte over is not.
    let mut asm = PunchAssembler::new(P1.len());
    assert_eq!(texts(asm.feed(P1)), [P1.to_vec()]);
    let mut asm = PunchAssembler::new(P1.len() - 1);
    assert!(matches!(
        asm.feed(P1).as_slice(),
        [Err(PunchError::TooLarge { .. })]
    ));
    assert_eq!(asm.finish(), None);
}

#[test]
fn unterminated_program_is_reported_at_finish() {
    let mut asm = PunchAssembler::new(1000);
    let out = asm.feed(b"%\nO1\n%\n%\nO2\nG00");
    assert_eq!(out.len(), 1);
    assert_eq!(asm.pending(), 8);
    assert_eq!(
        asm.finish(),
        Some(PunchError::Unterminated { offset: 7, len: 8 })
    );
    // Afresh: offsets count from the new punch-out.
    assert_eq!(asm.pending(), 0);
    assert_eq!(texts(asm.feed(b"%\nO3\n%")), [b"%\nO3\n%".to_vec()]);
    // A lone tape-start mark left open is no program.
    asm.feed(b"\n%\n");
    assert_eq!(asm.finish(), None);
}

#[test]
fn code_errors_name_the_program() {
    let mut tape = encode(P1, TapeCode::Iso).unwrap();
    tape[4] ^= 0x80;
    tape.extend(encode(P1, TapeCode::Iso).unwrap());
    let mut asm = PunchAssembler::new(1000);
    let out = asm.feed(&tape);
    assert_eq!(out.len(), 2);
    assert!(matches!(
        &out[0],
        Err(PunchError::Code {
            offset: 0,
            error: TapeError::Parity {
                code: TapeCode::Iso,
                offset: 4,
                ..
            }
        })
    ));
    assert_eq!(out[1].as_ref().unwrap().text, P1);
}

#[test]
fn program_numbers_and_comments() {
    let cases: [(&[u8], Option<&str>, Option<&str>); 8] = [
        (b"%\nO1234(PART)\nM30\n%", Some("O1234"), Some("PART")),
        (b"%\n:1234\nM30\n%", Some("O1234"), None),
        (b"%O0012(A)(B)\nM30\n%", Some("O0012"), Some("A")),
        (b"%\n(HEAD)\nO5 (  FIVE )\n%", Some("O5"), Some("FIVE")),
        (b"%\nG00X0\n(CUT)\n%", None, None),
        (b"%\nO123456789\n%", None, None),
        (b"%\nO12345678\n%", Some("O12345678"), None),
        (b"%\nO1(UNCLOSED\n%", Some("O1"), None),
    ];
    for (text, o, c) in cases {
        let p = PunchedText::from_text(TapeCode::Ascii, text.to_vec());
        assert_eq!(
            p.o_number.as_deref(),
            o,
            "{:?}",
            String::from_utf8_lossy(text)
        );
        assert_eq!(
            p.comment.as_deref(),
            c,
            "{:?}",
            String::from_utf8_lossy(text)
        );
    }
    let long = format!("%\nO1({})\n%", "X".repeat(100));
    let p = PunchedText::from_text(TapeCode::Ascii, long.into_bytes());
    assert_eq!(p.comment.map(|c| c.len()), Some(COMMENT_MAX));
}

fn request(text: &[u8]) -> Option<RemoteRequest> {
    RequestPatterns::default()
        .match_program(&PunchedText::from_text(TapeCode::Ascii, text.to_vec()))
}

#[test]
fn default_request_patterns() {
    let o1234 = Some(RemoteRequest {
        program: "O1234".into(),
        written: "O1234".into(),
    });
    assert_eq!(request(b"%\n(REQ O1234)\n%"), o1234);
    assert_eq!(request(b"%\n( req  o 1234 )\n\r\r%"), o1234);
    assert_eq!(request(b"%\n(PRG=1234)\n%"), o1234);
    assert_eq!(request(b"%(prg = 1234)%"), o1234);
    let r = request(b"%\n(PRG=0012)\n%").unwrap();
    assert_eq!(r.program, "O12");
    assert_eq!(r.written, "O0012");
    // The EIA spelling of a request.
    let mut asm = PunchAssembler::new(100);
    let out = asm.feed(&encode(b"%\n(REQ O55)\n%", TapeCode::Eia).unwrap());
    let program = out.into_iter().next().unwrap().unwrap();
    assert_eq!(
        RequestPatterns::default()
            .match_program(&program)
            .map(|r| r.program),
        Some("O55".to_string())
    );
}

#[test]
fn programs_that_are_no_requests() {
    for text in [
        &b"%\nO1(REQ O1234)\nM30\n%"[..],
        b"%\n(REQ O1234)\nM30\n%",
        b"%\n(REQ O1234)(REQ O1234)\n%",
        b"%\n(REQ O)\n%",
        b"%\n(REQ O123456789)\n%",
        b"%\n(REQ OA12)\n%",
        b"%\n(REQ P1234)\n%",
        b"%\n(PRG=1234\n%",
        b"%\n%",
        b"",
    ] {
        assert_eq!(request(text), None, "{:?}", String::from_utf8_lossy(text));
    }
}

#[test]
fn custom_request_patterns() {
    let pats =
        RequestPatterns::parse(&["CALL{n}".to_string(), "(SEND {n} NOW)".to_string()]).unwrap();
    let m = |t: &[u8]| pats.match_text(t).map(|r| r.program);
    assert_eq!(m(b"%\nCALL 77\n%"), Some("O77".into()));
    assert_eq!(m(b"%\n(send 0 now)\n%"), Some("O0".into()));
    assert_eq!(m(b"%\n(REQ O1234)\n%"), None);
    assert_eq!(m(b"%\nCALL 77\nM30\n%"), None);
    assert_eq!(
        RequestPatterns::parse(&[])
            .unwrap()
            .match_text(b"%\n(REQ O1)\n%"),
        None
    );
}

#[test]
fn bad_request_patterns() {
    for bad in [
        "(REQ O)",
        "(REQ O{n}{n})",
        "{n}",
        "  {n} ",
        "(REQ {x}{n})",
        "(REQ O{n}%)",
        "(REQ O{N})",
        "(REQ\nO{n})",
        "(RÉQ O{n})",
    ] {
        let e = RequestPatterns::parse(&[bad.to_string()]).unwrap_err();
        assert!(e.to_string().contains(&format!("{bad:?}")), "{e}");
    }
}

#[test]
fn request_candidates() {
    let c = |text: &[u8]| request(text).unwrap().candidates();
    assert_eq!(c(b"%\n(PRG=12)\n%"), ["O12", "O0012"]);
    assert_eq!(c(b"%\n(PRG=0012)\n%"), ["O12", "O0012"]);
    assert_eq!(c(b"%\n(PRG=00012)\n%"), ["O12", "O0012", "O00012"]);
    assert_eq!(c(b"%\n(PRG=1234)\n%"), ["O1234"]);
    assert_eq!(c(b"%\n(PRG=12345678)\n%"), ["O12345678"]);
    assert_eq!(c(b"%\n(PRG=0)\n%"), ["O0", "O0000"]);
}

#[test]
fn timestamps_of_known_dates() {
    for (secs, want) in [
        (0, "19700101T000000Z"),
        (951_782_400, "20000229T000000Z"),
        (946_684_799, "19991231T235959Z"),
        (1_709_210_096, "20240229T123456Z"),
        (1_795_328_100, "20261122T061500Z"),
        (4_107_542_400, "21000301T000000Z"),
    ] {
        assert_eq!(compact_utc(secs * 1000 + 999), want, "{secs}");
    }
    assert_eq!(civil_from_days(0), (1970, 1, 1));
    assert_eq!(civil_from_days(59), (1970, 3, 1));
    assert_eq!(civil_from_days(11_016), (2000, 2, 29));
    let _ = compact_utc(u64::MAX);
}

#[test]
fn library_names() {
    let ms = 1_795_328_100_000;
    let none = |_: &str| false;
    assert_eq!(
        library_name("mill-1", Some("O1234"), ms, none).unwrap(),
        "mill-1-O1234-20261122T061500Z"
    );
    assert_eq!(
        library_name("mill-1", None, ms, none).unwrap(),
        "mill-1-punch-20261122T061500Z"
    );
    let taken = [
        "mill-1-O1234-20261122T061500Z",
        "mill-1-O1234-20261122T061500Z-2",
    ];
    assert_eq!(
        library_name("mill-1", Some("O1234"), ms, |n| taken.contains(&n)).unwrap(),
        "mill-1-O1234-20261122T061500Z-3"
    );
    assert_eq!(library_name("mill-1", Some("O1"), ms, |_| true), None);
    for (machine, o) in [
        ("a/b*c$d?e#f", Some("O1")),
        ("_x", Some("O1/2")),
        ("", Some("")),
        ("ü", None),
        (&"m".repeat(300), Some("O12345678")),
    ] {
        let name = library_name(machine, o, ms, none).unwrap();
        assert!(validate_name(&name).is_ok(), "{name}");
        assert!(!name.contains(['/', '*', '$', '?', '#', ':']), "{name}");
    }
    assert_eq!(
        library_name("a/b", Some(""), ms, none).unwrap(),
        "a_b-punch-20261122T061500Z"
    );
}

fn realistic_punch() -> impl Strategy<Value = Vec<u8>> {
    (0..3usize, proptest::bool::ANY).prop_map(|(code, ncr0)| {
        let code = CODES[code];
        let mut text = Vec::new();
        for p in [P1, &eia_safe(P2), P3] {
            text.extend(p);
            text.extend(b"\n\n");
        }
        if ncr0 && code != TapeCode::Eia {
            text = text
                .iter()
                .flat_map(|&b| if b == LF { vec![LF, CR, CR] } else { vec![b] })
                .collect();
        }
        encode(&text, code).unwrap()
    })
}

proptest! {
    #[test]
    fn any_split_gives_the_same_programs(
        tape in realistic_punch(),
        cuts in proptest::collection::vec(any::<proptest::sample::Index>(), 0..10),
    ) {
        let want = texts(PunchAssembler::new(1000).feed(&tape));
        prop_assert_eq!(want.len(), 3);
        let mut cuts: Vec<usize> = cuts.iter().map(|i| i.index(tape.len() + 1)).collect();
        cuts.sort_unstable();
        let mut asm = PunchAssembler::new(1000);
        let mut got = Vec::new();
        let mut from = 0;
        for cut in cuts.into_iter().chain([tape.len()]) {
            got.extend(texts(asm.feed(&tape[from..cut])));
            from = cut;
        }
        prop_assert_eq!(got, want);
        prop_assert_eq!(asm.finish(), None);
    }

    #[test]
    fn garbage_never_panics(
        pieces in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..64), 0..20),
        max in 1..100usize,
    ) {
        let mut asm = PunchAssembler::new(max);
        for piece in &pieces {
            for program in asm.feed(piece).into_iter().flatten() {
                prop_assert!(program.text.first() == Some(&EOR));
                prop_assert!(program.text.last() == Some(&EOR));
                let _ = RequestPatterns::default().match_program(&program);
            }
            prop_assert!(asm.pending() <= max);
        }
        asm.finish();
        prop_assert_eq!(asm.pending(), 0);
    }
}
