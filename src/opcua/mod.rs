//! The OPC UA server (docs/opcua.md): the cell's machines as OPC 40501 machine tools and its
//! PLCs as objects with their tags, built only from the public bus contract like the console
//! and the MTConnect agent. The gateway serves one for its own cell (`[opcua]`), on its own
//! session; `cellgate opcua` serves every cell behind a router, on a session of its own: the
//! same code. It only reads: every write and method call is refused.
//!
//! - [`space`]: the NodeSets and the instances of their types;
//! - [`auth`]: who may open a session;
//! - what each node shows is the core's ([`cellgate_core::opcua`]): this room only does I/O.

pub mod auth;
pub mod space;

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use opcua::nodes::BaseEventType;
use opcua::server::address_space::AddressSpace;
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::ServerContext;
use opcua::server::node_manager::memory::{
    InMemoryNodeManager, InMemoryNodeManagerBuilder, InMemoryNodeManagerImpl,
    InMemoryNodeManagerImplBuilder,
};
use opcua::server::{ServerBuilder, ServerEndpoint, ServerHandle, SubscriptionCache};
use opcua::types::{
    ByteString, DataValue, DateTime, LocalizedText, NodeId, ReferenceTypeId, StatusCode, UAString,
    Variant,
};
use tokio_util::sync::CancellationToken;
use zenoh::Session;

use crate::client::follow::{self, Follower};
use cellgate_core::config::{OpcuaConfig, SecurityConfig};
use cellgate_core::mtconnect::{CellDesc, Update};
use cellgate_core::opcua::{MachineShows, Model, Out};

/// What the server serves and how.
#[derive(Debug, Clone)]
pub struct OpcuaSettings {
    pub config: OpcuaConfig,
    /// The bus prefix `P` of the cells.
    pub prefix: String,
    /// The one cell served; `None`: every cell that answers (site view).
    pub only: Option<String>,
    /// The gateway's own cell, described by its cell file (its gateway is not asked).
    pub own: Option<CellDesc>,
    /// Users and roles.
    pub security: SecurityConfig,
    /// Where the PKI folder is when `config.pki_dir` does not say.
    pub default_pki: PathBuf,
}

/// Why the server stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum OpcuaError {
    #[error("opcua: cannot listen on {addr}: {source}")]
    Bind {
        addr: String,
        #[source]
        source: std::io::Error,
    },
    #[error("opcua: {0}")]
    Setup(String),
    #[error("opcua: subscribing to the cells' publications: {0}")]
    Subscribe(#[source] zenoh::Error),
}

/// The node manager of the companion specifications and the cells' nodes.
pub struct CellNodes {
    name: String,
    namespaces: Vec<NamespaceMetadata>,
}

#[async_trait::async_trait]
impl InMemoryNodeManagerImpl for CellNodes {
    async fn init(&self, _space: &mut AddressSpace, _context: ServerContext) {}

    fn name(&self) -> &str {
        &self.name
    }

    fn namespaces(&self) -> Vec<NamespaceMetadata> {
        self.namespaces.clone()
    }

    /// The server only reads: every write is refused, node by node.
    async fn write(
        &self,
        _context: &opcua::server::node_manager::RequestContext,
        _space: &opcua::sync::RwLock<AddressSpace>,
        nodes: &mut [&mut opcua::server::node_manager::WriteNode],
    ) -> Result<(), StatusCode> {
        for n in nodes {
            n.set_status(StatusCode::BadNotWritable);
        }
        Ok(())
    }

    /// No method runs here (the companion specifications' methods, file transfer and job
    /// control, would act on the cell): every call is refused.
    async fn call(
        &self,
        _context: &opcua::server::node_manager::RequestContext,
        _space: &opcua::sync::RwLock<AddressSpace>,
        calls: &mut [&mut &mut opcua::server::node_manager::MethodCall],
    ) -> Result<(), StatusCode> {
        for c in calls {
            c.set_status(StatusCode::BadNotExecutable);
        }
        Ok(())
    }
}

