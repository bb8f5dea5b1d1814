//! The cell in OPC UA (OPC 40501-1 Machine Tools; docs/opcua.md): what each node of a
//! machine tool and of a PLC should show, from the bus contract's messages. Sans-IO: the
//! gateway's `opcua` room builds the address space, sets the values given here and sends the
//! events; what a value means is decided here, once, beside the MTConnect mapping it shares
//! its view of a machine with ([`crate::mtconnect::mapping::MachineView`]).

use std::collections::BTreeMap;

use crate::mtconnect::Update;
use crate::mtconnect::buffer::Cond;
use crate::mtconnect::desc::CellDesc;
use crate::mtconnect::mapping::MachineView;
use crate::{history, pb};

/// The namespace of OPC 40501-1.
pub const MACHINE_TOOL_NS: &str = "http://opcfoundation.org/UA/MachineTool/";
/// The namespace of OPC 40001-1 (Machinery).
pub const MACHINERY_NS: &str = "http://opcfoundation.org/UA/Machinery/";
/// The namespace of OPC 10000-100 (Devices).
pub const DI_NS: &str = "http://opcfoundation.org/UA/DI/";
/// The namespace of OPC 10000-200 (Industrial Automation).
pub const IA_NS: &str = "http://opcfoundation.org/UA/IA/";

/// The UNECE Recommendation 20 unit of an MTConnect unit (a PLC tag's `mtconnect` units), as
/// OPC UA's `EUInformation` names it (Part 8 §5.6.3): its common code packed in an `Int32`,
/// its symbol and its name. `None` for a unit without one here (the tag then has none).
pub fn engineering_unit(mtconnect: &str) -> Option<(i32, &'static str, &'static str)> {
    let (code, symbol, name) = match mtconnect {
        "AMPERE" => ("AMP", "A", "ampere"),
        "CELSIUS" => ("CEL", "°C", "degree Celsius"),
        "DECIBEL" => ("2N", "dB", "decibel"),
        "DEGREE" => ("DD", "°", "degree"),
        "HERTZ" => ("HTZ", "Hz", "hertz"),
        "JOULE" => ("JOU", "J", "joule"),
        "KILOGRAM" => ("KGM", "kg", "kilogram"),
        "LITER" => ("LTR", "l", "litre"),
        "LITER/SECOND" => ("G51", "l/s", "litre per second"),
        "MILLIGRAM" => ("MGM", "mg", "milligram"),
        "MILLILITER" => ("MLT", "ml", "millilitre"),
        "MILLIMETER" => ("MMT", "mm", "millimetre"),
        "MILLIMETER/SECOND" => ("C16", "mm/s", "millimetre per second"),
        "NEWTON" => ("NEW", "N", "newton"),
        "NEWTON_METER" => ("NU", "N·m", "newton metre"),
        "OHM" => ("OHM", "Ω", "ohm"),
        "PASCAL" => ("PAL", "Pa", "pascal"),
        "PASCAL_SECOND" => ("C65", "Pa·s", "pascal second"),
        "PERCENT" => ("P1", "%", "percent"),
        "REVOLUTION/MINUTE" => ("RPM", "r/min", "revolutions per minute"),
        "SECOND" => ("SEC", "s", "second"),
        "VOLT" => ("VLT", "V", "volt"),
        "VOLT_AMPERE" => ("D46", "V·A", "volt - ampere"),
        "WATT" => ("WTT", "W", "watt"),
        "WATT_SECOND" => ("J55", "W·s", "watt second"),
        _ => return None,
    };
    // Part 8 §5.6.3: each character of the code in a byte, the first the highest.
    let id = code.bytes().fold(0i32, |id, b| (id << 8) | i32::from(b));
    Some((id, symbol, name))
}

/// The namespace of the UNECE units in `EUInformation`.
pub const UNECE_UNITS_NS: &str = "http://www.opcfoundation.org/UA/units/un/cefact";

/// `ProductionStateMachineType`'s states (OPC 40501-1 §8.4.8): what the program being sent
/// is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProgramState {
    /// No program ran since the server (or a CNC reset) started.
    Initializing,
    /// The program is being sent and the CNC takes it.
    Running,
    /// The remote buffer acknowledged the whole program (the job completed).
    Ended,
    /// The job is still open, but the CNC is in alarm or the line is cut.
    Interrupted,
    /// The job failed or was cancelled.
    Aborted,
}

