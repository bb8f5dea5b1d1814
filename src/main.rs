//! The `cellgate` command: runs one cell's gateway, or checks a cell file.
//!
//! Exit codes: 0 success, 1 runtime failure, 2 bad configuration or usage.

use std::future::Future;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use clap::{Args, Parser, Subcommand, ValueEnum};

use cellgate::bus::BusMode;
use cellgate::client::cli as client;
use cellgate::telemetry::{self, LogFormat, TelemetryError};
use cellgate_core::config::{CellConfig, ConfigErrors};

const EXIT_RUNTIME: u8 = 1;
const EXIT_CONFIG: u8 = 2;

/// One gateway per manufacturing cell: FANUC remote-buffer and Fuji MICREX-F links on the
/// Zenoh bus.
#[derive(Debug, Parser)]
#[command(name = "cellgate", version, about, propagate_version = true)]
struct Cli {
    /// More log output: -v debug for cellgate, -vv debug for everything, -vvv trace.
    /// RUST_LOG, when set, takes precedence.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    /// Log line format (overrides telemetry.log_format of the cell file).
    #[arg(long, value_enum, global = true)]
    log_format: Option<LogFormatArg>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the gateway until SIGINT or SIGTERM; SIGHUP reloads its cell file (as `cellgate
    /// reload` does). Without --config, runs the embedded default cell (simulated, no
    /// hardware, no external router).
    Run(RunArgs),
    /// Check a cell file: print its validated summary, or every error (exit code 2).
    CheckConfig {
        /// The cell file (TOML).
        file: PathBuf,
    },
    /// Print the zenoh access-control section the cell file's roles become (json5): the
    /// gateway's own, or with --router the one for a zenoh router between the gateway and
    /// its clients.
    Acl(AclArgs),
    /// Send an NC program to a machine and follow the job to its end (exit 0 only if the
    /// whole program was delivered).
    #[command(after_help = examples::SUBMIT)]
    Submit(client::SubmitArgs),
    /// Show the status of the cell's machines.
    #[command(after_help = examples::STATUS)]
    Status(client::StatusArgs),
    /// Print the cell's events (status, jobs, alarms, DI, links) as they happen.
    #[command(after_help = examples::WATCH)]
    Watch(client::WatchArgs),
    /// Output the DO image of a machine (SDO).
    Do(client::DoArgs),
    /// Read the DI image of a machine now (RDI → SDI).
    Di(client::DiArgs),
    /// The cell's program library: put, get, ls, rm, and revisions: history, diff, release,
    /// lock, adopt.
    #[command(subcommand, after_help = examples::PROGRAM)]
    Program(client::ProgramCommand),
    /// Cancel a job, waiting or running, by its id.
    Cancel(client::CancelArgs),
    /// The cell's history: jobs (with the revision each sent), alarms, link and CNC states,
    /// PLC stations, G05 streams, tag values.
    #[command(after_help = examples::HISTORY)]
    History(cellgate::client::cli::records::HistoryCommand),
    /// The audit trail: every write the gateway took, who asked, and what came of it.
    Audit(cellgate::client::cli::records::AuditCommand),
    /// Time shares per machine and hour or shift: reading, idle, alarm, link down; parts.
    Utilisation(cellgate::client::cli::records::UtilisationArgs),
    /// Serve the web console for every cell behind an endpoint (a site view) until SIGINT or
    /// SIGTERM; a gateway serves its own cell's with `[console]` in its cell file.
    Console(cellgate::console::SiteArgs),
    /// Serve an MTConnect agent for every cell behind an endpoint (a site view) until SIGINT
    /// or SIGTERM; a gateway serves its own cell's with `[mtconnect]` in its cell file.
    Mtconnect(cellgate::mtconnect::SiteArgs),
    /// Serve an OPC UA server (OPC 40501 Machine Tools) for every cell behind an endpoint (a
    /// site view) until SIGINT or SIGTERM; a gateway serves its own cell's with `[opcua]`.
    Opcua(cellgate::opcua::SiteArgs),
    /// Copy every cell's history and audit trail into PostgreSQL (the site's history) until
    /// SIGINT or SIGTERM; with --status, say where each cell stands and exit.
    #[command(after_help = examples::HISTORIAN)]
    Historian(cellgate::historian::HistorianArgs),
    /// The jobs of the cell's machines: the one being sent and the ones waiting (with --all,
    /// the ones that ended too).
    Jobs(client::JobsArgs),
    /// One job: its latest event, or with --follow its events until it ends.
    Job(client::JobArgs),
    /// Stream G05 binary blocks from a CSV file (or standard input) to a machine (§9); exit 0
    /// only if the stream ended cleanly.
    #[command(after_help = examples::G05)]
    G05(client::G05Args),
    /// The cell PLC's memory and transfers: read, write, clear, send, status.
    #[command(subcommand, after_help = examples::PLC)]
    Plc(cellgate::client::plc::PlcCommand),
    /// The cell PLC's named tags: get, set.
    #[command(subcommand)]
    Tag(cellgate::client::plc::TagCommand),
    /// Simulated machines: drive those of a running cell (state, di, alarm, reset, read,
    /// hold, auto, punch), or run a simulated device on its own (fanuc, fuji).
    #[command(subcommand)]
    Sim(SimCommand),
    /// Exit 0 if the gateway at the endpoint answers and every link is up; 1 otherwise,
    /// saying what is down. The probe of containers and service managers.
    Health(client::HealthArgs),
    /// Have the gateway read its cell file again and apply what changed (machines, PLCs,
    /// tags, settings) without a restart; exit 0 once it took the file, 2 with every reason
    /// when it refused it.
    #[command(after_help = examples::RELOAD)]
    Reload(client::ReloadArgs),
    /// Run a zenoh router for the cell's gateways and clients until SIGINT or SIGTERM: the
    /// zenoh runtime in router mode, as zenohd runs it, without its plugins.
    Router(RouterArgs),
}

#[derive(Debug, Args)]
struct RouterArgs {
    /// A zenoh json5 configuration file (TLS, access control, ...); the options below
    /// override its endpoints.
    #[arg(short, long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Endpoint to listen on. Repeatable. Default: the file's, else tcp/127.0.0.1:7447.
    #[arg(short, long = "listen", value_name = "ENDPOINT")]
    listen: Vec<String>,
    /// Endpoint of another router to connect to. Repeatable.
    #[arg(short = 'e', long = "connect", value_name = "ENDPOINT")]
    connect: Vec<String>,
}

#[derive(Debug, Args)]
struct AclArgs {
    /// The cell file (TOML).
    file: PathBuf,
    /// The section for a zenoh router that the gateway and its clients connect to: the
    /// roles, enforced there on the clients, and the gateway's own rights.
    #[arg(long, requires = "gateway_cn")]
    router: bool,
    /// With --router: the common name of the gateway's certificate. Repeatable.
    #[arg(long = "gateway-cn", value_name = "NAME")]
    gateway_cn: Vec<String>,
}

#[derive(Debug, Subcommand)]
enum SimCommand {
    /// A FANUC remote-buffer board with a CNC behind it, served as a TCP serial device
    /// server; prints one JSON object per line for each event.
    Fanuc(cellgate::sim::server::SimFanucArgs),
    /// A Fuji FFU120B general interface module with a MICREX-F behind it, served as a TCP
    /// serial device server; prints one JSON object per line for each event.
    Fuji(cellgate::sim::fuji_server::SimFujiArgs),
    /// A whole simulated cell (32 machines on the four protocols, two PLCs, router, console,
    /// MTConnect) under load and a seeded schedule of faults, its invariants checked against
    /// the boards' own record; exit 0 only when every one held (docs/reliability.md).
    Soak(cellgate::soak::SoakArgs),
    #[command(flatten)]
    Control(cellgate::client::sim::SimControl),
}

#[derive(Debug, Clone, Args)]
struct RunArgs {
    /// The cell file (TOML). Default: the embedded simulated cell.
    #[arg(short, long, value_name = "FILE", env = "CELLGATE_CONFIG")]
    config: Option<PathBuf>,
    /// Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447. Repeatable; replaces
    /// bus.listen of the cell file.
    #[arg(short, long = "listen", value_name = "ENDPOINT")]
    listen: Vec<String>,
    /// Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447. Repeatable; replaces
    /// bus.connect of the cell file.
    #[arg(short = 'e', long = "connect", value_name = "ENDPOINT")]
    connect: Vec<String>,
    /// Disable zenoh multicast scouting (already off unless the cell file turns it on).
    #[arg(long)]
    no_multicast_scouting: bool,
    /// Zenoh session mode (overrides bus.mode).
    #[arg(long, value_enum)]
    mode: Option<ModeArg>,
    /// Key prefix of every key the gateway serves (overrides bus.prefix).
    #[arg(long)]
    prefix: Option<String>,
    /// Where the web console listens, ADDRESS:PORT (overrides console.listen; port 0 takes
    /// a free one), or `off` for no console.
    #[arg(long, value_name = "ADDR|off")]
    console: Option<String>,
    /// Where the MTConnect agent listens, ADDRESS:PORT (overrides mtconnect.listen; port 0
    /// takes a free one), or `off` for no agent.
    #[arg(long, value_name = "ADDR|off")]
    mtconnect: Option<String>,
    /// Where the OPC UA server listens, ADDRESS:PORT (overrides opcua.listen; port 0 takes a
    /// free one), or `off` for no server.
    #[arg(long, value_name = "ADDR|off")]
    opcua: Option<String>,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum LogFormatArg {
    Human,
    Json,
}

impl From<LogFormatArg> for LogFormat {
    fn from(f: LogFormatArg) -> Self {
        match f {
            LogFormatArg::Human => LogFormat::Human,
            LogFormatArg::Json => LogFormat::Json,
        }
    }
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum ModeArg {
    Peer,
    Client,
    Router,
}

/// Words people try for a subcommand, and the subcommand they mean where it exists.
const SYNONYMS: &[(&str, &str)] = &[
    ("list", "ls"),
    ("delete", "rm"),
    ("del", "rm"),
    ("remove", "rm"),
    ("queue", "jobs"),
    ("show", "get"),
];

/// The subcommand a word of `args` that is none means, if [`SYNONYMS`] knows it and it exists
/// where the word stands (`program delete` → `rm`).
fn synonym_of(args: &[String]) -> Option<&'static str> {
    use clap::CommandFactory;
    let mut cmd = Cli::command();
    for arg in args.iter().skip(1) {
        if arg.starts_with('-') {
            continue;
        }
        // A command without subcommands takes no more of them.
        cmd.get_subcommands().next()?;
        let next = cmd.find_subcommand(arg).cloned();
        match next {
            Some(sub) => cmd = sub,
            None => {
                let (_, meant) = SYNONYMS.iter().find(|(word, _)| word == arg)?;
                return cmd.find_subcommand(meant).map(|_| *meant);
            }
        }
    }
    None
}

/// For `-m`/`--machine` on a command that now takes its machine first, without a flag: the
/// form it has (clap alone says only "unexpected argument").
fn machine_flag_tip(args: &[String], invalid: &str) -> Option<String> {
    use clap::CommandFactory;
    if !(invalid.starts_with("-m") || invalid.starts_with("--machine")) {
        return None;
    }
    let mut cmd = Cli::command();
    let mut path = Vec::new();
    for arg in args.iter().skip(1) {
        if arg.starts_with('-') {
            continue;
        }
        match cmd.find_subcommand(arg).cloned() {
            Some(sub) => {
                path.push(arg.as_str());
                cmd = sub;
            }
            None => break,
        }
    }
    let first = cmd.get_positionals().next()?;
    let name = first.get_value_names()?.first()?.to_string();
    (name == "MACHINE").then(|| {
        let path = path.join(" ");
        format!(
            "-m/--machine is gone: name the machine first, as every command does: \
             `cellgate {path} MACHINE ...` (e.g. `cellgate {path} mill-1 ...`)"
        )
    })
}

/// `args` parsed; on an unknown subcommand that is a usual synonym (`list` → `ls`, `delete`
/// → `rm`), the one it means, before any near miss clap finds by spelling (`delete` is
/// nearer `release` than `rm`); on a `-m` the command no longer takes, the form it has.
fn parse_from(args: &[String]) -> Result<Cli, clap::Error> {
    use clap::error::{ContextKind, ContextValue, ErrorKind};
    Cli::try_parse_from(args).map_err(|mut e| {
        if e.kind() == ErrorKind::InvalidSubcommand
            && let Some(meant) = synonym_of(args)
        {
            e.insert(
                ContextKind::SuggestedSubcommand,
                ContextValue::String(meant.to_string()),
            );
        }
        if e.kind() == ErrorKind::UnknownArgument
            && let Some(ContextValue::String(invalid)) = e.get(ContextKind::InvalidArg)
            && let Some(tip) = machine_flag_tip(args, &invalid.clone())
        {
            e.insert(
                ContextKind::Suggested,
                ContextValue::StyledStrs(vec![tip.into()]),
            );
        }
        e
    })
}

/// The command line, parsed (see [`parse_from`]), or its error and exit.
fn parse_cli() -> Cli {
    let args: Vec<String> = std::env::args_os()
        .map(|a| a.to_string_lossy().into_owned())
        .collect();
    parse_from(&args).unwrap_or_else(|e| e.exit())
}

fn main() -> ExitCode {
    let cli = parse_cli();
    match cli.command {
        Command::CheckConfig { ref file } => check_config(file),
        Command::Acl(ref args) => acl(args),
        Command::Run(ref args) => run(&cli, args),
        Command::Submit(ref args) => client_command(&cli, args),
        Command::Status(ref args) => client_command(&cli, args),
        Command::Watch(ref args) => client_command(&cli, args),
        Command::Do(ref args) => client_command(&cli, args),
        Command::Di(ref args) => client_command(&cli, args),
        Command::Program(ref args) => client_command(&cli, args),
        Command::Cancel(ref args) => client_command(&cli, args),
        Command::History(ref args) => client_command(&cli, args),
        Command::Audit(ref args) => client_command(&cli, args),
        Command::Utilisation(ref args) => client_command(&cli, args),
        Command::Console(ref args) => site_console(args),
        Command::Mtconnect(ref args) => site_mtconnect(args),
        Command::Opcua(ref args) => site_opcua(args),
        Command::Historian(ref args) => historian(args),
        Command::Jobs(ref args) => client_command(&cli, args),
        Command::Job(ref args) => client_command(&cli, args),
        Command::G05(ref args) => client_command(&cli, args),
        Command::Plc(ref args) => client_command(&cli, args),
        Command::Tag(ref args) => client_command(&cli, args),
        Command::Sim(SimCommand::Fanuc(ref args)) => sim_fanuc(&cli, args.clone()),
        Command::Sim(SimCommand::Fuji(ref args)) => sim_fuji(&cli, args.clone()),
        Command::Sim(SimCommand::Soak(ref args)) => sim_soak(&cli, args.clone()),
        Command::Sim(SimCommand::Control(ref args)) => client_command(&cli, args),
        Command::Health(ref args) => client_command(&cli, args),
        Command::Reload(ref args) => client_command(&cli, args),
        Command::Router(ref args) => router(&cli, args),
    }
}

/// `cellgate router`: a zenoh router with multicast scouting off, until SIGINT or SIGTERM.
fn router(cli: &Cli, args: &RouterArgs) -> ExitCode {
    let mut config = match &args.config {
        Some(path) => match zenoh::Config::from_file(path) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("cellgate: {}: {e}", path.display());
                return ExitCode::from(EXIT_CONFIG);
            }
        },
        None => zenoh::Config::default(),
    };
    let listen = if args.listen.is_empty() && args.config.is_none() {
        vec!["tcp/127.0.0.1:7447".to_string()]
    } else {
        args.listen.clone()
    };
    let mut settings = vec![
        ("mode", "\"router\"".to_string()),
        ("scouting/multicast/enabled", "false".to_string()),
    ];
    if !listen.is_empty() {
        settings.push(("listen/endpoints", json_list(&listen)));
    }
    if !args.connect.is_empty() {
        settings.push(("connect/endpoints", json_list(&args.connect)));
    }
    for (key, value) in settings {
        if let Err(e) = config.insert_json5(key, &value) {
            eprintln!("cellgate: router setting {key} = {value}: {e}");
            return ExitCode::from(EXIT_CONFIG);
        }
    }
    let name = "cellgate router";
    service(cli, name, |stop| async move {
        let session = zenoh::open(config)
            .await
            .map_err(|e| format!("the zenoh router did not start: {e}"))?;
        tracing::info!(zid = %session.zid(), ?listen, "zenoh router running");
        stop.await;
        let _ = session.close().await;
        tracing::info!("zenoh router stopped");
        Ok(())
    })
}

