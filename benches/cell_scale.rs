//! What the gateway itself costs, in real time (zenoh does not run under paused time):
//!
//! 1. DO latency: from a client's put of a `DoCommand` to the host engine receiving the SDO
//!    request (it then queues the SDO bytes as the answer to the board's next SAT or GTD; that
//!    wait, up to Tp, belongs to the protocol, not to the gateway). p50 and p99.
//! 2. CPU and memory per machine with 64 simulated machines running jobs at once, each through
//!    its own link, simulated line and simulated board, all in this one process.
//!
//! `cargo bench --bench cell_scale` prints the figures; under `cargo test` a short smoke run
//! (a few machines and puts) checks that the benchmark still works.

#[path = "../tests/common/mod.rs"]
mod common;

use std::time::{Duration, Instant};

use cellgate::bus::keys::{CellKeys, MachineLeaf};
use cellgate::bus::{self, MachineLink};
use cellgate::cell::Cell;
use cellgate::link::driver;
use cellgate::sim::BoardHandle;
use cellgate::transport::{LineError, LineSettings, ModemIn, ModemOut, sim};
use cellgate_core::config::CellConfig;
use cellgate_core::engine::Engine;
use cellgate_core::fanuc::host::{EngineCommand, HostEngine};
use cellgate_core::fanuc::message::Framing;
use cellgate_core::fanuc::protocol_a::{ProtocolAConfig, ProtocolAHost};
use cellgate_core::pb;
use cellgate_core::sim::fanuc_board::BoardConfig;
use prost::Message;
use tokio_util::sync::CancellationToken;

/// A host engine that notes when a DO request reaches it.
struct Timed {
    inner: ProtocolAHost,
    seen: tokio::sync::mpsc::UnboundedSender<(u8, Instant)>,
}

impl Engine for Timed {
    type Command = EngineCommand;
    type Event = cellgate_core::fanuc::host::EngineEvent;
    fn handle_input(&mut self, now: Instant, bytes: &[u8]) {
        self.inner.handle_input(now, bytes)
    }
    fn handle_line_error(&mut self, now: Instant, error: LineError) {
        self.inner.handle_line_error(now, error)
    }
    fn handle_modem(&mut self, now: Instant, modem: ModemIn) {
        self.inner.handle_modem(now, modem)
    }
    fn handle_command(&mut self, now: Instant, command: EngineCommand) {
        if let EngineCommand::SetDo(v) = command {
            let _ = self.seen.send((v, Instant::now()));
        }
        self.inner.handle_command(now, command)
    }
    fn handle_timeout(&mut self, now: Instant) {
        self.inner.handle_timeout(now)
    }
    fn poll_transmit(&mut self, now: Instant) -> Option<Vec<u8>> {
        self.inner.poll_transmit(now)
    }
    fn poll_event(&mut self) -> Option<Self::Event> {
        self.inner.poll_event()
    }
    fn poll_timeout(&self) -> Option<Instant> {
        self.inner.poll_timeout()
    }
    fn modem_out(&self) -> ModemOut {
        self.inner.modem_out()
    }
}

