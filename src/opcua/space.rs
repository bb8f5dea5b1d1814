//! The address space: the companion specifications' NodeSets (OPC 40501 and what it depends
//! on, carried in `nodesets/` under the OPC Foundation MIT licence), and one object per
//! machine tool and PLC, built from the types the NodeSets declare.
//!
//! The stack imports NodeSets but does not instantiate types, so a machine tool is built here
//! as OPC 10000-3 §6 describes: every instance declaration of the type and its supertypes whose
//! modelling rule is Mandatory (and the optional ones the cell can fill, by browse path),
//! recursively through each child's own type.

use std::collections::BTreeSet;

use opcua::nodes::{
    DefaultTypeTree, HasNodeId as _, ImportedItem, NodeSetImport, NodeType, Object,
    ReferenceDirection, Variable,
};
use opcua::server::address_space::{AccessLevel, AddressSpace, EventNotifier};
use opcua::types::{
    BrowseDirection, DataValue, NodeClass, NodeId, NodeSetNamespaceMapper, ObjectId, ObjectTypeId,
    QualifiedName, ReferenceTypeId, Variant,
};

use cellgate_core::opcua::{DI_NS, MACHINE_TOOL_NS, MACHINERY_NS};

/// The namespace of the nodes the server makes: the cells' machines and PLCs.
pub const CELLS_NS: &str = "urn:cellgate:cells";

/// The NodeSets, in the order they depend on each other.
const NODESETS: [(&str, &str); 6] = [
    ("DI", include_str!("nodesets/Opc.Ua.Di.NodeSet2.xml")),
    ("IA", include_str!("nodesets/Opc.Ua.IA.NodeSet2.xml")),
    (
        "Machinery",
        include_str!("nodesets/Opc.Ua.Machinery.NodeSet2.xml"),
    ),
    (
        "ISA95-JOBCONTROL",
        include_str!("nodesets/opc.ua.isa95-jobcontrol.nodeset2.xml"),
    ),
    (
        "Machinery/Jobs",
        include_str!("nodesets/Opc.Ua.Machinery.Jobs.Nodeset2.xml"),
    ),
    (
        "MachineTool",
        include_str!("nodesets/Opc.Ua.MachineTool.NodeSet2.xml"),
    ),
];

/// A NodeSet import that registers its namespaces without printing them (the stack's own
/// prints each to standard output, which the gateway keeps for its ready lines).
struct Quiet(opcua::nodes::NodeSet2Import);

impl NodeSetImport for Quiet {
    fn register_namespaces(&self, namespaces: &mut NodeSetNamespaceMapper) {
        // The file's NamespaceUris in order are its indexes 1, 2, …
        for (i, ns) in self.0.get_own_namespaces().iter().enumerate() {
            namespaces.add_namespace(ns, i as u16 + 1);
        }
    }

    fn get_own_namespaces(&self) -> Vec<String> {
        self.0.get_own_namespaces()
    }

    fn load<'a>(
        &'a self,
        namespaces: &'a NodeSetNamespaceMapper,
    ) -> Box<dyn Iterator<Item = ImportedItem> + 'a> {
        self.0.load(namespaces)
    }
}

/// The NodeSets, parsed. They are part of the program: a failure is a bug, said as an error.
pub fn imports() -> Result<Vec<Box<dyn NodeSetImport>>, String> {
    NODESETS
        .iter()
        .map(|(name, xml)| {
            opcua::nodes::NodeSet2Import::new_str("en", xml, Vec::new())
                .map(|i| Box::new(Quiet(i)) as Box<dyn NodeSetImport>)
                .map_err(|e| format!("the {name} NodeSet: {e}"))
        })
        .collect()
}

/// Namespace indexes of the models, as the server numbered them.
#[derive(Debug, Clone, Copy)]
pub struct Ns {
    pub cells: u16,
    pub machine_tool: u16,
    pub machinery: u16,
    pub di: u16,
}

impl Ns {
    pub fn of(space: &AddressSpace) -> Option<Ns> {
        Some(Ns {
            cells: space.namespace_index(CELLS_NS)?,
            machine_tool: space.namespace_index(MACHINE_TOOL_NS)?,
            machinery: space.namespace_index(MACHINERY_NS)?,
            di: space.namespace_index(DI_NS)?,
        })
    }