fn json_list(items: &[String]) -> String {
    serde_json::to_string(items).unwrap_or_else(|_| "[]".to_string())
}

/// `cellgate submit`, `status`, `watch`, `do`, `di`, `program`, `cancel`: a zenoh client
/// of the cell's gateway. Logs (zenoh's included) go to stderr only when asked for with -v
/// or RUST_LOG.
fn client_command(cli: &Cli, command: &impl client::ClientCommand) -> ExitCode {
    let filter = match cli.verbose {
        0 => std::env::var("RUST_LOG").ok(),
        1 => Some("warn,cellgate=debug".to_string()),
        2 => Some("debug".to_string()),
        _ => Some("trace".to_string()),
    };
    if let Some(filter) = filter {
        let _ = tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::new(filter))
            .with_writer(std::io::stderr)
            .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
            .try_init();
    }
    client::execute(command)
}

/// `cellgate sim fanuc ...`: logs go to stderr, events as JSON lines to stdout.
fn sim_fanuc(cli: &Cli, args: cellgate::sim::server::SimFanucArgs) -> ExitCode {
    // A listener and a connection a board: --boards 1024 needs over 2048 descriptors.
    let _ = raise_open_file_limit();
    service(cli, "cellgate sim fanuc", |stop| async move {
        cellgate::sim::server::serve_fanuc(args, stop)
            .await
            .map_err(|e| e.to_string())
    })
}

