use super::agent::{Agent, Update};
use super::buffer::{SequenceBuffer, Value};
use super::desc::{CellDesc, MachineDesc, PlcDesc, TagDesc};
use super::model::uuid_for;
use super::request::{ErrorCode, Format, PathFilter, Query, Request};
use crate::fanuc::Protocol;
use crate::pb;

fn cell() -> CellDesc {
    CellDesc {
        cell: "demo".into(),
        machines: vec![
            MachineDesc {
                name: "mill-1".into(),
                protocol: Protocol::A,
                part_counter: Some(("plc-1".into(), "parts".into())),
                g05: false,
                identification: Default::default(),
            },
            MachineDesc {
                name: "lathe-1".into(),
                protocol: Protocol::B,
                part_counter: None,
                g05: false,
                identification: Default::default(),
            },
        ],
        plcs: vec![PlcDesc {
            name: "plc-1".into(),
            stations: vec![0],
            tags: vec![
                TagDesc {
                    name: "parts".into(),
                    native: "D0".into(),
                    typed: None,
                    units: None,
                },
                TagDesc {
                    name: "oil-temp".into(),
                    native: "D1".into(),
                    typed: super::types::tag_type("TEMPERATURE"),
                    units: Some("CELSIUS"),
                },
            ],
        }],
    }
}

fn agent() -> Agent {
    let mut a = Agent::new("test", 7, 1024, 1_000_000);
    a.add_cell(&cell(), 1_000_000);
    a.update("demo", Update::Gateway(true), 1_000_001);
    a
}

fn status(machine: &str, state: pb::LinkState) -> pb::MachineStatus {
    pb::MachineStatus {
        machine: machine.into(),
        protocol: pb::Protocol::A as i32,
        link_state: state as i32,
        ..Default::default()
    }
}

fn current_value(a: &Agent, id: &str) -> Value {
    let i = a.model().item_by_id(id).unwrap();
    a.buffer().state(i).unwrap().last.clone().unwrap().value
}

#[test]
fn sequence_numbers_have_no_gaps_and_the_ring_is_bounded() {
    let mut b = SequenceBuffer::new(4);
    for n in 0..10u32 {
        let seq = b.push(n % 3, 1, Value::Text(n.to_string().into()));
        assert_eq!(seq, u64::from(n) + 1);
    }
    assert_eq!((b.first(), b.last(), b.next()), (7, 10, 11));
    let (obs, next) = b.sample(7, 100, |_| true);
    let seqs: Vec<u64> = obs.iter().map(|o| o.seq).collect();
    assert_eq!(seqs, [7, 8, 9, 10]);
    assert_eq!(next, 11);
    assert!(
        b.check_from(6).is_err(),
        "evicted observations are out of range"
    );
    assert!(b.check_from(12).is_err());
    assert!(b.check_at(11).is_err());
}

#[test]
fn at_gives_the_state_as_of_an_evicted_history() {
    let mut b = SequenceBuffer::new(3);
    b.push(0, 1, Value::Text("a".into())); // 1
    b.push(1, 1, Value::Text("x".into())); // 2
    b.push(0, 1, Value::Text("b".into())); // 3
    b.push(0, 1, Value::Text("c".into())); // 4: evicts 1
    b.push(1, 1, Value::Text("y".into())); // 5: evicts 2
    // As of 3, item 1 is still "x" though its observation left the ring.
    let s = b.state_at(3);
    assert_eq!(s[0].last.as_ref().unwrap().value, Value::Text("b".into()));
    assert_eq!(s[1].last.as_ref().unwrap().value, Value::Text("x".into()));
}

