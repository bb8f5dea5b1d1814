//! The soak's cell: simulated boards and PLC modules in processes of their own, a line proxy in
//! front of each board, a zenoh router between the clients and the gateway, and the gateway
//! itself, each a child process the schedule may kill and start again.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use serde_json::Value;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::process::{Child, ChildStdin, Command};
use tokio_util::sync::CancellationToken;

use super::SoakError;
use super::proxy::LineProxy;

/// The four remote-buffer protocols, one board process each.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Family {
    A,
    ExpA,
    B,
    ExpB,
}

impl Family {
    pub(crate) const ALL: [Family; 4] = [Family::A, Family::ExpA, Family::B, Family::ExpB];

    fn sim(self) -> &'static str {
        match self {
            Family::A => "a",
            Family::ExpA => "exp-a",
            Family::B => "b",
            Family::ExpB => "exp-b",
        }
    }

    fn cell(self) -> &'static str {
        match self {
            Family::A => "protocol = \"a\"\n",
            Family::ExpA => "protocol = \"expansion-a\"\npacket_n = 4\n",
            Family::B => "protocol = \"b\"\n",
            Family::ExpB => "protocol = \"expansion-b\"\n",
        }
    }

    /// The line's rate: Protocol B runs at 19200 baud at most (§2.2, §6.3).
    pub(crate) fn baud(self) -> u32 {
        match self {
            Family::B => 19_200,
            _ => 38_400,
        }
    }

    /// Whether the line's messages carry a checksum (§4.3, §5.3): a corrupted or dropped byte
    /// on a Protocol B line reaches the CNC unseen, as on a real tape reader, so the soak
    /// injects those faults on the A family only.
    pub(crate) fn checked(self) -> bool {
        matches!(self, Family::A | Family::ExpA)
    }
}

/// A CNC of the soak's cell.
#[derive(Debug, Clone)]
pub(crate) struct MachineSpec {
    pub(crate) name: String,
    pub(crate) family: Family,
    /// Its board: the board process (by family) and its index there.
    pub(crate) board: usize,
}

/// What the boards say they received: every program, by SHA-256, and the alarms raised.
#[derive(Debug, Default)]
pub(crate) struct BoardRecord {
    /// SHA-256 (hex) → how many times a CNC read it whole.
    pub(crate) programs: HashMap<String, u32>,
    pub(crate) alarms: u64,
    pub(crate) commands_applied: u64,
}

/// One `cellgate sim fanuc --boards N` process, started again on the same ports.
struct BoardGroup {
    family: Family,
    first_port: u16,
    count: usize,
    child: Option<Child>,
    stdin: Option<ChildStdin>,
}

/// The whole cell.
pub(crate) struct Rig {
    exe: PathBuf,
    pub(crate) dir: PathBuf,
    /// Where the gateway keeps its library, journal and history (a small tmpfs when one can
    /// be mounted, for the full-disk fault).
    pub(crate) data: PathBuf,
    pub(crate) tmpfs: bool,
    pub(crate) machines: Vec<MachineSpec>,
    spare_port: u16,
    groups: Vec<BoardGroup>,
    pub(crate) proxies: Vec<LineProxy>,
    pub(crate) record: Arc<Mutex<BoardRecord>>,
    plcs: Vec<(u8, u16, Option<Child>)>,
    spare_board: Option<Child>,
    gateway: Option<Child>,
    /// The gateway's process id while it runs, 0 while it does not.
    pid: Arc<AtomicU32>,
    router: Option<Child>,
    pub(crate) bus_port: u16,
    pub(crate) router_port: u16,
    pub(crate) console_port: u16,
    pub(crate) mtconnect_port: u16,
    stop: CancellationToken,
    pub(crate) spare_present: bool,
    /// The gateway's log filter.
    pub(crate) log_filter: String,
    pub(crate) spare_tp: u16,
}

/// Boards per family for `machines` CNCs.
fn per_family(machines: usize) -> usize {
    machines.div_ceil(Family::ALL.len()).max(1)
}

