//! The simulated board as a TCP serial device server (`cellgate sim fanuc`).
//!
//! One connection at a time is the serial line: each new connection powers a fresh board on
//! (line up again) and replaces the previous connection. The board's output is paced at the
//! configured baud rate (11 bit times a character at 8N2, protocol notes 2), as a device
//! server's serial side would deliver it, and the host's input reaches the board at that rate
//! too, however fast it came over TCP. Every event
//! of interest goes to stdout as one JSON object per line:
//!
//! ```text
//! {"event":"listening","addr":"127.0.0.1:4001","protocol":"A","baud":9600}
//! {"event":"connected","peer":"127.0.0.1:50312"}
//! {"event":"link","state":"ready"}
//! {"event":"program","bytes":1234,"sha256":"…","first_line":"O1234"}
//! {"event":"do","image":165,"hex":"A5"}
//! {"event":"alarm","alarm":"SR0945","message":"…","cause":"checksum-retry-over","detail":"…"}
//! {"event":"punch","state":"finished","bytes":4096}
//! {"event":"g05","state":"started","axes":3,"unit_ms":8}
//! {"event":"g05","state":"underruns","new":1,"total":1}
//! {"event":"g05","state":"ended","end":"end-block","blocks":1000,"travel":[7000,-300,0],…}
//! ```
//!
//! Protocol B (`--protocol b|exp-b`): `--punch FILE` punches the file's bytes out, as they are
//! (the file holds the encoded tape), `--punch-after-ms` after each connection; `--no-notify`
//! turns the CNC reset/alarm notices off (parameter 5003#3 = 0). A raw TCP device server
//! carries no modem lines, so the ER off that replaces the notices then never reaches the
//! host: it sees only the DC3.
//!
//! `--commands-stdin`: operator commands as JSON lines on stdin, each given to the session
//! of the board behind the live connection, as an operator at the CNC would act; one
//! `command` event answers each line (blank lines aside), `applied: false` with a `reason`
//! when the board has no connection or the line is invalid. EOF stops only the commands:
//!
//! ```text
//! {"board":0,"command":"alarm"}          (also "reset", "hold", "start"; "board" defaults to 0)
//! {"board":0,"command":"di","value":165}
//! {"event":"command","command":"alarm","applied":true}
//! {"event":"command","command":"reset","applied":false,"reason":"no connection"}
//! ```
//!
//! G05 binary input operation (§9): `--g05-axes N` gives the CNC binary input operation with N
//! axes a block (parameter 7635); `--g05-unit-ms` (7618), `--g05-general` (7609#2 RDS = 1),
//! `--g05-aux` (7609#3 RAX and 2034) and `--g05-aux-low-first` (protocol notes 14) set the
//! rest. The `g05` events report its start, its underruns (at most one line a second) and
//! its end with the session's totals: blocks, travel per axis in least input increments,
//! significant auxiliary values, underruns, and the fewest whole blocks buffered at a unit
//! time.

use std::collections::VecDeque;
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll, ready};
use std::time::Duration;

use serde_json::{Value, json};
use tokio::io::{AsyncBufRead, AsyncBufReadExt, AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio::time::{Instant, Sleep};

use crate::sim::{BoardCommand, BoardConfig, BoardEvent, FanucBoard, SimError, run_board};
use crate::transport::{LineSettings, ModemIn, ModemOut, Pacer, Transport};
use cellgate_core::fanuc::g05::{AuxFunction, AuxOrder, DataFormat, G05Format, UnitTime};
use cellgate_core::fanuc::message::Framing;
use cellgate_core::fanuc::sat::Params;
use cellgate_core::fanuc::{CodeSystem, EndCode, Protocol};
use cellgate_core::program::tape::{self, TapeCode};
use cellgate_core::sim::cnc::{DEFAULT_BUFFER_SIZE, DEFAULT_CONSUME_RATE};

/// `--protocol`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SimProtocol {
    /// Protocol A (§4).
    A,
    /// Protocol A, and Expansion Protocol A when the host's SET selects n = 1, 2 or 4 (§5).
    #[value(name = "exp-a")]
    ExpA,
    /// Protocol B (§6): DC1 / DC3 flow control, punch-out.
    B,
    /// Expansion Protocol B (§7): Protocol B with a 2560-character stop level and allowance.
    #[value(name = "exp-b")]
    ExpB,
}

/// `--code`: the code of the messages' control part (parameter 5000#2, protocol notes 3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SimCode {
    Ascii,
    Iso,
}

/// `--end-code`: the end code of Protocol A messages (parameter 5000#3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SimEndCode {
    Cr,
    Etx,
}

