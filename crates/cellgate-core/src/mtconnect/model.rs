//! The device model a `/probe` shows (MTConnect Part 2): an Agent device, a Device per
//! machine and per PLC, their components and data items, with ids and UUIDs that stay the
//! same from one start to the next.

use std::collections::HashMap;

use sha2::{Digest, Sha256};

use super::desc::{CellDesc, MachineDesc, PlcDesc};

/// A data item's category (Part 2 §"DataItem"): what its observations are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Category {
    /// Discrete values: states, names, counts.
    Event,
    /// Continuous values with units.
    Sample,
    /// Health: Normal, Warning, Fault.
    Condition,
}

impl Category {
    /// The attribute value.
    pub fn name(self) -> &'static str {
        match self {
            Category::Event => "EVENT",
            Category::Sample => "SAMPLE",
            Category::Condition => "CONDITION",
        }
    }
}

/// What a data item observes, for the mapping.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Role {
    /// The device's AVAILABILITY.
    Availability,
    /// A machine's CNC alarms (SYSTEM condition).
    CncAlarm,
    /// A machine's link faults (COMMUNICATIONS condition).
    LinkFault,
    /// A machine's EXECUTION.
    Execution,
    /// A machine's PROGRAM.
    Program,
    /// A machine's BLOCK `block_fed`: the last block the remote buffer took whole.
    BlockFed,
    /// A machine's PART_COUNT, from a PLC tag.
    PartCount,
    /// A machine's DI image (G152).
    Di,
    /// A machine's DO image (F152).
    Do,
    /// The blocks of a machine's G05 stream the CNC took (estimated, §9.2).
    G05Blocks,
    /// A machine's G05 stream starving the CNC (MOTION_PROGRAM condition).
    G05Starved,
    /// A PLC station's health (COMMUNICATIONS condition).
    Station(u32),
    /// A PLC tag's value.
    Tag(String),
    /// The Agent device's DEVICE_ADDED.
    DeviceAdded,
    /// The Agent device's DEVICE_REMOVED.
    DeviceRemoved,
    /// The Agent device's DEVICE_CHANGED.
    DeviceChanged,
    /// ASSET_CHANGED of a device.
    AssetChanged,
    /// ASSET_REMOVED of a device.
    AssetRemoved,
    /// A cell gateway's CONNECTION_STATUS, on the Agent device's adapter for the cell.
    Connection(String),
}

/// One data item.
#[derive(Debug, Clone)]
pub struct DataItem {
    /// Unique in the agent.
    pub id: String,
    /// A name a client may filter on, if any.
    pub name: Option<String>,
    /// Its category.
    pub category: Category,
    /// Its type, as the standard names it (`EXECUTION`).
    pub kind: &'static str,
    /// Its subType, if any.
    pub sub_type: Option<&'static str>,
    /// The name its source gives it (`G152`, `D0`).
    pub native_name: Option<String>,
    /// The units of a SAMPLE (`CELSIUS`).
    pub units: Option<&'static str>,
    /// The device it belongs to (index into [`Model::devices`]).
    pub device: usize,
    /// The component it belongs to (index into [`Model::components`]).
    pub component: usize,
    /// What it observes.
    pub role: Role,
}

/// A component, or a device seen as the component of its device-level data items.
#[derive(Debug, Clone)]
pub struct Component {
    /// The element: `Device`, `Agent`, `Controller`, `Path`, `Adapters`, `Adapter`.
    pub element: &'static str,
    /// Unique in the agent.
    pub id: String,
    /// Its name, if any.
    pub name: Option<String>,
    /// Its device (index into [`Model::devices`]).
    pub device: usize,
    /// Its parent component; `None` for the device itself.
    pub parent: Option<usize>,
    /// Its data items, in order.
    pub items: Vec<usize>,
    /// Its child components, in order.
    pub children: Vec<usize>,
}

/// What a device stands for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    /// The agent itself.
    Agent,
    /// A machine of a cell: (cell, machine).
    Machine(String, String),
    /// A PLC of a cell: (cell, PLC).
    Plc(String, String),
}

