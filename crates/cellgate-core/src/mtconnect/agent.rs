//! The agent: the device model, the sequence buffer, and what each device was told; it takes
//! the bus contract's messages ([`Update`]) and answers `/probe`, `/current` and `/sample`.

use std::collections::HashMap;
use std::sync::Arc;

use super::assets::{Assets, FileAsset};
use super::buffer::{Cond, ItemState, Level, Observation, SequenceBuffer, Value};
use super::desc::CellDesc;
use super::mapping::{MachineView, PlcView, Wanted};
use super::model::{Category, Model, Role, Source};
use super::request::{ErrorCode, Format, MtError, Node, PathFilter, Query};
use super::{json, xml};
use crate::pb;

/// What a cell's gateway published or answered, for the agent.
#[derive(Debug, Clone)]
pub enum Update {
    /// A machine's status (boxed: it is the largest message by far).
    Status(Box<pb::MachineStatus>),
    /// A job's event.
    Job(pb::JobEvent),
    /// A machine's queue (read at start: the running job's name).
    Queue(String, pb::JobQueue),
    /// A G05 stream's status.
    G05(pb::G05Status),
    /// A PLC's status.
    Plc(pb::PlcStatus),
    /// A tag's value.
    Tag(pb::TagValue),
    /// A program the CNC punched out, and its library key on the bus.
    Punch(Box<pb::PunchedProgram>, String),
    /// The gateway came (true) or went (false).
    Gateway(bool),
}

pub use super::assets::ASSET_BUFFER_SIZE;

/// The `/sample` default count (Part 1).
pub const DEFAULT_COUNT: i64 = 100;

/// The agent's state.
pub struct Agent {
    model: Model,
    buffer: SequenceBuffer,
    instance_id: u64,
    sender: String,
    model_time_us: u64,
    machines: HashMap<(String, String), (usize, MachineView)>,
    plcs: HashMap<(String, String), (usize, PlcView)>,
    /// (cell, PLC, tag) → the machines it counts parts of.
    counters: HashMap<(String, String, String), Vec<String>>,
    /// Whether each cell's gateway is there.
    cells: HashMap<String, bool>,
    /// Each cell as last described.
    descs: HashMap<String, CellDesc>,
    assets: Assets,
}

/// A device's observations by component (index into the model's components).
pub type Grouped<'a> = Vec<(usize, Vec<&'a Observation>)>;

/// Which data items a request takes: `None` every one.
pub type Selection = Option<Vec<bool>>;

impl Agent {
    /// An agent with only its Agent device; `sender` names it in every header.
    pub fn new(sender: &str, instance_id: u64, buffer_size: usize, now_us: u64) -> Agent {
        let mut a = Agent {
            model: Model::new(sender),
            buffer: SequenceBuffer::new(buffer_size),
            instance_id,
            sender: sender.to_string(),
            model_time_us: now_us,
            machines: HashMap::new(),
            plcs: HashMap::new(),
            counters: HashMap::new(),
            cells: HashMap::new(),
            descs: HashMap::new(),
            assets: Assets::default(),
        };
        for i in 0..a.model.items.len() {
            let v = match a.model.items[i].role {
                Role::Availability => Value::Text("AVAILABLE".into()),
                _ => Value::Unavailable,
            };
            a.buffer.push(i as u32, now_us, v);
        }
        a
    }

    /// The model.
    pub fn model(&self) -> &Model {
        &self.model
    }

    /// The buffer.
    pub fn buffer(&self) -> &SequenceBuffer {
        &self.buffer
    }

    /// The instance id of every header.
    pub fn instance_id(&self) -> u64 {
        self.instance_id
    }

    /// The cell as last described, if modelled.
    pub fn desc(&self, cell: &str) -> Option<&CellDesc> {
        self.descs.get(cell)
    }

    /// Whether the cell is modelled.
    pub fn has_cell(&self, cell: &str) -> bool {
        self.cells.contains_key(cell)
    }

    /// The cells modelled.
    pub fn cells(&self) -> impl Iterator<Item = &str> {
        self.cells.keys().map(String::as_str)
    }