/// `cellgate sim fanuc`: a simulated remote-buffer board with its CNC, served over TCP.
#[derive(Debug, Clone, clap::Args)]
pub struct SimFanucArgs {
    /// Address to listen on; loopback only. With --boards N, the first of N consecutive ports.
    #[arg(long, default_value = "127.0.0.1:4001")]
    pub listen: SocketAddr,
    /// Independent boards (each with its CNC) served from this one process, on N consecutive
    /// ports from --listen, all with the options given; every event line carries `"board"`,
    /// the board's index from 0. For many links against one gateway.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=4096))]
    pub boards: u16,
    /// Remote-buffer protocol.
    #[arg(long, value_enum, default_value_t = SimProtocol::A)]
    pub protocol: SimProtocol,
    /// Baud rate at which the board's output is paced (11 bits a character).
    #[arg(long, default_value_t = 9600)]
    pub baud: u32,
    /// Code of the control part (5000#2).
    #[arg(long, value_enum, default_value_t = SimCode::Ascii)]
    pub code: SimCode,
    /// End code of messages (5000#3).
    #[arg(long, value_enum, default_value_t = SimEndCode::Cr)]
    pub end_code: SimEndCode,
    /// The board's buffer in bytes (8 KiB on the real board).
    #[arg(long, default_value_t = DEFAULT_BUFFER_SIZE)]
    pub buffer_size: usize,
    /// Bytes per second the running CNC reads from the buffer; 0 = as fast as data arrives.
    #[arg(long, default_value_t = DEFAULT_CONSUME_RATE)]
    pub consume_rate: u32,
    /// The CNC starts reading once the link is initialised and the first SAT has been
    /// answered (and again after every program; it resets itself after an alarm), so that
    /// any host's download works unattended.
    #[arg(long)]
    pub autostart: bool,
    /// Delay before the board's first SYN after power-on or a line error, in ms (§4.3 (1)).
    #[arg(long, default_value_t = 2000)]
    pub first_request_delay_ms: u64,
    /// Power-on Nb: minimum free buffer space before GTD, bytes (§4.5).
    #[arg(long, default_value_t = Params::POWER_ON.nb)]
    pub nb: u16,
    /// Power-on No: maximum overrun on reception, bytes.
    #[arg(long, default_value_t = Params::POWER_ON.no)]
    pub no: u16,
    /// Power-on Ne: retries on a transmission error.
    #[arg(long, default_value_t = Params::POWER_ON.ne)]
    pub ne: u16,
    /// Power-on Tp: SAT polling interval, s.
    #[arg(long, default_value_t = Params::POWER_ON.tp)]
    pub tp: u16,
    /// Power-on To: answer time-out, s.
    #[arg(long, default_value_t = Params::POWER_ON.to)]
    pub to: u16,
    /// Power-on Ti: minimum interval between transmitted bytes, ms (not applied).
    #[arg(long, default_value_t = Params::POWER_ON.ti)]
    pub ti: u16,
    /// Power-on Tx: wait from reception to transmission, ms.
    #[arg(long, default_value_t = Params::POWER_ON.tx)]
    pub tx: u16,
    /// Power-on Tw: wait after WAT, s.
    #[arg(long, default_value_t = Params::POWER_ON.tw)]
    pub tw: u16,
    /// Protocol B: CNC reset/alarm not posted to the host (parameter 5003#3 = 0): the board
    /// sends DC3 and turns ER off instead of SYN / NAK (§6.4).
    #[arg(long)]
    pub no_notify: bool,
    /// Protocol B with --no-notify: how long ER stays off after a reset or alarm, in ms.
    #[arg(long, default_value_t = 1000)]
    pub er_off_ms: u64,
    /// Protocol B: punch this file out to the host after each connection, byte for byte (it
    /// holds the encoded tape: ISO with parity, ASCII or EIA), framed as DC2 … DC4.
    #[arg(long, value_name = "FILE")]
    pub punch: Option<PathBuf>,
    /// Protocol B: how long after the host connects the --punch file is punched out, in ms.
    #[arg(long, default_value_t = 2000)]
    pub punch_after_ms: u64,
    /// Protocol B: the --punch file is program text (7-bit, EOB = LF) to punch in this code:
    /// ISO with even parity, ASCII, or EIA (parameter 0000#4). `raw`: the file is the tape.
    #[arg(long, value_enum, default_value_t = PunchCode::Raw)]
    pub punch_code: PunchCode,
    /// G05 binary input operation (§9) with this many axes a block (parameter 7635). Without
    /// it the CNC has no binary input operation.
    #[arg(long, value_name = "N")]
    pub g05_axes: Option<u8>,
    /// G05 unit time in ms (parameter 7618): 1, 2, 4, 8 or 16. Default 8.
    #[arg(long, value_name = "T", value_parser = parse_unit_time, requires = "g05_axes")]
    pub g05_unit_ms: Option<UnitTime>,
    /// G05 travels and auxiliary word in the general format (parameter 7609#2 RDS = 1);
    /// Protocol A requires the special one (§9.1 NOTE).
    #[arg(long, requires = "g05_axes")]
    pub g05_general: bool,
    /// G05 auxiliary word and its function (parameters 7609#3 RAX and 2034). Default none.
    #[arg(long, value_enum, value_name = "KIND", requires = "g05_axes")]
    pub g05_aux: Option<SimG05Aux>,
    /// The G05 auxiliary word's low 16 bits travel first (protocol notes 14).
    #[arg(long, requires = "g05_axes")]
    pub g05_aux_low_first: bool,
    /// Read operator commands as JSON lines on stdin and give each to the board's live
    /// session: `{"board": 0, "command": "alarm"}`; commands `alarm`, `reset`, `hold` (feed
    /// hold), `start` (cycle start) and `di` with `"value": 0-255`; `board` defaults to 0.
    /// Each line is answered by a `command` event (`applied`, and `reason` when not applied:
    /// no connection, invalid line). Lines of up to 4096 bytes; EOF stops only the commands.
    #[arg(long)]
    pub commands_stdin: bool,
}

