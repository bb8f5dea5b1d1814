use super::*;
use crate::fanuc::Protocol;
use crate::mtconnect::desc::{MachineDesc, PlcDesc, TagDesc};

fn cell() -> CellDesc {
    CellDesc {
        cell: "demo".into(),
        machines: vec![MachineDesc {
            name: "mill-1".into(),
            protocol: Protocol::A,
            part_counter: Some(("plc-1".into(), "parts".into())),
            g05: false,
            identification: Default::default(),
        }],
        plcs: vec![PlcDesc {
            name: "plc-1".into(),
            stations: vec![0],
            tags: vec![TagDesc {
                name: "parts".into(),
                native: "D0".into(),
                typed: None,
                units: None,
            }],
        }],
    }
}

fn status(state: pb::LinkState) -> Update {
    Update::Status(Box::new(pb::MachineStatus {
        machine: "mill-1".into(),
        protocol: pb::Protocol::A as i32,
        link_state: state as i32,
        ..Default::default()
    }))
}

fn job(kind: pb::job_event::Kind) -> Update {
    Update::Job(pb::JobEvent {
        job_id: "mill-1-1-1".into(),
        machine: "mill-1".into(),
        origin: Some(pb::JobOrigin {
            program: Some(pb::ProgramRef {
                library: "O1234.nc".into(),
                ..Default::default()
            }),
            started_unix_ms: 1,
            ..Default::default()
        }),
        kind: Some(kind),
        ..Default::default()
    })
}

fn machine_of(out: &[Out]) -> Option<&MachineShows> {
    out.iter().rev().find_map(|o| match o {
        Out::Machine { shows, .. } => Some(shows),
        _ => None,
    })
}

fn up() -> Model {
    let mut m = Model::new();
    m.set_cell(&cell());
    m.update("demo", Update::Gateway(true));
    m.update("demo", status(pb::LinkState::Idle));
    m
}

#[test]
fn a_job_runs_then_ends_and_a_failed_one_is_aborted() {
    use pb::job_event::Kind;
    let mut m = up();
    let s = m.shows("demo", "mill-1").unwrap();
    assert_eq!(
        (s.state, s.channel),
        (ProgramState::Initializing, ChannelState::Reset)
    );
    assert!(s.reachable);
    let out = m.update("demo", job(Kind::Started(Default::default())));
    let s = machine_of(&out).expect("a started job changes the machine");
    assert_eq!(s.program, "O1234.nc");
    assert_eq!(s.state, ProgramState::Running);
    assert_eq!(s.state.name(), "Running");
    assert_eq!(
        (s.channel, s.mode),
        (ChannelState::Active, OperationMode::Automatic)
    );
    let out = m.update("demo", job(Kind::Completed(Default::default())));
    assert_eq!(machine_of(&out).unwrap().state, ProgramState::Ended);
    assert_eq!(machine_of(&out).unwrap().channel, ChannelState::Reset);
    m.update("demo", job(Kind::Started(Default::default())));
    let out = m.update("demo", job(Kind::Failed(Default::default())));
    let s = machine_of(&out).unwrap();
    assert_eq!(
        (s.state, s.channel),
        (ProgramState::Aborted, ChannelState::Interrupted)
    );
    // Nothing new: nothing sent again.
    assert!(m.update("demo", status(pb::LinkState::Idle)).is_empty());
}

