//! Who may do what on a cell with `[security]`: TLS with client certificates made here (a CA
//! and certificates generated with rcgen), roles turned into zenoh access control, clients in
//! client and peer mode connecting to the gateway directly and through a router. Each refusal
//! is checked where it would show: the simulated board's DO image, the jobs the gateway knows,
//! the program library's directory; and `without_roles_the_same_requests_take_effect` runs the
//! same requests against the same cell without roles to show that those checks see an effect
//! when there is one. Real time, loopback, multicast scouting off.

use crate::common;

use std::path::{Path, PathBuf};
use std::time::Duration;

use cellgate::bus::admin::AdminRoute;
use cellgate::bus::keys::{CellKeys, MachineLeaf};
use cellgate::bus::{self, BusError};
use cellgate::cell::Cell;
use cellgate::client::{Client, ClientError, ClientSecurity, ConnectOptions, Credentials};
use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use common::bus::free_port;
use prost::Message;
use tokio_util::sync::CancellationToken;
use zenoh::Session;

use common::cli::cellgate;
const CELL: &str = "secure";
const MACHINE: &str = "m1";

use common::pki::Pki;

/// The roles of the examples: a dashboard that reads, an MES that submits and keeps the
/// library, an operator who outputs DO, cancels and writes tags, an administrator.
const ROLES: &str = r#"
[[security.roles]]
name = "dashboard"
cert_common_names = ["dash"]
permissions = ["status.read"]

[[security.roles]]
name = "mes"
cert_common_names = ["mes"]
permissions = ["job.submit", "program.write"]

[[security.roles]]
name = "operator"
cert_common_names = ["op"]
permissions = ["status.read", "io.do", "job.cancel", "plc.tag", "sim.control"]

[[security.roles]]
name = "admin"
cert_common_names = ["adm"]
permissions = ["status.read", "admin.read"]
"#;

/// One Protocol A machine on a simulated line, listening on TLS at `endpoint`; `extra` is
/// appended (roles, more `[security]`).
fn cell_file(
    pki: &Pki,
    dir: &Path,
    listen: &str,
    connect: &str,
    mode: &str,
    extra: &str,
) -> String {
    format!(
        r#"
cell = "{CELL}"

[bus]
mode = "{mode}"
listen = [{listen}]
connect = [{connect}]

[programs]
dir = "{programs}"
max_size = 1048576

[[machines]]
name = "{MACHINE}"
protocol = "a"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}

[security.tls]
ca = "{ca}"
certificate = "{cert}"
private_key = "{key}"
{extra}
"#,
        programs = dir.join("programs").display(),
        ca = pki.ca().display(),
        cert = pki.cert("gateway").display(),
        key = pki.key("gateway").display(),
    )
}

/// Logs on the test's output when RUST_LOG asks for them.
fn logs() {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_test_writer()
        .try_init();
}

fn config(text: &str) -> CellConfig {
    logs();
    CellConfig::from_toml_str(text, "test cell").unwrap_or_else(|e| panic!("{e}\n{text}"))
}

// ---- a gateway in this process ------------------------------------------------------------------

/// A gateway assembled as `gateway::run` does it (session from the whole cell file, admin
/// route, links, routes), so that the test can look at the simulated board and the library.
struct Gateway {
    endpoint: String,
    session: Session,
    keys: CellKeys,
    cell: Cell,
    programs: PathBuf,
    links_stop: CancellationToken,
    stop: CancellationToken,
    served: tokio::task::JoinHandle<Result<(), BusError>>,
    admin: tokio::task::JoinHandle<()>,
}

