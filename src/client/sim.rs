//! The client side of the simulated machines' controls: `cellgate sim state|di|alarm|reset|
//! read|hold|auto|punch`, over the keys of `crate::bus::route_sim`.

use std::path::PathBuf;

use clap::{Args, Subcommand, ValueEnum};
use serde_json::{Value, json};

use super::cli::{ClientCommand, ConnectArgs, Io};
use super::{Client, ClientError, parse_byte, render};
use crate::bus::keys::SimLeaf;
use crate::bus::payload::{BusMessage, encoding};
use cellgate_core::pb;

/// How long `sim alarm` and `sim reset` wait for the gateway to see what the CNC did: a
/// Protocol A board tells its alarm at its next SAT, which comes at least every 10 s
/// (§4.4.2), Protocol B at once (§6.1.2).
const SEEN_WITHIN: std::time::Duration = std::time::Duration::from_secs(15);

fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Waits until the gateway holds `machine` in alarm or has recorded its alarm since `asked`
/// (`kind` an alarm), or holds it out of alarm (`kind` a reset), so that the command after this one meets the state the operator made (a
/// program submitted at once otherwise reaches a board the gateway still thinks is
/// ready). Says on stderr when it does not within [`SEEN_WITHIN`].
async fn seen_by_gateway(
    client: &Client,
    io: &mut Io<'_>,
    machine: &str,
    asked: u64,
    kind: pb::AlarmKind,
) {
    let until = tokio::time::Instant::now() + SEEN_WITHIN;
    loop {
        let seen = client.status(Some(machine)).await.ok().is_some_and(|all| {
            all.iter().any(|s| match kind {
                pb::AlarmKind::CncReset => !render::in_alarm(s),
                _ => {
                    render::in_alarm(s)
                        || s.last_alarm
                            .as_ref()
                            .is_some_and(|a| a.kind() == kind && a.unix_ms + 1_000 >= asked)
                }
            })
        });
        if seen {
            return;
        }
        if tokio::time::Instant::now() >= until {
            let what = if kind == pb::AlarmKind::CncAlarm {
                "alarm"
            } else {
                "reset"
            };
            let _ = writeln!(
                io.err,
                "{machine}: the gateway has not seen the {what} yet; it will at the board's next status message"
            );
            return;
        }
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    }
}

impl Client {
    /// Gives a simulated machine a control (or, for [`SimLeaf::State`], reads its state) and
    /// returns its state once the simulated board took it.
    pub async fn sim_control<M: BusMessage>(
        &self,
        machine: &str,
        leaf: SimLeaf,
        payload: Option<&M>,
    ) -> Result<pb::SimState, ClientError> {
        Self::machine_arg(machine)?;
        let key = self.keys().sim(machine, leaf);
        let payload = payload.map(|m| (m.encode_to_vec(), encoding::<M>()));
        self.get_one_pub(&format!("sim {} of {machine}", leaf.chunk()), &key, payload)
            .await
    }

    /// Has a simulated CNC punch `program` out and waits, up to the ordinary time-out, for
    /// the gateway to publish what it received (its `PunchedProgram`, with the name it was
    /// stored under): the machine's state once the board took the punch (part way through
    /// it), and the punched program, `None` if it did not come in time.
    pub async fn sim_punch(
        &self,
        machine: &str,
        program: Vec<u8>,
    ) -> Result<(pb::SimState, Option<pb::PunchedProgram>), ClientError> {
        Self::machine_arg(machine)?;
        let key = self
            .keys()
            .leaf(machine, crate::bus::keys::MachineLeaf::Punch);
        // Subscribed before the punch starts, so that its end is not missed.
        let punched = self.subscribe(&key).await?;
        let p = pb::SimPunch { program };
        let state = self.sim_control(machine, SimLeaf::Punch, Some(&p)).await?;
        let arrived = tokio::time::timeout(self.timeout, async {
            while let Ok(sample) = punched.recv_async().await {
                let bytes = sample.payload().to_bytes();
                if let Ok(p) =
                    super::decode::<pb::PunchedProgram>(&key, &key, &bytes, sample.encoding())
                {
                    return Some(p);
                }
            }
            None
        })
        .await
        .ok()
        .flatten();
        let _ = punched.undeclare().await;
        Ok((state, arrived))
    }

    /// The state of every simulated machine of the cell, sorted by name.
    pub async fn sim_states(&self) -> Result<Vec<pb::SimState>, ClientError> {
        let key = self.keys().sim("*", SimLeaf::State);
        let mut all: Vec<pb::SimState> = self
            .get_all_pub("simulated machines", &key, None)
            .await?
            .into_iter()
            .map(|(_, s)| s)
            .collect();
        all.sort_by(|a, b| a.machine.cmp(&b.machine));
        Ok(all)
    }
}

