//! The cell's machine links, built from the cell file: for each `[[machines]]` entry a
//! transport (serial port, TCP device server, or a simulated line with a simulated board on its
//! far end), a host engine for its protocol, and a link task (`link::driver`); likewise for
//! each `[[plcs]]` entry, with the FFU120B master and a PLC link task ([`crate::plc::link`]).

use std::time::Duration;

use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::link::driver::{self, LinkHandle};
use crate::link::pump::now;
use crate::plc::{PlcHandle, TagTable};
use crate::sim;
use crate::sim::micrex_handle::MicrexHandle;
use crate::transport::parity::GatewayParity;
use crate::transport::serial::ReopeningSerial;
use crate::transport::sim::SimLine;
use crate::transport::tcp::{TcpOptions, TcpTransport};
use crate::transport::{Transport, TransportError};
use cellgate_core::config::G05Config;
use cellgate_core::config::{CellConfig, MachineConfig, PlcConfig, TransportConfig};
use cellgate_core::engine::parity::{ParityBy, ParityCodec};
use cellgate_core::fanuc::message::Framing;
use cellgate_core::fanuc::protocol_a::ProtocolAHost;
use cellgate_core::fanuc::protocol_b::ProtocolBHost;
use cellgate_core::fuji::master::Master;

/// One machine of the running cell.
pub struct MachineRuntime {
    pub config: MachineConfig,
    pub link: LinkHandle,
    /// The simulated board on the far end of a `sim` transport.
    pub board: Option<sim::BoardHandle>,
    /// The simulated line of a `sim` transport: fault injection and counters.
    pub line: Option<SimLine>,
    running: Running,
}

impl MachineRuntime {
    /// The link as the bus routes take it.
    pub fn bus_link(&self) -> crate::bus::MachineLink {
        crate::bus::MachineLink {
            config: self.config.clone(),
            link: self.link.clone(),
            sim: self.board.as_ref().map(sim::BoardHandle::control),
        }
    }
}

/// One PLC of the running cell.
pub struct PlcRuntime {
    pub config: PlcConfig,
    pub link: PlcHandle,
    /// The simulated MICREX-F on the far end of a `sim` transport.
    pub sim: Option<MicrexHandle>,
    /// The simulated line of a `sim` transport: fault injection and counters.
    pub line: Option<SimLine>,
    running: Running,
}

/// A link's own task, and the token that stops it alone (a reload that removes or changes
/// its entry): machines and PLCs alike.
struct Running {
    stop: CancellationToken,
    task: Option<JoinHandle<()>>,
}

impl Running {
    /// Runs the link task `task` of `what` (`machine`, `PLC`) `name`, saying how it ended.
    fn spawn<E: std::fmt::Display + Send + 'static>(
        what: &'static str,
        name: String,
        stop: CancellationToken,
        task: JoinHandle<Result<(), E>>,
    ) -> Self {
        let task = tokio::spawn(async move {
            match task.await {
                Ok(Ok(())) => tracing::info!(%name, "{what} link stopped"),
                Ok(Err(e)) => tracing::error!(%name, error = %e, "{what} link ended"),
                Err(e) => tracing::error!(%name, error = %e, "{what} link task failed"),
            }
        });
        Running {
            stop,
            task: Some(task),
        }
    }

    /// Stops the link and waits for its task to end.
    async fn stop(&mut self) {
        self.stop.cancel();
        if let Some(task) = self.task.take() {
            let _ = task.await;
        }
    }
}

/// A machine's or a PLC's link, as the cell starts, stops and finds them by name.
trait Device {
    fn name(&self) -> &str;
    fn running(&mut self) -> &mut Running;
    /// Stops the simulated device on the far end of a `sim` transport, if there is one.
    async fn stop_sim(self);
}

impl Device for MachineRuntime {
    fn name(&self) -> &str {
        &self.config.name
    }
    fn running(&mut self) -> &mut Running {
        &mut self.running
    }
    async fn stop_sim(self) {
        if let Some(board) = self.board
            && let Err(e) = board.shutdown().await
        {
            tracing::debug!(machine = %self.config.name, error = %e, "simulated board stopped");
        }
    }
}

