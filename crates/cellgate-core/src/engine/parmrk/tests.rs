use super::*;

fn decode_all(d: &mut MarkDecoder) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let mut b = [0u8; 64];
        let n = d.decode(&mut b);
        if n == 0 {
            return out;
        }
        out.extend_from_slice(&b[..n]);
    }
}

#[test]
fn plain_bytes_pass() {
    let mut d = MarkDecoder::default();
    d.feed(&[0x11, 0x13, 0x0D, 0x00, 0x41]);
    assert_eq!(decode_all(&mut d), [0x11, 0x13, 0x0D, 0x00, 0x41]);
    assert!(d.errors.is_empty());
}

#[test]
fn doubled_ff_is_one_ff() {
    let mut d = MarkDecoder::default();
    d.feed(&[0x01, 0xFF, 0xFF, 0x02]);
    assert_eq!(decode_all(&mut d), [0x01, 0xFF, 0x02]);
}

#[test]
fn marked_character_is_dropped_and_reported_in_order() {
    let mut d = MarkDecoder::default();
    d.feed(&[b'A', 0xFF, 0x00, b'x', b'B', 0xFF, 0x00, 0x00, b'C']);
    let mut b = [0u8; 16];
    assert_eq!(d.decode(&mut b), 1, "a read stops before a mark");
    assert_eq!(&b[..1], b"A");
    assert!(d.errors.is_empty());
    assert_eq!(d.decode(&mut b), 1);
    assert_eq!(&b[..1], b"B");
    assert_eq!(d.errors.pop_front(), Some(LineError::Parity));
    assert_eq!(d.decode(&mut b), 1);
    assert_eq!(&b[..1], b"C");
    assert_eq!(d.errors.pop_front(), Some(LineError::Framing));
}

#[test]
fn marks_split_across_reads() {
    let mut d = MarkDecoder::default();
    d.feed(&[b'a', 0xFF]);
    assert_eq!(decode_all(&mut d), b"a");
    d.feed(&[0x00]);
    assert_eq!(decode_all(&mut d), b"");
    d.feed(&[b'z', b'b', 0xFF]);
    assert_eq!(decode_all(&mut d), b"b");
    assert_eq!(d.errors.pop_front(), Some(LineError::Parity));
    d.feed(&[0xFF]);
    assert_eq!(decode_all(&mut d), [0xFF]);
}

#[test]
fn incomplete_mark_at_end_of_input_is_data() {
    let mut d = MarkDecoder::default();
    d.feed(&[0xFF]);
    assert_eq!(decode_all(&mut d), b"");
    let mut b = [0u8; 4];
    assert_eq!(d.finish(&mut b), 1);
    assert_eq!(b[0], 0xFF);
}

#[test]
fn full_output_keeps_the_rest() {
    let mut d = MarkDecoder::default();
    d.feed(&[1, 2, 3, 0xFF, 0xFF]);
    let mut b = [0u8; 2];
    assert_eq!(d.decode(&mut b), 2);
    assert_eq!(decode_all(&mut d), [3, 0xFF]);
}