/// One device.
#[derive(Debug, Clone)]
pub struct Device {
    /// Its name: the cell file's, or `CELL.NAME` where another cell's device took it first.
    pub name: String,
    /// Its UUID: the same for the same cell and name, on any agent, at any start.
    pub uuid: String,
    /// Its id (unique in the agent).
    pub id: String,
    /// What it stands for.
    pub source: Source,
    /// Its description: what it is and which cell.
    pub description: String,
    /// The component that is the device itself (index into [`Model::components`]).
    pub component: usize,
    /// Every data item of the device, its components' included.
    pub items: Vec<usize>,
    /// Removed from its cell by a reload: left out of every document (its data items are
    /// kept, so that sequence numbers and ids stay, and come back if it does).
    pub removed: bool,
}

/// The whole model.
#[derive(Debug, Clone, Default)]
pub struct Model {
    /// The devices, the Agent first.
    pub devices: Vec<Device>,
    /// Every component, each device's own first, in document order per device.
    pub components: Vec<Component>,
    /// Every data item.
    pub items: Vec<DataItem>,
    by_id: HashMap<String, usize>,
    by_name: HashMap<String, usize>,
}

/// A name-based UUID (RFC 9562 §5.8, version 8, from SHA-256 as its appendix B.2 shows): the
/// same `name` always gives the same UUID.
pub fn uuid_for(name: &str) -> String {
    let hash = Sha256::digest(format!("cellgate mtconnect {name}").as_bytes());
    let mut b = [0u8; 16];
    b.copy_from_slice(&hash[..16]);
    b[6] = (b[6] & 0x0F) | 0x80;
    b[8] = (b[8] & 0x3F) | 0x80;
    let h = hex::encode(b);
    format!(
        "{}-{}-{}-{}-{}",
        &h[0..8],
        &h[8..12],
        &h[12..16],
        &h[16..20],
        &h[20..32]
    )
}

/// An id (an XML NCName) from a name made of `[A-Za-z0-9_-.]`: one that starts with a digit,
/// '-' or '.' gets a leading '_'.
fn id_of(name: &str) -> String {
    if name.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_') {
        name.to_string()
    } else {
        format!("_{name}")
    }
}

/// The Agent device's id.
pub const AGENT_ID: &str = "agent";

impl Model {
    /// A model with only the Agent device.
    pub fn new(sender: &str) -> Model {
        let mut m = Model::default();
        let dev = m.device(
            "Agent".to_string(),
            uuid_for(&format!("agent {sender}")),
            AGENT_ID.to_string(),
            Source::Agent,
            format!("cellgate's MTConnect agent on {sender}"),
            "Agent",
        );
        let c = m.devices[dev].component;
        m.item(
            c,
            "agent_avail",
            None,
            Category::Event,
            "AVAILABILITY",
            Role::Availability,
        );
        m.item(
            c,
            "device_added",
            None,
            Category::Event,
            "DEVICE_ADDED",
            Role::DeviceAdded,
        );
        m.item(
            c,
            "device_removed",
            None,
            Category::Event,
            "DEVICE_REMOVED",
            Role::DeviceRemoved,
        );
        m.item(
            c,
            "device_changed",
            None,
            Category::Event,
            "DEVICE_CHANGED",
            Role::DeviceChanged,
        );
        m.component(dev, c, "Adapters", "agent_adapters", None);
        m
    }

    /// The device named `name` (or with that UUID), if any.
    pub fn device_named(&self, name: &str) -> Option<usize> {
        self.by_name
            .get(name)
            .copied()
            .or_else(|| self.devices.iter().position(|d| d.uuid == name))
            .filter(|&d| !self.devices[d].removed)
    }

    /// The data item with this id, if any.
    pub fn item_by_id(&self, id: &str) -> Option<usize> {
        self.by_id.get(id).copied()
    }

    /// Whether the cell already has devices here.
    pub fn has_cell(&self, cell: &str) -> bool {
        self.devices.iter().any(|d| match &d.source {
            Source::Machine(c, _) | Source::Plc(c, _) => c == cell,
            Source::Agent => false,
        })
    }

