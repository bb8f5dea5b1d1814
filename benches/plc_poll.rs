//! Tag polling on one RS-485 line against the line-time floor, in virtual time.
//!
//! One FFU120B line in mode 3 at 19200 baud (8 data bits, odd parity, 1 stop bit: 11 bits a
//! character), 31 stations with 10 tags each, the simulated MICREX-F on a simulated line paced
//! at the baud rate (`transport::sim`), the gateway's PLC link task (`plc::link`) polling it.
//! Each station's tags fall into two poll groups:
//!
//! - `fast`: D0 u16, D1 i16, D2–D3 u32, D4 BCD, D5 u16, M0 bits 0 and 1 — two reads a station
//!   (D0–D5 and M0);
//! - `slow`: W9 (32-bit BCD area) 0 BCD, 1 u32, 2 i32 — one read a station.
//!
//! Three runs: each group alone polled as fast as the line allows (poll_ms 10, far below a
//! round's line time; the other group at one hour, so it reads once at the start), then all
//! ten tags of each station in one group. For each, from [`PlcEvent::PollDone`], the achieved
//! round interval (mean and worst over the measured rounds) against the line-time floor: the
//! bytes one round puts on the wire (every read's request and reply frame, as the master and
//! the module encode them) ÷ the line rate. The ratio floor ÷ achieved has a target of ≥ 90 %.
//! The bytes the simulated line carried per round are printed too, as a check of the floor's
//! byte count.
//!
//! The floor is line time only. The module's own time between a request and its reply (the
//! simulator's `processing_delay`, 5 ms by default; the manual gives no figure) is spent once
//! per read on a half-duplex line that carries one request at a time, so the table is printed
//! twice: with the default delay, and with a module that answers at once, which leaves what
//! the master, the link task and the 1 ms tokio timer cost on their own. The column
//! `ratio+mod` counts the module's time into the floor.
//!
//! Everything runs in paused tokio time, so the figures do not depend on the build profile or
//! the machine: `cargo bench --profile dev --bench plc_poll` prints the same table as a release
//! build. Under `cargo test` (no `--bench` argument) a short smoke run (3 stations, 3 rounds)
//! checks that the benchmark still works.

use std::time::Duration;

use cellgate::plc::TagTable;
use cellgate::plc::link::{PlcEvent, spawn};
use cellgate::sim::micrex_handle::MicrexHandle;
use cellgate::transport::LineSettings;
use cellgate::transport::sim::Dir;
use cellgate_core::config::{Real, TagConfig, TagType};
use cellgate_core::fuji::command::{Module, Request};
use cellgate_core::fuji::frame::{BccKind, FrameSettings};
use cellgate_core::fuji::master::{Master, MasterSettings, OperationMode};
use cellgate_core::sim::micrex::MicrexConfig;
use tokio_util::sync::CancellationToken;

/// As fast as the line allows: far below the line time of any round here.
const SATURATE_MS: u32 = 10;
/// A group that is not being measured: read once at the start, then not for an hour.
const IDLE_MS: u32 = 3_600_000;
/// Rounds left out at the start (the first round of each group, with the idle group's read).
const WARM_UP: usize = 2;

fn line() -> LineSettings {
    LineSettings {
        baud: 19200,
        data_bits: cellgate::transport::DataBits::Eight,
        parity: cellgate::transport::Parity::Odd,
        stop_bits: cellgate::transport::StopBits::One,
        ..LineSettings::default()
    }
}

fn frame() -> FrameSettings {
    // The module's initial framing (`:`, CR, code transposition) with a BCC (add, Set 1).
    FrameSettings {
        bcc: BccKind::Set1,
        ..FrameSettings::default()
    }
}

fn tag(station: u8, name: &str, module: Module, address: u16, kind: TagType) -> TagConfig {
    TagConfig {
        name: format!("s{station}-{name}"),
        station,
        module,
        address,
        kind,
        bit: None,
        scale: Real(1.0),
        poll_ms: SATURATE_MS,
        deadband: Real(0.0),
        writable: false,
        history: false,
        mtconnect: None,
    }
}

