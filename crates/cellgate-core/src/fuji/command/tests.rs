use super::*;
use crate::fuji::frame::{FrameDecoder, FrameSettings, TextForm};

fn line(text: &[u8]) -> String {
    String::from_utf8(FrameSettings::default().encode(text)).unwrap()
}

fn decode_line(l: &str) -> CommandText {
    let mut d = FrameDecoder::command_set(&FrameSettings::default());
    let mut out = d.decode(l.as_bytes());
    assert_eq!(out.len(), 1, "{out:?}");
    CommandText::parse(&out.remove(0).unwrap()).unwrap()
}

#[test]
fn section_7_2_read_sample() {
    // SND$ = ":000000010400000200" + CR: read 2 bytes of M from relative address 0.
    let r = Request::read_words(Module::M, 0, 1).unwrap();
    assert_eq!(line(&r.encode(0).unwrap()), ":000000010400000200\r");
    // The reply; the program takes the status at MID$(RCV$, 4, 2) and the count value at
    // MID$(RCV$, 22, 4), read directly as four hex digits: 16-bit areas go high byte first.
    let reply = ":0000000107000002000112AB\r";
    assert_eq!(&reply[3..5], "00");
    assert_eq!(&reply[21..25], "12AB");
    let text = decode_line(reply);
    assert!(r.answered_by(&text));
    assert_eq!(
        r.parse_reply(0, &text),
        Ok(Reply::Read {
            module: Module::M,
            address: 0,
            data: vec![0x12, 0xAB],
            words: vec![0x12AB],
        })
    );
}

#[test]
fn section_7_4_transfer_from_the_plc_is_low_byte_first() {
    // The program rearranges MID$(RCV$, 14, 2) + MID$(RCV$, 12, 2): an SI word, low first.
    let received = ":900000010234 12\r".replace(' ', "");
    assert_eq!(&received[13..15], "12");
    assert_eq!(&received[11..13], "34");
    let text = decode_line(&received);
    let (message, data) = unsolicited_transfer(&text).unwrap();
    assert_eq!(message, 1);
    assert_eq!(decode_words(Attribute::Si, &data), vec![0x1234]);
    // A reply to a request is not a transfer.
    let reply = decode_line(":0000000107000002000112AB\r");
    assert_eq!(unsolicited_transfer(&reply), None);
}

#[test]
fn section_7_5_transfer_to_the_plc() {
    // Timer 10, set value "12345678" rearranged to "78563412", message module 02, BYTEN 08.
    let mut data = vec![10, 0, 0, 0];
    data.extend(encode_words(Module::file(32, FileType::Di).unwrap(), &[0x1234_5678]).unwrap());
    let r = Request::Transfer { message: 2, data };
    assert_eq!(line(&r.encode(0).unwrap()), ":90000002080A00000078563412\r");
    // The answer: STA at MID$(RCV$, 4, 2).
    let reply = ":9000000200\r";
    assert_eq!(&reply[3..5], "00");
    let text = decode_line(reply);
    assert_eq!(
        r.parse_reply(0, &text),
        Ok(Reply::Transferred { message: 2 })
    );
}

#[test]
fn write_and_clear_texts() {
    let r = Request::write_words(Module::D, 0x10, &[0x1234, 0xBEEF]).unwrap();
    let text = r.encode(0).unwrap();
    assert_eq!(
        text,
        [
            0x01, 0x00, 0x00, 0x05, 0x08, 0x10, 0x00, 0x04, 0x00, 0x12, 0x34, 0xBE, 0xEF
        ]
    );
    let reply =
        CommandText::parse(&[0x01, 0x00, 0x00, 0x05, 0x04, 0x10, 0x00, 0x04, 0x00]).unwrap();
    assert_eq!(
        r.parse_reply(0, &reply),
        Ok(Reply::Written {
            module: Module::D,
            address: 0x10,
            bytes: 4
        })
    );
    let c = Request::Clear { module: Module::BD };
    assert_eq!(c.encode(7).unwrap(), [0x01, 0x07, 0x05, 0x0E, 0x00]);
    let reply = CommandText::parse(&[0x01, 0x00, 0x85, 0x0E, 0x00]).unwrap();
    assert!(c.answered_by(&reply), "the multi-drop MODE bit is accepted");
    assert_eq!(
        c.parse_reply(7, &reply),
        Ok(Reply::Cleared { module: Module::BD })
    );
    // RSNO is BCD: station 42 is 42h.
    let r = Request::read_words(Module::D, 0, 1).unwrap();
    assert_eq!(r.encode(42).unwrap()[1], 0x42);
    assert_eq!(r.encode(100), Err(CommandError::Station { station: 100 }));
}

