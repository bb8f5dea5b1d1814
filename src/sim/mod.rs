//! Simulated devices for tests, CI and laptops, run over the gateway's transports: the core's
//! sans-IO models ([`cellgate_core::sim`]: a FANUC remote-buffer board with a CNC behind it,
//! an FFU120B with a MICREX-F) in tokio tasks.
//!
//! - [`server`]: the board as a TCP serial device server (`cellgate sim fanuc`);
//! - [`micrex_handle`], [`fuji_server`]: the simulated PLC over a transport, and as a TCP
//!   device server (`cellgate sim fuji`).
//!
//! [`BoardHandle`] runs a board over any [`Transport`] in a tokio task, and is what tests and
//! an embedded cell use: commands in, a snapshot of the board's state, and a broadcast of its
//! events.

pub mod fuji_server;
pub mod micrex_handle;
pub mod server;

use std::future::Future;
use std::sync::{Arc, Mutex, PoisonError};

use tokio::sync::{broadcast, mpsc, watch};
use tokio::task::JoinHandle;

use crate::link::pump::{Pump, PumpError};
use crate::transport::Transport;
use cellgate_core::engine::Engine;
use cellgate_core::fanuc::alarm::CncAlarm;
use cellgate_core::fanuc::sat::{Params, StatusData};

use cellgate_core::sim::{
    BoardCommand, BoardConfig, BoardConfigError, BoardEvent, BoardLinkState, FanucBoard, G05Stats,
    ReceivedProgram,
};

/// Errors of the simulators, kept apart from the protocol events they report.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SimError {
    #[error("simulated FANUC board: {0}")]
    Config(#[from] BoardConfigError),
    #[error("simulated FANUC board: cannot read the punch-out file {path}: {source}")]
    PunchFile {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("simulated FANUC board: --punch needs --protocol b or exp-b (punch-out is §6.1.1 2)")]
    PunchNeedsProtocolB,
    #[error("punch file {}: {error}", path.display())]
    PunchCode {
        path: std::path::PathBuf,
        #[source]
        error: cellgate_core::program::tape::TapeError,
    },
    #[error(
        "simulator listen address {addr} is not loopback: simulators bind 127.0.0.1 or ::1 only"
    )]
    NotLoopback { addr: std::net::SocketAddr },
    #[error(
        "{boards} boards need {boards} consecutive ports from {addr}: give a port from 1 to \
         {}",
        65536 - u32::from(*boards)
    )]
    Ports {
        addr: std::net::SocketAddr,
        boards: u16,
    },
    #[error("a simulated board stopped: {0}")]
    Board(String),
    #[error("simulator cannot listen on {addr}: {source}")]
    Bind {
        addr: std::net::SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("simulated board line ({line}): {source}")]
    Line {
        line: String,
        #[source]
        source: std::io::Error,
    },
    #[error("simulator event output: {0}")]
    Output(#[source] std::io::Error),
}

/// The board's state as last seen by its task.
#[derive(Debug, Clone)]
pub struct BoardSnapshot {
    pub link: BoardLinkState,
    /// What the next SAT would say (§4.4.2): status, alarm cause, bytes buffered, params, n.
    pub status: StatusData,
    pub params: Params,
    pub packet_n: u8,
    pub reading: bool,
    pub buffered: usize,
    pub di_image: u8,
    pub do_image: u8,
    /// Every program the CNC read, oldest first.
    pub programs: Vec<ReceivedProgram>,
    /// Every SR alarm the board raised, oldest first.
    pub alarms: Vec<CncAlarm>,
    /// NC data bytes stored in the buffer since power-on.
    pub data_received: u64,
    /// Protocol B: DC1 codes sent since power-on (read requests and resumptions).
    pub dc1_sent: u64,
    /// Protocol B: DC3 codes sent since power-on (stops, ends of reads, before notices).
    pub dc3_sent: u64,
    /// Protocol B: most characters received after one DC3 (§6.3).
    pub max_overrun: usize,
    /// Protocol B: SR0856 alarms raised for data past the allowance or a full buffer.
    pub overruns: u64,
    /// Protocol B: punched bytes handed to the line since power-on.
    pub punched: u64,
    /// G05 binary input operation of the current or last session (§9); `None` when the CNC
    /// has no G05 settings.
    pub g05: Option<G05Stats>,
    /// Whether the board's task has ended (line closed or error).
    pub stopped: bool,
    /// Whether the CNC is in alarm.
    pub alarm: bool,
    /// Whether the operator starts reads and resets alarms by himself.
    pub autostart: bool,
    /// Commands the board has taken since power-on ([`BoardControl::apply`] waits on it).
    pub commands_taken: u64,
}