    /// Machinery's `Machines` folder (OPC 40001-1 §8.1).
    pub fn machines_folder(&self) -> NodeId {
        NodeId::new(self.machinery, 1001)
    }

    /// `MachineToolType`.
    pub fn machine_tool_type(&self) -> NodeId {
        NodeId::new(self.machine_tool, 13)
    }
}

/// Optional instance declarations a machine tool gets, by browse path below the machine: the
/// ones the cell has something for (docs/opcua.md).
const OPTIONAL: [&str; 4] = [
    "Notification/Messages",
    "Production/ActiveProgram",
    "Monitoring/MachineTool/OperationCounters",
    "Monitoring/MachineTool/OperationCounters/PartsProducedInLifetime",
];

/// Looks nodes and references up in the server's own space first, then in the base
/// namespace's (ns 0 lives in the stack's core node manager).
pub struct Spaces<'a> {
    pub own: &'a AddressSpace,
    pub core: &'a AddressSpace,
    pub types: &'a DefaultTypeTree,
}

impl Spaces<'_> {
    fn space(&self, id: &NodeId) -> &AddressSpace {
        if id.namespace == 0 {
            self.core
        } else {
            self.own
        }
    }

    fn find(&self, id: &NodeId) -> Option<&NodeType> {
        self.space(id).find(id)
    }

    fn targets(
        &self,
        id: &NodeId,
        r: ReferenceTypeId,
        dir: BrowseDirection,
    ) -> Vec<(NodeId, NodeId)> {
        self.space(id)
            .find_references(id, Some((r, true)), self.types, dir)
            .map(|x| (x.reference_type.clone(), x.target_node.clone()))
            .collect()
    }

    fn one(&self, id: &NodeId, r: ReferenceTypeId, dir: BrowseDirection) -> Option<NodeId> {
        self.targets(id, r, dir).into_iter().next().map(|(_, t)| t)
    }

    fn type_of(&self, id: &NodeId) -> Option<NodeId> {
        self.one(
            id,
            ReferenceTypeId::HasTypeDefinition,
            BrowseDirection::Forward,
        )
    }

    /// The declarations below `node` (a type or an instance declaration), with the reference
    /// that holds them, that an instance gets: Mandatory ones, and optional ones on `path`.
    fn declarations(&self, node: &NodeId, path: &str) -> Vec<(NodeId, NodeId, String)> {
        let mut out = Vec::new();
        for (r, child) in self.targets(
            node,
            ReferenceTypeId::HierarchicalReferences,
            BrowseDirection::Forward,
        ) {
            if r == ReferenceTypeId::HasSubtype {
                continue;
            }
            let Some(n) = self.find(&child) else { continue };
            if !matches!(n.node_class(), NodeClass::Object | NodeClass::Variable) {
                continue;
            }
            let name = n.as_node().browse_name().name.to_string();
            let at = if path.is_empty() {
                name.clone()
            } else {
                format!("{path}/{name}")
            };
            let rule = self.one(
                &child,
                ReferenceTypeId::HasModellingRule,
                BrowseDirection::Forward,
            );
            let mandatory = rule == Some(ObjectId::ModellingRule_Mandatory.into());
            let wanted = rule.is_some() && OPTIONAL.contains(&at.as_str());
            if mandatory || wanted {
                out.push((r, child, name));
            }
        }
        out
    }

    /// The declarations an instance of `type_id` gets, the subtype's first.
    fn type_declarations(&self, type_id: &NodeId, path: &str) -> Vec<(NodeId, NodeId, String)> {
        let mut out: Vec<(NodeId, NodeId, String)> = Vec::new();
        let mut t = Some(type_id.clone());
        let mut hops = 0;
        while let Some(id) = t {
            for d in self.declarations(&id, path) {
                if !out.iter().any(|o| o.2 == d.2) {
                    out.push(d);
                }
            }
            t = self.one(&id, ReferenceTypeId::HasSubtype, BrowseDirection::Inverse);
            hops += 1;
            if hops > 32 {
                break;
            }
        }
        out
    }
}