/// A simulated machine's state in one line.
pub fn state_text(s: &pb::SimState) -> String {
    let mut t = format!(
        "{} (simulated, board {}): CNC {}, {}, autostart {}; DI {}, DO {}; {} buffered; {} \
         program(s) read",
        s.machine,
        s.board_link,
        if s.reading { "reading" } else { "not reading" },
        if s.alarm { "IN ALARM" } else { "no alarm" },
        if s.autostart { "on" } else { "off" },
        render::byte_image(s.di),
        render::byte_image(s.do_image),
        render::bytes(s.buffered),
        s.programs_read,
    );
    if !s.last_program.is_empty() {
        t.push_str(&format!(", the last {}", s.last_program));
    }
    if s.punched_bytes > 0 {
        t.push_str(&format!(
            "; {} punched since the gateway started",
            render::bytes(s.punched_bytes)
        ));
    }
    t
}

/// What a punch of a `size`-byte file came to: the program the gateway received (its size,
/// and where it was stored), or that nothing came.
pub fn punch_text(machine: &str, size: u64, punched: Option<&pb::PunchedProgram>) -> String {
    let Some(p) = punched else {
        return format!(
            "{machine}: punching {} (the board took it), but the gateway published no punched \
             program within the time-out; `cellgate watch {machine}` shows it when it comes",
            render::bytes(size)
        );
    };
    let name = if p.o_number.is_empty() {
        "a program".to_string()
    } else {
        p.o_number.clone()
    };
    let received = p.program.len() as u64;
    let mut t = format!(
        "{machine} punched {name}: {} received",
        render::bytes(received)
    );
    if received != size {
        t.push_str(&format!(
            " of the file's {} (a program is punched from its first % through its EOR %)",
            render::bytes(size)
        ));
    }
    if p.damaged {
        t.push_str(&format!(
            ", DAMAGED ({}): not stored, punch it again",
            p.damage
        ));
    } else if !p.library_name.is_empty() {
        t.push_str(&format!(", stored in the library as {}", p.library_name));
    } else if let Some(r) = &p.request {
        t.push_str(&format!(", a remote request for {}", r.program));
    }
    t
}

/// A simulated machine's state as JSON.
pub fn state_json(s: &pb::SimState) -> Value {
    json!({
        "machine": s.machine, "reading": s.reading, "alarm": s.alarm,
        "autostart": s.autostart, "di": s.di, "do_image": s.do_image, "buffered": s.buffered,
        "programs_read": s.programs_read, "last_program": s.last_program,
        "punched_bytes": s.punched_bytes, "board_link": s.board_link,
    })
}

/// `on` or `off`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum OnOff {
    On,
    Off,
}

/// The controls of the simulated machines (`kind = "sim"`) of a running cell: what an
/// operator does at the CNC.
/// A simulated machine to act on, and how its state is printed after.
#[derive(Debug, Clone, Args)]
pub struct SimMachine {
    #[command(flatten)]
    connect: ConnectArgs,
    /// The machine.
    #[arg(value_name = "MACHINE")]
    machine: String,
    /// Print the machine's state as JSON instead of text.
    #[arg(long)]
    json: bool,
}

impl SimMachine {
    /// Sends `leaf` with no payload; the machine's state after, and whether to print JSON.
    async fn control(
        &self,
        client: &Client,
        leaf: SimLeaf,
    ) -> Result<(pb::SimState, bool), ClientError> {
        let none: Option<&pb::SimState> = None;
        Ok((
            client.sim_control(&self.machine, leaf, none).await?,
            self.json,
        ))
    }
}