/// `cellgate sim fuji ...`: logs go to stderr, events as JSON lines to stdout.
fn sim_fuji(cli: &Cli, args: cellgate::sim::fuji_server::SimFujiArgs) -> ExitCode {
    service(cli, "cellgate sim fuji", |stop| async move {
        cellgate::sim::fuji_server::serve_fuji(args, stop)
            .await
            .map_err(|e| e.to_string())
    })
}

/// `cellgate sim soak ...`: the schedule and progress on stderr, the final line on stdout.
fn sim_soak(cli: &Cli, args: cellgate::soak::SoakArgs) -> ExitCode {
    // Every board, proxy and client connection is a descriptor.
    let _ = raise_open_file_limit();
    // Its clients' reconnections through faults are expected: only what goes wrong.
    service_logging(cli, "cellgate sim soak", Some("error"), |stop| async move {
        let token = tokio_util::sync::CancellationToken::new();
        let cancel = token.clone();
        tokio::spawn(async move {
            stop.await;
            cancel.cancel();
        });
        let report = cellgate::soak::run(args, token)
            .await
            .map_err(|e| e.to_string())?;
        for broken in &report.broken {
            eprintln!("soak: broken: {broken}");
        }
        println!("{}", report.line());
        if report.passed {
            Ok(())
        } else {
            Err("an invariant did not hold (above)".to_string())
        }
    })
}

