//! Link efficiency of the FANUC protocols over the simulated line, in virtual time:
//!
//!   efficiency = NC bytes delivered ÷ (seconds × characters per second of the line)
//!
//! beside the protocol's own upper bound (framing overhead only, no turnaround time).
//! The CNC reads faster than any line here, so the line and the protocol are the only limits.
//!
//! A second table runs Protocol B and Expansion B with the CNC reading at half the line's
//! rate, so that the board stops and resumes the host with DC3 / DC1 all the way through: it
//! shows the cycles, the most characters the board received after one DC3 against its
//! allowance (§6.3, §7), and the SR0856 overruns (there must be none).
//!
//! `cargo bench --bench link_efficiency` prints the tables; under `cargo test` a short smoke
//! run checks that the benchmark still works.

#[path = "../tests/common/mod.rs"]
mod common;

use std::time::Duration;

use cellgate::link::driver::LinkEvent;
use cellgate::transport::LineSettings;
use cellgate_core::fanuc::message::MAX_DAT_DATA;
use cellgate_core::fanuc::packet;
use cellgate_core::fanuc::sat::Params;

struct Case {
    protocol: &'static str,
    packet_n: Option<u8>,
    baud: u32,
}

impl Case {
    fn label(&self) -> String {
        match self.packet_n {
            Some(n) => format!("{} n={n}", self.protocol),
            None => self.protocol.to_string(),
        }
    }

    /// Data ÷ characters on the line when nothing but framing costs time.
    fn upper_bound(&self) -> f64 {
        if self.protocol.ends_with('b') {
            // Protocol B sends nothing but the data part (§8.1).
            return 1.0;
        }
        match self.packet_n {
            // One data packet: packet no + 256·n data + 2 checksum + CR (§5.2).
            Some(n) => {
                let d = packet::data_len(n) as f64;
                d / (packet::packet_len(n) as f64)
            }
            // One GTD (6 characters) and one DAT of L data bytes (L + 6), where L is the
            // longest DAT the board's free space allows: min(4096, Nb − No) (§4.5 note 1).
            None => {
                let p = Params::POWER_ON;
                let l = (MAX_DAT_DATA as f64).min(f64::from(p.nb - p.no));
                l / (l + 12.0)
            }
        }
    }
}

/// What one run measured.
struct Run {
    bytes: u64,
    /// Virtual seconds from the first NC byte to the job's end (Protocol B family: to the
    /// CNC having read the whole program).
    secs: f64,
    /// The board's flow control (Protocol B family).
    dc3: u64,
    dc1: u64,
    max_overrun: usize,
    overruns: u64,
}

/// Runs one program through a one-machine simulated cell whose CNC reads `consume_rate`
/// bytes a second.
async fn measure(case: &Case, size: usize, consume_rate: u32) -> Run {
    let config = common::sim_cell(case.protocol, case.packet_n, case.baud, consume_rate);
    let (cell, token) = common::start(&config).await;
    let m = cell.machine("m1").expect("machine m1");
    let mut events = m.link.subscribe();
    let program = common::nc_program(size, 1);
    common::queue(&m.link, 1, program).await;
    let mut started = None;
    let (bytes, end) = common::next_event(&mut events, Duration::from_secs(24 * 3600), |ev| {
        match ev {
            // Time counts from the first NC byte on the line, so link start-up is left out.
            LinkEvent::Progress { .. } if started.is_none() => {
                started = Some(tokio::time::Instant::now());
                None
            }
            LinkEvent::JobDone { bytes, .. } => Some((*bytes, tokio::time::Instant::now())),
            LinkEvent::JobFailed { reason, .. } => panic!("{}: job failed: {reason}", case.label()),
            _ => None,
        }
    })
    .await;
    let board = m.board.as_ref().expect("a simulated board");
    // A Protocol B host is done once it has handed out the EOR, which may still be on its
    // way: count until the CNC has read the whole program.
    let (board, end) = if case.protocol.ends_with('b') {
        let snap = board.wait_for(|s| !s.programs.is_empty()).await;
        (snap, tokio::time::Instant::now())
    } else {
        (board.snapshot(), end)
    };
    token.cancel();
    cell.join().await;
    Run {
        bytes,
        secs: (end - started.unwrap_or(end)).as_secs_f64(),
        dc3: board.dc3_sent,
        dc1: board.dc1_sent,
        max_overrun: board.max_overrun,
        overruns: board.overruns,
    }
}

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let size = if full { 1 << 20 } else { 32 * 1024 };
    let mut cases = Vec::new();
    for baud in [19_200, 86_400] {
        cases.push(Case {
            protocol: "a",
            packet_n: None,
            baud,
        });
        for n in [1, 2, 4] {
            cases.push(Case {
                protocol: "expansion-a",
                packet_n: Some(n),
                baud,
            });
        }
    }
    // Protocol B runs at 19200 baud at most (§6.3); Expansion B up to 86400.
    let b_cases: Vec<Case> = [
        ("b", 4_800),
        ("b", 19_200),
        ("expansion-b", 4_800),
        ("expansion-b", 19_200),
        ("expansion-b", 86_400),
    ]
    .into_iter()
    .map(|(protocol, baud)| Case {
        protocol,
        packet_n: None,
        baud,
    })
    .collect();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .start_paused(true)
        .build()
        .expect("tokio runtime");
    println!(
        "link efficiency, {} KiB program, simulated line 8N2 (11 bits a character), virtual time",
        size / 1024
    );
    println!("CNC reading faster than the line:");
    println!(
        "{:<16} {:>6} {:>10} {:>10} {:>11} {:>12}",
        "protocol", "baud", "bytes", "seconds", "efficiency", "upper bound"
    );
    for case in cases.iter().chain(&b_cases) {
        let wall = std::time::Instant::now();
        let run = rt.block_on(measure(case, size, 10_000_000));
        let cps = LineSettings::with_baud(case.baud).chars_per_sec();
        let efficiency = run.bytes as f64 / (run.secs * cps);
        println!(
            "{:<16} {:>6} {:>10} {:>10.1} {:>10.1}% {:>11.1}%   ({:.2} s wall)",
            case.label(),
            case.baud,
            run.bytes,
            run.secs,
            100.0 * efficiency,
            100.0 * case.upper_bound(),
            wall.elapsed().as_secs_f64()
        );
    }
    println!();
    println!("Protocol B family, CNC reading at half the line's rate (DC3/DC1 flow control):");
    println!(
        "{:<16} {:>6} {:>10} {:>10} {:>9} {:>9} {:>9} {:>13} {:>7}",
        "protocol", "baud", "bytes", "seconds", "of CNC", "DC3", "DC1", "max overrun", "SR0856"
    );
    for case in &b_cases {
        let cps = LineSettings::with_baud(case.baud).chars_per_sec();
        let rate = (cps / 2.0) as u32;
        let wall = std::time::Instant::now();
        let run = rt.block_on(measure(case, size, rate));
        let allowance = if case.protocol == "b" { 512 } else { 1280 };
        println!(
            "{:<16} {:>6} {:>10} {:>10.1} {:>8.1}% {:>9} {:>9} {:>7} / {:<4} {:>7}   ({:.2} s wall)",
            case.label(),
            case.baud,
            run.bytes,
            run.secs,
            100.0 * run.bytes as f64 / (run.secs * f64::from(rate)),
            run.dc3,
            run.dc1,
            run.max_overrun,
            allowance,
            run.overruns,
            wall.elapsed().as_secs_f64()
        );
        assert_eq!(
            run.overruns,
            0,
            "{}: the host overran the board",
            case.label()
        );
    }
}
