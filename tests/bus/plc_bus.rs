//! The PLC keys over zenoh, against a PLC link and a simulated MICREX-F assembled here (so
//! that the test can reach into the simulated PLC): every STA code as its typed error, reads
//! and writes of every attribute with their byte order on the line, and tags published on
//! change past their deadband. Real time, multi-thread runtime, loopback, multicast off.

use crate::common;

use std::time::Duration;

use cellgate::bus::{self, PlcLink};
use cellgate::plc::TagTable;
use cellgate::sim::micrex_handle::MicrexHandle;
use cellgate_core::config::{CellConfig, TransportConfig};
use cellgate_core::fuji::command::{FileType, Module};
use cellgate_core::fuji::master::Master;
use cellgate_core::pb;
use cellgate_core::sim::micrex::{MicrexCommand, MicrexEvent};
use common::bus::{client_config, free_port, get_err, get_one};
use prost::Message;
use tokio_util::sync::CancellationToken;

const PLC: &str = "plc-1";

fn config(port: u16, dir: &std::path::Path) -> CellConfig {
    let text = format!(
        r#"cell = "plc-bus"

[bus]
listen = ["tcp/127.0.0.1:{port}"]

[programs]
dir = "{}"

[[plcs]]
name = "{PLC}"
mode = 1
timeout_ms = 300

[plcs.transport]
kind = "sim"
line = {{ baud = 19200 }}

[plcs.sim]
messages = [1]

[[plcs.tags]]
name = "level"
module = "D"
address = 20
type = "u16"
poll_ms = 50
deadband = 10.0
"#,
        dir.join("programs").display()
    );
    CellConfig::from_toml_str(&text, "plc bus test").unwrap_or_else(|e| panic!("{e}"))
}

struct Rig {
    client: zenoh::Session,
    gateway: zenoh::Session,
    keys: cellgate::bus::keys::CellKeys,
    sim: MicrexHandle,
    stop: CancellationToken,
    served: tokio::task::JoinHandle<Result<(), bus::BusError>>,
    /// The simulated line: faults.
    line: cellgate::transport::sim::SimLine,
    _dir: tempfile::TempDir,
}