impl Device for PlcRuntime {
    fn name(&self) -> &str {
        &self.config.name
    }
    fn running(&mut self) -> &mut Running {
        &mut self.running
    }
    async fn stop_sim(self) {
        if let Some(sim) = self.sim {
            sim.shutdown().await;
        }
    }
}

/// Stops the link of `name` in `devices` (and its simulated device), waits for it to end,
/// and hands back its entry's runtime.
async fn remove<D: Device>(devices: &mut Vec<D>, name: &str) -> Option<D> {
    let i = devices.iter().position(|d| d.name() == name)?;
    let mut d = devices.remove(i);
    d.running().stop().await;
    Some(d)
}

/// Waits for every link task of `devices` to end (after the shutdown token was cancelled),
/// then stops their simulated devices.
async fn join<D: Device>(devices: Vec<D>) {
    let mut devices = devices;
    for d in &mut devices {
        if let Some(task) = d.running().task.take() {
            let _ = task.await;
        }
    }
    for d in devices {
        d.stop_sim().await;
    }
}

/// Why a machine's link could not be started.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CellError {
    #[error("machine {machine}: {source}")]
    Transport {
        machine: String,
        #[source]
        source: TransportError,
    },
    #[error("machine {machine}: {source}")]
    ProtocolA {
        machine: String,
        #[source]
        source: cellgate_core::fanuc::protocol_a::InvalidConfig,
    },
    #[error("machine {machine}: {source}")]
    ProtocolB {
        machine: String,
        #[source]
        source: cellgate_core::fanuc::protocol_b::InvalidConfig,
    },
    #[error("PLC {plc}: {source}")]
    Master {
        plc: String,
        #[source]
        source: cellgate_core::fuji::master::InvalidSettings,
    },
    #[error("PLC {plc}: {source}")]
    Micrex {
        plc: String,
        #[source]
        source: cellgate_core::sim::micrex::MicrexConfigError,
    },
    #[error("machine {machine}: simulated board: {source}")]
    Board {
        machine: String,
        #[source]
        source: crate::sim::SimError,
    },
}

/// The links of a cell, running. Each link stops with the token the cell was started with,
/// or alone when a reload takes it away ([`Cell::remove_machine`], [`Cell::remove_plc`]).
pub struct Cell {
    pub machines: Vec<MachineRuntime>,
    pub plcs: Vec<PlcRuntime>,
    shutdown: CancellationToken,
}

impl Cell {
    /// Starts a link for every machine and PLC of the cell.
    pub async fn start(
        config: &CellConfig,
        shutdown: &CancellationToken,
    ) -> Result<Self, CellError> {
        let mut cell = Cell {
            machines: Vec::new(),
            plcs: Vec::new(),
            shutdown: shutdown.clone(),
        };
        for machine in &config.machines {
            cell.add_machine(machine).await?;
        }
        for plc in &config.plcs {
            cell.add_plc(plc).await?;
        }
        Ok(cell)
    }

    /// Starts the link of `machine` and answers it as the bus routes take it. Its name must
    /// not be running already.
    pub async fn add_machine(
        &mut self,
        machine: &MachineConfig,
    ) -> Result<crate::bus::MachineLink, CellError> {
        let runtime = self.start_machine(machine).await?;
        let link = runtime.bus_link();
        self.machines.push(runtime);
        Ok(link)
    }

    /// Stops the link of machine `name` (and its simulated board) and waits for it to end;
    /// its configuration, if it ran.
    pub async fn remove_machine(&mut self, name: &str) -> Option<MachineConfig> {
        let m = remove(&mut self.machines, name).await?;
        let config = m.config.clone();
        m.stop_sim().await;
        Some(config)
    }

    /// Starts the link of `plc` and answers it as the bus routes take it.
    pub async fn add_plc(&mut self, plc: &PlcConfig) -> Result<crate::bus::PlcLink, CellError> {
        let runtime = self.start_plc(plc).await?;
        let link = crate::bus::PlcLink {
            config: runtime.config.clone(),
            link: runtime.link.clone(),
        };
        self.plcs.push(runtime);
        Ok(link)
    }