/// The multi-thread runtime zenoh needs, its threads named `thread_name` where given. One that
/// cannot start is said on stderr, and is the exit code.
fn multi_thread(thread_name: Option<&str>) -> Result<tokio::runtime::Runtime, ExitCode> {
    let mut builder = tokio::runtime::Builder::new_multi_thread();
    builder.enable_all();
    if let Some(name) = thread_name {
        builder.thread_name(name);
    }
    builder.build().map_err(|e| {
        eprintln!("cellgate: cannot start the Tokio runtime: {e}");
        ExitCode::from(EXIT_RUNTIME)
    })
}

/// Runs `body` until it ends or SIGINT / SIGTERM, on the multi-thread runtime zenoh needs,
/// with logs on stderr in the chosen format: the frame of `router` and the simulators. An
/// error `body` returns is printed after `name` and exits with code 2.
fn service<F, Fut>(cli: &Cli, name: &str, body: F) -> ExitCode
where
    F: FnOnce(std::pin::Pin<Box<dyn Future<Output = ()> + Send>>) -> Fut,
    Fut: Future<Output = Result<(), String>>,
{
    service_logging(cli, name, None, body)
}

/// [`service`], logging at `filter` (RUST_LOG overrides it) instead of the default.
fn service_logging<F, Fut>(cli: &Cli, name: &str, filter: Option<&str>, body: F) -> ExitCode
where
    F: FnOnce(std::pin::Pin<Box<dyn Future<Output = ()> + Send>>) -> Fut,
    Fut: Future<Output = Result<(), String>>,
{
    let runtime = match multi_thread(None) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    let mut telemetry = cellgate::telemetry::TelemetryConfig::default();
    if let Some(filter) = filter {
        telemetry.log_filter = filter.to_string();
    }
    if let Some(format) = cli.log_format {
        telemetry.log_format = format.into();
    }
    runtime.block_on(async move {
        let mut guard = match telemetry::init(&telemetry) {
            Ok(guard) => guard,
            Err(e) => {
                eprintln!("cellgate: {e}");
                return ExitCode::from(EXIT_CONFIG);
            }
        };
        let code = match shutdown_signal() {
            Ok(stop) => match body(Box::pin(stop)).await {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    eprintln!("{name}: {e}");
                    ExitCode::from(EXIT_CONFIG)
                }
            },
            Err(e) => {
                eprintln!("cellgate: cannot install the SIGINT/SIGTERM handlers: {e}");
                ExitCode::from(EXIT_RUNTIME)
            }
        };
        if let Err(e) = guard.shutdown() {
            eprintln!("cellgate: {e}");
        }
        code
    })
}