async fn start_gateway(config: CellConfig) -> Gateway {
    let session = bus::open_cell(&config).await.unwrap();
    let keys = CellKeys::new(&config.bus.prefix, &config.cell).unwrap();
    let links_stop = CancellationToken::new();
    let cell = Cell::start(&config, &links_stop).await.unwrap();
    let machines = cell.machine_links();
    let stop = CancellationToken::new();
    let (ready_tx, ready) = tokio::sync::oneshot::channel();
    let served = {
        let (s, c, stop) = (session.clone(), config.clone(), stop.clone());
        tokio::spawn(
            async move { bus::serve_announced(&s, &c, machines, stop, Some(ready_tx)).await },
        )
    };
    // As `gateway::run` does: the cell is announced once every route is declared, so a
    // client that found the gateway gets answers from every route.
    ready.await.expect("the routes are declared");
    let admin = {
        let route = AdminRoute::declare(&session, &keys, &config).await.unwrap();
        let stop = stop.clone();
        tokio::spawn(async move {
            route.run(&stop).await;
            route.undeclare().await;
        })
    };
    let gw = Gateway {
        endpoint: config.bus.listen.first().cloned().unwrap_or_default(),
        session,
        keys,
        cell,
        programs: config.programs.dir.clone(),
        links_stop,
        stop,
        served,
        admin,
    };
    // The links are up (Protocol A: ≈2 s power-on delay): their tokens stand. The gateway's
    // own session asks, which no access rule filters.
    for m in &config.machines {
        let token = gw.keys.machine(&m.name);
        let mut up = false;
        for _ in 0..300 {
            let replies = gw.session.liveliness().get(token.as_str()).await.unwrap();
            if replies.recv_async().await.is_ok() {
                up = true;
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(up, "the link of {} never came up", m.name);
    }
    gw
}

impl Gateway {
    fn board(&self) -> &cellgate::sim::BoardHandle {
        self.cell.machine(MACHINE).unwrap().board.as_ref().unwrap()
    }

    /// The latest event of every job the gateway knows of, as its own session sees them.
    async fn jobs(&self) -> Vec<pb::JobEvent> {
        let replies = self
            .session
            .get(self.keys.job_events(MACHINE, "*"))
            .timeout(Duration::from_secs(5))
            .await
            .unwrap();
        let mut jobs = Vec::new();
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                jobs.push(pb::JobEvent::decode(sample.payload().to_bytes().as_ref()).unwrap());
            }
        }
        jobs
    }

    /// The programs in the library's directory.
    fn programs(&self) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(&self.programs)
            .map(|entries| {
                entries
                    .filter_map(|e| e.ok()?.file_name().into_string().ok())
                    .filter(|n| !n.starts_with('.'))
                    .collect()
            })
            .unwrap_or_default();
        names.sort();
        names
    }

    fn options(&self, security: ClientSecurity) -> ConnectOptions {
        ConnectOptions {
            endpoint: self.endpoint.clone(),
            security,
            timeout: Duration::from_secs(10),
            ..ConnectOptions::default()
        }
    }

    async fn client(&self, security: ClientSecurity) -> Client {
        Client::connect(&self.options(security)).await.unwrap()
    }

    async fn stop(self) {
        self.stop.cancel();
        tokio::time::timeout(Duration::from_secs(10), self.served)
            .await
            .expect("routes stop")
            .unwrap()
            .unwrap();
        let _ = self.admin.await;
        self.links_stop.cancel();
        self.cell.join().await;
        self.session.close().await.unwrap();
    }
}

// ---- raw zenoh clients ----------------------------------------------------------------------------

/// A zenoh session in `mode` ("client" or "peer") that connects to `endpoint` only, listens
/// nowhere, never scouts, checks the server with the test CA and, with `who`, shows that
/// certificate.
async fn open(pki: &Pki, endpoint: &str, mode: &str, who: Option<&str>) -> zenoh::Result<Session> {
    let mut c = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, k: &str, v: String| c.insert_json5(k, &v).unwrap();
    set(&mut c, "mode", format!("{mode:?}"));
    set(&mut c, "connect/endpoints", format!("[{endpoint:?}]"));
    set(&mut c, "listen/endpoints", "[]".to_string());
    set(&mut c, "scouting/multicast/enabled", "false".to_string());
    let tls = "transport/link/tls";
    set(
        &mut c,
        &format!("{tls}/root_ca_certificate"),
        format!("{:?}", pki.ca()),
    );
    if let Some(who) = who {
        set(&mut c, &format!("{tls}/enable_mtls"), "true".to_string());
        set(
            &mut c,
            &format!("{tls}/connect_certificate"),
            format!("{:?}", pki.cert(who)),
        );
        set(
            &mut c,
            &format!("{tls}/connect_private_key"),
            format!("{:?}", pki.key(who)),
        );
    }
    let session = zenoh::open(c).await?;
    if mode == "peer" {
        // A peer opens even when its connection fails; wait until it reaches the gateway.
        for _ in 0..200 {
            if session.info().peers_zid().await.next().is_some() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(25)).await;
        }
    }
    // A session that has just opened may not have heard of the gateway's queryables yet: a
    // get then finds nothing to ask. Wait (3 s at most: a role may not see it) until the
    // gateway's liveliness token, declared after its routes, is visible.
    for _ in 0..30 {
        if let Ok(replies) = session.liveliness().get("cellgate/*/gateway").await
            && replies.recv_async().await.is_ok()
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    Ok(session)
}

