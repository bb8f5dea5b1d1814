use super::*;
use proptest::prelude::*;

/// The §7-2 read request: read 2 bytes of M (01) from relative address 0.
const READ_TEXT: [u8; 9] = [0x00, 0x00, 0x00, 0x01, 0x04, 0x00, 0x00, 0x02, 0x00];

fn oks(v: Vec<Decoded>) -> Vec<Vec<u8>> {
    v.into_iter().filter_map(Result::ok).collect()
}

fn errs(v: &[Decoded]) -> Vec<ReceiveErrorKind> {
    v.iter()
        .filter_map(|d| d.as_ref().err().map(ReceiveError::kind))
        .collect()
}

fn bcc_settings(kind: BccKind, range: BccRange, calc: BccCalc, code: BccCode) -> FrameSettings {
    FrameSettings {
        bcc: kind,
        bcc_range: range,
        bcc_calc: calc,
        bcc_code: code,
        ..FrameSettings::default()
    }
}

#[test]
fn default_settings_encode_the_section_7_read_sample() {
    let s = FrameSettings::default();
    assert!(s.validate().is_empty());
    assert_eq!(s.encode(&READ_TEXT), b":000000010400000200\r");
    assert_eq!(s.line_len(READ_TEXT.len()), 20);
}

#[test]
fn appendix_bcc_example_goes_after_the_end_code() {
    let s = bcc_settings(
        BccKind::Set1,
        BccRange::StartTextEnd,
        BccCalc::Add,
        BccCode::TransmissionCode,
    );
    assert_eq!(s.encode(&READ_TEXT), b":000000010400000200\rAE");
    let s2 = FrameSettings {
        bcc: BccKind::Set2,
        ..s.clone()
    };
    assert_eq!(s2.encode(&READ_TEXT), b":000000010400000200\rEA");
    let bin = FrameSettings {
        bcc_code: BccCode::Binary,
        ..s.clone()
    };
    assert_eq!(bin.encode(&READ_TEXT), b":000000010400000200\r\xAE");
    // Range "text": BCC over the text only, before the end code.
    let t = bcc_settings(
        BccKind::Set1,
        BccRange::Text,
        BccCalc::Add,
        BccCode::TransmissionCode,
    );
    let sum = super::super::bcc::sum8(b"000000010400000200");
    let mut want = b":000000010400000200".to_vec();
    want.extend_from_slice(&hex2(sum));
    want.push(CR);
    assert_eq!(t.encode(&READ_TEXT), want);
    for s in [s, s2, bin, t] {
        let mut d = FrameDecoder::command_set(&s);
        assert_eq!(
            oks(d.decode(&s.encode(&READ_TEXT))),
            vec![READ_TEXT.to_vec()]
        );
    }
}