impl HostEngine for Timed {
    fn data_wanted(&self) -> usize {
        self.inner.data_wanted()
    }
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

async fn do_latency(puts: usize) {
    let port = common::bus::free_port();
    let text = format!(
        "cell = \"bench\"\n[bus]\nlisten = [\"tcp/127.0.0.1:{port}\"]\n\
         [[machines]]\nname = \"m1\"\nprotocol = \"a\"\ntransport = {{ kind = \"sim\", line = {{ baud = 19200 }} }}\n"
    );
    let config = CellConfig::from_toml_str(&text, "bench").expect("bench cell");
    let machine = config.machines[0].clone();
    let line = LineSettings::with_baud(19_200);
    let (host, device, _control) = sim::line(line);
    let board = BoardHandle::spawn(
        BoardConfig {
            autostart: true,
            ..BoardConfig::default()
        },
        device,
    )
    .expect("board");
    let (seen_tx, mut seen_rx) = tokio::sync::mpsc::unbounded_channel();
    let engine = Timed {
        inner: ProtocolAHost::new(
            ProtocolAConfig {
                framing: Framing::default(),
                char_time: line.char_time(),
                ..ProtocolAConfig::default()
            },
            cellgate::link::pump::now(),
        )
        .expect("engine"),
        seen: seen_tx,
    };
    let stop = CancellationToken::new();
    let (link, task) = driver::spawn("m1", engine, host, stop.clone());
    let gateway = bus::open(&config.bus).await.expect("gateway session");
    let routes_stop = CancellationToken::new();
    let served = {
        let (gw, cfg, rs) = (gateway.clone(), config.clone(), routes_stop.clone());
        let machines = vec![MachineLink {
            config: machine,
            link,
            sim: None,
        }];
        tokio::spawn(async move { bus::serve(&gw, &cfg, machines, rs).await })
    };
    let client = bus::open(&common::bus::client_config(port))
        .await
        .expect("client session");
    let keys = CellKeys::new(&config.bus.prefix, &config.cell).expect("keys");
    common::bus::wait_token(&client, &keys.machine("m1"), true).await;
    let do_key = keys.leaf("m1", MachineLeaf::Do);
    let publisher = client
        .declare_publisher(do_key)
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .expect("publisher");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut latencies = Vec::with_capacity(puts);
    for i in 0..puts {
        let value = (i % 256) as u8;
        let payload = pb::DoCommand {
            value: u32::from(value),
            mask: None,
        }
        .encode_to_vec();
        let sent = Instant::now();
        publisher.put(payload).await.expect("put");
        let (got, at) = tokio::time::timeout(Duration::from_secs(5), seen_rx.recv())
            .await
            .expect("the engine got the DO request in time")
            .expect("the engine is running");
        assert_eq!(got, value);
        latencies.push(at - sent);
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    latencies.sort();
    println!(
        "DO put → engine: {} puts, p50 {:.3} ms, p99 {:.3} ms, max {:.3} ms",
        puts,
        percentile(&latencies, 0.50).as_secs_f64() * 1e3,
        percentile(&latencies, 0.99).as_secs_f64() * 1e3,
        latencies.last().copied().unwrap_or_default().as_secs_f64() * 1e3
    );
    publisher.undeclare().await.expect("undeclare");
    routes_stop.cancel();
    let _ = served.await;
    stop.cancel();
    let _ = task.await;
    let _ = board.shutdown().await;
    client.close().await.expect("close client");
    gateway.close().await.expect("close gateway");
}

/// CPU seconds (user + system) this process has used.
fn cpu_seconds() -> f64 {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: getrusage writes a rusage into the pointer it is given.
    let usage = unsafe {
        libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr());
        usage.assume_init()
    };
    let t = |tv: libc::timeval| tv.tv_sec as f64 + tv.tv_usec as f64 / 1e6;
    t(usage.ru_utime) + t(usage.ru_stime)
}

/// (resident now, peak resident) in KiB, from /proc/self/status.
fn memory_kib() -> (u64, u64) {
    common::memory_kib("self")
}

async fn scale(machines: usize, program_size: usize) {
    let port = common::bus::free_port();
    let dir = tempfile::tempdir().expect("tempdir");
    let mut text = format!(
        "cell = \"scale\"\n[bus]\nlisten = [\"tcp/127.0.0.1:{port}\"]\n[programs]\ndir = {:?}\n",
        dir.path().join("programs")
    );
    for i in 0..machines {
        let (protocol, n) = if i % 2 == 0 {
            ("a", "")
        } else {
            ("expansion-a", "packet_n = 1\n")
        };
        text.push_str(&format!(
            "[[machines]]\nname = \"m{i}\"\nprotocol = \"{protocol}\"\ntp = 1\ntw = 1\n{n}\
             transport = {{ kind = \"sim\", line = {{ baud = 19200 }} }}\nsim = {{ consume_rate = 100000 }}\n"
        ));
    }
    let config = CellConfig::from_toml_str(&text, "scale").expect("scale cell");
    let (rss_before, _) = memory_kib();
    let gateway = bus::open(&config.bus).await.expect("gateway session");
    let links_stop = CancellationToken::new();
    let cell = Cell::start(&config, &links_stop).await.expect("cell");
    let links = cell.machine_links();
    let routes_stop = CancellationToken::new();
    let served = {
        let (gw, cfg, rs) = (gateway.clone(), config.clone(), routes_stop.clone());
        tokio::spawn(async move { bus::serve(&gw, &cfg, links, rs).await })
    };
    let client = bus::open(&common::bus::client_config(port))
        .await
        .expect("client session");
    let keys = CellKeys::new(&config.bus.prefix, &config.cell).expect("keys");
    for m in &cell.machines {
        common::bus::wait_token(&client, &keys.machine(&m.config.name), true).await;
    }
    let cpu_start = cpu_seconds();
    let wall = Instant::now();
    let mut events = Vec::new();
    for m in &cell.machines {
        events.push(m.link.subscribe());
        let request = pb::JobRequest {
            program: Some(pb::job_request::Program::Inline(common::nc_program(
                program_size,
                events.len() as u32,
            ))),
            name: String::new(),
            priority: 0,
            append_eor: false,
            ..Default::default()
        };
        let accepted: pb::JobAccepted = common::bus::get_one(
            &client,
            &keys.leaf(&m.config.name, MachineLeaf::Submit),
            Some(request.encode_to_vec()),
        )
        .await;
        assert!(!accepted.job_id.is_empty());
    }
    let mut peak = 0;
    for rx in &mut events {
        common::next_event(rx, Duration::from_secs(600), |ev| match ev {
            driver::LinkEvent::JobDone { .. } => Some(()),
            driver::LinkEvent::JobFailed { reason, .. } => panic!("job failed: {reason}"),
            _ => None,
        })
        .await;
        peak = peak.max(memory_kib().1);
    }
    let secs = wall.elapsed().as_secs_f64();
    let cpu = cpu_seconds() - cpu_start;
    let (rss_after, hwm) = memory_kib();
    let n = machines as f64;
    println!(
        "{machines} machines, one {} KiB job each at 19200 baud, all done in {secs:.1} s:",
        program_size / 1024
    );
    println!(
        "  CPU {cpu:.2} s = {:.1} % of one core, {:.2} % of a core per machine",
        100.0 * cpu / secs,
        100.0 * cpu / secs / n
    );
    println!(
        "  memory: resident {:.1} MiB before the cell, {:.1} MiB after, peak {:.1} MiB; {:.0} KiB per machine",
        rss_before as f64 / 1024.0,
        rss_after as f64 / 1024.0,
        hwm.max(peak) as f64 / 1024.0,
        (hwm.max(peak).saturating_sub(rss_before)) as f64 / n
    );
    routes_stop.cancel();
    let _ = served.await;
    links_stop.cancel();
    cell.join().await;
    client.close().await.expect("close client");
    gateway.close().await.expect("close gateway");
}

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("tokio runtime");
    rt.block_on(async {
        if full {
            do_latency(1000).await;
            scale(64, 32 * 1024).await;
        } else {
            do_latency(20).await;
            scale(4, 4 * 1024).await;
        }
    });
}
