//! Zenoh client helpers for tests that talk to a gateway over loopback.
#![allow(dead_code)]

use std::time::Duration;

use cellgate_core::pb;
use prost::Message;
use zenoh::Session;

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A first port with `n - 1` free ports after it (checked by binding them all), below the
/// ephemeral range (32768 and up on Linux), where many in a row are rarely all free.
pub fn free_ports(n: u16) -> u16 {
    let mut first = 10_000;
    while first + n < 32_768 {
        let bound: Vec<_> = (0..n)
            .map_while(|i| std::net::TcpListener::bind(("127.0.0.1", first + i)).ok())
            .collect();
        if bound.len() == usize::from(n) {
            return first;
        }
        first += bound.len() as u16 + 1;
    }
    panic!("no {n} consecutive free ports below 32768");
}

pub fn client_config(port: u16) -> cellgate::bus::BusConfig {
    cellgate::bus::BusConfig {
        mode: cellgate::bus::BusMode::Client,
        listen: Vec::new(),
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..cellgate::bus::BusConfig::default()
    }
}

pub type Replies = Vec<Result<(String, Vec<u8>, String), (Vec<u8>, String)>>;

/// Every reply to a get on `key`, with its key, payload and encoding (or error payload and
/// encoding).
pub async fn get(client: &Session, key: &str, payload: Option<Vec<u8>>) -> Replies {
    let mut builder = client.get(key.to_string()).timeout(Duration::from_secs(5));
    if let Some(p) = payload {
        builder = builder.payload(p);
    }
    let replies = builder.await.unwrap();
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        out.push(match reply.result() {
            Ok(s) => Ok((
                s.key_expr().to_string(),
                s.payload().to_bytes().into_owned(),
                s.encoding().to_string(),
            )),
            Err(e) => Err((
                e.payload().to_bytes().into_owned(),
                e.encoding().to_string(),
            )),
        });
    }
    out
}

/// The one message answering a get, decoded; panics on an error reply.
pub async fn get_one<M: Message + Default>(
    client: &Session,
    key: &str,
    payload: Option<Vec<u8>>,
) -> M {
    let replies = get(client, key, payload).await;
    assert_eq!(replies.len(), 1, "{key}: {replies:?}");
    match replies.into_iter().next().unwrap() {
        Ok((_, bytes, _)) => M::decode(bytes.as_slice()).unwrap(),
        Err((bytes, _)) => panic!(
            "{key}: error reply {:?}",
            pb::ErrorReply::decode(bytes.as_slice())
        ),
    }
}

/// The one error reply to a get.
pub async fn get_err(client: &Session, key: &str, payload: Option<Vec<u8>>) -> pb::ErrorReply {
    let replies = get(client, key, payload).await;
    assert_eq!(replies.len(), 1, "{key}: {replies:?}");
    match replies.into_iter().next().unwrap() {
        Err((bytes, encoding)) => {
            assert_eq!(encoding, "application/protobuf;cellgate.v1.ErrorReply");
            pb::ErrorReply::decode(bytes.as_slice()).unwrap()
        }
        Ok(ok) => panic!("{key}: expected an error, got {ok:?}"),
    }
}

