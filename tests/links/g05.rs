//! G05 streams through every protocol to the simulated CNC, in virtual time: what the CNC took
//! is exactly what was streamed, and the stream's own figures tell the truth about underruns.

use crate::common;

use std::time::Duration;

use cellgate::link::driver::LinkEvent;
use cellgate::link::g05::{G05Desk, StreamHandle};
use cellgate_core::config::CellConfig;
use cellgate_core::fanuc::g05::AuxWord;
use cellgate_core::fanuc::g05::stream::{
    Batch, BatchError, BlockIn, EndReason, Offered, StreamState,
};
use cellgate_core::fanuc::host::LinkState;
use cellgate_core::sim::cnc::G05End;
use common::{next_event, start};

const HOUR: Duration = Duration::from_secs(3600);

/// A cell with one simulated machine taking G05 streams.
fn g05_cell(protocol: &str, packet_n: Option<u8>, baud: u32, g05: &str, extra: &str) -> CellConfig {
    let n = packet_n
        .map(|n| format!("packet_n = {n}\n"))
        .unwrap_or_default();
    let text = format!(
        r#"
cell = "g05"
[bus]
listen = []
[[machines]]
name = "m1"
protocol = "{protocol}"
{n}{extra}
transport = {{ kind = "sim", line = {{ baud = {baud} }} }}
sim = {{ axes = 16, consume_rate = 4000 }}
[machines.g05]
{g05}
"#
    );
    CellConfig::from_toml_str(&text, "g05 cell").unwrap_or_else(|e| panic!("{e}"))
}

/// Deterministic travels within ±`range`, never all zero.
struct Path {
    x: u64,
    axes: usize,
    range: i32,
    /// Every 50th block carries a significant auxiliary value (an M code).
    aux: bool,
    n: u32,
}

impl Path {
    fn block(&mut self) -> BlockIn {
        self.n += 1;
        let aux = (self.aux && self.n % 50 == 0).then(|| AuxWord::significant(self.n / 50));
        let travels = (0..self.axes)
            .map(|i| {
                self.x = self
                    .x
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1);
                let v = ((self.x >> 33) % (2 * self.range as u64 + 1)) as i32 - self.range;
                if i == 0 && v == 0 { 1 } else { v }
            })
            .collect();
        BlockIn { travels, aux }
    }
}

/// How the producer sends.
#[derive(Clone, Copy)]
enum Producer {
    /// As many blocks as the credits allow, as soon as they allow.
    Eager,
    /// Bursts and pauses up to half the credit window (§6 of the G05 issue).
    Jittery,
    /// The priming level first, then at once every block the credits allow, so that the DAT
    /// after the one carrying the `G05` block is a full one.
    PrimeThenEager,
}

struct Outcome {
    stats: cellgate_core::sim::cnc::G05Stats,
    figures: cellgate_core::fanuc::g05::stream::StreamFigures,
    sums: Vec<i64>,
}

/// Streams `blocks` blocks to machine m1 of `config` and waits for the stream to end.
async fn stream(config: &CellConfig, blocks: u64, producer: Producer) -> Outcome {
    stream_from(config, blocks, producer, false).await
}