/// `cellgate check-config FILE`: the same check a reload makes.
fn check_config(file: &Path) -> ExitCode {
    match cellgate::gateway::check_cell_file(file) {
        Ok(config) => {
            for w in config.warnings() {
                eprintln!("{}: warning: {w}", file.display());
            }
            // A closed pipe (`| head`) is no error worth a panic.
            use std::io::Write as _;
            let _ = writeln!(std::io::stdout().lock(), "{}", config.summary());
            ExitCode::SUCCESS
        }
        Err(errors) => {
            for e in errors {
                eprintln!("{e}");
            }
            ExitCode::from(EXIT_CONFIG)
        }
    }
}

/// `cellgate acl FILE [--router --gateway-cn NAME]`.
fn acl(args: &AclArgs) -> ExitCode {
    // The rules need the roles, not the certificates: they may not exist yet.
    let loaded = cellgate_core::config::file::read_text_bounded(
        &args.file,
        cellgate_core::config::file::MAX_CELL_FILE,
    )
    .map_err(|e| {
        ConfigErrors(vec![cellgate_core::config::ConfigError::Read {
            origin: args.file.display().to_string(),
            reason: e.to_string(),
        }])
    })
    .and_then(|text| {
        CellConfig::from_toml_str_without_files(&text, &args.file.display().to_string())
    });
    let config = match loaded {
        Ok(config) => config,
        Err(errors) => {
            print_errors(&args.file.display().to_string(), &errors);
            return ExitCode::from(EXIT_CONFIG);
        }
    };
    let keys = match cellgate::bus::keys::CellKeys::new(&config.bus.prefix, &config.cell) {
        Ok(keys) => keys,
        Err(e) => {
            eprintln!("{}: {e}", args.file.display());
            return ExitCode::from(EXIT_CONFIG);
        }
    };
    let security = &config.security;
    if !security.enforces_roles() {
        eprintln!(
            "{}: no [[security.roles]]: nothing to enforce",
            args.file.display()
        );
        return ExitCode::from(EXIT_CONFIG);
    }
    let section = if args.router {
        cellgate::bus::acl::router_access_control(
            security,
            &keys,
            &config.bus.prefix,
            &args.gateway_cn,
        )
    } else {
        match cellgate::bus::acl::access_control(security, &keys, &config.bus.prefix) {
            Some(section) => section,
            None => return ExitCode::from(EXIT_CONFIG),
        }
    };
    match serde_json::to_string_pretty(&serde_json::json!({ "access_control": section })) {
        Ok(text) => {
            // A closed pipe (`| head`) is not an error worth a panic.
            use std::io::Write as _;
            let _ = writeln!(std::io::stdout().lock(), "{text}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("cellgate: {e}");
            ExitCode::from(EXIT_RUNTIME)
        }
    }
}

fn load(file: &Path) -> Result<CellConfig, ConfigErrors> {
    let config = CellConfig::load(file)?;
    config.validate()?;
    Ok(config)
}

/// Every error on its own line of stderr, each prefixed with where the configuration
/// came from (unless the message already starts with it).
fn print_errors(origin: &str, errors: &ConfigErrors) {
    for error in &errors.0 {
        let line = error.to_string();
        if line.starts_with(origin) {
            eprintln!("{line}");
        } else {
            eprintln!("{origin}: {line}");
        }
    }
}

/// `cellgate run`.
fn run(cli: &Cli, args: &RunArgs) -> ExitCode {
    let (mut config, origin) = match &args.config {
        Some(file) => match load(file) {
            Ok(config) => (config, file.display().to_string()),
            Err(errors) => {
                print_errors(&file.display().to_string(), &errors);
                return ExitCode::from(EXIT_CONFIG);
            }
        },
        None => (
            CellConfig::embedded_default(),
            "embedded default".to_string(),
        ),
    };
    let (verbose, log_format) = (cli.verbose, cli.log_format);
    let overridden = apply_overrides(&mut config, verbose, log_format, args);
    if overridden {
        if let Err(errors) = config.validate() {
            print_errors(&format!("{origin} (with command-line options)"), &errors);
            return ExitCode::from(EXIT_CONFIG);
        }
    }
    // The zenoh file and the rules the roles become are checked before anything starts: a
    // configuration zenoh refuses is a configuration error, not a run-time failure.
    if let Err(e) = cellgate::bus::session::cell_zenoh_config(&config) {
        eprintln!("{origin}: {e}");
        return ExitCode::from(EXIT_CONFIG);
    }

    // An address another process listens on is one line, before anything is created.
    if let Some(line) = listen::first_in_use(&config) {
        eprintln!("cellgate: {line}");
        return ExitCode::from(EXIT_RUNTIME);
    }

    let open_files = raise_open_file_limit();

    // Zenoh needs the multi-thread runtime.
    let runtime = match multi_thread(Some("cellgate")) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    // A reload reads the file again and writes the same options over it.
    let source = match &args.config {
        Some(file) => {
            let args = args.clone();
            cellgate::gateway::CellSource::file(file).with_adjust(move |c| {
                apply_overrides(c, verbose, log_format, &args);
            })
        }
        None => cellgate::gateway::CellSource::embedded(),
    };
    let code = runtime.block_on(run_async(config, origin, source, open_files));
    // Everything that matters was closed above; do not wait on stray blocking tasks.
    runtime.shutdown_timeout(Duration::from_secs(2));
    code
}

/// Writes the command-line options over the configuration; true if any was given.
fn apply_overrides(
    config: &mut CellConfig,
    verbose: u8,
    log_format: Option<LogFormatArg>,
    args: &RunArgs,
) -> bool {
    let mut any = false;
    if !args.listen.is_empty() {
        config.bus.listen = args.listen.clone();
        any = true;
    }
    if !args.connect.is_empty() {
        config.bus.connect = args.connect.clone();
        any = true;
    }
    if args.no_multicast_scouting {
        config.bus.multicast_scouting = false;
    }
    if let Some(mode) = args.mode {
        config.bus.mode = match mode {
            ModeArg::Peer => BusMode::Peer,
            ModeArg::Client => BusMode::Client,
            ModeArg::Router => BusMode::Router,
        };
        any = true;
    }
    if let Some(prefix) = &args.prefix {
        config.bus.prefix = prefix.clone();
        any = true;
    }
    match args.console.as_deref() {
        None => {}
        Some("off") => config.console = None,
        Some(addr) => {
            config.console.get_or_insert_with(Default::default).listen = addr.to_string();
            any = true;
        }
    }
    match args.mtconnect.as_deref() {
        None => {}
        Some("off") => config.mtconnect = None,
        Some(addr) => {
            config.mtconnect.get_or_insert_with(Default::default).listen = addr.to_string();
            any = true;
        }
    }
    match args.opcua.as_deref() {
        None => {}
        Some("off") => config.opcua = None,
        Some(addr) => {
            config.opcua.get_or_insert_with(Default::default).listen = addr.to_string();
            any = true;
        }
    }
    if let Some(format) = log_format {
        config.telemetry.log_format = format.into();
    }
    match verbose {
        0 => {}
        1 => config.telemetry.log_filter = "info,cellgate=debug".to_string(),
        2 => config.telemetry.log_filter = "debug".to_string(),
        _ => config.telemetry.log_filter = "trace".to_string(),
    }
    any
}

/// Raises the soft limit on open files to the hard one and returns the limit in force. Each
/// link holds a descriptor (a TCP socket or a serial port), the bus and the library a few
/// more; a systemd service starts with a soft limit of 1024, too few for a plant's links.
fn raise_open_file_limit() -> Option<u64> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit and setrlimit only read or write the struct they are given.
    unsafe {
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) != 0 {
            return None;
        }
        if limit.rlim_cur < limit.rlim_max {
            let raised = libc::rlimit {
                rlim_cur: limit.rlim_max,
                rlim_max: limit.rlim_max,
            };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &raised) == 0 {
                return Some(limit.rlim_max);
            }
        }
    }
    Some(limit.rlim_cur)
}