    /// Adds a cell's devices (once), each data item UNAVAILABLE until its first update, and a
    /// DEVICE_ADDED for each on the Agent device.
    pub fn add_cell(&mut self, desc: &CellDesc, now_us: u64) {
        if self.cells.contains_key(&desc.cell) {
            return;
        }
        let first_item = self.model.items.len();
        let added = self.model.add_cell(desc);
        self.cells.insert(desc.cell.clone(), false);
        self.descs.insert(desc.cell.clone(), desc.clone());
        for m in &desc.machines {
            let dev = self.dev_of(&Source::Machine(desc.cell.clone(), m.name.clone()));
            if let Some(dev) = dev {
                self.machines.insert(
                    (desc.cell.clone(), m.name.clone()),
                    (dev, MachineView::default()),
                );
            }
            if let Some((plc, tag)) = &m.part_counter {
                self.counters
                    .entry((desc.cell.clone(), plc.clone(), tag.clone()))
                    .or_default()
                    .push(m.name.clone());
            }
        }
        for p in &desc.plcs {
            if let Some(dev) = self.dev_of(&Source::Plc(desc.cell.clone(), p.name.clone())) {
                self.plcs.insert(
                    (desc.cell.clone(), p.name.clone()),
                    (dev, PlcView::default()),
                );
            }
        }
        for i in first_item..self.model.items.len() {
            let v = match &self.model.items[i].role {
                Role::Connection(_) => Value::Text("CLOSED".into()),
                _ => Value::Unavailable,
            };
            self.buffer.push(i as u32, now_us, v);
        }
        self.model_time_us = now_us;
        if let Some(i) = self.model.item_of(0, &Role::DeviceAdded) {
            for d in added {
                let uuid: Arc<str> = self.model.devices[d].uuid.as_str().into();
                self.buffer.push(i as u32, now_us, Value::Text(uuid));
            }
        }
    }

    /// Takes a cell's description again (its gateway reloaded its cell file, or came back
    /// with another): a machine or PLC added gets a device and a DEVICE_ADDED (one removed
    /// earlier comes back under its old UUID); one removed has its data items UNAVAILABLE,
    /// leaves the documents and gets a DEVICE_REMOVED; one whose description changed in a
    /// way its data items show (protocol family, G05, part counter, stations, tags) gets a
    /// DEVICE_CHANGED, its data items staying as first modelled until the agent restarts.
    /// A cell not modelled yet is added. Returns the observations made.
    pub fn change_cell(&mut self, desc: &CellDesc, now_us: u64) -> usize {
        let Some(old) = self.descs.get(&desc.cell).cloned() else {
            let before = self.buffer.last();
            self.add_cell(desc, now_us);
            return (self.buffer.last() - before) as usize;
        };
        if old == *desc {
            return 0;
        }
        let cell = desc.cell.clone();
        let up = self.cells.get(&cell).copied().unwrap_or(false);
        let (mut added, mut removed, mut changed) = (Vec::new(), Vec::new(), Vec::new());
        let mut n = 0;
        for m in &desc.machines {
            let shape = |o: &super::desc::MachineDesc| machine_shape(o) != machine_shape(m);
            let was = old.machines.iter().find(|o| o.name == m.name);
            let source = Source::Machine(cell.clone(), m.name.clone());
            let (dev, taken) = self.take_device(&source, was.is_some_and(shape), now_us, |model| {
                model.add_machine(&cell, m)
            });
            n += taken.record(dev, &mut added, &mut changed);
            self.machines
                .entry((cell.clone(), m.name.clone()))
                .or_insert_with(|| {
                    let mut view = MachineView::default();
                    view.gateway_up = up;
                    (dev, view)
                });
        }
        for p in &desc.plcs {
            let shape = |o: &super::desc::PlcDesc| plc_shape(o) != plc_shape(p);
            let was = old.plcs.iter().find(|o| o.name == p.name);
            let source = Source::Plc(cell.clone(), p.name.clone());
            let (dev, taken) = self.take_device(&source, was.is_some_and(shape), now_us, |model| {
                model.add_plc(&cell, p)
            });
            n += taken.record(dev, &mut added, &mut changed);
            self.plcs
                .entry((cell.clone(), p.name.clone()))
                .or_insert_with(|| {
                    let mut view = PlcView::default();
                    view.gateway_up = up;
                    (dev, view)
                });
        }
        let gone_machines = old
            .machines
            .iter()
            .filter(|o| !desc.machines.iter().any(|m| m.name == o.name))
            .map(|o| Source::Machine(cell.clone(), o.name.clone()));
        let gone_plcs = old
            .plcs
            .iter()
            .filter(|o| !desc.plcs.iter().any(|p| p.name == o.name))
            .map(|o| Source::Plc(cell.clone(), o.name.clone()));
        let gone: Vec<Source> = gone_machines.chain(gone_plcs).collect();
        for source in gone {
            let Some(dev) = self.dev_of(&source) else {
                continue;
            };
            match &source {
                Source::Machine(c, m) => {
                    self.machines.remove(&(c.clone(), m.clone()));
                }
                Source::Plc(c, p) => {
                    self.plcs.remove(&(c.clone(), p.clone()));
                }
                Source::Agent => {}
            }
            let items = self.model.devices[dev].items.clone();
            for i in items {
                let w = match self.model.items[i].category {
                    Category::Condition => Wanted::Conditions(None),
                    _ => Wanted::Value(Value::Unavailable),
                };
                n += self.want(i, w, now_us);
            }
            self.model.devices[dev].removed = true;
            removed.push(dev);
        }
        self.counters.retain(|(c, _, _), _| *c != cell);
        for m in &desc.machines {
            if let Some((plc, tag)) = &m.part_counter {
                self.counters
                    .entry((cell.clone(), plc.clone(), tag.clone()))
                    .or_default()
                    .push(m.name.clone());
            }
        }
        self.descs.insert(cell, desc.clone());
        if !(added.is_empty() && removed.is_empty() && changed.is_empty()) {
            self.model_time_us = now_us;
        }
        for (role, devs) in [
            (Role::DeviceAdded, added),
            (Role::DeviceRemoved, removed),
            (Role::DeviceChanged, changed),
        ] {
            if let Some(i) = self.model.item_of(0, &role) {
                for d in devs {
                    let uuid: Arc<str> = self.model.devices[d].uuid.as_str().into();
                    self.buffer.push(i as u32, now_us, Value::Text(uuid));
                    n += 1;
                }
            }
        }
        n
    }