#[test]
fn sample_count_stops_and_tells_where_to_go_on() {
    let mut b = SequenceBuffer::new(100);
    for n in 0..10 {
        b.push(n % 2, 1, Value::Unavailable);
    }
    let (obs, next) = b.sample(1, 2, |i| i == 1);
    assert_eq!(obs.iter().map(|o| o.seq).collect::<Vec<_>>(), [2, 4]);
    assert_eq!(next, 5);
    let (obs, next) = b.sample(1, -3, |_| true);
    assert_eq!(obs.iter().map(|o| o.seq).collect::<Vec<_>>(), [8, 9, 10]);
    assert_eq!(next, 11);
    assert!(b.check_count(0).is_err());
    assert!(b.check_count(101).is_err());
    assert!(
        b.check_count(i64::MIN).is_err(),
        "no overflow on the most negative count"
    );
}

#[test]
fn uuids_are_stable_and_of_version_8() {
    let a = uuid_for("machine demo/mill-1");
    assert_eq!(a, uuid_for("machine demo/mill-1"));
    assert_ne!(a, uuid_for("machine demo/mill-2"));
    assert_eq!(a.len(), 36);
    assert_eq!(&a[14..15], "8");
    let a2 = agent();
    let b2 = agent();
    assert_eq!(a2.model().devices[1].uuid, b2.model().devices[1].uuid);
}

#[test]
fn devices_are_named_as_in_the_cell_file_and_a_second_cell_is_qualified() {
    let mut a = agent();
    let names: Vec<&str> = a.model().devices.iter().map(|d| d.name.as_str()).collect();
    assert_eq!(names, ["Agent", "mill-1", "lathe-1", "plc-1"]);
    let mut other = cell();
    other.cell = "line-2".into();
    a.add_cell(&other, 2);
    assert!(a.model().device_named("line-2.mill-1").is_some());
}

#[test]
fn execution_follows_the_link_and_the_job() {
    let mut a = agent();
    assert_eq!(current_value(&a, "mill-1_execution"), Value::Unavailable);
    a.update(
        "demo",
        Update::Status(Box::new(status("mill-1", pb::LinkState::Idle))),
        2,
    );
    assert_eq!(
        current_value(&a, "mill-1_execution"),
        Value::Text("READY".into())
    );
    assert_eq!(
        current_value(&a, "mill-1_avail"),
        Value::Text("AVAILABLE".into())
    );
    let started = pb::JobEvent {
        job_id: "mill-1-1-1".into(),
        machine: "mill-1".into(),
        origin: Some(pb::JobOrigin {
            program: Some(pb::ProgramRef {
                library: "O1234.nc".into(),
                ..Default::default()
            }),
            name: "ignored".into(),
            ..Default::default()
        }),
        kind: Some(pb::job_event::Kind::Started(Default::default())),
        ..Default::default()
    };
    a.update("demo", Update::Job(started), 3);
    a.update(
        "demo",
        Update::Status(Box::new(status("mill-1", pb::LinkState::Sending))),
        4,
    );
    assert_eq!(
        current_value(&a, "mill-1_execution"),
        Value::Text("ACTIVE".into())
    );
    assert_eq!(
        current_value(&a, "mill-1_program"),
        Value::Text("O1234.nc".into())
    );
    // The block being fed: none before the first progress that names one.
    assert_eq!(current_value(&a, "mill-1_block_fed"), Value::Unavailable);
    let progress = |block: &str| pb::JobEvent {
        job_id: "mill-1-1-1".into(),
        machine: "mill-1".into(),
        kind: Some(pb::job_event::Kind::Progress(pb::job_event::Progress {
            block: block.into(),
            ..Default::default()
        })),
        ..Default::default()
    };
    a.update("demo", Update::Job(progress("N20 G01 X25. F150")), 4);
    a.update("demo", Update::Job(progress("")), 4);
    assert_eq!(
        current_value(&a, "mill-1_block_fed"),
        Value::Text("N20 G01 X25. F150".into())
    );
    let done = pb::JobEvent {
        job_id: "mill-1-1-1".into(),
        machine: "mill-1".into(),
        kind: Some(pb::job_event::Kind::Completed(Default::default())),
        ..Default::default()
    };
    a.update("demo", Update::Job(done), 5);
    a.update(
        "demo",
        Update::Status(Box::new(status("mill-1", pb::LinkState::Idle))),
        6,
    );
    assert_eq!(
        current_value(&a, "mill-1_execution"),
        Value::Text("PROGRAM_COMPLETED".into())
    );
    // A reset ends it: READY, and READY still once the CNC operates again.
    let mut reset = status("mill-1", pb::LinkState::Idle);
    reset.sat = Some(pb::Sat {
        buffer_status: pb::BufferStatus::Reset as i32,
        ..Default::default()
    });
    a.update("demo", Update::Status(Box::new(reset.clone())), 7);
    assert_eq!(
        current_value(&a, "mill-1_execution"),
        Value::Text("READY".into())
    );
    reset.sat.as_mut().unwrap().buffer_status = pb::BufferStatus::Operating as i32;
    a.update("demo", Update::Status(Box::new(reset)), 8);
    assert_eq!(
        current_value(&a, "mill-1_execution"),
        Value::Text("READY".into())
    );
    a.update("demo", Update::Gateway(false), 9);
    assert_eq!(current_value(&a, "mill-1_execution"), Value::Unavailable);
    assert_eq!(
        current_value(&a, "mill-1_avail"),
        Value::Text("UNAVAILABLE".into())
    );
}