/// Builds [`CellNodes`]: imports the NodeSets and opens the cells' namespace.
struct CellNodesBuilder {
    imports: Vec<Box<dyn opcua::nodes::NodeSetImport>>,
}

impl InMemoryNodeManagerImplBuilder for CellNodesBuilder {
    type Impl = CellNodes;

    fn build(self, context: ServerContext, space: &mut AddressSpace) -> CellNodes {
        let mut uris: Vec<String> = Vec::new();
        let mut types = context.type_tree.write();
        for import in &self.imports {
            space.import_node_set(&**import, types.namespaces_mut());
            for ns in import.get_own_namespaces() {
                if !uris.contains(&ns) {
                    uris.push(ns);
                }
            }
        }
        uris.push(space::CELLS_NS.to_string());
        let mut namespaces = Vec::new();
        for uri in uris {
            let index = types.namespaces_mut().add_namespace(&uri);
            space.add_namespace(&uri, index);
            namespaces.push(NamespaceMetadata {
                namespace_uri: uri,
                namespace_index: index,
                ..Default::default()
            });
        }
        CellNodes {
            name: "cellgate".to_string(),
            namespaces,
        }
    }
}

/// An alert of a machine: OPC 40501's NotificationEventType, from the machine's
/// Notification/Messages.
#[derive(opcua::Event)]
#[opcua(
    identifier = "i=35",
    namespace = "http://opcfoundation.org/UA/MachineTool/"
)]
pub struct Notification {
    base: BaseEventType,
    own_namespace_index: u16,
    /// The SR number or cellgate's own code.
    identifier: UAString,
}

/// The nodes of one machine or PLC, to set values on and to remove.
#[derive(Default)]
struct Shape {
    nodes: Vec<NodeId>,
}

/// The server's view of the cells: the model, and the nodes it made.
pub struct Shown {
    manager: Arc<InMemoryNodeManager<CellNodes>>,
    subscriptions: Arc<SubscriptionCache>,
    handle: ServerHandle,
    ns: space::Ns,
    /// Names machines `CELL.MACHINE` (a site server).
    qualify: bool,
    model: Mutex<Model>,
    shapes: Mutex<HashMap<(String, String), Shape>>,
    /// Each type's instance, planned once.
    templates: Mutex<HashMap<NodeId, space::Template>>,
}

impl Shown {
    fn model(&self) -> MutexGuard<'_, Model> {
        self.model.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn id(&self, cell: &str, name: &str) -> String {
        format!("{cell}/{name}")
    }

    fn node(&self, cell: &str, name: &str, path: &str) -> NodeId {
        NodeId::new(self.ns.cells, format!("{cell}/{name}/{path}"))
    }

    fn shown_name(&self, cell: &str, name: &str) -> String {
        if self.qualify {
            format!("{cell}.{name}")
        } else {
            name.to_string()
        }
    }

