//! The client commands against a gateway serving the embedded default cell: mill-1
//! (Protocol A, 19200 baud) and mill-2 (Expansion Protocol A, 86400 baud), each a simulated
//! remote-buffer board with its CNC on a simulated line. The library functions are called in
//! process, against a gateway assembled here like `gateway::run` does it, so that the test
//! can look into the simulated CNCs; the `cellgate` binary is run against that gateway and
//! against a `cellgate run` process. Real time, loopback, multicast off.

use crate::common;

use common::bus::free_port;

use std::path::Path;
use std::time::Duration;

use cellgate::bus;
use cellgate::bus::keys::CellKeys;
use cellgate::cell::Cell;
use cellgate::client::cli::{
    self, CancelArgs, ClientCommand, ConnectArgs, DiArgs, DoArgs, Io, ProgramCommand, StatusArgs,
    SubmitArgs, WatchArgs,
};
use cellgate::client::{Client, ClientError, ConnectOptions, WatchEvent};
use cellgate::gateway;
use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use sha2::{Digest, Sha256};
use tokio_util::sync::CancellationToken;
use zenoh::Session;

const CELL: &str = "line-7";
const MILL_A: &str = "mill-1";
const MILL_X: &str = "mill-2";
use common::cli::{BIN, cellgate};

/// A plain NC program of about `size` bytes: `%`, an O number, G01 blocks, M30, EOR `%`.
fn nc_program(size: usize, number: u32) -> Vec<u8> {
    let mut p = format!("%\nO{number:04}\n").into_bytes();
    let mut n = 1;
    while p.len() + 24 < size {
        p.extend_from_slice(format!("N{n} G01 X{}.5 Y-{}.25\n", n % 400, n % 90).as_bytes());
        n += 1;
    }
    p.extend_from_slice(b"M30\n%");
    p
}

// ---------------------------------------------------------------------------------------------
// A gateway in this process: the simulated cell's links served with `bus::serve`, plus the
// gateway's admin key and liveliness token (as `gateway::run` declares them).
// ---------------------------------------------------------------------------------------------

struct Gateway {
    endpoint: String,
    session: Session,
    cell: Cell,
    links_stop: CancellationToken,
    stop: CancellationToken,
    served: tokio::task::JoinHandle<Result<(), bus::BusError>>,
    admin: tokio::task::JoinHandle<()>,
    _dir: tempfile::TempDir,
}

async fn start_gateway() -> Gateway {
    start_gateway_with(|_| {}).await
}

/// [`start_gateway`], with the machine links changed by `links` before they are served.
async fn start_gateway_with(links: impl FnOnce(&mut Vec<bus::MachineLink>)) -> Gateway {
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let mut config = CellConfig::embedded_default();
    // Its MTConnect agent would take a fixed port; this test does not look at it.
    config.mtconnect = None;
    config.opcua = None;
    config.cell = CELL.to_string();
    config.bus.listen = vec![format!("tcp/127.0.0.1:{port}")];
    config.bus.connect = Vec::new();
    config.bus.multicast_scouting = false;
    config.programs.dir = dir.path().join("programs");
    config.programs.max_size = 1 << 20;
    let session = bus::open(&config.bus).await.unwrap();

    let links_stop = CancellationToken::new();
    let cell = Cell::start(&config, &links_stop).await.unwrap();
    let mut machines = cell.machine_links();
    links(&mut machines);
    let stop = CancellationToken::new();
    let (ready_tx, ready) = tokio::sync::oneshot::channel();
    let served = {
        let (s, c, stop) = (session.clone(), config.clone(), stop.clone());
        tokio::spawn(
            async move { bus::serve_announced(&s, &c, machines, stop, Some(ready_tx)).await },
        )
    };
    // Announced once every route is declared, as `gateway::run` does.
    ready.await.expect("the routes are declared");
    let admin = {
        let keys = CellKeys::new(&config.bus.prefix, &config.cell).unwrap();
        let key = keys.admin();
        let doc = gateway::admin_document(&config, &session.zid().to_string()).to_string();
        let queryable = session.declare_queryable(key.as_str()).await.unwrap();
        let token = session
            .liveliness()
            .declare_token(keys.gateway())
            .await
            .unwrap();
        tokio::spawn(async move {
            let _token = token;
            while let Ok(q) = queryable.recv_async().await {
                let _ = q.reply(key.as_str(), doc.as_str()).await;
            }
        })
    };
    let gw = Gateway {
        endpoint: format!("tcp/127.0.0.1:{port}"),
        session,
        cell,
        links_stop,
        stop,
        served,
        admin,
        _dir: dir,
    };
    // Both links initialised: their liveliness tokens stand.
    let client = gw.client().await;
    for m in [MILL_A, MILL_X] {
        let key = client.keys().machine(m);
        let mut up = false;
        for _ in 0..300 {
            let replies = client
                .session()
                .liveliness()
                .get(key.as_str())
                .await
                .unwrap();
            if replies.recv_async().await.is_ok() {
                up = true;
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(up, "{m}'s link never came up");
    }
    client.close().await;
    gw
}

impl Gateway {
    fn connect(&self) -> ConnectArgs {
        common::bus::connect_args(self.endpoint.clone(), Some("tester".to_string()))
    }

    async fn client(&self) -> Client {
        Client::connect(&self.connect().options().unwrap())
            .await
            .unwrap()
    }

    fn board(&self, machine: &str) -> &cellgate::sim::BoardHandle {
        self.cell.machine(machine).unwrap().board.as_ref().unwrap()
    }

    async fn stop(self) {
        self.stop.cancel();
        tokio::time::timeout(Duration::from_secs(10), self.served)
            .await
            .expect("serve did not stop")
            .unwrap()
            .unwrap();
        self.admin.abort();
        self.links_stop.cancel();
        tokio::time::timeout(Duration::from_secs(10), self.cell.join())
            .await
            .expect("links did not stop");
        self.session.close().await.unwrap();
    }
}

/// Runs a command in process; returns (exit code, stdout, stderr).
async fn run(command: &impl ClientCommand) -> (u8, String, String) {
    let (mut out, mut err) = (Vec::new(), Vec::new());
    let code = {
        let mut io = Io {
            out: &mut out,
            err: &mut err,
            progress_bar: false,
        };
        cli::run_command(command, &mut io).await
    };
    (
        code,
        String::from_utf8_lossy(&out).into_owned(),
        String::from_utf8_lossy(&err).into_owned(),
    )
}

fn submit_args(gw: &Gateway, machine: &str) -> SubmitArgs {
    SubmitArgs {
        connect: gw.connect(),
        machine: Some(machine.to_string()),
        file: None,
        library: None,
        revision: None,
        key: None,
        priority: 0,
        name: None,
        append_eor: false,
        detach: false,
        resume: None,
        from_block: None,
        header_lines: None,
        resume_after_restart: false,
        deadline: None,
        request_id: None,
        json: false,
    }
}

fn write_file(dir: &Path, name: &str, data: &[u8]) -> std::path::PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, data).unwrap();
    path
}

/// Waits until the board's CNC has received `n` programs; returns the last.
async fn received(gw: &Gateway, machine: &str, n: usize) -> cellgate_core::sim::ReceivedProgram {
    let board = gw.board(machine);
    let snap = tokio::time::timeout(
        Duration::from_secs(30),
        board.wait_for(|s| s.programs.len() >= n),
    )
    .await
    .expect("the CNC never received the program");
    snap.programs[n - 1].clone()
}