#[test]
fn every_sta_code_is_a_typed_error_that_says_what_it_means() {
    let r = Request::write_words(Module::D, 3, &[1]).unwrap();
    let cases = [
        (0x12, Sta::MemoryWrite, "program area"),
        (0x20, Sta::UndefinedCommand, "undefined command"),
        (0x21, Sta::Parameter, "parameter error"),
        (
            0x22,
            Sta::Interlock,
            "module in interlock: only the loader may",
        ),
        (0x24, Sta::ModuleNumber, "no such module"),
        (0x32, Sta::OverMemorySize, "beyond the module"),
        (0xA7, Sta::Transfer, "transfer command error"),
        (0x99, Sta::Other(0x99), "does not list"),
    ];
    for (code, sta, words) in cases {
        let reply = CommandText::parse(&[0x01, code, 0x00, 0x05, 0x00]).unwrap();
        let Err(ReplyError::Sta(e)) = r.parse_reply(4, &reply) else {
            panic!("STA {code:02X} not an error");
        };
        assert_eq!(e.sta, sta);
        assert_eq!(e.sta.code(), code);
        assert_eq!((e.station, e.module, e.address), (4, 0x05, Some(3)));
        let msg = e.to_string();
        assert!(msg.contains(words), "{msg}");
        assert!(
            msg.contains(&format!("(STA {code:02X}, FFU120B §5-3-5)")),
            "{msg}"
        );
        assert!(
            msg.contains("station 04") && msg.contains("module D (05h)"),
            "{msg}"
        );
    }
    let e = Sta::from_code(0x22).unwrap().to_string();
    assert_eq!(
        e,
        "module in interlock: only the loader may read or write now (STA 22, FFU120B §5-3-5)"
    );
    assert_eq!(Sta::from_code(0), None);
}

#[test]
fn requests_the_module_would_refuse_are_refused_first() {
    // Odd byte count for a 16-bit area; not whole 32-bit words.
    let r = Request::Read {
        module: Module::D,
        address: 0,
        bytes: 3,
    };
    assert!(matches!(
        r.check(),
        Err(CommandError::ByteCount {
            word_bytes: 2,
            bytes: 3,
            ..
        })
    ));
    let r = Request::Write {
        module: Module::TS,
        address: 0,
        data: vec![0; 6],
    };
    assert!(matches!(
        r.check(),
        Err(CommandError::ByteCount { word_bytes: 4, .. })
    ));
    // Limits: read 212, write 220, transfer 220.
    assert!(Request::read_words(Module::D, 0, 106).is_ok());
    assert!(matches!(
        Request::read_words(Module::D, 0, 107),
        Err(CommandError::TooMany { max: 212, .. })
    ));
    assert!(Request::write_words(Module::D, 0, &[0; 110]).is_ok());
    assert!(matches!(
        Request::write_words(Module::D, 0, &[0; 111]),
        Err(CommandError::TooMany { max: 220, .. })
    ));
    assert!(matches!(
        Request::Transfer {
            message: 1,
            data: vec![0; 221]
        }
        .check(),
        Err(CommandError::TooMany { max: 220, .. })
    ));
    assert!(matches!(
        Request::read_words(Module::D, 0, 0),
        Err(CommandError::Empty { .. })
    ));
    assert!(matches!(
        Request::read_words(Module::D, 65535, 2),
        Err(CommandError::AddressRange { .. })
    ));
    assert!(matches!(
        Request::write_words(Module::D, 0, &[0x1_0000]),
        Err(CommandError::ValueTooWide { bits: 16, .. })
    ));
    // Modules the table lacks.
    for name in ["X", "W25", "W110", "W29", "W30:XX", "D:DI", ""] {
        let e = name.parse::<Module>().unwrap_err();
        assert!(e.to_string().contains("FFU120B §5-3-3"), "{e}");
    }
    let msg = Request::Read {
        module: Module::D,
        address: 0,
        bytes: 3,
    }
    .check()
    .unwrap_err()
    .to_string();
    assert!(msg.contains("STA 21"), "{msg}");
}

