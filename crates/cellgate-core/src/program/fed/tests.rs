use super::*;

const PROGRAM: &[u8] = b"%\nO1234 (SQUARE)\nN10 G21 G90\n\nN20 G00 X0 Y0\nN30 M30\n%";

fn at(fed: &mut FedBlocks, acked: u64) -> Option<String> {
    fed.acked(acked).map(|s| s.to_string())
}

#[test]
fn the_last_whole_block_acknowledged_is_named() {
    let mut fed = FedBlocks::new();
    fed.push(PROGRAM);
    assert_eq!(at(&mut fed, 0), None);
    // The tape mark is no block; a block half acknowledged is not fed yet.
    assert_eq!(at(&mut fed, 2), None);
    assert_eq!(at(&mut fed, 10), None);
    assert_eq!(at(&mut fed, 17).as_deref(), Some("O1234 (SQUARE)"));
    // An empty line leaves the last block as it was.
    assert_eq!(at(&mut fed, 30).as_deref(), Some("N10 G21 G90"));
    assert_eq!(at(&mut fed, 29).as_deref(), Some("N10 G21 G90"));
    assert_eq!(
        at(&mut fed, PROGRAM.len() as u64).as_deref(),
        Some("N30 M30"),
        "the EOR % is no block"
    );
}

#[test]
fn bytes_come_in_pieces_and_questions_skip_lines() {
    // Byte by byte, asked at every offset, and in one question at the end: the same blocks.
    let mut each = FedBlocks::new();
    let mut seen = Vec::new();
    for (i, b) in PROGRAM.iter().enumerate() {
        each.push(&[*b]);
        if let Some(t) = at(&mut each, i as u64 + 1)
            && seen.last() != Some(&t)
        {
            seen.push(t);
        }
    }
    assert_eq!(
        seen,
        ["O1234 (SQUARE)", "N10 G21 G90", "N20 G00 X0 Y0", "N30 M30"]
    );
    // A line across two questions is read whole; several lines in one, the last counts.
    let mut fed = FedBlocks::new();
    fed.push(&PROGRAM[..20]);
    assert_eq!(at(&mut fed, 20).as_deref(), Some("O1234 (SQUARE)"));
    fed.push(&PROGRAM[20..]);
    assert_eq!(at(&mut fed, 29).as_deref(), Some("N10 G21 G90"));
    // Asking past what was handed over reads what there is.
    assert_eq!(at(&mut fed, 1_000).as_deref(), Some("N30 M30"));
}

#[test]
fn a_long_block_is_cut_and_memory_stays_bounded() {
    let mut fed = FedBlocks::new();
    let long = format!("N10 ({})\n", "X".repeat(10_000));
    // A line longer than the text kept, acknowledged in small steps.
    fed.push(long.as_bytes());
    for n in (0..long.len() as u64).step_by(100) {
        fed.acked(n);
        assert!(fed.head.len() <= MAX_BLOCK_TEXT);
    }
    let t = fed.acked(long.len() as u64).unwrap();
    assert_eq!(t.chars().count(), MAX_BLOCK_TEXT);
    assert!(t.starts_with("N10 (XXX"));
    assert!(fed.window.is_empty());
    // CR LF line ends and blanks are trimmed; bytes that are not UTF-8 do not stop it.
    fed.push(b"  N20 G01 X1.\r\nN30 \xff\n");
    assert_eq!(
        fed.acked(long.len() as u64 + 15).as_deref(),
        Some("N20 G01 X1.")
    );
    assert_eq!(
        fed.acked(long.len() as u64 + 21).as_deref(),
        Some("N30 \u{fffd}")
    );
}

#[test]
fn a_run_asked_about_only_at_its_end_keeps_only_the_last_bytes_sent() {
    // An Expansion A board whose CNC reads as fast as the line answers only at the program's
    // end (§5.3): 1 MiB handed over and sent in 1 KiB packets, then one answer for all of it.
    let mut fed = FedBlocks::new();
    let mut program = Vec::new();
    let mut n = 0;
    while program.len() < 1 << 20 {
        n += 10;
        program.extend(format!("N{n} G01 X{} Y{}\n", n % 977, n % 131).as_bytes());
    }
    program.extend(b"M30\n%");
    let mut most = 0;
    for (i, piece) in program.chunks(1024).enumerate() {
        fed.push(piece);
        fed.sent(((i + 1) * 1024).min(program.len()) as u64);
        most = most.max(fed.held());
    }
    assert!(most <= SENT_KEPT + 1024, "{most} bytes held");
    assert_eq!(at(&mut fed, program.len() as u64).as_deref(), Some("M30"));

    // An answer for bytes already let go names the last block let go, if it lies within
    // the answer; the blocks after it, once they are answered for.
    let mut fed = FedBlocks::new();
    fed.push(&program[..64 * 1024]);
    fed.sent(64 * 1024);
    let let_go = 64 * 1024 - SENT_KEPT;
    let text = at(&mut fed, let_go as u64).expect("a block");
    let line = format!("{text}\n");
    let end = program[..let_go]
        .windows(line.len())
        .rposition(|w| w == line.as_bytes())
        .expect("a line of the program")
        + line.len();
    assert!(end <= let_go && let_go - end < 64, "{end} {let_go}");
    let later = at(&mut fed, let_go as u64 + 200).expect("a block");
    assert_ne!(later, text);
}

#[test]
fn acknowledgements_far_behind_what_was_sent_still_move_the_block() {
    // Protocol B acknowledges only what reached the board before its next control code:
    // 64 KiB may be sent while the first is answered for. Each answer names a block that
    // ends within it, not far before it, and none at all is no answer.
    let program: Vec<u8> = (0..8000)
        .flat_map(|n| format!("N{n} G01 X{n}\n").into_bytes())
        .collect();
    let mut fed = FedBlocks::new();
    for (i, piece) in program[..64 * 1024].chunks(256).enumerate() {
        fed.push(piece);
        fed.sent(((i + 1) * 256) as u64);
    }
    let mut last_end = 0;
    for acked in (4096..=48 * 1024).step_by(4096) {
        let text = at(&mut fed, acked as u64).expect("a block at every answer");
        let line = format!("{text}\n");
        let end = program[..acked]
            .windows(line.len())
            .rposition(|w| w == line.as_bytes())
            .expect("a line of the program")
            + line.len();
        assert!(end > last_end, "the block moves on: {text} at {acked}");
        assert!(
            acked - end <= 4 * LET_GO_STEP,
            "{text} ends at {end}, {acked} acknowledged"
        );
        last_end = end;
    }
}