/// The appendix's worked example in EBCDIC (items 13, 14; FFU120B notes 10): every character
/// of the frame is EBCDIC, the start code `:` (7Ah) and the BCC's hex characters included, and
/// the BCC is summed over the bytes as transmitted.
#[test]
fn the_appendix_example_in_ebcdic() {
    let s = FrameSettings {
        code: TransmissionCode::Ebcdic,
        ..bcc_settings(
            BccKind::Set1,
            BccRange::StartTextEnd,
            BccCalc::Add,
            BccCode::TransmissionCode,
        )
    };
    // ':' 7Ah, "000000010400000200" as F0h–F9h, CR 0Dh.
    let mut body = vec![0x7A];
    body.extend(b"000000010400000200".iter().map(|c| 0xF0 + (c - b'0')));
    body.push(CR);
    let sum = super::super::bcc::sum8(&body);
    // 7A + 15 × F0 + F1 + F4 + F2 + 0D = 116E: the BCC is 6Eh, written "6E" in EBCDIC.
    assert_eq!(sum, 0x6E);
    let mut want = body.clone();
    want.extend([0xF6, 0xC5]);
    assert_eq!(s.encode(&READ_TEXT), want);
    let mut d = FrameDecoder::command_set(&s);
    assert_eq!(oks(d.decode(&want)), vec![READ_TEXT.to_vec()]);
    // The ASCII frame is no EBCDIC frame: its start code is not found.
    let ascii = FrameSettings {
        code: TransmissionCode::Ascii,
        ..s.clone()
    };
    let mut d = FrameDecoder::command_set(&s);
    assert!(oks(d.decode(&ascii.encode(&READ_TEXT))).is_empty());
    // (A run of garbage is counted once it ends: here at the silence that clears it.)
    d.clear();
    assert_eq!(d.counts().start_code, 1);
    // LF is 25h in EBCDIC; a spoilt hex character is a BCC error, then a text-form error.
    let lf = FrameSettings {
        end_code: EndCode::Lf,
        ..s.clone()
    };
    assert_eq!(lf.end_bytes(), [0x25]);
    let mut spoilt = want.clone();
    spoilt[3] = 0xF1;
    let mut d = FrameDecoder::command_set(&s);
    assert!(oks(d.decode(&spoilt)).is_empty());
    assert_eq!(d.counts().bcc, 1);
    // EBCDIC with 7 data bits is initial error F6.
    let seven = crate::engine::LineSettings {
        data_bits: crate::engine::line::DataBits::Seven,
        ..crate::engine::LineSettings::default()
    };
    let f6: Vec<_> = s
        .validate_with_line(&seven)
        .iter()
        .map(FrameProblem::initial_error)
        .collect();
    assert_eq!(f6, [Some(0xF6)]);
    assert!(ascii.validate_with_line(&seven).is_empty());
}

#[test]
fn validate_reports_every_initial_error() {
    let problems = |s: &FrameSettings| -> Vec<Option<u8>> {
        s.validate()
            .iter()
            .map(FrameProblem::initial_error)
            .collect()
    };
    // F1 and F2 together, then F3.
    let s = bcc_settings(
        BccKind::Set1,
        BccRange::Text,
        BccCalc::Crc16,
        BccCode::Binary,
    );
    assert_eq!(problems(&s), vec![Some(0xF1), Some(0xF2)]);
    let s = bcc_settings(
        BccKind::Set1,
        BccRange::TextEnd,
        BccCalc::Crc16,
        BccCode::TransmissionCode,
    );
    assert_eq!(problems(&s), vec![Some(0xF3)]);
    let s = bcc_settings(
        BccKind::Set2,
        BccRange::StartText,
        BccCalc::Crc16,
        BccCode::TransmissionCode,
    );
    assert_eq!(problems(&s), vec![Some(0xF2), Some(0xF3)]);
    // No BCC: the BCC items do not matter.
    let s = bcc_settings(
        BccKind::None,
        BccRange::Text,
        BccCalc::Crc16,
        BccCode::Binary,
    );
    assert!(s.validate().is_empty());
    // Set 1 / Set 2 codes without their bytes: F0, and F5 for an end code with none.
    let s = FrameSettings {
        start_code: StartCode::Set2,
        start_codes: vec![0x2A],
        end_code: EndCode::Set1,
        ..FrameSettings::default()
    };
    assert_eq!(problems(&s), vec![Some(0xF0), Some(0xF5)]);
    let s = FrameSettings {
        end_code: EndCode::Set2,
        end_codes: vec![1, 2, 3],
        ..FrameSettings::default()
    };
    assert_eq!(problems(&s), vec![Some(0xF0)]);
    // A hex character as a code, with transposition: not an initial error, but ambiguous.
    let s = FrameSettings {
        start_code: StartCode::Set1,
        start_codes: vec![b'A'],
        ..FrameSettings::default()
    };
    assert_eq!(problems(&s), vec![None]);
    let msg = s.validate()[0].to_string();
    assert!(msg.contains("hex character"), "{msg}");
    let msg = FrameProblem::CrcInTransmissionCode.to_string();
    assert!(msg.contains("F3") && msg.contains("§4-7"), "{msg}");
}

#[test]
fn empty_input_gives_nothing() {
    let mut d = FrameDecoder::command_set(&FrameSettings::default());
    assert!(d.decode(b"").is_empty());
    assert_eq!(d.buffered(), 0);
    assert_eq!(d.counts().total(), 0);
}

