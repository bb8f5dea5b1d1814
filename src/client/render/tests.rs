use super::*;

#[test]
fn times_are_utc() {
    assert_eq!(clock(0), "00:00:00.000Z");
    assert_eq!(clock(1_700_000_000_123), "22:13:20.123Z");
    assert_eq!(date_time(1_700_000_000_123), "2023-11-14 22:13:20Z");
    assert_eq!(date_time(951_782_400_000), "2000-02-29 00:00:00Z");
}

#[test]
fn sizes_and_images_read_well() {
    assert_eq!(bytes(512), "512 B");
    assert_eq!(bytes(40 * 1024), "40.0 KiB");
    assert_eq!(bytes(3 * 1024 * 1024 / 2), "1.5 MiB");
    assert_eq!(byte_image(0x5A), "0x5A 0b01011010");
}

fn status() -> pb::MachineStatus {
    pb::MachineStatus {
        machine: "mill-1".to_string(),
        protocol: pb::Protocol::ExpansionA as i32,
        link_state: pb::LinkState::Sending as i32,
        sat: Some(pb::Sat {
            buffer_status: pb::BufferStatus::Alarm as i32,
            alarm_cause: pb::AlarmCause::ChecksumRetryOver as i32,
            bytes_buffered: Some(300),
            ..pb::Sat::default()
        }),
        counters: Some(pb::LinkCounters {
            nc_bytes_sent: 2048,
            jobs_completed: 3,
            programs_punched: 5,
            retries: 4,
            ..pb::LinkCounters::default()
        }),
        current_job_id: "mill-1-x-7".to_string(),
        do_image: Some(0xA5),
        last_alarm: Some(pb::AlarmEvent {
            machine: "mill-1".to_string(),
            kind: pb::AlarmKind::LinkAlarm as i32,
            alarm_number: "SR0945".to_string(),
            message: "retry over".to_string(),
            unix_ms: 0,
            code: "SR0945".to_string(),
        }),
        ..pb::MachineStatus::default()
    }
}

#[test]
fn the_status_table_shows_what_the_contract_carries() {
    let t = status_table(&[status()]);
    let mut lines = t.lines();
    let header = lines.next().unwrap();
    assert!(header.starts_with("MACHINE"), "{t}");
    let row = lines.next().unwrap();
    for cell in [
        "mill-1",
        "Expansion A",
        "sending",
        "alarm: checksum retry over",
        "300",
        "mill-1-x-7",
        "0xA5",
        "2.0 KiB",
    ] {
        assert!(row.contains(cell), "{cell:?} missing from {row:?}");
    }
    assert!(
        lines
            .next()
            .unwrap()
            .contains("link alarm SR0945: retry over"),
        "{t}"
    );
    assert_eq!(status_table(&[]), "no machine answered\n");
}

#[test]
fn punched_programs_read_as_sentences() {
    let mut p = pb::PunchedProgram {
        machine: "lathe-1".to_string(),
        name: "SHAFT".to_string(),
        o_number: "O1234".to_string(),
        code_system: pb::CodeSystem::Eia as i32,
        program: b"%\nO1234(SHAFT)\n%".to_vec(),
        library_name: "lathe-1-O1234-20261122T061500Z".to_string(),
        unix_ms: 0,
        request: None,
        damaged: false,
        damage: String::new(),
        comparison: None,
    };
    let mut printer = WatchPrinter::new();
    let line = printer
        .line(&WatchEvent::Punched(Box::new(p.clone())), 0)
        .unwrap();
    assert!(
        line.contains("lathe-1 punched SHAFT (16 bytes, CODE_SYSTEM_EIA)"),
        "{line}"
    );
    assert!(
        line.ends_with("stored as lathe-1-O1234-20261122T061500Z"),
        "{line}"
    );
    p.library_name.clear();
    p.request = Some(pb::RemoteRequest {
        program: "O12".to_string(),
        error: "no program O12".to_string(),
        ..pb::RemoteRequest::default()
    });
    let line = printer
        .line(&WatchEvent::Punched(Box::new(p.clone())), 0)
        .unwrap();
    assert!(
        line.ends_with("remote request for O12 refused: no program O12"),
        "{line}"
    );
    let damaged = pb::PunchedProgram {
        damaged: true,
        damage: "parity error in a received character during the punch-out".to_string(),
        library_name: String::new(),
        ..p.clone()
    };
    let line = printer
        .line(&WatchEvent::Punched(Box::new(damaged)), 0)
        .unwrap();
    assert!(
        line.ends_with(
            "DAMAGED (parity error in a received character during the punch-out): not \
             stored, punch it again"
        ),
        "{line}"
    );
    let j = watch_json(&WatchEvent::Punched(Box::new(p)), 0);
    assert_eq!(j["event"], "punched");
    assert_eq!(j["punched"]["code_system"], "CODE_SYSTEM_EIA");
    assert_eq!(j["punched"]["request"]["program"], "O12");
    assert_eq!(
        watch_machine(&WatchEvent::Punched(Box::default())),
        Some("")
    );
}