/// How often the memory the gateway freed is given back to the system.
const TRIM_EVERY: std::time::Duration = std::time::Duration::from_secs(2);

/// Gives the memory freed inside the allocator's heaps back to the system, every
/// [`TRIM_EVERY`]. glibc returns only the top of a heap by itself: the buffers a busy link
/// takes for its job (program, fed blocks, file reads) and lets go of afterwards stay
/// resident between the allocations that live on, and a thousand busy links grew the
/// resident size by about 50 KiB each that way (docs/performance.md, "Where a link's memory
/// and CPU go"). A trim takes a few milliseconds on a blocking thread.
async fn give_back_freed_memory() {
    let mut tick = tokio::time::interval(TRIM_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        // SAFETY: malloc_trim only walks the allocator's own free lists.
        #[cfg(target_env = "gnu")]
        let _ = tokio::task::spawn_blocking(|| unsafe { libc::malloc_trim(0) }).await;
    }
}

async fn run_async(
    config: CellConfig,
    origin: String,
    source: cellgate::gateway::CellSource,
    open_files: Option<u64>,
) -> ExitCode {
    let mut guard = match telemetry::init(&config.telemetry) {
        Ok(guard) => guard,
        Err(e) => {
            eprintln!("cellgate: {e}");
            return ExitCode::from(match e {
                TelemetryError::Filter { .. }
                | TelemetryError::Exporter { .. }
                | TelemetryError::PrometheusAddress { .. }
                | TelemetryError::PrometheusBind { .. } => EXIT_CONFIG,
                _ => EXIT_RUNTIME,
            });
        }
    };
    tracing::info!(version = cellgate::gateway::VERSION, config = %origin, "starting cellgate");
    for w in config.warnings() {
        tracing::warn!("{w}");
    }
    // Two descriptors a link leaves room for reconnections; the rest is the bus's and the
    // library's.
    let wanted = 2 * (config.machines.len() + config.plcs.len()) as u64 + 256;
    if let Some(limit) = open_files.filter(|&l| l < wanted) {
        tracing::warn!(
            limit,
            wanted,
            "the limit on open files is low for this cell's links; raise it (LimitNOFILE=, ulimit -n)"
        );
    }

    let trimming = tokio::spawn(give_back_freed_memory());

    // Once it serves, what the cell offers and where, for whoever started it by hand.
    let (serving, served) = tokio::sync::oneshot::channel();
    let overview = serving_text(&config);
    let announce = tokio::spawn(async move {
        if let Ok(ready) = served.await {
            use std::io::Write as _;
            let ready: cellgate::gateway::Ready = ready;
            let console = ready
                .console
                .map(|url| format!("console: {url}\n"))
                .unwrap_or_default();
            let mtconnect = ready
                .mtconnect
                .map(|url| format!("mtconnect: {url}\n"))
                .unwrap_or_default();
            let opcua = ready
                .opcua
                .map(|url| format!("opcua: {url}\n"))
                .unwrap_or_default();
            // A closed stdout (a service manager's) is no reason to stop.
            let _ = write!(
                std::io::stdout().lock(),
                "{overview}{console}{mtconnect}{opcua}"
            );
        }
    });
    let (reload, reloads) = cellgate::gateway::Reloads::new();
    let hangups = match reload_on_hangup(reload) {
        Ok(task) => task,
        Err(e) => {
            tracing::error!("cannot install the SIGHUP handler: {e}");
            return ExitCode::from(EXIT_RUNTIME);
        }
    };
    let options = cellgate::gateway::RunOptions {
        ready: Some(serving),
        source: Some(source),
        reloads: Some(reloads),
    };
    let code = match shutdown_signal() {
        Ok(shutdown) => match cellgate::gateway::run_with(config, shutdown, options).await {
            Ok(()) => ExitCode::SUCCESS,
            Err(cellgate::gateway::GatewayError::Bus(cellgate::bus::BusError::Open {
                listen,
                source,
                ..
            })) if source.to_string().contains("Address already in use") => {
                // Taken since the check before the start.
                eprintln!("cellgate: {}", listen::bus_in_use(&listen.join(", ")));
                ExitCode::from(EXIT_RUNTIME)
            }
            Err(e) => {
                tracing::error!("cellgate failed: {e}");
                ExitCode::from(EXIT_RUNTIME)
            }
        },
        Err(e) => {
            tracing::error!("cannot install the SIGINT/SIGTERM handlers: {e}");
            ExitCode::from(EXIT_RUNTIME)
        }
    };
    hangups.abort();
    announce.abort();
    trimming.abort();
    if let Err(e) = guard.shutdown() {
        eprintln!("cellgate: {e}");
    }
    code
}