#[test]
fn partial_input_byte_by_byte() {
    let s = bcc_settings(
        BccKind::Set1,
        BccRange::StartTextEnd,
        BccCalc::Add,
        BccCode::TransmissionCode,
    );
    let line = s.encode(&READ_TEXT);
    let mut d = FrameDecoder::command_set(&s);
    let mut got = Vec::new();
    for (i, b) in line.iter().enumerate() {
        let out = d.decode(&[*b]);
        if i + 1 < line.len() {
            assert!(out.is_empty(), "text complete after {i} bytes");
            assert!(d.in_text());
        }
        got.extend(out);
    }
    assert_eq!(oks(got), vec![READ_TEXT.to_vec()]);
    assert!(!d.in_text());
}

#[test]
fn corrupt_bcc_is_counted_and_the_next_text_decodes() {
    let s = bcc_settings(
        BccKind::Set1,
        BccRange::StartTextEnd,
        BccCalc::Add,
        BccCode::TransmissionCode,
    );
    let mut line = s.encode(&READ_TEXT);
    let last = line.len() - 1;
    line[last] = b'0';
    line.extend(s.encode(&READ_TEXT));
    let mut d = FrameDecoder::command_set(&s);
    let out = d.decode(&line);
    assert_eq!(errs(&out), vec![ReceiveErrorKind::Bcc]);
    assert_eq!(oks(out), vec![READ_TEXT.to_vec()]);
    assert_eq!(d.counts().bcc, 1);
    assert_eq!(d.counts().total(), 1);
}

#[test]
fn garbage_before_a_start_code_is_one_start_code_error() {
    let s = FrameSettings::default();
    let mut d = FrameDecoder::command_set(&s);
    let mut line = b"\x00\xffjunk".to_vec();
    line.extend(s.encode(&READ_TEXT));
    let out = d.decode(&line);
    assert_eq!(
        out[0],
        Err(ReceiveError::StartCode { dropped: 6 }),
        "{out:?}"
    );
    assert_eq!(oks(out), vec![READ_TEXT.to_vec()]);
    // Fed byte by byte, the same run of garbage is still one error.
    let mut d = FrameDecoder::command_set(&s);
    let mut all = Vec::new();
    for b in &line {
        all.extend(d.decode(&[*b]));
    }
    assert_eq!(errs(&all), vec![ReceiveErrorKind::StartCode]);
    assert_eq!(oks(all), vec![READ_TEXT.to_vec()]);
    // Garbage with no start code after it is counted when the decoder is cleared.
    let mut d = FrameDecoder::command_set(&s);
    assert!(d.decode(b"noise").is_empty());
    d.clear();
    assert_eq!(d.counts().start_code, 1);
}

#[test]
fn unreadable_transposed_text_is_a_text_form_error() {
    let s = FrameSettings::default();
    let mut d = FrameDecoder::command_set(&s);
    let out = d.decode(b":00000001040000020G\r:0000000104000002\r:000\r");
    assert_eq!(
        out,
        vec![
            Err(ReceiveError::TextForm(TextForm::NotHex {
                offset: 17,
                byte: b'G'
            })),
            Ok(vec![0, 0, 0, 1, 4, 0, 0, 2]),
            Err(ReceiveError::TextForm(TextForm::OddLength { len: 3 })),
        ]
    );
    // Lower-case hex is not the transmission code's "A to F" (§4-3 item 14).
    let out = d.decode(b":0000000104000002ff\r");
    assert_eq!(errs(&out), vec![ReceiveErrorKind::TextForm]);
    assert_eq!(d.counts().text_form, 3);
    // A text shorter than a command-set header.
    let out = d.decode(b":00000001\r");
    assert_eq!(
        out,
        vec![Err(ReceiveError::TextForm(TextForm::TooShort {
            len: 4,
            min: 5
        }))]
    );
}