    /// The device of `source` as a description taken again has it: added by `add` (its data
    /// items UNAVAILABLE), brought back if it was removed, or kept, `changed` or not.
    fn take_device(
        &mut self,
        source: &Source,
        changed: bool,
        now_us: u64,
        add: impl FnOnce(&mut Model) -> usize,
    ) -> (usize, Taken) {
        match self.dev_of(source) {
            None => {
                let first = self.model.items.len();
                let dev = add(&mut self.model);
                (dev, Taken::Added(self.unavailable_from(first, now_us)))
            }
            Some(dev) if self.model.devices[dev].removed => {
                self.model.devices[dev].removed = false;
                (dev, Taken::Added(0))
            }
            Some(dev) if changed => (dev, Taken::Changed),
            Some(dev) => (dev, Taken::Kept),
        }
    }

    /// Data items from `first` on, new: UNAVAILABLE until their first update.
    fn unavailable_from(&mut self, first: usize, now_us: u64) -> usize {
        for i in first..self.model.items.len() {
            self.buffer.push(i as u32, now_us, Value::Unavailable);
        }
        self.model.items.len() - first
    }

    fn dev_of(&self, source: &Source) -> Option<usize> {
        self.model.devices.iter().position(|d| d.source == *source)
    }

    /// Takes an update of `cell`; returns how many observations it made.
    pub fn update(&mut self, cell: &str, update: Update, now_us: u64) -> usize {
        let key = |name: &str| (cell.to_string(), name.to_string());
        match update {
            Update::Gateway(up) => {
                let Some(was) = self.cells.get_mut(cell) else {
                    return 0;
                };
                *was = up;
                let mut n = 0;
                let machines: Vec<_> = self
                    .machines
                    .iter_mut()
                    .filter(|((c, _), _)| c == cell)
                    .map(|(k, (_, v))| {
                        v.gateway_up = up;
                        k.clone()
                    })
                    .collect();
                for k in machines {
                    n += self.refresh_machine(&k, now_us);
                }
                let plcs: Vec<_> = self
                    .plcs
                    .iter_mut()
                    .filter(|((c, _), _)| c == cell)
                    .map(|(k, (_, v))| {
                        v.gateway_up = up;
                        k.clone()
                    })
                    .collect();
                for k in plcs {
                    n += self.refresh_plc(&k, now_us);
                }
                let status = if up { "ESTABLISHED" } else { "CLOSED" };
                if let Some(i) = self.model.item_of(0, &Role::Connection(cell.to_string())) {
                    n += self.want(i, Wanted::Value(Value::Text(status.into())), now_us);
                }
                n
            }
            Update::Status(s) => {
                let k = key(&s.machine);
                let Some((_, view)) = self.machines.get_mut(&k) else {
                    return 0;
                };
                view.status(*s);
                self.refresh_machine(&k, now_us)
            }
            Update::Job(e) => {
                let k = key(&e.machine);
                let Some((_, view)) = self.machines.get_mut(&k) else {
                    return 0;
                };
                view.job(&e);
                self.refresh_machine(&k, now_us)
            }
            Update::Queue(m, q) => {
                let k = key(&m);
                let Some((_, view)) = self.machines.get_mut(&k) else {
                    return 0;
                };
                view.queue(&q);
                self.refresh_machine(&k, now_us)
            }
            Update::G05(g) => {
                let k = key(&g.machine);
                let Some((_, view)) = self.machines.get_mut(&k) else {
                    return 0;
                };
                view.g05(&g);
                self.refresh_machine(&k, now_us)
            }
            Update::Plc(s) => {
                let k = key(&s.plc);
                let mut n = 0;
                for t in &s.tags {
                    n += self.count_parts(cell, t, now_us);
                }
                let Some((_, view)) = self.plcs.get_mut(&k) else {
                    return n;
                };
                view.status(&s);
                n + self.refresh_plc(&k, now_us)
            }
            Update::Punch(p, location) => {
                let Some((dev, _)) = self.machines.get(&key(&p.machine)) else {
                    return 0;
                };
                let dev = *dev;
                let Some(asset) = FileAsset::of_punched(&p, cell, dev, location, now_us) else {
                    return 0;
                };
                let id: Arc<str> = asset.asset_id.as_str().into();
                self.assets.put(asset);
                match self.model.item_of(dev, &Role::AssetChanged) {
                    Some(i) => {
                        self.buffer.push(i as u32, now_us, Value::Text(id));
                        1
                    }
                    None => 0,
                }
            }
            Update::Tag(t) => {
                let k = key(&t.plc);
                let mut n = self.count_parts(cell, &t, now_us);
                if let Some((_, view)) = self.plcs.get_mut(&k) {
                    view.tag(&t);
                    n += self.refresh_plc(&k, now_us);
                }
                n
            }
        }
    }