    /// Stops the link of PLC `name` (and its simulated MICREX-F) and waits for it to end.
    pub async fn remove_plc(&mut self, name: &str) -> Option<PlcConfig> {
        let p = remove(&mut self.plcs, name).await?;
        let config = p.config.clone();
        p.stop_sim().await;
        Some(config)
    }

    /// Gives PLC `name` the tags (and so poll groups) of `plc`, in its running link.
    pub async fn set_plc_tags(
        &mut self,
        plc: &PlcConfig,
    ) -> Result<crate::bus::PlcLink, crate::plc::PlcLinkError> {
        let Some(p) = self.plcs.iter_mut().find(|p| p.config.name == plc.name) else {
            return Err(crate::plc::PlcLinkError::NotRunning {
                plc: plc.name.clone(),
            });
        };
        p.link.set_tags(TagTable::new(&plc.name, &plc.tags)).await?;
        p.config.tags = plc.tags.clone();
        Ok(crate::bus::PlcLink {
            config: p.config.clone(),
            link: p.link.clone(),
        })
    }

    /// Starts the link of a `[[plcs]]` entry; a `sim` transport gets a simulated MICREX-F
    /// with every station of the entry on its far end.
    async fn start_plc(&mut self, plc: &PlcConfig) -> Result<PlcRuntime, CellError> {
        let stop = self.shutdown.child_token();
        let name = plc.name.clone();
        let master = Master::new(plc.master_settings()).map_err(|source| CellError::Master {
            plc: name.clone(),
            source,
        })?;
        let mut micrex = None;
        let mut sim_line = None;
        let transport: Box<dyn Transport> = match &plc.transport {
            TransportConfig::Sim { line } => {
                let (host, device, control) = crate::transport::sim::line(*line);
                let handle = MicrexHandle::spawn(
                    cellgate_core::sim::micrex::MicrexConfig::for_plc(plc),
                    plc.sim.ticks.clone(),
                    device,
                )
                .map_err(|source| CellError::Micrex {
                    plc: name.clone(),
                    source,
                })?;
                micrex = Some(handle);
                sim_line = Some(control);
                Box::new(host)
            }
            other => open_transport(&name, other, TransportConfig::DEFAULT_TCP_WINDOW).await?,
        };
        let tags = TagTable::new(&name, &plc.tags);
        let (link, task) =
            crate::plc::link::spawn(name.clone(), master, tags, transport, stop.clone());
        Ok(PlcRuntime {
            config: plc.clone(),
            link,
            sim: micrex,
            line: sim_line,
            running: Running::spawn("PLC", name, stop, task),
        })
    }

    pub fn plc(&self, name: &str) -> Option<&PlcRuntime> {
        self.plcs.iter().find(|p| p.config.name == name)
    }

    /// The PLC links as the bus routes take them.
    pub fn plc_links(&self) -> Vec<crate::bus::PlcLink> {
        self.plcs
            .iter()
            .map(|p| crate::bus::PlcLink {
                config: p.config.clone(),
                link: p.link.clone(),
            })
            .collect()
    }

    async fn start_machine(
        &mut self,
        machine: &MachineConfig,
    ) -> Result<MachineRuntime, CellError> {
        let stop = self.shutdown.child_token();
        let name = machine.name.clone();
        let framing = Framing::new(machine.code, machine.effective_end_code());
        let mut board = None;
        let mut sim_line = None;
        let transport: Box<dyn Transport> = match &machine.transport {
            TransportConfig::Sim { line } => {
                let (host, device, control) = crate::transport::sim::line(*line);
                let handle =
                    sim::BoardHandle::spawn(machine_board_config(machine, framing), device)
                        .map_err(|source| CellError::Board {
                            machine: name.clone(),
                            source,
                        })?;
                board = Some(handle);
                sim_line = Some(control);
                Box::new(host)
            }
            other => open_transport(&name, other, machine.tcp_window()).await?,
        };
        let (link, task) = if let Some(b) = machine.protocol_b_config() {
            let engine = ProtocolBHost::new(b, now()).map_err(|source| CellError::ProtocolB {
                machine: name.clone(),
                source,
            })?;
            driver::spawn(name.clone(), engine, transport, stop.clone())
        } else {
            let a = machine.protocol_a_config().unwrap_or_default();
            let engine = ProtocolAHost::new(a, now()).map_err(|source| CellError::ProtocolA {
                machine: name.clone(),
                source,
            })?;
            driver::spawn(name.clone(), engine, transport, stop.clone())
        };
        Ok(MachineRuntime {
            config: machine.clone(),
            link,
            board,
            line: sim_line,
            running: Running::spawn("machine", name, stop, task),
        })
    }

