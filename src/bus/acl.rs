//! The cell file's roles as zenoh access-control rules for the cell's own keys, so that nobody
//! writes ACL rules for cellgate's key space by hand.
//!
//! How zenoh applies them (zenoh 1.10, `net/routing/interceptor/access_control.rs`): each
//! transport of the gateway's session gets an *ingress* filter for what the remote end sends
//! (queries, puts, deletes, subscriber, queryable and liveliness declarations, liveliness
//! queries) and an *egress* filter for what the gateway sends it (replies, publications, its
//! own declarations and liveliness tokens), both chosen by the remote end's identity: the
//! common name of its TLS certificate, its user name. A message passes when a rule of a
//! subject the transport matches *includes* the message's key expression: a rule on
//! `P/C/machine/*/status` lets a get on `P/C/machine/m1/status` or `P/C/machine/*/status`
//! through, not one on `P/C/**`. Anything else is denied (`default_permission = deny`). A
//! refused query is answered at once with no reply; a refused put or delete vanishes. The
//! gateway's own session talking to itself passes no transport and is never filtered.
//!
//! Zenoh's rules see operations and keys, never payloads, so every write has a key of its own
//! (`…/submit`, `…/program/NAME/write`, `…/mem/…/write`, `…/tag/NAME/set`,
//! `…/transfer/N/send`) and a permission that reads a key never writes through it. The G05
//! keys are all `g05.stream`'s: reading a stream is part of producing one.
//!
//! The keys a permission reads or writes through are the rows of the route table that name it
//! (`routes::granted`): a route added there is granted with no second list here. What the
//! table does not hold stays listed here: the reads several permissions share, the events and
//! publications, the G05 streams, the reload and admin keys.
//!
//! Behind a router the gateway has one transport, the router's, and cannot tell the router's
//! clients apart: the router must hold a role with every permission, and the router enforces
//! the roles on its clients with the rules [`router_access_control`] gives.

use serde_json::{Value, json};

use super::keys::{CellKeys, MachineLeaf, admin_selector, gateway_selector};
use super::{published, routes};
use cellgate_core::config::{Permission, SecurityConfig};

pub use super::error::{AclError, ID_PREFIX};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Flow {
    /// What the remote end sends to the gateway.
    Ingress,
    /// What the gateway sends to the remote end.
    Egress,
}

impl Flow {
    fn name(self) -> &'static str {
        match self {
            Flow::Ingress => "ingress",
            Flow::Egress => "egress",
        }
    }

    fn mirror(self) -> Flow {
        match self {
            Flow::Ingress => Flow::Egress,
            Flow::Egress => Flow::Ingress,
        }
    }
}

/// One allow rule: these messages, in this direction, on keys these patterns include.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Grant {
    flow: Flow,
    messages: &'static [&'static str],
    keys: Vec<String>,
}

const QUERY: &[&str] = &["query"];
const REPLY_AND_QUERYABLE: &[&str] = &["reply", "declare_queryable"];
const WRITE: &[&str] = &["query", "put", "delete"];
const SERVED_WRITE: &[&str] = &["reply", "declare_queryable", "declare_subscriber"];

fn grant(flow: Flow, messages: &'static [&'static str], keys: Vec<String>) -> Grant {
    Grant {
        flow,
        messages,
        keys,
    }
}

/// What every role gets: the gateway's and the machines' liveliness tokens (and the PLC
/// stations', once they exist), so that a client can tell the cell is there. Liveliness gets
/// and subscriptions may name any key of the cell, and `P/*/gateway` for discovery; what
/// comes back is filtered by the egress rule, so only this cell's tokens do.
fn presence(keys: &CellKeys, prefix: &str) -> Vec<Grant> {
    vec![
        grant(
            Flow::Ingress,
            &["liveliness_query", "declare_liveliness_subscriber"],
            vec![keys.all(), gateway_selector(prefix, "*")],
        ),
        grant(
            Flow::Egress,
            &["liveliness_token"],
            vec![keys.gateway(), keys.any_machine(), keys.any_plc()],
        ),
    ]
}