/// [`stream`], opened once the link is ready or, with `standing`, once the CNC has been
/// waiting for data a while (its board asking with GTD and getting WAT).
async fn stream_from(
    config: &CellConfig,
    blocks: u64,
    producer: Producer,
    standing: bool,
) -> Outcome {
    let (cell, token) = start(config).await;
    let m = cell.machine("m1").unwrap();
    let board = m.board.as_ref().unwrap();
    let mut events = m.link.subscribe();
    next_event(&mut events, HOUR, |ev| {
        matches!(
            ev,
            LinkEvent::State {
                state: LinkState::Ready
            }
        )
        .then_some(())
    })
    .await;
    if standing {
        board.wait_for(|s| s.reading).await;
        tokio::time::sleep(Duration::from_secs(3)).await;
    }
    let g = m.config.g05.clone().unwrap();
    let desk = G05Desk::new(&m.config, m.link.clone(), token.child_token());
    desk.allow_slow_line();
    let (handle, opened) = desk.open(Some("test".into())).await.unwrap();
    assert_eq!(opened.window, g.window_blocks());
    let axes = usize::from(g.format.axes);
    let range = match g.format.data_format {
        cellgate_core::fanuc::g05::DataFormat::Special => 8191,
        cellgate_core::fanuc::g05::DataFormat::General => 32767,
    };
    let mut path = Path {
        x: 7,
        axes,
        range,
        aux: g.format.aux.rax(),
        n: 0,
    };
    let mut sums = vec![0i64; axes];
    let mut seq = 0;
    let mut sent = 0u64;
    let mut jitter = 1u64;
    let window = u64::from(opened.window);
    while sent < blocks {
        let credits = u64::from(wait_credits(&handle, 1).await);
        let mut n = credits.min(blocks - sent);
        if let Producer::PrimeThenEager = producer
            && seq == 0
        {
            n = u64::from(opened.prime).min(blocks);
        }
        if let Producer::Jittery = producer {
            jitter = jitter
                .wrapping_mul(2_862_933_555_777_941_757)
                .wrapping_add(3);
            // A burst of up to the credits, then a pause of up to half the window's time.
            n = n.min(1 + (jitter >> 40) % credits.max(1));
            let pause = (jitter >> 20) % (window / 2 + 1) * u64::from(opened.unit_time_ms);
            tokio::time::sleep(Duration::from_millis(pause / 4)).await;
        }
        let batch: Vec<BlockIn> = (0..n).map(|_| path.block()).collect();
        for b in &batch {
            for (s, t) in sums.iter_mut().zip(&b.travels) {
                *s += i64::from(*t);
            }
        }
        sent += n;
        let r = handle
            .batch(Batch {
                seq,
                blocks: batch,
                end: sent == blocks,
            })
            .await;
        assert!(r.is_ok(), "batch {seq} refused: {r:?}");
        seq += 1;
    }
    let figures = wait_over(&handle).await;
    let snap = board
        .wait_for(|s| s.g05.as_ref().is_some_and(|g| g.end.is_some()))
        .await;
    token.cancel();
    cell.join().await;
    Outcome {
        stats: snap.g05.unwrap(),
        figures,
        sums,
    }
}

async fn wait_credits(handle: &StreamHandle, at_least: u32) -> u32 {
    let mut status = handle.status();
    tokio::time::timeout(HOUR, async {
        loop {
            let c = status.borrow_and_update().figures.credits;
            if c >= at_least {
                return c;
            }
            if status.changed().await.is_err() {
                panic!("the stream ended: {:?}", status.borrow().figures);
            }
        }
    })
    .await
    .expect("credits never came back")
}

async fn wait_over(handle: &StreamHandle) -> cellgate_core::fanuc::g05::stream::StreamFigures {
    let mut status = handle.status();
    tokio::time::timeout(HOUR, async {
        loop {
            let s = status.borrow_and_update().clone();
            if s.is_over() {
                return s.figures;
            }
            if status.changed().await.is_err() {
                return status.borrow().figures.clone();
            }
        }
    })
    .await
    .expect("the stream never ended")
}

fn assert_exact(o: &Outcome, blocks: u64) {
    assert_eq!(o.stats.end, Some(G05End::EndBlock), "{:?}", o.stats);
    assert_eq!(o.stats.blocks, blocks);
    assert_eq!(o.stats.travel, o.sums, "per-axis totals");
    assert_eq!(o.figures.state, StreamState::Completed, "{:?}", o.figures);
    assert_eq!(o.figures.received, blocks);
}

const BLOCKS: u64 = 100_000;

fn assert_no_underrun(o: &Outcome) {
    assert_eq!(o.stats.underruns, 0, "the CNC waited: {:?}", o.stats);
    assert_eq!(o.figures.underruns, 0, "the estimate: {:?}", o.figures);
}

/// 6 axes every 8 ms: 13-byte blocks, 17 875 baud required (§9.2); 19 200 is 1.07× that.
const SIX_AXES_8MS: &str = "axes = 6";
/// 14 axes and an M code every 4 ms: 33-byte blocks, 90 750 baud; 14 axes alone, 29-byte
/// blocks, 79 750 baud: 86 400 is 1.08× that.
const FOURTEEN_AXES_4MS: &str = "axes = 14\nunit_time_ms = 4";

#[tokio::test(start_paused = true)]
async fn protocol_a_takes_100_000_blocks_without_an_underrun() {
    let config = g05_cell("a", None, 19_200, SIX_AXES_8MS, "tx = 0\nti = 0");
    let o = stream(&config, BLOCKS, Producer::Eager).await;
    assert_exact(&o, BLOCKS);
    assert_no_underrun(&o);
}

