//! The client commands of the `cellgate` binary: their arguments (clap) and what each one
//! does with a connected [`Client`], writing to the given output streams.
//!
//! Exit codes: 0 success; 1 failure at run time (no gateway, no answer, a job that failed or
//! was cancelled); 2 a request the gateway refused (its `ErrorReply` is printed) or bad usage;
//! 130 `submit` interrupted by Ctrl-C (the job keeps running).

use std::future::Future;
use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use clap::Args;

use super::{Client, ClientError, ClientSecurity, ConnectOptions, Credentials, DEFAULT_ENDPOINT};
use cellgate_core::pb;

mod g05;
mod io;
mod jobs;
mod program;
pub mod records;
mod reload;
mod status;
mod submit;
mod watch;

pub use self::g05::*;
pub use self::io::*;
pub use self::jobs::*;
pub use self::program::*;
pub use self::reload::*;
pub use self::status::*;
pub use self::submit::*;
pub use self::watch::*;

/// Exit code of an interrupted `submit`.
pub const EXIT_INTERRUPTED: u8 = 130;

/// Inline programs above this size get a hint to use the library instead.
const INLINE_HINT: u64 = 16 * 1024 * 1024;

/// The name of the user this process runs as, where `$USER` is unset (containers, systemd
/// units): `/etc/passwd`'s name for the owner of `/proc/self`, else `uid N`, so that the
/// records never say "by (cli)" with nobody.
fn system_user() -> Option<String> {
    use std::os::unix::fs::MetadataExt as _;
    let uid = std::fs::metadata("/proc/self").ok()?.uid();
    let by_name = std::fs::read_to_string("/etc/passwd")
        .ok()
        .and_then(|passwd| {
            passwd.lines().find_map(|l| {
                let mut f = l.split(':');
                let name = f.next()?;
                (f.nth(1)?.parse::<u32>().ok()? == uid).then(|| name.to_string())
            })
        });
    Some(by_name.unwrap_or_else(|| format!("uid {uid}")))
}

/// Where the gateway is: options every client command takes.
#[derive(Debug, Clone, Args)]
pub struct ConnectArgs {
    /// Zenoh endpoint of the gateway (or of a router it is connected to). The client connects
    /// there only: client mode, no listen endpoint, multicast scouting off.
    #[arg(short = 'e', long = "connect", value_name = "ENDPOINT", default_value = DEFAULT_ENDPOINT, env = "CELLGATE_CONNECT")]
    pub connect: String,
    /// Key prefix the gateway serves under (its bus.prefix).
    #[arg(
        long,
        value_name = "PREFIX",
        default_value = "cellgate",
        env = "CELLGATE_PREFIX"
    )]
    pub prefix: String,
    /// The cell. Default: the only cell whose gateway answers at the endpoint.
    #[arg(long, value_name = "CELL", env = "CELLGATE_CELL")]
    pub cell: Option<String>,
    /// Seconds to wait for the answer to an ordinary request (status, program library).
    #[arg(long, value_name = "SECS", default_value_t = 10)]
    pub timeout: u64,
    /// The CA that signed the gateway's certificate (PEM), for a tls/ endpoint.
    #[arg(long, value_name = "FILE", env = "CELLGATE_TLS_CA")]
    pub tls_ca: Option<PathBuf>,
    /// This client's certificate (PEM), for a gateway that requires client certificates; its
    /// common name is what the gateway's roles name.
    #[arg(
        long,
        value_name = "FILE",
        env = "CELLGATE_TLS_CERT",
        requires = "tls_key"
    )]
    pub tls_cert: Option<PathBuf>,
    /// The private key of --tls-cert (PEM).
    #[arg(
        long,
        value_name = "FILE",
        env = "CELLGATE_TLS_KEY",
        requires = "tls_cert"
    )]
    pub tls_key: Option<PathBuf>,
    /// User name, for a gateway with a users file. The password comes from --password-file
    /// or the environment variable CELLGATE_PASSWORD.
    #[arg(long, value_name = "NAME", env = "CELLGATE_USER")]
    pub user: Option<String>,
    /// A file whose first line is the password of --user.
    #[arg(long, value_name = "FILE", requires = "user")]
    pub password_file: Option<PathBuf>,
    /// Who you are, for the gateway's audit trail (attached to every request; the gateway
    /// records it as your word). Default: --user, else your login name.
    #[arg(long = "as", value_name = "NAME", env = "CELLGATE_AS")]
    pub as_user: Option<String>,
}

