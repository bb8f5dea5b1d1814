//! The OPC UA server against a simulated cell (the embedded default cell, run in this
//! process), read by asyncua from PyPI, an independent client (`opcua_client.py` beside this
//! file): every CNC under Machines has every mandatory node of OPC 40501's MachineToolType
//! with its type (read from the NodeSet files, not from the server's own code), a job's
//! ActiveProgram goes to its name and Running, then Ended, a CNC alarm is an event from the
//! machine's Notification/Messages, a write is refused, and on a cell with users an anonymous
//! session and a wrong password are refused while the right one is taken. A site server
//! follows two gateways on one router.
//!
//! asyncua is installed by `.ci/run` (pip); where it is missing, each test says it was
//! skipped.

use crate::common;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use cellgate::bus::keys::SimLeaf;
use cellgate_core::config::CellConfig;
use cellgate_core::pb;
use common::bus::free_port;

use super::gateway::{Gateway, Surface};

/// A gateway of the embedded default cell in this process, its OPC UA server on a free port.
async fn start(edit: impl FnOnce(&mut CellConfig, &Path)) -> Gateway {
    Gateway::serving(Surface::Opcua, None, edit).await
}

/// Whether asyncua can be imported; says so when not.
fn asyncua() -> bool {
    let ok = Command::new("python3")
        .args(["-c", "import asyncua"])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !ok {
        eprintln!("SKIPPED: asyncua is not installed (pip install asyncua; .ci/run does)");
    }
    ok
}

fn script() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/console/opcua_client.py")
}

/// Runs `opcua_client.py ARGS` to its end; its standard output.
async fn run(args: &[&str]) -> String {
    let mut command = tokio::process::Command::new("python3");
    command.arg(script()).args(args).stderr(Stdio::inherit());
    let out = tokio::time::timeout(Duration::from_secs(120), command.output())
        .await
        .expect("the client ends")
        .unwrap();
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}

/// `opcua_client.py follow`: its lines as they come.
struct Follower {
    child: Child,
    lines: mpsc::Receiver<String>,
    seen: Vec<String>,
}

impl Follower {
    fn start(url: &str, machine: &str) -> Follower {
        Follower::run(&["follow", url, machine])
    }

    /// `opcua_client.py ARGS`, its lines followed.
    fn run(args: &[&str]) -> Follower {
        let mut child = Command::new("python3")
            .arg(script())
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let out = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(out).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Follower {
            child,
            lines,
            seen: Vec::new(),
        }
    }

    /// Takes the lines that came so far.
    fn drain(&mut self) {
        while let Ok(l) = self.lines.try_recv() {
            self.seen.push(l);
        }
    }