/// Waits until the board's DO image is `image`.
async fn do_image(gw: &Gateway, machine: &str, image: u8) {
    let board = gw.board(machine);
    tokio::time::timeout(
        Duration::from_secs(10),
        board.wait_for(|s| s.do_image == image),
    )
    .await
    .unwrap_or_else(|_| panic!("the board's DO never became {image:#04X}"));
}

fn sha(data: &[u8]) -> [u8; 32] {
    Sha256::digest(data).into()
}

// ---------------------------------------------------------------------------------------------
// Tests
// ---------------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn submit_delivers_the_program_and_exits_0() {
    let gw = start_gateway().await;
    let files = tempfile::tempdir().unwrap();
    let program = nc_program(3000, 4711);
    let mut args = submit_args(&gw, MILL_A);
    args.file = Some(write_file(files.path(), "O4711.nc", &program));
    args.name = Some("bracket".to_string());
    let (code, out, err) = run(&args).await;
    assert_eq!(code, 0, "stdout {out:?}\nstderr {err}");
    let job = out.trim();
    assert!(job.starts_with("mill-1-"), "{out:?}");
    assert!(err.contains(&format!("{job}: queued")), "{err}");
    assert!(err.contains(&format!("{job}: started")), "{err}");
    assert!(err.contains(&format!("{job}: completed")), "{err}");
    let got = received(&gw, MILL_A, 1).await;
    assert_eq!(got.len, program.len() as u64);
    assert_eq!(got.sha256, sha(&program));
    assert_eq!(got.first_line, "O4711");

    // The job's last event stays available, and the counters show it.
    let client = gw.client().await;
    let last = client.job_latest(MILL_A, job).await.unwrap();
    assert!(matches!(
        last.kind,
        Some(pb::job_event::Kind::Completed(ref c)) if c.bytes_sent == program.len() as u64
    ));
    let status = client.status(Some(MILL_A)).await.unwrap();
    assert_eq!(status[0].counters.as_ref().unwrap().jobs_completed, 1);
    client.close().await;
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refused_submits_exit_2_with_the_gateways_message() {
    let gw = start_gateway().await;
    let files = tempfile::tempdir().unwrap();

    // No EOR: the gateway refuses (unless --append-eor).
    let no_eor = b"%\nO0001\nG00X0\n".to_vec();
    let mut args = submit_args(&gw, MILL_A);
    args.file = Some(write_file(files.path(), "no-eor.nc", &no_eor));
    let (code, out, err) = run(&args).await;
    assert_eq!(code, 2, "{err}");
    assert!(out.is_empty(), "{out:?}");
    assert!(err.contains("ERROR_CODE_INVALID_REQUEST"), "{err}");
    assert!(err.contains("no EOR"), "{err}");

    // An unknown machine; the gateway names the ones it has.
    let mut args = submit_args(&gw, "nosuch");
    args.file = Some(write_file(files.path(), "ok.nc", b"%\nO1\n%"));
    let (code, _, err) = run(&args).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("ERROR_CODE_UNKNOWN_MACHINE"), "{err}");
    assert!(err.contains("mill-1"), "{err}");

    // A library program that does not exist.
    let mut args = submit_args(&gw, MILL_A);
    args.library = Some("O9999".to_string());
    let (code, _, err) = run(&args).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("ERROR_CODE_NOT_FOUND"), "{err}");

    // A file that cannot be read is a usage error too, before anything is sent.
    let mut args = submit_args(&gw, MILL_A);
    args.file = Some(files.path().join("missing.nc"));
    let (code, _, err) = run(&args).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("missing.nc"), "{err}");

    // With --append-eor the first program goes through.
    let mut args = submit_args(&gw, MILL_A);
    args.file = Some(write_file(files.path(), "no-eor.nc", &no_eor));
    args.append_eor = true;
    let (code, _, err) = run(&args).await;
    assert_eq!(code, 0, "{err}");
    let got = received(&gw, MILL_A, 1).await;
    assert_eq!(got.len, no_eor.len() as u64 + 1);
    // Nothing refused ever reached a CNC.
    assert_eq!(gw.board(MILL_A).programs().len(), 1);
    assert!(gw.board(MILL_X).programs().is_empty());
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_shows_every_machine_as_a_table_and_as_json() {
    let gw = start_gateway().await;
    let args = StatusArgs {
        connect: gw.connect(),
        machine: None,
        json: false,
    };
    let (code, out, err) = run(&args).await;
    assert_eq!(code, 0, "{err}");
    let lines: Vec<&str> = out.lines().collect();
    assert!(lines[0].starts_with("MACHINE"), "{out}");
    // One row per served machine, by name (lathe-1 too, once Protocol B links are driven).
    let row = |m: &str| {
        lines
            .iter()
            .find(|l| l.starts_with(&format!("{m} ")))
            .copied()
            .unwrap_or_else(|| panic!("no row for {m}:\n{out}"))
    };
    assert!(row(MILL_A).contains(" A "), "{out}");
    assert!(row(MILL_X).contains(" Expansion A "), "{out}");
    for m in [MILL_A, MILL_X] {
        assert!(row(m).contains(" idle "), "{out}");
    }

    let args = StatusArgs {
        connect: gw.connect(),
        machine: Some(MILL_X.to_string()),
        json: true,
    };
    let (code, out, err) = run(&args).await;
    assert_eq!(code, 0, "{err}");
    let json: serde_json::Value = serde_json::from_str(&out).unwrap();
    let all = json.as_array().unwrap();
    assert_eq!(all.len(), 1, "{out}");
    assert_eq!(all[0]["machine"], MILL_X);
    assert_eq!(all[0]["protocol"], "PROTOCOL_EXPANSION_A");
    // The link is initialised (start_gateway saw its liveliness token).
    assert_eq!(all[0]["link_state"], "LINK_STATE_IDLE", "{out}");
    assert_eq!(all[0]["counters"]["jobs_completed"], 0, "{out}");

    let args = StatusArgs {
        connect: gw.connect(),
        machine: Some("nosuch".to_string()),
        json: false,
    };
    let (code, _, err) = run(&args).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("ERROR_CODE_UNKNOWN_MACHINE"), "{err}");
    // `jobs` of a machine the cell lacks speaks of its queue, not of a status.
    let ep = gw.endpoint.clone();
    let (code, _, err) = cellgate(&["jobs", "-e", &ep, "nosuch"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("ERROR_CODE_UNKNOWN_MACHINE"), "{err}");
    assert!(
        err.contains("queue of nosuch") && !err.contains("status of"),
        "{err}"
    );
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn do_and_di_round_trip_through_the_board() {
    let gw = start_gateway().await;
    let args = DoArgs {
        connect: gw.connect(),
        machine: MILL_A.to_string(),
        value: 0xA5,
        mask: None,
        no_wait: false,
        json: false,
    };
    let (code, out, err) = run(&args).await;
    assert_eq!(code, 0, "{err}");
    assert_eq!(out.trim(), "mill-1 DO 0xA5 0b10100101");
    do_image(&gw, MILL_A, 0xA5).await;

    // Only the masked bits change.
    let args = DoArgs {
        value: 0x00,
        mask: Some(0x0F),
        ..args
    };
    let (code, out, err) = run(&args).await;
    assert_eq!(code, 0, "{err}");
    assert_eq!(out.trim(), "mill-1 DO 0xA0 0b10100000");
    do_image(&gw, MILL_A, 0xA0).await;
    let client = gw.client().await;
    let s = client.status(Some(MILL_A)).await.unwrap();
    assert_eq!(s[0].do_image, Some(0xA0));

    gw.board(MILL_X).set_di(0x3C);
    let args = DiArgs {
        connect: gw.connect(),
        machine: MILL_X.to_string(),
        json: false,
    };
    let (code, out, err) = run(&args).await;
    assert_eq!(code, 0, "{err}");
    assert!(out.starts_with("mill-2 DI 0x3C 0b00111100 (60)"), "{out}");
    assert!(out.contains("0 0 1 1 1 1 0 0"), "{out}");
    gw.board(MILL_X).set_di(0x81);
    // A second read right after the first: RDI goes out with the answer to the board's next
    // SAT or GTD, which may be a whole poll away.
    let di = client.read_di(MILL_X).await.unwrap();
    assert_eq!(di.value, 0x81);
    client.close().await;

    // Refused by the gateway: an unknown machine.
    let args = DiArgs {
        connect: gw.connect(),
        machine: "nosuch".to_string(),
        json: true,
    };
    let (code, _, err) = run(&args).await;
    assert_eq!(code, 2, "{err}");
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_program_library_round_trips_and_feeds_a_job() {
    let gw = start_gateway().await;
    let files = tempfile::tempdir().unwrap();
    let program = nc_program(2500, 815);
    let file = write_file(files.path(), "O0815.nc", &program);
    let put = ProgramCommand::Put {
        connect: gw.connect(),
        name: "O0815".to_string(),
        file: file.clone(),
        comment: None,
        json: true,
    };
    let (code, out, err) = run(&put).await;
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("O0815: stored"), "{err}");
    // Sizes as everywhere else on the command line (and in the console).
    let size = cellgate::client::render::bytes(program.len() as u64);
    assert!(
        err.contains(&format!("stored, {size}, revision 1")),
        "{err}"
    );
    let stored: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(stored["size"], program.len(), "{out}");

    let ls = ProgramCommand::Ls {
        connect: gw.connect(),
        json: true,
    };
    let (code, out, err) = run(&ls).await;
    assert_eq!(code, 0, "{err}");
    let list: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(list[0]["name"], "O0815");
    assert_eq!(list[0]["size"], program.len());

    let copy = files.path().join("copy.nc");
    let get = ProgramCommand::Get {
        connect: gw.connect(),
        name: "O0815".to_string(),
        revision: None,
        output: Some(copy.clone()),
        json: false,
    };
    let (code, _, err) = run(&get).await;
    assert_eq!(code, 0, "{err}");
    assert_eq!(std::fs::read(&copy).unwrap(), program);

    // Submitted from the library to the Expansion A machine.
    let mut args = submit_args(&gw, MILL_X);
    args.library = Some("O0815".to_string());
    let (code, out, err) = run(&args).await;
    assert_eq!(code, 0, "{out}{err}");
    let got = received(&gw, MILL_X, 1).await;
    assert_eq!(got.sha256, sha(&program));

    let rm = ProgramCommand::Rm {
        connect: gw.connect(),
        name: "O0815".to_string(),
        json: false,
    };
    let (code, _, err) = run(&rm).await;
    assert_eq!(code, 0, "{err}");
    let (code, out, _) = run(&ls).await;
    assert_eq!(code, 0);
    assert_eq!(out.trim(), "[]");
    // Removing it again, or fetching it, is refused; a bad name never leaves the client.
    let (code, _, err) = run(&rm).await;
    assert_eq!(code, 2, "{err}");
    let (code, _, err) = run(&get).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("ERROR_CODE_NOT_FOUND"), "{err}");
    let bad = ProgramCommand::Put {
        connect: gw.connect(),
        name: "../etc".to_string(),
        file,
        comment: None,
        json: false,
    };
    let (code, _, err) = run(&bad).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("not valid"), "{err}");
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_running_job_is_cancelled_and_watch_sees_it() {
    let gw = start_gateway().await;
    let client = gw.client().await;
    let mut watch = client.watch().await.unwrap();
    // At 19200 baud this takes about 20 s: long enough to cancel it part way.
    let program = nc_program(40_000, 42);
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(program.clone())),
        ..pb::JobRequest::default()
    };
    let (accepted, mut follower) = client.submit(MILL_A, &request).await.unwrap();
    let job = accepted.job_id.clone();
    // Wait until the board has acknowledged part of the program.
    loop {
        let e = follower.next().await.unwrap().unwrap();
        if matches!(e.kind, Some(pb::job_event::Kind::Progress(p)) if p.bytes_sent > 0) {
            break;
        }
    }
    // The job id names the machine.
    let args = CancelArgs {
        connect: gw.connect(),
        job_id: job.clone(),
        legacy_job_id: None,
        json: false,
    };
    let (code, _, err) = run(&args).await;
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("cancelled by request"), "{err}");
    let last = follower.wait_end().await.unwrap();
    match last.kind {
        Some(pb::job_event::Kind::Cancelled(c)) => {
            assert!(c.byte_offset > 0 && c.byte_offset < program.len() as u64)
        }
        other => panic!("{other:?}"),
    }
    follower.close().await;

    // Cancelling it again: it already ended.
    let (code, _, err) = run(&args).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("already ended"), "{err}");

    // The watch saw the link up, the job's events in order, and the cancel request after the
    // job started. The delete reaches the watch through the gateway's router while the
    // gateway acts on it, so it may show before or after the job's `cancelled` event.
    let mut seen: Vec<String> = Vec::new();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while !(seen.iter().any(|s| s == "cancelled") && seen.iter().any(|s| s == "cancel-requested")) {
        let e = tokio::time::timeout_at(deadline, watch.next())
            .await
            .expect("watch never saw the job end and the cancel request")
            .unwrap();
        match e {
            WatchEvent::Link { machine, up } if machine == MILL_A => {
                seen.push(format!("link {up}"))
            }
            WatchEvent::Job(e) if e.job_id == job => {
                let kind = cellgate::client::render::job_kind_text(&e);
                seen.push(kind.split(' ').next().unwrap().to_string())
            }
            WatchEvent::CancelRequested { job_id, .. } if job_id == job => {
                seen.push("cancel-requested".to_string())
            }
            _ => {}
        }
    }
    let pos = |s: &str| seen.iter().position(|x| x == s);
    assert_eq!(
        seen.first().map(String::as_str),
        Some("link true"),
        "{seen:?}"
    );
    assert!(pos("queued") < pos("started"), "{seen:?}");
    assert!(pos("started") < pos("cancel-requested"), "{seen:?}");
    assert!(pos("started") < pos("cancelled"), "{seen:?}");
    watch.close().await;
    client.close().await;
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watch_prints_lines_and_json() {
    let gw = start_gateway().await;
    let args = WatchArgs {
        connect: gw.connect(),
        machine: Some(MILL_X.to_string()),
        tags: None,
        json: true,
        count: Some(2),
    };
    // The current tokens come first: mill-2's link is up; then its status (a DI read
    // publishes DI and changes the status).
    let watching = tokio::spawn(async move { run(&args).await });
    tokio::time::sleep(Duration::from_millis(500)).await;
    gw.board(MILL_X).set_di(0x42);
    let client = gw.client().await;
    client.read_di(MILL_X).await.unwrap();
    let (code, out, err) = tokio::time::timeout(Duration::from_secs(20), watching)
        .await
        .expect("watch did not stop after 2 lines")
        .unwrap();
    assert_eq!(code, 0, "{err}");
    let lines: Vec<serde_json::Value> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 2, "{out}");
    assert_eq!(lines[0]["event"], "link_up");
    assert_eq!(lines[0]["machine"], MILL_X);
    for l in &lines[1..] {
        let machine = l["status"]["machine"]
            .as_str()
            .or(l["di"]["machine"].as_str());
        assert_eq!(machine, Some(MILL_X), "{l}");
    }
    client.close().await;
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connecting_tells_what_is_wrong() {
    // Nothing listens.
    let port = free_port();
    let options = ConnectOptions {
        endpoint: format!("tcp/127.0.0.1:{port}"),
        ..ConnectOptions::default()
    };
    let e = Client::connect(&options).await.unwrap_err();
    assert!(matches!(e, ClientError::Unreachable { .. }), "{e}");
    assert_eq!(e.exit_code(), 1);
    assert!(e.to_string().contains("`cellgate run` running"), "{e}");

    // A malformed endpoint or prefix is a usage error.
    let bad = ConnectOptions {
        endpoint: "not-an-endpoint".to_string(),
        ..ConnectOptions::default()
    };
    assert_eq!(Client::connect(&bad).await.unwrap_err().exit_code(), 2);
    let bad = ConnectOptions {
        prefix: "a/**".to_string(),
        ..ConnectOptions::default()
    };
    assert_eq!(Client::connect(&bad).await.unwrap_err().exit_code(), 2);

    let gw = start_gateway().await;
    // The one cell is found without --cell.
    let client = gw.client().await;
    assert_eq!(client.cell(), CELL);
    assert_eq!(
        client.configured_machines(),
        ["mill-1", "mill-2", "lathe-1"]
    );
    client.close().await;

    // A cell that is not there: the answering ones are named.
    let mut options = gw.connect().options().unwrap();
    options.cell = Some("line-8".to_string());
    let e = Client::connect(&options).await.unwrap_err();
    assert!(matches!(e, ClientError::NoGateway { .. }), "{e}");
    assert!(
        e.to_string().contains("cells answering there: line-7"),
        "{e}"
    );
    // Another prefix: nobody answers.
    let mut options = gw.connect().options().unwrap();
    options.prefix = "elsewhere".to_string();
    let e = Client::connect(&options).await.unwrap_err();
    assert!(e.to_string().contains("no gateway answered"), "{e}");

    // Two cells on one endpoint: --cell is needed.
    let other = gw
        .session
        .declare_queryable("cellgate/line-9/@admin")
        .callback(|q| {
            use zenoh::Wait;
            let _ = q.reply("cellgate/line-9/@admin", "{}").wait();
        })
        .await
        .unwrap();
    let e = Client::connect(&gw.connect().options().unwrap())
        .await
        .unwrap_err();
    assert!(matches!(e, ClientError::SeveralCells { .. }), "{e}");
    assert!(e.to_string().contains("line-7, line-9"), "{e}");
    assert_eq!(e.exit_code(), 2);
    let mut options = gw.connect().options().unwrap();
    options.cell = Some(CELL.to_string());
    let client = Client::connect(&options).await.unwrap();
    let served = client.status(None).await.unwrap();
    assert!(served.iter().any(|s| s.machine == MILL_A), "{served:?}");
    client.close().await;
    other.undeclare().await.unwrap();
    gw.stop().await;
}