/// Following jobs: their events published, a get for the latest one, cancels seen.
fn job_events(keys: &CellKeys, p: Permission) -> Vec<Grant> {
    let events = vec![keys.any_job_events()];
    let published = published::read_by(keys, p);
    vec![
        grant(Flow::Ingress, QUERY, events.clone()),
        grant(Flow::Egress, REPLY_AND_QUERYABLE, events.clone()),
        grant(Flow::Ingress, &["declare_subscriber"], published.clone()),
        grant(Flow::Egress, &["put"], published),
        // A cancel (a client's delete) is seen by whoever follows the job.
        grant(Flow::Egress, &["delete"], events),
    ]
}

/// A route a permission writes on: gets, puts and deletes in; replies and the gateway's
/// queryable and subscriber declarations out.
fn writes(keys: Vec<String>) -> Vec<Grant> {
    vec![
        grant(Flow::Ingress, WRITE, keys.clone()),
        grant(Flow::Egress, SERVED_WRITE, keys),
    ]
}

/// Reading the library: gets (a program, a wildcard listing, revisions, a comparison), and
/// the gateway's word of each change (`…/program/NAME/changed`).
fn program_reads(keys: &CellKeys) -> Vec<Grant> {
    let read = routes::granted(keys, Permission::ProgramRead);
    let published = published::read_by(keys, Permission::ProgramRead);
    vec![
        grant(Flow::Ingress, QUERY, read.clone()),
        grant(Flow::Egress, REPLY_AND_QUERYABLE, read),
        // The library's changes and events: subscribed to, published by the gateway.
        grant(Flow::Ingress, &["declare_subscriber"], published.clone()),
        grant(Flow::Egress, &["put"], published),
    ]
}

/// Gets on keys that only answer.
fn reads(keys: Vec<String>) -> Vec<Grant> {
    vec![
        grant(Flow::Ingress, QUERY, keys.clone()),
        grant(Flow::Egress, REPLY_AND_QUERYABLE, keys),
    ]
}

