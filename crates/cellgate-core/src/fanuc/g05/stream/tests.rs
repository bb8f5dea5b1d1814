use super::*;
use crate::engine::LineSettings;
use crate::fanuc::g05::UnitTime;

fn settings() -> StreamSettings {
    let mut format = G05Format::new(2);
    format.unit_time_ms = UnitTime::Ms8;
    StreamSettings {
        format,
        before: Bytes::from_static(b"G05\n"),
        after: Bytes::from_static(b"M30\n"),
        window: 10,
        prime: 4,
        idle: Duration::from_secs(2),
        line: LineSettings::with_baud(9600),
        in_flight: 2048,
    }
}

fn blocks(n: usize) -> Vec<BlockIn> {
    (0..n)
        .map(|i| BlockIn {
            travels: vec![i as i32 + 1, -1],
            aux: None,
        })
        .collect()
}

fn batch(seq: u64, n: usize) -> Batch {
    Batch {
        seq,
        blocks: blocks(n),
        end: false,
    }
}

fn binary_len(chunks: &[Chunk]) -> usize {
    chunks
        .iter()
        .map(|c| match c {
            Chunk::Binary(b) | Chunk::Primed { blocks: b, .. } => b.len(),
            Chunk::Text(_) => 0,
        })
        .sum()
}

#[test]
fn blocks_wait_for_the_priming_level_then_flow() {
    let t0 = Instant::now();
    let mut s = Stream::new(settings(), t0);
    assert_eq!(s.offer(t0, &batch(0, 3)), Ok(Offered::Accepted));
    assert!(s.take_chunks().is_empty(), "below the priming level");
    assert_eq!(s.credits(), 7);
    assert_eq!(s.offer(t0, &batch(1, 1)), Ok(Offered::Accepted));
    let c = s.take_chunks();
    // The G05 block and the priming level's blocks are one chunk (§9.2).
    assert_eq!(c.len(), 1);
    assert!(
        matches!(&c[0], Chunk::Primed { text, .. } if text == &Bytes::from_static(b"G05\n")),
        "{c:?}"
    );
    assert_eq!(binary_len(&c), 4 * 5);
    assert_eq!(s.state(), StreamState::Streaming);
    s.offer(t0, &batch(2, 2)).unwrap();
    assert_eq!(binary_len(&s.take_chunks()), 2 * 5);
    // Credits come back as blocks go on the line: "G05\n" and two blocks.
    s.on_sent(t0, 4 + 10);
    assert_eq!(s.figures().on_line, 2);
    assert_eq!(s.credits(), 10 - 4);
}

#[test]
fn gaps_repeats_credits_and_bad_blocks_refuse_the_whole_batch() {
    let t0 = Instant::now();
    let mut s = Stream::new(settings(), t0);
    s.offer(t0, &batch(0, 2)).unwrap();
    assert_eq!(s.offer(t0, &batch(0, 2)), Ok(Offered::Repeat));
    assert!(matches!(
        s.offer(t0, &batch(2, 1)),
        Err(BatchError::Gap {
            expected: 1,
            got: 2
        })
    ));
    assert!(matches!(
        s.offer(t0, &batch(1, 9)),
        Err(BatchError::Credits { credits: 8, .. })
    ));
    let mut bad = batch(1, 3);
    bad.blocks[1].travels = vec![1, 9000];
    let e = s.offer(t0, &bad).unwrap_err();
    assert!(e.to_string().contains("9000"), "{e}");
    let mut short = batch(1, 1);
    short.blocks[0].travels = vec![1];
    assert!(s.offer(t0, &short).is_err());
    let f = s.figures();
    assert_eq!(
        (f.received, f.gaps, f.repeats, f.refused, f.next_seq),
        (2, 1, 1, 3, 1)
    );
    // Nothing of the refused batches was taken: the next good one is block 3.
    s.offer(t0, &batch(1, 2)).unwrap();
    assert_eq!(s.figures().received, 4);
}