    /// Builds the nodes of `desc`'s machines and PLCs that are not there, removes those gone.
    fn reshape(&self, desc: &CellDesc) {
        let mut shapes = self.shapes.lock().unwrap_or_else(|e| e.into_inner());
        let wanted: Vec<(String, bool)> = desc
            .machines
            .iter()
            .map(|m| (m.name.clone(), true))
            .chain(desc.plcs.iter().map(|p| (p.name.clone(), false)))
            .collect();
        let gone: Vec<(String, String)> = shapes
            .keys()
            .filter(|(c, n)| *c == desc.cell && !wanted.iter().any(|(w, _)| w == n))
            .cloned()
            .collect();
        let core = self
            .handle
            .node_managers()
            .get_of_type::<opcua::server::node_manager::memory::CoreNodeManager>();
        let mut changed = !gone.is_empty();
        {
            let mut own = self.manager.address_space().write();
            for k in gone {
                if let Some(s) = shapes.remove(&k) {
                    space::remove(&mut own, &s.nodes);
                }
            }
        }
        for (name, machine) in wanted {
            let key = (desc.cell.clone(), name.clone());
            if shapes.contains_key(&key) {
                continue;
            }
            changed = true;
            let planned = {
                let own = self.manager.address_space().read();
                let core_space = core.as_ref().map(|c| c.address_space().read());
                let types = self.handle.type_tree().read();
                let empty = AddressSpace::new();
                let spaces = space::Spaces {
                    own: &own,
                    core: core_space.as_deref().unwrap_or(&empty),
                    types: &types,
                };
                let type_id = if machine {
                    self.ns.machine_tool_type()
                } else {
                    space::base_object_type()
                };
                let mut templates = self.templates.lock().unwrap_or_else(|e| e.into_inner());
                let mut planned = templates
                    .entry(type_id.clone())
                    .or_insert_with(|| space::Template::of(&spaces, self.ns.cells, &type_id))
                    .stamp(
                        &self.id(&desc.cell, &name),
                        &self.shown_name(&desc.cell, &name),
                        &self.ns.machines_folder(),
                        ReferenceTypeId::Organizes.into(),
                    );
                if machine {
                    // The remote buffer feeds one NC channel: a `ChannelMonitoringType`
                    // object under Monitoring.
                    let channel = NodeId::new(self.ns.machine_tool, 16);
                    planned.extend(
                        templates
                            .entry(channel.clone())
                            .or_insert_with(|| {
                                space::Template::of(&spaces, self.ns.cells, &channel)
                            })
                            .stamp(
                                &format!("{}/Monitoring/Channel1", self.id(&desc.cell, &name)),
                                "Channel1",
                                &self.node(&desc.cell, &name, "Monitoring"),
                                ReferenceTypeId::HasComponent.into(),
                            ),
                    );
                } else if let Some(p) = desc.plcs.iter().find(|p| p.name == name) {
                    planned.extend(self.tags(&desc.cell, p));
                }
                planned
            };
            let mut own = self.manager.address_space().write();
            let nodes = space::add(&mut own, planned);
            drop(own);
            if machine && let Some(m) = desc.machines.iter().find(|m| m.name == name) {
                self.identify(&desc.cell, m);
            }
            shapes.insert(key, Shape { nodes });
        }
        if changed {
            tracing::info!(cell = %desc.cell, "opcua: the cell's nodes follow its machines and PLCs");
            // Part 3 §9.32: BaseModelChangeEventType says nodes came or went; a client
            // browses again.
            let mut id = [0u8; 16];
            let _ = getrandom::fill(&mut id);
            let server: NodeId = opcua::types::ObjectId::Server.into();
            let event = BaseEventType::new_now(
                opcua::types::ObjectTypeId::BaseModelChangeEventType,
                ByteString::from(id.to_vec()),
                LocalizedText::new(
                    "en",
                    &format!("the machines and PLCs of cell {} changed", desc.cell),
                ),
            )
            .set_source_node(server.clone())
            .set_source_name(UAString::from("Server"))
            .set_severity(100);
            self.subscriptions
                .notify_events([(&event as &dyn opcua::nodes::Event, &server)].into_iter());
        }
    }