impl BoardSnapshot {
    fn of(board: &FanucBoard) -> Self {
        let mut s = BoardSnapshot {
            link: board.link_state(),
            status: board.status_data(),
            params: board.params(),
            packet_n: board.packet_n(),
            reading: false,
            buffered: 0,
            di_image: 0,
            do_image: 0,
            programs: Vec::new(),
            alarms: Vec::new(),
            data_received: 0,
            dc1_sent: 0,
            dc3_sent: 0,
            max_overrun: 0,
            overruns: 0,
            punched: 0,
            g05: None,
            stopped: false,
            alarm: false,
            autostart: false,
            commands_taken: 0,
        };
        s.refresh(board);
        s
    }

    fn refresh(&mut self, board: &FanucBoard) {
        let cnc = board.cnc();
        self.link = board.link_state();
        self.status = board.status_data();
        self.params = board.params();
        self.packet_n = board.packet_n();
        self.reading = cnc.reading();
        self.buffered = cnc.buffered();
        self.di_image = cnc.di();
        self.do_image = cnc.do_image();
        self.alarm = cnc.alarm().is_some();
        self.autostart = board.autostart();
        let flow = board.flow_counters();
        self.dc1_sent = flow.dc1_sent;
        self.dc3_sent = flow.dc3_sent;
        self.max_overrun = flow.max_overrun;
        self.overruns = flow.overruns;
        self.punched = flow.punched;
        if let Some(stats) = cnc.g05_stats()
            && self.g05.as_ref() != Some(stats)
        {
            self.g05 = Some(stats.clone());
        }
    }

    fn record(&mut self, event: &BoardEvent) {
        match event {
            BoardEvent::ProgramReceived(p) => self.programs.push(p.clone()),
            BoardEvent::Alarm { alarm, .. } => self.alarms.push(*alarm),
            BoardEvent::DataReceived { bytes, .. } => self.data_received += *bytes as u64,
            _ => {}
        }
    }
}

/// A simulated board running in a tokio task over a [`Transport`].
///
/// Dropping the handle stops the board.
#[derive(Debug)]
pub struct BoardHandle {
    commands: mpsc::UnboundedSender<BoardCommand>,
    events: broadcast::Sender<BoardEvent>,
    state: watch::Receiver<BoardSnapshot>,
    task: JoinHandle<Result<(), SimError>>,
    /// Commands sent so far; held while one is sent, so that its number is its place.
    sent: Arc<Mutex<u64>>,
}

/// What a running cell's bus routes drive a simulated board with: its commands, and its
/// state once it took one. Cheap to clone; it does not keep the board running.
#[derive(Debug, Clone)]
pub struct BoardControl {
    commands: mpsc::UnboundedSender<BoardCommand>,
    state: watch::Receiver<BoardSnapshot>,
    sent: Arc<Mutex<u64>>,
}

/// A command the simulated board did not take.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ControlError {
    #[error("the simulated board has stopped")]
    Stopped,
    #[error("the simulated board did not take the command within {} ms", .0.as_millis())]
    Late(std::time::Duration),
}

impl BoardControl {
    /// The board's state now.
    pub fn snapshot(&self) -> BoardSnapshot {
        self.state.borrow().clone()
    }

    /// Gives the board `command` and returns its state once it has taken it (within
    /// `within`).
    pub async fn apply(
        &self,
        command: BoardCommand,
        within: std::time::Duration,
    ) -> Result<BoardSnapshot, ControlError> {
        let number = {
            let mut sent = self.sent.lock().unwrap_or_else(PoisonError::into_inner);
            self.commands
                .send(command)
                .map_err(|_| ControlError::Stopped)?;
            *sent += 1;
            *sent
        };
        let mut state = self.state.clone();
        let taken = tokio::time::timeout(
            within,
            state.wait_for(|s| s.stopped || s.commands_taken >= number),
        )
        .await
        .map_err(|_| ControlError::Late(within))?
        .map_err(|_| ControlError::Stopped)?
        .clone();
        if taken.commands_taken < number {
            return Err(ControlError::Stopped);
        }
        Ok(taken)
    }
}

/// Events kept for slow subscribers; older ones are lost (`RecvError::Lagged`).
const EVENT_CAPACITY: usize = 4096;