#[test]
fn the_end_sends_the_end_block_and_the_closing_text() {
    let t0 = Instant::now();
    let mut s = Stream::new(settings(), t0);
    s.offer(
        t0,
        &Batch {
            seq: 0,
            blocks: blocks(2),
            end: true,
        },
    )
    .unwrap();
    // A short stream ended by its producer is sent whole, priming or not.
    let c = s.take_chunks();
    assert!(
        matches!(c.first(), Some(Chunk::Primed { text, .. }) if text == &Bytes::from_static(b"G05\n")),
        "{c:?}"
    );
    assert_eq!(c.get(1), Some(&Chunk::Binary(Bytes::from(vec![0u8; 5]))));
    assert_eq!(c.last(), Some(&Chunk::Text(Bytes::from_static(b"M30\n"))));
    assert!(s.is_closing());
    assert_eq!(s.credits(), 0);
    assert!(matches!(
        s.offer(t0, &batch(1, 1)),
        Err(BatchError::Ended { .. })
    ));
}

#[test]
fn a_stream_lost_before_its_g05_block_sends_nothing() {
    let t0 = Instant::now();
    let mut s = Stream::new(settings(), t0);
    s.offer(t0, &batch(0, 2)).unwrap();
    s.finish(EndReason::ProducerLost);
    assert!(s.take_chunks().is_empty());
    assert_eq!(s.state(), StreamState::Failed);
}

#[test]
fn underruns_are_estimated_from_the_line_and_the_unit_time() {
    let t0 = Instant::now();
    let ms = Duration::from_millis;
    let mut s = Stream::new(settings(), t0);
    s.offer(t0, &batch(0, 4)).unwrap();
    s.take_chunks();
    // The G05 block and four blocks handed to the line at t0: 24 characters, 27.5 ms at
    // 9600 baud, so the CNC has read the G05 block by 27.5 ms and taken its first block
    // one T (8 ms) later at the latest: its unit times are counted from 35.5 ms.
    s.on_sent(t0, 4 + 20);
    // 8 ms slots: at 76 ms five slots have passed, four found a block (judged with the
    // estimate's lag).
    s.tick(t0 + ms(76) + ESTIMATE_LAG);
    let f = s.figures();
    assert_eq!((f.cnc_buffer, f.underruns), (0, 1));
    // A producer silent for the idle time with the CNC dry is taken as gone.
    assert_eq!(s.tick(t0 + ms(1000)), None);
    assert_eq!(s.tick(t0 + ms(2000)), Some(EndReason::ProducerIdle));
}

/// The estimate never counts an underrun the CNC cannot have had. A stream opened while the
/// CNC waits: 100 blocks of 8 ms (800 ms of the CNC's time) go out with the `G05` block in one
/// piece of 504 characters, which the board takes only once it has arrived whole, 578 ms
/// later at 9600 baud; the producer's next 50 blocks are handed over at 1000 ms and have
/// arrived by 1287 ms, before the CNC, which started at 578 ms, has used the first 100. The
/// estimate once counted from the hand-over and said 25 unit times found the CNC empty.
#[test]
fn the_estimate_counts_no_underrun_the_cnc_cannot_have_had() {
    let t0 = Instant::now();
    let ms = Duration::from_millis;
    let mut s = Stream::new(
        StreamSettings {
            window: 1000,
            prime: 100,
            ..settings()
        },
        t0,
    );
    s.offer(t0, &batch(0, 100)).unwrap();
    s.take_chunks();
    s.on_sent(t0, 4 + 500);
    for at in (0..1000).step_by(100) {
        s.tick(t0 + ms(at));
    }
    s.offer(t0 + ms(1000), &batch(1, 50)).unwrap();
    s.on_sent(t0 + ms(1000), 4 + 750);
    for at in (1000..1600).step_by(20) {
        s.tick(t0 + ms(at));
    }
    let f = s.figures();
    assert_eq!(f.underruns, 0, "{f:?}");
    // Slots from 585.5 ms (577.5 ms on the line, one T): 118 by 1530 ms, the last tick less
    // the estimate's lag.
    assert_eq!(f.cnc_buffer, 150 - 118, "{f:?}");
    // Past the 150 blocks, the CNC does run dry, and the estimate says so.
    for at in (1600..2200).step_by(20) {
        s.tick(t0 + ms(at));
    }
    assert!(s.figures().underruns > 0, "{:?}", s.figures());
}

