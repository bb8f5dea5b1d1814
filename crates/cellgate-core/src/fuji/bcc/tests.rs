use super::*;

fn bcc(kind: BccKind, calc: BccCalc, code: BccCode) -> Bcc {
    Bcc {
        kind,
        calc,
        code,
        crc16: Crc16::Arc,
    }
}

/// The appendix example: `:000000010400000200` CR, add, start+text+end → AEh.
const APPENDIX: &[u8] = b":000000010400000200\r";

#[test]
fn appendix_example_add_set1_set2_binary() {
    let add = |kind, code| bcc(kind, BccCalc::Add, code).encode(APPENDIX);
    assert_eq!(sum8(APPENDIX), 0xAE);
    assert_eq!(
        add(BccKind::Set1, BccCode::TransmissionCode).as_slice(),
        &[0x41, 0x45]
    );
    assert_eq!(
        add(BccKind::Set2, BccCode::TransmissionCode).as_slice(),
        &[0x45, 0x41]
    );
    assert_eq!(add(BccKind::Set1, BccCode::Binary).as_slice(), &[0xAE]);
    assert_eq!(add(BccKind::Set2, BccCode::Binary).as_slice(), &[0xAE]);
}

#[test]
fn calculations_on_known_values() {
    let b = |calc| bcc(BccKind::Set1, calc, BccCode::Binary);
    assert_eq!(b(BccCalc::Add).value(APPENDIX), 0xAE);
    assert_eq!(b(BccCalc::AddInvert).value(APPENDIX), 0x51);
    assert_eq!(
        b(BccCalc::Eor).value(&[0x3A, 0x30, 0x31]),
        0x3A ^ 0x30 ^ 0x31
    );
    // Standard check values of the CRCs on 8005h.
    assert_eq!(Crc16::Arc.checksum(b"123456789"), 0xBB3D);
    assert_eq!(Crc16::Buypass.checksum(b"123456789"), 0xFEE8);
    assert_eq!(Crc16::Modbus.checksum(b"123456789"), 0x4B37);
    assert_eq!(Crc16::Arc.checksum(b""), 0);
}

#[test]
fn crc_byte_order_and_length() {
    let set1 = bcc(BccKind::Set1, BccCalc::Crc16, BccCode::Binary);
    let set2 = bcc(BccKind::Set2, BccCalc::Crc16, BccCode::Binary);
    assert_eq!(set1.encode(b"123456789").as_slice(), &[0xBB, 0x3D]);
    assert_eq!(set2.encode(b"123456789").as_slice(), &[0x3D, 0xBB]);
    assert_eq!((set1.len(), set2.len()), (2, 2));
    // CRC in transmission code is initial error F3; if asked for it is four characters.
    let tc = bcc(BccKind::Set1, BccCalc::Crc16, BccCode::TransmissionCode);
    assert_eq!(tc.encode(b"123456789").as_slice(), b"BB3D");
    let tc2 = bcc(BccKind::Set2, BccCalc::Crc16, BccCode::TransmissionCode);
    assert_eq!(tc2.encode(b"123456789").as_slice(), b"3DBB");
    assert_eq!(tc.len(), 4);
}

#[test]
fn every_kind_encodes_then_verifies_and_catches_a_flip() {
    let kinds = [BccKind::Set1, BccKind::Set2];
    let calcs = [
        BccCalc::Add,
        BccCalc::AddInvert,
        BccCalc::Eor,
        BccCalc::Crc16,
    ];
    let codes = [BccCode::TransmissionCode, BccCode::Binary];
    let crcs = [Crc16::Arc, Crc16::Buypass, Crc16::Modbus];
    for kind in kinds {
        for calc in calcs {
            for code in codes {
                for crc16 in crcs {
                    let b = Bcc {
                        kind,
                        calc,
                        code,
                        crc16,
                    };
                    let enc = b.encode(APPENDIX);
                    assert_eq!(enc.as_slice().len(), b.len(), "{b:?}");
                    assert_eq!(b.verify(APPENDIX, enc.as_slice()), Ok(()), "{b:?}");
                    let mut bad = enc.as_slice().to_vec();
                    bad[0] ^= 0x01;
                    assert!(b.verify(APPENDIX, &bad).is_err(), "{b:?}");
                    // A changed byte in the range changes every calculation's result.
                    let mut other = APPENDIX.to_vec();
                    other[3] ^= 0x04;
                    assert!(b.verify(&other, enc.as_slice()).is_err(), "{b:?}");
                    if code == BccCode::TransmissionCode {
                        assert!(enc.as_slice().iter().all(|c| hex_value(*c).is_some()));
                    }
                }
            }
        }
    }
}

#[test]
fn no_bcc_is_empty() {
    let b = bcc(BccKind::None, BccCalc::Crc16, BccCode::Binary);
    assert!(b.is_empty());
    assert_eq!(b.encode(APPENDIX).as_slice(), b"");
    assert_eq!(b.verify(APPENDIX, b""), Ok(()));
}

#[test]
fn hex_helpers_are_upper_case_only() {
    assert_eq!(hex2(0xAE), *b"AE");
    assert_eq!(parse_hex2(b'A', b'E'), Some(0xAE));
    assert_eq!(parse_hex2(b'a', b'e'), None);
    assert_eq!(parse_hex2(b'G', b'0'), None);
}

#[test]
fn serde_spellings() {
    #[derive(Deserialize)]
    struct W {
        calc: BccCalc,
        kind: BccKind,
        code: BccCode,
        crc: Crc16,
    }
    let w: W =
        toml::from_str("calc = \"crc-16\"\nkind = \"set2\"\ncode = \"binary\"\ncrc = \"modbus\"")
            .unwrap();
    assert_eq!(
        (w.calc, w.kind, w.code, w.crc),
        (
            BccCalc::Crc16,
            BccKind::Set2,
            BccCode::Binary,
            Crc16::Modbus
        )
    );
    let w: W = toml::from_str(
        "calc = \"add-invert\"\nkind = \"none\"\ncode = \"transmission-code\"\ncrc = \"arc\"",
    )
    .unwrap();
    assert_eq!(w.calc, BccCalc::AddInvert);
}
