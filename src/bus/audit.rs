//! The audit trail of the writes the gateway takes: who, what, and what came of it.
//!
//! zenoh does not tell a queryable or subscriber which authenticated client sent a message
//! (its access control sees the certificate's common name or the user name, but nothing
//! public carries them to the application; `Query::source_info` is optional, set by the
//! sender and unchecked). So the audit records three things, each for what it is worth:
//! - `origin`: the `RequestOrigin` the client attached, its own word;
//! - `roles`: the roles of the cell file whose permissions take the request — the access
//!   control let it through, so the sender holds one of them;
//! - `principal`: when those roles name exactly one certificate common name or user name,
//!   that one — then the sender is known whatever it says.

use zenoh::bytes::ZBytes;

use cellgate_core::bounds;
use cellgate_core::codes::BusCode;
use cellgate_core::config::{Permission, SecurityConfig};
use cellgate_core::pb;

use crate::history::History;

/// The roles of the cell file, for the audit's `roles` and `principal`.
#[derive(Debug, Clone, Default)]
pub(crate) struct Auditor {
    /// Each role: its name, its permissions, the names that hold it.
    roles: Vec<(String, Vec<Permission>, Vec<String>)>,
}

/// One audited write.
pub(crate) struct Audit<'a> {
    /// `job.submit`, `io.do`, ...
    pub action: &'a str,
    /// The permission that takes it.
    pub permission: Permission,
    pub key: &'a str,
    /// The machine or PLC link it acts on (empty for the library).
    pub machine: &'a str,
    pub target: String,
    pub detail: String,
    pub origin: Option<pb::RequestOrigin>,
}

impl Auditor {
    pub(crate) fn new(security: &SecurityConfig) -> Self {
        Auditor {
            roles: security
                .roles
                .iter()
                .map(|r| {
                    let names = r
                        .cert_common_names
                        .iter()
                        .chain(&r.usernames)
                        .cloned()
                        .collect();
                    (r.name.clone(), r.permissions.clone(), names)
                })
                .collect(),
        }
    }

    /// The roles that hold `p`, and the one name they give when they give one only.
    /// Whether the cell has no roles: every client may do anything.
    pub(crate) fn open(&self) -> bool {
        self.roles.is_empty()
    }

    fn who_may(&self, p: Permission) -> (Vec<String>, String) {
        let mut roles = Vec::new();
        let mut names = std::collections::BTreeSet::new();
        for (role, permissions, holders) in &self.roles {
            if permissions.contains(&p) {
                roles.push(role.clone());
                names.extend(holders.iter().cloned());
            }
        }
        let principal = if names.len() == 1 {
            names.into_iter().next().unwrap_or_default()
        } else {
            String::new()
        };
        (roles, principal)
    }

    /// Records `a` with its outcome.
    pub(crate) fn record<E: BusCode + std::fmt::Display>(
        &self,
        history: &History,
        a: Audit<'_>,
        outcome: Result<(), &E>,
    ) {
        if history.enabled() {
            let machine = a.machine.to_string();
            history.audit(&machine, self.build(a, outcome));
        }
    }

    /// Records a console's note `a`, which stands for `count` refusals the console gathered:
    /// kept as it comes, with its count, so that one user's refusals of different kinds stay
    /// apart and a minute's summary says how many it stands for.
    pub(crate) fn record_note<E: BusCode + std::fmt::Display>(
        &self,
        history: &History,
        a: Audit<'_>,
        outcome: Result<(), &E>,
        count: u32,
    ) {
        if history.enabled() {
            let machine = a.machine.to_string();
            let record = pb::AuditRecord {
                count: count.max(1),
                ..self.build(a, outcome)
            };
            history.audit_gathered(&machine, record);
        }
    }

    fn build<E: BusCode + std::fmt::Display>(
        &self,
        a: Audit<'_>,
        outcome: Result<(), &E>,
    ) -> pb::AuditRecord {
        let (roles, principal) = self.who_may(a.permission);
        let (ok, code, error) = match outcome {
            Ok(()) => (true, 0, String::new()),
            Err(e) => (false, e.code() as i32, e.to_string()),
        };
        pb::AuditRecord {
            action: a.action.to_string(),
            key: a.key.to_string(),
            target: a.target,
            detail: a.detail,
            origin: a.origin,
            roles,
            principal,
            ok,
            code,
            error,
            count: 0,
        }
    }
}

/// What a write's attachment says of its sender: the `RequestOrigin`, or a note that it
/// could not be read (the request itself is served all the same).
pub(crate) fn origin_of(attachment: Option<&ZBytes>) -> Option<pb::RequestOrigin> {
    let bytes = attachment?.to_bytes();
    let limits = bounds::Limits {
        max_inline: 0,
        max_program: 0,
    };
    Some(
        bounds::decode::<pb::RequestOrigin>(&bytes, &limits).unwrap_or_else(|e| {
            pb::RequestOrigin {
                user: "(unreadable)".to_string(),
                via: e.to_string().chars().take(128).collect(),
            }
        }),
    )
}
