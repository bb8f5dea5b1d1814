use super::*;

const PROGRAM: &[u8] = b"%\nO1234 (BRACKET)\nG90 G54\n N10 G01 X1\nN20 X2\nN30X3\nM30\n%";

#[test]
fn the_block_holding_an_offset() {
    let at = |o| block_at(PROGRAM, o);
    let b = at(0).unwrap();
    assert_eq!((b.line, b.sequence.as_deref(), b.offset), (1, None, 0));
    // The first byte of line 4, and one in its middle: the same block.
    let start4 = PROGRAM.windows(4).position(|w| w == b" N10").unwrap() as u64;
    for o in [start4, start4 + 5] {
        let b = at(o).unwrap();
        assert_eq!(
            (b.line, b.sequence.as_deref(), b.offset),
            (4, Some("N10"), start4)
        );
    }
    let start6 = PROGRAM.windows(3).position(|w| w == b"N30").unwrap() as u64;
    let b = at(start6).unwrap();
    assert_eq!((b.line, b.sequence.as_deref()), (6, Some("N30")));
    let b = at(PROGRAM.len() as u64 - 1).unwrap();
    assert_eq!((b.line, b.sequence), (8, None));
    assert_eq!(at(PROGRAM.len() as u64), None);
}

#[test]
fn starts_by_sequence_number_or_line_with_the_header_before() {
    let header = b"%\nO1234 (BRACKET)\nG90 G54\n".len() as u64;
    let (h, b) = find_start(PROGRAM, StartAt::Sequence(20), 0).unwrap();
    assert_eq!((h, b.line, b.sequence.as_deref()), (header, 5, Some("N20")));
    let (h, b) = find_start(PROGRAM, StartAt::Line(7), 0).unwrap();
    assert_eq!((h, b.line), (header, 7));
    // A header of two lines.
    let (h, _) = find_start(PROGRAM, StartAt::Line(6), 2).unwrap();
    assert_eq!(h, b"%\nO1234 (BRACKET)\n".len() as u64);
    // A start inside the header: the header stops before it.
    let (h, b) = find_start(PROGRAM, StartAt::Line(2), 0).unwrap();
    assert_eq!((h, b.offset), (2, 2));
    // The EOR line, without LF.
    let (_, b) = find_start(PROGRAM, StartAt::Line(8), 0).unwrap();
    assert_eq!(b.offset, PROGRAM.len() as u64 - 1);
    assert_eq!(
        find_start(PROGRAM, StartAt::Sequence(99), 0),
        Err(BlockError::NoSequence(99))
    );
    assert_eq!(
        find_start(PROGRAM, StartAt::Line(50), 0),
        Err(BlockError::NoLine { line: 50, lines: 8 })
    );
    assert_eq!(
        find_start(PROGRAM, StartAt::Line(0), 0),
        Err(BlockError::LineZero)
    );
}

#[test]
fn a_sequence_number_is_found_by_its_value_whatever_its_leading_zeros() {
    let program = b"%\nO1\nN0010 G01 X1\nN0020 X2\nM30\n%";
    let (_, b) = find_start(program, StartAt::Sequence(10), 0).unwrap();
    assert_eq!((b.line, b.sequence.as_deref()), (3, Some("N0010")));
    let (_, b) = find_start(program, StartAt::Sequence(20), 0).unwrap();
    assert_eq!(b.line, 4);
    assert_eq!(
        find_start(program, StartAt::Sequence(1), 0),
        Err(BlockError::NoSequence(1))
    );
}

#[test]
fn pieces_find_what_the_whole_finds() {
    for split in 1..PROGRAM.len() {
        let (a, b) = PROGRAM.split_at(split);
        let mut search = StartSearch::new(StartAt::Sequence(30), 0).unwrap();
        let found = search.feed(a).or_else(|| search.feed(b));
        assert_eq!(found, find_start(PROGRAM, StartAt::Sequence(30), 0).ok());
        let mut at = BlockAt::new(20);
        let block = at.feed(a).or_else(|| at.feed(b)).or_else(|| at.finish());
        assert_eq!(block, block_at(PROGRAM, 20), "split at {split}");
    }
}
