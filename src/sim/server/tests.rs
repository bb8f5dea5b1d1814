use super::*;
use clap::Parser;

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    args: SimFanucArgs,
}

#[tokio::test(start_paused = true)]
async fn output_is_paced_at_the_baud_rate() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let (a, mut b) = tokio::io::duplex(1 << 16);
    let mut line = PacedLine::new(a, LineSettings::with_baud(9600), "test".into());
    let start = Instant::now();
    line.write_all(&[0x55; 873]).await.unwrap();
    // 9600 baud at 11 bits: 872.7 characters a second; the write returns when the last
    // 16 (the FIFO) are accepted: 857 characters' time.
    let took = start.elapsed();
    let expected = LineSettings::with_baud(9600).time_for_chars(857);
    assert!(
        took >= expected && took < expected + Duration::from_millis(5),
        "{took:?}"
    );
    let mut got = vec![0; 873];
    b.read_exact(&mut got).await.unwrap();
}

#[test]
fn parses_protocol_b_with_punch_and_notification_off() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("tape.iso");
    std::fs::write(&file, b"\xA5\n\x4FO1\n\xA5").unwrap();
    let cli = Cli::try_parse_from([
        "sim",
        "--protocol",
        "exp-b",
        "--code",
        "iso",
        "--no-notify",
        "--punch",
        file.to_str().unwrap(),
        "--punch-after-ms",
        "500",
    ])
    .unwrap();
    let config = cli.args.board_config().unwrap();
    assert_eq!(config.protocol, Protocol::ExpansionB);
    assert!(!config.notify_alarm_reset);
    let plan = cli.args.punch_plan().unwrap().unwrap();
    assert_eq!(plan.data, b"\xA5\n\x4FO1\n\xA5");
    assert_eq!(plan.after, Duration::from_millis(500));

    let cli = Cli::try_parse_from(["sim", "--protocol", "b"]).unwrap();
    assert_eq!(cli.args.board_config().unwrap().protocol, Protocol::B);
    assert!(cli.args.board_config().unwrap().notify_alarm_reset);
    assert_eq!(cli.args.punch_plan().unwrap(), None);

    let cli = Cli::try_parse_from(["sim", "--punch", "x"]).unwrap();
    assert!(matches!(
        cli.args.punch_plan(),
        Err(SimError::PunchNeedsProtocolB)
    ));
    let missing = dir.path().join("missing");
    let cli = Cli::try_parse_from([
        "sim",
        "--protocol",
        "b",
        "--punch",
        missing.to_str().unwrap(),
    ])
    .unwrap();
    let err = cli.args.punch_plan().unwrap_err();
    assert!(err.to_string().contains("missing"), "{err}");
}

#[test]
fn punch_code_encodes_a_text_file() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("O1.nc");
    let text = b"%\nO1(PART)\nG00X1.\nM30\n%";
    std::fs::write(&file, text).unwrap();
    let plan = |code: &str| {
        let cli = Cli::try_parse_from([
            "sim",
            "--protocol",
            "b",
            "--punch",
            file.to_str().unwrap(),
            "--punch-code",
            code,
        ])
        .unwrap();
        cli.args.punch_plan().map(|p| p.unwrap().data)
    };
    for (name, code) in [
        ("iso", TapeCode::Iso),
        ("ascii", TapeCode::Ascii),
        ("eia", TapeCode::Eia),
    ] {
        let data = plan(name).unwrap();
        assert_eq!(data, tape::encode(text, code).unwrap(), "{name}");
        assert_eq!(
            tape::decode(&data).unwrap(),
            (code, text.to_vec()),
            "{name}"
        );
    }
    assert_eq!(plan("raw").unwrap(), text);
    // A character EIA cannot punch is refused, naming the file.
    std::fs::write(&file, b"%\nO1\n#1=2\n%").unwrap();
    let err = plan("eia").unwrap_err();
    assert!(err.to_string().contains("O1.nc"), "{err}");
}

