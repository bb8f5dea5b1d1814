use super::*;

fn all(p: &mut Program) -> Vec<u8> {
    p.take(usize::MAX)
}

/// The byte-at-a-time scan `push` replaced with runs: what it accepts, drops and fails on.
fn reference(data: &[u8], forbidden: Option<u8>) -> (Vec<u8>, u64, Result<(), u64>, bool) {
    let (mut buf, mut ignored, mut scan) = (Vec::new(), 0, Scan::Leader);
    for &b in data {
        if scan == Scan::Ended {
            ignored += 1;
            continue;
        }
        if forbidden == Some(b) {
            let offset = buf.len() as u64;
            return (buf, ignored, Err(offset), false);
        }
        buf.push(b);
        scan = match scan {
            Scan::Leader if is_eor(b) || is_significant(b) => Scan::Body,
            Scan::Body if is_eor(b) => Scan::Ended,
            s => s,
        };
    }
    (buf, ignored, Ok(()), scan == Scan::Ended)
}

#[test]
fn runs_take_in_what_the_byte_scan_would() {
    let alphabet = [b'%', 0xA5, b'X', b'\n', b' ', 0x0D, 0x03];
    let mut seed = 0x9E37_79B9_7F4A_7C15u64;
    for case in 0..2000 {
        let len = case % 40;
        let data: Vec<u8> = (0..len)
            .map(|_| {
                seed ^= seed << 13;
                seed ^= seed >> 7;
                seed ^= seed << 17;
                alphabet[(seed % alphabet.len() as u64) as usize]
            })
            .collect();
        let forbidden = [None, Some(0x0D), Some(0x03)][case % 3];
        let (buf, ignored, result, ended) = reference(&data, forbidden);
        // Whole, and split in two at each of the first eight places.
        for split in [data.len()].into_iter().chain(0..data.len().min(8)) {
            let mut p = Program::new();
            let got = p
                .push(&data[..split], forbidden)
                .and_then(|()| p.push(&data[split..], forbidden));
            let got = got.map_err(|e| match e {
                ProgramSendError::EndCodeInData { offset, .. } => offset,
                other => panic!("{other:?}"),
            });
            assert_eq!(got, result, "{data:02x?} split at {split}");
            assert_eq!(p.complete(), ended, "{data:02x?}");
            if result.is_ok() {
                assert_eq!(p.ignored, ignored, "{data:02x?}");
            }
            assert_eq!(all(&mut p), buf, "{data:02x?} split at {split}");
        }
    }
}

#[test]
fn binary_bytes_are_not_scanned_for_eor() {
    let mut p = Program::new();
    p.push(b"%\nG05\n", None).unwrap();
    p.push_binary(b"\x25\x25\xA5\x00");
    assert!(!p.complete(), "a % inside binary data is no EOR");
    p.push(b"M30\n", None).unwrap();
    p.end().unwrap();
    assert_eq!(all(&mut p), b"%\nG05\n\x25\x25\xA5\x00M30\n%");
    // After EOR, binary bytes are dropped too.
    p.push_binary(b"\x01");
    assert_eq!(p.buffered(), 0);
}

#[test]
fn tape_start_mark_and_eor() {
    let mut p = Program::new();
    p.push(b"\0\0 \n%\nO0001\nG01X1;\n%\nM30 after EOR\n", None)
        .unwrap();
    assert!(p.complete());
    assert_eq!(all(&mut p), b"\0\0 \n%\nO0001\nG01X1;\n%");
    assert!(p.all_sent());
    assert_eq!(p.wanted(100), 0);
}

#[test]
fn program_without_tape_start_ends_at_first_percent() {
    let mut p = Program::new();
    p.push(b"O1\nX1%junk", None).unwrap();
    assert_eq!(all(&mut p), b"O1\nX1%");
}

#[test]
fn eor_appended_when_missing_with_the_tape_start_code() {
    let mut p = Program::new();
    p.push(&[0xA5, b'\n', b'O', b'1'], None).unwrap();
    assert!(!p.complete());
    p.end().unwrap();
    assert!(p.eor_appended);
    assert_eq!(all(&mut p), [0xA5, b'\n', b'O', b'1', 0xA5]);
    let mut empty = Program::new();
    empty.push(b"\n\n", None).unwrap();
    assert_eq!(empty.end(), Err(ProgramSendError::Empty));
}

#[test]
fn end_code_is_refused_with_its_offset() {
    let mut p = Program::new();
    assert_eq!(
        p.push(b"%\nO1\r\n", Some(0x0D)),
        Err(ProgramSendError::EndCodeInData {
            offset: 4,
            end: 0x0D
        })
    );
}

#[test]
fn split_input_and_bounded_wants() {
    let mut p = Program::new();
    p.push(b"%\nG0", None).unwrap();
    p.push(b"1\n", None).unwrap();
    assert_eq!(p.wanted(12), 6);
    assert_eq!(
        p.wanted(8),
        0,
        "more than half the limit is held: refilled later"
    );
    assert_eq!(p.take(2), b"%\n");
    assert_eq!(p.wanted(8), 4);
    assert!(p.can_fill(4));
    assert!(!p.can_fill(5));
    assert_eq!(p.take(3), b"G01");
    assert_eq!(p.sent, 5);
}

#[test]
fn split_input_is_buffered_whole() {
    let mut p = Program::new();
    p.push(b"%\nG0", None).unwrap();
    p.push(b"1\n", None).unwrap();
    assert!(p.can_fill(6));
    assert!(!p.can_fill(7));
    assert_eq!(p.take(3), b"%\nG");
    assert_eq!(p.sent, 3);
    p.push(b"%", None).unwrap();
    assert!(p.ends_within(4));
    assert!(p.can_fill(100));
    assert_eq!(p.find_in_next(10, b'%'), Some(6));
}

#[test]
fn take_front_copies_across_the_rings_wrap_and_stops_at_what_is_held() {
    let mut buf: VecDeque<u8> = VecDeque::with_capacity(8);
    buf.extend(b"abcdef");
    assert_eq!(take_front(&mut buf, 4), b"abcd");
    // Written past the end of the ring: the bytes now lie in two slices.
    buf.extend(b"ghijk");
    assert!(!buf.as_slices().1.is_empty(), "{:?}", buf.as_slices());
    assert_eq!(take_front(&mut buf, 5), b"efghi");
    assert_eq!(take_front(&mut buf, 10), b"jk");
    assert_eq!(take_front(&mut buf, 1), b"");
}