/// The replies to a get: Ok payloads and Err payloads.
async fn get(
    s: &Session,
    key: &str,
    payload: Option<Vec<u8>>,
    within: Duration,
) -> Vec<Result<Vec<u8>, Vec<u8>>> {
    let mut b = s.get(key.to_string()).timeout(within);
    if let Some(p) = payload {
        b = b.payload(p);
    }
    let replies = b.await.unwrap();
    let mut out = Vec::new();
    while let Ok(r) = replies.recv_async().await {
        out.push(match r.result() {
            Ok(s) => Ok(s.payload().to_bytes().into_owned()),
            Err(e) => Err(e.payload().to_bytes().into_owned()),
        });
    }
    out
}

/// Polls `check` until it holds, for up to 15 s: a DO output waits for the board's next SAT
/// (Tp = 5 s), a program for the CNC to read it.
async fn eventually(what: &str, mut check: impl FnMut() -> bool) {
    for _ in 0..750 {
        if check() {
            return;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    panic!("never happened: {what}");
}

fn small_program(n: u32) -> Vec<u8> {
    format!("%\nO{n:04}\nG00X0Y0\nM30\n%").into_bytes()
}

/// A program the simulated CNC takes a while to read (2000 bytes/s).
fn long_program() -> Vec<u8> {
    common::nc_program(40_000, 7)
}

/// What a client without the permissions tries: submit a job, output DO (put and get),
/// store programs (put and confirmed get), remove one, cancel a job. Returns how many replies
/// its gets received: the submit, the DO output, the library write.
async fn try_every_write(s: &Session, k: &CellKeys, job: &str, program: &str) -> [usize; 3] {
    let mut replies = [0; 3];
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(small_program(9))),
        request_id: "intruder-1".to_string(),
        ..Default::default()
    };
    let job_key = k.leaf(MACHINE, MachineLeaf::Submit);
    replies[0] = get(
        s,
        &job_key,
        Some(request.encode_to_vec()),
        Duration::from_secs(30),
    )
    .await
    .len();
    let do_key = k.leaf(MACHINE, MachineLeaf::Do);
    let cmd = pb::DoCommand {
        value: 0x5A,
        mask: None,
    };
    s.put(do_key.as_str(), cmd.encode_to_vec()).await.unwrap();
    replies[1] = get(
        s,
        &do_key,
        Some(cmd.encode_to_vec()),
        Duration::from_secs(30),
    )
    .await
    .len();
    s.put(k.program_write("PUT-BY-INTRUDER"), small_program(1))
        .await
        .unwrap();
    let write = pb::ProgramWrite {
        op: Some(pb::program_write::Op::Store(small_program(2))),
        comment: String::new(),
    };
    replies[2] = get(
        s,
        &k.program_write("GET-BY-INTRUDER"),
        Some(write.encode_to_vec()),
        Duration::from_secs(15),
    )
    .await
    .len();
    s.delete(k.program_write(program)).await.unwrap();
    s.delete(k.job_events(MACHINE, job)).await.unwrap();
    replies
}

/// Starts the MES's long job and a program in the library, for the intruder to go after.
async fn mes_job_and_program(gw: &Gateway, pki: &Pki) -> String {
    let mes = gw.client(pki.client("mes")).await;
    mes.program_put("KEEP", &small_program(3)).await.unwrap();
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(long_program())),
        request_id: "mes-long".to_string(),
        ..Default::default()
    };
    let (accepted, follower) = mes.submit(MACHINE, &request).await.unwrap();
    follower.close().await;
    mes.close().await;
    accepted.job_id
}

fn is_cancelled(e: &pb::JobEvent) -> bool {
    matches!(e.kind, Some(pb::job_event::Kind::Cancelled(_)))
}