    fn count_parts(&mut self, cell: &str, t: &pb::TagValue, now_us: u64) -> usize {
        let Some(machines) = self
            .counters
            .get(&(cell.to_string(), t.plc.clone(), t.name.clone()))
            .cloned()
        else {
            return 0;
        };
        let mut n = 0;
        for m in machines {
            let k = (cell.to_string(), m);
            if let Some((_, view)) = self.machines.get_mut(&k) {
                view.count_parts(t);
                n += self.refresh_machine(&k, now_us);
            }
        }
        n
    }

    fn refresh_machine(&mut self, k: &(String, String), now_us: u64) -> usize {
        let Some((dev, view)) = self.machines.get(k) else {
            return 0;
        };
        let wanted = wanted_of(&self.model, *dev, |role| view.wanted(role));
        self.want_all(wanted, now_us)
    }

    fn refresh_plc(&mut self, k: &(String, String), now_us: u64) -> usize {
        let Some((dev, view)) = self.plcs.get(k) else {
            return 0;
        };
        let wanted = wanted_of(&self.model, *dev, |role| view.wanted(role));
        self.want_all(wanted, now_us)
    }

    fn want_all(&mut self, wanted: Vec<(usize, Wanted)>, now_us: u64) -> usize {
        wanted
            .into_iter()
            .map(|(i, w)| self.want(i, w, now_us))
            .sum()
    }

    /// Records what differs between data item `i`'s state and `wanted`.
    fn want(&mut self, i: usize, wanted: Wanted, now_us: u64) -> usize {
        let state = self.buffer.state(i).cloned().unwrap_or_default();
        let item = i as u32;
        match wanted {
            Wanted::Value(v) => {
                if state.last.as_ref().map(|o| &o.value) == Some(&v) {
                    return 0;
                }
                self.buffer.push(item, now_us, v);
                1
            }
            Wanted::Conditions(None) => {
                if state.active.is_empty()
                    && state.last.as_ref().map(|o| &o.value) == Some(&Value::Unavailable)
                {
                    return 0;
                }
                self.buffer.push(item, now_us, Value::Unavailable);
                1
            }
            Wanted::Conditions(Some(conds)) => {
                let mut n = 0;
                let active: Vec<&Cond> = state
                    .active
                    .iter()
                    .filter_map(|o| match &o.value {
                        Value::Cond(c) => Some(c),
                        _ => None,
                    })
                    .collect();
                if conds.is_empty() {
                    let normal = matches!(
                        state.last.as_ref().map(|o| &o.value),
                        Some(Value::Cond(Cond {
                            level: Level::Normal,
                            ..
                        }))
                    );
                    if !active.is_empty() || !normal {
                        self.buffer.push(
                            item,
                            now_us,
                            Value::Cond(Cond {
                                level: Level::Normal,
                                native_code: "".into(),
                                text: "".into(),
                            }),
                        );
                        n += 1;
                    }
                    return n;
                }
                // Cleared ones first, then the new or changed ones.
                for a in &active {
                    if !conds.iter().any(|c| c.native_code == a.native_code) {
                        self.buffer.push(
                            item,
                            now_us,
                            Value::Cond(Cond {
                                level: Level::Normal,
                                native_code: a.native_code.clone(),
                                text: "".into(),
                            }),
                        );
                        n += 1;
                    }
                }
                for c in conds {
                    if !active.iter().any(|a| **a == c) {
                        self.buffer.push(item, now_us, Value::Cond(c));
                        n += 1;
                    }
                }
                n
            }
        }
    }