/// Machines and PLCs listed when `cellgate run` serves; a larger cell gets a count.
const OVERVIEW_LINES: usize = 32;

/// What `cellgate run` prints once it serves: where clients reach it, what each machine and
/// PLC takes, and the first command to try.
fn serving_text(config: &CellConfig) -> String {
    let listen = config.bus.listen.first().cloned();
    let mut t = format!(
        "cellgate {} serves cell {} on {} (Ctrl-C stops it)\n",
        cellgate::gateway::VERSION,
        config.cell,
        if config.bus.listen.is_empty() {
            "no endpoint of its own".to_string()
        } else {
            config.bus.listen.join(", ")
        }
    );
    t.push_str(&config.overview(OVERVIEW_LINES));
    let connect = match listen.as_deref() {
        Some(ep) if ep == cellgate::client::DEFAULT_ENDPOINT => String::new(),
        Some(ep) => format!(" -e {ep}"),
        None => " -e ENDPOINT".to_string(),
    };
    // A secured cell takes no client without its credentials: the hint says which.
    let mut who = String::new();
    if let Some(tls) = &config.security.tls {
        who.push_str(&format!(" --tls-ca {}", tls.ca.display()));
        if tls.require_client_certificates {
            who.push_str(" --tls-cert CERT --tls-key KEY");
        }
    }
    if config.security.users_file.is_some() {
        who.push_str(" --user NAME");
    }
    t.push_str(&format!(
        "try: cellgate status{connect}{who}   (every command: cellgate --help)\n"
    ));
    if config.security.users_file.is_some() {
        t.push_str(&format!(
            "     (the password of --user from --password-file or ${})\n",
            cellgate::client::cli::PASSWORD_ENV
        ));
    }
    t
}