    /// The links as the bus routes take them.
    pub fn machine_links(&self) -> Vec<crate::bus::MachineLink> {
        self.machines.iter().map(MachineRuntime::bus_link).collect()
    }

    pub fn machine(&self, name: &str) -> Option<&MachineRuntime> {
        self.machines.iter().find(|m| m.config.name == name)
    }

    /// Waits for every link task to end (after the shutdown token was cancelled), then stops
    /// the simulated boards.
    pub async fn join(self) {
        join(self.machines).await;
        join(self.plcs).await;
    }
}

/// Opens a serial port or connects to a device server (not a `sim` transport, whose far end
/// the caller builds). `default_window` is the in-flight bound of a `tcp` transport whose file
/// sets none (the machine's protocol's, or the PLC's).
pub async fn open_transport(
    name: &str,
    config: &TransportConfig,
    default_window: u32,
) -> Result<Box<dyn Transport>, CellError> {
    let err = |source| CellError::Transport {
        machine: name.to_string(),
        source,
    };
    let transport: Box<dyn Transport> = match config {
        TransportConfig::Serial {
            path,
            reconnect_min_ms,
            reconnect_max_ms,
            ..
        } => Box::new(
            // With the parity made by the gateway the port runs 8 data bits, no parity.
            ReopeningSerial::open(
                path.clone(),
                config.port_line(),
                Duration::from_millis(*reconnect_min_ms),
                Duration::from_millis(*reconnect_max_ms),
            )
            .map_err(err)?,
        ),
        TransportConfig::Tcp {
            address,
            line,
            reconnect_min_ms,
            reconnect_max_ms,
            ..
        } => {
            let opts = TcpOptions {
                window: config.window_or(default_window) as usize,
                backoff_min: Duration::from_millis(*reconnect_min_ms),
                backoff_max: Duration::from_millis(*reconnect_max_ms),
                ..TcpOptions::default()
            };
            Box::new(
                TcpTransport::connect(address.clone(), *line, opts)
                    .await
                    .map_err(err)?,
            )
        }
        TransportConfig::Sim { line } => Box::new(crate::transport::sim::line(*line).0),
    };
    // A port that passes whole 8-bit frames: the gateway makes and checks the parity bit
    // (FFU120B §4-3 items 5-6; the configuration refuses it without 7 data bits and parity).
    Ok(
        match ParityCodec::new(config.line().parity)
            .filter(|_| config.parity_by() == ParityBy::Gateway)
        {
            Some(codec) => Box::new(GatewayParity::new(transport, codec)),
            None => transport,
        },
    )
}

/// The simulated board for a `sim` machine. It powers on with the machine's configured §4.5
/// values rather than the factory ones: the host sets them by SET at the first SAT anyway, and
/// a short Tp then applies from the first poll. Its CNC starts reading by itself, so that
/// queued jobs are delivered without an operator.
fn machine_board_config(
    machine: &MachineConfig,
    framing: Framing,
) -> cellgate_core::sim::fanuc_board::BoardConfig {
    let sim = machine.board_sim();
    cellgate_core::sim::fanuc_board::BoardConfig {
        protocol: machine.protocol,
        framing,
        params: machine.params(),
        buffer_size: sim.buffer_size as usize,
        consume_rate: sim.consume_rate,
        autostart: true,
        notify_alarm_reset: machine.effective_notify_alarm_reset(),
        g05: machine.g05.as_ref().map(G05Config::format),
        ..cellgate_core::sim::fanuc_board::BoardConfig::default()
    }
}
