//! The `cellgate` binary as tests run it: one way to start it (no setting leaks in from the
//! environment of whoever runs the tests), its output, and the children it leaves.

use std::ffi::OsStr;
use std::io::Read;
use std::process::{Child, Command, ExitStatus, Output, Stdio};
use std::sync::{Arc, Mutex};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

/// The binary under test.
pub const BIN: &str = env!("CARGO_BIN_EXE_cellgate");

/// Environment variables the binary reads; cleared so that a test sees only what it sets.
const ENV: &[&str] = &[
    "RUST_LOG",
    "CELLGATE_CONFIG",
    "CELLGATE_CONNECT",
    "CELLGATE_CELL",
    "CELLGATE_PREFIX",
    "CELLGATE_TLS_CA",
    "CELLGATE_TLS_CERT",
    "CELLGATE_TLS_KEY",
    "CELLGATE_USER",
    "CELLGATE_PASSWORD",
    "CELLGATE_AS",
    "OTEL_EXPORTER_OTLP_ENDPOINT",
];

/// The listeners of `cellgate run` other than the bus, off: a test that needs one turns it on.
pub const ONLY_THE_BUS: [&str; 6] = ["--console", "off", "--mtconnect", "off", "--opcua", "off"];

/// `cellgate run` on the embedded default cell, its bus on `endpoint` and no other listener
/// ([`ONLY_THE_BUS`]), working in `dir` (its program library goes there).
pub fn run_on(endpoint: &str, dir: &std::path::Path) -> Command {
    let mut c = command(["run", "--listen", endpoint]);
    c.args(ONLY_THE_BUS).current_dir(dir);
    c
}

/// The binary with `args`, its environment cleared of the variables it reads and its stdin
/// closed.
pub fn command<I, S>(args: I) -> Command
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let mut c = Command::new(BIN);
    c.args(args).stdin(Stdio::null());
    for v in ENV {
        c.env_remove(v);
    }
    c
}

/// Runs the binary to its end: (exit code, stdout, stderr).
pub fn run<I, S>(args: I) -> (i32, String, String)
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let out = command(args).output().unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// [`run`] off the async runtime's threads.
pub async fn cellgate<I, S>(args: I) -> (i32, String, String)
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let args: Vec<std::ffi::OsString> = args
        .into_iter()
        .map(|a| a.as_ref().to_os_string())
        .collect();
    tokio::task::spawn_blocking(move || run(args))
        .await
        .unwrap()
}

/// Stdout and stderr of a finished run, one after the other.
pub fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// Kills a child process when the test ends, however it ends.
pub struct Reaper(pub Child);

impl Drop for Reaper {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A child's stderr, collected on a thread so the pipe never fills up, and readable while the
/// child runs.
pub struct Stderr {
    text: Arc<Mutex<Vec<u8>>>,
    thread: JoinHandle<()>,
}

impl Stderr {
    /// What the child wrote so far.
    pub fn so_far(&self) -> String {
        String::from_utf8_lossy(&self.text.lock().unwrap()).into_owned()
    }

    /// Waits until the child wrote `needle` (true) or `limit` passed (false).
    pub fn wait_for(&self, needle: &str, limit: Duration) -> bool {
        let deadline = Instant::now() + limit;
        while Instant::now() < deadline {
            if self.so_far().contains(needle) {
                return true;
            }
            thread::sleep(Duration::from_millis(20));
        }
        false
    }

    /// Everything the child wrote, once its stderr closed.
    pub fn join(self) -> thread::Result<String> {
        let Stderr { text, thread } = self;
        thread.join()?;
        Ok(String::from_utf8_lossy(&text.lock().unwrap()).into_owned())
    }
}

/// Collects a child's stderr on a thread so the pipe never fills up.
pub fn collect_stderr(child: &mut Child) -> Stderr {
    let mut stderr = child.stderr.take().unwrap();
    let text = Arc::new(Mutex::new(Vec::new()));
    let sink = text.clone();
    let thread = thread::spawn(move || {
        let mut buf = [0u8; 4096];
        while let Ok(n) = stderr.read(&mut buf) {
            if n == 0 {
                break;
            }
            sink.lock().unwrap().extend_from_slice(&buf[..n]);
        }
    });
    Stderr { text, thread }
}

/// The child's exit status, if it ends within `limit`.
pub fn wait_with_deadline(child: &mut Child, limit: Duration) -> Option<ExitStatus> {
    let deadline = Instant::now() + limit;
    while Instant::now() < deadline {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(status);
        }
        thread::sleep(Duration::from_millis(20));
    }
    None
}

/// [`command`] without arguments yet.
pub fn bin() -> Command {
    command(std::iter::empty::<&str>())
}
