//! A program checked in arbitrary pieces gives the same answer as checked whole, never
//! panics, and the blocks of any program are found without panicking.
#![no_main]

use cellgate_core::fanuc::{EndCode, Protocol};
use cellgate_core::program::blocks::{StartAt, block_at, find_start};
use cellgate_core::program::scan::{ProgramRules, Scanner, scan};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&sel, rest)) = data.split_first() else {
        return;
    };
    let rules = ProgramRules {
        protocol: match sel & 3 {
            0 => Protocol::A,
            1 => Protocol::ExpansionA,
            2 => Protocol::B,
            _ => Protocol::ExpansionB,
        },
        end_code: if sel & 4 == 0 {
            EndCode::Cr
        } else {
            EndCode::Etx
        },
        max_size: 1 + u64::from(sel >> 3) * 64,
    };
    let whole = scan(rules, rest);
    let mut scanner = Scanner::new(rules);
    let mut pieces = rest;
    let mut piece_result = Ok(());
    let mut cut = usize::from(sel % 7) + 1;
    while !pieces.is_empty() && piece_result.is_ok() {
        let (head, tail) = pieces.split_at(cut.min(pieces.len()));
        piece_result = scanner.feed(head);
        pieces = tail;
        cut = cut * 3 % 11 + 1;
    }
    let by_pieces = piece_result.and_then(|()| scanner.finish());
    assert_eq!(
        whole.is_ok(),
        by_pieces.is_ok(),
        "{whole:?} / {by_pieces:?}"
    );
    if let (Ok(a), Ok(b)) = (&whole, &by_pieces) {
        assert_eq!(a.size, b.size);
        assert_eq!(a.has_eor, b.has_eor);
    }
    let offset = u64::from(sel) * 3;
    let block = block_at(rest, offset);
    if let Some(b) = block {
        assert!(b.offset <= offset && usize::try_from(b.offset).unwrap() <= rest.len());
    }
    let at = if sel & 1 == 0 {
        StartAt::Line(u64::from(sel >> 1))
    } else {
        StartAt::Sequence(u64::from(sel))
    };
    if let Ok((header, start)) = find_start(rest, at, u32::from(sel % 4)) {
        assert!(header <= start.offset);
        assert!(usize::try_from(start.offset).unwrap() <= rest.len());
    }
});
