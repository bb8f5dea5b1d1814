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
//!
//! Sessions are bounded per user (`console.sessions_per_user`): a user's new session ends
//! that user's oldest, never anybody else's, so no user can log another out by logging in
//! often. Every session carries a token cancelled when it ends (logout, expiry, a bound, a
//! user whose roles changed), which ends the event streams it opened. Password guesses are
//! throttled per name and per address ([`super::throttle`]).

use std::collections::{BTreeSet, HashMap};
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use cellgate_core::config::file::{MAX_SIDE_FILE, read_text_bounded};
use cellgate_core::config::{Permission, SecurityConfig};
use subtle::ConstantTimeEq as _;
use tokio_util::sync::CancellationToken;

use super::throttle::Throttle;

/// The session cookie's name.
pub const COOKIE: &str = "cellgate_console";
/// The device cookie's name ([`super::throttle`]): a browser the user logged in on before.
pub const DEVICE_COOKIE: &str = "cellgate_device";
/// How long a browser keeps its device cookie: a year.
pub const DEVICE_MAX_AGE_S: u64 = 365 * 24 * 3600;

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
    /// Cancelled when the session ends.
    pub ended: CancellationToken,
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
    /// Too many failures of this name or from this address: nothing is looked at until then.
    #[error("too many failed logins: try again in {} s", .0.as_secs().max(1))]
    Throttled(Duration),
    #[error("this console takes no passwords: the cell has no users file")]
    NoUsers,
    #[error("user {0} holds no role of the cell: nothing to do here")]
    NoRole(String),
}

/// The cell's users and roles, as the cell file gives them (replaced on a reload).
#[derive(Debug, Default)]
struct Cell {
    secured: bool,
    users: HashMap<String, String>,
    security: SecurityConfig,
}