    /// A PLC's tags, as variables of the PLC's object.
    fn tags(&self, cell: &str, p: &cellgate_core::mtconnect::desc::PlcDesc) -> Vec<space::Planned> {
        use opcua::nodes::{Base, NodeBase as _, Variable};
        use opcua::types::{DataTypeId, NodeClass, QualifiedName, VariableTypeId};
        let read = opcua::server::address_space::AccessLevel::CURRENT_READ.bits();
        let variable = |id: &NodeId, name: QualifiedName, data_type: DataTypeId, value| {
            let display = name.name.to_string();
            Variable::new_full(
                Base::new(NodeClass::Variable, id, name, display.as_str()),
                data_type.into(),
                false,
                -1,
                value,
                read,
                read,
                None,
                None,
            )
        };
        let parent = NodeId::new(self.ns.cells, self.id(cell, &p.name));
        let mut out = Vec::new();
        for t in &p.tags {
            let id = self.node(cell, &p.name, &t.name);
            let mut v = variable(
                &id,
                QualifiedName::new(self.ns.cells, t.name.as_str()),
                DataTypeId::Double,
                DataValue::null(),
            );
            v.set_description(LocalizedText::new("", t.native.as_str()));
            // A measured value with units: BaseAnalogType with its EngineeringUnits (Part 8
            // §5.3.2), the units the tag's `mtconnect` type reports in.
            let unit = t.units.and_then(cellgate_core::opcua::engineering_unit);
            out.push(space::Planned {
                parent: parent.clone(),
                reference: ReferenceTypeId::HasComponent.into(),
                node: v.into(),
                type_definition: Some(if unit.is_some() {
                    VariableTypeId::BaseAnalogType.into()
                } else {
                    VariableTypeId::BaseDataVariableType.into()
                }),
            });
            if let Some((unit_id, symbol, name)) = unit {
                let eu = opcua::types::EUInformation {
                    namespace_uri: UAString::from(cellgate_core::opcua::UNECE_UNITS_NS),
                    unit_id,
                    display_name: LocalizedText::new("", symbol),
                    description: LocalizedText::new("en", name),
                };
                let value =
                    DataValue::new_now(Variant::from(opcua::types::ExtensionObject::new(eu)));
                let property = variable(
                    &self.node(cell, &p.name, &format!("{}/EngineeringUnits", t.name)),
                    QualifiedName::new(0, "EngineeringUnits"),
                    DataTypeId::EUInformation,
                    value,
                );
                out.push(space::Planned {
                    parent: id.clone(),
                    reference: ReferenceTypeId::HasProperty.into(),
                    node: property.into(),
                    type_definition: Some(VariableTypeId::PropertyType.into()),
                });
            }
        }
        out
    }

    /// Identification: the cell file's `identification`, else defaults that say so.
    fn identify(&self, cell: &str, m: &cellgate_core::mtconnect::desc::MachineDesc) {
        let id = &m.identification;
        let manufacturer = id
            .manufacturer
            .clone()
            .unwrap_or_else(|| "unknown (identification.manufacturer not set)".to_string());
        let serial = id
            .serial_number
            .clone()
            .unwrap_or_else(|| "unknown (identification.serial_number not set)".to_string());
        let uri = id
            .product_instance_uri
            .clone()
            .unwrap_or_else(|| format!("urn:cellgate:{cell}:{}", m.name));
        self.set(vec![
            (
                self.node(cell, &m.name, "Identification/Manufacturer"),
                Variant::from(LocalizedText::new("", &manufacturer)),
                StatusCode::Good,
            ),
            (
                self.node(cell, &m.name, "Identification/SerialNumber"),
                Variant::from(serial),
                StatusCode::Good,
            ),
            (
                self.node(cell, &m.name, "Identification/ProductInstanceUri"),
                Variant::from(uri),
                StatusCode::Good,
            ),
        ]);
    }

    fn set(&self, values: Vec<(NodeId, Variant, StatusCode)>) {
        let now = DateTime::now();
        let values: Vec<(NodeId, DataValue)> = values
            .into_iter()
            .map(|(id, v, status)| {
                let mut dv = DataValue::new_at(v, now);
                dv.status = Some(status);
                (id, dv)
            })
            .collect();
        let space = self.manager.address_space().read();
        let values: Vec<(NodeId, DataValue)> = values
            .into_iter()
            .filter(|(id, _)| space.node_exists(id))
            .collect();
        drop(space);
        if let Err(e) = self.manager.set_values(
            &self.subscriptions,
            values.iter().map(|(id, v)| (id, None, v.clone())),
        ) {
            tracing::warn!(error = %e, "opcua: values not set");
        }
    }