/// `--g05-aux`: parameters 7609#3 RAX and 2034 (§9.1 (6), (7)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SimG05Aux {
    /// RAX = 0: no auxiliary word.
    None,
    /// Second auxiliary function (2034 = 0).
    Second,
    /// Miscellaneous function (2034 = 1).
    M,
    /// S function (2034 = 2).
    S,
    /// T function (2034 = 3).
    T,
}

impl From<SimG05Aux> for AuxFunction {
    fn from(a: SimG05Aux) -> Self {
        match a {
            SimG05Aux::None => AuxFunction::None,
            SimG05Aux::Second => AuxFunction::Second,
            SimG05Aux::M => AuxFunction::M,
            SimG05Aux::S => AuxFunction::S,
            SimG05Aux::T => AuxFunction::T,
        }
    }
}

fn parse_unit_time(text: &str) -> Result<UnitTime, String> {
    let ms: u32 = text
        .parse()
        .map_err(|_| format!("{text:?} is not a number of ms"))?;
    UnitTime::try_from(ms).map_err(|e| e.to_string())
}

/// How the `--punch` file becomes a tape.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PunchCode {
    Raw,
    Iso,
    Ascii,
    Eia,
}

/// A punch-out the server does on every connection.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PunchPlan {
    /// The bytes, as they go on the line.
    pub data: Vec<u8>,
    /// Time from the connection to the punch-out command.
    pub after: Duration,
}

impl SimFanucArgs {
    /// The board these arguments describe.
    pub fn board_config(&self) -> Result<BoardConfig, SimError> {
        let protocol = match self.protocol {
            SimProtocol::A => Protocol::A,
            SimProtocol::ExpA => Protocol::ExpansionA,
            SimProtocol::B => Protocol::B,
            SimProtocol::ExpB => Protocol::ExpansionB,
        };
        let framing = Framing::new(
            match self.code {
                SimCode::Ascii => CodeSystem::Ascii,
                SimCode::Iso => CodeSystem::Iso,
            },
            match self.end_code {
                SimEndCode::Cr => EndCode::Cr,
                SimEndCode::Etx => EndCode::Etx,
            },
        );
        let config = BoardConfig {
            protocol,
            framing,
            params: Params {
                nb: self.nb,
                no: self.no,
                ne: self.ne,
                tp: self.tp,
                to: self.to,
                ti: self.ti,
                tx: self.tx,
                tw: self.tw,
            },
            buffer_size: self.buffer_size,
            consume_rate: self.consume_rate,
            autostart: self.autostart,
            first_request_delay: Duration::from_millis(self.first_request_delay_ms),
            notify_alarm_reset: !self.no_notify,
            er_off_time: Duration::from_millis(self.er_off_ms),
            g05: self.g05_format(),
            ..BoardConfig::default()
        };
        config.validate()?;
        Ok(config)
    }

    /// The `--punch` file, read once (Protocol B only).
    pub fn punch_plan(&self) -> Result<Option<PunchPlan>, SimError> {
        let Some(path) = &self.punch else {
            return Ok(None);
        };
        if matches!(self.protocol, SimProtocol::A | SimProtocol::ExpA) {
            return Err(SimError::PunchNeedsProtocolB);
        }
        let text = std::fs::read(path).map_err(|source| SimError::PunchFile {
            path: path.clone(),
            source,
        })?;
        let code = match self.punch_code {
            PunchCode::Raw => None,
            PunchCode::Iso => Some(TapeCode::Iso),
            PunchCode::Ascii => Some(TapeCode::Ascii),
            PunchCode::Eia => Some(TapeCode::Eia),
        };
        let data = match code {
            None => text,
            Some(code) => tape::encode(&text, code).map_err(|error| SimError::PunchCode {
                path: path.clone(),
                error,
            })?,
        };
        Ok(Some(PunchPlan {
            data,
            after: Duration::from_millis(self.punch_after_ms),
        }))
    }

    /// The CNC's G05 settings, when `--g05-axes` is given.
    pub fn g05_format(&self) -> Option<G05Format> {
        Some(G05Format {
            axes: self.g05_axes?,
            data_format: if self.g05_general {
                DataFormat::General
            } else {
                DataFormat::Special
            },
            aux: self.g05_aux.map_or(AuxFunction::None, AuxFunction::from),
            unit_time_ms: self.g05_unit_ms.unwrap_or_default(),
            aux_order: if self.g05_aux_low_first {
                AuxOrder::LowFirst
            } else {
                AuxOrder::HighFirst
            },
        })
    }

