use super::*;
use crate::engine::line::StopBits;
use std::time::Duration;

fn line_8n1(baud: u32) -> LineSettings {
    LineSettings {
        stop_bits: StopBits::One,
        ..LineSettings::with_baud(baud)
    }
}

#[test]
fn chars_in_inverts_time_for_chars() {
    for line in [
        LineSettings::with_baud(86_400),
        line_8n1(19_200),
        LineSettings::with_baud(50),
    ] {
        for n in [0u64, 1, 2, 7, 1000, 123_457] {
            let t = line.time_for_chars(n);
            assert_eq!(line.chars_in(t), n, "{line} n={n}");
            if n > 0 {
                let just_before = t - Duration::from_nanos(1);
                assert_eq!(line.chars_in(just_before), n - 1, "{line} n={n}");
            }
        }
    }
}

#[test]
fn batches_wait_for_half_a_window() {
    let line = LineSettings::with_baud(9600);
    let mut p = Pacer::new(line, 8);
    let t0 = Instant::now();
    assert_eq!(p.batch(t0, 100), 8);
    p.wrote(8, t0);
    // One character out: one free, but a writer holding more waits for four (half the
    // window), and not a nanosecond less.
    let one = t0 + line.time_for_chars(1);
    assert_eq!(p.writable(one), 1);
    assert_eq!(p.batch(one, 100), 0);
    let four = p.batch_at(one, 100);
    assert_eq!(four, t0 + line.time_for_chars(4));
    assert_eq!(p.batch(four - Duration::from_nanos(1), 100), 0);
    assert_eq!(p.batch(four, 100), 4);
    // A short message goes as soon as it fits whole.
    assert_eq!(p.batch(one, 1), 1);
    assert_eq!(p.batch_at(one, 1), one);
    assert_eq!(p.batch_at(t0, 2), t0 + line.time_for_chars(2));
    // Written back to back, the run goes on: the line never fell idle.
    let pl = p.wrote(4, four);
    assert_eq!(pl.run_start(), t0);
    assert_eq!(pl.first(), 8);
    // An idle line takes everything at once.
    let later = t0 + line.time_for_chars(100);
    assert_eq!(p.batch(later, 3), 3);
    assert_eq!(p.batch_at(later, 3), later);
    assert_eq!(Pacer::new(line, 1).low_water(10), 1);
    assert_eq!(Pacer::new(line, 256).low_water(0), 1);
}

#[test]
fn fresh_pacer_allows_a_full_window() {
    let p = Pacer::new(LineSettings::with_baud(9600), 16);
    let now = Instant::now();
    assert_eq!(p.writable(now), 16);
    assert_eq!(p.unsent(now), 0);
    assert_eq!(p.next_writable_at(now), now);
    assert_eq!(p.idle_at(), None);
}

#[test]
fn window_fills_and_drains_at_line_rate() {
    let line = LineSettings::with_baud(9600); // 11 bits: 1145.83 us a character
    let mut p = Pacer::new(line, 4);
    let t0 = Instant::now();
    let pl = p.wrote(4, t0);
    assert_eq!(p.writable(t0), 0);
    assert_eq!(p.unsent(t0), 4);
    assert_eq!(pl.done_at(0), t0 + line.time_for_chars(1));
    assert_eq!(pl.done_at(3), t0 + line.time_for_chars(4));
    // The front leaves after one character time, and not a nanosecond earlier.
    let front = p.next_writable_at(t0);
    assert_eq!(front, t0 + line.char_time());
    assert_eq!(p.writable(front - Duration::from_nanos(1)), 0);
    assert_eq!(p.writable(front), 1);
    // Continuing the run keeps the characters back to back.
    let pl2 = p.wrote(1, front);
    assert_eq!(pl2.done_at(0), t0 + line.time_for_chars(5));
    assert_eq!(p.idle_at(), Some(t0 + line.time_for_chars(5)));
    // Everything gone: a full window again.
    let later = t0 + line.time_for_chars(5);
    assert_eq!(p.unsent(later), 0);
    assert_eq!(p.writable(later), 4);
}

#[test]
fn idle_line_starts_a_new_run() {
    let line = line_8n1(19_200);
    let mut p = Pacer::new(line, 8);
    let t0 = Instant::now();
    p.wrote(2, t0);
    let t1 = t0 + Duration::from_secs(1);
    let pl = p.wrote(3, t1);
    assert_eq!(pl.done_at(0), t1 + line.time_for_chars(1));
    assert_eq!(pl.done_at(2), t1 + line.time_for_chars(3));
}

#[test]
fn long_runs_keep_the_nominal_rate() {
    // Write in window-sized bursts, each as soon as allowed, for 100k characters.
    for line in [LineSettings::with_baud(86_400), line_8n1(19_200)] {
        let mut p = Pacer::new(line, 16);
        let t0 = Instant::now();
        let mut now = t0;
        let mut written = 0u64;
        let mut last = t0;
        while written < 100_000 {
            now = p.next_writable_at(now);
            let n = p
                .writable(now)
                .min(usize::try_from(100_000 - written).unwrap());
            let pl = p.wrote(n, now);
            last = pl.done_at(n as u64 - 1);
            written += n as u64;
        }
        assert_eq!(last, t0 + line.time_for_chars(100_000), "{line}");
    }
}

#[test]
fn overfilling_only_delays() {
    let line = LineSettings::with_baud(9600);
    let mut p = Pacer::new(line, 2);
    let t0 = Instant::now();
    p.wrote(10, t0);
    assert_eq!(p.writable(t0), 0);
    assert_eq!(p.next_writable_at(t0), t0 + line.time_for_chars(9));
    p.reset();
    assert_eq!(p.writable(t0), 2);
}

#[test]
fn zero_window_is_one() {
    let p = Pacer::new(LineSettings::with_baud(9600), 0);
    assert_eq!(p.window(), 1);
}