#[test]
fn module_table_by_name() {
    let table = [
        ("B", 0x00, 16, 1),
        ("M", 0x01, 16, 1),
        ("K", 0x02, 16, 1),
        ("F", 0x03, 16, 1),
        ("A", 0x04, 16, 1),
        ("D", 0x05, 16, 1),
        ("W9", 0x09, 32, 2),
        ("TS", 0x0A, 32, 2),
        ("TR", 0x0B, 32, 2),
        ("CS", 0x0C, 32, 2),
        ("CR", 0x0D, 32, 2),
        ("BD", 0x0E, 32, 2),
        ("WL", 0x14, 16, 1),
        ("W21", 0x15, 16, 1),
        ("W22", 0x16, 16, 1),
        ("W23", 0x17, 16, 1),
        ("W24", 0x18, 16, 1),
        ("W30", 0x1E, 16, 3),
        ("W31:DI", 0x1F, 32, 4),
        ("W32:BD", 0x20, 32, 2),
        ("W109", 0x6D, 16, 3),
        ("W120", 0x78, 16, 1),
        ("W121", 0x79, 16, 1),
        ("W122", 0x7A, 16, 1),
        ("W123", 0x7B, 16, 1),
    ];
    for (name, number, bits, attr) in table {
        let m = Module::by_name(name).unwrap_or_else(|| panic!("{name}"));
        assert_eq!(m.number(), number, "{name}");
        assert_eq!(m.word_bytes() * 8, bits, "{name}");
        assert_eq!(m.attribute().code(), attr, "{name}");
        assert_eq!(m.to_string(), name);
        assert_eq!(Module::from_number(number, Some(m.attribute())), Some(m));
    }
    assert_eq!(Module::by_name("w31:di"), Module::file(31, FileType::Di));
    assert_eq!(Module::fixed_table().count(), 21);
    assert!(Module::by_name("WL").unwrap().needs_p_link());
    assert!(Module::by_name("W123").unwrap().needs_p_link());
    assert!(!Module::W24.needs_p_link());
    // Modules serialise as their symbol.
    #[derive(serde::Deserialize, serde::Serialize)]
    struct W {
        m: Module,
    }
    let w: W = toml::from_str("m = \"W40:DI\"").unwrap();
    assert_eq!(w.m, Module::file(40, FileType::Di).unwrap());
    assert_eq!(toml::to_string(&w).unwrap().trim(), "m = \"W40:DI\"");
    assert!(toml::from_str::<W>("m = \"Q\"").is_err());
}

#[test]
fn byte_order_per_attribute() {
    // 16-bit areas: high byte first; SI: low first; 32-bit BCD and DI: low first (§5-3-6).
    let d = encode_words(Module::D, &[0x1234]).unwrap();
    assert_eq!(d, [0x12, 0x34]);
    let si = Module::file(30, FileType::Si).unwrap();
    assert_eq!(
        encode_words(si, &[0x1234, 0x5678]).unwrap(),
        [0x34, 0x12, 0x78, 0x56]
    );
    assert_eq!(
        encode_words(Module::TS, &[0x7856_3412]).unwrap(),
        [0x12, 0x34, 0x56, 0x78]
    );
    let di = Module::file(31, FileType::Di).unwrap();
    assert_eq!(
        decode_words(di.attribute(), &[0x12, 0x34, 0x56, 0x78]),
        [0x7856_3412]
    );
    for m in [Module::D, si, Module::TS, di] {
        let values: Vec<u32> = if m.word_bytes() == 2 {
            vec![0, 1, 0xFFFF, 0x8001]
        } else {
            vec![0, 1, u32::MAX, 0x8000_0001]
        };
        let bytes = encode_words(m, &values).unwrap();
        assert_eq!(bytes.len(), values.len() * m.word_bytes());
        assert_eq!(decode_words(m.attribute(), &bytes), values, "{m}");
    }
    // A trailing partial word is dropped, not read past.
    assert_eq!(
        decode_words(Attribute::Bcd32, &[1, 2, 3]),
        Vec::<u32>::new()
    );
}