impl ProgramState {
    /// The state's name, as the standard writes it (CurrentState's text).
    pub fn name(self) -> &'static str {
        match self {
            ProgramState::Initializing => "Initializing",
            ProgramState::Running => "Running",
            ProgramState::Ended => "Ended",
            ProgramState::Interrupted => "Interrupted",
            ProgramState::Aborted => "Aborted",
        }
    }

    /// The state object of `ProductionStateMachineType` in the MachineTool namespace
    /// (CurrentState's `Id`).
    pub fn state_node(self) -> u32 {
        match self {
            ProgramState::Initializing => 135,
            ProgramState::Running => 138,
            ProgramState::Ended => 140,
            ProgramState::Interrupted => 139,
            ProgramState::Aborted => 141,
        }
    }

    /// The state's `StateNumber` in the NodeSet.
    pub fn number(self) -> u32 {
        match self {
            ProgramState::Initializing => 0,
            ProgramState::Running => 1,
            ProgramState::Ended => 2,
            ProgramState::Interrupted => 3,
            ProgramState::Aborted => 4,
        }
    }
}

/// `ChannelState` (OPC 40501-1 §12.1), its enumeration values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChannelState {
    /// The CNC runs a program (it reads blocks from the remote buffer).
    Active = 0,
    /// The CNC is in alarm, or the program was cut short: it can be restarted.
    Interrupted = 1,
    /// No program runs.
    Reset = 2,
}

/// `MachineOperationMode` (OPC 40501-1 §12.5), the values the remote buffer can tell.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OperationMode {
    /// The CNC reads a program from the remote buffer: DNC operation is automatic operation.
    Automatic = 1,
    /// Anything else: the remote buffer does not tell the CNC's mode unless it reads.
    Other = 5,
}

/// What a machine tool's nodes show.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MachineShows {
    /// Whether the gateway is there and the link up: without, values are Bad (no
    /// communication) but for ActiveProgram, which keeps the last known program.
    pub reachable: bool,
    /// ActiveProgram.Name: the library name of the program sent, or the inline job's name.
    pub program: String,
    /// ActiveProgram.State.
    pub state: ProgramState,
    /// Channel's ChannelState.
    pub channel: ChannelState,
    /// Monitoring/MachineTool/OperationMode; `Other` when the line cannot tell.
    pub mode: OperationMode,
    /// Monitoring/MachineTool/OperationCounters/PartsProducedInLifetime, where the cell
    /// counts the machine's parts (`part_counter`).
    pub parts: Option<i64>,
}

/// A CNC alarm or a link fault that began: an event of the machine's Notification/Messages.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Alert {
    /// The SR number, or cellgate's own code (docs/mtconnect.md lists them).
    pub code: String,
    /// What happened, in words.
    pub message: String,
    /// OPC UA severity, 1–1000 (Part 5 §6.4.2 bands): a CNC alarm 800 (MediumHigh: the
    /// program stopped), a link fault 600 (Medium: nothing reaches the CNC), a G05 stream
    /// starving 400 (MediumLow: the CNC waits).
    pub severity: u16,
}

/// What changed, for the server to show.
#[derive(Debug, Clone, PartialEq)]
pub enum Out {
    /// A machine's nodes.
    Machine {
        /// The machine's cell.
        cell: String,
        /// The machine's name.
        machine: String,
        /// What its nodes show.
        shows: MachineShows,
    },
    /// A PLC: whether it answers, and its tags' values (`None`: not known now).
    Plc {
        /// The PLC's cell.
        cell: String,
        /// The PLC's name.
        plc: String,
        /// Whether a station answers and the gateway is there.
        up: bool,
        /// Its named tags, in the cell file's order.
        tags: Vec<(String, Option<f64>)>,
    },
    /// An alert began on a machine.
    Alert {
        /// The machine's cell.
        cell: String,
        /// The machine's name.
        machine: String,
        /// What began.
        alert: Alert,
    },
}

#[derive(Debug, Default)]
struct Machine {
    view: MachineView,
    /// The codes of the conditions active when last looked at: an alert is sent when one
    /// begins, not again while it lasts.
    active: Vec<String>,
    shown: Option<MachineShows>,
}

#[derive(Debug, Default)]
struct Plc {
    gateway_up: bool,
    stations_up: bool,
    tags: BTreeMap<String, Option<f64>>,
}

#[derive(Debug)]
struct Cell {
    desc: CellDesc,
    machines: BTreeMap<String, Machine>,
    plcs: BTreeMap<String, Plc>,
}

/// Every cell the server shows, as it was told.
#[derive(Debug, Default)]
pub struct Model {
    cells: BTreeMap<String, Cell>,
}

/// The severities of the alerts (see [`Alert::severity`]).
const SEVERITY_CNC: u16 = 800;
const SEVERITY_LINK: u16 = 600;
const SEVERITY_G05: u16 = 400;

impl Model {
    /// An empty model.
    pub fn new() -> Model {
        Model::default()
    }

    /// The description of `cell`, if it is shown.
    pub fn desc(&self, cell: &str) -> Option<&CellDesc> {
        self.cells.get(cell).map(|c| &c.desc)
    }