    pub fn line_settings(&self) -> LineSettings {
        LineSettings::with_baud(self.baud)
    }
}

/// Where the JSON events go.
pub type EventSink = Arc<dyn Fn(&Value) + Send + Sync>;

/// Serves the board on `args.listen` until `shutdown` completes, printing one JSON event per
/// line on stdout.
pub async fn serve_fanuc(
    args: SimFanucArgs,
    shutdown: impl Future<Output = ()>,
) -> Result<(), SimError> {
    let config = args.board_config()?;
    let punch = args.punch_plan()?;
    if !args.listen.ip().is_loopback() {
        return Err(SimError::NotLoopback { addr: args.listen });
    }
    let stdout: EventSink = Arc::new(|v: &Value| {
        use std::io::Write;
        let mut out = std::io::stdout().lock();
        // A closed stdout must not stop the simulator.
        let _ = writeln!(out, "{v}").and_then(|()| out.flush());
    });
    // Every port is bound before any board runs: a port in use fails the whole command.
    let mut listeners = Vec::with_capacity(usize::from(args.boards));
    for i in 0..args.boards {
        let port = args
            .listen
            .port()
            .checked_add(i)
            .filter(|_| args.listen.port() != 0);
        let addr = match port {
            Some(port) => SocketAddr::new(args.listen.ip(), port),
            None if args.boards == 1 => args.listen,
            None => {
                return Err(SimError::Ports {
                    addr: args.listen,
                    boards: args.boards,
                });
            }
        };
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|source| SimError::Bind { addr, source })?;
        listeners.push(listener);
    }
    let slots: Vec<SessionSlot> = (0..args.boards).map(|_| SessionSlot::default()).collect();
    // Aborted when the boards stop.
    let _commands = args.commands_stdin.then(|| {
        let (slots, sink) = (slots.clone(), stdout.clone());
        tokio_util::task::AbortOnDropHandle::new(tokio::spawn(async move {
            route_commands(stdin_reader(), &slots, &sink).await;
        }))
    });
    if args.boards == 1
        && let (Some(listener), Some(slot)) = (listeners.pop(), slots.first())
    {
        let settings = args.line_settings();
        return serve_fanuc_board(
            listener,
            config,
            settings,
            punch,
            stdout,
            slot.clone(),
            shutdown,
        )
        .await;
    }
    let stop = tokio_util::sync::CancellationToken::new();
    let mut boards = tokio::task::JoinSet::new();
    for (i, (listener, slot)) in listeners.into_iter().zip(slots).enumerate() {
        let out = stdout.clone();
        let sink: EventSink = Arc::new(move |v: &Value| {
            let mut v = v.clone();
            v["board"] = json!(i);
            out(&v);
        });
        let (config, settings, punch) = (config.clone(), args.line_settings(), punch.clone());
        let stop = stop.clone();
        boards.spawn(async move {
            serve_fanuc_board(
                listener,
                config,
                settings,
                punch,
                sink,
                slot,
                stop.cancelled_owned(),
            )
            .await
        });
    }
    let mut shutdown = std::pin::pin!(shutdown);
    let mut result = Ok(());
    loop {
        tokio::select! {
            () = &mut shutdown => break,
            ended = boards.join_next() => match ended {
                None => break,
                Some(Ok(Ok(()))) => {}
                Some(Ok(Err(e))) => { result = Err(e); break; }
                Some(Err(e)) => { result = Err(SimError::Board(e.to_string())); break; }
            },
        }
    }
    stop.cancel();
    while boards.join_next().await.is_some() {}
    result
}

/// Serves the board on a bound listener (tests bind port 0), sending JSON events to `sink`.
pub async fn serve_fanuc_on(
    listener: TcpListener,
    config: BoardConfig,
    settings: LineSettings,
    sink: EventSink,
    shutdown: impl Future<Output = ()>,
) -> Result<(), SimError> {
    serve_fanuc_with(listener, config, settings, None, sink, shutdown).await
}

/// [`serve_fanuc_on`], punching `punch` out on every connection.
pub async fn serve_fanuc_with(
    listener: TcpListener,
    config: BoardConfig,
    settings: LineSettings,
    punch: Option<PunchPlan>,
    sink: EventSink,
    shutdown: impl Future<Output = ()>,
) -> Result<(), SimError> {
    let slot = SessionSlot::default();
    serve_fanuc_board(listener, config, settings, punch, sink, slot, shutdown).await
}

