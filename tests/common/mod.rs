//! Shared set-up for tests that run a simulated cell.
#![allow(dead_code)]

pub mod bus;
pub mod cli;
pub mod device_server;
pub mod pki;
pub mod postgres;

use std::time::Duration;

use cellgate::cell::Cell;
use cellgate::link::driver::{LinkEvent, LinkHandle};
use cellgate_core::config::CellConfig;
use tokio::sync::broadcast;
use tokio_util::sync::CancellationToken;

/// A plain-text NC program of about `size` bytes: tape-start `%`, an O number, numbered G01
/// blocks ending in LF, M30, and the EOR `%`. Deterministic for a given `seed`.
pub fn nc_program(size: usize, seed: u32) -> Vec<u8> {
    let mut p = format!("%\nO{:04}\n", seed % 10_000).into_bytes();
    let mut n: u32 = 1;
    let mut x = seed;
    while p.len() + 40 < size {
        x = x.wrapping_mul(1_103_515_245).wrapping_add(12_345);
        let line = format!(
            "N{n} G01 X{}.{:03} Y-{}.{:03} F{}\n",
            x % 500,
            (x >> 8) % 1000,
            (x >> 4) % 300,
            (x >> 12) % 1000,
            100 + x % 4000
        );
        p.extend_from_slice(line.as_bytes());
        n += 1;
    }
    p.extend_from_slice(b"M30\n%");
    p
}

/// A one-machine cell file with a simulated board on a simulated line.
pub fn sim_cell(protocol: &str, packet_n: Option<u8>, baud: u32, consume_rate: u32) -> CellConfig {
    let n = packet_n
        .map(|n| format!("packet_n = {n}\n"))
        .unwrap_or_default();
    let text = format!(
        r#"
cell = "test"
[bus]
listen = []
[[machines]]
name = "m1"
protocol = "{protocol}"
{n}transport = {{ kind = "sim", line = {{ baud = {baud} }} }}
sim = {{ consume_rate = {consume_rate} }}
"#
    );
    match CellConfig::from_toml_str(&text, "test cell") {
        Ok(c) => c,
        Err(e) => panic!("test cell file is invalid:\n{e}"),
    }
}

/// Starts the cell's links; the token stops them.
pub async fn start(config: &CellConfig) -> (Cell, CancellationToken) {
    let token = CancellationToken::new();
    let cell = Cell::start(config, &token).await.expect("cell starts");
    (cell, token)
}

/// Waits (in virtual time when paused) for the first event `pick` accepts.
pub async fn next_event<T>(
    events: &mut cellgate::link::fanout::Receiver<LinkEvent>,
    within: Duration,
    mut pick: impl FnMut(&LinkEvent) -> Option<T>,
) -> T {
    let found = tokio::time::timeout(within, async {
        loop {
            match events.recv().await {
                Ok(ev) => {
                    if let Some(v) = pick(&ev) {
                        return v;
                    }
                }
                Err(broadcast::error::RecvError::Lagged(n)) => {
                    panic!("test fell {n} link events behind")
                }
                Err(broadcast::error::RecvError::Closed) => panic!("link stopped"),
            }
        }
    })
    .await;
    match found {
        Ok(v) => v,
        Err(_) => panic!("no matching link event within {within:?}"),
    }
}

/// Queues `program` as job `id` on `link`.
pub async fn queue(link: &LinkHandle, id: u64, program: Vec<u8>) {
    let size = program.len() as u64;
    link.send(cellgate::link::driver::LinkCommand::Queue(
        cellgate::link::driver::ProgramJob {
            id,
            name: format!("job-{id}"),
            size: Some(size),
            source: cellgate::link::driver::JobSource::program(std::io::Cursor::new(program)),
            progress_interval: None,
        },
    ))
    .await
    .expect("link accepts the job");
}

/// (VmRSS, VmHWM) in KiB of process `pid` ("self" for this one), from /proc/PID/status.
pub fn memory_kib(pid: &str) -> (u64, u64) {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}