/// `n` consecutive free loopback ports.
fn free_ports(n: usize) -> Result<u16, SoakError> {
    for _ in 0..200 {
        let first = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map_err(SoakError::Io)?
            .port();
        if usize::from(first) + n >= 65_000 {
            continue;
        }
        let all = (0..n).all(|i| {
            u16::try_from(i)
                .ok()
                .and_then(|i| first.checked_add(i))
                .is_some_and(|p| std::net::TcpListener::bind(("127.0.0.1", p)).is_ok())
        });
        if all {
            return Ok(first);
        }
    }
    Err(SoakError::Setup(
        "no run of free loopback ports".to_string(),
    ))
}

fn free_port() -> Result<u16, SoakError> {
    free_ports(1)
}

impl Rig {
    /// Lays out the cell in `dir` for `machines` CNCs; starts nothing yet.
    pub(crate) async fn new(
        exe: PathBuf,
        dir: PathBuf,
        machines: usize,
        stop: CancellationToken,
    ) -> Result<Rig, SoakError> {
        let data = dir.join("data");
        std::fs::create_dir_all(&data).map_err(SoakError::Io)?;
        let tmpfs = mount_tmpfs(&data);
        let per = per_family(machines);
        let mut groups = Vec::new();
        let mut specs = Vec::new();
        let mut proxies = Vec::new();
        for (g, family) in Family::ALL.into_iter().enumerate() {
            let first_port = free_ports(per)?;
            for b in 0..per {
                if specs.len() == machines {
                    break;
                }
                let port = first_port
                    + u16::try_from(b).map_err(|_| SoakError::Setup("too many boards".into()))?;
                proxies.push(
                    LineProxy::start(port, stop.clone())
                        .await
                        .map_err(SoakError::Io)?,
                );
                specs.push(MachineSpec {
                    name: format!("{}-{}", family.sim(), b + 1),
                    family,
                    board: g * per + b,
                });
            }
            groups.push(BoardGroup {
                family,
                first_port,
                count: per,
                child: None,
                stdin: None,
            });
        }
        // The spare machine the reloads add, change and remove: a Protocol A board of its own.
        let spare_port = free_port()?;
        let plcs = vec![(1, free_port()?, None), (4, free_port()?, None)];
        Ok(Rig {
            exe,
            dir,
            data,
            tmpfs,
            machines: specs,
            spare_port,
            groups,
            proxies,
            record: Arc::default(),
            plcs,
            spare_board: None,
            gateway: None,
            pid: Arc::default(),
            router: None,
            bus_port: free_port()?,
            router_port: free_port()?,
            console_port: free_port()?,
            mtconnect_port: free_port()?,
            stop,
            spare_present: true,
            log_filter: "warn".to_string(),
            spare_tp: 5,
        })
    }

    /// The cell file as the schedule has it now.
    pub(crate) fn cell_file(&self) -> String {
        let mut text = format!(
            "cell = \"soak\"\n[bus]\nmode = \"peer\"\nlisten = [\"tcp/127.0.0.1:{}\"]\n\
             connect = [\"tcp/127.0.0.1:{}\"]\n\
             [telemetry]\nlog_filter = {:?}\n\
             [programs]\ndir = {:?}\n\
             [console]\nlisten = \"127.0.0.1:{}\"\n\
             [mtconnect]\nlisten = \"127.0.0.1:{}\"\n",
            self.bus_port,
            self.router_port,
            self.log_filter,
            self.data.join("programs"),
            self.console_port,
            self.mtconnect_port,
        );
        for (m, proxy) in self.machines.iter().zip(&self.proxies) {
            text.push_str(&format!(
                "[[machines]]\nname = \"{}\"\n{}\
                 transport = {{ kind = \"tcp\", address = \"127.0.0.1:{}\", line = {{ baud = {} }} }}\n",
                m.name,
                m.family.cell(),
                proxy.port,
                m.family.baud()
            ));
        }
        if self.spare_present {
            text.push_str(&format!(
                "[[machines]]\nname = \"spare\"\nprotocol = \"a\"\ntp = {}\n\
                 transport = {{ kind = \"tcp\", address = \"127.0.0.1:{}\", line = {{ baud = 38400 }} }}\n",
                self.spare_tp, self.spare_port
            ));
        }
        for (mode, port, _) in &self.plcs {
            text.push_str(&format!(
                "[[plcs]]\nname = \"plc-{mode}\"\nmode = {mode}\ntimeout_ms = 1000\n\
                 transport = {{ kind = \"tcp\", address = \"127.0.0.1:{port}\", line = {{ baud = 19200 }} }}\n"
            ));
            if *mode == 1 {
                text.push_str(
                    "[[plcs.tags]]\nname = \"count\"\nmodule = \"D\"\naddress = 20\n\
                     type = \"u16\"\npoll_ms = 500\nwritable = true\nhistory = true\n",
                );
            }
        }
        text
    }