    /// Adds a cell's machines and PLCs (and its adapter on the Agent device); returns the
    /// devices added.
    pub fn add_cell(&mut self, cell: &CellDesc) -> Vec<usize> {
        let mut added = Vec::new();
        if let Some(adapters) = self.components.iter().position(|c| c.element == "Adapters") {
            let a = self.component(
                0,
                adapters,
                "Adapter",
                &id_of(&format!("cell_{}", cell.cell)),
                Some(cell.cell.clone()),
            );
            let id = format!("{}_connection", self.components[a].id);
            self.item(
                a,
                &id,
                None,
                Category::Event,
                "CONNECTION_STATUS",
                Role::Connection(cell.cell.clone()),
            );
        }
        for m in &cell.machines {
            added.push(self.add_machine(&cell.cell, m));
        }
        for p in &cell.plcs {
            added.push(self.add_plc(&cell.cell, p));
        }
        added
    }

    /// A device name for `name` of `cell`: the name itself, or `CELL.NAME` when taken.
    fn free_name(&self, cell: &str, name: &str) -> String {
        if self.by_name.contains_key(name) || name == "Agent" {
            format!("{cell}.{name}")
        } else {
            name.to_string()
        }
    }

    /// A device's own data items (availability, asset changed and removed) and its
    /// Controller component, whose index is returned.
    fn device_items(&mut self, dev: usize, d: &str) -> usize {
        let c = self.devices[dev].component;
        self.item(
            c,
            &format!("{d}_avail"),
            None,
            Category::Event,
            "AVAILABILITY",
            Role::Availability,
        );
        self.item(
            c,
            &format!("{d}_asset_chg"),
            None,
            Category::Event,
            "ASSET_CHANGED",
            Role::AssetChanged,
        );
        self.item(
            c,
            &format!("{d}_asset_rem"),
            None,
            Category::Event,
            "ASSET_REMOVED",
            Role::AssetRemoved,
        );
        self.component(
            dev,
            c,
            "Controller",
            &format!("{d}_controller"),
            Some("controller".into()),
        )
    }

    pub(super) fn add_machine(&mut self, cell: &str, m: &MachineDesc) -> usize {
        let name = self.free_name(cell, &m.name);
        let d = id_of(&name);
        let dev = self.device(
            name,
            uuid_for(&format!("machine {cell}/{}", m.name)),
            d.clone(),
            Source::Machine(cell.to_string(), m.name.clone()),
            format!(
                "FANUC CNC on a remote buffer, {} (cell {cell})",
                m.protocol.title()
            ),
            "Device",
        );
        let cont = self.device_items(dev, &d);
        self.item(
            cont,
            &format!("{d}_system"),
            Some("cnc_alarm"),
            Category::Condition,
            "SYSTEM",
            Role::CncAlarm,
        );
        self.item(
            cont,
            &format!("{d}_comms"),
            Some("link"),
            Category::Condition,
            "COMMUNICATIONS",
            Role::LinkFault,
        );
        if m.protocol.is_a_family() {
            let di = self.item(
                cont,
                &format!("{d}_di"),
                Some("di"),
                Category::Event,
                "VARIABLE",
                Role::Di,
            );
            self.items[di].native_name = Some("G152".into());
            let dout = self.item(
                cont,
                &format!("{d}_do"),
                Some("do"),
                Category::Event,
                "VARIABLE",
                Role::Do,
            );
            self.items[dout].native_name = Some("F152".into());
        }
        let path = self.component(dev, cont, "Path", &format!("{d}_path"), Some("path".into()));
        self.item(
            path,
            &format!("{d}_execution"),
            Some("execution"),
            Category::Event,
            "EXECUTION",
            Role::Execution,
        );
        self.item(
            path,
            &format!("{d}_program"),
            Some("program"),
            Category::Event,
            "PROGRAM",
            Role::Program,
        );
        // Named for what it is: the block the remote buffer took last, which the CNC executes
        // when it comes to it (docs/mtconnect.md).
        self.item(
            path,
            &format!("{d}_block_fed"),
            Some("block_fed"),
            Category::Event,
            "BLOCK",
            Role::BlockFed,
        );
        if let Some((plc, tag)) = &m.part_counter {
            let pc = self.item(
                path,
                &format!("{d}_part_count"),
                Some("part_count"),
                Category::Event,
                "PART_COUNT",
                Role::PartCount,
            );
            self.items[pc].native_name = Some(format!("{plc}/{tag}"));
        }
        if m.g05 {
            let b = self.item(
                path,
                &format!("{d}_g05_blocks"),
                Some("g05_blocks"),
                Category::Event,
                "BLOCK_COUNT",
                Role::G05Blocks,
            );
            self.items[b].native_name = Some("G05".into());
            self.item(
                path,
                &format!("{d}_g05"),
                Some("g05"),
                Category::Condition,
                "MOTION_PROGRAM",
                Role::G05Starved,
            );
        }
        dev
    }