#[tokio::test(start_paused = true)]
async fn expansion_a_takes_100_000_blocks_without_an_underrun() {
    let config = g05_cell(
        "expansion-a",
        Some(2),
        86_400,
        FOURTEEN_AXES_4MS,
        "tx = 0\nti = 0",
    );
    let o = stream(&config, BLOCKS, Producer::Eager).await;
    assert_exact(&o, BLOCKS);
    assert_no_underrun(&o);
}

#[tokio::test(start_paused = true)]
async fn protocol_b_takes_100_000_blocks_without_an_underrun() {
    let config = g05_cell("b", None, 19_200, "axes = 6\ndata_format = \"general\"", "");
    let o = stream(&config, BLOCKS, Producer::Jittery).await;
    assert_exact(&o, BLOCKS);
    assert_no_underrun(&o);
}

/// With an auxiliary word (M codes, high half first) on Expansion B.
#[tokio::test(start_paused = true)]
async fn expansion_b_takes_100_000_blocks_and_their_m_codes_without_an_underrun() {
    let config = g05_cell(
        "expansion-b",
        None,
        86_400,
        "axes = 12\nunit_time_ms = 4\naux = \"m\"",
        "",
    );
    let o = stream(&config, BLOCKS, Producer::Jittery).await;
    assert_exact(&o, BLOCKS);
    assert_no_underrun(&o);
    assert_eq!(o.stats.aux_count, BLOCKS / 50);
    assert_eq!(o.stats.aux.first(), Some(&1));
}

/// G05 opened on Protocol A while the CNC waits (§9.2): 6 axes every 4 ms, 13-byte blocks,
/// 35 750 baud required; 38 400 is 1.07× that. The board asks again at once after a WAT
/// (Tw = 0), so a GTD is waiting when the priming level is reached and the first DAT carries
/// it alone; the producer then tops the window up at once, so the next DAT is full. The board
/// uses a DAT only once all of it has arrived: the CNC starts with the blocks of the first
/// and needs the second whole before they run out. 500 ms of blocks (the `prime_ms` default)
/// followed by a full DAT of 1950 bytes (562 ms with its GTD) ran it dry; the priming in force
/// covers that, and the CNC and the estimate count no underrun.
#[tokio::test(start_paused = true)]
async fn protocol_a_from_a_waiting_cnc_never_runs_dry() {
    let config = g05_cell(
        "a",
        None,
        38_400,
        "axes = 6\nunit_time_ms = 4",
        "tx = 0\nti = 0\ntw = 0",
    );
    let m = &config.machines[0];
    let g = m.g05.as_ref().unwrap();
    assert!(g.prime_blocks_on(m.g05_refill()) > g.prime_blocks());
    assert_eq!(config.warnings(), Vec::<String>::new());
    let o = stream_from(&config, 20_000, Producer::PrimeThenEager, true).await;
    assert_exact(&o, 20_000);
    assert_no_underrun(&o);
}

/// 7 axes every 8 ms need 20 625 baud; at 19 200 (0.93×) the CNC waits, and the stream's
/// estimate says so rather than hiding it.
#[tokio::test(start_paused = true)]
async fn below_the_required_baud_underruns_are_counted_and_published() {
    let mut config = g05_cell("a", None, 19_200, SIX_AXES_8MS, "tx = 0\nti = 0");
    config.machines[0].g05.as_mut().unwrap().format.axes = 7;
    let o = stream(&config, 20_000, Producer::Eager).await;
    assert_exact(&o, 20_000);
    assert!(o.stats.underruns > 500, "{:?}", o.stats);
    // The estimate is within a fifth of what the CNC counted.
    let (est, real) = (o.figures.underruns as f64, o.stats.underruns as f64);
    assert!(
        (est - real).abs() < real / 5.0,
        "estimated {est}, counted {real}"
    );
}

/// Opens a stream on a Protocol B machine (6 axes, 8 ms) of a started cell.
async fn open_b() -> (
    cellgate::cell::Cell,
    tokio_util::sync::CancellationToken,
    std::sync::Arc<G05Desk>,
    StreamHandle,
) {
    let config = g05_cell("b", None, 19_200, SIX_AXES_8MS, "");
    let (cell, token) = start(&config).await;
    let m = cell.machine("m1").unwrap();
    let desk = G05Desk::new(&m.config, m.link.clone(), token.child_token());
    let (handle, _) = desk.open(None).await.unwrap();
    (cell, token, desk, handle)
}

fn simple(n: usize) -> Vec<BlockIn> {
    (0..n)
        .map(|i| BlockIn {
            travels: vec![1, 2, 3, 4, 5, i as i32 % 7 - 3],
            aux: None,
        })
        .collect()
}