#[test]
fn a_new_start_code_restarts_the_frame() {
    let s = FrameSettings::default();
    let mut d = FrameDecoder::command_set(&s);
    let mut line = b":000000".to_vec();
    line.extend(s.encode(&READ_TEXT));
    let out = d.decode(&line);
    assert_eq!(
        out[0],
        Err(ReceiveError::TextForm(TextForm::Truncated { after: 6 }))
    );
    assert_eq!(oks(out), vec![READ_TEXT.to_vec()]);
}

#[test]
fn overlong_text_is_dropped_and_the_decoder_resyncs() {
    let s = FrameSettings::default();
    let mut d = FrameDecoder::command_set(&s);
    let mut line = vec![b':'];
    line.extend(std::iter::repeat_n(b'0', 2 * MAX_COMMAND_TEXT + 10));
    line.push(CR);
    line.extend(s.encode(&READ_TEXT));
    let out = d.decode(&line);
    assert_eq!(errs(&out), vec![ReceiveErrorKind::TooLong]);
    assert_eq!(oks(out), vec![READ_TEXT.to_vec()]);
    assert!(d.buffered() <= RX_BUFFER);
    // Exactly the longest text passes; one byte more does not.
    let ok = s.encode(&vec![0x11; MAX_COMMAND_TEXT]);
    assert_eq!(oks(d.decode(&ok)).len(), 1);
    let long = s.encode(&vec![0x11; MAX_COMMAND_TEXT + 1]);
    assert_eq!(errs(&d.decode(&long)), vec![ReceiveErrorKind::TooLong]);
    assert_eq!(d.counts().too_long, 2);
}

#[test]
fn binary_text_may_carry_the_end_code_byte() {
    let s = FrameSettings {
        transposition: false,
        bcc: BccKind::Set1,
        bcc_range: BccRange::StartTextEnd,
        bcc_calc: BccCalc::Crc16,
        bcc_code: BccCode::Binary,
        ..FrameSettings::default()
    };
    assert!(s.validate().is_empty());
    // A write of CR LF ETX ':' to D: BYTEN = 4 + 4.
    let text = [
        0x01, 0x00, 0x00, 0x05, 0x08, 0x00, 0x00, 0x04, 0x00, CR, LF, ETX, b':',
    ];
    let line = s.encode(&text);
    let mut d = FrameDecoder::command_set(&s);
    assert_eq!(oks(d.decode(&line)), vec![text.to_vec()]);
    // Without the end code where BYTEN says: text form unidentified, then resync.
    let mut bad = line.clone();
    bad[5] = 0x09;
    bad.extend(&line);
    let out = d.decode(&bad);
    assert!(errs(&out).contains(&ReceiveErrorKind::TextForm), "{out:?}");
    assert_eq!(oks(out), vec![text.to_vec()]);
}

#[test]
fn start_code_none_frames_follow_each_other() {
    let s = FrameSettings {
        start_code: StartCode::None,
        bcc: BccKind::Set1,
        bcc_range: BccRange::TextEnd,
        bcc_calc: BccCalc::Eor,
        bcc_code: BccCode::Binary,
        ..FrameSettings::default()
    };
    let mut line = s.encode(&READ_TEXT);
    line.extend(s.encode(&[1, 2, 3, 4, 0]));
    let mut d = FrameDecoder::command_set(&s);
    assert_eq!(
        oks(d.decode(&line)),
        vec![READ_TEXT.to_vec(), vec![1, 2, 3, 4, 0]]
    );
    // Half a frame, then a silence (cleared), then a whole one.
    let whole = s.encode(&READ_TEXT);
    assert!(d.decode(&whole[..7]).is_empty());
    d.clear();
    assert_eq!(oks(d.decode(&whole)), vec![READ_TEXT.to_vec()]);
}