/// A node to add, and the reference from its parent.
pub struct Planned {
    pub parent: NodeId,
    pub reference: NodeId,
    pub node: NodeType,
    pub type_definition: Option<NodeId>,
}

/// Plans an instance of `type_id` named `name` below `parent` (by `reference`), its node ids
/// `s=ID_PREFIX/Path/To/Child` in the cells' namespace.
pub fn plan_instance(
    spaces: &Spaces<'_>,
    ns: u16,
    id: &str,
    name: &str,
    type_id: &NodeId,
    parent: &NodeId,
    reference: NodeId,
) -> Vec<Planned> {
    let root = NodeId::new(ns, id.to_string());
    let mut out = vec![Planned {
        parent: parent.clone(),
        reference,
        node: Object::new(
            &root,
            QualifiedName::new(ns, name),
            name,
            EventNotifier::empty(),
        )
        .into(),
        type_definition: Some(type_id.clone()),
    }];
    let mut seen = BTreeSet::new();
    plan_children(
        spaces,
        ns,
        &root,
        id,
        "",
        std::slice::from_ref(type_id),
        &mut out,
        &mut seen,
        0,
    );
    out
}

/// Plans the children of instance `node` (its id `id`, at `path` below the machine), declared
/// by `sources` (its declaration and its type).
#[allow(clippy::too_many_arguments)]
fn plan_children(
    spaces: &Spaces<'_>,
    ns: u16,
    node: &NodeId,
    id: &str,
    path: &str,
    sources: &[NodeId],
    out: &mut Vec<Planned>,
    seen: &mut BTreeSet<String>,
    depth: usize,
) {
    if depth > 12 {
        return;
    }
    // Every declaration of a name counts: a child declared on the instance declaration
    // overrides the type's attributes, and the children of both are the child's (the fully
    // inherited instance declaration hierarchy, OPC 10000-3 §6.3.3.3).
    let mut decls: Vec<(NodeId, String, Vec<NodeId>)> = Vec::new();
    for s in sources {
        let found = if spaces.find(s).is_some_and(|n| {
            matches!(
                n.node_class(),
                NodeClass::ObjectType | NodeClass::VariableType
            )
        }) {
            spaces.type_declarations(s, path)
        } else {
            spaces.declarations(s, path)
        };
        for (r, d, name) in found {
            match decls.iter_mut().find(|o| o.1 == name) {
                Some(o) => o.2.push(d),
                None => decls.push((r, name, vec![d])),
            }
        }
    }
    for (reference, name, all) in decls {
        let decl = all[0].clone();
        let child_id = format!("{id}/{name}");
        if !seen.insert(child_id.clone()) {
            continue;
        }
        let child_path = if path.is_empty() {
            name.clone()
        } else {
            format!("{path}/{name}")
        };
        let Some(d) = spaces.find(&decl) else {
            continue;
        };
        let new_id = NodeId::new(ns, child_id.clone());
        // Messages is where the machine's alerts come from: clients subscribe to it.
        let notify = name == "Messages";
        let Some(made) = copy_node(d, &new_id, None, notify) else {
            continue;
        };
        let type_definition = spaces.type_of(&decl);
        out.push(Planned {
            parent: node.clone(),
            reference,
            node: made,
            type_definition: type_definition.clone(),
        });
        let mut next = Vec::new();
        for d in &all {
            next.push(d.clone());
            next.extend(spaces.type_of(d));
        }
        next.dedup();
        plan_children(
            spaces,
            ns,
            &new_id,
            &child_id,
            &child_path,
            &next,
            out,
            seen,
            depth + 1,
        );
    }
}

