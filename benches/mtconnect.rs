//! What the MTConnect agent costs on a cell of 1 024 machines.
//!
//! The agent is fed as the gateway feeds it (the bus contract's messages, applied to the
//! shared agent), without zenoh, so that only the agent is measured:
//!
//! 1. `/current` of 1 024 machines (and a PLC with 16 tags): the XML and JSON documents
//!    rendered from the agent, median and slowest of 50, and over HTTP (axum, loopback);
//! 2. the sequence buffer's memory: the size of a slot, and what a full buffer of the
//!    observations this cell makes takes in all (allocator statistics are not used: the
//!    figure is slots × slot size + the text each value holds);
//! 3. ten streaming `/sample` clients (`interval=1000`, as monitoring tools poll) on a busy
//!    cell, the DI image of every Protocol A machine (half of them) changing 4 times a second
//!    (2 048 observations/s), every machine's status taken: the process's CPU over 10 s
//!    without clients and with them, as a share of one core.
//!
//! `cargo bench --bench mtconnect` prints the figures; under `cargo test` a short smoke run
//! (16 machines, 1 s) checks that it runs.

use std::sync::Arc;
use std::time::{Duration, Instant};

use cellgate::mtconnect::{Hub, http};
use cellgate_core::fanuc::Protocol;
use cellgate_core::mtconnect::buffer::{Observation, Value};
use cellgate_core::mtconnect::desc::{CellDesc, MachineDesc, PlcDesc, TagDesc};
use cellgate_core::mtconnect::{Agent, Format, Query, Update};
use cellgate_core::pb;
use tokio_util::sync::CancellationToken;

fn now_us() -> u64 {
    cellgate::mtconnect::now_us()
}

fn cpu_seconds() -> f64 {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: getrusage writes a rusage into the pointer it is given.
    let usage = unsafe {
        libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr());
        usage.assume_init()
    };
    let t = |tv: libc::timeval| tv.tv_sec as f64 + tv.tv_usec as f64 / 1e6;
    t(usage.ru_utime) + t(usage.ru_stime)
}

fn cell(machines: usize) -> CellDesc {
    CellDesc {
        cell: "bench".into(),
        machines: (0..machines)
            .map(|i| MachineDesc {
                name: format!("m{i:04}"),
                protocol: if i % 2 == 0 { Protocol::A } else { Protocol::B },
                part_counter: None,
                g05: false,
                identification: Default::default(),
            })
            .collect(),
        plcs: vec![PlcDesc {
            name: "plc-1".into(),
            stations: vec![0],
            tags: (0..16)
                .map(|t| TagDesc {
                    name: format!("t{t}"),
                    native: format!("D{t}"),
                    typed: None,
                    units: None,
                })
                .collect(),
        }],
    }
}

fn status(i: usize, di: u32) -> pb::MachineStatus {
    pb::MachineStatus {
        machine: format!("m{i:04}"),
        protocol: if i % 2 == 0 {
            pb::Protocol::A
        } else {
            pb::Protocol::B
        } as i32,
        link_state: if i % 3 == 0 {
            pb::LinkState::Sending
        } else {
            pb::LinkState::Idle
        } as i32,
        di_image: Some(di),
        ..Default::default()
    }
}

fn agent(machines: usize, buffer: usize) -> Agent {
    let now = now_us();
    let mut a = Agent::new("bench", 1, buffer, now);
    a.add_cell(&cell(machines), now);
    a.update("bench", Update::Gateway(true), now);
    for i in 0..machines {
        a.update("bench", Update::Status(Box::new(status(i, 0))), now);
    }
    a
}

fn median(mut v: Vec<Duration>) -> (Duration, Duration) {
    v.sort();
    (v[v.len() / 2], *v.last().unwrap_or(&Duration::ZERO))
}