/// [`serve_fanuc_with`], each connection's session reachable through `slot` for operator
/// commands ([`route_commands`]).
pub async fn serve_fanuc_board(
    listener: TcpListener,
    config: BoardConfig,
    settings: LineSettings,
    punch: Option<PunchPlan>,
    sink: EventSink,
    slot: SessionSlot,
    shutdown: impl Future<Output = ()>,
) -> Result<(), SimError> {
    config.validate()?;
    let punch = punch.map(Arc::new);
    let addr = listener.local_addr().map_err(SimError::Output)?;
    let mut listening = json!({
        "event": "listening",
        "addr": addr.to_string(),
        "protocol": config.protocol.name(),
        "baud": settings.baud,
    });
    if let Some(g05) = &config.g05 {
        listening["g05"] = serde_json::to_value(g05).unwrap_or(Value::Null);
    }
    sink(&listening);
    serve_one_at_a_time(
        listener,
        shutdown,
        &sink,
        "simulated board",
        |stream, peer| {
            // In the slot before `connected` is reported, so that a command sent on seeing
            // it reaches this session.
            let (commands, commands_rx) = mpsc::unbounded_channel();
            slot.replace(&commands);
            let session = run_session(
                stream,
                peer,
                config.clone(),
                settings,
                punch.clone(),
                sink.clone(),
                (commands, commands_rx),
            );
            async move {
                match session.await {
                    Ok(()) => "connection closed".to_string(),
                    Err(e) => e.to_string(),
                }
            }
        },
    )
    .await;
    Ok(())
}

/// The accept loop of a simulated device server: one connection at a time, as a serial
/// line has one host; a new connection replaces the old one (a host that reconnects after a
/// cut finds the device at once). Each connection runs the session `start` makes of it, and
/// ends with the reason that session gives. Reports `connected` and `disconnected` on `sink`.
pub(crate) async fn serve_one_at_a_time<F, S>(
    listener: TcpListener,
    shutdown: impl Future<Output = ()>,
    sink: &EventSink,
    what: &'static str,
    mut start: F,
) where
    F: FnMut(TcpStream, SocketAddr) -> S,
    S: Future<Output = String> + Send + 'static,
{
    let mut shutdown = std::pin::pin!(shutdown);
    type Session = Pin<Box<dyn Future<Output = String> + Send>>;
    let mut session: Option<(SocketAddr, Session)> = None;
    loop {
        tokio::select! {
            () = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    if let Some((old, _)) = session.take() {
                        sink(&json!({
                            "event": "disconnected",
                            "peer": old.to_string(),
                            "reason": "replaced by a new connection",
                        }));
                    }
                    // Started first: what `start` sets up (a command slot) is in place by
                    // the time `connected` shows.
                    let started = Box::pin(start(stream, peer));
                    sink(&json!({"event": "connected", "peer": peer.to_string()}));
                    session = Some((peer, started));
                }
                Err(e) => {
                    tracing::warn!(error = %e, "{what}: accept failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            },
            reason = async {
                match session.as_mut() {
                    Some((_, s)) => s.await,
                    None => std::future::pending().await,
                }
            }, if session.is_some() => {
                let peer = session.take().map(|(p, _)| p.to_string());
                sink(&json!({"event": "disconnected", "peer": peer, "reason": reason}));
            }
        }
    }
}

async fn run_session(
    stream: TcpStream,
    peer: SocketAddr,
    config: BoardConfig,
    settings: LineSettings,
    punch: Option<Arc<PunchPlan>>,
    sink: EventSink,
    (commands, commands_rx): (
        mpsc::UnboundedSender<BoardCommand>,
        mpsc::UnboundedReceiver<BoardCommand>,
    ),
) -> Result<(), SimError> {
    // Small messages must not wait for Nagle.
    let _ = stream.set_nodelay(true);
    let board = FanucBoard::new(config, Instant::now().into_std())?;
    let line = PacedLine::new(stream, settings, format!("tcp {peer} paced at {settings}"));
    // Operator commands come from the planned punch-out and the slot (weak there); this
    // sender lives as long as the session (the board stops when the channel closes).
    let punch_task = punch.map(|plan| {
        let commands = commands.clone();
        tokio::spawn(async move {
            tokio::time::sleep(plan.after).await;
            let _ = commands.send(BoardCommand::Punch(plan.data.clone()));
        })
    });
    let result = run_board(
        board,
        line,
        commands_rx,
        |_, events, _| {
            for e in events.iter() {
                if let Some(v) = event_json(e) {
                    sink(&v);
                }
            }
        },
        std::future::pending::<()>(),
    )
    .await;
    if let Some(task) = punch_task {
        task.abort();
    }
    drop(commands);
    result
}

/// Where operator commands reach a board's live session: its sender, replaced at each
/// connection. Weak, so that the sender dies with its session and a command then finds no
/// connection.
#[derive(Debug, Clone, Default)]
pub struct SessionSlot(Arc<std::sync::Mutex<Option<mpsc::WeakUnboundedSender<BoardCommand>>>>);

impl SessionSlot {
    fn replace(&self, commands: &mpsc::UnboundedSender<BoardCommand>) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = Some(commands.downgrade());
    }

    /// Gives `command` to the live session; false when there is none.
    pub fn send(&self, command: BoardCommand) -> bool {
        let sender = self
            .0
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_ref()
            .and_then(mpsc::WeakUnboundedSender::upgrade);
        sender.is_some_and(|s| s.send(command).is_ok())
    }
}

/// The longest command line taken, without its LF.
pub const MAX_COMMAND_LINE: usize = 4096;

