//! G05 streams against the line rate, in virtual time, with a producer whose batches jitter:
//! underruns the simulated CNC counted, the stream's own estimate, and the fewest blocks the
//! CNC had in its buffer, at 0.95×, 1.0×, 1.05× and 1.2× the §9.2 requirement, for 3 axes at
//! T = 2 ms and 8 ms, through Protocol A, Expansion A, B and Expansion B, over two virtual
//! minutes each; and Protocol A opened while the CNC already waits for data, the producer's
//! first batch exactly the priming level (the board takes a DAT only whole, §9.2). Everything
//! runs in virtual time, so the figures do not depend on the machine or the build profile
//! (`cargo bench --profile dev` gives the same table).
//!
//! `cargo bench --bench g05_stream` prints the table; under `cargo test` a short smoke run
//! checks that the benchmark still works.

#[path = "../tests/common/mod.rs"]
mod common;

use std::time::Duration;

use cellgate::link::g05::G05Desk;
use cellgate_core::config::{CellConfig, TransportConfig};
use cellgate_core::fanuc::g05::G05Format;
use cellgate_core::fanuc::g05::stream::{Batch, BlockIn};

struct Row {
    label: String,
    ratio: f64,
    t_ms: u32,
    blocks: u64,
    cnc_underruns: u64,
    estimated: u64,
    min_buffered: Option<u64>,
    /// How the CNC left binary input, and how the stream ended on the gateway's side.
    end: String,
}

/// One stream of `millis` virtual milliseconds at `ratio` × the required baud; with `waiting`,
/// opened once the CNC has been waiting for data a while, the first batch the priming level.
async fn run(
    protocol: &str,
    packet_n: Option<u8>,
    t_ms: u32,
    ratio: f64,
    millis: u64,
    waiting: bool,
) -> Row {
    let format = {
        let mut f = G05Format::new(3);
        f.unit_time_ms = cellgate_core::fanuc::g05::UnitTime::from_ms(t_ms).expect("a unit time");
        f
    };
    let required = cellgate_core::fanuc::g05::required_baud(&format, 11.0);
    let baud = (f64::from(required) * ratio).round() as u32;
    let n = packet_n
        .map(|n| format!("packet_n = {n}\n"))
        .unwrap_or_default();
    // Written at a rate the cell file takes, then set to the one measured: the file refuses
    // a line below §9.2's requirement and rates the CNC's parameters do not offer.
    let text = format!(
        "cell = \"bench\"\n[bus]\nlisten = []\n[[machines]]\nname = \"m1\"\nprotocol = \
         \"{protocol}\"\n{n}tx = 0\nti = 0\ntransport = {{ kind = \"sim\", line = {{ baud = 86400 \
         }} }}\n[machines.g05]\naxes = 3\nunit_time_ms = {t_ms}\n"
    );
    let text = match protocol {
        // Protocol B runs at 19200 baud at most (§2.2).
        "b" => text
            .replace("tx = 0\nti = 0\n", "")
            .replace("baud = 86400", "baud = 19200"),
        "expansion-b" => text.replace("tx = 0\nti = 0\n", ""),
        _ => text,
    };
    // A waiting CNC's board asks again at once after a WAT (Tw = 0), so that a GTD is
    // waiting when the priming level is reached and the first DAT carries only it.
    let text = if waiting {
        text.replace("tx = 0\n", "tx = 0\ntw = 0\n")
    } else {
        text
    };
    let mut config = CellConfig::from_toml_str(&text, "bench").unwrap_or_else(|e| panic!("{e}"));
    if let TransportConfig::Sim { line } = &mut config.machines[0].transport {
        line.baud = baud;
    }
    let (cell, token) = common::start(&config).await;
    let m = cell.machine("m1").unwrap();
    if waiting {
        m.board.as_ref().unwrap().wait_for(|s| s.reading).await;
        tokio::time::sleep(Duration::from_secs(3)).await;
    }
    let desk = G05Desk::new(&m.config, m.link.clone(), token.child_token());
    desk.allow_slow_line();
    let (handle, opened) = desk.open(None).await.unwrap();
    let blocks = millis / u64::from(t_ms);
    let window = u64::from(opened.window);
    let mut status = handle.status();
    let (mut sent, mut seq, mut x) = (0u64, 0u64, 12345u64);
    while sent < blocks {
        let credits = loop {
            let c = u64::from(status.borrow_and_update().figures.credits);
            if c > 0 {
                break c;
            }
            if status.changed().await.is_err() {
                break 0;
            }
        };
        if credits == 0 {
            break;
        }
        x = x
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1442695040888963407);
        // The producer tops the window up at irregular moments: a pause of up to a quarter of
        // the window's time (at most 500 ms, well inside the stream's idle limit), then every
        // block the credits allow. The blocks in the window cover the pause, so the CNC
        // starves only if the line cannot carry them in time.
        let pause = ((x >> 13) % (window / 4 + 1) * u64::from(t_ms)).min(500);
        // From a waiting CNC: the priming level first, then at once every block the credits
        // allow, so that the DAT after the first is a full one.
        let first = waiting && seq == 0;
        if !(waiting && seq <= 1) {
            tokio::time::sleep(Duration::from_millis(pause)).await;
        }
        let credits = u64::from(status.borrow_and_update().figures.credits).max(credits);
        let burst = if first {
            u64::from(opened.prime).min(blocks)
        } else {
            credits.min(blocks - sent)
        };
        let batch: Vec<BlockIn> = (0..burst)
            .map(|i| BlockIn {
                travels: vec![1 + (i % 3) as i32, -2, 3],
                aux: None,
            })
            .collect();
        sent += burst;
        handle
            .batch(Batch {
                seq,
                blocks: batch,
                end: sent == blocks,
            })
            .await
            .unwrap();
        seq += 1;
    }
    let (figures, ending) = loop {
        let s = status.borrow_and_update().clone();
        if s.is_over() || status.changed().await.is_err() {
            let s = status.borrow().clone();
            let ending = format!(
                "{:?}{}",
                s.figures.state,
                s.figures
                    .end_reason
                    .map(|r| format!(": {r}"))
                    .unwrap_or_default()
            );
            break (s.figures.clone(), ending);
        }
    };
    let board = m.board.as_ref().unwrap();
    let g05 = board
        .wait_for(|s| s.g05.as_ref().is_some_and(|g| g.end.is_some()))
        .await
        .g05
        .unwrap();
    token.cancel();
    cell.join().await;
    let label = match packet_n {
        Some(n) => format!("{protocol} n={n}"),
        None if waiting => format!("{protocol} CNC waiting"),
        None => protocol.to_string(),
    };
    Row {
        label,
        ratio,
        t_ms,
        blocks: g05.blocks,
        cnc_underruns: g05.underruns,
        estimated: figures.underruns,
        min_buffered: g05.min_buffered_blocks,
        end: format!("{} / {}", g05.end.map_or("-", |e| e.name()), ending),
    }
}