/// `--protocol b --punch FILE`: the file's bytes go out as DC2 … DC4 after the delay,
/// and the punch-out shows in the JSON events.
#[tokio::test]
async fn protocol_b_server_punches_the_file_after_connecting() {
    use tokio::io::AsyncReadExt;
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let config = BoardConfig {
        protocol: Protocol::B,
        framing: Framing::new(CodeSystem::Iso, EndCode::Cr),
        ..BoardConfig::default()
    };
    let tape: Vec<u8> = b"%\nO0001\nG00X0\nM30\n%"
        .iter()
        .map(|&b| CodeSystem::Iso.encode(b))
        .collect();
    let plan = PunchPlan {
        data: tape.clone(),
        after: Duration::from_millis(50),
    };
    let (tx, mut json) = mpsc::unbounded_channel();
    let sink: EventSink = Arc::new(move |v| {
        let _ = tx.send(v.clone());
    });
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(serve_fanuc_with(
        listener,
        config,
        LineSettings::with_baud(115_200),
        Some(plan),
        sink,
        async {
            let _ = stopped.await;
        },
    ));
    let mut stream = TcpStream::connect(addr).await.unwrap();
    let mut got = Vec::new();
    let mut buf = [0u8; 256];
    while got.last() != Some(&0x14) {
        let n = tokio::time::timeout(Duration::from_secs(10), stream.read(&mut buf))
            .await
            .unwrap()
            .unwrap();
        assert!(n > 0, "connection closed after {got:?}");
        got.extend_from_slice(&buf[..n]);
    }
    let mut expected = vec![0x12];
    expected.extend_from_slice(&tape);
    expected.push(0x14);
    assert_eq!(got, expected);
    let finished = loop {
        let v = tokio::time::timeout(Duration::from_secs(10), json.recv())
            .await
            .unwrap()
            .unwrap();
        if v["event"] == "punch" && v["state"] == "finished" {
            break v;
        }
    };
    assert_eq!(finished["bytes"], tape.len());
    stop.send(()).unwrap();
    server.await.unwrap().unwrap();
}

#[test]
fn parses_the_g05_options() {
    let cli = Cli::try_parse_from([
        "sim",
        "--protocol",
        "b",
        "--g05-axes",
        "3",
        "--g05-unit-ms",
        "2",
        "--g05-general",
        "--g05-aux",
        "m",
        "--g05-aux-low-first",
    ])
    .unwrap();
    let config = cli.args.board_config().unwrap();
    assert_eq!(
        config.g05,
        Some(G05Format {
            axes: 3,
            data_format: DataFormat::General,
            aux: AuxFunction::M,
            unit_time_ms: UnitTime::Ms2,
            aux_order: AuxOrder::LowFirst,
        })
    );
    // Defaults: special, no auxiliary word, 8 ms, high half first.
    let cli = Cli::try_parse_from(["sim", "--g05-axes", "2"]).unwrap();
    assert_eq!(
        cli.args.board_config().unwrap().g05,
        Some(G05Format::new(2))
    );
    let cli = Cli::try_parse_from(["sim"]).unwrap();
    assert_eq!(cli.args.board_config().unwrap().g05, None);
    for aux in ["none", "second", "s", "t"] {
        let cli = Cli::try_parse_from(["sim", "--g05-axes", "1", "--g05-aux", aux]).unwrap();
        assert_eq!(cli.args.g05_format().unwrap().aux.name(), aux);
    }
    // 7618 offers 1, 2, 4, 8 and 16 ms only.
    let err = Cli::try_parse_from(["sim", "--g05-axes", "1", "--g05-unit-ms", "3"])
        .err()
        .unwrap();
    assert!(err.to_string().contains("7618"), "{err}");
    // The other options need --g05-axes.
    assert!(Cli::try_parse_from(["sim", "--g05-general"]).is_err());
    assert!(Cli::try_parse_from(["sim", "--g05-unit-ms", "2"]).is_err());
    // Protocol A requires the special format; 0 axes is no format.
    let cli = Cli::try_parse_from(["sim", "--g05-axes", "1", "--g05-general"]).unwrap();
    let err = cli.args.board_config().unwrap_err();
    assert!(err.to_string().contains("§9.1 NOTE"), "{err}");
    let cli = Cli::try_parse_from(["sim", "--protocol", "b", "--g05-axes", "0"]).unwrap();
    let err = cli.args.board_config().unwrap_err();
    assert!(err.to_string().contains("7635"), "{err}");
}