    // ---- requests -------------------------------------------------------------------------

    /// The device named in the URI (`/NAME/probe`), by name or UUID.
    pub fn device(&self, name: &str) -> Result<usize, MtError> {
        self.model
            .device_named(name)
            .ok_or_else(|| MtError::new(ErrorCode::NoDevice, format!("no device {name:?} here")))
    }

    /// The elements from `Devices` down to data item `i`, for a `path` filter.
    fn chain(&self, i: usize) -> Vec<Node<'_>> {
        let item = &self.model.items[i];
        let mut comps = Vec::new();
        let mut c = Some(item.component);
        while let Some(ci) = c {
            comps.push(ci);
            c = self.model.components[ci].parent;
        }
        comps.reverse();
        let mut chain: Vec<Node<'_>> = vec![("Devices", Vec::new())];
        for (n, &ci) in comps.iter().enumerate() {
            let comp = &self.model.components[ci];
            if n > 0 {
                chain.push(("Components", Vec::new()));
            }
            let mut attrs = vec![("id", comp.id.as_str())];
            if let Some(name) = &comp.name {
                attrs.push(("name", name.as_str()));
            }
            if comp.parent.is_none() {
                attrs.push(("uuid", self.model.devices[comp.device].uuid.as_str()));
            }
            chain.push((comp.element, attrs));
        }
        chain.push(("DataItems", Vec::new()));
        let mut attrs = vec![
            ("id", item.id.as_str()),
            ("type", item.kind),
            ("category", item.category.name()),
        ];
        if let Some(n) = &item.name {
            attrs.push(("name", n.as_str()));
        }
        if let Some(s) = item.sub_type {
            attrs.push(("subType", s));
        }
        if let Some(u) = item.units {
            attrs.push(("units", u));
        }
        if let Some(n) = &item.native_name {
            attrs.push(("nativeName", n.as_str()));
        }
        chain.push(("DataItem", attrs));
        chain
    }

    /// The data items a request for `device` (all if `None`) with `path` takes.
    pub fn select(&self, device: Option<usize>, path: Option<&str>) -> Result<Selection, MtError> {
        if device.is_none() && path.is_none() {
            return Ok(None);
        }
        let filter = path.map(PathFilter::parse).transpose()?;
        let mut any = false;
        let mask: Vec<bool> = (0..self.model.items.len())
            .map(|i| {
                let ok = device.is_none_or(|d| self.model.items[i].device == d)
                    && filter.as_ref().is_none_or(|f| f.selects(&self.chain(i)));
                any |= ok;
                ok
            })
            .collect();
        if !any {
            return Err(MtError::new(
                ErrorCode::InvalidPath,
                format!(
                    "the path {:?} selects no data item",
                    path.unwrap_or_default()
                ),
            ));
        }
        Ok(Some(mask))
    }

    /// `/probe`: the device model (every device, or `device`'s).
    pub fn probe(&self, device: Option<usize>, format: Format, now_us: u64) -> String {
        match format {
            Format::Xml => self.probe_xml(device, now_us),
            Format::Json => json::probe(self, device, now_us),
        }
    }

    /// `/current`: every selected data item's state, now or as of `at`.
    pub fn current(
        &self,
        device: Option<usize>,
        q: &Query,
        now_us: u64,
    ) -> Result<String, MtError> {
        let sel = self.select(device, q.path.as_deref())?;
        let at_state;
        let state: &[ItemState] = match q.at {
            Some(at) => {
                let at = self.buffer.check_at(at)?;
                at_state = self.buffer.state_at(at);
                &at_state
            }
            None => self.buffer.latest(),
        };
        let wanted = |i: usize| sel.as_ref().is_none_or(|m| m[i]);
        let obs: Vec<&Observation> = state
            .iter()
            .enumerate()
            .filter(|(i, _)| wanted(*i))
            .flat_map(|(_, s)| s.shown())
            .collect();
        let next = match q.at {
            Some(at) => at as u64 + 1,
            None => self.buffer.next(),
        };
        Ok(self.streams(device, &obs, next, q.format, now_us))
    }

    /// `/sample`: observations from `from` (default the first kept), `count` at most
    /// (default 100); returns the document, the `nextSequence` it gives and how many
    /// observations it holds.
    pub fn sample(
        &self,
        device: Option<usize>,
        q: &Query,
        sel: &Selection,
        now_us: u64,
    ) -> Result<(String, u64, usize), MtError> {
        let count = self.buffer.check_count(q.count.unwrap_or(DEFAULT_COUNT))?;
        let from = match q.from {
            Some(f) => self.buffer.check_from(f)?,
            None => self.buffer.first(),
        };
        let (obs, next) = self
            .buffer
            .sample(from, count, |i| sel.as_ref().is_none_or(|m| m[i as usize]));
        Ok((
            self.streams(device, &obs, next, q.format, now_us),
            next,
            obs.len(),
        ))
    }

    /// An MTConnectError document.
    pub fn error(&self, e: &MtError, format: Format, now_us: u64) -> String {
        match format {
            Format::Json => json::error(self, e, now_us),
            Format::Xml => {
                let mut x = xml::Xml::new("Error", 512);
                self.header(&mut x, now_us, None);
                x.open("Errors", &[]);
                x.text("Error", &[("errorCode", e.code.name())], &e.message);
                x.close("Errors");
                x.finish("Error")
            }
        }
    }

    /// The assets kept.
    pub fn kept_assets(&self) -> &Assets {
        &self.assets
    }

    /// `/assets` (of `device`, newest first, `count` at most, of `type` File only), or
    /// `/asset/ID` (`id`): an Assets document, or ASSET_NOT_FOUND.
    pub fn assets(
        &self,
        device: Option<usize>,
        id: Option<&str>,
        q: &Query,
        now_us: u64,
    ) -> Result<String, MtError> {
        let list: Vec<&FileAsset> = match id {
            Some(id) => vec![self.assets.get(id).ok_or_else(|| {
                MtError::new(ErrorCode::AssetNotFound, format!("no asset {id:?} is kept"))
            })?],
            None => {
                let count = q.count.unwrap_or(DEFAULT_COUNT);
                if count < 1 || count > ASSET_BUFFER_SIZE as i64 {
                    return Err(MtError::new(
                        ErrorCode::OutOfRange,
                        format!(
                            "'count' must be between 1 and {ASSET_BUFFER_SIZE}; {count} is not"
                        ),
                    ));
                }
                match q.asset_type.as_deref() {
                    Some(t) if t != "File" => Vec::new(),
                    _ => self.assets.newest(device, count as usize),
                }
            }
        };
        Ok(match q.format {
            Format::Json => json::assets(self, &list, now_us),
            Format::Xml => {
                let mut x = xml::Xml::new("Assets", 512 + list.len() * 512);
                let size = ASSET_BUFFER_SIZE.to_string();
                let count = self.assets.len().to_string();
                let mt = self.model_change_time();
                let mut attrs = self.header_attrs(now_us);
                attrs.retain(|(k, _)| *k != "bufferSize");
                let mut attrs: Vec<(&str, &str)> =
                    attrs.iter().map(|(k, v)| (*k, v.as_str())).collect();
                attrs.extend([
                    ("assetBufferSize", size.as_str()),
                    ("assetCount", count.as_str()),
                    ("deviceModelChangeTime", mt.as_str()),
                ]);
                x.empty("Header", &attrs);
                x.open("Assets", &[]);
                for a in list {
                    self.file_xml(&mut x, a);
                }
                x.close("Assets");
                x.finish("Assets")
            }
        })
    }

    /// The asset `id` kept, as one XML element on one line (an SHDR `@ASSET@` line).
    pub fn asset_element(&self, id: &str) -> Option<String> {
        let a = self.assets.get(id)?;
        let mut x = xml::Xml::fragment(512);
        self.file_xml(&mut x, a);
        Some(x.finish_fragment().replace(['\n', '\r'], " "))
    }

    /// A File asset (Part 4 "File").
    fn file_xml(&self, x: &mut xml::Xml, a: &FileAsset) {
        let ts = xml::timestamp(a.time_us);
        let size = a.size.to_string();
        x.open(
            "File",
            &[
                ("assetId", &a.asset_id),
                ("timestamp", &ts),
                ("deviceUuid", &self.model.devices[a.device].uuid),
                ("name", &a.name),
                ("mediaType", "text/plain"),
                ("applicationCategory", "DEVICE"),
                ("applicationType", "PRODUCTION_PROGRAM"),
                ("size", &size),
                ("versionId", &a.version),
                ("state", a.state()),
            ],
        );
        x.empty("FileLocation", &[("href", &a.location)]);
        x.text("CreationTime", &[], &ts);
        x.close("File");
    }

    /// The header's attributes common to every document.
    pub fn header_attrs(&self, now_us: u64) -> Vec<(&'static str, String)> {
        vec![
            ("creationTime", xml::timestamp(now_us)),
            ("sender", self.sender.clone()),
            ("instanceId", self.instance_id.to_string()),
            ("version", xml::VERSION.to_string()),
            ("bufferSize", self.buffer.size().to_string()),
        ]
    }

    /// When the device model last changed.
    pub fn model_change_time(&self) -> String {
        xml::timestamp(self.model_time_us)
    }

    fn header(&self, x: &mut xml::Xml, now_us: u64, extra: Option<&[(&str, &str)]>) {
        let base = self.header_attrs(now_us);
        let mut attrs: Vec<(&str, &str)> = base.iter().map(|(k, v)| (*k, v.as_str())).collect();
        if let Some(e) = extra {
            attrs.extend_from_slice(e);
        }
        x.empty("Header", &attrs);
    }

    fn probe_xml(&self, device: Option<usize>, now_us: u64) -> String {
        let asset_size = ASSET_BUFFER_SIZE.to_string();
        let asset_count = self.assets.len().to_string();
        let mut x = xml::Xml::new("Devices", 4096 + 1024 * self.model.items.len() / 4);
        let mt = self.model_change_time();
        self.header(
            &mut x,
            now_us,
            Some(&[
                ("assetBufferSize", asset_size.as_str()),
                ("assetCount", asset_count.as_str()),
                ("deviceModelChangeTime", mt.as_str()),
            ]),
        );
        x.open("Devices", &[]);
        for (d, dev) in self.model.devices.iter().enumerate() {
            if device.is_some_and(|want| want != d) || dev.removed {
                continue;
            }
            let comp = &self.model.components[dev.component];
            x.open(
                comp.element,
                &[("id", &dev.id), ("name", &dev.name), ("uuid", &dev.uuid)],
            );
            x.text("Description", &[], &dev.description);
            self.component_xml(&mut x, dev.component);
            x.close(comp.element);
        }
        x.close("Devices");
        x.finish("Devices")
    }

    fn component_xml(&self, x: &mut xml::Xml, c: usize) {
        let comp = &self.model.components[c];
        if !comp.items.is_empty() {
            x.open("DataItems", &[]);
            for &i in &comp.items {
                let item = &self.model.items[i];
                let mut attrs = vec![
                    ("category", item.category.name()),
                    ("id", item.id.as_str()),
                    ("type", item.kind),
                ];
                if let Some(n) = &item.name {
                    attrs.push(("name", n.as_str()));
                }
                if let Some(s) = item.sub_type {
                    attrs.push(("subType", s));
                }
                if let Some(u) = item.units {
                    attrs.push(("units", u));
                }
                // The name the source gives it (G152, D0) is its Source (Part 2 "Source").
                match &item.native_name {
                    Some(n) => {
                        x.open("DataItem", &attrs);
                        x.text("Source", &[], n);
                        x.close("DataItem");
                    }
                    None => x.empty("DataItem", &attrs),
                }
            }
            x.close("DataItems");
        }
        if !comp.children.is_empty() {
            x.open("Components", &[]);
            for &child in &comp.children {
                let ch = &self.model.components[child];
                let mut attrs = vec![("id", ch.id.as_str())];
                if let Some(n) = &ch.name {
                    attrs.push(("name", n.as_str()));
                }
                x.open(ch.element, &attrs);
                self.component_xml(x, child);
                x.close(ch.element);
            }
            x.close("Components");
        }
    }

    /// The observations grouped by device and component, in model order.
    pub fn grouped<'a>(&self, obs: &[&'a Observation]) -> Vec<(usize, Grouped<'a>)> {
        let mut by_comp: Vec<Vec<&Observation>> = vec![Vec::new(); self.model.components.len()];
        for o in obs {
            if let Some(item) = self.model.items.get(o.item as usize) {
                by_comp[item.component].push(o);
            }
        }
        let mut by_dev: Vec<Grouped<'_>> = vec![Vec::new(); self.model.devices.len()];
        for (c, list) in by_comp.into_iter().enumerate() {
            if !list.is_empty() {
                by_dev[self.model.components[c].device].push((c, list));
            }
        }
        by_dev
            .into_iter()
            .enumerate()
            .filter(|(d, comps)| !comps.is_empty() && !self.model.devices[*d].removed)
            .collect()
    }

    fn streams(
        &self,
        _device: Option<usize>,
        obs: &[&Observation],
        next: u64,
        format: Format,
        now_us: u64,
    ) -> String {
        if format == Format::Json {
            return json::streams(self, obs, next, now_us);
        }
        let mut x = xml::Xml::new("Streams", 1024 + obs.len() * 160);
        let (n, f, l) = (
            next.to_string(),
            self.buffer.first().to_string(),
            self.buffer.last().max(1).to_string(),
        );
        let mt = self.model_change_time();
        self.header(
            &mut x,
            now_us,
            Some(&[
                ("nextSequence", n.as_str()),
                ("firstSequence", f.as_str()),
                ("lastSequence", l.as_str()),
                ("deviceModelChangeTime", mt.as_str()),
            ]),
        );
        x.open("Streams", &[]);
        for (d, comps) in self.grouped(obs) {
            let dev = &self.model.devices[d];
            x.open("DeviceStream", &[("name", &dev.name), ("uuid", &dev.uuid)]);
            for (c, list) in comps {
                let comp = &self.model.components[c];
                let mut attrs = vec![
                    ("component", comp.element),
                    ("componentId", comp.id.as_str()),
                ];
                if let Some(n) = &comp.name {
                    attrs.push(("name", n.as_str()));
                }
                x.open("ComponentStream", &attrs);
                for (cat, wrap) in [
                    (Category::Sample, "Samples"),
                    (Category::Event, "Events"),
                    (Category::Condition, "Condition"),
                ] {
                    let of: Vec<&&Observation> = list
                        .iter()
                        .filter(|o| self.model.items[o.item as usize].category == cat)
                        .collect();
                    if of.is_empty() {
                        continue;
                    }
                    x.open(wrap, &[]);
                    for o in of {
                        self.observation_xml(&mut x, o);
                    }
                    x.close(wrap);
                }
                x.close("ComponentStream");
            }
            x.close("DeviceStream");
        }
        x.close("Streams");
        x.finish("Streams")
    }

    fn observation_xml(&self, x: &mut xml::Xml, o: &Observation) {
        let item = &self.model.items[o.item as usize];
        let ts = xml::timestamp(o.time_us);
        let seq = o.seq.to_string();
        let mut attrs = vec![
            ("dataItemId", item.id.as_str()),
            ("timestamp", ts.as_str()),
            ("sequence", seq.as_str()),
        ];
        if let Some(n) = &item.name {
            attrs.push(("name", n.as_str()));
        }
        if let Some(s) = item.sub_type {
            attrs.push(("subType", s));
        }
        if item.category == Category::Condition {
            attrs.push(("type", item.kind));
            match &o.value {
                Value::Cond(c) => {
                    if !c.native_code.is_empty() {
                        attrs.push(("nativeCode", &c.native_code));
                        // One activation per native code: its id is the code.
                        attrs.push(("conditionId", &c.native_code));
                    }
                    x.text(c.level.element(), &attrs, &c.text);
                }
                _ => x.empty("Unavailable", &attrs),
            }
            return;
        }
        let element = xml::element_of(item.kind);
        if matches!(item.role, Role::AssetChanged | Role::AssetRemoved) {
            // The schema wants the asset's type: File, the only kind kept; none when none.
            let kind = match o.value {
                Value::Text(_) => "File",
                _ => "UNAVAILABLE",
            };
            attrs.push(("assetType", kind));
        }
        match &o.value {
            Value::Text(t) => x.text(&element, &attrs, t),
            _ => x.text(&element, &attrs, "UNAVAILABLE"),
        }
    }
}