/// Reads operator commands, one JSON object a line, from `input` until EOF, gives each to the
/// session in `slots[board]` and answers each on `sink` with a `command` event (carrying
/// `"board"` when there are several boards). A bad line is answered and skipped.
pub async fn route_commands<R: AsyncBufRead + Unpin>(
    mut input: R,
    slots: &[SessionSlot],
    sink: &EventSink,
) {
    let mut line = Vec::new();
    loop {
        let too_long = match read_bounded_line(&mut input, &mut line).await {
            Ok(Some(too_long)) => too_long,
            Ok(None) => break,
            Err(e) => {
                tracing::warn!(error = %e, "operator commands: read failed");
                break;
            }
        };
        let (mut event, parsed) = if too_long {
            (
                json!({"event": "command", "command": null}),
                Err(format!("line longer than {MAX_COMMAND_LINE} bytes")),
            )
        } else if line.iter().all(u8::is_ascii_whitespace) {
            continue;
        } else {
            parse_command(&line, slots.len())
        };
        let outcome = parsed.and_then(|(board, command)| match slots.get(board) {
            Some(slot) if slot.send(command) => Ok(()),
            _ => Err("no connection".to_string()),
        });
        match outcome {
            Ok(()) => event["applied"] = json!(true),
            Err(reason) => {
                event["applied"] = json!(false);
                event["reason"] = json!(reason);
            }
        }
        sink(&event);
    }
}

/// The next line of `input` into `line`, without its LF: `Some(true)` when it was longer
/// than [`MAX_COMMAND_LINE`] (then skipped to its end, never held whole), `None` at EOF.
async fn read_bounded_line<R: AsyncBufRead + Unpin>(
    input: &mut R,
    line: &mut Vec<u8>,
) -> std::io::Result<Option<bool>> {
    line.clear();
    let (mut any, mut too_long) = (false, false);
    loop {
        let available = input.fill_buf().await?;
        if available.is_empty() {
            return Ok(any.then_some(too_long));
        }
        any = true;
        let (piece, used, ended) = match available.iter().position(|&b| b == b'\n') {
            Some(i) => (&available[..i], i + 1, true),
            None => (available, available.len(), false),
        };
        if !too_long {
            if line.len() + piece.len() > MAX_COMMAND_LINE {
                too_long = true;
                line.clear();
            } else {
                line.extend_from_slice(piece);
            }
        }
        input.consume(used);
        if ended {
            return Ok(Some(too_long));
        }
    }
}

/// A command line: the skeleton of its `command` event (the command and, with several
/// boards, the board, as far as the line says them) and the board and command, or why not.
fn parse_command(line: &[u8], boards: usize) -> (Value, Result<(usize, BoardCommand), String>) {
    let mut event = json!({"event": "command", "command": null});
    let value: Value = match serde_json::from_slice(line) {
        Ok(v) => v,
        Err(e) => return (event, Err(format!("not JSON: {e}"))),
    };
    let Some(fields) = value.as_object() else {
        return (event, Err("not a JSON object".to_string()));
    };
    let command = fields.get("command").and_then(Value::as_str);
    if let Some(c) = command {
        event["command"] = json!(c);
    }
    let board = match fields.get("board") {
        None => Some(0),
        Some(b) => b.as_u64(),
    };
    if boards > 1
        && let Some(b) = board
    {
        event["board"] = json!(b);
    }
    let parsed = board_command(fields, board, command, boards);
    if let (Ok((_, BoardCommand::SetDi(v))), Some(map)) = (&parsed, event.as_object_mut()) {
        map.insert("value".into(), json!(v));
    }
    (event, parsed)
}

/// The board and command a command line's `fields` name, or why not.
fn board_command(
    fields: &serde_json::Map<String, Value>,
    board: Option<u64>,
    command: Option<&str>,
    boards: usize,
) -> Result<(usize, BoardCommand), String> {
    let Some(board) = board else {
        return Err("\"board\" is not a whole number".to_string());
    };
    let board = usize::try_from(board)
        .ok()
        .filter(|&b| b < boards)
        .ok_or_else(|| format!("board {board} out of range: {boards} board(s) from 0"))?;
    let command = match command {
        Some("alarm") => BoardCommand::RaiseAlarm,
        Some("reset") => BoardCommand::Reset,
        Some("hold") => BoardCommand::StopReading,
        Some("start") => BoardCommand::StartReading,
        Some("di") => {
            let di = fields.get("value");
            let di = di
                .and_then(Value::as_u64)
                .and_then(|v| u8::try_from(v).ok());
            BoardCommand::SetDi(di.ok_or("di needs a \"value\" from 0 to 255")?)
        }
        Some(other) => {
            return Err(format!(
                "unknown command {other:?}: alarm, reset, hold, start or di"
            ));
        }
        None => return Err("no \"command\" string".to_string()),
    };
    Ok((board, command))
}

