//! Runs a simulated FFU120B + MICREX-F ([`Micrex`]) over any transport in a tokio task: what
//! an embedded cell (`transport.kind = "sim"`), `cellgate sim fuji` and tests use.
//!
//! Besides the module's own behaviour it can change words by itself ([`SimTick`]): the
//! stand-in for a sequence program, so that tags of the embedded cell move (a part counter,
//! a door). This is the simulator's, not the MICREX-F's.

use std::collections::BTreeMap;
use std::time::Duration;

use tokio::sync::{broadcast, mpsc, oneshot};
use tokio::task::JoinHandle;
use tokio::time::Instant;

use crate::link::pump::{Pump, PumpError};
use crate::transport::Transport;
use cellgate_core::config::SimTick;
use cellgate_core::engine::Engine;
use cellgate_core::fuji::command::Module;
use cellgate_core::sim::micrex::{
    Micrex, MicrexCommand, MicrexConfig, MicrexConfigError, MicrexEvent,
};

enum Control {
    Command(MicrexCommand),
    Words {
        station: u8,
        module: Module,
        address: u16,
        count: usize,
        reply: oneshot::Sender<Option<Vec<u32>>>,
    },
}

/// A running simulated module.
pub struct MicrexHandle {
    commands: mpsc::UnboundedSender<Control>,
    events: broadcast::Sender<MicrexEvent>,
    task: JoinHandle<Result<(), PumpError>>,
}

impl MicrexHandle {
    /// Starts the module on `line` (the device end of a line).
    pub fn spawn<T: Transport + 'static>(
        config: MicrexConfig,
        ticks: Vec<SimTick>,
        line: T,
    ) -> Result<MicrexHandle, MicrexConfigError> {
        Self::spawn_subscribed(config, ticks, line).map(|(handle, _)| handle)
    }

    /// [`MicrexHandle::spawn`], with a subscription to its events made before the module
    /// starts, so that none is missed.
    pub fn spawn_subscribed<T: Transport + 'static>(
        config: MicrexConfig,
        ticks: Vec<SimTick>,
        line: T,
    ) -> Result<(MicrexHandle, broadcast::Receiver<MicrexEvent>), MicrexConfigError> {
        let engine = Micrex::new(config)?;
        let (cmd_tx, mut cmd_rx) = mpsc::unbounded_channel();
        let (events, first) = broadcast::channel(4096);
        let ev = events.clone();
        let task = tokio::spawn(async move {
            let mut pump = Pump::new(engine, line);
            let start = Instant::now();
            let mut due: Vec<Instant> = ticks
                .iter()
                .map(|t| start + Duration::from_millis(u64::from(t.every_ms)))
                .collect();
            loop {
                while let Some(e) = pump.engine_mut().poll_event() {
                    let _ = ev.send(e);
                }
                let next = due.iter().min().copied();
                tokio::select! {
                    biased;
                    c = cmd_rx.recv() => match c {
                        None => return Ok(()),
                        Some(Control::Command(c)) => pump.command(c),
                        Some(Control::Words { station, module, address, count, reply }) => {
                            let _ = reply.send(pump.engine().words(station, module, address, count));
                        }
                    },
                    () = async { match next {
                        Some(t) => tokio::time::sleep_until(t).await,
                        None => std::future::pending().await,
                    } } => {
                        let now = Instant::now();
                        for (t, d) in ticks.iter().zip(due.iter_mut()) {
                            if *d <= now {
                                *d += Duration::from_millis(u64::from(t.every_ms));
                                tick(&mut pump, t);
                            }
                        }
                    }
                    r = pump.step() => r?,
                }
            }
        });
        Ok((
            MicrexHandle {
                commands: cmd_tx,
                events,
                task,
            },
            first,
        ))
    }

    /// Sends a command to the module (ignored once it has stopped).
    pub fn command(&self, command: MicrexCommand) {
        let _ = self.commands.send(Control::Command(command));
    }

    /// Words of a station's module as the PLC holds them now.
    pub async fn words(
        &self,
        station: u8,
        module: Module,
        address: u16,
        count: usize,
    ) -> Option<Vec<u32>> {
        let (tx, rx) = oneshot::channel();
        self.commands
            .send(Control::Words {
                station,
                module,
                address,
                count,
                reply: tx,
            })
            .ok()?;
        rx.await.ok().flatten()
    }

    pub fn subscribe(&self) -> broadcast::Receiver<MicrexEvent> {
        self.events.subscribe()
    }

    /// Waits until the module's line ends (the transport closed or failed), keeping it
    /// running until then.
    pub async fn finished(self) -> Result<(), PumpError> {
        let MicrexHandle { commands, task, .. } = self;
        let result = task.await;
        drop(commands);
        result.unwrap_or(Ok(()))
    }

    /// Stops the module and waits for its task.
    pub async fn shutdown(self) {
        drop(self.commands);
        let _ = self.task.await;
    }
}

/// One tick of the simulated sequence program: add and flip bits, wrapping at the word size.
fn tick<T: Transport>(pump: &mut Pump<Micrex, T>, t: &SimTick) {
    let Some(old) = pump
        .engine()
        .words(t.station, t.module, t.address, 1)
        .and_then(|w| w.first().copied())
    else {
        return;
    };
    let mask: u32 = if t.module.word_bytes() == 2 {
        0xFFFF
    } else {
        u32::MAX
    };
    let new = (old.wrapping_add(t.add) ^ t.xor) & mask;
    pump.command(MicrexCommand::SetWords {
        station: t.station,
        module: t.module,
        address: t.address,
        words: vec![new],
    });
}

/// Words per station the simulator starts with, for tests that preset memory.
pub type Preset = BTreeMap<(u8, Module, u16), u32>;