#[test]
fn a_cnc_alarm_is_a_fault_with_a_native_code_that_a_reset_clears() {
    let mut a = agent();
    let mut s = status("lathe-1", pb::LinkState::Alarm);
    s.protocol = pb::Protocol::B as i32;
    s.last_alarm = Some(pb::AlarmEvent {
        machine: "lathe-1".into(),
        kind: pb::AlarmKind::CncAlarm as i32,
        message: "the CNC raised an alarm (NAK; §6.4)".into(),
        ..Default::default()
    });
    a.update("demo", Update::Status(Box::new(s.clone())), 2);
    let i = a.model().item_by_id("lathe-1_system").unwrap();
    let shown = a.buffer().state(i).unwrap().shown();
    assert_eq!(shown.len(), 1);
    let doc = a.current(None, &Query::default(), 3).unwrap();
    assert!(doc.contains("nativeCode=\"CG-NAK\""), "{doc}");
    assert!(doc.contains("<Fault"), "{doc}");
    s.link_state = pb::LinkState::Idle as i32;
    a.update("demo", Update::Status(Box::new(s)), 4);
    let doc = a.current(None, &Query::default(), 5).unwrap();
    assert!(!doc.contains("<Fault"), "{doc}");
}

#[test]
fn a_sat_in_alarm_status_is_a_system_fault_with_the_gateways_code_not_a_link_fault() {
    let mut a = agent();
    let mut s = status("mill-1", pb::LinkState::Alarm);
    s.last_alarm = Some(pb::AlarmEvent {
        machine: "mill-1".into(),
        kind: pb::AlarmKind::CncAlarm as i32,
        message: "remote buffer in alarm status: NC alarm (SAT byte 3 = 0, §4.4.2 1)".into(),
        code: "CG-SAT-NC".into(),
        ..Default::default()
    });
    a.update("demo", Update::Status(Box::new(s)), 2);
    let doc = a.current(None, &Query::default(), 3).unwrap();
    assert!(
        doc.contains("type=\"SYSTEM\" nativeCode=\"CG-SAT-NC\""),
        "{doc}"
    );
    assert!(!doc.contains("type=\"COMMUNICATIONS\" nativeCode"), "{doc}");
}

#[test]
fn a_link_alarm_keeps_the_manual_number() {
    let mut a = agent();
    let mut s = status("mill-1", pb::LinkState::Alarm);
    s.last_alarm = Some(pb::AlarmEvent {
        kind: pb::AlarmKind::LinkAlarm as i32,
        alarm_number: "SR0944".into(),
        message: "time-out".into(),
        ..Default::default()
    });
    a.update("demo", Update::Status(Box::new(s)), 2);
    let doc = a.current(None, &Query::default(), 3).unwrap();
    assert!(
        doc.contains("type=\"COMMUNICATIONS\" nativeCode=\"SR0944\""),
        "{doc}"
    );
}

