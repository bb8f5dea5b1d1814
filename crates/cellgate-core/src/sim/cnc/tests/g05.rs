use super::super::*;
use crate::fanuc::g05::{AuxFunction, AuxWord, DataFormat, G05Encoder, UnitTime};

fn ms(v: f64) -> Duration {
    Duration::from_secs_f64(v / 1000.0)
}

fn g05_cnc(format: G05Format, rate: u32, t0: Instant) -> Cnc {
    let mut cnc = Cnc::new(8192, rate, 1 << 20, t0).with_g05(format).unwrap();
    assert!(cnc.start_reading(t0));
    cnc
}

/// Blocks for `travels` (and `aux`), each encoded, concatenated.
fn blocks(format: G05Format, travels: &[Vec<i32>], aux: &[Option<AuxWord>]) -> Vec<u8> {
    let mut e = G05Encoder::new(format).unwrap();
    let mut out = Vec::new();
    for (i, t) in travels.iter().enumerate() {
        e.block(t, aux.get(i).copied().flatten(), &mut out).unwrap();
    }
    out
}

fn end(format: G05Format) -> Vec<u8> {
    let mut out = Vec::new();
    format.encode_end(&mut out);
    out
}

fn notices(cnc: &mut Cnc) -> Vec<G05Notice> {
    std::iter::from_fn(|| cnc.take_g05_notice()).collect()
}

fn stats(cnc: &Cnc) -> G05Stats {
    cnc.g05_stats().unwrap().clone()
}

#[test]
fn enters_after_the_g05_block_takes_a_block_per_unit_time_and_ends_at_the_end_block() {
    let t0 = Instant::now();
    let f = G05Format::new(2); // 8 ms, special, 5-byte blocks
    let mut cnc = g05_cnc(f, 1000, t0);
    let travels: Vec<Vec<i32>> = (1..=5).map(|i| vec![i, -10 * i]).collect();
    let mut data = b"%\nO1\nG05\n".to_vec();
    data.extend(blocks(f, &travels, &[]));
    data.extend(end(f));
    data.extend_from_slice(b"M30\n%");
    cnc.push_data(t0, &data);
    assert_eq!(cnc.when_program_ends(), None, "the G05 block comes first");
    // The 9 text bytes are read at 1000 B/s: G05 ends at 9 ms.
    assert_eq!(cnc.next_g05_deadline(), Some(t0 + ms(9.0)));
    cnc.advance(t0 + ms(9.0) - Duration::from_nanos(1));
    assert!(!cnc.in_binary());
    cnc.advance(t0 + ms(9.0));
    assert!(cnc.in_binary());
    assert_eq!(notices(&mut cnc), [G05Notice::Entered { at: t0 + ms(9.0) }]);
    assert_eq!(cnc.buffered(), 6 * 5 + 5);
    // One block per 8 ms, from 8 ms after G05: at 17, 25, 33, 41, 49 ms.
    for (i, slot) in [17.0, 25.0, 33.0, 41.0, 49.0].into_iter().enumerate() {
        assert_eq!(cnc.next_g05_deadline(), Some(t0 + ms(slot)));
        cnc.advance(t0 + ms(slot) - Duration::from_nanos(1));
        assert_eq!(cnc.buffered(), (6 - i) * 5 + 5, "before slot {i}");
        cnc.advance(t0 + ms(slot));
        assert_eq!(cnc.buffered(), (5 - i) * 5 + 5, "after slot {i}");
        assert_eq!(stats(&cnc).blocks, i as u64 + 1);
    }
    assert!(cnc.in_binary());
    // Free space grows one block per slot: 10 more bytes free after two more slots.
    assert_eq!(
        cnc.when_free_at_least(cnc.free() + 6),
        Some(t0 + ms(57.0)),
        "two blocks away, but only the end block remains: its slot"
    );
    assert_eq!(cnc.when_free_at_least(cnc.free() + 5), Some(t0 + ms(57.0)));
    // The end block at 57 ms; "M30\n%" then at 1000 B/s: the program ends at 62 ms.
    cnc.advance(t0 + ms(57.0));
    assert!(!cnc.in_binary());
    let n = notices(&mut cnc);
    let [G05Notice::Left { end, stats: s }] = &n[..] else {
        panic!("{n:?}");
    };
    assert_eq!(*end, G05End::EndBlock);
    assert_eq!(s.blocks, 5);
    assert_eq!(s.travel, [15, -150]);
    assert_eq!(s.underruns, 0);
    assert_eq!(s.min_buffered_blocks, Some(2), "block 5 and the end block");
    assert_eq!(s.sessions, 1);
    assert!(!s.active);
    assert_eq!(cnc.when_program_ends(), Some(t0 + ms(62.0)));
    cnc.advance(t0 + ms(62.0));
    let p = cnc.take_finished().unwrap();
    assert_eq!(p.len, data.len() as u64);
    assert_eq!(
        &p.data[..],
        &data[..],
        "binary blocks are part of the program"
    );
    assert!(!cnc.reading());
    assert_eq!(cnc.read_total(), data.len() as u64);
}