/// A site server's end as an exit code: a bad option or cell file is a configuration error.
fn site_ended(r: Result<(), cellgate::client::site::SiteError>) -> Result<(), (u8, String)> {
    match r {
        Ok(()) => Ok(()),
        Err(cellgate::client::site::SiteError::Config(e)) => Err((EXIT_CONFIG, e)),
        Err(e) => Err((EXIT_RUNTIME, e.to_string())),
    }
}

/// `cellgate console`: the site view until SIGINT or SIGTERM.
fn site_console(args: &cellgate::console::SiteArgs) -> ExitCode {
    run_site(|shutdown| async move { site_ended(cellgate::console::site(args, shutdown).await) })
}

/// `cellgate mtconnect`: the site agent until SIGINT or SIGTERM.
fn site_mtconnect(args: &cellgate::mtconnect::SiteArgs) -> ExitCode {
    run_site(|shutdown| async move { site_ended(cellgate::mtconnect::site(args, shutdown).await) })
}

/// `cellgate opcua`: the site OPC UA server until SIGINT or SIGTERM.
fn site_opcua(args: &cellgate::opcua::SiteArgs) -> ExitCode {
    run_site(|shutdown| async move { site_ended(cellgate::opcua::site(args, shutdown).await) })
}

/// `cellgate historian`: the site's history in PostgreSQL until SIGINT or SIGTERM.
fn historian(args: &cellgate::historian::HistorianArgs) -> ExitCode {
    run_site(|shutdown| async move {
        match cellgate::historian::run(args, shutdown).await {
            Ok(()) => Ok(()),
            Err(cellgate::historian::HistorianError::Config(e)) => Err((EXIT_CONFIG, e)),
            Err(e) => Err((EXIT_RUNTIME, e.to_string())),
        }
    })
}

/// A site process (console, MTConnect agent, historian): logs to stderr (colours only for a terminal),
/// a runtime, `serve` until SIGINT or SIGTERM; an error is printed with its exit code.
fn run_site<F, Fut>(serve: F) -> ExitCode
where
    F: FnOnce(std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send>>) -> Fut,
    Fut: std::future::Future<Output = Result<(), (u8, String)>>,
{
    let rust_log = std::env::var("RUST_LOG").ok();
    let filter = cellgate::telemetry::filter("info", rust_log.as_deref())
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
    let runtime = match multi_thread(None) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    let code = runtime.block_on(async {
        let shutdown = match shutdown_signal() {
            Ok(s) => s,
            Err(e) => {
                eprintln!("cellgate: cannot watch for signals: {e}");
                return ExitCode::from(EXIT_RUNTIME);
            }
        };
        match serve(Box::pin(shutdown)).await {
            Ok(()) => ExitCode::SUCCESS,
            Err((code, message)) => {
                eprintln!("cellgate: {message}");
                ExitCode::from(code)
            }
        }
    });
    runtime.shutdown_timeout(Duration::from_secs(2));
    code
}

/// Reloads the cell file on every SIGHUP (whose default action would end the gateway): the
/// handler is installed before this returns. What came of each reload the gateway logs.
fn reload_on_hangup(
    reload: cellgate::gateway::ReloadHandle,
) -> std::io::Result<tokio::task::JoinHandle<()>> {
    use tokio::signal::unix::{SignalKind, signal};
    let mut hangup = signal(SignalKind::hangup())?;
    Ok(tokio::spawn(async move {
        while hangup.recv().await.is_some() {
            tracing::info!("SIGHUP received: reloading the cell file");
            let origin = cellgate_core::pb::RequestOrigin {
                user: "SIGHUP".to_string(),
                via: "signal".to_string(),
            };
            if reload.reload(false, "signal", Some(origin)).await.is_none() {
                break;
            }
        }
    }))
}

/// Completes on the first SIGINT or SIGTERM. The handlers are installed before it is
/// returned, so a signal that arrives while the gateway is starting is not lost.
fn shutdown_signal() -> std::io::Result<impl Future<Output = ()>> {
    use tokio::signal::unix::{SignalKind, signal};
    let mut terminate = signal(SignalKind::terminate())?;
    let mut interrupt = signal(SignalKind::interrupt())?;
    Ok(async move {
        tokio::select! {
            _ = terminate.recv() => tracing::info!("SIGTERM received"),
            _ = interrupt.recv() => tracing::info!("SIGINT received"),
        }
    })
}

#[path = "main/examples.rs"]
mod examples;
#[path = "main/listen.rs"]
mod listen;

#[cfg(test)]
#[path = "main/tests.rs"]
mod tests;