#[test]
fn g05_events_as_json() {
    use cellgate_core::sim::{G05End, G05Stats};
    let v = event_json(&BoardEvent::G05Started {
        axes: 3,
        unit_ms: 2,
    })
    .unwrap();
    assert_eq!(
        v,
        json!({"event": "g05", "state": "started", "axes": 3, "unit_ms": 2})
    );
    let v = event_json(&BoardEvent::G05Underruns { new: 4, total: 9 }).unwrap();
    assert_eq!(
        v,
        json!({"event": "g05", "state": "underruns", "new": 4, "total": 9})
    );
    let stats = G05Stats {
        active: false,
        sessions: 1,
        blocks: 10,
        travel: vec![7000, -300],
        aux: vec![3, 5],
        aux_count: 2,
        underruns: 1,
        min_buffered_blocks: Some(0),
        end: Some(G05End::EndBlock),
    };
    let v = event_json(&BoardEvent::G05Ended {
        end: G05End::EndBlock,
        stats,
    })
    .unwrap();
    assert_eq!(v["end"], "end-block");
    assert_eq!(v["travel"], json!([7000, -300]));
    assert_eq!(v["aux"], json!([3, 5]));
    assert_eq!(v["underruns"], 1);
    assert_eq!(v["blocks"], 10);
    assert_eq!(v["min_buffered_blocks"], 0);
}

/// `--g05-axes`: binary data after `G05` over TCP; start and end with totals as JSON.
#[tokio::test]
async fn g05_session_over_tcp_reported_as_json() {
    use cellgate_core::fanuc::g05::G05Encoder;
    use tokio::io::AsyncWriteExt;
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let format = G05Format {
        axes: 2,
        aux: AuxFunction::T,
        unit_time_ms: UnitTime::Ms1,
        ..G05Format::new(2)
    };
    let config = BoardConfig {
        protocol: Protocol::B,
        autostart: true,
        consume_rate: 0,
        g05: Some(format),
        ..BoardConfig::default()
    };
    let (tx, mut json) = mpsc::unbounded_channel();
    let sink: EventSink = Arc::new(move |v| {
        let _ = tx.send(v.clone());
    });
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(serve_fanuc_on(
        listener,
        config,
        LineSettings::with_baud(115_200),
        sink,
        async {
            let _ = stopped.await;
        },
    ));
    let mut tape = b"%
O7
G05
"
    .to_vec();
    let mut e = G05Encoder::new(format).unwrap();
    for k in 1..=20 {
        let tool = (k == 10).then_some(cellgate_core::fanuc::g05::AuxWord::significant(12));
        e.block(&[k, -1], tool, &mut tape).unwrap();
    }
    e.end(&mut tape);
    tape.extend_from_slice(
        b"M30
%",
    );
    let mut stream = TcpStream::connect(addr).await.unwrap();
    stream.write_all(&tape).await.unwrap();
    let mut seen = Vec::new();
    let ended = loop {
        let v = tokio::time::timeout(Duration::from_secs(10), json.recv())
            .await
            .unwrap()
            .unwrap();
        if v["event"] == "listening" {
            assert_eq!(v["g05"]["axes"], 2);
            assert_eq!(v["g05"]["unit_time_ms"], 1);
        }
        if v["event"] == "g05" {
            seen.push(v["state"].clone());
            if v["state"] == "ended" {
                break v;
            }
        }
    };
    assert_eq!(seen.first(), Some(&json!("started")));
    assert_eq!(ended["end"], "end-block");
    assert_eq!(ended["blocks"], 20);
    assert_eq!(ended["travel"], json!([210, -20]));
    assert_eq!(ended["aux"], json!([12]));
    let program = loop {
        let v = tokio::time::timeout(Duration::from_secs(10), json.recv())
            .await
            .unwrap()
            .unwrap();
        if v["event"] == "program" {
            break v;
        }
    };
    assert_eq!(program["bytes"], tape.len());
    stop.send(()).unwrap();
    server.await.unwrap().unwrap();
}