#[test]
fn underruns_are_counted_exactly_when_the_buffer_runs_dry() {
    let t0 = Instant::now();
    let f = G05Format {
        unit_time_ms: UnitTime::Ms1,
        ..G05Format::new(1)
    };
    // Rate 0: the CNC reads text as fast as it comes; G05 is read at t0.
    let mut cnc = g05_cnc(f, 0, t0);
    cnc.push_data(t0, b"G05\n");
    cnc.advance(t0);
    assert!(cnc.in_binary());
    assert_eq!(cnc.next_g05_deadline(), Some(t0 + ms(1.0)));
    // Three blocks arrive at 2.5 ms: slots 1 and 2 had none.
    let three = blocks(f, &[vec![1], vec![2], vec![3]], &[]);
    cnc.push_data(t0 + ms(2.5), &three);
    assert_eq!(stats(&cnc).underruns, 2);
    assert_eq!(stats(&cnc).min_buffered_blocks, None, "not started yet");
    let n = notices(&mut cnc);
    assert_eq!(
        n[1..],
        [G05Notice::Underruns { new: 2, total: 2 }],
        "first report at once"
    );
    // Slots 3, 4, 5 take them (3, 2, 1 whole blocks waiting); 6..=10 have none.
    cnc.advance(t0 + ms(10.0));
    let s = stats(&cnc);
    assert_eq!(s.blocks, 3);
    assert_eq!(s.travel, [6]);
    assert_eq!(s.underruns, 7);
    assert_eq!(s.min_buffered_blocks, Some(0));
    assert!(notices(&mut cnc).is_empty(), "at most one report a second");
    // Starved: the next wake is the report a second after the last one.
    assert_eq!(cnc.next_g05_deadline(), Some(t0 + ms(1002.5)));
    cnc.advance(t0 + ms(1002.5));
    // Slots 1..=1002 are due, 3 took blocks.
    assert_eq!(stats(&cnc).underruns, 999);
    assert_eq!(
        notices(&mut cnc),
        [G05Notice::Underruns {
            new: 997,
            total: 999
        }]
    );
    // The end block at slot 1003.
    cnc.push_data(t0 + ms(1002.7), &end(f));
    assert_eq!(cnc.next_g05_deadline(), Some(t0 + ms(1003.0)));
    cnc.advance(t0 + ms(1003.0));
    let n = notices(&mut cnc);
    let [G05Notice::Left { end, stats: s }] = &n[..] else {
        panic!("{n:?}");
    };
    assert_eq!((*end, s.underruns, s.blocks), (G05End::EndBlock, 999, 3));
    assert_eq!(cnc.next_g05_deadline(), None);
}