/// The rules of one permission: on the keys of the route table's rows that name it
/// ([`routes::granted`]) and of the publications it may read ([`published::read_by`]), and
/// on the keys listed here for what the tables do not say (the reads that more than one
/// permission makes, the G05 streams' writes, the reload and admin keys, presence).
fn grants(p: Permission, keys: &CellKeys, prefix: &str) -> Vec<Grant> {
    let leaf = |l: MachineLeaf| keys.any_leaf(l);
    match p {
        Permission::StatusRead => {
            // Gets on status, DI, the queue, a job's latest event, a PLC link's status and a
            // tag change nothing: the writes of those keys have keys of their own.
            let answered = vec![
                leaf(MachineLeaf::Status),
                leaf(MachineLeaf::Di),
                leaf(MachineLeaf::Job),
                keys.any_plc_status(),
                keys.any_plc_tag(),
                keys.any_job_events(),
            ];
            vec![
                grant(Flow::Ingress, QUERY, answered.clone()),
                grant(Flow::Egress, REPLY_AND_QUERYABLE, answered),
                // Any subscription in the cell; the egress rule below picks what reaches it.
                grant(Flow::Ingress, &["declare_subscriber"], vec![keys.all()]),
                grant(Flow::Egress, &["put"], {
                    // What the gateway publishes, and a client's put on `…/do`, which is
                    // itself the DO's event (bus.md).
                    let mut seen = published::read_by(keys, p);
                    seen.push(leaf(MachineLeaf::Do));
                    seen
                }),
                grant(Flow::Egress, &["delete"], vec![keys.any_job_events()]),
            ]
        }
        Permission::JobSubmit => {
            let queried = vec![leaf(MachineLeaf::Submit), leaf(MachineLeaf::Job)];
            let mut g = vec![
                grant(Flow::Ingress, QUERY, queried.clone()),
                grant(Flow::Egress, REPLY_AND_QUERYABLE, queried),
            ];
            g.extend(job_events(keys, p));
            g
        }
        Permission::JobCancel => {
            let mut g = vec![
                grant(Flow::Ingress, &["delete"], vec![keys.any_job_events()]),
                grant(
                    Flow::Egress,
                    &["declare_subscriber"],
                    vec![keys.any_job_events()],
                ),
                grant(Flow::Ingress, QUERY, vec![keys.any_job_cancel()]),
                grant(
                    Flow::Egress,
                    REPLY_AND_QUERYABLE,
                    vec![keys.any_job_cancel()],
                ),
            ];
            g.extend(job_events(keys, p));
            g
        }
        Permission::ProgramRead => program_reads(keys),
        Permission::ProgramWrite => {
            let mut g = writes(routes::granted(keys, p));
            g.extend(program_reads(keys));
            g
        }
        // Gets and puts; a delete outputs nothing.
        Permission::IoDo => vec![
            grant(Flow::Ingress, &["query", "put"], routes::granted(keys, p)),
            grant(Flow::Egress, SERVED_WRITE, routes::granted(keys, p)),
        ],
        // Gets, puts and deletes; memory is read and written through one permission (the
        // memory viewer is an engineer's tool).
        Permission::PlcTag | Permission::PlcMem | Permission::PlcTransfer => {
            writes(routes::granted(keys, p))
        }
        Permission::G05Stream => {
            let mut g = writes(vec![keys.every_g05_key()]);
            // A stream's credits and state come back as publications.
            g.push(grant(
                Flow::Ingress,
                &["declare_subscriber"],
                vec![keys.every_g05_key()],
            ));
            g.push(grant(Flow::Egress, &["put"], published::read_by(keys, p)));
            // The producer's liveliness token, which the gateway watches to end a stream
            // whose producer went away.
            g.push(grant(
                Flow::Ingress,
                &["liveliness_token"],
                vec![keys.every_g05_key()],
            ));
            g.push(grant(
                Flow::Egress,
                &["declare_liveliness_subscriber"],
                vec![keys.every_g05_key()],
            ));
            g
        }
        // Gets only. A release changes state, so it has a key of its own, answered like a
        // write.
        Permission::ProgramRelease
        | Permission::HistoryRead
        | Permission::AuditRead
        | Permission::AuditNote => reads(routes::granted(keys, p)),
        // Reading a simulated machine's state is part of driving it.
        Permission::SimControl => writes(routes::granted(keys, p)),
        // A reload changes the whole cell: a key of its own, answered like a write.
        Permission::CellReload => reads(vec![keys.reload()]),
        Permission::AdminRead => vec![
            grant(
                Flow::Ingress,
                QUERY,
                vec![keys.admin(), admin_selector(prefix, "*")],
            ),
            grant(Flow::Egress, REPLY_AND_QUERYABLE, vec![keys.admin()]),
        ],
    }
}

fn rule_json(id: String, g: &Grant) -> Value {
    json!({
        "id": id,
        "messages": g.messages,
        "flows": [g.flow.name()],
        "permission": "allow",
        "key_exprs": g.keys,
    })
}

/// The rules, subjects and policies of the roles; `subjects` of a role are one zenoh subject
/// per kind of name (a zenoh subject with both would require both at once).
struct Generated {
    rules: Vec<Value>,
    subjects: Vec<Value>,
    policies: Vec<Value>,
}

fn generate(
    security: &SecurityConfig,
    keys: &CellKeys,
    prefix: &str,
    flows: impl Fn(Flow) -> Flow,
    id_prefix: &str,
) -> Generated {
    let mut rules = Vec::new();
    let mut rule_ids_of = |name: &str, grants: Vec<Grant>| -> Vec<String> {
        let mut ids = Vec::new();
        for (i, g) in grants.iter().enumerate() {
            let id = format!("{id_prefix}{name}/{}", i + 1);
            let g = Grant {
                flow: flows(g.flow),
                ..g.clone()
            };
            rules.push(rule_json(id.clone(), &g));
            ids.push(id);
        }
        ids
    };
    let presence_ids = rule_ids_of("presence", presence(keys, prefix));
    let permission_ids: Vec<(Permission, Vec<String>)> = Permission::ALL
        .into_iter()
        .filter(|p| security.roles.iter().any(|r| r.permissions.contains(p)))
        .map(|p| (p, rule_ids_of(p.name(), grants(p, keys, prefix))))
        .collect();

    let mut subjects = Vec::new();
    let mut policies = Vec::new();
    for role in &security.roles {
        let mut ids = Vec::new();
        if !role.cert_common_names.is_empty() {
            let id = format!("{id_prefix}role/{}/certificates", role.name);
            subjects.push(json!({ "id": id, "cert_common_names": role.cert_common_names }));
            ids.push(id);
        }
        if !role.usernames.is_empty() {
            let id = format!("{id_prefix}role/{}/users", role.name);
            subjects.push(json!({ "id": id, "usernames": role.usernames }));
            ids.push(id);
        }
        let mut rules = presence_ids.clone();
        for (p, r) in &permission_ids {
            if role.permissions.contains(p) {
                rules.extend(r.iter().cloned());
            }
        }
        policies.push(json!({
            "id": format!("{id_prefix}role/{}", role.name),
            "rules": rules,
            "subjects": ids,
        }));
    }
    Generated {
        rules,
        subjects,
        policies,
    }
}