#[test]
fn a_cut_line_or_a_cnc_alarm_interrupts_the_running_program_and_alerts_once() {
    use pb::job_event::Kind;
    let mut m = up();
    m.update("demo", job(Kind::Started(Default::default())));
    let out = m.update("demo", status(pb::LinkState::Down));
    let s = machine_of(&out).unwrap();
    assert_eq!(s.state, ProgramState::Interrupted);
    assert!(!s.reachable);
    let alerts: Vec<_> = out
        .iter()
        .filter_map(|o| match o {
            Out::Alert { alert, .. } => Some(alert.clone()),
            _ => None,
        })
        .collect();
    assert_eq!(alerts.len(), 1, "{out:?}");
    assert_eq!(alerts[0].severity, 600);
    // Still down: no second alert.
    let again = m.update("demo", status(pb::LinkState::Down));
    assert!(
        !again.iter().any(|o| matches!(o, Out::Alert { .. })),
        "{again:?}"
    );
    m.update("demo", status(pb::LinkState::Sending));
    let mut alarm = pb::MachineStatus {
        machine: "mill-1".into(),
        protocol: pb::Protocol::A as i32,
        link_state: pb::LinkState::Alarm as i32,
        ..Default::default()
    };
    alarm.last_alarm = Some(pb::AlarmEvent {
        machine: "mill-1".into(),
        kind: pb::AlarmKind::CncAlarm as i32,
        code: "SR0945".into(),
        message: "checksum error".into(),
        ..Default::default()
    });
    let out = m.update("demo", Update::Status(Box::new(alarm)));
    let s = machine_of(&out).unwrap();
    assert_eq!(
        (s.state, s.channel),
        (ProgramState::Interrupted, ChannelState::Interrupted)
    );
    let alert = out
        .iter()
        .find_map(|o| match o {
            Out::Alert { alert, .. } => Some(alert),
            _ => None,
        })
        .expect("a CNC alarm is an alert");
    assert_eq!((alert.code.as_str(), alert.severity), ("SR0945", 800));
}

#[test]
fn the_gateway_going_makes_every_machine_unreachable_and_a_plcs_tags_unknown() {
    let mut m = up();
    let tag = pb::TagValue {
        plc: "plc-1".into(),
        name: "parts".into(),
        value: Some(41.0),
        quality: pb::TagQuality::Good as i32,
        ..Default::default()
    };
    m.update(
        "demo",
        Update::Plc(pb::PlcStatus {
            plc: "plc-1".into(),
            stations: vec![pb::PlcStation {
                station: 0,
                up: true,
                ..Default::default()
            }],
            ..Default::default()
        }),
    );
    let out = m.update("demo", Update::Tag(tag));
    assert_eq!(machine_of(&out).unwrap().parts, Some(41));
    assert!(out.iter().any(|o| matches!(o,
        Out::Plc { up: true, tags, .. } if tags == &vec![("parts".to_string(), Some(41.0))])));
    let out = m.update("demo", Update::Gateway(false));
    assert!(!machine_of(&out).unwrap().reachable);
    assert!(out.iter().any(|o| matches!(o,
        Out::Plc { up: false, tags, .. } if tags == &vec![("parts".to_string(), None)])));
}

#[test]
fn a_cell_described_again_keeps_its_machines_and_drops_those_gone() {
    use pb::job_event::Kind;
    let mut m = up();
    m.update("demo", job(Kind::Started(Default::default())));
    let mut more = cell();
    let mut second = more.machines[0].clone();
    second.name = "lathe-1".into();
    more.machines.push(second);
    let out = m.set_cell(&more);
    assert_eq!(
        out.iter()
            .filter(|o| matches!(o, Out::Machine { .. }))
            .count(),
        2
    );
    assert_eq!(
        m.shows("demo", "mill-1").unwrap().state,
        ProgramState::Running
    );
    assert!(!m.shows("demo", "lathe-1").unwrap().reachable);
    more.machines.remove(0);
    m.set_cell(&more);
    assert!(m.shows("demo", "mill-1").is_none());
    assert!(m.update("demo-2", Update::Gateway(true)).is_empty());
}

#[test]
fn units_are_the_unece_codes_packed_as_part_8_says() {
    // Part 8's own example: degree Celsius, "CEL", 4408652.
    assert_eq!(
        engineering_unit("CELSIUS"),
        Some((4_408_652, "°C", "degree Celsius"))
    );
    assert_eq!(engineering_unit("PERCENT").unwrap().0, 0x5031);
    assert_eq!(engineering_unit("COUNT"), None);
    // Every unit a tag type reports in by default has one.
    for t in crate::config::mtconnect_types::TAG_TYPES {
        if let Some(u) = t.units {
            assert!(engineering_unit(u).is_some(), "{u}");
        }
    }
}