#[test]
fn blocks_on_time_have_no_underrun() {
    let t0 = Instant::now();
    let f = G05Format {
        unit_time_ms: UnitTime::Ms2,
        ..G05Format::new(3)
    };
    let mut cnc = g05_cnc(f, 0, t0);
    cnc.push_data(t0, b"G05\n");
    cnc.advance(t0);
    // One block every 2 ms, each 1 ms before its slot.
    for i in 0..100 {
        let block = blocks(f, &[vec![i, 1, -1]], &[]);
        cnc.push_data(t0 + ms(2.0 * f64::from(i) + 1.0), &block);
    }
    cnc.push_data(t0 + ms(201.0), &end(f));
    cnc.advance(t0 + ms(202.0));
    let s = stats(&cnc);
    assert_eq!(s.underruns, 0);
    assert_eq!(s.blocks, 100);
    assert_eq!(s.travel, [(0..100).sum::<i64>(), 100, -100]);
    assert_eq!(s.min_buffered_blocks, Some(1));
    assert_eq!(s.end, Some(G05End::EndBlock));
}

#[test]
fn a_wrong_check_byte_raises_sr0890_and_leaves_binary_mode() {
    let t0 = Instant::now();
    let f = G05Format::new(2);
    let mut cnc = g05_cnc(f, 0, t0);
    let mut data = b"N1G05;".to_vec();
    let good = blocks(f, &[vec![1, 1], vec![2, 2], vec![3, 3]], &[]);
    data.extend(&good);
    // Block 2's check byte.
    data[6 + 9] ^= 0x02;
    cnc.push_data(t0, &data);
    cnc.advance(t0 + ms(8.0));
    assert_eq!(stats(&cnc).blocks, 1);
    assert!(cnc.reading());
    cnc.advance(t0 + ms(16.0));
    assert!(!cnc.reading());
    assert!(!cnc.in_binary());
    assert_eq!(cnc.alarm(), Some(AlarmCause::NcAlarm));
    assert_eq!(cnc.status(), BufferStatus::Alarm);
    let n = notices(&mut cnc);
    assert!(matches!(n[0], G05Notice::Entered { .. }), "{n:?}");
    let G05Notice::CheckSum(e) = &n[1] else {
        panic!("{n:?}");
    };
    assert!(matches!(e, G05DecodeError::CheckByte { block: 2, .. }));
    let G05Notice::Left { end, stats: s } = &n[2] else {
        panic!("{n:?}");
    };
    assert_eq!((*end, s.blocks), (G05End::CheckSum, 1));
    // Nothing more is taken until a reset.
    cnc.advance(t0 + ms(100.0));
    assert_eq!(cnc.buffered(), 5);
    assert!(!cnc.start_reading(t0 + ms(100.0)));
    cnc.reset(t0 + ms(100.0));
    assert_eq!(cnc.buffered(), 0);
    assert!(notices(&mut cnc).is_empty());
}