    fn machine_values(
        &self,
        cell: &str,
        machine: &str,
        s: &MachineShows,
    ) -> Vec<(NodeId, Variant, StatusCode)> {
        let live = if s.reachable {
            StatusCode::Good
        } else {
            StatusCode::BadNoCommunication
        };
        let n = |p: &str| self.node(cell, machine, p);
        let state_node = NodeId::new(self.ns.machine_tool, s.state.state_node());
        // Other is what the line cannot tell apart (docs/opcua.md): Good, as the standard's
        // clients read it, not Uncertain, which most refuse to read as a value.
        let mode_status = live;
        let mut v = vec![
            (
                n("Production/ActiveProgram/Name"),
                Variant::from(s.program.clone()),
                StatusCode::Good,
            ),
            (
                n("Production/ActiveProgram/NumberInList"),
                Variant::from(0u16),
                StatusCode::Good,
            ),
            (
                n("Production/ActiveProgram/State/CurrentState"),
                Variant::from(LocalizedText::new("en", s.state.name())),
                StatusCode::Good,
            ),
            (
                n("Production/ActiveProgram/State/CurrentState/Id"),
                Variant::from(state_node),
                StatusCode::Good,
            ),
            (
                n("Production/ActiveProgram/State/CurrentState/Number"),
                Variant::from(s.state.number()),
                StatusCode::Good,
            ),
            (
                n("Monitoring/MachineTool/OperationMode"),
                Variant::from(s.mode as i32),
                mode_status,
            ),
            (
                n("Monitoring/Channel1/ChannelState"),
                Variant::from(s.channel as i32),
                live,
            ),
        ];
        if let Some(parts) = s.parts {
            v.push((
                n("Monitoring/MachineTool/OperationCounters/PartsProducedInLifetime"),
                Variant::from(parts.max(0) as u64),
                live,
            ));
        }
        v
    }

    fn apply(&self, outs: Vec<Out>) {
        let mut values = Vec::new();
        for o in outs {
            match o {
                Out::Machine {
                    cell,
                    machine,
                    shows,
                } => {
                    values.extend(self.machine_values(&cell, &machine, &shows));
                }
                Out::Plc {
                    cell,
                    plc,
                    up,
                    tags,
                } => {
                    for (tag, value) in tags {
                        let (v, status) = match value {
                            Some(v) if up => (Variant::from(v), StatusCode::Good),
                            _ => (Variant::Empty, StatusCode::BadNoCommunication),
                        };
                        values.push((self.node(&cell, &plc, &tag), v, status));
                    }
                }
                Out::Alert {
                    cell,
                    machine,
                    alert,
                } => self.alert(&cell, &machine, &alert),
            }
        }
        if !values.is_empty() {
            self.set(values);
        }
    }

    /// Sends an alert from the machine's Notification/Messages: to its subscribers and to the
    /// Server object's.
    fn alert(&self, cell: &str, machine: &str, alert: &cellgate_core::opcua::Alert) {
        let source = self.node(cell, machine, "Notification/Messages");
        let mut id = [0u8; 16];
        let _ = getrandom::fill(&mut id);
        let event = Notification {
            base: BaseEventType::new_now(
                NodeId::new(self.ns.machine_tool, 35),
                ByteString::from(id.to_vec()),
                LocalizedText::new("en", &format!("{}: {}", alert.code, alert.message)),
            )
            .set_source_node(source.clone())
            .set_source_name(UAString::from(self.shown_name(cell, machine)))
            .set_severity(alert.severity),
            own_namespace_index: self.ns.machine_tool,
            identifier: UAString::from(alert.code.as_str()),
        };
        tracing::info!(cell, machine, code = %alert.code, "opcua: alert");
        // The stack hands an event of any node to the Server object's subscribers as well.
        self.subscriptions
            .notify_events([(&event as &dyn opcua::nodes::Event, &source)].into_iter());
    }
}

impl Follower for Shown {
    fn known(&self, cell: &str) -> Option<CellDesc> {
        self.model().desc(cell).cloned()
    }

    fn describe(&self, desc: &CellDesc) {
        self.reshape(desc);
        let outs = self.model().set_cell(desc);
        self.apply(outs);
    }