    pub(crate) fn cell_path(&self) -> PathBuf {
        self.dir.join("cell.toml")
    }

    /// Writes the cell file (whole, then renamed: the gateway never reads half of it).
    pub(crate) fn write_cell_file(&self) -> Result<(), SoakError> {
        let tmp = self.dir.join(".cell.toml.new");
        std::fs::write(&tmp, self.cell_file()).map_err(SoakError::Io)?;
        std::fs::rename(&tmp, self.cell_path()).map_err(SoakError::Io)
    }

    /// Starts every process: boards, PLC modules, the spare's board, the router, the gateway.
    pub(crate) async fn start_all(&mut self) -> Result<(), SoakError> {
        for g in 0..self.groups.len() {
            self.start_group(g)?;
        }
        for i in 0..self.plcs.len() {
            self.start_plc(i)?;
        }
        self.start_spare()?;
        self.start_router()?;
        self.write_cell_file()?;
        self.start_gateway()?;
        Ok(())
    }

    fn command(&self, args: &[&str]) -> Command {
        let mut c = Command::new(&self.exe);
        c.args(args)
            .current_dir(&self.dir)
            .env("RUST_LOG", "warn")
            .env_remove("CELLGATE_CONFIG")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .kill_on_drop(true);
        c
    }

    /// A log file the child's stderr goes to, appended across its restarts.
    fn log(&self, name: &str) -> Result<Stdio, SoakError> {
        let f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(self.dir.join(name))
            .map_err(SoakError::Io)?;
        Ok(Stdio::from(f))
    }

    /// `cellgate sim fanuc` as every board of the soak runs: its CNC reads at once, and its
    /// operator presses cycle start a second after a reset (§8.2).
    fn board_command(&self) -> Command {
        self.command(&[
            "sim",
            "fanuc",
            "--autostart",
            "--consume-rate",
            "0",
            "--first-request-delay-ms",
            "1000",
        ])
    }

    fn start_group(&mut self, g: usize) -> Result<(), SoakError> {
        let group = &self.groups[g];
        let (family, first, count) = (group.family, group.first_port, group.count);
        let mut c = self.board_command();
        c.arg("--commands-stdin");
        c.args(["--protocol", family.sim()])
            .args(["--baud", &family.baud().to_string()])
            .args(["--boards", &count.to_string()])
            .args(["--listen", &format!("127.0.0.1:{first}")])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(self.log("boards.log")?);
        if family == Family::ExpA {
            c.args(["--g05-axes", "3"]);
        }
        let mut child = c.spawn().map_err(|e| SoakError::Spawn("sim fanuc", e))?;
        let first_board = g * count;
        if let Some(out) = child.stdout.take() {
            let record = Arc::clone(&self.record);
            // Every event, as the board said it, for a look after a failed run.
            let mut journal = std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(self.dir.join(format!("boards-{}.jsonl", family.sim())))
                .ok();
            tokio::spawn(async move {
                let mut lines = BufReader::new(out).lines();
                while let Ok(Some(line)) = lines.next_line().await {
                    if let Some(j) = journal.as_mut() {
                        use std::io::Write as _;
                        let _ = writeln!(j, "{line}");
                    }
                    let Ok(e) = serde_json::from_str::<Value>(&line) else {
                        continue;
                    };
                    note_board_event(&record, first_board, &e);
                }
            });
        }
        let group = &mut self.groups[g];
        group.stdin = child.stdin.take();
        group.child = Some(child);
        Ok(())
    }