#[test]
fn special_and_general_with_and_without_the_auxiliary_word() {
    for (data_format, aux) in [
        (DataFormat::Special, AuxFunction::None),
        (DataFormat::Special, AuxFunction::M),
        (DataFormat::General, AuxFunction::None),
        (DataFormat::General, AuxFunction::T),
    ] {
        let t0 = Instant::now();
        let f = G05Format {
            data_format,
            aux,
            aux_order: crate::fanuc::g05::AuxOrder::LowFirst,
            unit_time_ms: UnitTime::Ms4,
            ..G05Format::new(3)
        };
        let (min, max) = data_format.travel_range();
        let travels: Vec<Vec<i32>> = (0..40)
            .map(|i| vec![min + i, max - i, if i % 2 == 0 { 7 } else { -7 }])
            .collect();
        let auxes: Vec<Option<AuxWord>> = (0..40u32)
            .map(|i| match i % 3 {
                _ if !aux.rax() => None,
                0 => Some(AuxWord::significant(i)),
                1 => Some(AuxWord {
                    value: 99,
                    significant: false,
                }),
                _ => None,
            })
            .collect();
        let mut cnc = g05_cnc(f, 0, t0);
        let mut data = b"G05\n".to_vec();
        data.extend(blocks(f, &travels, &auxes));
        data.extend(end(f));
        data.extend_from_slice(b"M30\n%");
        cnc.push_data(t0, &data);
        cnc.advance(t0 + ms(4.0 * 41.0));
        let p = cnc.take_finished().expect("M30 and EOR read as NC text");
        assert_eq!(p.len, data.len() as u64);
        let n = notices(&mut cnc);
        let Some(G05Notice::Left { end, stats: s }) = n.last() else {
            panic!("{n:?}");
        };
        assert_eq!(*end, G05End::EndBlock, "{f:?}");
        assert_eq!(s.blocks, 40);
        let sum = |a: usize| travels.iter().map(|t| i64::from(t[a])).sum::<i64>();
        assert_eq!(s.travel, [sum(0), sum(1), sum(2)], "{f:?}");
        let expected: Vec<u32> = if aux.rax() {
            (0..40).filter(|i| i % 3 == 0).collect()
        } else {
            Vec::new()
        };
        assert_eq!(s.aux, expected, "{f:?}");
        assert_eq!(s.aux_count, expected.len() as u64);
        assert_eq!(s.underruns, 0);
    }
}

#[test]
fn a_second_g05_in_the_same_program_is_a_second_session() {
    let t0 = Instant::now();
    let f = G05Format::new(1);
    let mut cnc = g05_cnc(f, 0, t0);
    let mut data = b"%\nG05\n".to_vec();
    data.extend(blocks(f, &[vec![5]], &[]));
    data.extend(end(f));
    data.extend_from_slice(b"G01X1.\nG5\n");
    data.extend(blocks(f, &[vec![-3], vec![-4]], &[]));
    data.extend(end(f));
    data.extend_from_slice(b"M30\n%");
    cnc.push_data(t0, &data);
    cnc.advance(t0 + ms(15.0));
    assert_eq!(stats(&cnc).travel, [5]);
    // The end block at 16 ms; the text after it, and the second G05, are read at once
    // (rate 0): a new session from 16 ms, its blocks at 24 and 32, its end at 40.
    cnc.advance(t0 + ms(16.0));
    assert!(cnc.in_binary());
    let n = notices(&mut cnc);
    assert!(
        matches!(
            &n[..],
            [
                G05Notice::Entered { .. },
                G05Notice::Left { end: G05End::EndBlock, stats: first },
                G05Notice::Entered { at },
            ] if first.travel == [5] && *at == t0 + ms(16.0)
        ),
        "{n:?}"
    );
    cnc.advance(t0 + ms(40.0));
    let s = stats(&cnc);
    assert_eq!((s.sessions, s.blocks, s.travel.clone()), (2, 2, vec![-7]));
    assert!(cnc.take_finished().is_some());
}

#[test]
fn without_g05_settings_g05_is_just_text() {
    let t0 = Instant::now();
    let mut cnc = Cnc::new(8192, 0, 1 << 20, t0);
    cnc.start_reading(t0);
    cnc.push_data(t0, b"%\nG05\n\x00\x02\x02%");
    cnc.advance(t0);
    assert!(!cnc.in_binary());
    assert_eq!(cnc.g05_stats(), None);
    assert_eq!(cnc.next_g05_deadline(), None);
    assert_eq!(cnc.take_finished().unwrap().len, 10);
}

