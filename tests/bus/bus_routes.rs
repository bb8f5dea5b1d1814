//! The cell on the bus, end to end in one process: a gateway session serving two machines
//! whose links are stand-ins, and a client session talking to it over tcp/127.0.0.1 with
//! multicast scouting off. Real time (zenoh cannot run under paused time), short waits.

use crate::common;

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use cellgate::bus::keys::{CellKeys, MachineLeaf};
use cellgate::bus::{self, MachineLink};
use cellgate::link::driver::{LinkCommand, LinkEvent, LinkHandle, ProgramJob};
use cellgate_core::config::CellConfig;
use cellgate_core::fanuc::error::{LinkAlarm, ProtocolError};
use cellgate_core::fanuc::host::LinkState;
use cellgate_core::fanuc::message::{Command, FrameError};
use cellgate_core::fanuc::sat::{BufferStatus, Params, StatusData};
use cellgate_core::pb;
use cellgate_core::pb::job_event::Kind;
use prost::Message;
use tokio::io::AsyncReadExt;
use tokio::sync::{Semaphore, mpsc};
use tokio_util::sync::CancellationToken;
use zenoh::Session;
use zenoh::sample::Locality;

use common::bus::{client_config, eventually, free_port, get, get_err, get_one, wait_token};

// ---------------------------------------------------------------------------------------------
// A stand-in link: takes jobs when released, "sends" them in chunks, answers DO and DI.
// ---------------------------------------------------------------------------------------------

type Log = Arc<Mutex<Vec<String>>>;
/// Programs the link delivered: (job name, bytes).
type Delivered = Arc<Mutex<Vec<(String, Vec<u8>)>>>;

struct FakeLink {
    commands: mpsc::Receiver<LinkCommand>,
    events: cellgate::link::fanout::Sender<LinkEvent>,
    log: Log,
    delivered: Delivered,
    release: Arc<Semaphore>,
    chunk: usize,
    pace: Duration,
    pending: VecDeque<ProgramJob>,
    do_image: u8,
    /// ReadDi goes unanswered while set: a board that never gets to its next exchange.
    mute_di: Arc<std::sync::atomic::AtomicBool>,
}

/// What the test holds of a stand-in link.
#[derive(Clone)]
struct FakeCtl {
    events: cellgate::link::fanout::Sender<LinkEvent>,
    log: Log,
    delivered: Delivered,
    release: Arc<Semaphore>,
    mute_di: Arc<std::sync::atomic::AtomicBool>,
}

impl FakeCtl {
    fn emit(&self, e: LinkEvent) {
        let _ = self.events.send(e);
    }
    fn log(&self) -> Vec<String> {
        self.log.lock().unwrap().clone()
    }
}

fn fake_link(machine: &str, chunk: usize, pace: Duration) -> (LinkHandle, FakeCtl) {
    let (cmd_tx, cmd_rx) = mpsc::channel(64);
    let (ev_tx, _) = cellgate::link::fanout::channel(1024);
    let ctl = FakeCtl {
        events: ev_tx.clone(),
        log: Log::default(),
        delivered: Arc::default(),
        release: Arc::new(Semaphore::new(0)),
        mute_di: Arc::default(),
    };
    let fake = FakeLink {
        commands: cmd_rx,
        events: ev_tx.clone(),
        log: ctl.log.clone(),
        delivered: ctl.delivered.clone(),
        release: ctl.release.clone(),
        chunk,
        pace,
        pending: VecDeque::new(),
        do_image: 0,
        mute_di: ctl.mute_di.clone(),
    };
    tokio::spawn(fake.run());
    (LinkHandle::from_channels(machine, cmd_tx, ev_tx), ctl)
}

impl FakeLink {
    fn emit(&self, e: LinkEvent) {
        let _ = self.events.send(e);
    }

    fn other(&mut self, cmd: LinkCommand) {
        match cmd {
            LinkCommand::Queue(job) => self.pending.push_back(job),
            LinkCommand::SetDo { value, mask, .. } => {
                self.log
                    .lock()
                    .unwrap()
                    .push(format!("SetDo {value} {mask}"));
                self.do_image = (self.do_image & !mask) | (value & mask);
                self.emit(LinkEvent::Do {
                    value: self.do_image,
                });
            }
            LinkCommand::ReadDi => {
                self.log.lock().unwrap().push("ReadDi".to_string());
                if !self.mute_di.load(std::sync::atomic::Ordering::SeqCst) {
                    self.emit(LinkEvent::Di { value: 0x5A });
                }
            }
            other => self.log.lock().unwrap().push(format!("{other:?}")),
        }
    }

    async fn run(mut self) {
        loop {
            if let Some(job) = self.pending.pop_front() {
                self.job(job).await;
                continue;
            }
            match self.commands.recv().await {
                Some(LinkCommand::Queue(job)) => self.job(job).await,
                Some(other) => self.other(other),
                None => return,
            }
        }
    }