// ---- the tests ----------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dashboard_reads_status_but_its_writes_reach_nothing() {
    let pki = Pki::new();
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let listen = format!("\"tls/127.0.0.1:{port}\"");
    let gw = start_gateway(config(&cell_file(
        &pki,
        dir.path(),
        &listen,
        "",
        "peer",
        ROLES,
    )))
    .await;
    let job = mes_job_and_program(&gw, &pki).await;
    let k = gw.keys.clone();

    for mode in ["client", "peer"] {
        let dash = open(&pki, &gw.endpoint, mode, Some("dash")).await.unwrap();
        // Status: one machine, with the MES's job on it.
        let status = get(
            &dash,
            &k.any_leaf(MachineLeaf::Status),
            None,
            Duration::from_secs(5),
        )
        .await;
        assert_eq!(status.len(), 1, "{mode}: {status:?}");
        let status = pb::MachineStatus::decode(status[0].as_ref().unwrap().as_slice()).unwrap();
        assert_eq!(status.machine, MACHINE);
        // Job events are read too.
        assert_eq!(
            get(
                &dash,
                &k.job_events(MACHINE, &job),
                None,
                Duration::from_secs(5)
            )
            .await
            .len(),
            1
        );
        // Every write is refused at once: no reply, and nothing waits for the time-out.
        let began = std::time::Instant::now();
        let replies = try_every_write(&dash, &k, &job, "KEEP").await;
        assert_eq!(
            replies, [0; 3],
            "{mode}: the dashboard's writes got answers"
        );
        assert!(
            began.elapsed() < Duration::from_secs(5),
            "{mode}: {:?}",
            began.elapsed()
        );
        // Nor is the admin document shown.
        assert!(
            get(&dash, &k.admin(), None, Duration::from_secs(5))
                .await
                .is_empty()
        );
        dash.close().await.unwrap();
    }

    // Whatever a put might still do would be done by now (DO goes out at the next SAT).
    tokio::time::sleep(Duration::from_secs(6)).await;
    assert_eq!(gw.board().do_image(), 0, "the board's DO changed");
    let jobs = gw.jobs().await;
    assert_eq!(jobs.len(), 1, "{jobs:?}");
    assert_eq!(jobs[0].job_id, job);
    assert!(!is_cancelled(&jobs[0]), "{jobs:?}");
    assert_eq!(gw.programs(), ["KEEP.nc"]);

    // The operator may: cancel the job, output DO.
    let op = gw.client(pki.client("op")).await;
    let last = op.cancel(MACHINE, &job).await.unwrap();
    assert!(is_cancelled(&last), "{last:?}");
    let status = op.set_do(MACHINE, 0x5A, None).await.unwrap();
    assert_eq!(status.do_image, Some(0x5A));
    eventually("the board outputs the operator's DO", || {
        gw.board().do_image() == 0x5A
    })
    .await;
    // A DO put, unconfirmed, goes out too.
    op.put_do(MACHINE, 0x33, None).await.unwrap();
    eventually("the board outputs the operator's put", || {
        gw.board().do_image() == 0x33
    })
    .await;
    // But not submit: the request is not taken.
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(small_program(4))),
        ..Default::default()
    };
    let Err(e) = op.submit(MACHINE, &request).await else {
        panic!("the operator submitted a job");
    };
    assert!(matches!(e, ClientError::NotTaken { .. }), "{e}");
    assert!(e.to_string().contains("lacks the permission"), "{e}");
    op.close().await;
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_roles_the_same_requests_take_effect() {
    // The same cell, TLS and certificates, but no roles: what the dashboard sends above now
    // does what it says, and the checks above see it.
    let pki = Pki::new();
    let dir = tempfile::tempdir().unwrap();
    let listen = format!("\"tls/127.0.0.1:{}\"", free_port());
    let gw = start_gateway(config(&cell_file(
        &pki,
        dir.path(),
        &listen,
        "",
        "peer",
        "",
    )))
    .await;
    let job = mes_job_and_program(&gw, &pki).await;
    let dash = open(&pki, &gw.endpoint, "client", Some("dash"))
        .await
        .unwrap();
    let replies = try_every_write(&dash, &gw.keys, &job, "KEEP").await;
    assert_eq!(
        replies, [1; 3],
        "submit, DO and library write each answered"
    );
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert_eq!(gw.board().do_image(), 0x5A);
    let jobs = gw.jobs().await;
    assert_eq!(jobs.len(), 2, "{jobs:?}");
    assert!(
        jobs.iter().any(|j| j.job_id == job && is_cancelled(j)),
        "{jobs:?}"
    );
    assert_eq!(gw.programs(), ["GET-BY-INTRUDER.nc", "PUT-BY-INTRUDER.nc"]);
    dash.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_mes_client_submits_and_the_job_completes() {
    let pki = Pki::new();
    let dir = tempfile::tempdir().unwrap();
    let listen = format!("\"tls/127.0.0.1:{}\"", free_port());
    let gw = start_gateway(config(&cell_file(
        &pki,
        dir.path(),
        &listen,
        "",
        "peer",
        ROLES,
    )))
    .await;
    // The MES may not read @admin: the cell is found by its gateway's liveliness token.
    let mes = gw.client(pki.client("mes")).await;
    assert_eq!(mes.cell(), CELL);
    assert!(mes.admin().is_null());
    let program = common::nc_program(2_000, 12);
    mes.program_put("O0012", &program).await.unwrap();
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Library("O0012".to_string())),
        request_id: "mes-1".to_string(),
        ..Default::default()
    };
    let (accepted, mut follower) = mes.submit(MACHINE, &request).await.unwrap();
    let end = tokio::time::timeout(Duration::from_secs(60), follower.wait_end())
        .await
        .expect("the job ends")
        .unwrap();
    follower.close().await;
    assert!(
        matches!(end.kind, Some(pb::job_event::Kind::Completed(_))),
        "{end:?}"
    );
    eventually("the CNC has read the program", || {
        gw.board().programs().len() == 1
    })
    .await;
    let received = gw.board().programs();
    assert_eq!(
        received[0].len,
        program.len() as u64,
        "job {}",
        accepted.job_id
    );
    // Reading status is not among the MES's permissions.
    let e = mes.status(Some(MACHINE)).await.unwrap_err();
    assert!(matches!(e, ClientError::NotTaken { .. }), "{e}");
    mes.close().await;
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_without_a_certificate_cannot_connect_at_all() {
    let pki = Pki::new();
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let listen = format!("\"tls/127.0.0.1:{port}\"");
    let gw = start_gateway(config(&cell_file(
        &pki,
        dir.path(),
        &listen,
        "",
        "peer",
        ROLES,
    )))
    .await;
    // TLS, the right CA, no certificate.
    assert!(open(&pki, &gw.endpoint, "client", None).await.is_err());
    // A certificate with a role's common name from another CA.
    assert!(
        open(&pki, &gw.endpoint, "client", Some("forged-dash"))
            .await
            .is_err()
    );
    // Plain TCP to the TLS port.
    let tcp = format!("tcp/127.0.0.1:{port}");
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"client\"").unwrap();
    c.insert_json5("connect/endpoints", &format!("[{tcp:?}]"))
        .unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    assert!(zenoh::open(c).await.is_err());
    // The same through the client library: it says what to check.
    let e = Client::connect(&gw.options(ClientSecurity {
        ca: Some(pki.ca()),
        ..ClientSecurity::default()
    }))
    .await
    .unwrap_err();
    assert!(
        matches!(e, ClientError::Unreachable { secured: true, .. }),
        "{e}"
    );
    assert!(e.to_string().contains("--tls-cert"), "{e}");
    // A certificate of the CA in no role connects, and is shown nothing.
    let nobody = open(&pki, &gw.endpoint, "client", Some("nobody"))
        .await
        .unwrap();
    let status = get(
        &nobody,
        &gw.keys.any_leaf(MachineLeaf::Status),
        None,
        Duration::from_secs(5),
    )
    .await;
    assert!(status.is_empty(), "{status:?}");
    nobody.close().await.unwrap();
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn admin_is_shown_to_admin_read_only_and_hands_out_no_key_material() {
    let pki = Pki::new();
    let dir = tempfile::tempdir().unwrap();
    let listen = format!("\"tls/127.0.0.1:{}\"", free_port());
    let gw = start_gateway(config(&cell_file(
        &pki,
        dir.path(),
        &listen,
        "",
        "peer",
        ROLES,
    )))
    .await;
    let adm = gw.client(pki.client("adm")).await;
    let doc = adm.admin().to_string();
    assert!(
        doc.contains(&pki.key("gateway").display().to_string()),
        "{doc}"
    );
    assert!(doc.contains("\"admin.read\""), "{doc}");
    let gateway_key = std::fs::read_to_string(pki.key("gateway")).unwrap();
    let key_body = gateway_key.lines().nth(1).unwrap();
    assert!(
        !doc.contains(key_body),
        "the private key is in the admin document"
    );
    assert!(
        !doc.contains("PRIVATE KEY") && !doc.contains("BEGIN"),
        "{doc}"
    );
    adm.close().await;
    let dash = gw.client(pki.client("dash")).await;
    assert!(dash.admin().is_null());
    dash.close().await;
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_router_enforces_the_roles_on_its_clients() {
    // dashboard, MES ─tls─▶ router ◀─tls─ gateway (client mode). The router holds the rules
    // `cellgate acl --router` prints; the gateway gives the router every permission.
    let pki = Pki::new();
    let dir = tempfile::tempdir().unwrap();
    let router_port = free_port();
    let router_ep = format!("tls/127.0.0.1:{router_port}");
    let roles = format!(
        "{ROLES}\n[[security.roles]]\nname = \"router\"\ncert_common_names = [\"router\"]\n\
         permissions = [{}]\n",
        cellgate_core::config::Permission::ALL
            .iter()
            .map(|p| format!("\"{p}\""))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let cell = config(&cell_file(
        &pki,
        dir.path(),
        "",
        &format!("{router_ep:?}"),
        "client",
        &roles,
    ));
    let keys = CellKeys::new(&cell.bus.prefix, &cell.cell).unwrap();
    let acl = cellgate::bus::acl::router_access_control(
        &cell.security,
        &keys,
        &cell.bus.prefix,
        &["cellgate-gw".to_string()],
    );
    let mut rc = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, k: &str, v: String| c.insert_json5(k, &v).unwrap();
    set(&mut rc, "mode", "\"router\"".to_string());
    set(&mut rc, "listen/endpoints", format!("[{router_ep:?}]"));
    set(&mut rc, "scouting/multicast/enabled", "false".to_string());
    let tls = "transport/link/tls";
    set(
        &mut rc,
        &format!("{tls}/root_ca_certificate"),
        format!("{:?}", pki.ca()),
    );
    set(
        &mut rc,
        &format!("{tls}/listen_certificate"),
        format!("{:?}", pki.cert("router")),
    );
    set(
        &mut rc,
        &format!("{tls}/listen_private_key"),
        format!("{:?}", pki.key("router")),
    );
    set(&mut rc, &format!("{tls}/enable_mtls"), "true".to_string());
    set(&mut rc, "access_control", acl.to_string());
    let router = zenoh::open(rc).await.unwrap();

    let mut gw = start_gateway(cell).await;
    gw.endpoint = router_ep.clone();
    let k = gw.keys.clone();
    let job = mes_job_and_program(&gw, &pki).await;
    let dash = open(&pki, &router_ep, "client", Some("dash"))
        .await
        .unwrap();
    let status = get(
        &dash,
        &k.any_leaf(MachineLeaf::Status),
        None,
        Duration::from_secs(5),
    )
    .await;
    assert_eq!(status.len(), 1, "{status:?}");
    assert_eq!(try_every_write(&dash, &k, &job, "KEEP").await, [0; 3]);
    tokio::time::sleep(Duration::from_secs(6)).await;
    assert_eq!(gw.board().do_image(), 0);
    let jobs = gw.jobs().await;
    assert_eq!(jobs.len(), 1, "{jobs:?}");
    assert!(!is_cancelled(&jobs[0]));
    assert_eq!(gw.programs(), ["KEEP.nc"]);
    // The operator, through the router, may.
    let op = gw.client(pki.client("op")).await;
    assert!(is_cancelled(&op.cancel(MACHINE, &job).await.unwrap()));
    op.close().await;
    dash.close().await.unwrap();
    gw.stop().await;
    router.close().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn user_names_identify_clients_too() {
    let pki = Pki::new();
    let dir = tempfile::tempdir().unwrap();
    let users = dir.path().join("users.txt");
    std::fs::write(&users, "mes-user:mes-password\nviewer:viewer-password\n").unwrap();
    let listen = format!("\"tls/127.0.0.1:{}\"", free_port());
    let text = format!(
        r#"
cell = "{CELL}"
[bus]
listen = [{listen}]
[programs]
dir = "{programs}"
[[machines]]
name = "{MACHINE}"
protocol = "a"
transport = {{ kind = "sim", line = {{ baud = 19200 }} }}
[security]
users_file = "{users}"
[security.tls]
ca = "{ca}"
certificate = "{cert}"
private_key = "{key}"
require_client_certificates = false
[[security.roles]]
name = "viewer"
usernames = ["viewer"]
permissions = ["status.read"]
"#,
        programs = dir.path().join("programs").display(),
        users = users.display(),
        ca = pki.ca().display(),
        cert = pki.cert("gateway").display(),
        key = pki.key("gateway").display(),
    );
    let gw = start_gateway(config(&text)).await;
    let as_user = |user: &str, password: &str| ClientSecurity {
        ca: Some(pki.ca()),
        credentials: Some(Credentials {
            user: user.to_string(),
            password: password.to_string(),
        }),
        ..ClientSecurity::default()
    };
    let viewer = gw.client(as_user("viewer", "viewer-password")).await;
    assert_eq!(viewer.status(None).await.unwrap().len(), 1);
    let do_result = viewer.set_do(MACHINE, 1, None).await.unwrap_err();
    assert!(
        matches!(do_result, ClientError::NotTaken { .. }),
        "{do_result}"
    );
    viewer.close().await;
    // A known user in no role connects and is shown nothing, not even the gateway; a wrong
    // password or none does not connect.
    let stranger = Client::connect(&gw.options(as_user("mes-user", "mes-password"))).await;
    let Err(e) = stranger else {
        panic!("a user in no role found the cell")
    };
    assert!(matches!(e, ClientError::NoGateway { .. }), "{e}");
    assert!(e.to_string().contains("roles name"), "{e}");
    let wrong = Client::connect(&gw.options(as_user("viewer", "guess"))).await;
    assert!(
        matches!(wrong, Err(ClientError::Unreachable { .. })),
        "{wrong:?}"
    );
    let none = Client::connect(&gw.options(ClientSecurity {
        ca: Some(pki.ca()),
        ..ClientSecurity::default()
    }))
    .await;
    assert!(
        matches!(none, Err(ClientError::Unreachable { .. })),
        "{none:?}"
    );
    assert_eq!(gw.board().do_image(), 0);
    gw.stop().await;
}

// ---- the binary --------------------------------------------------------------------------------------

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_cli_connects_with_the_certificate_it_is_given() {
    let pki = Pki::new();
    let dir = tempfile::tempdir().unwrap();
    let listen = format!("\"tls/127.0.0.1:{}\"", free_port());
    let gw = start_gateway(config(&cell_file(
        &pki,
        dir.path(),
        &listen,
        "",
        "peer",
        ROLES,
    )))
    .await;
    let with = |who: &str, command: &[&str]| {
        let mut args: Vec<String> = command.iter().map(ToString::to_string).collect();
        args.extend(
            [
                "--connect",
                &gw.endpoint,
                "--tls-ca",
                &pki.ca().display().to_string(),
                "--tls-cert",
                &pki.cert(who).display().to_string(),
                "--tls-key",
                &pki.key(who).display().to_string(),
            ]
            .map(ToString::to_string),
        );
        args
    };
    let (code, out, err) = cellgate(with("dash", &["status"])).await;
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(out.contains(MACHINE), "{out}");
    let (code, _, err) = cellgate(with("dash", &["do", MACHINE, "0x0F"])).await;
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("lacks the permission"), "{err}");
    assert_eq!(gw.board().do_image(), 0);
    let (code, out, err) = cellgate(with("op", &["do", MACHINE, "0x0F"])).await;
    assert_eq!(code, 0, "{out}\n{err}");
    eventually("the board outputs DO", || gw.board().do_image() == 0x0F).await;
    // The simulated board's controls are sim.control's.
    let (code, _, err) = cellgate(with("dash", &["sim", "di", MACHINE, "0x21"])).await;
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("lacks the permission"), "{err}");
    assert_eq!(gw.board().snapshot().di_image, 0);
    let (code, out, err) = cellgate(with("op", &["sim", "di", MACHINE, "0x21"])).await;
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(out.contains("DI 0x21"), "{out}");
    assert_eq!(gw.board().snapshot().di_image, 0x21);
    // No certificate: no connection, and the message says what to give.
    let (code, _, err) = cellgate(vec![
        "status".to_string(),
        "--connect".to_string(),
        gw.endpoint.clone(),
        "--tls-ca".to_string(),
        pki.ca().display().to_string(),
    ])
    .await;
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("--tls-cert"), "{err}");
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn misconfiguration_stops_the_gateway_before_it_starts() {
    let pki = Pki::new();
    let dir = tempfile::tempdir().unwrap();
    let run = |text: String| {
        let path = dir.path().join(format!("cell-{}.toml", free_port()));
        std::fs::write(&path, text).unwrap();
        vec![
            "run".to_string(),
            "--config".to_string(),
            path.display().to_string(),
        ]
    };
    let listen = format!("\"tls/127.0.0.1:{}\"", free_port());
    let good = cell_file(&pki, dir.path(), &listen, "", "peer", ROLES);
    let cases = [
        (
            good.replace("\"io.do\"", "\"io.dance\""),
            "unknown permission \"io.dance\"",
        ),
        (
            good.replace(
                &pki.cert("gateway").display().to_string(),
                "/nonexistent/gw.pem",
            ),
            "security.tls.certificate = /nonexistent/gw.pem: cannot read it",
        ),
        (
            good.replace(
                &pki.key("gateway").display().to_string(),
                &pki.cert("gateway").display().to_string(),
            ),
            "does not hold a PEM private key",
        ),
        (
            good.replace("tls/127.0.0.1", "tcp/127.0.0.1"),
            "[security.tls] is set, but this endpoint is not TLS",
        ),
    ];
    for (text, expected) in cases {
        let (code, _, err) = cellgate(run(text)).await;
        assert_eq!(code, 2, "{err}");
        assert!(err.contains(expected), "expected {expected:?} in:\n{err}");
    }
    // A zenoh file that would open the cell to anyone no rule names.
    let zenoh_file = dir.path().join("zenoh.json5");
    std::fs::write(
        &zenoh_file,
        r#"{ access_control: { enabled: true, default_permission: "allow",
             rules: [], subjects: [], policies: [] } }"#,
    )
    .unwrap();
    let text = good.replace(
        "connect = []",
        &format!(
            "connect = []\nzenoh_config = {:?}",
            zenoh_file.display().to_string()
        ),
    );
    let (code, _, err) = cellgate(run(text.clone())).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("default_permission = \"allow\""), "{err}");
    let path = dir.path().join("allow.toml");
    std::fs::write(&path, &text).unwrap();
    let (code, _, err) =
        cellgate(vec!["check-config".to_string(), path.display().to_string()]).await;
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("default_permission = \"allow\""), "{err}");
    // check-config shows the roles.
    let path = dir.path().join("good.toml");
    std::fs::write(&path, &good).unwrap();
    let (code, out, err) =
        cellgate(vec!["check-config".to_string(), path.display().to_string()]).await;
    assert_eq!(code, 0, "{err}");
    assert!(
        out.contains("operator: certificates op: status.read, io.do, job.cancel, plc.tag"),
        "{out}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_example_script_and_secure_cell_work_together() {
    // README's steps: examples/tls/make-certs.sh, then examples/secure-cell.toml.
    let examples = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples");
    let dir = tempfile::tempdir().unwrap();
    let tls = dir.path().join("tls");
    let made = std::process::Command::new("sh")
        .arg(examples.join("tls/make-certs.sh"))
        .arg(&tls)
        .output();
    match made {
        Ok(out) if out.status.success() => {}
        Ok(out) if String::from_utf8_lossy(&out.stderr).contains("openssl is not installed") => {
            eprintln!("skipped: openssl is not installed");
            return;
        }
        other => panic!("make-certs.sh failed: {other:?}"),
    }
    let port = free_port();
    let text = std::fs::read_to_string(examples.join("secure-cell.toml"))
        .unwrap()
        .replace("tls/127.0.0.1:7447", &format!("tls/127.0.0.1:{port}"))
        .replace("= \"tls/", &format!("= \"{}/", tls.display()))
        .replace(
            "dir = \"programs\"",
            &format!("dir = \"{}/programs\"", dir.path().display()),
        );
    let gw = start_gateway(config(&text)).await;
    let cert = |name: &str| ClientSecurity {
        ca: Some(tls.join("ca.pem")),
        certificate: Some(tls.join(format!("{name}.pem"))),
        private_key: Some(tls.join(format!("{name}-key.pem"))),
        credentials: None,
    };
    let mes = gw.client(cert("mes-1")).await;
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(small_program(5))),
        ..Default::default()
    };
    let (_, mut follower) = mes.submit("mill-1", &request).await.unwrap();
    let end = follower.wait_end().await.unwrap();
    assert!(
        matches!(end.kind, Some(pb::job_event::Kind::Completed(_))),
        "{end:?}"
    );
    follower.close().await;
    mes.close().await;
    let dashboard = gw.client(cert("dashboard-1")).await;
    assert_eq!(dashboard.status(None).await.unwrap().len(), 2);
    let e = dashboard.set_do("mill-1", 1, None).await.unwrap_err();
    assert!(matches!(e, ClientError::NotTaken { .. }), "{e}");
    dashboard.close().await;
    let operator = gw.client(cert("operator-1")).await;
    operator.set_do("mill-1", 1, None).await.unwrap();
    operator.close().await;
    gw.stop().await;
}