#[derive(Debug, Clone, Subcommand)]
pub enum SimControl {
    /// A simulated machine's state (default: every simulated machine of the cell): reading,
    /// alarm, autostart, DI, DO, buffer, programs read.
    State {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The machine; default every simulated machine.
        #[arg(value_name = "MACHINE")]
        machine: Option<String>,
        /// Print JSON (an array of machine, reading, alarm, autostart, di, do_image, ...).
        #[arg(long)]
        json: bool,
    },
    /// Set the DI image a simulated board reports (Protocol A family); read it with
    /// `cellgate di MACHINE`.
    Di {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The machine.
        #[arg(value_name = "MACHINE")]
        machine: String,
        /// The DI bits: 0x.. hex, 0b.. binary or decimal, 0..=255.
        #[arg(value_name = "VALUE", value_parser = parse_byte)]
        value: u8,
        /// Print the machine's state as JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Raise a CNC alarm on a simulated machine; returns once the gateway has seen it (a
    /// Protocol A board tells it at its next SAT). With autostart on, its operator resets it
    /// once the host has seen it; with `sim auto MACHINE off` it stays until `sim reset`.
    Alarm(SimMachine),
    /// Reset a simulated CNC: its alarm cleared, its buffer emptied (a job being sent is
    /// cancelled by the reset); returns once the gateway no longer holds it in alarm.
    Reset(SimMachine),
    /// Cycle start: the simulated CNC reads from its buffer, so a waiting job starts
    /// (refused while the CNC is in alarm).
    Read(SimMachine),
    /// Feed hold: the simulated CNC stops reading; its buffer is kept.
    Hold(SimMachine),
    /// Autostart on or off. On (the default cell's machines start so), the operator starts
    /// every read and resets every alarm by himself; off, only `sim read` and `sim reset` do.
    Auto {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The machine.
        #[arg(value_name = "MACHINE")]
        machine: String,
        /// on or off.
        #[arg(value_enum, value_name = "ON|OFF")]
        on: OnOff,
        /// Print the machine's state as JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Make a simulated CNC punch a program out to the gateway (Protocol B family): it
    /// appears on the machine's punch key and, by default, in the program library.
    Punch {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The machine.
        #[arg(value_name = "MACHINE")]
        machine: String,
        /// The program: plain text from the tape-start % through the EOR % (at most 64 KiB);
        /// the gateway encodes it in the machine's code.
        #[arg(value_name = "FILE")]
        file: PathBuf,
        /// Print the machine's state as JSON instead of text.
        #[arg(long)]
        json: bool,
    },
}

impl ClientCommand for SimControl {
    fn connect_args(&self) -> &ConnectArgs {
        match self {
            SimControl::State { connect, .. }
            | SimControl::Di { connect, .. }
            | SimControl::Auto { connect, .. }
            | SimControl::Punch { connect, .. } => connect,
            SimControl::Alarm(m)
            | SimControl::Reset(m)
            | SimControl::Read(m)
            | SimControl::Hold(m) => &m.connect,
        }
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        let none: Option<&pb::SimState> = None;
        let (state, json) = match self {
            SimControl::State {
                machine: None,
                json,
                ..
            } => {
                let all = client.sim_states().await?;
                if *json {
                    let v: Vec<Value> = all.iter().map(state_json).collect();
                    let _ = writeln!(io.out, "{}", Value::Array(v));
                } else if all.is_empty() {
                    let _ = writeln!(io.out, "no simulated machine answered");
                } else {
                    for s in &all {
                        let _ = writeln!(io.out, "{}", state_text(s));
                    }
                }
                return Ok(0);
            }
            SimControl::State {
                machine: Some(m),
                json,
                ..
            } => (client.sim_control(m, SimLeaf::State, none).await?, *json),
            SimControl::Di {
                machine,
                value,
                json,
                ..
            } => {
                let di = pb::SimDi {
                    value: u32::from(*value),
                };
                (
                    client.sim_control(machine, SimLeaf::Di, Some(&di)).await?,
                    *json,
                )
            }
            SimControl::Alarm(m) => {
                let asked = now_ms();
                let done = m.control(client, SimLeaf::Alarm).await?;
                seen_by_gateway(client, io, &m.machine, asked, pb::AlarmKind::CncAlarm).await;
                done
            }
            SimControl::Reset(m) => {
                let asked = now_ms();
                let done = m.control(client, SimLeaf::Reset).await?;
                seen_by_gateway(client, io, &m.machine, asked, pb::AlarmKind::CncReset).await;
                done
            }
            SimControl::Read(m) => m.control(client, SimLeaf::Read).await?,
            SimControl::Hold(m) => m.control(client, SimLeaf::Hold).await?,
            SimControl::Auto {
                machine, on, json, ..
            } => {
                let a = pb::SimAutostart {
                    on: *on == OnOff::On,
                };
                let s = client
                    .sim_control(machine, SimLeaf::Autostart, Some(&a))
                    .await?;
                (s, *json)
            }
            SimControl::Punch {
                machine,
                file,
                json,
                ..
            } => {
                let program = super::read_file(file).await?;
                let size = program.len() as u64;
                let (state, punched) = client.sim_punch(machine, program).await?;
                if *json {
                    let mut v = state_json(&state);
                    v["punched"] = punched.as_ref().map_or(Value::Null, render::punched_json);
                    let _ = writeln!(io.out, "{v}");
                } else {
                    let _ = writeln!(io.out, "{}", punch_text(machine, size, punched.as_ref()));
                }
                return Ok(if punched.is_some_and(|p| !p.damaged) {
                    0
                } else {
                    1
                });
            }
        };
        if json {
            let _ = writeln!(io.out, "{}", state_json(&state));
        } else {
            let _ = writeln!(io.out, "{}", state_text(&state));
        }
        Ok(0)
    }
}