#[test]
fn part_count_comes_from_the_tag() {
    let mut a = agent();
    a.update(
        "demo",
        Update::Status(Box::new(status("mill-1", pb::LinkState::Idle))),
        2,
    );
    a.update(
        "demo",
        Update::Tag(pb::TagValue {
            plc: "plc-1".into(),
            name: "parts".into(),
            value: Some(42.0),
            quality: pb::TagQuality::Good as i32,
            ..Default::default()
        }),
        3,
    );
    assert_eq!(
        current_value(&a, "mill-1_part_count"),
        Value::Text("42".into())
    );
    assert_eq!(
        current_value(&a, "plc-1_tag_parts"),
        Value::Text("42".into())
    );
}

#[test]
fn a_typed_tag_is_a_sample_with_its_units() {
    let mut a = agent();
    let probe = a.probe(None, Format::Xml, 2);
    assert!(
        probe.contains(r#"category="SAMPLE" id="plc-1_tag_oil-temp" type="TEMPERATURE" name="oil-temp" units="CELSIUS""#),
        "{probe}"
    );
    // An untyped tag stays a VARIABLE event.
    assert!(
        probe.contains(r#"category="EVENT" id="plc-1_tag_parts" type="VARIABLE""#),
        "{probe}"
    );
    a.update(
        "demo",
        Update::Tag(pb::TagValue {
            plc: "plc-1".into(),
            name: "oil-temp".into(),
            value: Some(41.5),
            quality: pb::TagQuality::Good as i32,
            ..Default::default()
        }),
        3,
    );
    let current = a.current(None, &Query::default(), 4).unwrap();
    assert!(current.contains("<Samples>"), "{current}");
    assert!(
        current.contains(r#"dataItemId="plc-1_tag_oil-temp""#),
        "{current}"
    );
    assert!(current.contains(">41.5</Temperature>"), "{current}");
}

#[test]
fn unchanged_values_make_no_observation() {
    let mut a = agent();
    let n = a.update(
        "demo",
        Update::Status(Box::new(status("mill-1", pb::LinkState::Idle))),
        2,
    );
    assert!(n > 0);
    let again = a.update(
        "demo",
        Update::Status(Box::new(status("mill-1", pb::LinkState::Idle))),
        3,
    );
    assert_eq!(again, 0);
}

#[test]
fn path_filters_select_by_type_id_name_and_component() {
    let a = agent();
    let sel = |p: &str| {
        a.select(None, Some(p))
            .map(|m| {
                let m = m.unwrap();
                (0..m.len())
                    .filter(|&i| m[i])
                    .map(|i| a.model().items[i].id.clone())
                    .collect::<Vec<_>>()
            })
            .map_err(|e| e.code)
    };
    assert_eq!(
        sel("//DataItem[@type=\"EXECUTION\"]").unwrap(),
        ["mill-1_execution", "lathe-1_execution"]
    );
    assert_eq!(
        sel("//DataItem[@id='mill-1_program']").unwrap(),
        ["mill-1_program"]
    );
    assert_eq!(
        sel("//Device[@name=\"mill-1\"]//Path").unwrap(),
        [
            "mill-1_execution",
            "mill-1_program",
            "mill-1_block_fed",
            "mill-1_part_count"
        ]
    );
    assert_eq!(
        sel("//DataItem[@category=\"CONDITION\" and @type=\"SYSTEM\"]").unwrap(),
        ["mill-1_system", "lathe-1_system"]
    );
    assert_eq!(
        sel("//DataItem[@type=\"PROGRAM\"]|//DataItem[@name=\"di\"]").unwrap(),
        ["mill-1_di", "mill-1_program", "lathe-1_program"]
    );
    assert_eq!(
        sel("//DataItem[@type=\"NOPE\"]"),
        Err(ErrorCode::InvalidPath)
    );
    assert_eq!(sel("//DataItem[type=1"), Err(ErrorCode::InvalidPath));
    assert!(
        PathFilter::parse("//Device/").is_err(),
        "a step after every /"
    );
}

#[test]
fn queries_refuse_unknown_and_malformed_parameters() {
    let parse = |r, pairs: &[(&'static str, &'static str)]| {
        Query::parse(r, pairs.iter().copied()).map_err(|e| e.code)
    };
    assert_eq!(
        parse(Request::Sample, &[("from", "x")]),
        Err(ErrorCode::InvalidRequest)
    );
    assert_eq!(
        parse(Request::Probe, &[("from", "1")]),
        Err(ErrorCode::InvalidRequest)
    );
    assert_eq!(
        parse(Request::Sample, &[("heartbeat", "0")]),
        Err(ErrorCode::OutOfRange)
    );
    let q = parse(Request::Sample, &[("count", "5"), ("format", "json")]).unwrap();
    assert_eq!((q.count, q.format), (Some(5), Format::Json));
}

#[test]
fn documents_carry_the_2_5_namespaces_and_the_buffer() {
    let a = agent();
    let probe = a.probe(None, Format::Xml, 5);
    assert!(probe.contains("xmlns=\"urn:mtconnect.org:MTConnectDevices:2.5\""));
    assert!(probe.contains("<Agent id=\"agent\""));
    let cur = a.current(None, &Query::default(), 5).unwrap();
    assert!(cur.contains("bufferSize=\"1024\""));
    assert!(cur.contains(&format!("nextSequence=\"{}\"", a.buffer().next())));
    let json: serde_json::Value = serde_json::from_str(&a.probe(None, Format::Json, 5)).unwrap();
    assert_eq!(json["MTConnectDevices"]["jsonVersion"], 2);
}

#[test]
fn json_streams_escape_text_and_keep_the_structure() {
    let mut a = agent();
    let mut s = status("mill-1", pb::LinkState::Alarm);
    s.last_alarm = Some(pb::AlarmEvent {
        kind: pb::AlarmKind::CncAlarm as i32,
        message: "quote \" backslash \\ line\nend \u{1}".into(),
        ..Default::default()
    });
    a.update("demo", Update::Status(Box::new(s)), 2);
    let q = Query {
        format: Format::Json,
        ..Query::default()
    };
    let doc = a.current(None, &q, 3).unwrap();
    let v: serde_json::Value = serde_json::from_str(&doc).unwrap();
    let streams = v["MTConnectStreams"]["Streams"]["DeviceStream"]
        .as_array()
        .unwrap();
    assert_eq!(streams.len(), 4, "Agent, two machines, a PLC: {doc}");
    let mill = streams.iter().find(|d| d["name"] == "mill-1").unwrap();
    let controller = mill["ComponentStream"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["component"] == "Controller")
        .unwrap();
    let fault = &controller["Condition"]["Fault"][0];
    assert_eq!(fault["nativeCode"], "CG-ALM");
    assert_eq!(fault["value"], "quote \" backslash \\ line\nend \u{1}");
    assert_eq!(
        v["MTConnectStreams"]["Header"]["nextSequence"],
        a.buffer().next()
    );
}

proptest::proptest! {
    /// Nothing a client puts in a request's query can panic the agent: every request is
    /// answered with a document or an error.
    #[test]
    fn any_query_is_answered_without_a_panic(
        key in proptest::sample::select(vec!["path", "at", "from", "count", "interval", "heartbeat", "format", "x"]),
        value in ".{0,40}",
        number in proptest::num::i64::ANY,
        path in "[/@\\[\\]\"'=*|a-zA-Z_ -]{0,40}",
    ) {
        let a = agent();
        let number = number.to_string();
        for (k, v) in [(key, value.as_str()), (key, number.as_str()), ("path", path.as_str())] {
            for r in [Request::Probe, Request::Current, Request::Sample, Request::Assets] {
                if let Ok(q) = Query::parse(r, [(k, v)]) {
                    let sel = a.select(None, q.path.as_deref());
                    let _ = a.current(None, &q, 1);
                    if let Ok(sel) = sel {
                        let _ = a.sample(None, &q, &sel, 1);
                    }
                }
            }
        }
    }
}

#[test]
fn a_starving_g05_stream_is_a_warning_while_it_is_open() {
    let mut a = Agent::new("test", 7, 1024, 1);
    let mut desc = cell();
    desc.machines[0].g05 = true;
    a.add_cell(&desc, 1);
    a.update("demo", Update::Gateway(true), 1);
    let mut s = status("mill-1", pb::LinkState::Sending);
    s.last_alarm = Some(pb::AlarmEvent {
        kind: pb::AlarmKind::G05 as i32,
        message: "G05 stream s1 starved the CNC: 3 underruns".into(),
        ..Default::default()
    });
    let stream = |state: pb::G05State| pb::G05Status {
        machine: "mill-1".into(),
        stream_id: "s1".into(),
        state: state as i32,
        on_line: 100,
        cnc_buffer: 10,
        ..Default::default()
    };
    a.update("demo", Update::G05(stream(pb::G05State::Streaming)), 2);
    a.update("demo", Update::Status(Box::new(s)), 3);
    let doc = a.current(None, &Query::default(), 4).unwrap();
    assert!(
        doc.contains("type=\"MOTION_PROGRAM\" nativeCode=\"CG-G05\""),
        "{doc}"
    );
    assert_eq!(
        current_value(&a, "mill-1_g05_blocks"),
        Value::Text("90".into())
    );
    a.update("demo", Update::G05(stream(pb::G05State::Completed)), 5);
    let doc = a.current(None, &Query::default(), 6).unwrap();
    assert!(!doc.contains("CG-G05"), "{doc}");
}

#[test]
fn assets_are_bounded_and_a_punch_again_replaces_its_asset() {
    use super::assets::{ASSET_BUFFER_SIZE, Assets, FileAsset};
    let punched = |name: &str, text: &[u8]| pb::PunchedProgram {
        machine: "lathe-1".into(),
        library_name: name.into(),
        program: text.to_vec(),
        ..Default::default()
    };
    let a = FileAsset::of_punched(&punched("O1", b"%\nO1\n%\n"), "demo", 2, "k".into(), 1).unwrap();
    assert_eq!(a.asset_id, "demo.lathe-1.O1");
    assert_eq!(a.state(), "REVISION");
    let damaged = pb::PunchedProgram {
        damaged: true,
        ..punched("O2", b"%\n%\n")
    };
    assert!(FileAsset::of_punched(&damaged, "demo", 2, "k".into(), 1).is_none());
    assert!(FileAsset::of_punched(&punched("", b"%\n%\n"), "demo", 2, "k".into(), 1).is_none());
    let mut assets = Assets::default();
    assets.put(a.clone());
    let again = FileAsset::of_punched(&punched("O1", b"%\nO1\nM30\n%\n"), "demo", 2, "k".into(), 2)
        .unwrap();
    assert_ne!(again.version, a.version, "a version per content");
    assets.put(again.clone());
    assert_eq!(assets.len(), 1);
    assert_eq!(assets.get("demo.lathe-1.O1"), Some(&again));
    for n in 0..ASSET_BUFFER_SIZE + 10 {
        let mut f = a.clone();
        f.asset_id = format!("x{n}");
        assets.put(f);
    }
    assert_eq!(assets.len(), ASSET_BUFFER_SIZE);
    assert_eq!(
        assets.newest(None, 1)[0].asset_id,
        format!("x{}", ASSET_BUFFER_SIZE + 9)
    );
    assert!(assets.get("demo.lathe-1.O1").is_none(), "the oldest went");
}

#[test]
fn a_reloaded_cell_adds_removes_and_changes_devices() {
    let mut a = agent();
    a.update(
        "demo",
        Update::Status(Box::new(status("lathe-1", pb::LinkState::Idle))),
        2_000_000,
    );
    let uuid = |a: &Agent, name: &str| {
        let d = a.model().device_named(name).unwrap();
        a.model().devices[d].uuid.clone()
    };
    let (mill, lathe) = (uuid(&a, "mill-1"), uuid(&a, "lathe-1"));
    // The same description again changes nothing.
    assert_eq!(a.change_cell(&cell(), 3_000_000), 0);
    // lathe-1 out, mill-3 in, mill-1 now takes G05 streams.
    let mut next = cell();
    next.machines.retain(|m| m.name != "lathe-1");
    next.machines[0].g05 = true;
    next.machines.push(MachineDesc {
        name: "mill-3".into(),
        protocol: Protocol::ExpansionA,
        part_counter: None,
        g05: false,
        identification: Default::default(),
    });
    assert!(a.change_cell(&next, 4_000_000) > 0);
    assert_eq!(
        current_value(&a, "device_added"),
        Value::Text(uuid(&a, "mill-3").into())
    );
    assert_eq!(
        current_value(&a, "device_removed"),
        Value::Text(lathe.clone().into())
    );
    assert_eq!(
        current_value(&a, "device_changed"),
        Value::Text(mill.into())
    );
    // The removed device's data items went UNAVAILABLE before it left the documents.
    assert_eq!(current_value(&a, "lathe-1_avail"), Value::Unavailable);
    assert!(a.model().device_named("lathe-1").is_none());
    let probe = a.probe(None, Format::Xml, 4_000_001);
    assert!(probe.contains("name=\"mill-3\"") && !probe.contains("name=\"lathe-1\""));
    let current = a.current(None, &Query::default(), 4_000_001).unwrap();
    assert!(!current.contains("lathe-1"), "{current}");
    // The new device takes updates; its data items start UNAVAILABLE.
    assert_eq!(current_value(&a, "mill-3_execution"), Value::Unavailable);
    a.update(
        "demo",
        Update::Status(Box::new(status("mill-3", pb::LinkState::Idle))),
        5_000_000,
    );
    assert_eq!(
        current_value(&a, "mill-3_execution"),
        Value::Text("READY".into())
    );
    // lathe-1 back: its old device and UUID, in the documents again.
    assert!(a.change_cell(&cell(), 6_000_000) > 0);
    assert_eq!(current_value(&a, "device_added"), Value::Text(lathe.into()));
    assert!(a.model().device_named("lathe-1").is_some());
    assert!(a.model().device_named("mill-3").is_none());
}

/// A punched program reaches an agent fed by the SHDR port as the reference agent reads it:
/// the asset itself on an `@ASSET@` line, then ASSET_CHANGED with its type before its id.
#[test]
fn a_punched_programs_asset_goes_out_on_shdr_as_the_reference_agent_reads_it() {
    let mut a = agent();
    let p = pb::PunchedProgram {
        machine: "lathe-1".into(),
        library_name: "O7".into(),
        program: b"%\nO7\nM30\n%\n".to_vec(),
        ..Default::default()
    };
    let from = a.buffer().next();
    a.update(
        "demo",
        Update::Punch(Box::new(p), "cellgate/demo/program/O7".into()),
        2_000_000,
    );
    let (obs, _) = a.buffer().sample(from, 100, |_| true);
    let text = super::shdr::lines(&a, &obs);
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 2, "{text}");
    let asset: Vec<&str> = lines[0].splitn(5, '|').collect();
    assert_eq!(
        asset[1..4],
        ["@ASSET@", "demo.lathe-1.O7", "File"],
        "{text}"
    );
    assert!(
        asset[4].starts_with("<File assetId=\"demo.lathe-1.O7\"") && asset[4].ends_with("</File>"),
        "{text}"
    );
    assert!(
        lines[1].ends_with("|lathe-1:lathe-1_asset_chg|File|demo.lathe-1.O7"),
        "{text}"
    );
}