pub async fn wait_token(client: &Session, key: &str, present: bool) {
    for _ in 0..100 {
        let replies = client.liveliness().get(key.to_string()).await.unwrap();
        if replies.recv_async().await.is_ok() == present {
            return;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("liveliness token {key} never became present = {present}");
}

/// Polls `check` until it holds, for up to 5 s.
pub async fn eventually(what: &str, mut check: impl FnMut() -> bool) {
    for _ in 0..250 {
        if check() {
            return;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    panic!("never happened: {what}");
}

/// A gateway session serving a cell of real links (simulated boards on simulated lines),
/// and a separate client session, both on loopback with multicast scouting off.
pub struct RunningCell {
    pub client: Session,
    pub gateway: Session,
    pub keys: cellgate::bus::keys::CellKeys,
    pub cell: cellgate::cell::Cell,
    routes_stop: tokio_util::sync::CancellationToken,
    links_stop: tokio_util::sync::CancellationToken,
    served: tokio::task::JoinHandle<Result<(), cellgate::bus::BusError>>,
    /// The cell's history, kept in its own directory as the gateway keeps it.
    pub history: cellgate::history::History,
    history_stop: tokio_util::sync::CancellationToken,
    history_writer: Option<tokio::task::JoinHandle<()>>,
    pub dir: tempfile::TempDir,
}

pub type Sub =
    zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

impl RunningCell {
    /// Starts the cell `config(port, dir)` gives, for a free loopback port and a fresh
    /// directory, and waits until every machine's liveliness token is up. `late`: serve the
    /// bus only once every link is already up, as a gateway whose routes start after its
    /// links would.
    pub async fn start(
        config: impl FnOnce(u16, &std::path::Path) -> cellgate_core::config::CellConfig,
        late: bool,
    ) -> Self {
        let dir = tempfile::tempdir().unwrap();
        // A free port can be taken by another test between the check and the bind: retry.
        let mut config = config(free_port(), dir.path());
        let mut attempts = 0;
        let gateway = loop {
            match cellgate::bus::open(&config.bus).await {
                Ok(s) => break s,
                Err(e) if attempts < 5 && e.to_string().contains("in use") => {
                    attempts += 1;
                    config.bus.listen = vec![format!("tcp/127.0.0.1:{}", free_port())];
                }
                Err(e) => panic!("{e}"),
            }
        };
        let port: u16 = config.bus.listen[0]
            .rsplit(':')
            .next()
            .and_then(|p| p.parse().ok())
            .unwrap();
        let links_stop = tokio_util::sync::CancellationToken::new();
        let cell = cellgate::cell::Cell::start(&config, &links_stop)
            .await
            .unwrap();
        assert_eq!(cell.machines.len(), config.machines.len());
        if late {
            for m in &cell.machines {
                let link = m.link.clone();
                eventually("the link is up before the routes start", move || {
                    link.state() == Some(cellgate_core::fanuc::host::LinkState::Ready)
                })
                .await;
            }
        }
        let machines = cell.machine_links();
        let routes_stop = tokio_util::sync::CancellationToken::new();
        let (ready_tx, ready) = tokio::sync::oneshot::channel();
        let plcs = cell.plc_links();
        let history_stop = tokio_util::sync::CancellationToken::new();
        let (history, history_writer) = if config.history.enabled {
            let (h, w) = cellgate::history::History::open(
                &config.history.dir_in(&config.programs.dir),
                &config.history,
                history_stop.clone(),
            )
            .await
            .unwrap();
            (h, Some(w))
        } else {
            (cellgate::history::History::disabled(), None)
        };
        let served = {
            let (gw, cfg, stop) = (gateway.clone(), config.clone(), routes_stop.clone());
            let h = history.clone();
            tokio::spawn(async move {
                tokio::try_join!(
                    cellgate::bus::serve_recorded(
                        &gw,
                        &cfg,
                        machines,
                        stop.clone(),
                        Some(ready_tx),
                        h.clone(),
                    ),
                    cellgate::bus::serve_plcs_recorded(&gw, &cfg, plcs, stop, h),
                )
                .map(|_| ())
            })
        };
        // Announced once every route is declared, as `gateway::run` does.
        ready.await.expect("the routes are declared");
        let client = cellgate::bus::open(&client_config(port)).await.unwrap();
        let keys = cellgate::bus::keys::CellKeys::new(&config.bus.prefix, &config.cell).unwrap();
        // Every link comes up with its board (Protocol A: ≈2 s power-on delay, §4.3 (1)).
        for m in &config.machines {
            wait_token(&client, &keys.machine(&m.name), true).await;
        }
        RunningCell {
            client,
            gateway,
            keys,
            cell,
            routes_stop,
            links_stop,
            served,
            history,
            history_stop,
            history_writer,
            dir,
        }
    }

    /// Stops the routes, then the links, then both sessions.
    pub async fn stop(self) {
        self.routes_stop.cancel();
        tokio::time::timeout(Duration::from_secs(10), self.served)
            .await
            .expect("routes stop")
            .unwrap()
            .unwrap();
        self.links_stop.cancel();
        self.cell.join().await;
        self.history_stop.cancel();
        if let Some(w) = self.history_writer {
            w.await.unwrap();
        }
        self.client.close().await.unwrap();
        self.gateway.close().await.unwrap();
    }

    pub fn board(&self, machine: &str) -> &cellgate::sim::BoardHandle {
        self.cell.machine(machine).unwrap().board.as_ref().unwrap()
    }

    pub async fn subscribe(&self, key: String) -> Sub {
        self.client.declare_subscriber(key).await.unwrap()
    }

    /// Submits an inline program; returns the job id, with the job's event subscriber
    /// declared before the request so that no event is missed.
    pub async fn submit(&self, machine: &str, program: &[u8]) -> (String, Sub) {
        use cellgate::bus::keys::MachineLeaf;
        let events = self.subscribe(self.keys.job_events(machine, "*")).await;
        let request = pb::JobRequest {
            program: Some(pb::job_request::Program::Inline(program.to_vec())),
            name: format!("{machine} test"),
            priority: 0,
            append_eor: false,
            ..Default::default()
        };
        let accepted: pb::JobAccepted = get_one(
            &self.client,
            &self.keys.leaf(machine, MachineLeaf::Submit),
            Some(request.encode_to_vec()),
        )
        .await;
        (accepted.job_id, events)
    }
}

/// The job's events until it ends, checking that progress never goes backwards.
pub async fn follow(events: &Sub, job: &str, within: Duration) -> Vec<pb::job_event::Kind> {
    use pb::job_event::Kind;
    let mut seen = Vec::new();
    let mut last_sent = 0;
    tokio::time::timeout(within, async {
        loop {
            let sample = events.recv_async().await.unwrap();
            let ev = pb::JobEvent::decode(sample.payload().to_bytes().as_ref()).unwrap();
            if ev.job_id != job {
                continue;
            }
            let kind = ev.kind.unwrap();
            if let Kind::Progress(p) = &kind {
                assert!(
                    p.bytes_sent >= last_sent,
                    "progress went backwards: {seen:?} then {p:?}"
                );
                last_sent = p.bytes_sent;
            }
            let end = matches!(
                kind,
                Kind::Completed(_) | Kind::Failed(_) | Kind::Cancelled(_)
            );
            seen.push(kind);
            if end {
                return;
            }
        }
    })
    .await
    .unwrap_or_else(|_| panic!("job {job} did not end within {within:?}: {seen:?}"));
    seen
}

/// A client's connection arguments for `endpoint`, without credentials.
pub fn connect_args(
    endpoint: String,
    as_user: Option<String>,
) -> cellgate::client::cli::ConnectArgs {
    cellgate::client::cli::ConnectArgs {
        connect: endpoint,
        prefix: "cellgate".to_string(),
        cell: None,
        timeout: 10,
        tls_ca: None,
        tls_cert: None,
        tls_key: None,
        user: None,
        password_file: None,
        as_user,
    }
}

/// A site console, `cellgate console -e tcp/127.0.0.1:ROUTER --listen 127.0.0.1:PORT`, without
/// credentials, running until [`SiteConsole::stop`].
pub struct SiteConsole {
    pub url: String,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<Result<(), cellgate::console::SiteError>>,
}

impl SiteConsole {
    pub fn start(router_port: u16) -> Self {
        let port = free_port();
        let args = cellgate::console::SiteArgs {
            connect: connect_args(format!("tcp/127.0.0.1:{router_port}"), None),
            listen: Some(format!("127.0.0.1:{port}")),
            config: None,
        };
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            cellgate::console::site(&args, async {
                let _ = stopped.await;
            })
            .await
        });
        SiteConsole {
            url: format!("http://127.0.0.1:{port}"),
            stop,
            task,
        }
    }

    /// Stops the console and checks that it ended without an error.
    pub async fn stop(self) {
        let _ = self.stop.send(());
        self.task.await.unwrap().unwrap();
    }
}
