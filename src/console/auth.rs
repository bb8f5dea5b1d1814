//! Who uses the console, and what they may do: the same roles as the bus.
//!
//! On a cell with `[security]`, a browser user logs in with a name and password of the cell's
//! users file (zenoh's `user:password` lines) or presents a client certificate of the cell's
//! CA; the roles that name the user (`usernames`, `cert_common_names`) give the permissions.
//! Without `[security]` there is nobody to tell apart: every user may do everything, as on
//! the bus, and the console listens on loopback only unless told otherwise.
//!
//! A session is a random token in an `HttpOnly`, `SameSite=Strict` cookie; it ends after
//! `session_idle_minutes` without a request and after `session_hours` however busy. Every
//! write carries the session's CSRF token in `X-CSRF-Token`, so that a page of another site
//! cannot make a logged-in browser act.

use std::collections::{BTreeSet, HashMap};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use cellgate_core::config::{Permission, SecurityConfig};
use subtle::ConstantTimeEq as _;

/// The session cookie's name.
pub const COOKIE: &str = "cellgate_console";

/// Sessions kept at most; the oldest go first beyond it.
const MAX_SESSIONS: usize = 4096;

/// A logged-in user.
#[derive(Debug, Clone)]
pub struct User {
    pub name: String,
    /// How they proved it: `password`, `certificate`, or `none` (a cell without security).
    pub via: &'static str,
    pub permissions: BTreeSet<Permission>,
    pub csrf: String,
    created: Instant,
    last: Instant,
}

impl User {
    pub fn may(&self, p: Permission) -> bool {
        self.permissions.contains(&p)
            // Writing the library includes reading it.
            || (p == Permission::ProgramRead && self.permissions.contains(&Permission::ProgramWrite))
    }
}

/// Why a login was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LoginError {
    #[error("unknown user or wrong password")]
    Refused,
    #[error("this console takes no passwords: the cell has no users file")]
    NoUsers,
    #[error("user {0} holds no role of the cell: nothing to do here")]
    NoRole(String),
}

/// Users, roles and sessions.
#[derive(Debug)]
pub struct Auth {
    secured: bool,
    users: HashMap<String, String>,
    security: SecurityConfig,
    idle: Duration,
    max_age: Duration,
    sessions: Mutex<HashMap<String, User>>,
}

fn token() -> String {
    let mut bytes = [0u8; 32];
    // The OS's random source; without it no session can be trusted, so none is made.
    if getrandom::fill(&mut bytes).is_err() {
        return String::new();
    }
    hex::encode(bytes)
}

impl Auth {
    /// `users_file` read at start; a file that cannot be read leaves nobody able to log in
    /// by password (said in the log).
    pub fn new(security: &SecurityConfig, idle: Duration, max_age: Duration) -> Self {
        let mut users = HashMap::new();
        if let Some(path) = &security.users_file {
            match std::fs::read_to_string(path) {
                Ok(text) => {
                    for line in text.lines() {
                        if let Some((u, p)) = line.split_once(':')
                            && !u.is_empty()
                        {
                            users.insert(u.to_string(), p.to_string());
                        }
                    }
                }
                Err(e) => tracing::error!(file = %path.display(), error = %e,
                    "console: the users file cannot be read; nobody can log in by password"),
            }
        }
        Auth {
            secured: security.tls.is_some() || security.users_file.is_some(),
            users,
            security: security.clone(),
            idle,
            max_age,
            sessions: Mutex::new(HashMap::new()),
        }
    }

    /// Whether users log in (the cell has `[security]`).
    pub fn secured(&self) -> bool {
        self.secured
    }

    /// The permissions of a user name or certificate name: those of the roles naming it;
    /// every permission on a cell without roles (as the bus then allows everything).
    fn permissions(&self, name: &str, by_certificate: bool) -> BTreeSet<Permission> {
        if !self.security.enforces_roles() {
            return Permission::ALL.into_iter().collect();
        }
        self.security
            .roles
            .iter()
            .filter(|r| {
                if by_certificate {
                    r.cert_common_names.iter().any(|n| n == name)
                } else {
                    r.usernames.iter().any(|n| n == name)
                }
            })
            .flat_map(|r| r.permissions.iter().copied())
            .collect()
    }

    fn open(
        &self,
        name: &str,
        via: &'static str,
        permissions: BTreeSet<Permission>,
    ) -> (String, User) {
        let now = Instant::now();
        let user = User {
            name: name.to_string(),
            via,
            permissions,
            csrf: token(),
            created: now,
            last: now,
        };
        let id = token();
        if let Ok(mut s) = self.sessions.lock() {
            if s.len() >= MAX_SESSIONS {
                let oldest = s.iter().min_by_key(|(_, u)| u.last).map(|(k, _)| k.clone());
                if let Some(k) = oldest {
                    s.remove(&k);
                }
            }
            s.insert(id.clone(), user.clone());
        }
        (id, user)
    }

    /// Checks a name and password against the users file; a session on success.
    pub fn login(&self, name: &str, password: &str) -> Result<(String, User), LoginError> {
        if self.users.is_empty() {
            return Err(LoginError::NoUsers);
        }
        let known = self.users.get(name).map(String::as_bytes).unwrap_or(b"");
        // Compared in constant time, and compared even for an unknown user.
        let same: bool = known.ct_eq(password.as_bytes()).into();
        if !same || !self.users.contains_key(name) || password.is_empty() {
            return Err(LoginError::Refused);
        }
        let permissions = self.permissions(name, false);
        if permissions.is_empty() {
            return Err(LoginError::NoRole(name.to_string()));
        }
        Ok(self.open(name, "password", permissions))
    }

    /// A session for a verified client certificate's common name, or for anybody on a cell
    /// without security.
    pub fn implicit(&self, certificate_name: Option<&str>) -> Option<(String, User)> {
        if !self.secured {
            return Some(self.open("anonymous", "none", self.permissions("", false)));
        }
        let name = certificate_name?;
        let permissions = self.permissions(name, true);
        if permissions.is_empty() {
            return None;
        }
        Some(self.open(name, "certificate", permissions))
    }

    /// The user of session `id`, if it is still valid (and marks it used).
    pub fn user(&self, id: &str) -> Option<User> {
        if id.is_empty() {
            return None;
        }
        let mut sessions = self.sessions.lock().ok()?;
        let now = Instant::now();
        let valid = sessions.get(id).is_some_and(|u| {
            now.duration_since(u.last) < self.idle && now.duration_since(u.created) < self.max_age
        });
        if !valid {
            sessions.remove(id);
            return None;
        }
        let u = sessions.get_mut(id)?;
        u.last = now;
        Some(u.clone())
    }

    /// When session `id` ends at the latest, as ms since the Unix epoch.
    pub fn expires_unix_ms(&self, user: &User) -> u64 {
        let left = self
            .idle
            .min(self.max_age.saturating_sub(user.created.elapsed()));
        cellgate_core::pb::unix_ms(std::time::SystemTime::now() + left)
    }

    pub fn logout(&self, id: &str) {
        if let Ok(mut s) = self.sessions.lock() {
            s.remove(id);
        }
    }

    /// Whether `given` is the user's CSRF token.
    pub fn csrf_ok(user: &User, given: Option<&str>) -> bool {
        match given {
            Some(g) if !user.csrf.is_empty() => user.csrf.as_bytes().ct_eq(g.as_bytes()).into(),
            _ => false,
        }
    }
}

#[cfg(test)]
mod tests;