// ---------------------------------------------------------------------------------------------
// The binary
// ---------------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_binary_submits_and_shows_status() {
    let gw = start_gateway().await;
    let files = tempfile::tempdir().unwrap();
    let program = nc_program(6000, 1234);
    let file = write_file(files.path(), "O1234.nc", &program);
    let file = file.to_str().unwrap();
    let ep = gw.endpoint.as_str();

    let (code, out, err) = cellgate(&["submit", "-e", ep, MILL_X, file]).await;
    assert_eq!(code, 0, "stdout {out:?}\nstderr {err}");
    assert!(out.trim().starts_with("mill-2-"), "{out:?}");
    assert!(err.contains("completed"), "{err}");
    let got = received(&gw, MILL_X, 1).await;
    assert_eq!(got.sha256, sha(&program));

    let (code, out, err) = cellgate(&["status", "--connect", ep, "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let json: serde_json::Value = serde_json::from_str(&out).unwrap();
    let names: Vec<&str> = json
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["machine"].as_str().unwrap())
        .collect();
    assert!(
        names.contains(&MILL_A) && names.contains(&MILL_X),
        "{names:?}"
    );
    let mut sorted = names.clone();
    sorted.sort_unstable();
    assert_eq!(names, sorted, "status is sorted by machine");
    let mill_x = json
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["machine"] == MILL_X)
        .unwrap();
    assert_eq!(mill_x["counters"]["jobs_completed"], 1, "{mill_x}");

    let (code, out, err) = cellgate(&["status", "-e", ep, "--cell", CELL, MILL_A]).await;
    assert_eq!(code, 0, "{err}");
    assert!(out.lines().nth(1).unwrap().starts_with("mill-1"), "{out}");

    // Refused (no EOR): exit 2 with the gateway's message; a DO value out of range never
    // leaves the command line.
    let bad = write_file(files.path(), "bad.nc", b"%\nO1\n");
    let (code, out, err) = cellgate(&["submit", "-e", ep, MILL_A, bad.to_str().unwrap()]).await;
    assert_eq!(code, 2, "{out}{err}");
    assert!(err.contains("no EOR"), "{err}");
    let (code, _, err) = cellgate(&["do", "-e", ep, MILL_A, "0x100"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("0..=255"), "{err}");
    let (code, out, err) = cellgate(&["do", "-e", ep, MILL_A, "0b1100_0011"]).await;
    assert_eq!(code, 0, "{err}");
    assert_eq!(out.trim(), "mill-1 DO 0xC3 0b11000011");
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_binary_says_when_no_gateway_answers() {
    let port = free_port();
    let ep = format!("tcp/127.0.0.1:{port}");
    let (code, _, err) = cellgate(&["status", "--connect", &ep]).await;
    assert_eq!(code, 1, "{err}");
    assert!(err.contains(&format!("cannot connect to {ep}")), "{err}");
    assert!(err.contains("`cellgate run` running"), "{err}");
}

// ---------------------------------------------------------------------------------------------
// The binary against a `cellgate run` process
// ---------------------------------------------------------------------------------------------

/// A `cellgate run` process on the embedded default cell, on a free loopback port, in a
/// temporary directory (its program library goes there). Stopped with SIGTERM on drop.
struct RunProcess {
    child: std::process::Child,
    endpoint: String,
    _dir: tempfile::TempDir,
}

impl RunProcess {
    async fn start() -> RunProcess {
        let port = free_port();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let dir = tempfile::tempdir().unwrap();
        let child = common::cli::bin()
            .args([
                "run",
                "-l",
                &endpoint,
                "--console",
                "off",
                "--mtconnect",
                "off",
                "--opcua",
                "off",
            ])
            .current_dir(dir.path())
            .env(
                "RUST_LOG",
                std::env::var("CELLGATE_TEST_RUST_LOG").unwrap_or("warn".into()),
            )
            .env_remove("CELLGATE_CONFIG")
            .env_remove("OTEL_EXPORTER_OTLP_ENDPOINT")
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            // CELLGATE_TEST_LOG=FILE keeps the gateway's log for a failing test.
            .stderr(match std::env::var_os("CELLGATE_TEST_LOG") {
                Some(f) => std::fs::File::create(f).unwrap().into(),
                None => std::process::Stdio::null(),
            })
            .spawn()
            .unwrap();
        let run = RunProcess {
            child,
            endpoint,
            _dir: dir,
        };
        // Up once mill-1 and mill-2 are initialised (status says idle).
        for _ in 0..120 {
            let (code, out, _) = cellgate(&["status", "-e", &run.endpoint, "--json"]).await;
            if code == 0 {
                let json: serde_json::Value = serde_json::from_str(&out).unwrap();
                let idle = json
                    .as_array()
                    .unwrap()
                    .iter()
                    .filter(|s| {
                        (s["machine"] == MILL_A || s["machine"] == MILL_X)
                            && s["link_state"] == "LINK_STATE_IDLE"
                    })
                    .count();
                if idle == 2 {
                    return run;
                }
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
        panic!(
            "cellgate run on {} never showed two idle links",
            run.endpoint
        );
    }
}

impl Drop for RunProcess {
    fn drop(&mut self) {
        let pid = self.child.id() as libc::pid_t;
        // SAFETY: kill(2) on the pid of a child this process spawned and has not reaped.
        unsafe {
            libc::kill(pid, libc::SIGTERM);
        }
        for _ in 0..100 {
            if matches!(self.child.try_wait(), Ok(Some(_))) {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_binary_against_cellgate_run() {
    let run = RunProcess::start().await;
    let ep = run.endpoint.as_str();
    let files = tempfile::tempdir().unwrap();
    let program = nc_program(4000, 77);
    let file = write_file(files.path(), "O0077.nc", &program);

    // The cell is found without --cell: the embedded default is "demo".
    let (code, out, err) = cellgate(&["status", "-e", ep]).await;
    assert_eq!(code, 0, "{err}");
    let rows: Vec<&str> = out.lines().skip(1).collect();
    assert!(rows.iter().any(|r| r.starts_with("mill-1 ")), "{out}");
    assert!(rows.iter().any(|r| r.starts_with("mill-2 ")), "{out}");

    for machine in [MILL_A, MILL_X] {
        let (code, out, err) =
            cellgate(&["submit", "-e", ep, machine, file.to_str().unwrap()]).await;
        assert_eq!(code, 0, "{machine}: stdout {out:?}\nstderr {err}");
        let job = out.trim();
        assert!(job.starts_with(&format!("{machine}-")), "{out:?}");
        assert!(
            err.contains(&format!(
                "{job}: completed: {}",
                cellgate::client::render::bytes(program.len() as u64)
            )),
            "{err}"
        );
    }
    let (code, out, err) = cellgate(&["status", "-e", ep, "--cell", "demo", "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let json: serde_json::Value = serde_json::from_str(&out).unwrap();
    for s in json.as_array().unwrap() {
        if s["machine"] == MILL_A || s["machine"] == MILL_X {
            assert_eq!(s["counters"]["jobs_completed"], 1, "{s}");
            assert_eq!(s["counters"]["nc_bytes_sent"], program.len(), "{s}");
        }
    }

    // A refused submit: exit 2 with the gateway's message.
    let (code, _, err) = cellgate(&["submit", "-e", ep, "nosuch", file.to_str().unwrap()]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("no machine \"nosuch\""), "{err}");
    drop(run);
}

/// A circle of `n` blocks in XY (Z still), as the CSV `cellgate g05` reads: relative travels.
fn circle_csv(n: usize, radius: f64) -> (String, [i64; 3]) {
    let mut csv = String::from("# X, Y, Z travels of a circle\n");
    let (mut px, mut py) = (radius.round() as i64, 0i64);
    let mut sums = [0i64; 3];
    for i in 1..=n {
        let a = std::f64::consts::TAU * i as f64 / n as f64;
        let (x, y) = (
            (radius * a.cos()).round() as i64,
            (radius * a.sin()).round() as i64,
        );
        let (dx, mut dy) = (x - px, y - py);
        // Never an all-zero block: that would end binary mode.
        if dx == 0 && dy == 0 {
            dy = 1;
        }
        csv.push_str(&format!("{dx},{dy},0\n"));
        sums[0] += dx;
        sums[1] += dy;
        (px, py) = (px + dx, py + dy);
    }
    (csv, sums)
}

/// `cellgate g05` streams a CSV (from a file, or piped in) to the embedded default cell's
/// G05 machine and exits 0 once the stream ended cleanly; a bad line and a machine without
/// G05 exit 2.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_g05_command_streams_a_csv_against_cellgate_run() {
    let run = RunProcess::start().await;
    let ep = run.endpoint.as_str();
    let files = tempfile::tempdir().unwrap();
    let (csv, _) = circle_csv(1500, 3000.0);
    let file = write_file(files.path(), "circle.csv", csv.as_bytes());
    let (code, out, err) =
        cellgate(&["g05", "-e", ep, MILL_X, file.to_str().unwrap(), "--json"]).await;
    assert_eq!(code, 0, "stdout {out:?}\nstderr {err}");
    let last: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(last["state"], "completed", "{out}");
    assert_eq!(last["received"], 1500, "{out}");
    assert_eq!(last["end_reason"], "Producer", "{out}");
    assert!(err.contains("3 axes, T = 2 ms"), "{err}");

    // Piped in on standard input.
    let mut child = tokio::process::Command::new(BIN)
        .args(["g05", "-e", ep, MILL_X, "-"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    {
        use tokio::io::AsyncWriteExt;
        let mut stdin = child.stdin.take().unwrap();
        stdin.write_all(csv.as_bytes()).await.unwrap();
    }
    let piped = child.wait_with_output().await.unwrap();
    // Without --json the last status is a line of text.
    let summary = String::from_utf8_lossy(&piped.stdout);
    assert!(
        summary.starts_with("G05 stream ") && summary.contains("completed: 1500 blocks"),
        "{summary}"
    );
    assert_eq!(
        piped.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&piped.stderr)
    );

    let bad = write_file(files.path(), "bad.csv", b"1,2,3\n4,x,6\n");
    let (code, _, err) = cellgate(&["g05", "-e", ep, MILL_X, bad.to_str().unwrap()]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("bad.csv:2") && err.contains("\"x\""), "{err}");

    let (code, _, err) = cellgate(&["g05", "-e", ep, MILL_A, file.to_str().unwrap()]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("[machines.g05]"), "{err}");
}

/// Resident memory of process `pid`, bytes (Linux: `VmRSS` of /proc/PID/status).
fn rss_of(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap();
    kb * 1024
}

/// The bound on what a flood may add to the gateway's resident memory.
const FLOOD_RSS_BOUND: u64 = 96 * 1024 * 1024;

/// One client floods `cellgate run` with 10 000 job submits and 10 000 DO puts in a few
/// seconds: the gateway answers what it can and refuses the rest (`QUEUE_FULL`, `BUSY`), its
/// memory stays within a bound, and every machine still serves afterwards.
#[cfg(target_os = "linux")]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_requests_leaves_the_gateway_bounded_and_serving() {
    use bus::keys::MachineLeaf;
    use prost::Message;
    let run = RunProcess::start().await;
    let pid = run.child.id();
    let before = rss_of(pid);
    let client = bus::open(&common::bus::client_config(
        run.endpoint.rsplit(':').next().unwrap().parse().unwrap(),
    ))
    .await
    .unwrap();
    let keys = CellKeys::new("cellgate", "demo").unwrap();
    let program = nc_program(2000, 5);
    let started = std::time::Instant::now();
    let mut pending = Vec::new();
    for i in 0..10_000u32 {
        let machine = if i % 2 == 0 { MILL_A } else { MILL_X };
        let request = pb::JobRequest {
            program: Some(pb::job_request::Program::Inline(program.clone())),
            request_id: format!("flood-{i}"),
            ..Default::default()
        };
        let replies = client
            .get(keys.leaf(machine, MachineLeaf::Submit))
            .payload(request.encode_to_vec())
            .timeout(Duration::from_secs(60))
            .await
            .unwrap();
        pending.push(replies);
    }
    for i in 0..10_000u32 {
        let machine = if i % 2 == 0 { MILL_A } else { MILL_X };
        let cmd = pb::DoCommand {
            value: i % 256,
            mask: None,
        };
        client
            .put(keys.leaf(machine, MachineLeaf::Do), cmd.encode_to_vec())
            .await
            .unwrap();
    }
    let sent_in = started.elapsed();
    let (mut accepted, mut refused, mut lost) = (0, std::collections::BTreeMap::new(), 0);
    for replies in pending {
        match replies.recv_async().await {
            Ok(r) => match r.result() {
                Ok(_) => accepted += 1,
                Err(e) => {
                    let code = pb::ErrorReply::decode(e.payload().to_bytes().as_ref())
                        .map(|e| e.code())
                        .unwrap_or(pb::ErrorCode::Unspecified);
                    *refused.entry(format!("{code:?}")).or_insert(0) += 1;
                }
            },
            Err(_) => lost += 1,
        }
    }
    let peak = rss_of(pid);
    eprintln!(
        "flood: sent in {sent_in:?}; {accepted} accepted, refused {refused:?}, {lost} without \
         answer; RSS {} MiB before, {} MiB after",
        before >> 20,
        peak >> 20
    );
    // Each machine takes 256 waiting jobs and the one being sent, plus one for each job that
    // ended while the flood lasted (its slot was free again); the rest are refused.
    let (_, out, _) = cellgate(&["status", "-e", &run.endpoint, "--json"]).await;
    let ended: u64 = serde_json::from_str::<serde_json::Value>(&out)
        .unwrap()
        .as_array()
        .unwrap()
        .iter()
        .map(|s| {
            let c = &s["counters"];
            c["jobs_completed"].as_u64().unwrap_or(0) + c["jobs_failed"].as_u64().unwrap_or(0)
        })
        .sum();
    assert!(
        accepted > 0 && accepted as u64 <= 2 * 257 + ended,
        "{accepted} accepted, {ended} ended"
    );
    assert_eq!(lost, 0, "every submit is answered");
    assert!(
        peak.saturating_sub(before) < FLOOD_RSS_BOUND,
        "RSS grew from {before} to {peak} bytes"
    );
    // Still serving: status answers for every machine, and DO output works.
    let (code, out, err) = cellgate(&["status", "-e", &run.endpoint, "--json"]).await;
    assert_eq!(code, 0, "{err}");
    assert_eq!(
        serde_json::from_str::<serde_json::Value>(&out)
            .unwrap()
            .as_array()
            .unwrap()
            .len(),
        3
    );
    // The flood's last puts may still wait at the link (at most 16 DO images wait there, older
    // ones give way to newer): once the image has settled, a DO must go out and be confirmed.
    let mut last = None;
    for _ in 0..60 {
        let (_, out, _) = cellgate(&["status", "-e", &run.endpoint, "--json", MILL_A]).await;
        let image = serde_json::from_str::<serde_json::Value>(&out)
            .ok()
            .map(|v| v[0]["do_image"].to_string());
        if image.is_some() && image == last {
            break;
        }
        last = image;
        tokio::time::sleep(Duration::from_millis(1000)).await;
    }
    let (code, _, err) = cellgate(&["do", "-e", &run.endpoint, MILL_A, "0x5A"]).await;
    assert_eq!(code, 0, "{err}");
    client.close().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_says_what_is_down_and_fails_when_the_gateway_is_gone() {
    // The embedded default cell, its links initialised: healthy.
    // Three CNCs and the PLC's station, once the station has answered its first poll.
    let run = RunProcess::start().await;
    let healthy = healthy_within(&run.endpoint, 30).await;
    assert!(healthy.is_ok(), "{healthy:?}");
    let (code, out, err) = cellgate(&["health", "-e", &run.endpoint]).await;
    assert_eq!(code, 0, "{out}{err}");
    assert!(out.contains("its 4 link(s) are up"), "{out}");
    drop(run);

    // A machine behind a device server that is not there: its link stays down.
    let dir = tempfile::tempdir().unwrap();
    let nobody = free_port();
    let cell = dir.path().join("cell.toml");
    std::fs::write(
        &cell,
        format!(
            r#"cell = "demo"
[bus]
multicast_scouting = false
[programs]
dir = "{programs}"
[[machines]]
name = "mill-1"
protocol = "a"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
[[machines]]
name = "mill-9"
protocol = "a"
transport = {{ kind = "tcp", address = "127.0.0.1:{nobody}", line = {{ baud = 19200 }} }}
[[plcs]]
name = "plc-9"
mode = 1
transport = {{ kind = "tcp", address = "127.0.0.1:{nobody}", line = {{ baud = 19200 }} }}
[[plcs.tags]]
name = "parts"
module = "D"
address = 0
type = "u16"
poll_ms = 200
"#,
            programs = dir.path().join("programs").display()
        ),
    )
    .unwrap();
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let mut child = common::cli::bin()
        .args(["run", "--config", cell.to_str().unwrap(), "-l", &endpoint])
        .env("RUST_LOG", "error")
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut last = (0, String::new(), String::new());
    for _ in 0..60 {
        last = cellgate(&["health", "-e", &endpoint]).await;
        // Until mill-1 is initialised, it is down too.
        if last.0 == 1 && last.1.contains("2 of 3") && !last.1.contains("mill-1") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    let (code, out, err) = last;
    assert_eq!(code, 1, "{out}{err}");
    assert!(
        out.contains("2 of 3 link(s) down: mill-9 (down), plc-9 station 0 (down)"),
        "{out}"
    );
    // A liveness probe does not care about the links.
    let (code, out, err) = cellgate(&["health", "-e", &endpoint, "--gateway-only"]).await;
    assert_eq!(code, 0, "{out}{err}");

    // Stopped: nothing answers.
    // SAFETY: kill(2) on the pid of a child this process spawned and has not reaped.
    unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
    assert!(child.wait().unwrap().success());
    let (code, _, err) = cellgate(&["health", "-e", &endpoint, "--gateway-only"]).await;
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("cannot connect"), "{err}");
}

/// Spawns `cellgate` with `args`, its output thrown away, stopped (SIGTERM) when dropped.
struct Spawned(std::process::Child);

impl Spawned {
    fn new(args: &[&str], dir: &std::path::Path) -> Spawned {
        Spawned(
            common::cli::bin()
                .args(args)
                .current_dir(dir)
                .env("RUST_LOG", "error")
                .env_remove("CELLGATE_CONFIG")
                .stdin(std::process::Stdio::null())
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::null())
                .spawn()
                .unwrap(),
        )
    }

    /// SIGTERM, then the exit status (killed after 10 s).
    fn stop(&mut self) -> std::process::ExitStatus {
        // SAFETY: kill(2) on the pid of a child this process spawned and has not reaped.
        unsafe { libc::kill(self.0.id() as libc::pid_t, libc::SIGTERM) };
        for _ in 0..200 {
            if let Ok(Some(status)) = self.0.try_wait() {
                return status;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.0.kill();
        self.0.wait().unwrap()
    }
}

impl Drop for Spawned {
    fn drop(&mut self) {
        if matches!(self.0.try_wait(), Ok(None)) {
            self.stop();
        }
    }
}

/// Polls `cellgate health` through `endpoint` until it exits 0 (at most `secs`).
async fn healthy_within(endpoint: &str, secs: u64) -> Result<Duration, String> {
    let started = std::time::Instant::now();
    let mut last = String::new();
    while started.elapsed() < Duration::from_secs(secs) {
        let (code, out, err) = cellgate(&["health", "-e", endpoint]).await;
        if code == 0 {
            return Ok(started.elapsed());
        }
        last = format!("{out}{err}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    Err(last)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gateway_serves_again_after_its_router_restarts() {
    let dir = tempfile::tempdir().unwrap();
    let router_ep = format!("tcp/127.0.0.1:{}", free_port());
    let gateway_ep = format!("tcp/127.0.0.1:{}", free_port());
    let mut router = Spawned::new(&["router", "-l", &router_ep], dir.path());
    tokio::time::sleep(Duration::from_millis(500)).await;
    // A peer connected to the router: it keeps retrying the router when it goes away.
    let _gateway = Spawned::new(
        &[
            "run",
            "--mode",
            "peer",
            "-l",
            &gateway_ep,
            "-e",
            &router_ep,
            "--console",
            "off",
            "--mtconnect",
            "off",
            "--opcua",
            "off",
        ],
        dir.path(),
    );
    healthy_within(&router_ep, 60).await.unwrap();
    let (code, out, err) = cellgate(&["status", "-e", &router_ep, "mill-1"]).await;
    assert_eq!(code, 0, "{out}{err}");

    assert!(router.stop().success(), "the router stops cleanly");
    let (code, _, _) = cellgate(&["health", "-e", &router_ep, "--timeout", "2"]).await;
    assert_eq!(code, 1, "no router, no answer through it");
    let _router = Spawned::new(&["router", "-l", &router_ep], dir.path());
    let back = healthy_within(&router_ep, 30).await.unwrap();
    eprintln!("serving through the new router after {back:?}");
    // A job goes through the new router end to end.
    let program = nc_program(1500, 42);
    let file = write_file(dir.path(), "O0042.nc", &program);
    let (code, out, err) =
        cellgate(&["submit", "-e", &router_ep, "mill-1", file.to_str().unwrap()]).await;
    assert_eq!(code, 0, "{out}{err}");
}

/// What status and a job's end say is what happened: the bytes after a program's EOR are
/// named as not sent, the line counters are there, a job the CNC never asks for shows as
/// waiting for the CNC (not an idle link), and cancelled it says it never started.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_and_job_ends_say_what_happened() {
    let gw = start_gateway().await;
    let files = tempfile::tempdir().unwrap();
    // A program file as editors write it: a line end after the EOR.
    let program = b"%\nO0042\nN10 G00 X0 Y0\nN20 M30\n%\n";
    let file = write_file(files.path(), "O0042.nc", program);
    let mut args = submit_args(&gw, MILL_A);
    args.file = Some(file);
    let (code, _, err) = run(&args).await;
    assert_eq!(code, 0, "{err}");
    let sent = cellgate::client::render::bytes(program.len() as u64 - 1);
    assert!(
        err.contains(&format!("completed: {sent} sent"))
            && err.contains("the 1 B after the EOR % not sent"),
        "{err}"
    );

    let client = gw.client().await;
    let s = &client.status(Some(MILL_A)).await.unwrap()[0];
    let c = s.counters.unwrap();
    assert!(
        c.bytes_sent.is_some_and(|b| b > program.len() as u64),
        "{c:?}"
    );
    assert!(c.bytes_received.is_some_and(|b| b > 0), "{c:?}");
    assert!(c.frames.is_some_and(|f| f > 0), "{c:?}");

    // The operator stops starting reads: the next job waits for the CNC.
    let board = gw.board(MILL_A);
    board.command(cellgate_core::sim::BoardCommand::SetAutostart(false));
    board.command(cellgate_core::sim::BoardCommand::StopReading);
    tokio::time::timeout(Duration::from_secs(10), board.wait_for(|s| !s.reading))
        .await
        .unwrap();
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(program.to_vec())),
        ..pb::JobRequest::default()
    };
    let (accepted, follower) = client.submit(MILL_A, &request).await.unwrap();
    let job = accepted.job_id.clone();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    loop {
        let s = client.status(Some(MILL_A)).await.unwrap().remove(0);
        if s.current_job_id == job && !s.waiting_for.is_empty() {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the job never showed as waiting: {s:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let status = StatusArgs {
        connect: gw.connect(),
        machine: Some(MILL_A.to_string()),
        json: false,
    };
    let (code, out, err) = run(&status).await;
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("waiting for CNC"), "{out}");
    assert!(
        out.contains(&format!("job {job} waits")) && out.contains("for the CNC to read it"),
        "{out}"
    );

    // The older form, machine first, still works.
    let cancel = CancelArgs {
        connect: gw.connect(),
        job_id: MILL_A.to_string(),
        legacy_job_id: Some(job.clone()),
        json: false,
    };
    let (code, _, err) = run(&cancel).await;
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains("cancelled by request before the CNC read any of it: nothing was sent"),
        "{err}"
    );
    assert!(!err.contains("resumes"), "{err}");
    follower.close().await;
    // Nothing to resume: it says why.
    let mut resume = submit_args(&gw, MILL_A);
    resume.resume = Some(job.clone());
    let (code, _, err) = run(&resume).await;
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("before any of it went to the board (0 B on the line"),
        "{err}"
    );
    // The job id names its machine, as for `cancel` and `job`: no MACHINE needed.
    let (code, _, err) = cellgate(&["submit", "-e", &gw.endpoint, "--resume", &job]).await;
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("before any of it went to the board (0 B on the line"),
        "{err}"
    );
    client.close().await;
    gw.stop().await;
}

/// One convention for the command line on `cellgate run`: an unknown machine fails at once
/// naming the cell's, a bad endpoint says what one looks like, `watch` is not drowned by a
/// counter tag unless asked, and the usual synonyms point to the subcommand.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_command_line_follows_one_convention() {
    let run = RunProcess::start().await;
    let ep = run.endpoint.as_str();

    let started = std::time::Instant::now();
    let (code, _, err) = cellgate(&["watch", "-e", ep, "mill-9"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(started.elapsed() < Duration::from_secs(15), "watch waited");
    assert!(
        err.contains("no machine or PLC \"mill-9\"")
            && err.contains("lathe-1, mill-1, mill-2")
            && err.contains("plc-1"),
        "{err}"
    );

    // Without --tags, the part counter (a change a second) stays out of the watch.
    let child = tokio::process::Command::new(BIN)
        .args(["watch", "-e", ep])
        .env_remove("CELLGATE_CONNECT")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let pid = child.id().unwrap() as libc::pid_t;
    let killer = tokio::spawn(async move {
        tokio::time::sleep(Duration::from_secs(4)).await;
        // SAFETY: kill(2) on the pid of a child this test spawned and has not reaped.
        unsafe {
            libc::kill(pid, libc::SIGINT);
        }
    });
    let out = child.wait_with_output().await.unwrap();
    killer.await.unwrap();
    let lines = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(lines.contains("mill-1 link up"), "{lines}");
    assert!(!lines.contains("plc-1/parts"), "{lines}");
    // Asked for, it is there; and watching the PLC shows its tags.
    let (code, out, err) = cellgate(&["watch", "-e", ep, "--tags=parts", "--count", "7"]).await;
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("plc-1/parts = "), "{out}");
    assert!(!out.contains("plc-1/door-open"), "{out}");
    let (code, out, err) = cellgate(&["watch", "-e", ep, "plc-1", "--count", "2"]).await;
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("plc-1 station 0 up"), "{out}");
    assert!(!out.contains("mill-1"), "{out}");

    let (code, _, err) = cellgate(&["status", "-e", "127.0.0.1:7447"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("endpoints look like tcp/127.0.0.1:7447"),
        "{err}"
    );
    assert!(!err.contains("Json5") && !err.contains(".cargo"), "{err}");

    for (line, meant) in [
        ("program delete O1", "'rm'"),
        ("program remove O1", "'rm'"),
        ("program list", "'ls'"),
    ] {
        let args: Vec<&str> = line.split(' ').collect();
        let (code, _, err) = cellgate(&args).await;
        assert_eq!(code, 2, "{err}");
        assert!(err.contains(meant), "{line}: {err}");
    }
    let (code, _, err) = cellgate(&["cancel", "-e", ep, "mill-1"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("not a job id"), "{err}");
    drop(run);
}

/// `jobs` shows a machine's queue in run order (and with --all the jobs that ended), `job`
/// a job's latest event or, following it, its events to its end; `status` names the
/// gateway's version and uptime.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_and_job_show_the_queue_and_a_jobs_events() {
    let gw = start_gateway().await;
    let ep = gw.endpoint.clone();
    let files = tempfile::tempdir().unwrap();
    // About 20 s at 19200 baud: the second job waits behind it.
    let long = write_file(files.path(), "long.nc", &nc_program(40_000, 7));
    let short = write_file(files.path(), "short.nc", &nc_program(600, 8));
    let submit = |file: &Path| {
        let ep = ep.clone();
        let file = file.to_str().unwrap().to_string();
        async move {
            let (code, out, err) =
                cellgate(&["submit", "-e", &ep, MILL_A, &file, "--detach"]).await;
            assert_eq!(code, 0, "{err}");
            out.trim().to_string()
        }
    };
    let first = submit(&long).await;
    let second = submit(&short).await;

    let (code, out, err) = cellgate(&["jobs", "-e", &ep, MILL_A]).await;
    assert_eq!(code, 0, "{err}");
    let rows: Vec<&str> = out.lines().skip(1).collect();
    assert!(
        rows[0].contains(&first) && rows[0].contains("active"),
        "{out}"
    );
    assert!(
        rows[1].contains(&second) && rows[1].contains("waiting, 0 ahead"),
        "{out}"
    );
    let (code, out, err) = cellgate(&["job", "-e", &ep, &second]).await;
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains(&format!("{second} on {MILL_A}: queued")),
        "{out}"
    );
    let (code, _, err) = cellgate(&["jobs", "-e", &ep, "mill-9"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("mill-1, mill-2"), "{err}");

    // The first is cancelled; following the second shows it run to its end, exit 0.
    let (code, _, err) = cellgate(&["cancel", "-e", &ep, &first]).await;
    assert_eq!(code, 0, "{err}");
    let (code, out, err) = cellgate(&["job", "-e", &ep, &second, "--follow"]).await;
    assert_eq!(code, 0, "{err}");
    let steps: Vec<&str> = out.lines().collect();
    assert!(steps.last().unwrap().contains(": completed: "), "{out}");
    assert!(
        !out.contains(" sent 0 B"),
        "no progress lines as text: {out}"
    );

    let (code, out, err) = cellgate(&["jobs", "-e", &ep, MILL_A, "--all", "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v[0]["active"], serde_json::Value::Null, "{v}");
    let ended: Vec<&str> = v[0]["ended"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["job_id"].as_str().unwrap())
        .collect();
    assert_eq!(ended, [first.as_str(), second.as_str()], "{v}");

    let (code, out, err) = cellgate(&["status", "-e", &ep]).await;
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains(&format!(
            "gateway: cellgate {}, cell {CELL}, up ",
            env!("CARGO_PKG_VERSION")
        )),
        "{out}"
    );
    gw.stop().await;
}

/// The simulation controls drive simulated machines only, and each what it can: a machine
/// without a simulated board, a punch on Protocol A and a cycle start in alarm are refused,
/// saying why.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn simulation_controls_refuse_what_the_machine_cannot_take() {
    // mill-2 as if it were a real machine: no simulated board to drive.
    let gw = start_gateway_with(|links| {
        for l in links.iter_mut().filter(|l| l.config.name == MILL_X) {
            l.sim = None;
        }
    })
    .await;
    let ep = gw.endpoint.clone();
    let (code, _, err) = cellgate(&["sim", "alarm", "-e", &ep, MILL_X]).await;
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("ERROR_CODE_NOT_SUPPORTED") && err.contains("not simulated"),
        "{err}"
    );
    let (code, _, err) = cellgate(&["sim", "reset", "-e", &ep, "mill-9"]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("ERROR_CODE_UNKNOWN_MACHINE"), "{err}");
    let (code, out, err) = cellgate(&["sim", "state", "-e", &ep, "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let all: serde_json::Value = serde_json::from_str(&out).unwrap();
    let names: Vec<&str> = all
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["machine"].as_str().unwrap())
        .collect();
    assert!(names.contains(&MILL_A) && !names.contains(&MILL_X), "{out}");

    let files = tempfile::tempdir().unwrap();
    let program = write_file(files.path(), "p.nc", b"%\nO0001\nM30\n%\n");
    let (code, _, err) =
        cellgate(&["sim", "punch", "-e", &ep, MILL_A, program.to_str().unwrap()]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("Protocol B function"), "{err}");

    let (code, _, err) = cellgate(&["sim", "auto", "-e", &ep, MILL_A, "off"]).await;
    assert_eq!(code, 0, "{err}");
    let (code, out, err) = cellgate(&["sim", "alarm", "-e", &ep, MILL_A, "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let state: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(state["alarm"], true, "{out}");
    assert_eq!(state["autostart"], false, "{out}");
    let (code, _, err) = cellgate(&["sim", "read", "-e", &ep, MILL_A]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("reset it first"), "{err}");
    let (code, out, err) = cellgate(&["sim", "reset", "-e", &ep, MILL_A]).await;
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("no alarm"), "{out}");
    assert!(!gw.board(MILL_A).snapshot().alarm);
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_user_in_the_environment_records_still_name_who_ran_the_command() {
    let gw = start_gateway().await;
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("O7777.nc");
    std::fs::write(&file, b"%\nO7777\nG00X0\nM30\n%\n").unwrap();
    let ep = gw.endpoint.clone();
    let out = tokio::task::spawn_blocking(move || {
        common::cli::command(["program", "put", "-e", &ep, "O7777"])
            .arg(&file)
            .env_remove("USER")
            .env_remove("LOGNAME")
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(out.status.success(), "{}", common::cli::text(&out));
    let (code, json, err) =
        cellgate(&["program", "history", "-e", &gw.endpoint, "O7777", "--json"]).await;
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    let by = &v["revisions"][0]["by"];
    assert_eq!(by["via"], "cli", "{v}");
    assert!(
        by["user"].as_str().is_some_and(|u| !u.is_empty()),
        "the record names somebody: {v}"
    );
    gw.stop().await;
}