    fn start_spare(&mut self) -> Result<(), SoakError> {
        let listen = format!("127.0.0.1:{}", self.spare_port);
        let mut c = self.board_command();
        c.args(["--baud", "38400", "--listen", &listen]);
        c.stderr(self.log("boards.log")?);
        self.spare_board = Some(c.spawn().map_err(|e| SoakError::Spawn("sim fanuc", e))?);
        Ok(())
    }

    fn start_plc(&mut self, i: usize) -> Result<(), SoakError> {
        let (mode, port, _) = self.plcs[i];
        let listen = format!("127.0.0.1:{port}");
        let mode_arg = mode.to_string();
        let mut c = self.command(&["sim", "fuji", "--listen", &listen, "--mode", &mode_arg]);
        c.stderr(self.log("plcs.log")?);
        let child = c.spawn().map_err(|e| SoakError::Spawn("sim fuji", e))?;
        self.plcs[i].2 = Some(child);
        Ok(())
    }

    pub(crate) fn start_router(&mut self) -> Result<(), SoakError> {
        let listen = format!("tcp/127.0.0.1:{}", self.router_port);
        let mut c = self.command(&["router", "--listen", &listen]);
        c.stderr(self.log("router.log")?);
        self.router = Some(c.spawn().map_err(|e| SoakError::Spawn("router", e))?);
        Ok(())
    }

    pub(crate) async fn stop_router(&mut self) {
        if let Some(mut r) = self.router.take() {
            let _ = r.kill().await;
        }
    }

    pub(crate) fn start_gateway(&mut self) -> Result<(), SoakError> {
        let config = self.cell_path();
        let config = config.to_string_lossy();
        let mut c = self.command(&["run", "--config", &config]);
        // Its cell file's log filter (`--gateway-log`) rules.
        c.env_remove("RUST_LOG").stderr(self.log("gateway.log")?);
        let child = c.spawn().map_err(|e| SoakError::Spawn("gateway", e))?;
        self.pid.store(child.id().unwrap_or(0), Ordering::SeqCst);
        self.gateway = Some(child);
        Ok(())
    }

    /// `kill -9` of the gateway.
    pub(crate) async fn kill_gateway(&mut self) {
        self.pid.store(0, Ordering::SeqCst);
        if let Some(mut g) = self.gateway.take() {
            let _ = g.start_kill();
            let _ = g.wait().await;
        }
    }

    /// Where the gateway's process id is kept (0 while it does not run).
    pub(crate) fn pid(&self) -> Arc<AtomicU32> {
        Arc::clone(&self.pid)
    }

    /// Kills the board process of `family` (every board of it loses power) and starts it
    /// again after `down`.
    pub(crate) async fn restart_boards(
        &mut self,
        family: Family,
        down: Duration,
    ) -> Result<(), SoakError> {
        let Some(g) = self.groups.iter().position(|g| g.family == family) else {
            return Ok(());
        };
        if let Some(mut c) = self.groups[g].child.take() {
            let _ = c.kill().await;
        }
        self.groups[g].stdin = None;
        tokio::time::sleep(down).await;
        self.start_group(g)
    }

    /// An operator command on `machine`'s CNC (`alarm`, `reset`); false if its board process
    /// could not take it.
    pub(crate) async fn operator(&mut self, machine: &MachineSpec, command: &str) -> bool {
        let Some(g) = self.groups.iter().position(|g| g.family == machine.family) else {
            return false;
        };
        let board = machine.board - g * self.groups[g].count;
        let Some(stdin) = self.groups[g].stdin.as_mut() else {
            return false;
        };
        let line = format!("{{\"board\":{board},\"command\":\"{command}\"}}\n");
        stdin.write_all(line.as_bytes()).await.is_ok() && stdin.flush().await.is_ok()
    }