#[test]
fn status_json_uses_the_proto_names() {
    let j = status_json(&status());
    assert_eq!(j["protocol"], "PROTOCOL_EXPANSION_A");
    assert_eq!(j["link_state"], "LINK_STATE_SENDING");
    assert_eq!(j["sat"]["buffer_status"], "BUFFER_STATUS_ALARM");
    assert_eq!(j["sat"]["bytes_buffered"], 300);
    assert_eq!(j["do_image"], 0xA5);
    assert_eq!(j["di_image"], Value::Null);
    assert_eq!(j["counters"]["jobs_completed"], 3);
    assert_eq!(j["counters"]["programs_punched"], 5);
    assert_eq!(j["last_alarm"]["alarm_number"], "SR0945");
}

#[test]
fn job_events_read_as_sentences() {
    let ev = |kind| pb::JobEvent {
        job_id: "j".to_string(),
        machine: "m".to_string(),
        unix_ms: 0,
        origin: None,
        kind: Some(kind),
    };
    let p = ev(Kind::Progress(pb::job_event::Progress {
        bytes_sent: 512,
        bytes_total: Some(2048),
        rate_bps: 1900,
        bytes_on_line: 512,
        ..Default::default()
    }));
    assert_eq!(job_kind_text(&p), "sent 512 B of 2.0 KiB (25%), 1900 B/s");
    let p = ev(Kind::Progress(pb::job_event::Progress {
        bytes_on_line: 1024,
        ..pb::job_event::Progress::default()
    }));
    assert_eq!(job_kind_text(&p), "sent 0 B, 1.0 KiB on the line, 0 B/s");
    let f = ev(Kind::Failed(pb::job_event::Failed {
        reason: "retry over".to_string(),
        byte_offset: 512,
        alarm_number: "SR0945".to_string(),
        code: pb::ErrorCode::LinkFailed as i32,
        bytes_on_line: 700,
        next_block: Some(pb::BlockPosition {
            line: 20,
            sequence_number: "N190".to_string(),
            byte_offset: 500,
        }),
    }));
    assert_eq!(
        job_kind_text(&f),
        "failed at byte 512: retry over [SR0945] (link failed); resumes at line 20 (N190)"
    );
    let j = job_event_json(&f);
    assert_eq!(j["failed"]["byte_offset"], 512);
    assert_eq!(j["failed"]["code"], "ERROR_CODE_LINK_FAILED");
    assert_eq!(j["failed"]["next_block"]["line"], 20);
}

#[test]
fn di_is_shown_in_hex_and_bits() {
    let t = di_text(&pb::DiImage {
        machine: "mill-1".to_string(),
        value: 0x5A,
        unix_ms: 0,
    });
    assert!(t.starts_with("mill-1 DI 0x5A 0b01011010 (90)"), "{t}");
    assert!(t.contains("0 1 0 1 1 0 1 0"), "{t}");
}

#[test]
fn watch_prints_a_status_only_when_its_headline_changes() {
    let mut p = WatchPrinter::new();
    let mut s = status();
    assert!(
        p.line(&WatchEvent::Status(Box::new(s.clone())), 0)
            .is_some()
    );
    s.counters.as_mut().unwrap().retries += 1;
    assert!(
        p.line(&WatchEvent::Status(Box::new(s.clone())), 0)
            .is_none()
    );
    s.do_image = Some(0);
    let line = p.line(&WatchEvent::Status(Box::new(s)), 0).unwrap();
    assert!(line.contains("DO 0x00"), "{line}");
    let link = WatchEvent::Link {
        machine: "mill-1".to_string(),
        up: false,
    };
    assert!(p.line(&link, 0).unwrap().ends_with("mill-1 link down"));
    assert_eq!(watch_json(&link, 5)["event"], "link_down");
    assert_eq!(watch_machine(&link), Some("mill-1"));
}

