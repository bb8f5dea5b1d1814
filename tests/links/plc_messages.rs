//! FFU120B non-procedure mode 4 (FFU120B §5-5; FFU120B notes 9) over the bus: the gateway is
//! the external device of a simulated FFU120B served as a TCP serial device server
//! (`serve_fuji_on`, the module behind `cellgate sim fuji`), through a `kind = "tcp"` PLC link.
//! Fixed-length messages both ways, 2N hex characters for N bytes with code transposition on
//! (FFU120B §4-3 items 14–15): what the PLC sends is published on `…/message`, what a
//! client sends on `…/message/send` reaches the module's receive message number. And a 7E1
//! line behind a device server that passes whole 8-bit frames, the parity made and checked by
//! the gateway (`parity_by = "gateway"`). Real time, loopback, multicast off.

use crate::common;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use cellgate::bus::keys::CellKeys;
use cellgate::bus::{self, PlcLink};
use cellgate::plc::TagTable;
use cellgate::sim::fuji_server::{SessionPlan, TransferArg, serve_fuji_on};
use cellgate_core::config::CellConfig;
use cellgate_core::fuji::master::Master;
use cellgate_core::pb;
use cellgate_core::sim::micrex::MicrexConfig;
use common::bus::{client_config, free_port, get_err, get_one};
use prost::Message;
use serde_json::Value;
use tokio_util::sync::CancellationToken;

const PLC: &str = "scanner";

fn config(port: u16, dir: &std::path::Path, plc: &str) -> CellConfig {
    let text = format!(
        r#"cell = "plc-messages"

[bus]
listen = ["tcp/127.0.0.1:{port}"]

[programs]
dir = "{}"

[[plcs]]
name = "{PLC}"
mode = 4
receive_message = 9
{plc}
"#,
        dir.join("programs").display()
    );
    CellConfig::from_toml_str(&text, "plc messages test").unwrap_or_else(|e| panic!("{e}"))
}