#[test]
fn non_procedure_fixed_and_variable_length() {
    let s = FrameSettings::default();
    // Fixed length without transposition: every 4 bytes, start and end codes are data
    // (appendix).
    let raw = FrameSettings {
        transposition: false,
        ..FrameSettings::default()
    };
    let mut d = FrameDecoder::non_procedure(&raw, Some(4));
    let out = oks(d.decode(b":AB\rXYZ"));
    assert_eq!(out, vec![b":AB\r".to_vec()]);
    assert_eq!(oks(d.decode(b"W")), vec![b"XYZW".to_vec()]);
    assert_eq!(raw.encode_bare(b":AB\r"), b":AB\r");
    // With transposition (the initial value): 2N hex characters a message, nothing else
    // (§4-3 items 14–15); item 14's example: 12h travels as "1" "2".
    assert_eq!(s.encode_bare(&[0x12, 0x3A, 0x0D, 0xFF]), b"123A0DFF");
    let mut d = FrameDecoder::non_procedure(&s, Some(4));
    assert!(d.decode(b"123A0D").is_empty());
    assert_eq!(oks(d.decode(b"FF3")), vec![vec![0x12, 0x3A, 0x0D, 0xFF]]);
    assert_eq!(
        errs(&d.decode(b"a3A0DFF")),
        vec![ReceiveErrorKind::TextForm]
    );
    assert_eq!(oks(d.decode(b"00000000")), vec![vec![0; 4]]);
    // The longest: 216 bytes, 432 characters, within the module's 512-byte buffer.
    let mut d = FrameDecoder::non_procedure(&s, Some(MAX_NON_PROCEDURE_TEXT));
    let long = s.encode_bare(&[0xA5; MAX_NON_PROCEDURE_TEXT]);
    assert_eq!(long.len(), 2 * MAX_NON_PROCEDURE_TEXT);
    assert_eq!(
        oks(d.decode(&long)),
        vec![vec![0xA5; MAX_NON_PROCEDURE_TEXT]]
    );
    // Variable length: up to the end code, 1..=216 bytes.
    let mut d = FrameDecoder::non_procedure(&s, None);
    let msg = s.encode(b"hello");
    assert_eq!(msg, b":68656C6C6F\r");
    assert_eq!(oks(d.decode(&msg)), vec![b"hello".to_vec()]);
    let long = s.encode(&[7u8; MAX_NON_PROCEDURE_TEXT + 1]);
    assert_eq!(errs(&d.decode(&long)), vec![ReceiveErrorKind::TooLong]);
    assert_eq!(errs(&d.decode(b":\r")), vec![ReceiveErrorKind::TextForm]);
}

fn start_codes() -> Vec<(StartCode, Vec<u8>)> {
    vec![
        (StartCode::None, vec![]),
        (StartCode::Stx, vec![]),
        (StartCode::Colon, vec![]),
        (StartCode::DoubleColon, vec![]),
        (StartCode::Set1, vec![0x2A]),
        (StartCode::Set2, vec![0x2A, 0x23]),
    ]
}

fn end_codes() -> Vec<(EndCode, Vec<u8>)> {
    vec![
        (EndCode::Etx, vec![]),
        (EndCode::Cr, vec![]),
        (EndCode::Lf, vec![]),
        (EndCode::CrLf, vec![]),
        (EndCode::DleEtx, vec![]),
        (EndCode::Set1, vec![0x04]),
        (EndCode::Set2, vec![0x17, 0x04]),
    ]
}

fn bcc_options() -> Vec<(BccKind, BccRange, BccCalc, BccCode)> {
    let mut v = vec![(
        BccKind::None,
        BccRange::Text,
        BccCalc::Add,
        BccCode::TransmissionCode,
    )];
    for kind in [BccKind::Set1, BccKind::Set2] {
        for range in [
            BccRange::Text,
            BccRange::TextEnd,
            BccRange::StartText,
            BccRange::StartTextEnd,
        ] {
            for calc in [
                BccCalc::Add,
                BccCalc::AddInvert,
                BccCalc::Eor,
                BccCalc::Crc16,
            ] {
                for code in [BccCode::TransmissionCode, BccCode::Binary] {
                    v.push((kind, range, calc, code));
                }
            }
        }
    }
    v
}

