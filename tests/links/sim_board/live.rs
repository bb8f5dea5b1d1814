use super::*;
use cellgate::sim::BoardHandle;
use cellgate::sim::server::PacedLine;
use cellgate::sim::server::{EventSink, serve_fanuc_on};
use cellgate::transport::LineSettings;
use std::sync::Arc;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};

/// Reads one message (up to CR) from the board.
async fn read_msg(rd: &mut (impl AsyncRead + Unpin)) -> Message {
    let mut frame = Vec::new();
    loop {
        let b = rd.read_u8().await.unwrap();
        frame.push(b);
        if b == b'\r' {
            return Framing::default().decode(&frame).unwrap();
        }
    }
}

async fn expect(rd: &mut (impl AsyncRead + Unpin), cmd: Command) -> Message {
    let m = read_msg(rd).await;
    assert_eq!(m.command, cmd, "got {m:?}");
    m
}

async fn send(wr: &mut (impl AsyncWrite + Unpin), msg: Message) {
    let bytes = Framing::default().encode_to_vec(&msg).unwrap();
    wr.write_all(&bytes).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn board_handle_over_a_pipe() {
    let (host, line) = tokio::io::duplex(64 * 1024);
    let config = BoardConfig {
        consume_rate: 0,
        ..BoardConfig::default()
    };
    let handle = BoardHandle::spawn(config, PacedLine::unpaced(line, "pipe")).unwrap();
    let mut events = handle.subscribe();
    let (mut rd, mut wr) = tokio::io::split(host);

    let start = tokio::time::Instant::now();
    expect(&mut rd, Command::Syn).await;
    assert_eq!(start.elapsed(), s(2));
    send(&mut wr, Message::new(Command::Syn)).await;
    expect(&mut rd, Command::Rdy).await;
    send(&mut wr, Message::new(Command::Rdy)).await;
    handle.wait_for(|s| s.link == BoardLinkState::Ready).await;

    handle.set_di(0x42);
    handle.start_reading();
    expect(&mut rd, Command::Gtd).await;
    send(&mut wr, Message::new(Command::Rdi)).await;
    let sdi = expect(&mut rd, Command::Sdi).await;
    assert_eq!(sdi.data, b"42");
    let prog = program(40);
    send(&mut wr, Message::with_data(Command::Dat, prog.clone())).await;
    let snap = handle.wait_for(|s| !s.programs.is_empty()).await;
    assert_eq!(snap.programs[0].sha256, sha(&prog));
    assert_eq!(handle.programs()[0].first_line, "O1234 (SIM)");

    let sat = expect(&mut rd, Command::Sat).await;
    assert_eq!(
        StatusData::decode(&sat.data).unwrap().status,
        Some(BufferStatus::Reset)
    );
    send(&mut wr, Message::with_data(Command::Sdo, "77")).await;
    handle.wait_for(|s| s.do_image == 0x77).await;
    assert_eq!(handle.do_image(), 0x77);

    let mut seen_program = false;
    while let Ok(e) = events.try_recv() {
        seen_program |= matches!(e, BoardEvent::ProgramReceived(_));
    }
    assert!(seen_program);
    handle.shutdown().await.unwrap();
}

#[tokio::test]
async fn tcp_device_server_reports_programs_as_json() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let config = BoardConfig {
        first_request_delay: ms(20),
        params: Params {
            tx: 0,
            tp: 1,
            tw: 1,
            ..Params::POWER_ON
        },
        consume_rate: 0,
        autostart: true,
        ..BoardConfig::default()
    };
    let (tx, mut json) = tokio::sync::mpsc::unbounded_channel();
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

    let stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    let (mut rd, mut wr) = stream.into_split();
    expect(&mut rd, Command::Syn).await;
    send(&mut wr, Message::new(Command::Syn)).await;
    expect(&mut rd, Command::Rdy).await;
    send(&mut wr, Message::new(Command::Rdy)).await;
    // Autostart: the CNC reads after the first SAT.
    expect(&mut rd, Command::Sat).await;
    send(&mut wr, Message::new(Command::Set)).await;
    expect(&mut rd, Command::Gtd).await;
    let prog = program(10);
    send(&mut wr, Message::with_data(Command::Dat, prog.clone())).await;

    let program_event = loop {
        let v = tokio::time::timeout(s(10), json.recv())
            .await
            .unwrap()
            .unwrap();
        if v["event"] == "program" {
            break v;
        }
    };
    assert_eq!(program_event["bytes"], prog.len());
    assert_eq!(program_event["sha256"], hex::encode(sha(&prog)));
    assert_eq!(program_event["first_line"], "O1234 (SIM)");
    // It reads again: GTD; no more data.
    expect(&mut rd, Command::Gtd).await;
    send(&mut wr, Message::new(Command::Eod)).await;

    // A new connection is the line up again: the board powers on afresh.
    drop((rd, wr));
    let stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    let (mut rd, _wr) = stream.into_split();
    expect(&mut rd, Command::Syn).await;

    stop.send(()).unwrap();
    server.await.unwrap().unwrap();
    let mut kinds = Vec::new();
    while let Ok(v) = json.try_recv() {
        kinds.push(v["event"].as_str().unwrap_or_default().to_string());
    }
    assert!(kinds.contains(&"disconnected".to_string()), "{kinds:?}");
    assert!(kinds.contains(&"connected".to_string()), "{kinds:?}");
}