#[test]
fn a_job_waiting_for_the_cnc_is_not_shown_as_an_idle_link() {
    let mut s = status();
    s.link_state = pb::LinkState::Idle as i32;
    s.current_job_id = "mill-1-x-8".to_string();
    s.waiting_for = "GTD: the CNC has not asked for the program (§4.4.1)".to_string();
    s.unix_ms = 100_000;
    s.waiting_since_unix_ms = 88_000;
    let t = status_table(&[s.clone()]);
    let row = t.lines().nth(1).unwrap();
    assert!(row.contains("waiting for CNC"), "{t}");
    assert!(!row.contains("idle"), "{t}");
    assert!(
        t.contains("mill-1: job mill-1-x-8 waits for 12 s for the CNC to read it (GTD"),
        "{t}"
    );
    assert_eq!(status_json(&s)["waiting_for"], s.waiting_for.as_str());
    let mut p = WatchPrinter::new();
    let line = p.line(&WatchEvent::Status(Box::new(s.clone())), 0).unwrap();
    assert!(line.contains("link waiting for CNC"), "{line}");
    // Idle with nothing pending is idle.
    s.current_job_id.clear();
    s.waiting_for.clear();
    let t = status_table(&[s]);
    assert!(t.lines().nth(1).unwrap().contains("idle"), "{t}");
    assert!(!t.contains("waits"), "{t}");
}

#[test]
fn job_ends_say_what_was_not_sent_and_why() {
    let ev = |kind| pb::JobEvent {
        job_id: "j".to_string(),
        machine: "m".to_string(),
        unix_ms: 0,
        origin: None,
        kind: Some(kind),
    };
    let c = ev(Kind::Completed(pb::job_event::Completed {
        bytes_sent: 126,
        bytes_after_eor: 1,
        duration_ms: 100,
        confirmation: pb::Confirmation::Acknowledged as i32,
    }));
    assert_eq!(
        job_kind_text(&c),
        "completed: 126 B sent in 0.1 s; the 1 B after the EOR % not sent (the CNC ignores them)"
    );
    assert_eq!(job_event_json(&c)["completed"]["bytes_after_eor"], 1);
    // Cancelled before it started: no "resumes at line 1".
    let never = ev(Kind::Cancelled(pb::job_event::Cancelled {
        by: "request".to_string(),
        ..pb::job_event::Cancelled::default()
    }));
    assert_eq!(
        job_kind_text(&never),
        "cancelled by request before the CNC read any of it: nothing was sent"
    );
    let midway = ev(Kind::Cancelled(pb::job_event::Cancelled {
        by: "request".to_string(),
        byte_offset: 40,
        bytes_on_line: 80,
        next_block: Some(pb::BlockPosition {
            line: 4,
            sequence_number: String::new(),
            byte_offset: 30,
        }),
    }));
    assert_eq!(
        job_kind_text(&midway),
        "cancelled by request at byte 40; resumes at line 4"
    );
}

#[test]
fn a_plc_stations_last_error_shows_its_age_and_sta_codes_are_hex() {
    let st = pb::PlcStation {
        plc: "plc-1".to_string(),
        up: true,
        error_replies: [(0xA7, 1), (0x22, 3)].into_iter().collect(),
        last_error: "STA A7: transfer refused".to_string(),
        last_error_unix_ms: 1_000_000,
        ..pb::PlcStation::default()
    };
    assert_eq!(
        last_error_text(&st, 1_000_000 + 12 * 60_000),
        "12 min ago: STA A7: transfer refused"
    );
    let plcs = [pb::PlcStatus {
        plc: "plc-1".to_string(),
        stations: vec![st.clone()],
        ..pb::PlcStatus::default()
    }];
    assert!(
        plc_status_text(&plcs, 1_000_000 + 5_000).contains("5 s ago: STA A7"),
        "{}",
        plc_status_text(&plcs, 1_005_000)
    );
    let j = error_replies_json(&st);
    assert_eq!(j, serde_json::json!({ "22": 3, "A7": 1 }));
}