#[test]
fn parses_and_validates_protocol_a() {
    let cli = Cli::try_parse_from([
        "sim",
        "--protocol",
        "exp-a",
        "--code",
        "iso",
        "--tp",
        "3",
        "--tw",
        "2",
    ])
    .unwrap();
    let config = cli.args.board_config().unwrap();
    assert_eq!(config.protocol, Protocol::ExpansionA);
    assert_eq!(config.framing.code, CodeSystem::Iso);
    assert_eq!(config.params.tp, 3);
    assert!(cli.args.listen.ip().is_loopback());

    let cli = Cli::try_parse_from(["sim", "--protocol", "b", "--buffer-size", "4000"]).unwrap();
    let err = cli.args.board_config().unwrap_err();
    assert!(err.to_string().contains("DC1"), "{err}");

    let cli = Cli::try_parse_from(["sim", "--tw", "9"]).unwrap();
    let err = cli.args.board_config().unwrap_err();
    assert!(err.to_string().contains("tw = 9"), "{err}");
}

/// The test's stand-in for stdout: every JSON event, the boards' and the commands', in order.
fn event_channel() -> (EventSink, mpsc::UnboundedReceiver<Value>) {
    let (tx, rx) = mpsc::unbounded_channel();
    let sink: EventSink = Arc::new(move |v| {
        let _ = tx.send(v.clone());
    });
    (sink, rx)
}

/// The next event `pick` takes, skipping the others.
async fn next_event(
    json: &mut mpsc::UnboundedReceiver<Value>,
    pick: impl Fn(&Value) -> bool,
) -> Value {
    loop {
        let v = tokio::time::timeout(Duration::from_secs(10), json.recv())
            .await
            .unwrap()
            .unwrap();
        if pick(&v) {
            return v;
        }
    }
}

#[test]
fn parses_commands_stdin() {
    assert!(!Cli::try_parse_from(["sim"]).unwrap().args.commands_stdin);
    let cli = Cli::try_parse_from(["sim", "--boards", "4", "--commands-stdin"]).unwrap();
    assert!(cli.args.commands_stdin);
}

/// `--commands-stdin`: an alarm line reaches the board behind the live connection, which
/// raises the CNC alarm (status `alarm`), and a reset line clears it.
#[tokio::test]
async fn stdin_alarm_reaches_the_connected_board() {
    use tokio::io::AsyncWriteExt;
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let config = BoardConfig {
        first_request_delay: Duration::from_millis(10),
        ..BoardConfig::default()
    };
    let (sink, mut json) = event_channel();
    let slot = SessionSlot::default();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(serve_fanuc_board(
        listener,
        config,
        LineSettings::with_baud(115_200),
        None,
        sink.clone(),
        slot.clone(),
        async {
            let _ = stopped.await;
        },
    ));
    let (mut stdin, input) = tokio::io::duplex(1024);
    let router = tokio::spawn(async move {
        route_commands(tokio::io::BufReader::new(input), &[slot], &sink).await;
    });
    let _host = TcpStream::connect(addr).await.unwrap();
    next_event(&mut json, |v| v["event"] == "connected").await;
    stdin
        .write_all(b"{\"board\": 0, \"command\": \"alarm\"}\n")
        .await
        .unwrap();
    let answer = next_event(&mut json, |v| v["event"] == "command").await;
    assert_eq!(
        answer,
        json!({"event": "command", "command": "alarm", "applied": true})
    );
    next_event(&mut json, |v| v["event"] == "cnc-alarm").await;
    next_event(&mut json, |v| {
        v["event"] == "status" && v["status"] == "alarm"
    })
    .await;
    stdin.write_all(b"{\"command\":\"reset\"}\n").await.unwrap();
    let answer = next_event(&mut json, |v| v["event"] == "command").await;
    assert_eq!(answer["applied"], true, "{answer}");
    next_event(&mut json, |v| v["event"] == "cnc-reset").await;
    next_event(&mut json, |v| {
        v["event"] == "status" && v["status"] != "alarm"
    })
    .await;
    // EOF ends the commands only: the board keeps serving.
    drop(stdin);
    router.await.unwrap();
    assert!(!server.is_finished());
    stop.send(()).unwrap();
    server.await.unwrap().unwrap();
}

