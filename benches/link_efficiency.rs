//! Link efficiency of the FANUC protocols over the simulated line, in virtual time:
//!
//!   efficiency = NC bytes delivered ÷ (seconds × characters per second of the line)
//!
//! beside the protocol's own upper bound (framing overhead only, no turnaround time).
//! The CNC reads faster than any line here, so the line and the protocol are the only limits.
//!
//! `cargo bench --bench link_efficiency` prints the table; under `cargo test` a short smoke
//! run checks that the benchmark still works.

#[path = "../tests/common/mod.rs"]
mod common;

use std::time::Duration;

use cellgate::fanuc::message::MAX_DAT_DATA;
use cellgate::fanuc::packet;
use cellgate::fanuc::sat::Params;
use cellgate::link::driver::LinkEvent;
use cellgate::transport::LineSettings;

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

/// Runs one program through a one-machine simulated cell; returns (bytes, virtual seconds).
async fn measure(case: &Case, size: usize) -> (u64, f64) {
    let config = common::sim_cell(case.protocol, case.packet_n, case.baud, 10_000_000);
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
    token.cancel();
    cell.join().await;
    let secs = (end - started.unwrap_or(end)).as_secs_f64();
    (bytes, secs)
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
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .start_paused(true)
        .build()
        .expect("tokio runtime");
    println!(
        "link efficiency, {} KiB program, simulated line 8N2 (11 bits a character), virtual time",
        size / 1024
    );
    println!(
        "{:<16} {:>6} {:>10} {:>10} {:>11} {:>12}",
        "protocol", "baud", "bytes", "seconds", "efficiency", "upper bound"
    );
    for case in &cases {
        let wall = std::time::Instant::now();
        let (bytes, secs) = rt.block_on(measure(case, size));
        let cps = LineSettings::with_baud(case.baud).chars_per_sec();
        let efficiency = bytes as f64 / (secs * cps);
        println!(
            "{:<16} {:>6} {:>10} {:>10.1} {:>10.1}% {:>11.1}%   ({:.2} s wall)",
            case.label(),
            case.baud,
            bytes,
            secs,
            100.0 * efficiency,
            100.0 * case.upper_bound(),
            wall.elapsed().as_secs_f64()
        );
    }
}