async fn start() -> Rig {
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let config = config(port, dir.path());
    let plc = config.plcs[0].clone();
    let TransportConfig::Sim { line } = plc.transport else {
        panic!("a sim transport");
    };
    // The module of the entry, with files of every type: W30 DI, W31 SI, W32 BD.
    let mut mc = cellgate_core::sim::micrex::MicrexConfig::for_plc(&plc);
    mc.files = vec![
        (30, FileType::Di, 64),
        (31, FileType::Si, 64),
        (32, FileType::Bd, 64),
    ];
    let (host, device, control) = cellgate::transport::sim::line(line);
    let sim = MicrexHandle::spawn(mc, Vec::new(), device).unwrap();
    let stop = CancellationToken::new();
    let (link, _task) = cellgate::plc::link::spawn(
        PLC,
        Master::new(plc.master_settings()).unwrap(),
        TagTable::new(PLC, &plc.tags),
        host,
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
    // The routes are up once the status key answers.
    let status = keys.plc_status(PLC);
    let mut up = false;
    for _ in 0..250 {
        let replies = common::bus::get(&client, &status, None).await;
        if replies.iter().any(|r| r.is_ok()) {
            up = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(up, "the PLC routes never answered {status}");
    Rig {
        client,
        gateway,
        keys,
        sim,
        stop,
        served,
        line: control,
        _dir: dir,
    }
}

impl Rig {
    fn mem(&self, module: &str, address: Option<u16>) -> String {
        self.keys.plc_mem(PLC, 0, module, address)
    }

    fn mem_write(&self, module: &str, address: Option<u16>) -> String {
        self.keys.plc_mem_write(PLC, 0, module, address)
    }

    async fn read(&self, module: &str, address: u16, count: usize) -> pb::PlcWords {
        let key = format!("{}?count={count}", self.mem(module, Some(address)));
        get_one(&self.client, &key, None).await
    }

    async fn write(&self, module: &str, address: u16, words: &[u32]) -> pb::PlcWritten {
        let w = pb::PlcWrite {
            words: words.to_vec(),
            clear: false,
        };
        get_one(
            &self.client,
            &self.mem_write(module, Some(address)),
            Some(w.encode_to_vec()),
        )
        .await
    }

    async fn read_err(&self, module: &str, address: u16) -> pb::ErrorReply {
        get_err(&self.client, &self.mem(module, Some(address)), None).await
    }

    async fn stop(self) {
        self.stop.cancel();
        let _ = tokio::time::timeout(Duration::from_secs(10), self.served).await;
        self.sim.shutdown().await;
        self.client.close().await.unwrap();
        self.gateway.close().await.unwrap();
    }
}

fn assert_sta(e: &pb::ErrorReply, code: pb::ErrorCode, sta: u32) {
    assert_eq!(e.code(), code, "{e:?}");
    assert_eq!(e.sta, Some(sta), "{e:?}");
    assert!(
        e.message.contains(&format!("STA {sta:02X}")),
        "the message names the code: {e:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_sta_code_is_typed_on_the_bus() {
    let rig = start().await;

    // 12: the words are in a write-protected range.
    rig.sim.command(MicrexCommand::Protect {
        station: 0,
        module: Module::D,
        address: 40,
        words: 2,
    });
    let w = pb::PlcWrite {
        words: vec![1],
        clear: false,
    };
    let e = get_err(
        &rig.client,
        &rig.mem_write("D", Some(41)),
        Some(w.encode_to_vec()),
    )
    .await;
    assert_sta(&e, pb::ErrorCode::PlcWriteProtected, 0x12);
    assert!(e.message.contains("program area"), "{e:?}");

    // 20 and 21 cannot be provoked by a correct host: the simulator forces them, on module B
    // (MOLN 00), which no tag polls.
    rig.sim.command(MicrexCommand::ForceNextSta {
        station: 0,
        moln: 0x00,
        sta: 0x20,
    });
    assert_sta(
        &rig.read_err("B", 0).await,
        pb::ErrorCode::PlcUndefinedCommand,
        0x20,
    );
    rig.sim.command(MicrexCommand::ForceNextSta {
        station: 0,
        moln: 0x00,
        sta: 0x21,
    });
    assert_sta(
        &rig.read_err("B", 0).await,
        pb::ErrorCode::PlcParameter,
        0x21,
    );

    // 22: interlock, reads and writes alike; lifted, the read works again.
    rig.sim.command(MicrexCommand::SetInterlock {
        station: 0,
        on: true,
    });
    let e = rig.read_err("D", 0).await;
    assert_sta(&e, pb::ErrorCode::PlcInterlock, 0x22);
    assert!(e.message.contains("loader"), "{e:?}");
    rig.sim.command(MicrexCommand::SetInterlock {
        station: 0,
        on: false,
    });
    rig.read("D", 0, 1).await;

    // 24: a file this PLC does not define; 32: beyond the module.
    assert_sta(
        &rig.read_err("W40", 0).await,
        pb::ErrorCode::PlcNoModule,
        0x24,
    );
    assert_sta(
        &rig.read_err("D", 65000).await,
        pb::ErrorCode::PlcOverMemory,
        0x32,
    );

    // A7: a transfer to a message number with no message module registered.
    let t = pb::PlcTransfer {
        plc: PLC.to_string(),
        message: 2,
        data: vec![0],
        from_plc: false,
        unix_ms: 0,
    };
    let e = get_err(
        &rig.client,
        &rig.keys.plc_transfer_send(PLC, 2),
        Some(t.encode_to_vec()),
    )
    .await;
    assert_sta(&e, pb::ErrorCode::PlcTransfer, 0xA7);

    // A code the manual does not list.
    rig.sim.command(MicrexCommand::ForceNextSta {
        station: 0,
        moln: 0x00,
        sta: 0x99,
    });
    assert_sta(
        &rig.read_err("B", 0).await,
        pb::ErrorCode::PlcOtherSta,
        0x99,
    );
    rig.stop().await;
}

/// The data bytes of the next write request the module sees.
async fn written_bytes(events: &mut tokio::sync::broadcast::Receiver<MicrexEvent>) -> Vec<u8> {
    loop {
        let e = tokio::time::timeout(Duration::from_secs(5), events.recv())
            .await
            .expect("a request within 5 s")
            .expect("module events");
        // Write 01/00: header (5), address (2), count (2), then the data.
        if let MicrexEvent::Request {
            cmnd: 0x01,
            mode: 0x00,
            text,
            ..
        } = e
        {
            return text[9..].to_vec();
        }
    }
}

/// Module key chunk, module, attribute code, words, their data bytes on the line.
type Case = (&'static str, Module, u32, Vec<u32>, Vec<u8>);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_attribute_is_read_and_written_in_its_byte_order() {
    let rig = start().await;
    let mut events = rig.sim.subscribe();
    let cases: [Case; 5] = [
        // 16-bit area: high byte first (FFU120B notes 4).
        (
            "D",
            Module::D,
            1,
            vec![0x1234, 0xFF83],
            vec![0x12, 0x34, 0xFF, 0x83],
        ),
        // 32-bit BCD area: low byte first.
        (
            "W9",
            Module::W9,
            2,
            vec![0x1234_5678],
            vec![0x78, 0x56, 0x34, 0x12],
        ),
        // SI file: 16-bit, low byte first.
        (
            "W31",
            Module::file(31, FileType::Si).unwrap(),
            3,
            vec![0xABCD],
            vec![0xCD, 0xAB],
        ),
        // DI file: 32-bit, low byte first.
        (
            "W30:DI",
            Module::file(30, FileType::Di).unwrap(),
            4,
            vec![0xDEAD_BEEF, 1],
            vec![0xEF, 0xBE, 0xAD, 0xDE, 1, 0, 0, 0],
        ),
        // BD file: 32-bit BCD, low byte first.
        (
            "W32:BD",
            Module::file(32, FileType::Bd).unwrap(),
            2,
            vec![0x0099_0001],
            vec![0x01, 0x00, 0x99, 0x00],
        ),
    ];
    for (chunk, module, attribute, words, wire) in cases {
        let written = rig.write(chunk, 3, &words).await;
        assert_eq!(written.words as usize, words.len(), "{chunk}: {written:?}");
        assert_eq!(
            written_bytes(&mut events).await,
            wire,
            "{chunk} on the line"
        );
        assert_eq!(
            rig.sim.words(0, module, 3, words.len()).await,
            Some(words.clone()),
            "{chunk} in the PLC"
        );
        let read = rig.read(chunk, 3, words.len()).await;
        assert_eq!(read.words, words, "{chunk} read back");
        assert_eq!(read.attribute, attribute, "{chunk}");
        // And what the PLC changes by itself reads as it holds it.
        let own: Vec<u32> = words.iter().map(|w| w ^ 0x0101).collect();
        rig.sim.command(MicrexCommand::SetWords {
            station: 0,
            module,
            address: 3,
            words: own.clone(),
        });
        assert_eq!(rig.read(chunk, 3, own.len()).await.words, own, "{chunk}");
    }
    rig.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tag_is_published_on_change_past_its_deadband() {
    let rig = start().await;
    let key = rig.keys.plc_tag(PLC, "level");
    let sub = rig.client.declare_subscriber(key.as_str()).await.unwrap();
    let set = |v: u32| {
        rig.sim.command(MicrexCommand::SetWords {
            station: 0,
            module: Module::D,
            address: 20,
            words: vec![v],
        })
    };
    let next = || async {
        let s = tokio::time::timeout(Duration::from_secs(5), sub.recv_async())
            .await
            .expect("a tag sample within 5 s")
            .unwrap();
        pb::TagValue::decode(s.payload().to_bytes().as_ref()).unwrap()
    };
    // The first good value, whatever came before it.
    set(100);
    let first = loop {
        let v = next().await;
        if v.value == Some(100.0) {
            break v;
        }
    };
    assert_eq!(first.quality(), pb::TagQuality::Good);
    // Changes within the deadband of 10 (from the last published value) are not published,
    // even when they add up to more than 10 in steps; the one beyond it is.
    for v in [105, 109, 95, 91] {
        set(v);
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
    set(111);
    let v = next().await;
    assert_eq!(v.value, Some(111.0), "{v:?}");
    // Nothing else came: no sample waits.
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(sub.try_recv().unwrap().is_none());
    // A get returns the latest value.
    let got: pb::TagValue = get_one(&rig.client, &key, None).await;
    assert_eq!(got.value, Some(111.0));
    drop(sub);
    rig.stop().await;
}

/// A character of a reply hit on the line (its start code, reported as a parity error by the
/// UART or the gateway's own parity check): the reply is dropped and asked for again, and the
/// PLC's status on the bus says so (FFU120B §5-6: the operator tells a noisy line).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_character_error_is_counted_in_the_plcs_status() {
    let rig = start().await;
    let from_plc = cellgate::transport::sim::End::Device.tx();
    rig.line
        .error_next(from_plc, cellgate::transport::LineError::Parity);
    let key = rig.keys.plc_status(PLC);
    let mut status = pb::PlcStatus::default();
    for _ in 0..100 {
        status = get_one(&rig.client, &key, None).await;
        if status.line_errors.get("parity").copied().unwrap_or(0) > 0
            && status.receive_errors.get("character").copied().unwrap_or(0) > 0
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(status.line_errors.get("parity"), Some(&1), "{status:?}");
    assert_eq!(status.line_errors.get("framing"), Some(&0), "{status:?}");
    // The text whose start code was hit is one text ended by a character error, not noise.
    assert_eq!(
        status.receive_errors.get("character"),
        Some(&1),
        "{status:?}"
    );
    assert_eq!(
        status.receive_errors.get("start_code"),
        Some(&0),
        "{status:?}"
    );
    // `cellgate plc status` shows it.
    let text = cellgate::client::render::plc_status_text(std::slice::from_ref(&status), 0);
    assert!(
        text.contains("plc-1: line errors: parity 1; texts dropped: character 1"),
        "{text}"
    );
    rig.stop().await;
}
