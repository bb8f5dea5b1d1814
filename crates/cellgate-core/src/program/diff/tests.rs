use super::*;

const A: &[u8] = b"%\nO1234 (FLANGE)\nN10 G00 X0 Y0\nN20 G01 X10 F100\nN30 M30\n%\n";

fn opts(list: &str) -> DiffOptions {
    DiffOptions::parse(list).unwrap()
}

#[test]
fn the_same_program_is_the_same() {
    let c = counts(A, A, DiffOptions::default()).unwrap();
    assert!(c.same(), "{c:?}");
    let (c, hunks) = diff(A, A, DiffOptions::default(), 3).unwrap();
    assert!(c.same());
    assert!(hunks.is_empty());
}

#[test]
fn a_changed_block_is_one_changed_not_one_removed_and_one_added() {
    let b = b"%\nO1234 (FLANGE)\nN10 G00 X0 Y0\nN20 G01 X12 F100\nN30 M30\n%\n";
    let (c, hunks) = diff(A, b, DiffOptions::default(), 1).unwrap();
    assert_eq!(
        c,
        DiffCounts {
            added: 0,
            removed: 0,
            changed: 1
        }
    );
    assert_eq!(hunks.len(), 1);
    let h = &hunks[0];
    let ops: Vec<(i32, &str, bool)> = h
        .lines
        .iter()
        .map(|l| (l.op, l.text.as_str(), l.changed))
        .collect();
    use pb::diff_line::Op;
    assert_eq!(
        ops,
        [
            (Op::Equal as i32, "N10 G00 X0 Y0", false),
            (Op::Removed as i32, "N20 G01 X10 F100", true),
            (Op::Added as i32, "N20 G01 X12 F100", true),
            (Op::Equal as i32, "N30 M30", false),
        ]
    );
    // Line numbers are the programs' own: `%` is line 1.
    assert_eq!((h.a_line, h.b_line), (3, 3));
    assert_eq!(h.lines[1].a_line, 4);
    assert_eq!(h.lines[2].b_line, 4);
}

#[test]
fn added_and_removed_blocks_are_counted_apart() {
    let b = b"%\nO1234 (FLANGE)\nN10 G00 X0 Y0\nN15 G04 P500\nN20 G01 X10 F100\n%\n";
    let c = counts(A, b, DiffOptions::default()).unwrap();
    // N15 added, N30 removed: the aligner pairs nothing, so one added, one removed.
    assert_eq!(
        c,
        DiffCounts {
            added: 1,
            removed: 1,
            changed: 0
        },
        "{c:?}"
    );
}

#[test]
fn renumbered_blocks_differ_unless_sequence_numbers_are_ignored() {
    let b = b"%\nO1234 (FLANGE)\nN100 G00 X0 Y0\nN200 G01 X10 F100\nN300 M30\n%\n";
    assert_eq!(counts(A, b, DiffOptions::default()).unwrap().changed, 3);
    assert!(counts(A, b, opts("sequence")).unwrap().same());
    // Only the number at the start of a block is a sequence number.
    let c = b"%\nO1234 (FLANGE)\nN10 G00 X0 Y0\nN20 G01 X10 F100 N5\nN30 M30\n%\n";
    assert_eq!(counts(A, c, opts("sequence")).unwrap().changed, 1);
    // A block delete stays: `/N10 X1` is not `N10 X1`.
    assert_eq!(strip_sequence("/N10 X1"), "/ X1");
    assert_eq!(strip_sequence("  N0010G00"), "  G00");
    assert_eq!(strip_sequence("NX1"), "NX1");
}

#[test]
fn blanks_and_comments_are_ignored_when_asked() {
    let b = b"%\nO1234(FLANGE REV B)\nN10G00X0Y0\n(ROUGHING)\nN20G01X10F100\nN30M30\n%\n";
    let plain = counts(A, b, DiffOptions::default()).unwrap();
    assert!(!plain.same());
    let blanks = counts(A, b, opts("blanks")).unwrap();
    assert!(!blanks.same(), "the comments still differ: {blanks:?}");
    assert!(counts(A, b, opts("blanks,comments")).unwrap().same());
    // An unclosed comment runs to the end of the block.
    assert_eq!(normalise("G00 (OPEN", opts("comments")), "G00 ");
}

#[test]
fn line_endings_do_not_make_blocks_differ() {
    let crlf = b"%\r\nO1234 (FLANGE)\r\nN10 G00 X0 Y0\r\nN20 G01 X10 F100\r\nN30 M30\r\n%\r\n";
    assert!(counts(A, crlf, DiffOptions::default()).unwrap().same());
    let cr = b"%\rO1234 (FLANGE)\rN10 G00 X0 Y0\rN20 G01 X10 F100\rN30 M30\r%";
    assert!(counts(A, cr, DiffOptions::default()).unwrap().same());
}

#[test]
fn a_program_that_is_not_text_is_refused_naming_the_byte() {
    let e = counts(A, b"%\nO1\x00\n%\n", DiffOptions::default()).unwrap_err();
    assert_eq!(
        e,
        NotText {
            which: "b",
            offset: 4,
            byte: 0
        }
    );
    assert!(e.to_string().contains("byte 4"), "{e}");
    let e = counts(b"\xa5O1\n", A, DiffOptions::default()).unwrap_err();
    assert_eq!(e.which, "a");
}

#[test]
fn empty_programs_compare() {
    assert!(counts(b"", b"", DiffOptions::default()).unwrap().same());
    let c = counts(b"", A, DiffOptions::default()).unwrap();
    assert_eq!(c.added, 6);
    let (_, hunks) = diff(A, b"", DiffOptions::default(), 3).unwrap();
    assert_eq!(hunks.len(), 1);
    assert_eq!(hunks[0].lines.len(), 6);
}

#[test]
fn options_parse_and_name_themselves() {
    assert_eq!(opts(""), DiffOptions::default());
    let o = opts("comments, sequence");
    assert_eq!(o.names(), ["sequence", "comments"]);
    let e = DiffOptions::parse("sequence,spaces").unwrap_err();
    assert!(e.to_string().contains("\"spaces\""), "{e}");
}

#[test]
fn hunks_keep_their_context_and_split_far_changes() {
    let mut a = String::from("%\n");
    let mut b = String::from("%\n");
    for i in 1..=40 {
        a.push_str(&format!("N{i} X{i}\n"));
        let x = if i == 5 || i == 35 { i + 1000 } else { i };
        b.push_str(&format!("N{i} X{x}\n"));
    }
    let (c, hunks) = diff(a.as_bytes(), b.as_bytes(), DiffOptions::default(), 3).unwrap();
    assert_eq!(c.changed, 2);
    assert_eq!(hunks.len(), 2, "two changes 30 blocks apart are two hunks");
    // 3 before, the pair, 3 after.
    assert_eq!(hunks[0].lines.len(), 8);
}