    /// The gateway's stderr so far, for panics.
    pub(crate) fn gateway_log(&self) -> String {
        std::fs::read(self.dir.join("gateway.log"))
            .map(|b| String::from_utf8_lossy(&b).into_owned())
            .unwrap_or_default()
    }

    /// Stops every process and unmounts the tmpfs; `keep`: its content copied out first, to
    /// `data.kept`, for a look at what failed.
    pub(crate) async fn shutdown(&mut self, keep: bool) {
        self.stop.cancel();
        self.pid.store(0, Ordering::SeqCst);
        if let Some(mut g) = self.gateway.take() {
            // SIGTERM first: the gateway's clean stop is part of what is checked.
            if let Some(pid) = g.id() {
                terminate(pid);
            }
            if tokio::time::timeout(Duration::from_secs(20), g.wait())
                .await
                .is_err()
            {
                let _ = g.kill().await;
            }
        }
        self.stop_router().await;
        for g in &mut self.groups {
            if let Some(mut c) = g.child.take() {
                let _ = c.kill().await;
            }
        }
        let others = self.plcs.iter_mut().map(|(_, _, c)| c);
        for c in others.chain(std::iter::once(&mut self.spare_board)) {
            if let Some(mut c) = c.take() {
                let _ = c.kill().await;
            }
        }
        if self.tmpfs {
            if keep {
                let _ = std::process::Command::new("cp")
                    .arg("-a")
                    .arg(&self.data)
                    .arg(self.dir.join("data.kept"))
                    .status();
            }
            unmount(&self.data);
            self.tmpfs = false;
        }
    }
}

fn note_board_event(record: &Mutex<BoardRecord>, _first_board: usize, e: &Value) {
    let mut r = record.lock().unwrap_or_else(PoisonError::into_inner);
    match e["event"].as_str() {
        Some("program") => {
            if let Some(sha) = e["sha256"].as_str() {
                *r.programs.entry(sha.to_string()).or_default() += 1;
            }
        }
        Some("alarm") => r.alarms += 1,
        Some("command") if e["applied"].as_bool() == Some(true) => r.commands_applied += 1,
        _ => {}
    }
}

fn terminate(pid: u32) {
    if let Ok(pid) = i32::try_from(pid) {
        // SAFETY: kill(2) with a child's pid and SIGTERM has no memory effects.
        unsafe {
            libc::kill(pid, libc::SIGTERM);
        }
    }
}

/// A 64 MiB tmpfs on `dir` where this process may mount one (root); false otherwise.
fn mount_tmpfs(dir: &Path) -> bool {
    std::process::Command::new("mount")
        .args([
            "-t",
            "tmpfs",
            "-o",
            "size=64m",
            "soak",
            &dir.to_string_lossy(),
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

fn unmount(dir: &Path) {
    let _ = std::process::Command::new("umount")
        .args(["-l", &dir.to_string_lossy()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status();
}

/// What `/proc` says of a process.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Proc {
    pub(crate) cpu_s: f64,
    pub(crate) rss_kib: u64,
    pub(crate) open_files: u64,
    pub(crate) threads: u64,
}

/// Process `pid`'s CPU time, resident size, open files and threads; None once it is gone.
pub(crate) fn process(pid: u32) -> Option<Proc> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name in parentheses: state is field 3, utime 14, stime 15.
    let rest = stat.rsplit_once(") ").map(|(_, r)| r)?;
    let f: Vec<&str> = rest.split_whitespace().collect();
    if f.first() == Some(&"Z") {
        return None;
    }
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // SAFETY: sysconf has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    let hz = if hz > 0 { hz as f64 } else { 100.0 };
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse::<u64>().ok())
            .unwrap_or(0)
    };
    let open_files = std::fs::read_dir(format!("/proc/{pid}/fd")).map_or(0, |d| d.count() as u64);
    Some(Proc {
        cpu_s: (ticks(11) + ticks(12)) / hz,
        rss_kib: field("VmRSS:"),
        open_files,
        threads: field("Threads:"),
    })
}