    /// Waits for a line that `done` holds of, among those seen so far too (values that change
    /// together come in one publish, in no set order); at most a minute: a guard against a
    /// hang.
    async fn wait(&mut self, done: impl Fn(&str) -> bool) -> String {
        if let Some(l) = self.seen.iter().find(|l| done(l)) {
            return l.clone();
        }
        for _ in 0..600 {
            while let Ok(l) = self.lines.try_recv() {
                self.seen.push(l.clone());
                if done(&l) {
                    return l;
                }
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        panic!("never seen; lines so far: {:?}", self.seen);
    }
}

impl Drop for Follower {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn machine_tools_have_their_mandatory_nodes_and_follow_a_job_and_an_alarm() {
    if !asyncua() {
        return;
    }
    let gw = start(|_, _| {}).await;
    let nodesets = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/opcua/nodesets");
    // The default cell's three CNCs, 17 mandatory nodes each by the NodeSet. The port takes
    // connections a moment before the machines are built: asked again until all three are
    // there (a missing or mistyped node fails at once).
    let mut checked = String::new();
    for _ in 0..50 {
        checked = run(&["check", &gw.url, nodesets.to_str().unwrap()]).await;
        let building = checked == "no machine tool under Machines"
            || (checked.starts_with("checked") && !checked.contains(" of 3 "));
        if !building {
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert_eq!(checked, "checked 51 nodes of 3 machine tools");

    let mut f = Follower::start(&gw.url, "mill-1");
    f.wait(|l| l == "ready").await;
    f.wait(|l| l == "value State Initializing").await;
    let client = gw.client().await;
    let mut program = b"%\nO4321\n".to_vec();
    for n in 1..=300 {
        program.extend_from_slice(format!("N{n} G01 X{n}.0 Y{n}.5 F200\n").as_bytes());
    }
    program.extend_from_slice(b"M30\n%\n");
    let request = pb::JobRequest {
        program: Some(pb::job_request::Program::Inline(program)),
        ..Default::default()
    };
    let (_, mut follower) = client.submit("mill-1", &request).await.unwrap();
    f.wait(|l| l == "value State Running").await;
    f.wait(|l| l == "value Name O4321").await;
    let end = tokio::time::timeout(Duration::from_secs(120), follower.wait_end())
        .await
        .expect("the job ends")
        .unwrap();
    assert!(
        matches!(end.kind, Some(pb::job_event::Kind::Completed(_))),
        "{end:?}"
    );
    follower.close().await;
    f.wait(|l| l == "value State Ended").await;

    // The operator resets the alarm, not the simulated CNC by itself.
    client
        .sim_control(
            "mill-1",
            SimLeaf::Autostart,
            Some(&pb::SimAutostart { on: false }),
        )
        .await
        .unwrap();
    client
        .sim_control::<pb::SimDi>("mill-1", SimLeaf::Alarm, None)
        .await
        .unwrap();
    // Protocol A's ALM carries no alarm number: cellgate's own code, severity MediumHigh.
    f.wait(|l| l == "event CG-ALM 800 mill-1").await;
    // Once, though the client subscribes to the Server object and the alarm lasts.
    tokio::time::sleep(Duration::from_secs(2)).await;
    f.drain();
    let events: Vec<_> = f.seen.iter().filter(|l| l.starts_with("event ")).collect();
    assert_eq!(events.len(), 1, "{:?}", f.seen);

    assert_eq!(
        run(&["write", &gw.url, "mill-1"]).await,
        "refused BadNotWritable"
    );
    // The PLC beside the machine tools: a tag with units is an analog value in degrees
    // Celsius (UNECE "CEL"), a count has none.
    assert_eq!(
        run(&["units", &gw.url, "plc-1", "spindle-temp"]).await,
        "BaseAnalogType 4408652 °C"
    );
    assert_eq!(
        run(&["units", &gw.url, "plc-1", "parts"]).await,
        "BaseDataVariableType none"
    );
    drop(f);
    client.close().await;
    gw.stop().await;
}

/// A cell with a users file: an operator who reads, and a user with no role.
fn secured(config: &mut CellConfig, dir: &Path) {
    let users = dir.join("users");
    std::fs::write(&users, "olga:tulips\nnobody:nothing\n").unwrap();
    let text = format!(
        r#"
cell = "demo"
[security]
users_file = {users:?}
[[security.roles]]
name = "operator"
usernames = ["olga"]
permissions = ["status.read", "io.do"]
"#
    );
    config.security = CellConfig::from_toml_str(&text, "security")
        .unwrap()
        .security;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cell_with_users_takes_only_a_user_with_the_right_password_and_status_read() {
    if !asyncua() {
        return;
    }
    let gw = start(secured).await;
    // No anonymous token policy is offered: the stack calls the token invalid.
    let anonymous = run(&["login", &gw.url]).await;
    assert!(
        anonymous.starts_with("refused BadIdentityToken"),
        "{anonymous}"
    );
    assert_eq!(
        run(&["login", &gw.url, "olga", "roses"]).await,
        "refused BadIdentityTokenRejected"
    );
    assert_eq!(
        run(&["login", &gw.url, "nobody", "nothing"]).await,
        "refused BadUserAccessDenied"
    );
    assert_eq!(run(&["login", &gw.url, "olga", "tulips"]).await, "ok");

    // SignAndEncrypt with a client certificate the operator has not trusted: refused, and
    // the certificate waits in rejected/ until the operator moves it to trusted/ (no
    // restart); never trusted on first use.
    let certs = tempfile::tempdir().unwrap();
    let dir = certs.path().to_str().unwrap();
    assert_eq!(
        run(&["secure", &gw.url, "olga", "tulips", dir]).await,
        "refused BadCertificateUntrusted"
    );
    let rejected: Vec<_> = std::fs::read_dir(gw.pki().join("rejected"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(rejected.len(), 1, "{rejected:?}");
    let name = rejected[0].file_name().unwrap();
    std::fs::rename(&rejected[0], gw.pki().join("trusted").join(name)).unwrap();
    assert_eq!(run(&["secure", &gw.url, "olga", "tulips", dir]).await, "ok");
    assert_eq!(
        run(&["secure", &gw.url, "olga", "roses", dir]).await,
        "refused BadIdentityTokenRejected"
    );
    // The key the server made is its user's alone.
    use std::os::unix::fs::PermissionsExt as _;
    let mode = std::fs::metadata(gw.pki().join("private/private.pem"))
        .unwrap()
        .permissions()
        .mode();
    assert_eq!(mode & 0o077, 0, "{mode:o}");
    gw.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_site_server_follows_the_cells_of_two_gateways() {
    if !asyncua() {
        return;
    }
    let router_port = free_port();
    let router = cellgate::bus::open(&cellgate::bus::BusConfig {
        mode: cellgate::bus::BusMode::Router,
        listen: vec![format!("tcp/127.0.0.1:{router_port}")],
        ..cellgate::bus::BusConfig::default()
    })
    .await
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let args = cellgate::opcua::SiteArgs {
        connect: common::bus::connect_args(format!("tcp/127.0.0.1:{router_port}"), None),
        listen: format!("127.0.0.1:{port}"),
        config: None,
        pki_dir: Some(dir.path().join("pki")),
    };
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let site = tokio::spawn(async move {
        cellgate::opcua::site(&args, async {
            let _ = stopped.await;
        })
        .await
    });
    let url = format!("opc.tcp://127.0.0.1:{port}/");
    // A client watching the Server object's events before any cell is there: each cell that
    // comes is a model change.
    let mut watcher = None;
    for _ in 0..100 {
        if tokio::net::TcpStream::connect(("127.0.0.1", port))
            .await
            .is_ok()
        {
            watcher = Some(Follower::run(&["events", &url]));
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let mut watcher = watcher.expect("the site server listens");
    watcher.wait(|l| l == "ready").await;
    let mut gateways = Vec::new();
    for cell in ["north", "south"] {
        let gw = start(|c, _| {
            c.cell = cell.to_string();
            c.bus.connect = vec![format!("tcp/127.0.0.1:{router_port}")];
            c.opcua = None;
        })
        .await;
        gateways.push(gw);
    }
    // Both cells' machines and PLCs, named CELL.NAME, once their gateways answered (asked
    // again until then: a guard of a minute, not a time the test asserts).
    let want: Vec<String> = ["north", "south"]
        .iter()
        .flat_map(|c| ["lathe-1", "mill-1", "mill-2", "plc-1"].map(|n| format!("{c}.{n}")))
        .collect();
    let mut names = String::new();
    for _ in 0..60 {
        names = run(&["names", &url]).await;
        if names.lines().collect::<Vec<_>>() == want {
            break;
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    assert_eq!(names.lines().collect::<Vec<_>>(), want, "{names}");
    let mut status = String::new();
    for _ in 0..60 {
        status = run(&["status", &url, "south.mill-1"]).await;
        if status == "Good" {
            break;
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    assert_eq!(status, "Good");
    watcher
        .wait(|l| l == "event BaseModelChangeEventType")
        .await;
    drop(watcher);
    // A gateway gone: its machines stay, their values without communication.
    let south = gateways.pop().unwrap();
    south.stop().await;
    for _ in 0..60 {
        status = run(&["status", &url, "south.mill-1"]).await;
        if status == "BadNoCommunication" {
            break;
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    assert_eq!(status, "BadNoCommunication");
    assert_eq!(run(&["status", &url, "north.mill-1"]).await, "Good");
    let _ = stop.send(());
    site.await.unwrap().unwrap();
    for gw in gateways {
        gw.stop().await;
    }
    router.close().await.unwrap();
}