/// A producer that has no credits cannot send: on a line too slow to take back the window's
/// blocks for a while, its silence does not count towards the idle time until credits come
/// back, even with the CNC dry.
#[test]
fn a_producer_without_credits_is_not_idle() {
    let t0 = Instant::now();
    let ms = Duration::from_millis;
    let mut s = Stream::new(settings(), t0);
    s.offer(t0, &batch(0, 10)).unwrap();
    assert_eq!(s.credits(), 0);
    // The G05 block on the line, none of the ten blocks yet: the CNC is dry from its first
    // unit time, and there are no credits until two blocks go at 3 s.
    s.on_sent(t0, 4);
    for at in (100..3000).step_by(100) {
        assert_eq!(s.tick(t0 + ms(at)), None, "at {at} ms");
    }
    assert!(s.figures().underruns > 0);
    s.on_sent(t0 + ms(3000), 4 + 10);
    assert_eq!(s.credits(), 2);
    assert_eq!(s.tick(t0 + ms(4900)), None);
    assert_eq!(s.tick(t0 + ms(5000)), Some(EndReason::ProducerIdle));
}

#[test]
fn a_stream_that_gets_no_batch_within_the_idle_time_ends() {
    let t0 = Instant::now();
    let ms = Duration::from_millis;
    let mut s = Stream::new(settings(), t0);
    assert_eq!(s.tick(t0 + ms(1999)), None);
    assert_eq!(s.tick(t0 + ms(2000)), Some(EndReason::NoBatch));
    // One batch, and the rule is the CNC's: silence alone ends nothing before the G05 block.
    let mut s = Stream::new(settings(), t0);
    s.offer(t0, &batch(0, 4)).unwrap();
    assert_eq!(s.tick(t0 + ms(5000)), None);
}

fn figures(underruns: u64, end_reason: Option<EndReason>) -> StreamFigures {
    StreamFigures {
        state: StreamState::Streaming,
        credits: 0,
        received: 100,
        on_line: 90,
        cnc_buffer: 0,
        underruns,
        gaps: 0,
        repeats: 0,
        refused: 0,
        next_seq: 1,
        last_error: None,
        end_reason,
    }
}

#[test]
fn starvation_and_an_idle_end_raise_alarms_once_per_episode() {
    let t0 = Instant::now();
    let ms = Duration::from_millis;
    let mut w = G05Watch::new();
    assert!(w.observe(t0, &figures(0, None)).is_empty());
    let a = w.observe(t0 + ms(100), &figures(3, None));
    assert!(
        matches!(a.as_slice(), [G05Alarm::Starving { underruns: 3, .. }]),
        "{a:?}"
    );
    // Rises within the quiet time belong to the same episode.
    assert!(w.observe(t0 + ms(600), &figures(9, None)).is_empty());
    assert!(w.observe(t0 + ms(1500), &figures(12, None)).is_empty());
    assert!(w.observe(t0 + ms(3000), &figures(12, None)).is_empty());
    // Quiet for longer than STARVATION_QUIET: a new episode.
    let a = w.observe(t0 + ms(3600), &figures(13, None));
    assert!(
        matches!(a.as_slice(), [G05Alarm::Starving { underruns: 13, .. }]),
        "{a:?}"
    );
    assert!(a[0].to_string().contains("starving"), "{}", a[0]);
    // A producer that fell silent ends the stream: one alarm, however often it is seen.
    let a = w.observe(t0 + ms(3700), &figures(13, Some(EndReason::ProducerIdle)));
    assert_eq!(
        a,
        [G05Alarm::Idle {
            reason: EndReason::ProducerIdle
        }]
    );
    assert!(
        w.observe(t0 + ms(3800), &figures(13, Some(EndReason::ProducerIdle)))
            .is_empty()
    );
    // The producer's own end is no alarm.
    let mut w = G05Watch::new();
    assert!(
        w.observe(t0, &figures(0, Some(EndReason::Producer)))
            .is_empty()
    );
}