    pub(super) fn add_plc(&mut self, cell: &str, p: &PlcDesc) -> usize {
        let name = self.free_name(cell, &p.name);
        let d = id_of(&name);
        let dev = self.device(
            name,
            uuid_for(&format!("plc {cell}/{}", p.name)),
            d.clone(),
            Source::Plc(cell.to_string(), p.name.clone()),
            format!("Fuji MICREX-F PLC through FFU120B modules (cell {cell})"),
            "Device",
        );
        let cont = self.device_items(dev, &d);
        for s in &p.stations {
            self.item(
                cont,
                &format!("{d}_station{s}"),
                Some(&format!("station-{s}")),
                Category::Condition,
                "COMMUNICATIONS",
                Role::Station(*s),
            );
        }
        for t in &p.tags {
            let (category, kind) = t.typed.map_or((Category::Event, "VARIABLE"), |ty| {
                let category = match ty.category {
                    super::types::TagCategory::Sample => Category::Sample,
                    super::types::TagCategory::Event => Category::Event,
                };
                (category, ty.name)
            });
            let i = self.item(
                cont,
                &format!("{d}_tag_{}", t.name),
                Some(&t.name),
                category,
                kind,
                Role::Tag(t.name.clone()),
            );
            self.items[i].units = t.units;
            if !t.native.is_empty() {
                self.items[i].native_name = Some(t.native.clone());
            }
        }
        dev
    }

    fn device(
        &mut self,
        name: String,
        uuid: String,
        id: String,
        source: Source,
        description: String,
        element: &'static str,
    ) -> usize {
        let dev = self.devices.len();
        let component = self.components.len();
        self.components.push(Component {
            element,
            id: id.clone(),
            name: Some(name.clone()),
            device: dev,
            parent: None,
            items: Vec::new(),
            children: Vec::new(),
        });
        self.by_name.insert(name.clone(), dev);
        self.devices.push(Device {
            name,
            uuid,
            id,
            source,
            description,
            component,
            items: Vec::new(),
            removed: false,
        });
        dev
    }

    fn component(
        &mut self,
        dev: usize,
        parent: usize,
        element: &'static str,
        id: &str,
        name: Option<String>,
    ) -> usize {
        self.components.push(Component {
            element,
            id: id.to_string(),
            name,
            device: dev,
            parent: Some(parent),
            items: Vec::new(),
            children: Vec::new(),
        });
        let c = self.components.len() - 1;
        self.components[parent].children.push(c);
        c
    }

    fn item(
        &mut self,
        component: usize,
        id: &str,
        name: Option<&str>,
        category: Category,
        kind: &'static str,
        role: Role,
    ) -> usize {
        let i = self.items.len();
        let device = self.components[component].device;
        self.items.push(DataItem {
            id: id.to_string(),
            name: name.map(str::to_string),
            category,
            kind,
            sub_type: None,
            native_name: None,
            units: None,
            device,
            component,
            role,
        });
        self.components[component].items.push(i);
        self.devices[device].items.push(i);
        self.by_id.insert(id.to_string(), i);
        i
    }

    /// The data item of device `dev` with role `role`.
    pub fn item_of(&self, dev: usize, role: &Role) -> Option<usize> {
        self.devices[dev]
            .items
            .iter()
            .copied()
            .find(|&i| self.items[i].role == *role)
    }

    /// Every data item of component `c` and its descendants.
    pub fn items_under(&self, c: usize) -> Vec<usize> {
        let mut out = self.components[c].items.clone();
        for &child in &self.components[c].children {
            out.extend(self.items_under(child));
        }
        out
    }
}