/// Standard input as an async reader, read by a thread of its own: tokio's stdin reads on a
/// blocking-pool thread that runtime shutdown waits for, so an idle open stdin would hang
/// SIGTERM. The thread ends with stdin (or the process).
fn stdin_reader() -> tokio::io::BufReader<tokio::io::DuplexStream> {
    let (mut tx, rx) = tokio::io::duplex(2 * MAX_COMMAND_LINE);
    let runtime = tokio::runtime::Handle::current();
    let spawned = std::thread::Builder::new()
        .name("commands-stdin".into())
        .spawn(move || {
            use std::io::Read;
            use tokio::io::AsyncWriteExt;
            let mut stdin = std::io::stdin().lock();
            let mut buf = [0u8; 4096];
            loop {
                let n = match stdin.read(&mut buf) {
                    Ok(0) => break,
                    Ok(n) => n,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                    Err(e) => {
                        tracing::warn!(error = %e, "operator commands: stdin failed");
                        break;
                    }
                };
                if runtime.block_on(tx.write_all(&buf[..n])).is_err() {
                    break;
                }
            }
        });
    // Without the thread the reader sees EOF at once: no commands, the boards serve on.
    if let Err(e) = spawned {
        tracing::warn!(error = %e, "operator commands: no thread to read stdin");
    }
    tokio::io::BufReader::new(rx)
}

/// The JSON line for a board event, for those worth printing.
pub fn event_json(event: &BoardEvent) -> Option<Value> {
    fn to<T: serde::Serialize>(v: &T) -> Value {
        serde_json::to_value(v).unwrap_or(Value::Null)
    }
    Some(match event {
        BoardEvent::LinkState(s) => json!({"event": "link", "state": s.name()}),
        BoardEvent::Status {
            status,
            alarm_cause,
        } => {
            json!({"event": "status", "status": to(status), "alarm_cause": alarm_cause.map(|c| to(&c))})
        }
        BoardEvent::ParamsChanged {
            params,
            packet_n,
            conversion,
        } => json!({
            "event": "params",
            "params": to(params),
            "packet_n": packet_n,
            "conversion": [conversion.0, conversion.1],
        }),
        BoardEvent::ProgramReceived(p) => json!({
            "event": "program",
            "bytes": p.len,
            "sha256": p.sha256_hex(),
            "first_line": p.first_line,
        }),
        BoardEvent::DoChanged(v) => json!({"event": "do", "image": v, "hex": format!("{v:02X}")}),
        BoardEvent::DiSent(v) => json!({"event": "di", "image": v, "hex": format!("{v:02X}")}),
        BoardEvent::Alarm {
            alarm,
            cause,
            detail,
        } => json!({
            "event": "alarm",
            "alarm": alarm.number(),
            "message": alarm.message(),
            "cause": to(cause),
            "detail": detail,
        }),
        BoardEvent::CncAlarm => json!({"event": "cnc-alarm"}),
        BoardEvent::CncReset => json!({"event": "cnc-reset"}),
        BoardEvent::ReadingStarted => json!({"event": "reading", "reading": true}),
        BoardEvent::ReadingStopped => json!({"event": "reading", "reading": false}),
        BoardEvent::BufferCleared => json!({"event": "buffer-cleared"}),
        BoardEvent::PunchStarted { bytes } => {
            json!({"event": "punch", "state": "started", "bytes": bytes})
        }
        BoardEvent::PunchFinished { bytes } => {
            json!({"event": "punch", "state": "finished", "bytes": bytes})
        }
        BoardEvent::PunchInterrupted { sent, bytes } => {
            json!({"event": "punch", "state": "interrupted", "sent": sent, "bytes": bytes})
        }
        BoardEvent::ErSignal { on } => json!({"event": "er", "on": on}),
        BoardEvent::ProtocolError { detail } => {
            json!({"event": "protocol-error", "detail": detail})
        }
        BoardEvent::G05Started { axes, unit_ms } => {
            json!({"event": "g05", "state": "started", "axes": axes, "unit_ms": unit_ms})
        }
        BoardEvent::G05Underruns { new, total } => {
            json!({"event": "g05", "state": "underruns", "new": new, "total": total})
        }
        BoardEvent::G05Ended { end, stats } => json!({
            "event": "g05",
            "state": "ended",
            "end": end.name(),
            "session": stats.sessions,
            "blocks": stats.blocks,
            "travel": stats.travel,
            "aux": stats.aux,
            "aux_count": stats.aux_count,
            "underruns": stats.underruns,
            "min_buffered_blocks": stats.min_buffered_blocks,
        }),
        _ => return None,
    })
}

/// The board's serial line over a byte stream, all modem lines on (the manual's wiring for
/// unused lines). Over a TCP connection ([`PacedLine::new`]): output paced at the baud rate
/// through a UART-sized window ([`Pacer`]), input delivered at the baud rate however fast it
/// came (the device server's serial side). Over an in-memory pipe in tests
/// ([`PacedLine::unpaced`]): bytes pass as they come.
pub struct PacedLine<S> {
    stream: S,
    /// `None`: unpaced.
    pace: Option<Box<Pace>>,
    name: String,
}