    /// Whether `cell` is shown.
    pub fn has_cell(&self, cell: &str) -> bool {
        self.cells.contains_key(cell)
    }

    /// The cells shown.
    pub fn cells(&self) -> impl Iterator<Item = &CellDesc> {
        self.cells.values().map(|c| &c.desc)
    }

    /// Shows `desc` (a new cell, or one whose machines or PLCs changed): what each machine
    /// and PLC of it shows now. Machines and PLCs kept keep what they were told.
    pub fn set_cell(&mut self, desc: &CellDesc) -> Vec<Out> {
        let cell = self.cells.entry(desc.cell.clone()).or_insert_with(|| Cell {
            desc: desc.clone(),
            machines: BTreeMap::new(),
            plcs: BTreeMap::new(),
        });
        cell.desc = desc.clone();
        let gateway_up = cell
            .machines
            .values()
            .next()
            .map(|m| m.view.gateway_up)
            .or_else(|| cell.plcs.values().next().map(|p| p.gateway_up))
            .unwrap_or(false);
        cell.machines
            .retain(|name, _| desc.machines.iter().any(|m| &m.name == name));
        cell.plcs
            .retain(|name, _| desc.plcs.iter().any(|p| &p.name == name));
        for m in &desc.machines {
            cell.machines.entry(m.name.clone()).or_insert_with(|| {
                let mut machine = Machine::default();
                machine.view.gateway_up = gateway_up;
                machine
            });
        }
        for p in &desc.plcs {
            cell.plcs.entry(p.name.clone()).or_insert_with(|| Plc {
                gateway_up,
                ..Plc::default()
            });
        }
        let mut out = Vec::new();
        let names: Vec<String> = cell.machines.keys().cloned().collect();
        for m in names {
            refresh_machine(cell, &m, &mut out, true);
        }
        let names: Vec<String> = cell.plcs.keys().cloned().collect();
        for p in names {
            plc_out(cell, &p, &mut out);
        }
        out
    }

    /// What `update` of `cell` changes.
    pub fn update(&mut self, cell_name: &str, update: Update) -> Vec<Out> {
        let Some(cell) = self.cells.get_mut(cell_name) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        match update {
            Update::Gateway(up) => {
                for m in cell.machines.values_mut() {
                    m.view.gateway_up = up;
                }
                for p in cell.plcs.values_mut() {
                    p.gateway_up = up;
                }
                let names: Vec<String> = cell.machines.keys().cloned().collect();
                for m in names {
                    refresh_machine(cell, &m, &mut out, false);
                }
                let names: Vec<String> = cell.plcs.keys().cloned().collect();
                for p in names {
                    plc_out(cell, &p, &mut out);
                }
            }
            Update::Status(s) => {
                let name = s.machine.clone();
                if let Some(m) = cell.machines.get_mut(&name) {
                    m.view.status(*s);
                    refresh_machine(cell, &name, &mut out, false);
                }
            }
            Update::Job(e) => {
                if let Some(m) = cell.machines.get_mut(&e.machine) {
                    m.view.job(&e);
                    refresh_machine(cell, &e.machine, &mut out, false);
                }
            }
            Update::Queue(name, q) => {
                if let Some(m) = cell.machines.get_mut(&name) {
                    m.view.queue(&q);
                    refresh_machine(cell, &name, &mut out, false);
                }
            }
            Update::G05(g) => {
                if let Some(m) = cell.machines.get_mut(&g.machine) {
                    m.view.g05(&g);
                    refresh_machine(cell, &g.machine, &mut out, false);
                }
            }
            Update::Plc(s) => {
                for t in &s.tags {
                    count_parts(cell, t, &mut out);
                }
                if let Some(p) = cell.plcs.get_mut(&s.plc) {
                    p.stations_up = s.stations.iter().any(|st| st.up);
                    for t in &s.tags {
                        p.tags.insert(t.name.clone(), tag_value(t));
                    }
                    plc_out(cell, &s.plc, &mut out);
                }
            }
            Update::Tag(t) => {
                count_parts(cell, &t, &mut out);
                if let Some(p) = cell.plcs.get_mut(&t.plc) {
                    p.tags.insert(t.name.clone(), tag_value(&t));
                    plc_out(cell, &t.plc, &mut out);
                }
            }
            // A punched program is no state of the machine tool (the library holds it).
            Update::Punch(..) => {}
        }
        out
    }

    /// What `machine` of `cell` shows now.
    pub fn shows(&self, cell: &str, machine: &str) -> Option<MachineShows> {
        let m = self.cells.get(cell)?.machines.get(machine)?;
        Some(shows_of(&m.view))
    }
}