fn ms(d: Duration) -> String {
    format!("{:.1} ms", d.as_secs_f64() * 1000.0)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    let (machines, runs, secs) = if full { (1024, 50, 10) } else { (16, 3, 1) };

    // 1. /current.
    let a = agent(machines, 131_072);
    let items = a.model().items.len();
    let mut xml = Vec::new();
    let mut json = Vec::new();
    let mut size = (0, 0);
    for _ in 0..runs {
        let t = Instant::now();
        let d = a.current(None, &Query::default(), now_us()).unwrap();
        xml.push(t.elapsed());
        size.0 = d.len();
        let t = Instant::now();
        let q = Query {
            format: Format::Json,
            ..Query::default()
        };
        let d = a.current(None, &q, now_us()).unwrap();
        json.push(t.elapsed());
        size.1 = d.len();
    }
    let (xm, xs) = median(xml);
    let (jm, js) = median(json);
    println!("/current of {machines} machines ({items} data items), {runs} runs:");
    println!(
        "  XML:  median {}, slowest {} ({} KiB)",
        ms(xm),
        ms(xs),
        size.0 / 1024
    );
    println!(
        "  JSON: median {}, slowest {} ({} KiB)",
        ms(jm),
        ms(js),
        size.1 / 1024
    );

    let hub = Hub::new(a);
    let stop = CancellationToken::new();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let app = http::router(Arc::clone(&hub), stop.clone());
    let server = {
        let stop = stop.clone();
        tokio::spawn(async move {
            axum::serve(listener, app)
                .with_graceful_shutdown(async move { stop.cancelled().await })
                .await
        })
    };
    let _ = tokio_rustls::rustls::crypto::ring::default_provider().install_default();
    let client = reqwest::Client::new();
    let mut over_http = Vec::new();
    for _ in 0..runs {
        let t = Instant::now();
        let body = client
            .get(format!("http://{addr}/current"))
            .send()
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap();
        over_http.push(t.elapsed());
        assert!(body.len() > 1000);
    }
    let (hm, hs) = median(over_http);
    println!(
        "  XML over HTTP (loopback): median {}, slowest {}",
        ms(hm),
        ms(hs)
    );

    // 2. Memory of the buffer.
    let slot = std::mem::size_of::<Observation>();
    let text: usize = {
        let agent = hub.lock();
        let latest = agent.buffer().latest();
        let texts: Vec<usize> = latest
            .iter()
            .filter_map(|s| s.last.as_ref())
            .map(|o| match &o.value {
                Value::Text(t) => t.len() + 16,
                Value::Cond(c) => c.native_code.len() + c.text.len() + 32,
                Value::Unavailable => 0,
            })
            .collect();
        texts.iter().sum::<usize>() / texts.len().max(1)
    };
    println!(
        "sequence buffer: {slot} bytes a slot + its value's text (here {text} bytes on average): \
         {:.1} MiB for the default 131 072 slots",
        (131_072 * (slot + text)) as f64 / (1 << 20) as f64
    );

    // 3. Streaming clients on a busy cell.
    let busy = {
        let hub = Arc::clone(&hub);
        let stop = stop.clone();
        tokio::spawn(async move {
            // Every machine's status 4 times a second, in 40 slices of 25 ms, its DI changed.
            let mut tick = tokio::time::interval(Duration::from_millis(25));
            let mut di = 0u32;
            loop {
                tokio::select! {
                    () = stop.cancelled() => return,
                    _ = tick.tick() => {}
                }
                di = di.wrapping_add(1);
                let now = now_us();
                {
                    let mut a = hub.lock();
                    for i in (di as usize % 10..machines).step_by(10) {
                        a.update("bench", Update::Status(Box::new(status(i, di % 256))), now);
                    }
                }
                hub.changed();
            }
        })
    };
    let window = Duration::from_secs(secs);
    let measure = || async {
        let c0 = cpu_seconds();
        let next0 = hub.lock().buffer().next();
        tokio::time::sleep(window).await;
        let made = hub.lock().buffer().next() - next0;
        ((cpu_seconds() - c0) / window.as_secs_f64(), made)
    };
    let (none, made) = measure().await;
    let mut clients = Vec::new();
    let received = Arc::new(std::sync::atomic::AtomicU64::new(0));
    for _ in 0..10 {
        let (client, received) = (client.clone(), Arc::clone(&received));
        let url = format!(
            "http://{addr}/sample?interval=1000&count=10000&from={}",
            hub.lock().buffer().next()
        );
        clients.push(tokio::spawn(async move {
            let mut r = client.get(url).send().await.unwrap();
            while let Ok(Some(chunk)) = r.chunk().await {
                received.fetch_add(chunk.len() as u64, std::sync::atomic::Ordering::Relaxed);
            }
        }));
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let (ten, _) = measure().await;
    println!(
        "busy cell ({} observations/s): CPU without clients {:.1} % of a core, with 10 \
         streaming /sample clients (interval=1000) {:.1} %: {:.1} % more ({} KiB/s streamed)",
        made / secs,
        none * 100.0,
        ten * 100.0,
        (ten - none) * 100.0,
        received.load(std::sync::atomic::Ordering::Relaxed) / 1024 / (secs + 1)
    );
    stop.cancel();
    busy.await.unwrap();
    for c in clients {
        c.abort();
    }
    let _ = server.await;
}