impl Cell {
    /// `users_file` read now; a file that cannot be read leaves nobody able to log in by
    /// password (said in the log).
    fn read(security: &SecurityConfig) -> Self {
        let mut users = HashMap::new();
        if let Some(path) = &security.users_file {
            match read_text_bounded(path, MAX_SIDE_FILE) {
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
        Cell {
            secured: security.tls.is_some() || security.users_file.is_some(),
            users,
            security: security.clone(),
        }
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

    /// Whether session `u` may go on under these users and roles.
    fn still_holds(&self, u: &User) -> bool {
        match u.via {
            "none" => !self.secured,
            "password" => {
                self.users.contains_key(&u.name)
                    && self.permissions(&u.name, false) == u.permissions
            }
            _ => self.permissions(&u.name, true) == u.permissions,
        }
    }
}

/// How long sessions last and how many a user holds (`[console]`; replaced on a reload).
#[derive(Debug, Clone, Copy)]
struct Limits {
    idle: Duration,
    max_age: Duration,
    per_user: usize,
}

/// Users, roles and sessions.
#[derive(Debug)]
pub struct Auth {
    cell: std::sync::RwLock<Cell>,
    limits: std::sync::RwLock<Limits>,
    sessions: Mutex<HashMap<String, User>>,
    throttle: Throttle,
}

pub(super) fn token() -> String {
    let mut bytes = [0u8; 32];
    // The OS's random source; without it no session can be trusted, so none is made.
    if getrandom::fill(&mut bytes).is_err() {
        return String::new();
    }
    hex::encode(bytes)
}

impl Auth {
    /// The cell's users and roles; sessions end after `idle` without a request, after
    /// `max_age` however busy; a user holds at most `per_user` sessions.
    pub fn new(
        security: &SecurityConfig,
        idle: Duration,
        max_age: Duration,
        per_user: usize,
    ) -> Self {
        Auth {
            cell: std::sync::RwLock::new(Cell::read(security)),
            limits: std::sync::RwLock::new(Limits {
                idle,
                max_age,
                per_user: per_user.max(1),
            }),
            sessions: Mutex::new(HashMap::new()),
            throttle: Throttle::default(),
        }
    }

    fn cell(&self) -> std::sync::RwLockReadGuard<'_, Cell> {
        self.cell.read().unwrap_or_else(|p| p.into_inner())
    }

    fn limits(&self) -> Limits {
        *self.limits.read().unwrap_or_else(|p| p.into_inner())
    }

    /// How long a session lasts at most, however busy.
    pub fn max_age(&self) -> Duration {
        self.limits().max_age
    }

    /// Takes new session limits (a reloaded `[console]`): a session past the new ones ends at
    /// its next request, a user past the new bound keeps their sessions until they log in
    /// again.
    pub fn set_limits(&self, idle: Duration, max_age: Duration, per_user: usize) {
        *self.limits.write().unwrap_or_else(|p| p.into_inner()) = Limits {
            idle,
            max_age,
            per_user: per_user.max(1),
        };
    }

    /// Whether users log in (the cell has `[security]`).
    pub fn secured(&self) -> bool {
        self.cell().secured
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
            ended: CancellationToken::new(),
        };
        let id = token();
        let mut s = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
        self.sweep(&mut s, now);
        // This user's oldest sessions make room for the new one; nobody else's.
        let mut own: Vec<(Instant, String)> = s
            .iter()
            .filter(|(_, u)| u.name == name && u.via == via)
            .map(|(k, u)| (u.created, k.clone()))
            .collect();
        let per_user = self.limits().per_user;
        if own.len() >= per_user {
            own.sort();
            for (_, k) in &own[..=own.len() - per_user] {
                if let Some(u) = s.remove(k) {
                    u.ended.cancel();
                }
            }
        }
        s.insert(id.clone(), user.clone());
        (id, user)
    }

    fn valid(&self, u: &User, now: Instant) -> bool {
        let l = self.limits();
        now.duration_since(u.last) < l.idle && now.duration_since(u.created) < l.max_age
    }

    /// Ends the sessions that are no longer valid.
    fn sweep(&self, s: &mut HashMap<String, User>, now: Instant) {
        s.retain(|_, u| {
            let keep = self.valid(u, now);
            if !keep {
                u.ended.cancel();
            }
            keep
        });
    }

    /// Checks a name and password from `addr`, on the browser that presents `device` (its
    /// device cookie), against the users file; on success a session and the browser's new
    /// device token. Throttled: past a few failures of the name or from the address (or, for
    /// a browser the user logged in on before, of that device alone), the password is not
    /// looked at until the wait has passed ([`LoginError::Throttled`]).
    pub fn login(
        &self,
        name: &str,
        password: &str,
        addr: IpAddr,
        device: Option<&str>,
    ) -> Result<(String, User, String), LoginError> {
        let (permissions, device) = self.verify(name, password, addr, device)?;
        let (id, user) = self.open(name, "password", permissions);
        Ok((id, user, device))
    }

    /// Checks a name and password as [`Auth::login`] does (throttled the same way), without
    /// opening a console session: what another door of the cell (the OPC UA server) asks.
    /// Answers the user's permissions.
    pub fn check(
        &self,
        name: &str,
        password: &str,
        addr: IpAddr,
    ) -> Result<BTreeSet<Permission>, LoginError> {
        self.verify(name, password, addr, None).map(|(p, _)| p)
    }

    fn verify(
        &self,
        name: &str,
        password: &str,
        addr: IpAddr,
        device: Option<&str>,
    ) -> Result<(BTreeSet<Permission>, String), LoginError> {
        let cell = self.cell();
        if cell.users.is_empty() {
            return Err(LoginError::NoUsers);
        }
        let now = Instant::now();
        if let Some(wait) = self.throttle.closed(name, addr, device, now) {
            return Err(LoginError::Throttled(wait));
        }
        let known = cell.users.get(name).map(String::as_bytes).unwrap_or(b"");
        // Compared in constant time, and compared even for an unknown user.
        let same: bool = known.ct_eq(password.as_bytes()).into();
        if !same || !cell.users.contains_key(name) || password.is_empty() {
            return Err(match self.throttle.failed(name, addr, device, now) {
                Some(wait) => LoginError::Throttled(wait),
                None => LoginError::Refused,
            });
        }
        let device = self.throttle.trust(name, device, now);
        let permissions = cell.permissions(name, false);
        drop(cell);
        if permissions.is_empty() {
            return Err(LoginError::NoRole(name.to_string()));
        }
        Ok((permissions, device))
    }

    /// A session for a verified client certificate's common name, or for anybody on a cell
    /// without security.
    pub fn implicit(&self, certificate_name: Option<&str>) -> Option<(String, User)> {
        let cell = self.cell();
        if !cell.secured {
            let all = cell.permissions("", false);
            drop(cell);
            return Some(self.open("anonymous", "none", all));
        }
        let name = certificate_name?;
        let permissions = cell.permissions(name, true);
        drop(cell);
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
        let mut sessions = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
        let now = Instant::now();
        let valid = sessions.get(id).is_some_and(|u| self.valid(u, now));
        if !valid {
            if let Some(u) = sessions.remove(id) {
                u.ended.cancel();
            }
            return None;
        }
        let u = sessions.get_mut(id)?;
        u.last = now;
        Some(u.clone())
    }

    /// Whether session `id` is still valid, without marking it used: what an event stream
    /// asks now and then, so that it ends with an expired session too.
    pub fn live(&self, id: &str) -> bool {
        let sessions = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
        sessions
            .get(id)
            .is_some_and(|u| self.valid(u, Instant::now()))
    }

    /// Takes the cell's users and roles anew (a reloaded cell file; the users file is read
    /// again): every session whose user is gone or whose permissions changed ends, and its
    /// event streams with it. Answers how many ended.
    pub fn set_security(&self, security: &SecurityConfig) -> usize {
        let fresh = Cell::read(security);
        let mut sessions = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
        let before = sessions.len();
        sessions.retain(|_, u| {
            let keep = fresh.still_holds(u);
            if !keep {
                u.ended.cancel();
            }
            keep
        });
        *self.cell.write().unwrap_or_else(|p| p.into_inner()) = fresh;
        before - sessions.len()
    }

    /// When session `id` ends at the latest, as ms since the Unix epoch.
    pub fn expires_unix_ms(&self, user: &User) -> u64 {
        let l = self.limits();
        let left = l.idle.min(l.max_age.saturating_sub(user.created.elapsed()));
        cellgate_core::pb::unix_ms(std::time::SystemTime::now() + left)
    }

    /// Ends session `id`: its event streams end with it.
    pub fn logout(&self, id: &str) {
        let mut s = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(u) = s.remove(id) {
            u.ended.cancel();
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