    fn take(&self, cell: &str, updates: Vec<Update>) {
        let mut outs = Vec::new();
        {
            let mut model = self.model();
            for u in updates {
                outs.extend(model.update(cell, u));
            }
        }
        self.apply(outs);
    }
}

/// How long the server lets sessions close when it stops.
const STOP_GRACE: Duration = Duration::from_secs(5);

/// A server listening, and its URL.
pub struct Served {
    pub url: String,
    pub shown: Arc<Shown>,
    pub auth: Option<Arc<crate::console::auth::Auth>>,
    task: tokio::task::JoinHandle<()>,
    handle: ServerHandle,
}

impl Served {
    /// Stops the server (its stop token cancelled) and waits, at most `STOP_GRACE`.
    pub async fn join(mut self) {
        self.handle.cancel();
        if tokio::time::timeout(STOP_GRACE, &mut self.task)
            .await
            .is_err()
        {
            tracing::warn!("opcua: sessions still open when it stopped; cut short");
            self.task.abort();
        }
    }

    /// Takes a reloaded `[security]`: users gone or changed log in no more.
    pub fn reload(&self, security: &SecurityConfig) {
        if let Some(a) = &self.auth {
            a.set_security(security);
        }
    }
}

/// Serves the OPC UA server on `session` until `stop`. Binds at once (so a port taken is an
/// error now), then serves in a task.
pub async fn serve(
    session: Session,
    settings: OpcuaSettings,
    stop: CancellationToken,
) -> Result<Served, OpcuaError> {
    let addr = settings.config.listen.clone();
    let tcp = tokio::net::TcpListener::bind(&addr)
        .await
        .map_err(|source| OpcuaError::Bind {
            addr: addr.clone(),
            source,
        })?;
    let local = tcp.local_addr().map_err(|source| OpcuaError::Bind {
        addr: addr.clone(),
        source,
    })?;
    let secured = auth::secured(&settings.security);
    if secured && settings.security.users_file.is_none() {
        tracing::warn!(
            "opcua: the cell has [security] but no users file: the OPC UA server takes user \
             names and passwords only, so nobody can open a session"
        );
    }
    let auth = secured.then(|| {
        Arc::new(crate::console::auth::Auth::new(
            &settings.security,
            Duration::from_secs(3600),
            Duration::from_secs(3600),
            1,
        ))
    });
    let (server, handle) = build_server(&settings, local, auth.clone())?;
    let manager = handle
        .node_managers()
        .get_of_type::<InMemoryNodeManager<CellNodes>>()
        .ok_or_else(|| OpcuaError::Setup("the cells' node manager is missing".into()))?;
    // The stack takes any number of connections and gives each 5 s for its Hello: clients
    // come in through a door (the listeners' cap on connections, a write timeout) and are
    // relayed to the stack's own listener on loopback.
    let inner = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .map_err(|source| OpcuaError::Bind {
            addr: "127.0.0.1:0".into(),
            source,
        })?;
    let inner_addr = inner.local_addr().map_err(|source| OpcuaError::Bind {
        addr: "127.0.0.1:0".into(),
        source,
    })?;
    let door = crate::door::Door::new("opcua", tcp, crate::door::connection_cap(), b"");
    tokio::spawn(relay(door, inner_addr, stop.clone()));
    let task_handle = handle.clone();
    let task = tokio::spawn(async move {
        if let Err(e) = server.run_with(inner).await {
            tracing::error!(error = %e, "opcua: the server stopped");
        }
        drop(task_handle);
    });
    // The namespaces are numbered once the server initialised its node managers.
    let ns = {
        let mut tries = 0;
        loop {
            // The server initialises its node managers holding the type tree: once the tree
            // knows MachineToolType, that is done and the address space is ours to extend.
            // Never wait on one lock while holding the other.
            let found = {
                let space = manager.address_space().read();
                space::Ns::of(&space)
            }
            .filter(|ns| {
                use opcua::nodes::TypeTree as _;
                handle
                    .type_tree()
                    .try_read()
                    .is_some_and(|t| t.get(&ns.machine_tool_type()).is_some())
            });
            if let Some(ns) = found {
                break ns;
            }
            tries += 1;
            if tries > 200 {
                return Err(OpcuaError::Setup("the address space was not built".into()));
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    };
    let shown = Arc::new(Shown {
        manager,
        subscriptions: handle.subscriptions().clone(),
        handle: handle.clone(),
        ns,
        qualify: settings.only.is_none(),
        model: Mutex::new(Model::new()),
        shapes: Mutex::new(HashMap::new()),
        templates: Mutex::new(HashMap::new()),
    });
    follow::start(
        session,
        settings.prefix.clone(),
        settings.only.clone(),
        settings.own.clone(),
        Arc::clone(&shown) as Arc<dyn Follower>,
        stop,
    )
    .await
    .map_err(OpcuaError::Subscribe)?;
    Ok(Served {
        url: format!("opc.tcp://{local}/"),
        shown,
        auth,
        task,
        handle,
    })
}

/// Relays each connection `door` admits to the stack's listener at `inner`, until `stop`.
async fn relay(door: crate::door::Door, inner: std::net::SocketAddr, stop: CancellationToken) {
    loop {
        let (mut outside, peer) = tokio::select! {
            () = stop.cancelled() => break,
            accepted = door.accept() => accepted,
        };
        let stop = stop.clone();
        tokio::spawn(async move {
            let Ok(mut stack) = tokio::net::TcpStream::connect(inner).await else {
                tracing::warn!(%peer, "opcua: the server's own listener does not answer");
                return;
            };
            let _ = stack.set_nodelay(true);
            tokio::select! {
                () = stop.cancelled() => {}
                r = tokio::io::copy_bidirectional(&mut outside, &mut stack) => {
                    if let Err(e) = r {
                        tracing::debug!(%peer, error = %e, "opcua: connection ended");
                    }
                }
            }
        });
    }
}

/// The server, built in one go: the stack's builder holds what cannot cross an await.
fn build_server(
    settings: &OpcuaSettings,
    local: std::net::SocketAddr,
    auth: Option<Arc<crate::console::auth::Auth>>,
) -> Result<(opcua::server::Server, ServerHandle), OpcuaError> {
    let secured = auth.is_some();
    let gate = Arc::new(auth::Gate { auth: auth.clone() });
    let pki = settings
        .config
        .pki_dir
        .clone()
        .unwrap_or_else(|| settings.default_pki.clone());
    let imports = space::imports().map_err(OpcuaError::Setup)?;
    let host = local.ip().to_string();
    let ids = auth::token_ids();
    let mut builder = ServerBuilder::new()
        .application_name(format!(
            "cellgate {}",
            settings.only.as_deref().unwrap_or("site")
        ))
        .application_uri(format!(
            "urn:cellgate:{}",
            settings.only.as_deref().unwrap_or("site")
        ))
        .product_uri("urn:cellgate")
        .host(host.clone())
        .port(local.port())
        .pki_dir(pki.clone())
        .with_authenticator(gate)
        .with_node_manager(InMemoryNodeManagerBuilder::new(CellNodesBuilder {
            imports,
        }))
        .token(CancellationToken::new())
        .max_sessions(64)
        .discovery_urls(vec![format!("opc.tcp://{local}/")]);
    if secured {
        let mut none = ServerEndpoint::new_none("/", &ids);
        none.password_security_policy = Some("Basic256Sha256".to_string());
        builder = builder
            .create_sample_keypair(settings.config.certificate.is_none())
            .add_endpoint("none", none)
            .add_endpoint(
                "sign",
                ServerEndpoint::new(
                    "/",
                    opcua::crypto::SecurityPolicy::Basic256Sha256,
                    opcua::types::MessageSecurityMode::Sign,
                    &ids,
                ),
            )
            .add_endpoint(
                "sign_encrypt",
                ServerEndpoint::new_basic256sha256_sign_encrypt("/", &ids),
            )
            .default_endpoint("sign_encrypt");
        if let (Some(c), Some(k)) = (&settings.config.certificate, &settings.config.private_key) {
            builder = builder
                .certificate_path(c.clone())
                .private_key_path(k.clone());
        }
    } else {
        builder = builder
            .create_sample_keypair(true)
            .add_endpoint("none", ServerEndpoint::new_none("/", &ids))
            .default_endpoint("none");
    }
    // A client watching every machine of a large cell in one subscription (two items a
    // machine tool) is not refused at a thousand.
    let limits = builder.limits_mut();
    // …nor one that asks for them in one request (an array of 2 048 items; a message stays
    // bounded by its size).
    limits.max_array_length = 16_384;
    limits.subscriptions.max_monitored_items_per_sub = 16_384;
    limits.operational.max_monitored_items_per_call = 16_384;
    let built = builder.build().map_err(OpcuaError::Setup)?;
    // The stack writes the key it made readable by all: only the gateway's user reads it.
    let private = pki.join("private");
    if private.is_dir() {
        use std::os::unix::fs::PermissionsExt as _;
        let _ = std::fs::set_permissions(&private, std::fs::Permissions::from_mode(0o700));
        let key = private.join("private.pem");
        if key.is_file() {
            std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).map_err(
                |e| OpcuaError::Setup(format!("{}: cannot make it private: {e}", key.display())),
            )?;
        }
    }
    Ok(built)
}

/// `cellgate opcua`: the site server, every cell behind the endpoint.
#[derive(Debug, Clone, clap::Args)]
pub struct SiteArgs {
    #[command(flatten)]
    pub connect: crate::client::cli::ConnectArgs,
    /// Where the server listens, ADDRESS:PORT.
    #[arg(long, value_name = "ADDR", default_value = OpcuaConfig::DEFAULT_LISTEN)]
    pub listen: String,
    /// A cell file whose `[security]` users and roles the server takes (and `[opcua]`'s PKI
    /// folder and certificate); without one, sessions are anonymous and it serves loopback
    /// only.
    #[arg(short = 'c', long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// The PKI folder (default: `pki` in the working directory).
    #[arg(long, value_name = "DIR")]
    pub pki_dir: Option<PathBuf>,
}

pub use crate::client::site::SiteError;

impl crate::client::site::SiteServer for Served {
    fn url(&self) -> &str {
        &self.url
    }

    fn join(self) -> impl std::future::Future<Output = ()> + Send {
        Served::join(self)
    }
}

/// Runs the site server until `shutdown`: a session of its own to the endpoint, every cell
/// under the prefix.
pub async fn site(
    args: &SiteArgs,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), SiteError> {
    let (mut config, security) = match &args.config {
        None => (OpcuaConfig::default(), SecurityConfig::default()),
        Some(path) => {
            let cell = cellgate_core::config::CellConfig::load(path)
                .map_err(|e| SiteError::Config(format!("{}: {e}", path.display())))?;
            (cell.opcua.unwrap_or_default(), cell.security)
        }
    };
    config.listen = args.listen.clone();
    if let Some(dir) = &args.pki_dir {
        config.pki_dir = Some(dir.clone());
    }
    if security.users_file.is_none() && !config.is_loopback() {
        return Err(SiteError::Config(format!(
            "--listen {}: beyond this host without users anyone who reaches it could read every \
             cell anonymously; listen on 127.0.0.1, or give --config a cell file with [security] \
             users",
            config.listen
        )));
    }
    let start = |session, options: crate::client::ConnectOptions, stop| {
        let settings = OpcuaSettings {
            config,
            prefix: options.prefix.clone(),
            only: options.cell.clone(),
            own: None,
            security,
            default_pki: PathBuf::from("pki"),
        };
        serve(session, settings, stop)
    };
    crate::client::site::serve(&args.connect, "opcua", start, shutdown).await
}