/// A node like `d` (an instance declaration, or a template's node) with id `id`, read-only,
/// without a value; named `name` when given; an object that notifies events with `notify`.
fn copy_node(d: &NodeType, id: &NodeId, name: Option<&str>, notify: bool) -> Option<NodeType> {
    let (browse, display) = match name {
        Some(n) => (QualifiedName::new(id.namespace, n), n.into()),
        None => (
            d.as_node().browse_name().clone(),
            d.as_node().display_name().clone(),
        ),
    };
    Some(match d {
        NodeType::Variable(v) => {
            let mut var = Variable::new_full(
                opcua::nodes::Base::new(NodeClass::Variable, id, browse, display),
                v.data_type(),
                false,
                v.value_rank(),
                DataValue::null(),
                AccessLevel::CURRENT_READ.bits(),
                AccessLevel::CURRENT_READ.bits(),
                v.array_dimensions(),
                None,
            );
            var.set_data_value(DataValue::new_now(Variant::Empty));
            var.into()
        }
        NodeType::Object(o) => {
            let notifier = if notify {
                EventNotifier::SUBSCRIBE_TO_EVENTS
            } else {
                o.event_notifier()
            };
            Object::new(id, browse, display, notifier).into()
        }
        _ => return None,
    })
}

/// An instance planned once per type, stamped out for each machine: walking the type's
/// declarations costs milliseconds, a copy microseconds.
pub struct Template {
    planned: Vec<Planned>,
}

/// The id the template's nodes start with.
const TEMPLATE: &str = "\u{1}";

impl Template {
    /// Plans an instance of `type_id` once.
    pub fn of(spaces: &Spaces<'_>, ns: u16, type_id: &NodeId) -> Template {
        let placeholder = NodeId::new(ns, "\u{2}");
        Template {
            planned: plan_instance(
                spaces,
                ns,
                TEMPLATE,
                TEMPLATE,
                type_id,
                &placeholder,
                ReferenceTypeId::Organizes.into(),
            ),
        }
    }

    /// The instance with ids `s=ID/…`, named `name`, below `parent` by `reference`.
    pub fn stamp(&self, id: &str, name: &str, parent: &NodeId, reference: NodeId) -> Vec<Planned> {
        let renamed = |n: &NodeId| -> Option<NodeId> {
            match &n.identifier {
                opcua::types::Identifier::String(s) => {
                    let rest = s.as_ref().strip_prefix(TEMPLATE)?;
                    Some(NodeId::new(n.namespace, format!("{id}{rest}")))
                }
                _ => None,
            }
        };
        self.planned
            .iter()
            .enumerate()
            .filter_map(|(i, p)| {
                let new_id = renamed(p.node.node_id())?;
                let root = i == 0;
                let notify = p.node.as_node().browse_name().name.as_ref() == "Messages";
                Some(Planned {
                    parent: if root {
                        parent.clone()
                    } else {
                        renamed(&p.parent)?
                    },
                    reference: if root {
                        reference.clone()
                    } else {
                        p.reference.clone()
                    },
                    node: copy_node(&p.node, &new_id, root.then_some(name), notify)?,
                    type_definition: p.type_definition.clone(),
                })
            })
            .collect()
    }
}

/// Adds what was planned; answers the ids added.
pub fn add(space: &mut AddressSpace, planned: Vec<Planned>) -> Vec<NodeId> {
    let mut added = Vec::with_capacity(planned.len());
    for p in planned {
        let id = p.node.node_id().clone();
        let mut refs: Vec<(NodeId, NodeId, ReferenceDirection)> = vec![(
            p.parent.clone(),
            p.reference.clone(),
            ReferenceDirection::Inverse,
        )];
        if let Some(t) = &p.type_definition {
            refs.push((
                t.clone(),
                ReferenceTypeId::HasTypeDefinition.into(),
                ReferenceDirection::Forward,
            ));
        }
        let refs: Vec<(&NodeId, &NodeId, ReferenceDirection)> =
            refs.iter().map(|(a, b, c)| (a, b, *c)).collect();
        if space.insert(p.node, Some(refs.as_slice())) {
            added.push(id);
        }
    }
    added
}

/// Removes nodes that were added, with their references.
pub fn remove(space: &mut AddressSpace, ids: &[NodeId]) {
    for id in ids {
        space.delete(id, true);
    }
}

/// The base object type, for a PLC: a device of DI's `DeviceType` would ask for a nameplate
/// the line does not give; a `BaseObjectType` with its tags as variables says only what is
/// known.
pub fn base_object_type() -> NodeId {
    ObjectTypeId::BaseObjectType.into()
}