    async fn job(&mut self, job: ProgramJob) {
        self.log.lock().unwrap().push(format!("queue {}", job.name));
        self.emit(LinkEvent::JobQueued {
            job: job.id,
            position: 0,
        });
        let release = self.release.clone();
        loop {
            tokio::select! {
                permit = release.acquire() => {
                    permit.unwrap().forget();
                    break;
                }
                cmd = self.commands.recv() => match cmd {
                    Some(LinkCommand::Cancel(id)) if id == job.id => {
                        self.log.lock().unwrap().push(format!("cancel {} at 0", job.name));
                        self.emit(LinkEvent::JobCancelled { job: id, offset: 0, sent: 0 });
                        return;
                    }
                    Some(other) => self.other(other),
                    None => return,
                },
            }
        }
        self.emit(LinkEvent::State {
            state: LinkState::Sending,
        });
        self.emit(LinkEvent::JobStarted { job: job.id });
        let mut data = Vec::new();
        let mut buf = vec![0u8; self.chunk];
        let cellgate::link::driver::JobSource::Program(mut source) = job.source else {
            panic!("the job manager hands programs from the journal");
        };
        loop {
            let n = source.read(&mut buf).await.unwrap();
            if n == 0 {
                break;
            }
            data.extend_from_slice(&buf[..n]);
            self.emit(LinkEvent::Progress {
                job: job.id,
                acked: data.len() as u64,
                sent: data.len() as u64,
                total: job.size,
                block: None,
            });
            tokio::select! {
                () = tokio::time::sleep(self.pace) => {}
                cmd = self.commands.recv() => match cmd {
                    Some(LinkCommand::Cancel(id)) if id == job.id => {
                        self.log.lock().unwrap().push(format!("cancel {} at {}", job.name, data.len()));
                        self.emit(LinkEvent::JobCancelled { job: id, offset: data.len() as u64, sent: data.len() as u64 });
                        self.emit(LinkEvent::State { state: LinkState::Ready });
                        return;
                    }
                    Some(other) => self.other(other),
                    None => return,
                },
            }
        }
        self.log.lock().unwrap().push(format!("done {}", job.name));
        let bytes = data.len() as u64;
        self.delivered
            .lock()
            .unwrap()
            .push((job.name.clone(), data));
        self.emit(LinkEvent::JobDone {
            job: job.id,
            bytes,
            confirmation: cellgate_core::fanuc::host::Confirmation::Acknowledged,
            block: None,
        });
        self.emit(LinkEvent::State {
            state: LinkState::Ready,
        });
    }
}

// ---------------------------------------------------------------------------------------------
// A gateway serving mill-1 (Protocol A, end code CR) and lathe-1 (Protocol B), and a client.
// ---------------------------------------------------------------------------------------------

const MILL: &str = "mill-1";
const LATHE: &str = "lathe-1";
const MAX_SIZE: u64 = 64 * 1024;

struct Cell {
    gateway: Session,
    client: Session,
    keys: CellKeys,
    mill: FakeCtl,
    lathe: FakeCtl,
    stop: CancellationToken,
    served: tokio::task::JoinHandle<Result<(), bus::BusError>>,
    dir: tempfile::TempDir,
}