struct Pace {
    pacer: Pacer,
    sleep: Pin<Box<Sleep>>,
    /// The host's characters on their way down the line, back to back at the baud rate
    /// from their arrival over TCP: pieces and when each has wholly reached the board.
    rx_line: Pacer,
    rx_queue: VecDeque<(std::time::Instant, Vec<u8>)>,
    rx_sleep: Pin<Box<Sleep>>,
    rx_eof: bool,
    /// The board's UART reads this many data bits: on a 7-bit line, bit 7 of what comes over
    /// TCP never reaches it (a device server set to the line sends 7 of the 8).
    mask: u8,
}

/// Characters the simulated UART holds beyond the one being sent (a 16-byte FIFO).
const UART_FIFO: usize = 16;

/// The host's characters reach the board in pieces of this many, each when its last has.
const RX_PIECE: usize = 32;

impl<S> PacedLine<S> {
    pub fn new(stream: S, settings: LineSettings, name: String) -> Self {
        PacedLine {
            stream,
            pace: Some(Box::new(Pace {
                pacer: Pacer::new(settings, UART_FIFO),
                sleep: Box::pin(tokio::time::sleep_until(Instant::now())),
                rx_line: Pacer::new(settings, usize::MAX),
                rx_queue: VecDeque::new(),
                rx_sleep: Box::pin(tokio::time::sleep_until(Instant::now())),
                rx_eof: false,
                mask: settings.data_mask(),
            })),
            name,
        }
    }

    /// Bytes pass both ways as fast as the stream takes them.
    pub fn unpaced(stream: S, name: impl Into<String>) -> Self {
        PacedLine {
            stream,
            pace: None,
            name: name.into(),
        }
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for PacedLine<S> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let this = &mut *self;
        let Some(p) = &mut this.pace else {
            return Pin::new(&mut this.stream).poll_read(cx, buf);
        };
        // Everything TCP has goes onto the line at once, timed from its arrival, so that the
        // line stays busy while earlier pieces are still on their way.
        while !p.rx_eof {
            let mut chunk = [0u8; 4096];
            let mut read = ReadBuf::new(&mut chunk);
            match Pin::new(&mut this.stream).poll_read(cx, &mut read) {
                Poll::Pending => break,
                Poll::Ready(Err(e)) => {
                    if p.rx_queue.is_empty() {
                        return Poll::Ready(Err(e));
                    }
                    p.rx_eof = true;
                }
                Poll::Ready(Ok(())) if read.filled().is_empty() => p.rx_eof = true,
                Poll::Ready(Ok(())) => {
                    let got = read.filled();
                    let placement = p.rx_line.wrote(got.len(), Instant::now().into_std());
                    for (i, piece) in got.chunks(RX_PIECE).enumerate() {
                        let last = (i * RX_PIECE + piece.len() - 1) as u64;
                        p.rx_queue
                            .push_back((placement.done_at(last), piece.to_vec()));
                    }
                }
            }
        }
        let Some((at, _)) = p.rx_queue.front() else {
            // Nothing on the way: EOF once TCP said so, else wait for TCP.
            return if p.rx_eof {
                Poll::Ready(Ok(()))
            } else {
                Poll::Pending
            };
        };
        if Instant::now().into_std() < *at {
            p.rx_sleep.as_mut().reset(Instant::from_std(*at));
            ready!(p.rx_sleep.as_mut().poll(cx));
        }
        let Some((_, mut piece)) = p.rx_queue.pop_front() else {
            return Poll::Pending;
        };
        let n = piece.len().min(buf.remaining());
        if p.mask != 0xFF {
            for b in &mut piece[..n] {
                *b &= p.mask;
            }
        }
        buf.put_slice(&piece[..n]);
        if n < piece.len() {
            let at = Instant::now().into_std();
            p.rx_queue.push_front((at, piece.split_off(n)));
        }
        Poll::Ready(Ok(()))
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for PacedLine<S> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        let this = &mut *self;
        let Some(p) = &mut this.pace else {
            return Pin::new(&mut this.stream).poll_write(cx, buf);
        };
        let mut now = Instant::now().into_std();
        if p.pacer.batch(now, buf.len()) == 0 {
            let at = Instant::from_std(p.pacer.batch_at(now, buf.len()));
            p.sleep.as_mut().reset(at);
            ready!(p.sleep.as_mut().poll(cx));
            now = Instant::now().into_std();
        }
        let room = p.pacer.batch(now, buf.len()).max(1);
        let n = ready!(Pin::new(&mut this.stream).poll_write(cx, &buf[..buf.len().min(room)]))?;
        p.pacer.wrote(n, now);
        Poll::Ready(Ok(n))
    }
    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }
    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}

impl<S: AsyncRead + AsyncWrite + Send + Unpin> Transport for PacedLine<S> {
    fn set_modem(&mut self, _out: ModemOut) -> std::io::Result<()> {
        Ok(())
    }
    fn modem(&mut self) -> std::io::Result<ModemIn> {
        Ok(ModemIn::ALL_ON)
    }
    /// The lines never change, so there is nothing to poll.
    fn modem_wakes_reader(&self) -> bool {
        true
    }
    fn describe(&self) -> String {
        self.name.clone()
    }
}

#[cfg(test)]
mod tests;