/// The ten tags of a station, with the poll intervals of the `fast` and `slow` groups.
fn station_tags(station: u8, fast_ms: u32, slow_ms: u32) -> Vec<TagConfig> {
    let mut fast = vec![
        tag(station, "count", Module::D, 0, TagType::U16),
        tag(station, "offset", Module::D, 1, TagType::I16),
        tag(station, "total", Module::D, 2, TagType::U32),
        tag(station, "recipe", Module::D, 4, TagType::Bcd),
        tag(station, "speed", Module::D, 5, TagType::U16),
        tag(station, "door", Module::M, 0, TagType::Bit),
        tag(station, "clamp", Module::M, 0, TagType::Bit),
    ];
    fast[5].bit = Some(0);
    fast[6].bit = Some(1);
    let slow = vec![
        tag(station, "timer", Module::W9, 0, TagType::Bcd),
        tag(station, "energy", Module::W9, 1, TagType::U32),
        tag(station, "drift", Module::W9, 2, TagType::I32),
    ];
    fast.iter_mut().for_each(|t| t.poll_ms = fast_ms);
    let mut slow = slow;
    slow.iter_mut().for_each(|t| t.poll_ms = slow_ms);
    fast.into_iter().chain(slow).collect()
}

struct Row {
    label: &'static str,
    reads: usize,
    rounds: usize,
    floor_bytes: usize,
    line_bytes: f64,
    floor: Duration,
    mean: Duration,
    worst: Duration,
}

/// Line bytes of one read: the request as the master frames it, the reply as the module does
/// (address, count, ATTR and the data: BYTEN = 5 + N, FFU120B notes 2).
fn read_bytes(
    frame: &FrameSettings,
    station: u8,
    module: Module,
    address: u16,
    words: u16,
) -> usize {
    let request = Request::read_words(module, address, usize::from(words))
        .and_then(|r| r.encode(station))
        .expect("a read the table allows");
    let reply_text = 10 + usize::from(words) * module.word_bytes();
    frame.encode(&request).len() + frame.line_len(reply_text)
}

/// Polls `stations` stations until `rounds` rounds of the measured group are done after the
/// warm-up. `fast_ms`/`slow_ms` set the two groups; `measure` is the interval of the group
/// measured (the groups are ordered by interval in the poll plan).
async fn run(
    label: &'static str,
    stations: u8,
    fast_ms: u32,
    slow_ms: u32,
    measure: u32,
    rounds: usize,
    delay: Duration,
) -> Row {
    let line = line();
    let frame = frame();
    let numbers: Vec<u8> = (1..=stations).collect();
    let mut mc = MicrexConfig::new(OperationMode::Three);
    mc.line = line;
    mc.frame = frame.clone();
    mc.stations = numbers.clone();
    mc.processing_delay = delay;
    let (host, device, sim_line) = cellgate::transport::sim::line(line);
    let sim = MicrexHandle::spawn(mc, Vec::new(), device).expect("a valid simulated module");
    let mut ms = MasterSettings::new(OperationMode::Three);
    ms.line = line;
    ms.frame = frame.clone();
    ms.reply_timeout = Duration::from_millis(200);
    ms.queue_limit = 1024;
    let tags: Vec<TagConfig> = numbers
        .iter()
        .flat_map(|&s| station_tags(s, fast_ms, slow_ms))
        .collect();
    let table = TagTable::new("bench", &tags);
    let group = table
        .groups()
        .iter()
        .position(|g| g.interval == Duration::from_millis(u64::from(measure)))
        .expect("the measured group exists");
    let plan = &table.groups()[group];
    let reads = plan.reads.len();
    let floor_bytes: usize = plan
        .reads
        .iter()
        .map(|r| read_bytes(&frame, r.station, r.module, r.address, r.words))
        .sum();
    let stop = CancellationToken::new();
    let (plc, task) = spawn(
        "bench",
        Master::new(ms).expect("valid master settings"),
        table,
        host,
        stop.clone(),
    );
    let mut events = plc.subscribe();
    let mut starts = Vec::new();
    let mut bytes_at = Vec::new();
    while starts.len() < WARM_UP + rounds + 1 {
        match events.recv().await {
            Ok(PlcEvent::PollDone { group: g, started }) if g == group => {
                starts.push(started);
                let on_wire = sim_line.counters(Dir::HostToDevice).written
                    + sim_line.counters(Dir::DeviceToHost).written;
                bytes_at.push(on_wire);
            }
            Ok(PlcEvent::Stopped { error }) => panic!("the PLC link stopped: {error:?}"),
            Ok(_) => {}
            Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
            Err(e) => panic!("PLC events: {e}"),
        }
    }
    let snapshot = plc.snapshot().await.expect("a running link");
    for (n, st) in &snapshot.counters.stations {
        assert!(st.up && st.timeouts == 0, "station {n}: {st:?}");
    }
    stop.cancel();
    let _ = task.await;
    sim.shutdown().await;
    // `started` of round k+1 minus that of round k is round k's interval; the bytes counted
    // at the end of consecutive rounds differ by one round's bytes.
    let measured = &starts[WARM_UP..];
    let gaps: Vec<Duration> = measured.windows(2).map(|w| w[1] - w[0]).collect();
    let mean = gaps.iter().sum::<Duration>() / gaps.len() as u32;
    let worst = gaps.iter().copied().max().unwrap_or_default();
    let b = &bytes_at[WARM_UP..];
    let line_bytes = (b[b.len() - 1] - b[0]) as f64 / (b.len() - 1) as f64;
    Row {
        label,
        reads,
        rounds: gaps.len(),
        floor_bytes,
        line_bytes,
        floor: line.time_for_chars(floor_bytes as u64),
        mean,
        worst,
    }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}