async fn cnc_end(cell: &cellgate::cell::Cell) -> cellgate_core::sim::cnc::G05Stats {
    let board = cell.machine("m1").unwrap().board.as_ref().unwrap();
    let snap = tokio::time::timeout(
        HOUR,
        board.wait_for(|s| s.g05.as_ref().is_some_and(|g| g.end.is_some())),
    )
    .await
    .expect("the CNC never left binary mode");
    snap.g05.unwrap()
}

/// Bad batches are refused whole with an error that says what is wrong; the stream goes on,
/// and the CNC takes exactly the blocks accepted.
#[tokio::test(start_paused = true)]
async fn bad_batches_are_refused_whole_and_the_stream_goes_on() {
    let (cell, token, _desk, h) = open_b().await;
    let ok = |seq, n| Batch {
        seq,
        blocks: simple(n),
        end: false,
    };
    assert_eq!(h.batch(ok(0, 100)).await, Ok(Offered::Accepted));
    let mut far = ok(1, 3);
    far.blocks[2].travels[4] = 9000;
    let e = h.batch(far).await.unwrap_err();
    assert!(
        e.to_string().contains("block 103") && e.to_string().contains("axis 5"),
        "{e}"
    );
    let mut short = ok(1, 1);
    short.blocks[0].travels.pop();
    assert!(matches!(
        h.batch(short).await,
        Err(BatchError::Block { .. })
    ));
    let credits = h.status().borrow().figures.credits as usize;
    assert!(matches!(
        h.batch(ok(1, credits + 1)).await,
        Err(BatchError::Credits { .. })
    ));
    assert!(matches!(
        h.batch(ok(5, 1)).await,
        Err(BatchError::Gap {
            expected: 1,
            got: 5
        })
    ));
    assert_eq!(h.batch(ok(0, 100)).await, Ok(Offered::Repeat));
    let last = Batch {
        seq: 1,
        blocks: simple(50),
        end: true,
    };
    assert_eq!(h.batch(last).await, Ok(Offered::Accepted));
    let f = wait_over(&h).await;
    assert_eq!(
        (f.state, f.received, f.gaps, f.repeats, f.refused),
        (StreamState::Completed, 150, 1, 1, 3)
    );
    let g = cnc_end(&cell).await;
    assert_eq!((g.blocks, g.end), (150, Some(G05End::EndBlock)));
    token.cancel();
    cell.join().await;
}

/// A producer that goes away mid-stream (its liveliness token is gone), one that falls
/// silent while the CNC runs dry, and a cancel: each ends binary mode with the end block and
/// says why.
#[tokio::test(start_paused = true)]
async fn a_lost_silent_or_cancelled_producer_ends_binary_mode_cleanly() {
    for how in [
        Some(EndReason::ProducerLost),
        None,
        Some(EndReason::Cancelled),
    ] {
        let (cell, token, _desk, h) = open_b().await;
        // Enough to prime and stream a while.
        for seq in 0..4 {
            h.batch(Batch {
                seq,
                blocks: simple(100),
                end: false,
            })
            .await
            .unwrap();
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
        if let Some(reason) = how {
            h.end(reason).await.unwrap();
        }
        let f = wait_over(&h).await;
        let expected = how.unwrap_or(EndReason::ProducerIdle);
        assert_eq!(f.end_reason, Some(expected), "{f:?}");
        assert_eq!(f.state, StreamState::Completed, "{f:?}");
        let g = cnc_end(&cell).await;
        assert_eq!(
            (g.blocks, g.end),
            (400, Some(G05End::EndBlock)),
            "{expected:?}"
        );
        token.cancel();
        cell.join().await;
    }
}

/// One stream at a time per machine; a machine without a `g05` table takes none.
#[tokio::test(start_paused = true)]
async fn a_busy_or_unconfigured_machine_refuses_to_open() {
    let (cell, token, desk, h) = open_b().await;
    let e = desk.open(None).await.unwrap_err();
    assert!(e.to_string().contains(&h.id), "{e}");
    let m = cell.machine("m1").unwrap();
    let mut unconfigured = m.config.clone();
    unconfigured.g05 = None;
    let plain = G05Desk::new(&unconfigured, m.link.clone(), token.child_token());
    let e = plain.open(None).await.unwrap_err();
    assert!(e.to_string().contains("[machines.g05]"), "{e}");
    token.cancel();
    cell.join().await;
}