/// Where a client command takes the password of `--user` from when no file is given.
pub const PASSWORD_ENV: &str = "CELLGATE_PASSWORD";

impl ConnectArgs {
    /// The options these arguments give; reads the password file, if any.
    pub fn options(&self) -> Result<ConnectOptions, ClientError> {
        let credentials = match &self.user {
            None => None,
            Some(user) => {
                let password = match &self.password_file {
                    Some(path) => std::fs::read_to_string(path)
                        .map_err(|source| ClientError::File {
                            path: path.clone(),
                            op: "read",
                            source,
                        })?
                        .lines()
                        .next()
                        .unwrap_or_default()
                        .to_string(),
                    None => std::env::var(PASSWORD_ENV).unwrap_or_default(),
                };
                if password.is_empty() {
                    return Err(ClientError::Security {
                        what: format!("--user {user}"),
                        reason: format!("no password: give --password-file or set {PASSWORD_ENV}"),
                    });
                }
                Some(Credentials {
                    user: user.clone(),
                    password,
                })
            }
        };
        let user = self
            .as_user
            .clone()
            .or_else(|| self.user.clone())
            .or_else(|| std::env::var("USER").ok().filter(|u| !u.is_empty()))
            .or_else(|| std::env::var("LOGNAME").ok().filter(|u| !u.is_empty()))
            .or_else(system_user)
            .unwrap_or_default();
        Ok(ConnectOptions {
            origin: Some(pb::RequestOrigin {
                user: user.chars().take(cellgate_core::bounds::MAX_TEXT).collect(),
                via: "cli".to_string(),
            }),
            endpoint: self.connect.clone(),
            prefix: self.prefix.clone(),
            cell: self.cell.clone(),
            timeout: Duration::from_secs(self.timeout.max(1)),
            security: ClientSecurity {
                ca: self.tls_ca.clone(),
                certificate: self.tls_cert.clone(),
                private_key: self.tls_key.clone(),
                credentials,
            },
        })
    }
}

/// Output streams of a command. `progress_bar` draws the live bar of `submit` on the
/// terminal's stderr (off when stderr is not a terminal, and in tests).
pub struct Io<'a> {
    pub out: &'a mut (dyn Write + Send),
    pub err: &'a mut (dyn Write + Send),
    pub progress_bar: bool,
}

/// A client command: where to connect, and what to do once connected.
pub trait ClientCommand {
    fn connect_args(&self) -> &ConnectArgs;
    /// Runs the command; `Ok` carries the exit code.
    fn run(
        &self,
        client: &Client,
        io: &mut Io<'_>,
    ) -> impl Future<Output = Result<u8, ClientError>>;
}

/// Connects, runs `command`, closes, and returns its exit code; errors are written to
/// `io.err`, prefixed `cellgate:`.
pub async fn run_command(command: &impl ClientCommand, io: &mut Io<'_>) -> u8 {
    let options = match command.connect_args().options() {
        Ok(o) => o,
        Err(e) => return report(io, &e),
    };
    let client = match Client::connect(&options).await {
        Ok(c) => c,
        Err(e) => return report(io, &e),
    };
    let result = command.run(&client, io).await;
    client.close().await;
    match result {
        Ok(code) => code,
        Err(e) => report(io, &e),
    }
}

fn report(io: &mut Io<'_>, e: &ClientError) -> u8 {
    let _ = writeln!(io.err, "cellgate: {e}");
    e.exit_code()
}

/// Runs a client command from the binary: a multi-thread runtime (zenoh's requirement), the
/// process's stdout and stderr.
pub fn execute(command: &impl ClientCommand) -> ExitCode {
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .worker_threads(2)
        .thread_name("cellgate-client")
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("cellgate: cannot start the Tokio runtime: {e}");
            return ExitCode::from(1);
        }
    };
    let mut out = std::io::stdout();
    let mut err = std::io::stderr();
    let progress_bar = err.is_terminal();
    let mut io = Io {
        out: &mut out,
        err: &mut err,
        progress_bar,
    };
    let code = runtime.block_on(run_command(command, &mut io));
    let _ = io.out.flush();
    runtime.shutdown_timeout(Duration::from_secs(1));
    ExitCode::from(code)
}
