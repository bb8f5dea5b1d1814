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

// The binary against a `cellgate run` process, and what a person meets first.
mod against_run;