/// The `access_control` section that enforces the roles on the gateway's own transports, or
/// `None` without roles.
pub fn access_control(security: &SecurityConfig, keys: &CellKeys, prefix: &str) -> Option<Value> {
    if !security.enforces_roles() {
        return None;
    }
    let g = generate(security, keys, prefix, |f| f, ID_PREFIX);
    Some(section(g))
}

/// The `access_control` section for a zenoh router the gateway and its clients connect to:
/// the roles, enforced on the clients' transports there, and `gateway`, the gateway's own
/// certificate common names, allowed what the gateway does (the roles' rules, mirrored). Give
/// the router's certificate common name a role with every permission in the cell file.
pub fn router_access_control(
    security: &SecurityConfig,
    keys: &CellKeys,
    prefix: &str,
    gateway: &[String],
) -> Value {
    let mut clients = generate(security, keys, prefix, |f| f, ID_PREFIX);
    let everything = SecurityConfig {
        roles: vec![cellgate_core::config::Role {
            name: "gateway".to_string(),
            cert_common_names: gateway.to_vec(),
            usernames: Vec::new(),
            permissions: Permission::ALL.to_vec(),
        }],
        ..SecurityConfig::default()
    };
    // The router sees the gateway send what the gateway's clients receive, and the other way
    // round; the ids must not collide with the clients' (role names are the user's).
    let own = generate(
        &everything,
        keys,
        prefix,
        Flow::mirror,
        &format!("{ID_PREFIX}gateway/"),
    );
    clients.rules.extend(own.rules);
    clients.subjects.extend(own.subjects);
    clients.policies.extend(own.policies);
    section(clients)
}

fn section(g: Generated) -> Value {
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": g.rules,
        "subjects": g.subjects,
        "policies": g.policies,
    })
}

/// `ours` added to the access_control section a zenoh file already has (`theirs`, as zenoh's
/// `get_json` gives it): the file's rules for other keys stay, cellgate's are appended, access
/// control is on and denies by default.
pub fn merge(theirs: &Value, ours: Value) -> Result<Value, AclError> {
    let mut merged = ours;
    if theirs.is_null() {
        return Ok(merged);
    }
    let enabled = theirs.get("enabled").and_then(Value::as_bool) == Some(true);
    if enabled && theirs.get("default_permission").and_then(Value::as_str) == Some("allow") {
        return Err(AclError::DefaultAllow);
    }
    for list in ["rules", "subjects", "policies"] {
        let entries = match theirs.get(list) {
            None | Some(Value::Null) => continue,
            Some(Value::Array(entries)) => entries,
            Some(other) => {
                return Err(AclError::Malformed(format!(
                    "{list} is not a list: {other}"
                )));
            }
        };
        for entry in entries {
            if let Some(id) = entry.get("id").and_then(Value::as_str)
                && id.starts_with(ID_PREFIX)
            {
                return Err(AclError::ReservedId {
                    list,
                    id: id.to_string(),
                });
            }
        }
        if let Some(Value::Array(ours)) = merged.get_mut(list) {
            let mut all = entries.clone();
            all.append(ours);
            *ours = all;
        }
    }
    Ok(merged)
}

#[cfg(test)]
mod tests;