async fn start_cell(pace: Duration) -> Cell {
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let mut config = CellConfig::embedded_default();
    // Its MTConnect agent would take a fixed port; this test does not look at it.
    config.mtconnect = None;
    config.opcua = None;
    config.cell = "test".to_string();
    config.bus.listen = vec![format!("tcp/127.0.0.1:{port}")];
    config.bus.connect = Vec::new();
    config.programs.dir = dir.path().join("programs");
    config.programs.max_size = MAX_SIZE;
    config.programs.fetch_prefixes = vec!["elsewhere/programs".to_string()];
    let mill_cfg = config.machine(MILL).unwrap().clone();
    let lathe_cfg = config.machine(LATHE).unwrap().clone();
    let (mill_link, mill) = fake_link(MILL, 256, pace);
    let (lathe_link, lathe) = fake_link(LATHE, 256, pace);
    let keys = CellKeys::new(&config.bus.prefix, &config.cell).unwrap();

    let gateway = bus::open(&config.bus).await.unwrap();
    let stop = CancellationToken::new();
    let (ready_tx, ready) = tokio::sync::oneshot::channel();
    let served = {
        let (gw, cfg, stop) = (gateway.clone(), config.clone(), stop.clone());
        let machines = vec![
            MachineLink {
                config: mill_cfg,
                link: mill_link,
                sim: None,
            },
            MachineLink {
                config: lathe_cfg,
                link: lathe_link,
                sim: None,
            },
        ];
        tokio::spawn(async move {
            bus::serve_announced(&gw, &cfg, machines, stop, Some(ready_tx)).await
        })
    };
    // Announced once every route is declared, as `gateway::run` does.
    ready.await.expect("the routes are declared");
    let client = bus::open(&client_config(port)).await.unwrap();
    let cell = Cell {
        gateway,
        client,
        keys,
        mill,
        lathe,
        stop,
        served,
        dir,
    };
    // The routes are up once a status get is answered.
    let status = cell.keys.leaf(MILL, MachineLeaf::Status);
    let mut answered = false;
    for _ in 0..100 {
        if !get(&cell.client, &status, None).await.is_empty() {
            answered = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(answered, "the gateway never answered {status}");
    // Now the machine tasks are subscribed: bring both links up.
    for f in [&cell.mill, &cell.lathe] {
        f.emit(LinkEvent::State {
            state: LinkState::Ready,
        });
    }
    for m in [MILL, LATHE] {
        wait_token(&cell.client, &cell.keys.machine(m), true).await;
    }
    cell
}

impl Cell {
    async fn stop(self) {
        self.stop.cancel();
        tokio::time::timeout(Duration::from_secs(10), self.served)
            .await
            .expect("serve did not stop")
            .unwrap()
            .unwrap();
        self.client.close().await.unwrap();
        self.gateway.close().await.unwrap();
    }

    /// Waits until the gateway routes publications on `key` to the client.
    async fn wait_subscribed(&self, key: &str) {
        let probe = self
            .gateway
            .declare_publisher(key.to_string())
            .allowed_destination(Locality::Remote)
            .await
            .unwrap();
        for _ in 0..200 {
            if probe.matching_status().await.unwrap().matching() {
                probe.undeclare().await.unwrap();
                return;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        panic!("the client's subscription to {key} never reached the gateway");
    }
}

fn request(program: pb::job_request::Program) -> pb::JobRequest {
    pb::JobRequest {
        program: Some(program),
        ..Default::default()
    }
}

fn inline(bytes: &[u8]) -> pb::JobRequest {
    request(pb::job_request::Program::Inline(bytes.to_vec()))
}

/// A Protocol-A-safe program of about `size` bytes.
fn program_of(size: usize) -> Vec<u8> {
    let mut p = b"%\nO4711\n".to_vec();
    let mut n = 0;
    while p.len() + 16 < size {
        p.extend_from_slice(format!("N{n:05}G01X{:03}\n", n % 1000).as_bytes());
        n += 1;
    }
    p.extend_from_slice(b"M30\n%\n");
    p
}

type Sub = zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

async fn next_sample(sub: &Sub) -> zenoh::sample::Sample {
    tokio::time::timeout(Duration::from_secs(10), sub.recv_async())
        .await
        .expect("no sample within 10 s")
        .unwrap()
}

/// The job events of `job` until it ends, inclusive.
async fn job_events_until_end(sub: &Sub, job: &str) -> Vec<pb::JobEvent> {
    let mut events = Vec::new();
    loop {
        let s = next_sample(sub).await;
        if s.kind() == zenoh::sample::SampleKind::Delete {
            // A cancel request (this session's own delete).
            continue;
        }
        assert_eq!(
            s.encoding().to_string(),
            "application/protobuf;cellgate.v1.JobEvent"
        );
        let e = pb::JobEvent::decode(s.payload().to_bytes().as_ref()).unwrap();
        if e.job_id != job {
            continue;
        }
        assert!(s.key_expr().as_str().ends_with(&format!("/job/{job}")));
        let end = matches!(
            e.kind,
            Some(Kind::Completed(_) | Kind::Failed(_) | Kind::Cancelled(_))
        );
        events.push(e);
        if end {
            return events;
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Tests
// ---------------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_is_accepted_and_its_events_arrive_in_order() {
    let cell = start_cell(Duration::from_millis(5)).await;
    let events_key = cell.keys.job_events(MILL, "*");
    let sub = cell
        .client
        .declare_subscriber(events_key.clone())
        .await
        .unwrap();
    cell.wait_subscribed(&cell.keys.job_events(MILL, "probe"))
        .await;
    cell.mill.release.add_permits(10);

    let program = program_of(40_000);
    let job_key = cell.keys.leaf(MILL, MachineLeaf::Submit);
    let replies = get(
        &cell.client,
        &job_key,
        Some(inline(&program).encode_to_vec()),
    )
    .await;
    assert_eq!(replies.len(), 1, "{replies:?}");
    let (key, bytes, encoding) = replies.into_iter().next().unwrap().unwrap();
    assert_eq!(key, job_key);
    assert_eq!(encoding, "application/protobuf;cellgate.v1.JobAccepted");
    let accepted = pb::JobAccepted::decode(bytes.as_slice()).unwrap();
    assert_eq!(accepted.queue_position, 0);
    assert!(accepted.job_id.starts_with("mill-1-"));

    let events = job_events_until_end(&sub, &accepted.job_id).await;
    assert!(
        matches!(events[0].kind, Some(Kind::Queued(_))),
        "{events:?}"
    );
    assert!(
        matches!(events[1].kind, Some(Kind::Started(_))),
        "{events:?}"
    );
    let mut last = 0;
    let mut progress = 0;
    for e in &events[2..events.len() - 1] {
        match &e.kind {
            Some(Kind::Progress(p)) => {
                assert!(p.bytes_sent >= last, "progress went backwards: {events:?}");
                assert_eq!(p.bytes_total, Some(program.len() as u64));
                last = p.bytes_sent;
                progress += 1;
            }
            other => panic!("unexpected {other:?} between started and the end"),
        }
        assert_eq!(e.machine, MILL);
    }
    assert!(progress >= 1, "no progress event: {events:?}");
    match &events.last().unwrap().kind {
        Some(Kind::Completed(c)) => assert_eq!(c.bytes_sent, program.len() as u64),
        other => panic!("{other:?}"),
    }
    let delivered = cell.mill.delivered.lock().unwrap().clone();
    assert_eq!(delivered, [("O4711".to_string(), program.clone())]);

    // The last event of the job stays available to a get.
    let last_event: pb::JobEvent = get_one(
        &cell.client,
        &cell.keys.job_events(MILL, &accepted.job_id),
        None,
    )
    .await;
    assert!(matches!(last_event.kind, Some(Kind::Completed(_))));
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn library_and_key_sources_are_streamed() {
    let cell = start_cell(Duration::from_millis(1)).await;
    cell.mill.release.add_permits(10);
    let sub = cell
        .client
        .declare_subscriber(cell.keys.job_events(MILL, "*"))
        .await
        .unwrap();
    cell.wait_subscribed(&cell.keys.job_events(MILL, "probe"))
        .await;

    // A program in the library, put on the bus.
    let stored = program_of(5_000);
    let lib_key = cell.keys.program_write("O4711");
    cell.client
        .put(lib_key.clone(), stored.clone())
        .await
        .unwrap();
    let path = cell.dir.path().join("programs").join("O4711.nc");
    eventually("the program is stored", || path.exists()).await;

    // A program another node serves on its own key.
    let served = b"%\nO9\nG00X0\nM30\n%".to_vec();
    let source_key = "elsewhere/programs/O9";
    let q = cell.client.declare_queryable(source_key).await.unwrap();
    let payload = served.clone();
    let server = tokio::spawn(async move {
        while let Ok(query) = q.recv_async().await {
            query
                .reply(query.key_expr().clone(), payload.clone())
                .await
                .unwrap();
        }
    });

    let job_key = cell.keys.leaf(MILL, MachineLeaf::Submit);
    let mut from_library = request(pb::job_request::Program::Library("O4711".into()));
    from_library.name = "from library".to_string();
    let a: pb::JobAccepted =
        get_one(&cell.client, &job_key, Some(from_library.encode_to_vec())).await;
    let from_key = request(pb::job_request::Program::Key(source_key.into()));
    let b: pb::JobAccepted = get_one(&cell.client, &job_key, Some(from_key.encode_to_vec())).await;
    job_events_until_end(&sub, &a.job_id).await;
    job_events_until_end(&sub, &b.job_id).await;
    let delivered = cell.mill.delivered.lock().unwrap().clone();
    assert_eq!(
        delivered,
        [
            ("from library".to_string(), stored),
            (source_key.to_string(), served)
        ]
    );
    server.abort();
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_kind_of_bad_request_gets_an_error_reply_and_nothing_is_queued() {
    use pb::ErrorCode as C;
    use pb::job_request::Program as P;
    let cell = start_cell(Duration::from_millis(1)).await;
    let mill = cell.keys.leaf(MILL, MachineLeaf::Submit);
    let lathe = cell.keys.leaf(LATHE, MachineLeaf::Submit);
    let nosuch = cell.keys.leaf("nosuch", MachineLeaf::Submit);
    let wild = cell.keys.any_leaf(MachineLeaf::Submit);
    let mut no_eor = inline(b"%\nO1\nG00X0\n");
    let too_big = inline(&program_of(MAX_SIZE as usize + 100));
    let ok = inline(b"%\nO1\n%").encode_to_vec();
    let cases: Vec<(&str, &str, Vec<u8>, C, &str)> = vec![
        (
            "unknown machine",
            &nosuch,
            ok.clone(),
            C::UnknownMachine,
            "no machine \"nosuch\"",
        ),
        (
            "wildcard machine",
            &wild,
            ok.clone(),
            C::InvalidRequest,
            "one machine",
        ),
        (
            "not protobuf",
            &mill,
            vec![0xFF, 0xFF, 0xFF],
            C::InvalidRequest,
            "not a cellgate.v1.JobRequest",
        ),
        (
            "no program",
            &mill,
            pb::JobRequest::default().encode_to_vec(),
            C::InvalidRequest,
            "names no program",
        ),
        (
            "empty program",
            &mill,
            inline(b"").encode_to_vec(),
            C::InvalidRequest,
            "empty",
        ),
        (
            "no EOR",
            &mill,
            no_eor.encode_to_vec(),
            C::InvalidRequest,
            "no EOR",
        ),
        (
            "8-bit byte",
            &mill,
            inline(b"%\nO1\nG00X\xB0\n%").encode_to_vec(),
            C::InvalidRequest,
            "bit 7",
        ),
        (
            "end code in data",
            &mill,
            inline(b"%\r\nO1\r\n%").encode_to_vec(),
            C::InvalidRequest,
            "CR (0Dh) at offset 1",
        ),
        (
            "Protocol B control code",
            &lathe,
            inline(b"%\nO1\x11\n%").encode_to_vec(),
            C::InvalidRequest,
            "DC1 (11h) at offset 4",
        ),
        (
            "too large",
            &mill,
            too_big.encode_to_vec(),
            C::InvalidRequest,
            "max_size",
        ),
        (
            "unknown library program",
            &mill,
            request(P::Library("nope".into())).encode_to_vec(),
            C::NotFound,
            "no program \"nope\"",
        ),
        (
            "bad library name",
            &mill,
            request(P::Library("../etc/passwd".into())).encode_to_vec(),
            C::InvalidRequest,
            "not valid",
        ),
        (
            "bad key",
            &mill,
            request(P::Key("a//b".into())).encode_to_vec(),
            C::InvalidRequest,
            "not a key expression",
        ),
        (
            "key nobody serves",
            &mill,
            request(P::Key("elsewhere/programs/nobody".into())).encode_to_vec(),
            C::FetchFailed,
            "elsewhere/programs/nobody",
        ),
        (
            "key outside programs.fetch_prefixes",
            &mill,
            request(P::Key("nobody/home".into())).encode_to_vec(),
            C::NotPermitted,
            "programs.fetch_prefixes",
        ),
        (
            "the gateway's own admin key",
            &mill,
            request(P::Key("cellgate/test/@admin".into())).encode_to_vec(),
            C::NotPermitted,
            "own authority",
        ),
        (
            "a wildcard key under an allowed prefix",
            &mill,
            request(P::Key("elsewhere/programs/*".into())).encode_to_vec(),
            C::NotPermitted,
            "without wildcards",
        ),
    ];
    for (what, key, payload, code, words) in cases {
        let e = get_err(&cell.client, key, Some(payload)).await;
        assert_eq!(e.code(), code, "{what}: {}", e.message);
        assert!(
            e.message.contains(words),
            "{what}: {:?} lacks {words:?}",
            e.message
        );
    }
    // The same program passes once its EOR is appended on request.
    no_eor.append_eor = true;
    cell.mill.release.add_permits(1);
    let accepted: pb::JobAccepted =
        get_one(&cell.client, &mill, Some(no_eor.encode_to_vec())).await;
    assert_eq!(accepted.queue_position, 0);
    eventually("the good job is delivered", || {
        cell.mill.log().iter().any(|l| l.starts_with("done"))
    })
    .await;
    // Nothing but the good job ever reached a link.
    assert_eq!(cell.mill.log(), ["queue O1", "done O1"]);
    assert!(cell.lathe.log().is_empty(), "{:?}", cell.lathe.log());
    let queue: pb::JobQueue =
        get_one(&cell.client, &cell.keys.leaf(LATHE, MachineLeaf::Job), None).await;
    assert_eq!(queue.machine, LATHE);
    assert!(queue.active.is_none() && queue.waiting.is_empty());
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_delete_on_the_job_key_cancels_it() {
    let cell = start_cell(Duration::from_millis(20)).await;
    let sub = cell
        .client
        .declare_subscriber(cell.keys.job_events(MILL, "*"))
        .await
        .unwrap();
    cell.wait_subscribed(&cell.keys.job_events(MILL, "probe"))
        .await;
    let job_key = cell.keys.leaf(MILL, MachineLeaf::Submit);
    let program = program_of(20_000);
    let a: pb::JobAccepted = get_one(
        &cell.client,
        &job_key,
        Some(inline(&program).encode_to_vec()),
    )
    .await;
    let b: pb::JobAccepted = get_one(
        &cell.client,
        &job_key,
        Some(inline(&program).encode_to_vec()),
    )
    .await;
    assert_eq!(b.queue_position, 0);
    let queue: pb::JobQueue =
        get_one(&cell.client, &cell.keys.leaf(MILL, MachineLeaf::Job), None).await;
    assert_eq!(queue.active.unwrap().job_id, a.job_id);
    assert_eq!(queue.waiting.len(), 1);

    // The waiting job goes at once and never reaches the link.
    cell.client
        .delete(cell.keys.job_events(MILL, &b.job_id))
        .await
        .unwrap();
    let events = job_events_until_end(&sub, &b.job_id).await;
    match &events.last().unwrap().kind {
        Some(Kind::Cancelled(c)) => {
            assert_eq!(c.by, "request");
            assert_eq!(c.byte_offset, 0);
        }
        other => panic!("{other:?}"),
    }

    // The active one is stopped by the link, part way.
    cell.mill.release.add_permits(1);
    loop {
        let s = next_sample(&sub).await;
        let e = pb::JobEvent::decode(s.payload().to_bytes().as_ref()).unwrap();
        if e.job_id == a.job_id && matches!(e.kind, Some(Kind::Progress(_))) {
            break;
        }
    }
    cell.client
        .delete(cell.keys.job_events(MILL, &a.job_id))
        .await
        .unwrap();
    let events = job_events_until_end(&sub, &a.job_id).await;
    match &events.last().unwrap().kind {
        Some(Kind::Cancelled(c)) => {
            assert_eq!(c.by, "request");
            assert!(c.byte_offset > 0 && c.byte_offset < program.len() as u64);
        }
        other => panic!("{other:?}"),
    }
    let log = cell.mill.log();
    assert_eq!(
        log.iter().filter(|l| l.starts_with("queue")).count(),
        1,
        "{log:?}"
    );
    assert!(
        log.iter().any(|l| l.starts_with("cancel O4711 at")),
        "{log:?}"
    );
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn do_reaches_the_link_as_set_do_and_shows_in_status() {
    let cell = start_cell(Duration::from_millis(1)).await;
    let do_key = cell.keys.leaf(MILL, MachineLeaf::Do);
    let cmd = pb::DoCommand {
        value: 0x81,
        mask: Some(0x0F),
    };
    cell.client
        .put(do_key.clone(), cmd.encode_to_vec())
        .await
        .unwrap();
    eventually("SetDo reaches the link", || {
        cell.mill.log().contains(&"SetDo 129 15".to_string())
    })
    .await;
    let status_key = cell.keys.leaf(MILL, MachineLeaf::Status);
    for _ in 0..100 {
        let s: pb::MachineStatus = get_one(&cell.client, &status_key, None).await;
        if s.do_image == Some(0x01) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let s: pb::MachineStatus = get_one(&cell.client, &status_key, None).await;
    assert_eq!(s.do_image, Some(0x01));

    // A get with a DoCommand answers the status once SDO went out.
    let all = pb::DoCommand {
        value: 0xF0,
        mask: None,
    };
    let s: pb::MachineStatus = get_one(&cell.client, &do_key, Some(all.encode_to_vec())).await;
    assert_eq!(s.do_image, Some(0xF0));
    assert!(cell.mill.log().contains(&"SetDo 240 255".to_string()));

    // Out of range, and Protocol B.
    let e = get_err(
        &cell.client,
        &do_key,
        Some(
            pb::DoCommand {
                value: 256,
                mask: None,
            }
            .encode_to_vec(),
        ),
    )
    .await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);
    let e = get_err(
        &cell.client,
        &cell.keys.leaf(LATHE, MachineLeaf::Do),
        Some(all.encode_to_vec()),
    )
    .await;
    assert_eq!(e.code(), pb::ErrorCode::NotSupported);
    cell.client
        .put(cell.keys.leaf(LATHE, MachineLeaf::Do), all.encode_to_vec())
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!(cell.lathe.log().is_empty(), "{:?}", cell.lathe.log());
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn di_get_reads_now_and_publishes() {
    let cell = start_cell(Duration::from_millis(1)).await;
    let di_key = cell.keys.leaf(MILL, MachineLeaf::Di);
    let sub = cell
        .client
        .declare_subscriber(di_key.clone())
        .await
        .unwrap();
    cell.wait_subscribed(&di_key).await;
    let replies = get(&cell.client, &di_key, None).await;
    assert_eq!(replies.len(), 1, "{replies:?}");
    let (_, bytes, encoding) = replies.into_iter().next().unwrap().unwrap();
    assert_eq!(encoding, "application/protobuf;cellgate.v1.DiImage");
    let di = pb::DiImage::decode(bytes.as_slice()).unwrap();
    assert_eq!((di.machine.as_str(), di.value), (MILL, 0x5A));
    assert_eq!(cell.mill.log(), ["ReadDi"]);
    let published =
        pb::DiImage::decode(next_sample(&sub).await.payload().to_bytes().as_ref()).unwrap();
    assert_eq!(published.value, 0x5A);
    let e = get_err(&cell.client, &cell.keys.leaf(LATHE, MachineLeaf::Di), None).await;
    assert_eq!(e.code(), pb::ErrorCode::NotSupported);
    // A wildcard get answers the last image read, without reading again.
    let replies = get(&cell.client, &cell.keys.any_leaf(MachineLeaf::Di), None).await;
    assert_eq!(replies.len(), 1, "{replies:?}");
    assert_eq!(cell.mill.log(), ["ReadDi"]);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_that_waits_holds_up_no_other_route() {
    let cell = start_cell(Duration::from_millis(1)).await;
    cell.mill
        .mute_di
        .store(true, std::sync::atomic::Ordering::SeqCst);
    let di_key = cell.keys.leaf(MILL, MachineLeaf::Di);
    let di = {
        let (client, key) = (cell.client.clone(), di_key.clone());
        tokio::spawn(async move { get(&client, &key, None).await })
    };
    eventually("the DI read reached the link", || {
        cell.mill.log().contains(&"ReadDi".to_string())
    })
    .await;
    // While the DI read waits for the board, the other routes answer, and so does the DI
    // route itself for another machine.
    let status: pb::MachineStatus = get_one(
        &cell.client,
        &cell.keys.leaf(MILL, MachineLeaf::Status),
        None,
    )
    .await;
    assert_eq!(status.machine, MILL);
    let accepted: pb::JobAccepted = get_one(
        &cell.client,
        &cell.keys.leaf(LATHE, MachineLeaf::Submit),
        Some(inline(b"%\nO1\nG01X1\n%").encode_to_vec()),
    )
    .await;
    assert!(!accepted.job_id.is_empty());
    let e = get_err(&cell.client, &cell.keys.leaf(LATHE, MachineLeaf::Di), None).await;
    assert_eq!(e.code(), pb::ErrorCode::NotSupported);
    assert!(
        !di.is_finished(),
        "the DI read cannot have been answered yet"
    );
    // The board answers: the waiting read completes with its image.
    cell.mill.emit(LinkEvent::Di { value: 0x21 });
    let replies = di.await.unwrap();
    let (_, bytes, _) = replies.into_iter().next().unwrap().unwrap();
    assert_eq!(pb::DiImage::decode(bytes.as_slice()).unwrap().value, 0x21);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn link_alarms_appear_on_the_alarm_key() {
    let cell = start_cell(Duration::from_millis(1)).await;
    let alarm_key = cell.keys.leaf(MILL, MachineLeaf::Alarm);
    let sub = cell
        .client
        .declare_subscriber(alarm_key.clone())
        .await
        .unwrap();
    cell.wait_subscribed(&alarm_key).await;
    cell.mill
        .emit(LinkEvent::Alarm(LinkAlarm::RetryOver { count: 10, ne: 9 }));
    let s = next_sample(&sub).await;
    assert_eq!(
        s.encoding().to_string(),
        "application/protobuf;cellgate.v1.AlarmEvent"
    );
    let a = pb::AlarmEvent::decode(s.payload().to_bytes().as_ref()).unwrap();
    assert_eq!(a.kind(), pb::AlarmKind::LinkAlarm);
    assert_eq!(a.alarm_number, "SR0945");
    assert_eq!(a.machine, MILL);
    assert!(a.message.contains("10 retries > Ne = 9"), "{}", a.message);
    cell.mill.emit(LinkEvent::CncReset);
    let a = pb::AlarmEvent::decode(next_sample(&sub).await.payload().to_bytes().as_ref()).unwrap();
    assert_eq!(a.kind(), pb::AlarmKind::CncReset);
    assert_eq!(a.alarm_number, "");
    cell.mill.emit(LinkEvent::CncAlarm);
    let a = pb::AlarmEvent::decode(next_sample(&sub).await.payload().to_bytes().as_ref()).unwrap();
    assert_eq!(a.kind(), pb::AlarmKind::CncAlarm);
    let status: pb::MachineStatus = get_one(
        &cell.client,
        &cell.keys.leaf(MILL, MachineLeaf::Status),
        None,
    )
    .await;
    assert_eq!(status.link_state(), pb::LinkState::Alarm);
    assert_eq!(status.last_alarm.unwrap().kind(), pb::AlarmKind::CncAlarm);
    assert_eq!(status.counters.unwrap().link_alarms, 1);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_is_published_on_change_and_answered_on_get() {
    let cell = start_cell(Duration::from_millis(1)).await;
    let key = cell.keys.leaf(MILL, MachineLeaf::Status);
    let s: pb::MachineStatus = get_one(&cell.client, &key, None).await;
    assert_eq!(s.machine, MILL);
    assert_eq!(s.protocol(), pb::Protocol::A);
    assert_eq!(s.link_state(), pb::LinkState::Idle);
    assert!(s.sat.is_none());
    assert!(s.unix_ms > 0);

    let sub = cell.client.declare_subscriber(key.clone()).await.unwrap();
    cell.wait_subscribed(&key).await;
    cell.mill.emit(LinkEvent::Status {
        status: StatusData {
            remote: Some(true),
            status: Some(BufferStatus::Operating),
            buffered: Some(300),
            params: Some(Params::POWER_ON),
            packet_n: Some(0),
            ..StatusData::default()
        },
    });
    cell.mill.emit(LinkEvent::ProtocolError {
        error: ProtocolError::ChecksumRetry {
            error: FrameError::Checksum {
                received: 0x12,
                computed: 0x13,
            },
            count: 1,
            ne: 3,
        },
        retried: true,
    });
    cell.mill.emit(LinkEvent::ProtocolError {
        error: ProtocolError::Unexpected {
            command: Command::Gtd,
            context: "in a test",
        },
        retried: false,
    });
    // Published on change: the last publication carries all three.
    let mut published = None;
    for _ in 0..3 {
        let sample = next_sample(&sub).await;
        assert_eq!(
            sample.encoding().to_string(),
            "application/protobuf;cellgate.v1.MachineStatus"
        );
        let s = pb::MachineStatus::decode(sample.payload().to_bytes().as_ref()).unwrap();
        if s.counters.as_ref().is_some_and(|c| c.protocol_errors == 2) {
            published = Some(s);
            break;
        }
    }
    let published = published.expect("no status with both protocol errors was published");
    let got: pb::MachineStatus = get_one(&cell.client, &key, None).await;
    for s in [&published, &got] {
        let sat = s.sat.as_ref().unwrap();
        assert_eq!(sat.remote, Some(true));
        assert_eq!(sat.buffer_status(), pb::BufferStatus::Operating);
        assert_eq!(sat.bytes_buffered, Some(300));
        assert_eq!(sat.params.as_ref().unwrap().nb, 2000);
        let c = s.counters.as_ref().unwrap();
        assert_eq!((c.retries, c.checksum_errors, c.protocol_errors), (1, 1, 2));
        assert_eq!(c.bytes_sent, None, "the link does not count framing bytes");
    }
    // Every machine at once, and an unknown one.
    let all = get(&cell.client, &cell.keys.any_leaf(MachineLeaf::Status), None).await;
    let mut names: Vec<String> = all
        .into_iter()
        .map(|r| {
            pb::MachineStatus::decode(r.unwrap().1.as_slice())
                .unwrap()
                .machine
        })
        .collect();
    names.sort();
    assert_eq!(names, [LATHE, MILL]);
    // Browsing the whole cell answers without errors: two statuses and two queues.
    let browse = get(&cell.client, &format!("{}/**", cell.keys.root()), None).await;
    assert!(browse.iter().all(Result::is_ok), "{browse:?}");
    let mut kinds: Vec<String> = browse.into_iter().map(|r| r.unwrap().2).collect();
    kinds.sort();
    assert_eq!(
        kinds,
        [
            "application/protobuf;cellgate.v1.JobQueue",
            "application/protobuf;cellgate.v1.JobQueue",
            "application/protobuf;cellgate.v1.MachineStatus",
            "application/protobuf;cellgate.v1.MachineStatus"
        ]
    );
    let e = get_err(
        &cell.client,
        &cell.keys.leaf("nosuch", MachineLeaf::Status),
        None,
    )
    .await;
    assert_eq!(e.code(), pb::ErrorCode::UnknownMachine);
    assert!(e.message.contains("lathe-1, mill-1"), "{}", e.message);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_program_library_stores_fetches_lists_and_removes() {
    let cell = start_cell(Duration::from_millis(1)).await;
    let o100 = cell.keys.program("O100");
    let o200 = cell.keys.program("O200");
    cell.client
        .put(cell.keys.program_write("O100"), b"%\nO100\n%".to_vec())
        .await
        .unwrap();
    cell.client
        .put(cell.keys.program_write("O200"), b"%\nO200\nM30\n%".to_vec())
        .await
        .unwrap();
    // Not a library name: refused, nothing stored.
    cell.client
        .put(cell.keys.program_write("-x"), b"x".to_vec())
        .await
        .unwrap();
    // Each put is stored on its own: the two may land in either order.
    for (key, want) in [
        (&o200, &b"%\nO200\nM30\n%"[..]),
        (&o100, &b"%\nO100\n%"[..]),
    ] {
        let mut got = Vec::new();
        for _ in 0..100 {
            let replies = get(&cell.client, key, None).await;
            if let Some(Ok((_, bytes, encoding))) = replies.into_iter().next() {
                assert_eq!(encoding, "application/octet-stream");
                got = bytes;
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        assert_eq!(got, want, "{key}");
    }

    let list = get(&cell.client, &cell.keys.any_program(), None).await;
    let mut infos: Vec<(String, String, u64)> = list
        .into_iter()
        .map(|r| {
            let (key, bytes, encoding) = r.unwrap();
            assert_eq!(encoding, "application/protobuf;cellgate.v1.ProgramInfo");
            let info = pb::ProgramInfo::decode(bytes.as_slice()).unwrap();
            assert!(info.modified_unix_ms > 0);
            (key, info.name, info.size)
        })
        .collect();
    infos.sort();
    assert_eq!(
        infos,
        [
            (o100.clone(), "O100".to_string(), 8),
            (o200.clone(), "O200".to_string(), 12)
        ]
    );

    cell.client
        .delete(cell.keys.program_write("O100"))
        .await
        .unwrap();
    for _ in 0..100 {
        if get(&cell.client, &o100, None)
            .await
            .first()
            .is_some_and(Result::is_err)
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let e = get_err(&cell.client, &o100, None).await;
    assert_eq!(e.code(), pb::ErrorCode::NotFound);
    let list = get(&cell.client, &cell.keys.any_program(), None).await;
    assert_eq!(list.len(), 1);
    let names: Vec<_> = std::fs::read_dir(cell.dir.path().join("programs"))
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n != ".journal" && n != ".revisions")
        .collect();
    // A store writes the program's file with the folder's first extension.
    assert_eq!(names, ["O200.nc"]);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_get_with_a_program_write_stores_and_removes_with_a_reply() {
    let cell = start_cell(Duration::from_millis(1)).await;
    let key = cell.keys.program_write("O300");
    let store = |bytes: &[u8]| {
        pb::ProgramWrite {
            op: Some(pb::program_write::Op::Store(bytes.to_vec())),
            comment: String::new(),
        }
        .encode_to_vec()
    };
    let remove = pb::ProgramWrite {
        op: Some(pb::program_write::Op::Remove(pb::program_write::Remove {})),
        comment: String::new(),
    }
    .encode_to_vec();
    let path = cell.dir.path().join("programs").join("O300.nc");

    // The reply comes once the program is on disk: no polling.
    let info: pb::ProgramInfo = get_one(&cell.client, &key, Some(store(b"%\nO300\n%"))).await;
    assert_eq!((info.name.as_str(), info.size), ("O300", 8));
    assert!(info.modified_unix_ms > 0);
    assert_eq!(std::fs::read(&path).unwrap(), b"%\nO300\n%");
    // A store replaces.
    let info: pb::ProgramInfo = get_one(&cell.client, &key, Some(store(b"%\nO300\nM30\n%"))).await;
    assert_eq!(info.size, 12);
    assert_eq!(std::fs::read(&path).unwrap(), b"%\nO300\nM30\n%");

    // Refusals are error replies, and change nothing.
    let too_big = vec![b'x'; MAX_SIZE as usize + 1];
    let e = get_err(&cell.client, &key, Some(store(&too_big))).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest, "{}", e.message);
    assert_eq!(std::fs::read(&path).unwrap(), b"%\nO300\nM30\n%");
    let e = get_err(&cell.client, &key, Some(b"\xff\xff".to_vec())).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);
    assert!(e.message.contains("ProgramWrite"), "{}", e.message);
    let e = get_err(&cell.client, &key, Some(Vec::new())).await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);
    assert!(e.message.contains("names no operation"), "{}", e.message);
    let e = get_err(
        &cell.client,
        &cell.keys.program_write("-bad"),
        Some(store(b"%\n%")),
    )
    .await;
    assert_eq!(e.code(), pb::ErrorCode::InvalidRequest);

    // Removal answers the program as it was; a second one finds nothing.
    let info: pb::ProgramInfo = get_one(&cell.client, &key, Some(remove.clone())).await;
    assert_eq!((info.name.as_str(), info.size), ("O300", 12));
    assert!(!path.exists());
    let e = get_err(&cell.client, &key, Some(remove)).await;
    assert_eq!(e.code(), pb::ErrorCode::NotFound);
    cell.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn liveliness_tokens_follow_the_link() {
    let cell = start_cell(Duration::from_millis(1)).await;
    let token = cell.keys.machine(MILL);
    // start_cell saw both tokens appear once the links were Ready.
    cell.mill.emit(LinkEvent::State {
        state: LinkState::LineDown,
    });
    wait_token(&cell.client, &token, false).await;
    let s: pb::MachineStatus = get_one(
        &cell.client,
        &cell.keys.leaf(MILL, MachineLeaf::Status),
        None,
    )
    .await;
    assert_eq!(s.link_state(), pb::LinkState::Down);
    // The other machine's token is untouched.
    wait_token(&cell.client, &cell.keys.machine(LATHE), true).await;
    cell.mill.emit(LinkEvent::State {
        state: LinkState::Ready,
    });
    wait_token(&cell.client, &token, true).await;
    // Shutting down withdraws them.
    let client = cell.client.clone();
    let keys = cell.keys.clone();
    cell.stop.cancel();
    wait_token(&client, &keys.machine(LATHE), false).await;
    cell.stop().await;
}
