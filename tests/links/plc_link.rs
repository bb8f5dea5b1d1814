//! The PLC link task against the simulated MICREX-F, in paused time (no zenoh).

use std::time::Duration;

use cellgate::plc::TagTable;
use cellgate::plc::link::{PlcEvent, spawn};
use cellgate::sim::micrex_handle::MicrexHandle;
use cellgate::transport::LineSettings;
use cellgate_core::config::{Real, TagConfig, TagType};
use cellgate_core::fuji::command::{Module, Reply, Request};
use cellgate_core::fuji::master::{Master, MasterError, MasterSettings, OperationMode};
use cellgate_core::sim::micrex::{MicrexCommand, MicrexConfig, MicrexEvent};
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
        history: false,
        mtconnect: None,
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
    mc.frame.bcc = cellgate_core::fuji::frame::BccKind::Set1;
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
    // The group's round times as the link measured them (PlcStatus.poll_groups).
    let g = &snap.groups[0];
    println!(
        "poll group: {} rounds, last {:?}, mean {:?}, max {:?}, achieved interval {:?}, {} overruns",
        g.rounds, g.last_round, g.mean_round, g.max_round, g.achieved_interval, g.overruns
    );
    assert_eq!((g.interval, g.reads), (Duration::from_millis(500), 4));
    assert!(g.rounds >= 40, "{g:?}");
    assert_eq!(g.achieved_interval, Duration::from_millis(500), "{g:?}");
    // The first round waits out the silent station's time-out and retries (200 ms each)
    // until the station is marked down: it overruns the interval; none after it does.
    assert!(g.max_round > Duration::from_millis(500), "{g:?}");
    assert_eq!(g.overruns, 1, "{g:?}");
    assert!(g.last_round < Duration::from_millis(200), "{g:?}");
    assert!(
        g.mean_round > Duration::ZERO && g.mean_round < g.max_round,
        "{g:?}"
    );
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

