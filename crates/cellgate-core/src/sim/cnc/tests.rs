use super::*;

fn secs(s: f64) -> Duration {
    Duration::from_secs_f64(s)
}

#[test]
fn consumes_at_rate_lazily() {
    let t0 = Instant::now();
    let mut cnc = Cnc::new(8192, 1000, 1 << 20, t0);
    assert!(cnc.start_reading(t0));
    assert_eq!(cnc.push_data(t0, &[b'X'; 3000]), Push::Stored(3000));
    cnc.advance(t0 + secs(1.0));
    assert_eq!(cnc.buffered(), 2000);
    cnc.advance(t0 + secs(1.5));
    assert_eq!(cnc.buffered(), 1500);
    // Free reaches 7692 once 1000 more are read: at 2.5 s.
    assert_eq!(cnc.when_free_at_least(8192 - 500), Some(t0 + secs(2.5)));
    cnc.advance(t0 + secs(10.0));
    assert_eq!(cnc.buffered(), 0);
    // Starved for 7 s: no credit banked; new data is read at the rate again.
    cnc.push_data(t0 + secs(10.0), &[b'Y'; 100]);
    cnc.advance(t0 + secs(10.05));
    assert_eq!(cnc.buffered(), 50);
    assert_eq!(cnc.read_total(), 3050);
}

#[test]
fn splits_programs_at_eor_and_ignores_the_rest() {
    let t0 = Instant::now();
    let mut cnc = Cnc::new(8192, 100, 1 << 20, t0);
    cnc.start_reading(t0);
    let tape = b"\n\n%\nO1234 (TEST)\nG01 X1.\nM30\n%\nIGNORED";
    cnc.push_data(t0, tape);
    let end = cnc.when_program_ends().unwrap();
    // Leader (2) + program through the second % (28): 30 bytes at 100 B/s.
    assert_eq!(end, t0 + secs(0.30));
    cnc.advance(end - Duration::from_nanos(1));
    assert!(cnc.take_finished().is_none());
    cnc.advance(end);
    let p = cnc.take_finished().unwrap();
    assert_eq!(&p.data[..], b"%\nO1234 (TEST)\nG01 X1.\nM30\n%");
    assert_eq!(p.first_line, "O1234 (TEST)");
    assert_eq!(p.len, 28);
    assert_eq!(p.sha256.to_vec(), Sha256::digest(&p.data).to_vec());
    assert!(!cnc.reading());
    assert_eq!(cnc.buffered(), 0, "data after EOR is ignored");
    assert_eq!(cnc.push_data(end, b"more"), Push::Ignored(4));
}

#[test]
fn program_end_found_across_pieces_and_consumption() {
    let t0 = Instant::now();
    let mut cnc = Cnc::new(8192, 10, 1 << 20, t0);
    cnc.start_reading(t0);
    cnc.push_data(t0, b"\n%\nO9\n");
    assert_eq!(
        cnc.when_program_ends(),
        None,
        "the first % is the tape start"
    );
    cnc.advance(t0 + secs(0.5));
    assert_eq!(cnc.buffered(), 1);
    cnc.push_data(t0 + secs(0.5), b"M30\n%\n");
    // 5 bytes read by 0.5 s, then 1 + 5 more through the ending %: at 1.1 s.
    assert_eq!(cnc.when_program_ends(), Some(t0 + secs(1.1)));
    cnc.advance(t0 + secs(1.1));
    assert_eq!(&cnc.take_finished().unwrap().data[..], b"%\nO9\nM30\n%");
    // CLB keeps the tape reader's state: inside a program, the next % ends it.
    cnc.start_reading(t0 + secs(2.0));
    cnc.push_data(t0 + secs(2.0), b"%O1\nG1\n");
    cnc.clear_buffer(t0 + secs(2.5));
    cnc.push_data(t0 + secs(2.5), b"G0%");
    assert_eq!(cnc.when_program_ends(), Some(t0 + secs(2.8)));
    cnc.advance(t0 + secs(2.8));
    assert_eq!(&cnc.take_finished().unwrap().data[..], b"%O1\nGG0%");
}

#[test]
fn program_without_tape_start_and_iso_parity() {
    let t0 = Instant::now();
    let mut cnc = Cnc::new(64, 0, 4, t0);
    cnc.start_reading(t0);
    // ISO: % is A5h, LF 0Ah.
    cnc.push_data(t0, b"O0001\nM30\n\xA5");
    cnc.advance(t0);
    let p = cnc.take_finished().unwrap();
    assert_eq!(p.first_line, "O0001");
    assert_eq!(p.len, 11);
    assert!(p.truncated);
    assert_eq!(&p.data[..], b"O000");
}

#[test]
fn overflow_reset_and_alarm() {
    let t0 = Instant::now();
    let mut cnc = Cnc::new(10, 1, 100, t0);
    cnc.start_reading(t0);
    assert_eq!(
        cnc.push_data(t0, &[b'1'; 11]),
        Push::Overflow { len: 11, free: 10 }
    );
    cnc.push_data(t0, b"%O1\nG0");
    assert_eq!(cnc.status(), BufferStatus::Operating);
    cnc.raise_alarm(t0, AlarmCause::NcAlarm);
    assert_eq!(cnc.status(), BufferStatus::Alarm);
    assert!(!cnc.start_reading(t0));
    assert_eq!(cnc.when_program_ends(), None);
    cnc.reset(t0);
    assert_eq!(cnc.status(), BufferStatus::Reset);
    assert_eq!(cnc.buffered(), 0);
}

mod g05;