#[test]
fn general_format_bytes_are_not_taken_for_eor_or_a_g05_block() {
    // 0025h is `%` in its low byte and 0A47h holds LF and `G`: as binary data they are
    // travels, and the program ends at the real EOR only.
    let t0 = Instant::now();
    let f = G05Format {
        data_format: DataFormat::General,
        ..G05Format::new(1)
    };
    let mut cnc = g05_cnc(f, 100, t0);
    let mut data = b"G05\n".to_vec();
    data.extend(blocks(f, &[vec![0x25], vec![0x0A47], vec![0x0A25]], &[]));
    data.extend(end(f));
    data.extend_from_slice(b"%");
    cnc.push_data(t0, &data);
    assert_eq!(cnc.when_program_ends(), None);
    // G05 read at 40 ms (100 B/s); blocks at 48, 56, 64; end at 72; `%` 10 ms later.
    cnc.advance(t0 + ms(72.0));
    assert_eq!(stats(&cnc).travel, [0x25 + 0x0A47 + 0x0A25]);
    assert_eq!(cnc.when_program_ends(), Some(t0 + ms(82.0)));
    cnc.advance(t0 + ms(82.0));
    assert_eq!(cnc.take_finished().unwrap().len, data.len() as u64);
}

#[test]
fn feed_hold_pauses_the_unit_times_and_reset_leaves_binary_mode() {
    let t0 = Instant::now();
    let f = G05Format::new(1);
    let mut cnc = g05_cnc(f, 0, t0);
    let mut data = b"G05\n".to_vec();
    data.extend(blocks(f, &[vec![1], vec![2], vec![3]], &[]));
    cnc.push_data(t0, &data);
    cnc.advance(t0 + ms(8.0));
    assert_eq!(stats(&cnc).blocks, 1);
    cnc.stop_reading(t0 + ms(10.0));
    cnc.advance(t0 + ms(100.0));
    assert_eq!(stats(&cnc).blocks, 1);
    assert_eq!(stats(&cnc).underruns, 0);
    assert_eq!(cnc.next_g05_deadline(), None);
    // Cycle start again: slots from then on.
    cnc.start_reading(t0 + ms(100.0));
    assert_eq!(cnc.next_g05_deadline(), Some(t0 + ms(108.0)));
    cnc.advance(t0 + ms(108.0));
    assert_eq!(stats(&cnc).blocks, 2);
    notices(&mut cnc);
    cnc.reset(t0 + ms(110.0));
    assert!(!cnc.in_binary());
    let n = notices(&mut cnc);
    assert!(
        matches!(&n[..], [G05Notice::Left { end: G05End::Reset, stats }] if stats.blocks == 2),
        "{n:?}"
    );
    // After the reset the CNC reads text, and a new G05 starts a new session.
    cnc.start_reading(t0 + ms(110.0));
    cnc.push_data(t0 + ms(110.0), b"G05\n");
    cnc.advance(t0 + ms(110.0));
    assert!(cnc.in_binary());
    assert_eq!(stats(&cnc).sessions, 2);
    assert_eq!(stats(&cnc).blocks, 0);
    cnc.raise_alarm(t0 + ms(111.0), AlarmCause::NcAlarm);
    assert!(!cnc.in_binary());
    assert_eq!(stats(&cnc).end, Some(G05End::Alarm));
}

#[test]
fn a_block_split_across_pushes_waits_until_whole() {
    let t0 = Instant::now();
    let f = G05Format {
        aux: AuxFunction::S,
        ..G05Format::new(2)
    };
    let mut cnc = g05_cnc(f, 0, t0);
    cnc.push_data(t0, b"G05\n");
    cnc.advance(t0);
    let b = blocks(f, &[vec![1, 2]], &[Some(AuxWord::significant(1200))]);
    cnc.push_data(t0 + ms(1.0), &b[..4]);
    cnc.advance(t0 + ms(8.0));
    assert_eq!(stats(&cnc).underruns, 1, "half a block is no block");
    cnc.push_data(t0 + ms(9.0), &b[4..]);
    cnc.advance(t0 + ms(16.0));
    let s = stats(&cnc);
    assert_eq!((s.blocks, s.underruns), (1, 1));
    assert_eq!(s.aux, [1200]);
    assert_eq!(s.min_buffered_blocks, Some(1));
}