#[test]
fn bcd_helpers() {
    assert_eq!(to_bcd(0), Some(0x00));
    assert_eq!(to_bcd(99), Some(0x99));
    assert_eq!(to_bcd(100), None);
    assert_eq!(from_bcd(0x42), Some(42));
    assert_eq!(from_bcd(0x4A), None);
    for v in 0..=99 {
        assert_eq!(from_bcd(to_bcd(v).unwrap()), Some(v));
    }
    assert_eq!(to_bcd8(12_345_678), Some(0x1234_5678));
    assert_eq!(from_bcd8(0x1234_5678), Some(12_345_678));
    assert_eq!(to_bcd8(100_000_000), None);
    assert_eq!(from_bcd8(0x0000_00A0), None);
    assert_eq!(from_bcd8(to_bcd8(99_999_999).unwrap()), Some(99_999_999));
}

#[test]
fn malformed_and_foreign_replies() {
    let r = Request::read_words(Module::D, 8, 2).unwrap();
    // Another module's reply does not answer this request.
    let other = CommandText::parse(&[0x00, 0x00, 0x00, 0x01, 0x00]).unwrap();
    assert!(!r.answered_by(&other));
    // Wrong attribute, short body, wrong echo.
    let bad_attr = CommandText::parse(&[0, 0, 0, 5, 9, 8, 0, 4, 0, 2, 1, 2, 3, 4]).unwrap();
    assert!(matches!(
        r.parse_reply(0, &bad_attr),
        Err(ReplyError::Malformed {
            problem: Malformed::Attribute { want: 1, got: 2 },
            ..
        })
    ));
    let short = CommandText::parse(&[0, 0, 0, 5, 7, 8, 0, 4, 0, 1, 1, 2]).unwrap();
    assert!(matches!(
        r.parse_reply(0, &short),
        Err(ReplyError::Malformed {
            problem: Malformed::Body { .. },
            ..
        })
    ));
    let echo = CommandText::parse(&[0, 0, 0, 5, 9, 9, 0, 4, 0, 1, 1, 2, 3, 4]).unwrap();
    let e = r.parse_reply(3, &echo).unwrap_err();
    assert!(
        e.to_string()
            .contains("relative address 9 echoed, 8 requested"),
        "{e}"
    );
    // BYTEN that does not count the body: text form unidentified (§5-6).
    assert_eq!(
        CommandText::parse(&[0, 0, 0, 5, 3, 1]),
        Err(TextForm::Byten {
            byten: 3,
            actual: 1
        })
    );
    assert!(CommandText::parse(&[0, 0, 0]).is_err());
}

#[test]
fn an_sta_error_names_a_message_for_a_transfer_and_a_module_otherwise() {
    let transfer = StaError {
        sta: Sta::Transfer,
        station: 0,
        cmnd: CMND_TRANSFER,
        mode: MODE_ADDRESS,
        module: 5,
        address: None,
    }
    .to_string();
    assert!(transfer.contains("STA A7"), "{transfer}");
    assert!(transfer.contains("message 5"), "{transfer}");
    assert!(!transfer.contains("module D"), "{transfer}");
    let read = StaError {
        sta: Sta::OverMemorySize,
        station: 2,
        cmnd: CMND_READ,
        mode: MODE_ADDRESS,
        module: 5,
        address: Some(65000),
    }
    .to_string();
    assert!(read.contains("module D (05h), address 65000"), "{read}");
}