/// What of a machine's description its data items show.
fn machine_shape(m: &super::desc::MachineDesc) -> (bool, bool, bool) {
    (m.protocol.is_a_family(), m.g05, m.part_counter.is_some())
}

/// What of a PLC's description its data items show.
fn plc_shape(p: &super::desc::PlcDesc) -> (Vec<u32>, Vec<(String, Option<&'static str>)>) {
    let tags = p
        .tags
        .iter()
        .map(|t| (t.name.clone(), t.typed.map(|t| t.name)))
        .collect();
    (p.stations.clone(), tags)
}

/// What a device's view wants of each of the device's data items, where it wants anything.
fn wanted_of(
    model: &Model,
    dev: usize,
    wanted: impl Fn(&Role) -> Option<Wanted>,
) -> Vec<(usize, Wanted)> {
    model.devices[dev]
        .items
        .iter()
        .filter_map(|&i| Some((i, wanted(&model.items[i].role)?)))
        .collect()
}

/// What taking a description again did to one device.
enum Taken {
    /// Added or brought back, with the observations its new data items made.
    Added(usize),
    Changed,
    Kept,
}

impl Taken {
    /// Notes `dev` in the list it belongs to; the observations made.
    fn record(self, dev: usize, added: &mut Vec<usize>, changed: &mut Vec<usize>) -> usize {
        match self {
            Taken::Added(n) => {
                added.push(dev);
                n
            }
            Taken::Changed => {
                changed.push(dev);
                0
            }
            Taken::Kept => 0,
        }
    }
}