/// Every combination the module accepts (§4-7), for each start code, end code, BCC and
/// transposition setting.
pub(crate) fn every_valid_setting() -> Vec<FrameSettings> {
    let mut all = Vec::new();
    for (start_code, start_codes) in start_codes() {
        for (end_code, end_codes) in end_codes() {
            for transposition in [true, false] {
                for (bcc, bcc_range, bcc_calc, bcc_code) in bcc_options() {
                    for code in [TransmissionCode::Ascii, TransmissionCode::Ebcdic] {
                        let s = FrameSettings {
                            start_code,
                            start_codes: start_codes.clone(),
                            end_code,
                            end_codes: end_codes.clone(),
                            transposition,
                            code,
                            bcc,
                            bcc_range,
                            bcc_calc,
                            bcc_code,
                            crc16: Crc16::Arc,
                        };
                        if s.validate().is_empty() {
                            all.push(s);
                        }
                    }
                }
            }
        }
    }
    all
}

#[test]
fn every_start_end_bcc_and_transposition_combination_round_trips() {
    let all = every_valid_setting();
    // 6 start codes × 7 end codes × 2 × (1 + 2 kinds × 4 ranges × 4 calcs × 2 codes, less
    // the initial errors F1–F3).
    assert!(all.len() > 1000, "{}", all.len());
    // A text whose data holds every control code the frames use.
    let mut text = vec![0x01, 0x00, 0x00, 0x05, 0x0C, 0x00, 0x00, 0x08, 0x00];
    text.extend([CR, LF, ETX, DLE, STX, b':', 0x2A, 0x04]);
    for s in &all {
        let mut line = s.encode(&READ_TEXT);
        line.extend(s.encode(&text));
        let mut d = FrameDecoder::command_set(s);
        let whole = d.decode(&line);
        assert_eq!(
            whole,
            vec![Ok(READ_TEXT.to_vec()), Ok(text.clone())],
            "{s:?}"
        );
        let mut d = FrameDecoder::command_set(s);
        let mut bytewise = Vec::new();
        for b in &line {
            bytewise.extend(d.decode(&[*b]));
        }
        assert_eq!(bytewise, whole, "byte by byte {s:?}");
        assert_eq!(d.counts().total(), 0);
    }
}

#[test]
fn serde_spellings_of_the_cell_file() {
    let s: FrameSettings = toml::from_str(
        "start_code = \"double-colon\"\nend_code = \"cr-lf\"\nbcc = \"set2\"\n\
         bcc_range = \"start+text+end\"\nbcc_calc = \"crc-16\"\nbcc_code = \"binary\"\n\
         transposition = false",
    )
    .unwrap();
    assert_eq!(s.start_code, StartCode::DoubleColon);
    assert_eq!(s.end_code, EndCode::CrLf);
    assert_eq!(s.bcc_range, BccRange::StartTextEnd);
    assert_eq!(s.bcc_calc, BccCalc::Crc16);
    let s: FrameSettings =
        toml::from_str("start_code = \":\"\nend_code = \"dle-etx\"\nbcc_range = \"text+end\"")
            .unwrap();
    assert_eq!(
        (s.start_code, s.end_code, s.bcc_range),
        (StartCode::Colon, EndCode::DleEtx, BccRange::TextEnd)
    );
    let s: FrameSettings = toml::from_str("start_code = \"set1\"\nstart_codes = [42]").unwrap();
    assert_eq!(s.start_bytes(), b"*");
    let d = FrameSettings::default();
    assert_eq!(toml::from_str::<FrameSettings>("").unwrap(), d);
    assert!(d.transposition);
    assert!(toml::from_str::<FrameSettings>("start_code = \"none\"").is_ok());
    assert!(toml::from_str::<FrameSettings>("end_code = \"none\"").is_err());
}