impl BoardHandle {
    /// Powers a board on and runs it over `line` until the handle is dropped, the line
    /// closes, or the line fails.
    pub fn spawn<T: Transport + 'static>(config: BoardConfig, line: T) -> Result<Self, SimError> {
        let board = FanucBoard::new(config, tokio::time::Instant::now().into_std())?;
        let (cmd_tx, cmd_rx) = mpsc::unbounded_channel();
        let (events, _) = broadcast::channel(EVENT_CAPACITY);
        let (state_tx, state) = watch::channel(BoardSnapshot::of(&board));
        let events_tx = events.clone();
        let task = tokio::spawn(async move {
            let result = run_board(
                board,
                line,
                cmd_rx,
                |board, new_events, taken| {
                    state_tx.send_modify(|s| {
                        for e in new_events.iter() {
                            s.record(e);
                        }
                        s.refresh(board);
                        s.commands_taken = taken;
                    });
                    for e in new_events.drain(..) {
                        // No subscriber is fine.
                        let _ = events_tx.send(e);
                    }
                },
                std::future::pending::<()>(),
            )
            .await;
            state_tx.send_modify(|s| s.stopped = true);
            result
        });
        Ok(BoardHandle {
            commands: cmd_tx,
            events,
            state,
            task,
            sent: Arc::new(Mutex::new(0)),
        })
    }

    /// Sends a command to the board (ignored once the board has stopped).
    pub fn command(&self, command: BoardCommand) {
        let mut sent = self.sent.lock().unwrap_or_else(PoisonError::into_inner);
        if self.commands.send(command).is_ok() {
            *sent += 1;
        }
    }

    /// A control of the board for the bus routes.
    pub fn control(&self) -> BoardControl {
        BoardControl {
            commands: self.commands.clone(),
            state: self.state.clone(),
            sent: Arc::clone(&self.sent),
        }
    }
    /// Cycle start in remote mode.
    pub fn start_reading(&self) {
        self.command(BoardCommand::StartReading);
    }
    pub fn set_di(&self, di: u8) {
        self.command(BoardCommand::SetDi(di));
    }
    pub fn raise_alarm(&self) {
        self.command(BoardCommand::RaiseAlarm);
    }
    pub fn reset(&self) {
        self.command(BoardCommand::Reset);
    }
    /// Protocol B: punch `bytes` out to the host as given (already encoded), DC2 … DC4.
    pub fn punch(&self, bytes: impl Into<Vec<u8>>) {
        self.command(BoardCommand::Punch(bytes.into()));
    }

    /// The board's events from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<BoardEvent> {
        self.events.subscribe()
    }

    pub fn snapshot(&self) -> BoardSnapshot {
        self.state.borrow().clone()
    }
    pub fn link_state(&self) -> BoardLinkState {
        self.state.borrow().link
    }
    pub fn do_image(&self) -> u8 {
        self.state.borrow().do_image
    }
    pub fn status(&self) -> StatusData {
        self.state.borrow().status
    }
    pub fn programs(&self) -> Vec<ReceivedProgram> {
        self.state.borrow().programs.clone()
    }

    /// Waits until `pred` holds for the board's state (or the board stops), and returns it.
    pub async fn wait_for(&self, mut pred: impl FnMut(&BoardSnapshot) -> bool) -> BoardSnapshot {
        let mut rx = self.state.clone();
        let found = rx
            .wait_for(|s| s.stopped || pred(s))
            .await
            .map(|s| s.clone());
        found.unwrap_or_else(|_| rx.borrow().clone())
    }

    /// Stops the board and returns how its task ended.
    pub async fn shutdown(self) -> Result<(), SimError> {
        let BoardHandle { commands, task, .. } = self;
        drop(commands);
        match task.await {
            Ok(result) => result,
            Err(e) => Err(SimError::Line {
                line: "board task".to_string(),
                source: std::io::Error::other(e),
            }),
        }
    }
}

/// Runs a board over a transport with the link [`Pump`] until the commands channel closes,
/// `shutdown` completes, or the line ends (end of stream: `Ok`) or fails. `report` gets the
/// board, the events of each step and the commands it has taken so far.
pub(crate) async fn run_board<T: Transport>(
    board: FanucBoard,
    line: T,
    mut commands: mpsc::UnboundedReceiver<BoardCommand>,
    mut report: impl FnMut(&FanucBoard, &mut Vec<BoardEvent>, u64),
    shutdown: impl Future<Output = ()>,
) -> Result<(), SimError> {
    let describe = line.describe();
    let mut pump = Pump::new(board, line);
    let mut shutdown = std::pin::pin!(shutdown);
    let mut events = Vec::new();
    let mut taken = 0u64;
    let result = loop {
        while let Some(e) = pump.engine_mut().poll_event() {
            events.push(e);
        }
        report(pump.engine(), &mut events, taken);
        events.clear();
        tokio::select! {
            stepped = pump.step() => match stepped {
                Ok(()) => {}
                Err(PumpError::Closed) => break Ok(()),
                Err(PumpError::Io(source)) => break Err(SimError::Line { line: describe, source }),
            },
            command = commands.recv() => match command {
                Some(c) => {
                    pump.command(c);
                    taken += 1;
                }
                None => break Ok(()),
            },
            () = &mut shutdown => break Ok(()),
        }
    };
    while let Some(e) = pump.engine_mut().poll_event() {
        events.push(e);
    }
    report(pump.engine(), &mut events, taken);
    result
}