/// Mode 5 (non-procedure, RS-485, FFU120B §5-5): the gateway is the module's external device.
/// A message the gateway sends reaches the module's receive message number; the messages the
/// PLC sends come out as events, in order; one spoilt on the line fails its BCC and is dropped
/// and counted (receive error 5), and the next one still arrives. With the manual's BCC (add,
/// Set 1).
#[tokio::test(start_paused = true)]
async fn mode_5_messages_both_ways_and_a_spoilt_one_is_dropped() {
    let line = LineSettings {
        baud: 9600,
        ..LineSettings::default()
    };
    let mut mc = MicrexConfig::new(OperationMode::Five);
    mc.line = line;
    mc.frame.bcc = cellgate_core::fuji::frame::BccKind::Set1;
    mc.receive_message = 7;
    let frame = mc.frame.clone();
    let (host, device, control) = cellgate::transport::sim::line(line);
    let (sim, mut sim_events) = MicrexHandle::spawn_subscribed(mc, Vec::new(), device).unwrap();
    let mut ms = MasterSettings::new(OperationMode::Five);
    ms.line = line;
    ms.frame = frame;
    let stop = CancellationToken::new();
    let (plc, _task) = spawn(
        "plc",
        Master::new(ms).unwrap(),
        TagTable::new("plc", &[]),
        host,
        stop.clone(),
    );
    let mut events = plc.subscribe();
    let r = plc.send_message(b"LOT 4711".to_vec()).await.unwrap();
    // ':' + 16 hex characters + 2 BCC characters + CR.
    assert_eq!(r, Ok(Reply::Sent { bytes: 20 }));
    let got = tokio::time::timeout(Duration::from_secs(5), async {
        loop {
            if let Ok(MicrexEvent::TransferReceived { message, data, .. }) = sim_events.recv().await
            {
                return (message, data);
            }
        }
    })
    .await
    .expect("the module received the message");
    assert_eq!(got, (7, b"LOT 4711".to_vec()));

    let mut received = Vec::new();
    for data in [b"FIRST".to_vec(), b"SECOND".to_vec(), b"THIRD".to_vec()] {
        if data == b"SECOND" {
            // Its second character (the first of the text) is hit on the line: ':' goes
            // through, '5' arrives as '4'.
            let dir = cellgate::transport::sim::End::Device.tx();
            control.corrupt_next(dir, 0);
            control.corrupt_next(dir, 0x01);
        }
        sim.command(MicrexCommand::QueueTransfer { message: 0, data });
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    while received.len() < 2 {
        match tokio::time::timeout(Duration::from_secs(10), events.recv()).await {
            Ok(Ok(PlcEvent::Message { data, .. })) => received.push(data),
            Ok(Ok(_)) => {}
            other => panic!("no message from the PLC: {other:?}"),
        }
    }
    assert_eq!(received, [b"FIRST".to_vec(), b"THIRD".to_vec()]);
    let c = plc.snapshot().await.unwrap().counters;
    assert_eq!((c.messages_sent, c.messages_received), (1, 2));
    assert_eq!(c.receive_errors.bcc, 1, "{:?}", c.receive_errors);
    // The command set is refused in mode 5.
    let r = plc
        .request(0, Request::read_words(Module::D, 0, 1).unwrap())
        .await
        .unwrap();
    assert!(matches!(&r, Err(MasterError::Refused(_))), "{r:?}");
    stop.cancel();
}

/// Mode 4, fixed length 6 with transposition (12 characters a message), on a 7E1 line whose
/// UART makes and checks parity, as a serial port's does: a character that arrives with a
/// parity error, reported by the driver, ends its message as a receive error (FFU120B §5-6)
/// and keeps its place, so the next message still arrives whole; both ways.
#[tokio::test(start_paused = true)]
async fn a_parity_error_drops_its_message_and_the_next_one_arrives() {
    use cellgate::transport::{DataBits, Parity, StopBits};
    let line = LineSettings {
        baud: 9600,
        data_bits: DataBits::Seven,
        parity: Parity::Even,
        stop_bits: StopBits::One,
        ..LineSettings::default()
    };
    let mut mc = MicrexConfig::new(OperationMode::Four);
    mc.line = line;
    mc.fixed_length = Some(6);
    mc.receive_message = 7;
    let frame = mc.frame.clone();
    let (host, device, control) = cellgate::transport::sim::line(line);
    let (sim, mut sim_events) = MicrexHandle::spawn_subscribed(mc, Vec::new(), device).unwrap();
    let mut ms = MasterSettings::new(OperationMode::Four);
    ms.line = line;
    ms.frame = frame;
    ms.fixed_length = Some(6);
    let stop = CancellationToken::new();
    let (plc, _task) = spawn(
        "plc",
        Master::new(ms).unwrap(),
        TagTable::new("plc", &[]),
        host,
        stop.clone(),
    );
    let mut events = plc.subscribe();
    let to_device = cellgate::transport::sim::End::Host.tx();
    let from_device = cellgate::transport::sim::End::Device.tx();
    let mut received = Vec::new();
    for data in [b"FIRST!", b"SECOND", b"THIRD!"] {
        if data == b"SECOND" {
            // Its first character arrives with a parity error (not delivered): the eleven
            // after it are no message, and the next message starts after them.
            control.error_next(to_device, cellgate::transport::LineError::Parity);
            control.error_next(from_device, cellgate::transport::LineError::Parity);
        }
        sim.command(MicrexCommand::QueueTransfer {
            message: 0,
            data: data.to_vec(),
        });
        let r = plc.send_message(data.to_vec()).await.unwrap();
        assert_eq!(r, Ok(Reply::Sent { bytes: 12 }));
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    while received.len() < 2 {
        match tokio::time::timeout(Duration::from_secs(10), events.recv()).await {
            Ok(Ok(PlcEvent::Message { data, .. })) => received.push(data),
            Ok(Ok(_)) => {}
            other => panic!("no message from the PLC: {other:?}"),
        }
    }
    assert_eq!(received, [b"FIRST!".to_vec(), b"THIRD!".to_vec()]);
    let c = plc.snapshot().await.unwrap().counters;
    assert_eq!(c.messages_received, 2);
    assert_eq!(
        (c.receive_errors.character, c.receive_errors.total()),
        (1, 1),
        "{:?}",
        c.receive_errors
    );
    assert_eq!(c.line_errors.parity, 1);
    // The module stored the first and the third of the gateway's messages.
    let mut stored = Vec::new();
    while let Ok(e) = sim_events.try_recv() {
        if let MicrexEvent::TransferReceived {
            message: 7, data, ..
        } = e
        {
            stored.push(data);
        }
    }
    assert_eq!(stored, [b"FIRST!".to_vec(), b"THIRD!".to_vec()]);
    stop.cancel();
}

/// A confirmed tag write is the tag's value at once: a get right after it answers what was
/// written, not the value of the last poll, and the change is published.
#[tokio::test(start_paused = true)]
async fn a_tag_reads_what_was_written_right_after_the_write() {
    let line = LineSettings {
        baud: 19200,
        ..LineSettings::default()
    };
    let mut mc = MicrexConfig::new(OperationMode::One);
    mc.line = line;
    mc.stations = vec![0];
    let frame = mc.frame.clone();
    let (host, device, _control) = cellgate::transport::sim::line(line);
    let _sim = MicrexHandle::spawn(mc, Vec::new(), device).unwrap();
    let mut ms = MasterSettings::new(OperationMode::One);
    ms.line = line;
    ms.frame = frame;
    let mut recipe = tag("recipe", 0, 1);
    recipe.writable = true;
    // A slow poll: the next round is far away when the get comes.
    recipe.poll_ms = 10_000;
    let stop = CancellationToken::new();
    let (plc, _task) = spawn(
        "plc",
        Master::new(ms).unwrap(),
        TagTable::new("plc", &[recipe]),
        host,
        stop.clone(),
    );
    let mut events = plc.subscribe();
    // The first round reads 0.
    loop {
        if let Ok(PlcEvent::Tag(v)) = events.recv().await {
            assert_eq!(v.value, Some(0.0));
            break;
        }
    }
    plc.write_tag("recipe", 42.0).await.unwrap().unwrap();
    let v = plc.get_tag("recipe").await.unwrap().unwrap();
    assert_eq!(v.value, Some(42.0), "{v:?}");
    assert_eq!(v.raw, Some(42));
    let published = loop {
        if let Ok(PlcEvent::Tag(v)) = events.recv().await {
            break v;
        }
    };
    assert_eq!(published.value, Some(42.0));
    stop.cancel();
}