/// The simulated module behind a device server, the gateway's PLC link to it, and a client.
struct Harness {
    client: zenoh::Session,
    gateway: zenoh::Session,
    keys: CellKeys,
    messages: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    sim_events: Arc<Mutex<Vec<Value>>>,
    stop: CancellationToken,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Harness {
    /// `plc`: the entry's keys after mode and receive message, its transport included (the
    /// device server's address is `{sim}`); `plan`: what the simulated module does.
    async fn start(dir: &std::path::Path, plc: &str, plan: SessionPlan) -> Harness {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let sim_port = listener.local_addr().unwrap().port();
        let port = free_port();
        let config = config(
            port,
            dir,
            &plc.replace("{sim}", &format!("127.0.0.1:{sim_port}")),
        );
        let plc = config.plcs[0].clone();
        let sim_events: Arc<Mutex<Vec<Value>>> = Arc::default();
        let sink = {
            let events = Arc::clone(&sim_events);
            Arc::new(move |v: &Value| events.lock().unwrap().push(v.clone()))
        };
        let stop = CancellationToken::new();
        let server = {
            let (stop, plc) = (stop.clone(), plc.clone());
            tokio::spawn(async move {
                serve_fuji_on(
                    listener,
                    MicrexConfig::for_plc(&plc),
                    plan,
                    sink,
                    stop.cancelled_owned(),
                )
                .await
                .unwrap();
            })
        };
        // The device server, opened as the gateway opens it (and the parity around it).
        let transport = cellgate::cell::open_transport(PLC, &plc.transport, 256)
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
            tokio::spawn(async move {
                let _ = bus::serve_plcs(&gw, &cfg, plcs, stop).await;
            })
        };
        let client = bus::open(&client_config(port)).await.unwrap();
        let keys = CellKeys::new(&config.bus.prefix, &config.cell).unwrap();
        let messages = client
            .declare_subscriber(keys.plc_message(PLC))
            .await
            .unwrap();
        let h = Harness {
            client,
            gateway,
            keys,
            messages,
            sim_events,
            stop,
            tasks: vec![server, served],
        };
        // The routes are up once the status key answers.
        for _ in 0..250 {
            let replies = common::bus::get(&h.client, &h.keys.plc_status(PLC), None).await;
            if let Some(Ok(_)) = replies.into_iter().next() {
                return h;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        panic!("the PLC routes never answered");
    }

    async fn status(&self) -> pb::PlcStatus {
        get_one(&self.client, &self.keys.plc_status(PLC), None).await
    }

    /// The next `n` messages the gateway publishes, in order.
    async fn published(&self, n: usize) -> Vec<Vec<u8>> {
        let mut got = Vec::new();
        while got.len() < n {
            let s = tokio::time::timeout(Duration::from_secs(20), self.messages.recv_async())
                .await
                .expect("the PLC's messages are published")
                .unwrap();
            let m = pb::PlcMessage::decode(s.payload().to_bytes().as_ref()).unwrap();
            assert!(m.from_plc);
            got.push(m.data);
        }
        got
    }

    /// Sends `data` on `…/message/send`; the answer.
    async fn send(&self, data: &[u8]) -> pb::PlcMessageSent {
        let m = pb::PlcMessage {
            data: data.to_vec(),
            ..pb::PlcMessage::default()
        };
        get_one(
            &self.client,
            &self.keys.plc_message_send(PLC),
            Some(m.encode_to_vec()),
        )
        .await
    }

    /// The first simulator event named `name`, waiting for it.
    async fn sim_event(&self, name: &str) -> Value {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
        loop {
            let found = self
                .sim_events
                .lock()
                .unwrap()
                .iter()
                .find(|v| v["event"] == name)
                .cloned();
            if let Some(v) = found {
                return v;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "the module had no {name} event"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    async fn stop(self) {
        self.stop.cancel();
        for t in self.tasks {
            let _ = tokio::time::timeout(Duration::from_secs(10), t).await;
        }
        self.client.close().await.unwrap();
        self.gateway.close().await.unwrap();
    }
}

fn transfers(data: &[&[u8]]) -> SessionPlan {
    SessionPlan {
        transfers: data
            .iter()
            .map(|d| TransferArg {
                message: 0,
                data: d.to_vec(),
            })
            .collect(),
        after: Duration::from_millis(1500),
        ..SessionPlan::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mode_4_fixed_length_messages_both_ways_over_tcp_and_the_bus() {
    let dir = tempfile::tempdir().unwrap();
    let h = Harness::start(
        dir.path(),
        "fixed_length = 12\n\
         transport = { kind = \"tcp\", address = \"{sim}\", line = { baud = 9600 } }",
        transfers(&[b"SCAN-0000042", b"SCAN-0000043"]),
    )
    .await;
    let status = h.status().await;
    assert_eq!((status.mode, status.fixed_length), (4, 12));

    // What the PLC sends is published, each message whole and in order: 24 characters on the
    // line are one 12-byte message, not two.
    assert_eq!(
        h.published(2).await,
        [b"SCAN-0000042".to_vec(), b"SCAN-0000043".to_vec()]
    );

    // A client's message goes to the module's receive message number, bare (fixed length: no
    // start code, end code or BCC) and, with code transposition on (the initial value, FFU120B
    // §4-3 items 14–15), as 24 hex characters for its 12 bytes.
    let sent = h.send(b"LOT-00000007").await;
    assert_eq!(
        (sent.bytes, sent.line_bytes, sent.receive_message),
        (12, 24, 9)
    );
    let received = h.sim_event("transfer-received").await;
    assert_eq!(received["message"], 9, "{received}");
    assert_eq!(
        received["hex"],
        hex::encode_upper(b"LOT-00000007"),
        "{received}"
    );

    // A message of another length, and the command set, are refused: typed, nothing sent.
    let send = h.keys.plc_message_send(PLC);
    let short = pb::PlcMessage {
        data: b"SHORT".to_vec(),
        ..pb::PlcMessage::default()
    };
    let e = get_err(&h.client, &send, Some(short.encode_to_vec())).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{e:?}");
    assert!(e.message.contains("exactly 12"), "{}", e.message);
    let e = get_err(&h.client, &h.keys.plc_mem(PLC, 0, "D", Some(0)), None).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{e:?}");
    assert!(e.message.contains("mode 4"), "{}", e.message);

    let status = h.status().await;
    assert_eq!(
        (status.messages_received, status.messages_sent),
        (2, 1),
        "{status:?}"
    );
    h.stop().await;
}

/// A 7E1 line behind a device server set to 8N1: it passes each character's whole frame,
/// the parity bit in bit 7 (FFU120B §4-3 items 5–6; FFU120B notes 10). With
/// `parity_by = "gateway"` the gateway adds even parity to what it sends, so the module takes
/// its message without a parity error, and checks it in what it receives: the module's
/// messages are published without their parity bits, and one whose character went out with
/// the wrong parity ends as a receive error while the next one still arrives (§5-6).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn parity_made_and_checked_by_the_gateway_behind_a_device_server_passing_frames() {
    let dir = tempfile::tempdir().unwrap();
    // Variable length: ':' + 12 hex characters + CR, 14 characters a message; the fifth
    // character of the second one goes out with a wrong parity bit.
    let mut plan = transfers(&[b"SCAN-1", b"SCAN-2", b"SCAN-3"]);
    plan.parity_by = cellgate_core::engine::parity::ParityBy::Gateway;
    plan.spoil_parity = vec![14 + 4];
    let h = Harness::start(
        dir.path(),
        "transport = { kind = \"tcp\", address = \"{sim}\", parity_by = \"gateway\", \
         line = { baud = 9600, data_bits = 7, parity = \"even\", stop_bits = 1 } }",
        plan,
    )
    .await;
    assert_eq!(
        h.published(2).await,
        [b"SCAN-1".to_vec(), b"SCAN-3".to_vec()]
    );
    let sent = h.send(b"LOT-7").await;
    assert_eq!((sent.bytes, sent.line_bytes), (5, 12));
    let received = h.sim_event("transfer-received").await;
    assert_eq!(received["hex"], hex::encode_upper(b"LOT-7"), "{received}");
    let status = h.status().await;
    assert_eq!(status.messages_received, 2, "{status:?}");
    assert_eq!(status.receive_errors["character"], 1, "{status:?}");
    let total: u64 = status.receive_errors.values().sum();
    assert_eq!(total, 1, "{status:?}");
    assert!(
        !h.sim_events
            .lock()
            .unwrap()
            .iter()
            .any(|v| v["event"] == "line-error" || v["event"] == "receive-error"),
        "the module found no error in what the gateway sent"
    );
    h.stop().await;
}