/// A tag's value while it is read good; `None` once stale or its station is down (the value
/// would be the last good one, FFU120B §5-6).
fn tag_value(t: &pb::TagValue) -> Option<f64> {
    match (t.quality(), t.value) {
        (pb::TagQuality::Good, Some(v)) => Some(v),
        _ => None,
    }
}

fn count_parts(cell: &mut Cell, t: &pb::TagValue, out: &mut Vec<Out>) {
    let counted: Vec<String> = cell
        .desc
        .machines
        .iter()
        .filter(|m| {
            m.part_counter
                .as_ref()
                .is_some_and(|(p, n)| *p == t.plc && *n == t.name)
        })
        .map(|m| m.name.clone())
        .collect();
    for name in counted {
        if let Some(m) = cell.machines.get_mut(&name) {
            m.view.count_parts(t);
            refresh_machine(cell, &name, out, false);
        }
    }
}

fn plc_out(cell: &Cell, name: &str, out: &mut Vec<Out>) {
    let Some(p) = cell.plcs.get(name) else { return };
    let up = p.gateway_up && p.stations_up;
    let tags = cell
        .desc
        .plcs
        .iter()
        .find(|d| d.name == name)
        .map(|d| {
            d.tags
                .iter()
                .map(|t| {
                    let v = p.tags.get(&t.name).copied().flatten();
                    (t.name.clone(), v.filter(|_| p.gateway_up))
                })
                .collect()
        })
        .unwrap_or_default();
    out.push(Out::Plc {
        cell: cell.desc.cell.clone(),
        plc: name.to_string(),
        up,
        tags,
    });
}

/// What a machine's view shows.
fn shows_of(view: &MachineView) -> MachineShows {
    let up = view.up();
    let activity = up.map(history::activity);
    let alarm = activity == Some(pb::MachineActivity::Alarm);
    let buffered = up
        .and_then(|s| s.sat.as_ref())
        .and_then(|sat| sat.bytes_buffered)
        .unwrap_or(0);
    let state = if view.job_running() {
        if up.is_none() || alarm {
            ProgramState::Interrupted
        } else {
            ProgramState::Running
        }
    } else {
        match view.job_completed() {
            Some(true) => ProgramState::Ended,
            Some(false) => ProgramState::Aborted,
            None => ProgramState::Initializing,
        }
    };
    let reading = activity == Some(pb::MachineActivity::Reading)
        || (view.job_running() && up.is_some() && !alarm)
        // Blocks still in the remote buffer (SAT bytes 5–8, §4.4.2): the CNC reads on.
        || (activity == Some(pb::MachineActivity::Idle)
            && buffered > 0
            && view.job_completed().is_some());
    let channel = if alarm || (up.is_some() && state == ProgramState::Aborted && !reading) {
        ChannelState::Interrupted
    } else if reading {
        ChannelState::Active
    } else {
        ChannelState::Reset
    };
    MachineShows {
        reachable: up.is_some(),
        program: view.program().unwrap_or_default().to_string(),
        state,
        channel,
        mode: if reading {
            OperationMode::Automatic
        } else {
            OperationMode::Other
        },
        parts: view.part_count(),
    }
}

/// The conditions active on a machine, each with its severity.
fn conditions(view: &MachineView) -> Vec<(Cond, u16)> {
    let mut all = Vec::new();
    for (conds, severity) in [
        (view.cnc_alarm(), SEVERITY_CNC),
        (view.link_fault(), SEVERITY_LINK),
        (view.g05_starved(), SEVERITY_G05),
    ] {
        all.extend(conds.unwrap_or_default().into_iter().map(|c| (c, severity)));
    }
    all
}

/// Pushes what machine `name` shows, if it changed (or always with `force`), and an alert for
/// every condition that began.
fn refresh_machine(cell: &mut Cell, name: &str, out: &mut Vec<Out>, force: bool) {
    let cell_name = cell.desc.cell.clone();
    let Some(m) = cell.machines.get_mut(name) else {
        return;
    };
    let shows = shows_of(&m.view);
    let conds = conditions(&m.view);
    let codes: Vec<String> = conds
        .iter()
        .map(|(c, _)| c.native_code.to_string())
        .collect();
    for (c, severity) in conds {
        if !m.active.iter().any(|a| **a == *c.native_code) {
            out.push(Out::Alert {
                cell: cell_name.clone(),
                machine: name.to_string(),
                alert: Alert {
                    code: c.native_code.to_string(),
                    message: c.text.to_string(),
                    severity,
                },
            });
        }
    }
    m.active = codes;
    if force || m.shown.as_ref() != Some(&shows) {
        m.shown = Some(shows.clone());
        out.push(Out::Machine {
            cell: cell_name,
            machine: name.to_string(),
            shows,
        });
    }
}

#[cfg(test)]
mod tests;
