//! FFU120B non-procedure mode 4 (FFU120B §5-5; FFU120B notes 9) over the bus: the gateway is
//! the external device of a simulated FFU120B served as a TCP serial device server
//! (`serve_fuji_on`, the module behind `cellgate sim fuji`), through a `kind = "tcp"` PLC link.
//! Fixed-length messages both ways, 2N hex characters for N bytes with code transposition on
//! (FFU120B §4-3 items 14–15): what the PLC sends is published on `…/message`, what a
//! client sends on `…/message/send` reaches the module's receive message number. Real time,
//! loopback, multicast off.

use crate::common;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use cellgate::bus::{self, PlcLink};
use cellgate::plc::TagTable;
use cellgate::sim::fuji_server::{TransferArg, TransferPlan, serve_fuji_on};
use cellgate::transport::tcp::{TcpOptions, TcpTransport};
use cellgate_core::config::{CellConfig, TransportConfig};
use cellgate_core::fuji::master::Master;
use cellgate_core::pb;
use cellgate_core::sim::micrex::MicrexConfig;
use common::bus::{client_config, free_port, get_err, get_one};
use prost::Message;
use serde_json::Value;
use tokio_util::sync::CancellationToken;

const PLC: &str = "scanner";

fn config(port: u16, sim_port: u16, dir: &std::path::Path) -> CellConfig {
    let text = format!(
        r#"cell = "plc-messages"

[bus]
listen = ["tcp/127.0.0.1:{port}"]

[programs]
dir = "{}"

[[plcs]]
name = "{PLC}"
mode = 4
fixed_length = 12
receive_message = 9
transport = {{ kind = "tcp", address = "127.0.0.1:{sim_port}", line = {{ baud = 9600 }} }}
"#,
        dir.join("programs").display()
    );
    CellConfig::from_toml_str(&text, "plc messages test").unwrap_or_else(|e| panic!("{e}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mode_4_fixed_length_messages_both_ways_over_tcp_and_the_bus() {
    let dir = tempfile::tempdir().unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let sim_port = listener.local_addr().unwrap().port();
    let port = free_port();
    let config = config(port, sim_port, dir.path());
    let plc = config.plcs[0].clone();

    // The simulated module of the entry, sending two messages once the gateway connects.
    let sim_events: Arc<Mutex<Vec<Value>>> = Arc::default();
    let sink = {
        let events = Arc::clone(&sim_events);
        Arc::new(move |v: &Value| events.lock().unwrap().push(v.clone()))
    };
    let plan = TransferPlan {
        transfers: vec![
            TransferArg {
                message: 0,
                data: b"SCAN-0000042".to_vec(),
            },
            TransferArg {
                message: 0,
                data: b"SCAN-0000043".to_vec(),
            },
        ],
        after: Duration::from_millis(1500),
    };
    let stop = CancellationToken::new();
    let server = {
        let stop = stop.clone();
        tokio::spawn(async move {
            serve_fuji_on(
                listener,
                MicrexConfig::for_plc(&plc),
                plan,
                sink,
                stop.cancelled_owned(),
            )
            .await
        })
    };

    let plc = config.plcs[0].clone();
    let TransportConfig::Tcp { address, line, .. } = &plc.transport else {
        panic!("a tcp transport");
    };
    let transport = TcpTransport::connect(address.clone(), *line, TcpOptions::default())
        .await
        .unwrap();
    let (link, _task) = cellgate::plc::link::spawn(
        PLC,
        Master::new(plc.master_settings()).unwrap(),
        TagTable::new(PLC, &plc.tags),
        transport,
        stop.clone(),
    );
    let gateway = bus::open(&config.bus).await.unwrap();
    let served = {
        let (gw, cfg, stop) = (gateway.clone(), config.clone(), stop.clone());
        let plcs = vec![PlcLink {
            config: plc.clone(),
            link,
        }];
        tokio::spawn(async move { bus::serve_plcs(&gw, &cfg, plcs, stop).await })
    };
    let client = bus::open(&client_config(port)).await.unwrap();
    let keys = cellgate::bus::keys::CellKeys::new(&config.bus.prefix, &config.cell).unwrap();
    let messages = client
        .declare_subscriber(keys.plc_message(PLC))
        .await
        .unwrap();
    // The routes are up once the status key answers.
    let mut status = None;
    for _ in 0..250 {
        let replies = common::bus::get(&client, &keys.plc_status(PLC), None).await;
        if let Some(Ok((_, payload, _))) = replies.into_iter().next() {
            status = Some(pb::PlcStatus::decode(payload.as_slice()).unwrap());
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let status = status.expect("the PLC routes never answered");
    assert_eq!((status.mode, status.fixed_length), (4, 12));

    // What the PLC sends is published, each message whole and in order: 24 characters on the
    // line are one 12-byte message, not two.
    let mut got = Vec::new();
    while got.len() < 2 {
        let s = tokio::time::timeout(Duration::from_secs(20), messages.recv_async())
            .await
            .expect("the PLC's messages are published")
            .unwrap();
        let m = pb::PlcMessage::decode(s.payload().to_bytes().as_ref()).unwrap();
        assert!(m.from_plc);
        got.push(m.data);
    }
    assert_eq!(got, [b"SCAN-0000042".to_vec(), b"SCAN-0000043".to_vec()]);

    // A client's message goes to the module's receive message number, bare (fixed length: no
    // start code, end code or BCC) and, with code transposition on (the initial value, FFU120B
    // §4-3 items 14–15), as 24 hex characters for its 12 bytes.
    let send = keys.plc_message_send(PLC);
    let m = pb::PlcMessage {
        data: b"LOT-00000007".to_vec(),
        ..pb::PlcMessage::default()
    };
    let sent: pb::PlcMessageSent = get_one(&client, &send, Some(m.encode_to_vec())).await;
    assert_eq!(
        (sent.bytes, sent.line_bytes, sent.receive_message),
        (12, 24, 9)
    );
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    let received = loop {
        let found = sim_events
            .lock()
            .unwrap()
            .iter()
            .find(|v| v["event"] == "transfer-received")
            .cloned();
        if let Some(v) = found {
            break v;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the module got no message"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(received["message"], 9, "{received}");
    assert_eq!(
        received["hex"],
        hex::encode_upper(b"LOT-00000007"),
        "{received}"
    );

    // A message of another length, and the command set, are refused: typed, nothing sent.
    let short = pb::PlcMessage {
        data: b"SHORT".to_vec(),
        ..pb::PlcMessage::default()
    };
    let e = get_err(&client, &send, Some(short.encode_to_vec())).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{e:?}");
    assert!(e.message.contains("exactly 12"), "{}", e.message);
    let e = get_err(&client, &keys.plc_mem(PLC, 0, "D", Some(0)), None).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{e:?}");
    assert!(e.message.contains("mode 4"), "{}", e.message);

    let status: pb::PlcStatus = get_one(&client, &keys.plc_status(PLC), None).await;
    assert_eq!(
        (status.messages_received, status.messages_sent),
        (2, 1),
        "{status:?}"
    );

    stop.cancel();
    let _ = tokio::time::timeout(Duration::from_secs(10), served).await;
    let _ = tokio::time::timeout(Duration::from_secs(10), server).await;
    client.close().await.unwrap();
    gateway.close().await.unwrap();
}