fn bench(stations: u8, rounds: usize, delay: Duration) -> Vec<Row> {
    let l = line();
    println!(
        "PLC tag polling: one RS-485 line (mode 3), {} baud, {} bits a character ({:.1} characters/s), \
         {stations} stations × 10 tags, BCC add Set 1, the simulated module answering {} ms after a \
         request, {rounds} rounds measured after {WARM_UP}",
        l.baud,
        l.bits_per_char(),
        l.chars_per_sec(),
        ms(delay),
    );
    println!(
        "{:<22} {:>5} {:>11} {:>11} {:>9} {:>9} {:>9} {:>7} {:>9} {:>8}",
        "group",
        "reads",
        "bytes/round",
        "line bytes",
        "floor ms",
        "mean ms",
        "worst ms",
        "ratio",
        "module ms",
        "ratio+mod"
    );
    let runs: [(&'static str, u32, u32, u32); 3] = [
        ("fast (7 tags/station)", SATURATE_MS, IDLE_MS, SATURATE_MS),
        ("slow (3 tags/station)", IDLE_MS, SATURATE_MS, SATURATE_MS),
        ("all 10 tags/station", SATURATE_MS, SATURATE_MS, SATURATE_MS),
    ];
    let mut rows = Vec::new();
    for (label, fast, slow, measure) in runs {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .start_paused(true)
            .build()
            .expect("tokio runtime");
        let r = rt.block_on(run(label, stations, fast, slow, measure, rounds, delay));
        // The module's own time (its processing delay once per read) is no line time: the
        // second ratio counts it in, and what is left is the master's and the link's.
        let module = delay * r.reads as u32;
        println!(
            "{:<22} {:>5} {:>11} {:>11.0} {:>9.1} {:>9.1} {:>9.1} {:>6.1}% {:>9.1} {:>7.1}%",
            r.label,
            r.reads,
            r.floor_bytes,
            r.line_bytes,
            ms(r.floor),
            ms(r.mean),
            ms(r.worst),
            100.0 * r.floor.as_secs_f64() / r.mean.as_secs_f64(),
            ms(module),
            100.0 * (r.floor + module).as_secs_f64() / r.mean.as_secs_f64(),
        );
        rows.push(r);
    }
    println!(
        "ratio = floor ÷ mean achieved interval (target ≥ 90 %); ratio+mod = (floor + module ms) ÷ mean"
    );
    rows
}

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    // The simulator's default processing delay, then a module that answers at once: what the
    // master, the link task and the timer cost on their own.
    let default_delay = MicrexConfig::new(OperationMode::Three).processing_delay;
    if full {
        bench(31, 20, default_delay);
        println!();
        bench(31, 20, Duration::ZERO);
    } else {
        let rows = bench(3, 3, default_delay);
        // The smoke run checks the measurement, not the speed: the simulated line carried
        // exactly the bytes the floor counts, and rounds were measured.
        for r in rows {
            assert!(r.rounds >= 2);
            assert!(
                (r.line_bytes - r.floor_bytes as f64).abs() < 0.5,
                "{}: the line carried {} bytes a round, the floor counts {}",
                r.label,
                r.line_bytes,
                r.floor_bytes
            );
        }
    }
}