fn virtual_time(millis: u64, ratios: &[f64], times: &[u32]) {
    println!(
        "G05 streams, 3 axes, jittery producer, {} virtual s each (§9.2 requirement: 38 500 baud \
         at T = 2 ms, 9 625 at 8 ms)",
        millis / 1000
    );
    println!(
        "{:<16} {:>5} {:>5} {:>8} {:>10} {:>10} {:>11}  end (CNC / stream)",
        "protocol", "T ms", "×req", "blocks", "underruns", "estimated", "min buffer"
    );
    for &t in times {
        for &ratio in ratios {
            for (protocol, n, waiting) in [
                ("a", None, false),
                ("a", None, true),
                ("expansion-a", Some(2), false),
                ("b", None, false),
                ("expansion-b", None, false),
            ] {
                let format = {
                    let mut f = G05Format::new(3);
                    f.unit_time_ms =
                        cellgate_core::fanuc::g05::UnitTime::from_ms(t).expect("a unit time");
                    f
                };
                let needed =
                    f64::from(cellgate_core::fanuc::g05::required_baud(&format, 11.0)) * ratio;
                if protocol == "b" && needed > 19_200.0 {
                    // Protocol B runs at 19200 baud at most (§2.2): no line is fast enough.
                    println!(
                        "{protocol:<16} {t:>5} {ratio:>5.2}  needs {needed:.0} baud; Protocol B stops at 19200"
                    );
                    continue;
                }
                let rt = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .start_paused(true)
                    .build()
                    .expect("tokio runtime");
                let r = rt.block_on(run(protocol, n, t, ratio, millis, waiting));
                println!(
                    "{:<16} {:>5} {:>5.2} {:>8} {:>10} {:>10} {:>11}  {}",
                    r.label,
                    r.t_ms,
                    r.ratio,
                    r.blocks,
                    r.cnc_underruns,
                    r.estimated,
                    r.min_buffered
                        .map_or_else(|| "-".to_string(), |b| b.to_string()),
                    r.end
                );
            }
        }
    }
}

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    if full {
        virtual_time(120_000, &[0.95, 1.0, 1.05, 1.2], &[2, 8]);
    } else {
        virtual_time(5_000, &[1.2], &[8]);
    }
}
