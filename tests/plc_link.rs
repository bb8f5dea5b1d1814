//! The PLC link task against the simulated MICREX-F, in paused time (no zenoh).

use std::time::Duration;

use cellgate::config::{Real, TagConfig, TagType};
use cellgate::fuji::command::{Module, Request};
use cellgate::fuji::master::{Master, MasterError, MasterSettings, OperationMode};
use cellgate::plc::TagTable;
use cellgate::plc::link::{PlcEvent, spawn};
use cellgate::sim::micrex::{MicrexCommand, MicrexConfig};
use cellgate::sim::micrex_handle::MicrexHandle;
use cellgate::transport::LineSettings;
use tokio_util::sync::CancellationToken;

fn tag(name: &str, station: u8, address: u16) -> TagConfig {
    TagConfig {
        name: name.to_string(),
        station,
        module: Module::D,
        address,
        kind: TagType::U16,
        bit: None,
        scale: Real(1.0),
        poll_ms: 500,
        deadband: Real(0.0),
        writable: false,
    }
}

#[tokio::test(start_paused = true)]
async fn a_silent_station_does_not_stop_the_live_ones_and_a_bad_bcc_is_retried() {
    let line = LineSettings {
        baud: 19200,
        ..LineSettings::default()
    };
    let stations = vec![1, 2, 3, 4];
    let mut mc = MicrexConfig::new(OperationMode::Three);
    mc.line = line;
    mc.stations = stations.clone();
    // A BCC on both ends (add, Set 1, §4-3 items 20–23), so a spoilt reply is a BCC error.
    mc.frame.bcc = cellgate::fuji::frame::BccKind::Set1;
    let mc_frame = mc.frame.clone();
    let (host, device, _control) = cellgate::transport::sim::line(line);
    let sim = MicrexHandle::spawn(mc, Vec::new(), device).unwrap();
    sim.command(MicrexCommand::SetSilent {
        station: 4,
        on: true,
    });
    let mut ms = MasterSettings::new(OperationMode::Three);
    ms.line = line;
    ms.frame = mc_frame.clone();
    ms.reply_timeout = Duration::from_millis(200);
    ms.probe_interval = Duration::from_secs(5);
    ms.queue_limit = 256;
    let tags: Vec<TagConfig> = stations
        .iter()
        .map(|&s| tag(&format!("t{s}"), s, 0))
        .collect();
    let stop = CancellationToken::new();
    let (plc, _task) = spawn(
        "plc",
        Master::new(ms).unwrap(),
        TagTable::new("plc", &tags),
        host,
        stop.clone(),
    );
    let mut events = plc.subscribe();
    let mut rounds = Vec::new();
    let start = tokio::time::Instant::now();
    while rounds.len() < 40 {
        if let Ok(PlcEvent::PollDone { started, .. }) = events.recv().await {
            rounds.push(started);
        }
    }
    let gaps: Vec<f64> = rounds
        .windows(2)
        .map(|w| (w[1] - w[0]).as_secs_f64() * 1000.0)
        .collect();
    // After the silent station is marked down, rounds keep their 500 ms interval.
    let late = &gaps[10..];
    let mean = late.iter().sum::<f64>() / late.len() as f64;
    let max = late.iter().cloned().fold(0.0, f64::max);
    println!(
        "3 live + 1 silent station, poll 500 ms: mean round interval {mean:.1} ms, max {max:.1} ms over {} rounds ({:.1} s)",
        late.len(),
        (tokio::time::Instant::now() - start).as_secs_f64()
    );
    assert!(max < 600.0, "rounds slowed down: {gaps:?}");
    let snap = plc.snapshot().await.unwrap();
    assert!(!snap.counters.stations[&4].up);
    for s in 1..=3 {
        assert!(snap.counters.stations[&s].up);
        assert!(snap.counters.stations[&s].replies >= 39);
    }

    // A corrupted BCC is retried and counted.
    sim.command(MicrexCommand::CorruptNextBcc { station: 2 });
    let r = plc
        .request(2, Request::read_words(Module::D, 0, 1).unwrap())
        .await
        .unwrap();
    assert!(r.is_ok(), "{r:?}");
    let snap = plc.snapshot().await.unwrap();
    let st = &snap.counters.stations[&2];
    assert!(st.retries >= 1, "{st:?}");
    assert_eq!(st.bcc_errors, 1, "{st:?}");

    // STA codes come back typed: interlock (22) and over memory size (32).
    sim.command(MicrexCommand::SetInterlock {
        station: 1,
        on: true,
    });
    let r = plc
        .request(1, Request::read_words(Module::D, 0, 1).unwrap())
        .await
        .unwrap();
    assert!(matches!(&r, Err(MasterError::Sta(e)) if e.sta.code() == 0x22));
    let r = plc
        .request(3, Request::read_words(Module::D, 65535, 1).unwrap())
        .await
        .unwrap();
    assert!(
        matches!(&r, Err(MasterError::Sta(e)) if e.sta.code() == 0x32),
        "{r:?}"
    );
    stop.cancel();
}