/// A board without a connection, before its first and after its last, takes no command;
/// with several boards the answer names the board.
#[tokio::test]
async fn stdin_command_to_a_board_without_connection_is_not_applied() {
    let (sink, mut json) = event_channel();
    let slots = [SessionSlot::default(), SessionSlot::default()];
    route_commands(&b"{\"board\":1,\"command\":\"reset\"}\n"[..], &slots, &sink).await;
    assert_eq!(
        json.recv().await.unwrap(),
        json!({
            "event": "command",
            "command": "reset",
            "board": 1,
            "applied": false,
            "reason": "no connection",
        })
    );
    // A session that has ended leaves its slot dead.
    let (tx, rx) = mpsc::unbounded_channel();
    slots[0].replace(&tx);
    drop((tx, rx));
    route_commands(&b"{\"command\":\"hold\"}"[..], &slots, &sink).await;
    let answer = json.recv().await.unwrap();
    assert_eq!(answer["board"], 0);
    assert_eq!(answer["applied"], false, "{answer}");
    assert_eq!(answer["reason"], "no connection");
}

/// Bad lines are answered with the reason and skipped; the line after each still works.
#[tokio::test]
async fn stdin_invalid_lines_say_why_and_the_next_still_works() {
    let (sink, mut json) = event_channel();
    let slot = SessionSlot::default();
    let (tx, mut rx) = mpsc::unbounded_channel();
    slot.replace(&tx);
    let mut input = Vec::new();
    input.extend_from_slice(b"{\"command\": \"alarm\"\n");
    input.extend_from_slice(b"[1, 2]\n");
    input.extend_from_slice(b"{\"command\": \"estop\"}\n");
    input.extend_from_slice(b"{\"board\": 1, \"command\": \"alarm\"}\n");
    input.extend_from_slice(b"{\"board\": -1, \"command\": \"alarm\"}\n");
    input.extend_from_slice(b"{\"command\": \"di\", \"value\": 256}\n");
    input.extend_from_slice(b"{\"board\": 0}\n");
    input.extend_from_slice(b"{\"command\": \"");
    input.extend(std::iter::repeat_n(b'a', MAX_COMMAND_LINE));
    input.extend_from_slice(b"\"}\n");
    input.extend_from_slice(b"\n  \r\n");
    input.extend_from_slice(b"{\"command\": \"di\", \"value\": 165}\r\n");
    input.extend_from_slice(b"{\"command\": \"start\"}");
    route_commands(&input[..], std::slice::from_ref(&slot), &sink).await;
    let mut answers = Vec::new();
    while let Ok(v) = json.try_recv() {
        answers.push(v);
    }
    let reasons: Vec<&str> = answers
        .iter()
        .filter_map(|v| v["reason"].as_str())
        .collect();
    assert_eq!(reasons.len(), 8, "{answers:#?}");
    for (reason, expected) in reasons.iter().zip([
        "not JSON",
        "not a JSON object",
        "unknown command \"estop\"",
        "board 1 out of range",
        "\"board\" is not a whole number",
        "di needs a \"value\" from 0 to 255",
        "no \"command\"",
        "line longer than 4096 bytes",
    ]) {
        assert!(
            reason.starts_with(expected),
            "{reason:?} is not {expected:?}"
        );
    }
    // One board: no "board" in the answers, as in the boards' own events.
    assert!(
        answers.iter().all(|v| v.get("board").is_none()),
        "{answers:#?}"
    );
    assert_eq!(answers[2]["command"], "estop");
    assert_eq!(
        answers[8],
        json!({"event": "command", "command": "di", "value": 165, "applied": true})
    );
    assert_eq!(
        answers[9],
        json!({"event": "command", "command": "start", "applied": true})
    );
    assert_eq!(answers.len(), 10, "{answers:#?}");
    assert_eq!(rx.try_recv(), Ok(BoardCommand::SetDi(165)));
    assert_eq!(rx.try_recv(), Ok(BoardCommand::StartReading));
    assert!(rx.try_recv().is_err());
}