fn arb_settings() -> impl Strategy<Value = FrameSettings> {
    (
        0usize..6,
        0usize..7,
        any::<bool>(),
        0usize..65,
        proptest::collection::vec(any::<u8>(), 0..3),
        proptest::collection::vec(any::<u8>(), 0..3),
    )
        .prop_map(|(si, ei, transposition, bi, sc, ec)| {
            let (start_code, _) = start_codes()[si].clone();
            let (end_code, _) = end_codes()[ei].clone();
            let (bcc, bcc_range, bcc_calc, bcc_code) = bcc_options()[bi];
            // Arbitrary set bytes, possibly the wrong number of them: the decoder must cope.
            FrameSettings {
                start_code,
                start_codes: sc,
                end_code,
                end_codes: ec,
                transposition,
                // A third of the cases in EBCDIC (item 13).
                code: if bi % 3 == 0 {
                    TransmissionCode::Ebcdic
                } else {
                    TransmissionCode::Ascii
                },
                bcc,
                bcc_range,
                bcc_calc,
                bcc_code,
                crc16: Crc16::Arc,
            }
        })
}

proptest! {
    #[test]
    fn arbitrary_bytes_never_panic_and_the_buffer_stays_bounded(
        s in arb_settings(),
        fixed in proptest::option::of(0usize..600),
        chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..700), 0..12),
    ) {
        let mut decoders = vec![
            FrameDecoder::command_set(&s),
            FrameDecoder::non_procedure(&s, None),
            FrameDecoder::non_procedure(&s, fixed),
        ];
        for d in &mut decoders {
            for c in &chunks {
                for t in d.decode(c).into_iter().flatten() {
                    prop_assert!(t.len() <= RX_BUFFER);
                }
                prop_assert!(d.buffered() <= RX_BUFFER);
            }
            d.clear();
            prop_assert_eq!(d.buffered(), 0);
        }
    }

    #[test]
    fn a_corrupted_byte_never_yields_a_text(
        text in proptest::collection::vec(any::<u8>(), 5..60),
        pos in any::<prop::sample::Index>(),
        flip in 1u8..=255,
    ) {
        let s = bcc_settings(BccKind::Set1, BccRange::StartTextEnd, BccCalc::Add, BccCode::TransmissionCode);
        let mut line = s.encode(&text);
        let i = pos.index(line.len());
        line[i] ^= flip;
        // A byte turned into a start or end code makes a different frame, not a corrupted one.
        prop_assume!(line[i] != b':' && line[i] != CR);
        let mut d = FrameDecoder::non_procedure(&s, None);
        let out = d.decode(&line);
        prop_assert!(out.iter().all(Result::is_err), "{:?}", out);
    }

    #[test]
    fn round_trip_arbitrary_texts(s in arb_settings(), text in proptest::collection::vec(any::<u8>(), 0..220)) {
        prop_assume!(s.validate().is_empty());
        let mut t = vec![0x01, 0x00, 0x00, 0x05];
        t.push(u8::try_from(text.len()).unwrap());
        t.extend(&text);
        let mut d = FrameDecoder::command_set(&s);
        prop_assert_eq!(d.decode(&s.encode(&t)), vec![Ok(t)]);
    }
}

/// A character error where a start code was awaited (the start code itself was hit): the
/// rest of that text is dropped as a text ended by a character error (§5-6), not as noise
/// before a start code, and a text that follows is read as usual.
#[test]
fn a_text_whose_start_code_was_spoilt_counts_as_ended_by_its_character_error() {
    let s = FrameSettings::default();
    let text = s.encode(&READ_TEXT);
    let mut d = FrameDecoder::command_set(&s);
    assert!(d.spoil(LineError::Parity).is_empty());
    let mut out = d.decode(&text[1..]);
    out.extend(d.decode(&text));
    assert_eq!(errs(&out), [ReceiveErrorKind::Character]);
    assert_eq!(oks(out), [READ_TEXT.to_vec()]);
    let c = d.counts();
    assert_eq!((c.character, c.start_code), (1, 0), "{c:?}");
    // Noise with no spoilt character before it stays noise; a spoilt character with no
    // text after it blames nothing that follows.
    let mut d = FrameDecoder::command_set(&s);
    assert!(d.spoil(LineError::Framing).is_empty());
    let mut out = d.decode(&text);
    out.extend(d.decode(b"xx"));
    out.extend(d.decode(&text));
    assert_eq!(errs(&out), [ReceiveErrorKind::StartCode]);
    assert_eq!(oks(out).len(), 2);
}
