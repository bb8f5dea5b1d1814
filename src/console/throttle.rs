//! Login throttling: password guessing costs time.
//!
//! Failures are counted per user name and per client address. A few are free (a typo, a
//! caps lock); past them, each failure closes that name or address for a time that doubles,
//! up to [`MAX_WAIT`]. While closed, a login is refused with 429 and `Retry-After` before the
//! password is even compared, so the right password too waits its turn; once the time has
//! passed it is taken. A name's count starts again when it logs in; an address's only
//! fades ([`FORGET`] after its last failure), so one good account does not open the door
//! for guesses at another from the same address.
//!
//! No crate offers this shape (rate limiters such as `governor` spend a unit on every
//! check; here only failures spend, and the wait grows): it is a small table per key.
//! Both tables are bounded (`MAX_KEYS`); beyond, entries that no longer close anything go
//! first, then the oldest.

use std::collections::HashMap;
use std::hash::Hash;
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Failures of one user name that cost nothing.
pub const FREE_PER_USER: u32 = 5;
/// Failures from one address that cost nothing (it may be a shared terminal).
pub const FREE_PER_ADDRESS: u32 = 20;
/// The first wait past the free failures; each further failure doubles it.
pub const FIRST_WAIT: Duration = Duration::from_secs(1);
/// The longest wait.
pub const MAX_WAIT: Duration = Duration::from_secs(300);
/// A key's failures are forgotten this long after its last one.
pub const FORGET: Duration = Duration::from_secs(15 * 60);
/// Keys kept per table at most.
const MAX_KEYS: usize = 16_384;
/// Failures of one trusted device that cost nothing: as many as a name's.
pub const FREE_PER_DEVICE: u32 = FREE_PER_USER;
/// Devices trusted at most; beyond, the least recently trusted is forgotten.
const MAX_DEVICES: usize = 16_384;

#[derive(Debug, Clone, Copy)]
struct Failures {
    count: u32,
    last: Instant,
    /// Closed until then.
    until: Instant,
}

#[derive(Debug)]
struct Table<K> {
    free: u32,
    keys: HashMap<K, Failures>,
}

impl<K: Hash + Eq + Clone> Table<K> {
    fn new(free: u32) -> Self {
        Table {
            free,
            keys: HashMap::new(),
        }
    }

    fn closed(&mut self, k: &K, now: Instant) -> Option<Duration> {
        let f = self.keys.get(k)?;
        if now.duration_since(f.last) >= FORGET {
            self.keys.remove(k);
            return None;
        }
        (f.until > now).then(|| f.until - now)
    }

    /// Counts a failure; the wait it imposes, if any.
    fn fail(&mut self, k: &K, now: Instant) -> Option<Duration> {
        if !self.keys.contains_key(k) && self.keys.len() >= MAX_KEYS {
            self.make_room(now);
        }
        let f = self.keys.entry(k.clone()).or_insert(Failures {
            count: 0,
            last: now,
            until: now,
        });
        if now.duration_since(f.last) >= FORGET {
            f.count = 0;
        }
        f.count = f.count.saturating_add(1);
        f.last = now;
        let excess = f.count.checked_sub(self.free + 1)?;
        let wait = FIRST_WAIT
            .checked_mul(1u32 << excess.min(16))
            .unwrap_or(MAX_WAIT)
            .min(MAX_WAIT);
        f.until = now + wait;
        Some(wait)
    }

    fn forget(&mut self, k: &K) {
        self.keys.remove(k);
    }

    fn make_room(&mut self, now: Instant) {
        self.keys
            .retain(|_, f| f.until > now && now.duration_since(f.last) < FORGET);
        if self.keys.len() >= MAX_KEYS
            && let Some(oldest) = self
                .keys
                .iter()
                .min_by_key(|(_, f)| f.last)
                .map(|(k, _)| k.clone())
        {
            self.keys.remove(&oldest);
        }
    }
}

/// A trusted device: whose it is and when it was last trusted.
#[derive(Debug, Clone)]
struct Device {
    user: String,
    trusted: Instant,
}

#[derive(Debug)]
struct Tables {
    users: Table<String>,
    addrs: Table<IpAddr>,
    devices: Table<String>,
    /// Device tokens handed out, with their user.
    known: HashMap<String, Device>,
}

/// The failures of logins, per user name and per client address, and per trusted device.
#[derive(Debug)]
pub struct Throttle {
    inner: Mutex<Tables>,
}

impl Default for Throttle {
    fn default() -> Self {
        Throttle {
            inner: Mutex::new(Tables {
                users: Table::new(FREE_PER_USER),
                addrs: Table::new(FREE_PER_ADDRESS),
                devices: Table::new(FREE_PER_DEVICE),
                known: HashMap::new(),
            }),
        }
    }
}

impl Tables {
    /// `device`, if it is a token handed to `user`'s browser.
    fn trusted(&self, user: &str, device: Option<&str>) -> Option<String> {
        let d = device.filter(|d| !d.is_empty())?;
        (self.known.get(d)?.user == user).then(|| d.to_string())
    }
}

impl Throttle {
    fn tables(&self) -> std::sync::MutexGuard<'_, Tables> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// How long `user` from `addr`, on the browser that presents `device` (its device
    /// cookie, if any), must wait before a login is looked at; `None`: now.
    pub fn closed(
        &self,
        user: &str,
        addr: IpAddr,
        device: Option<&str>,
        now: Instant,
    ) -> Option<Duration> {
        let mut t = self.tables();
        if let Some(d) = t.trusted(user, device) {
            return t.devices.closed(&d, now);
        }
        let a = t.users.closed(&user.to_string(), now);
        let b = t.addrs.closed(&addr, now);
        a.max(b)
    }

    /// Counts a failed login; how long the name, the address or the device is now closed,
    /// if at all. A trusted device's failure is the device's alone.
    pub fn failed(
        &self,
        user: &str,
        addr: IpAddr,
        device: Option<&str>,
        now: Instant,
    ) -> Option<Duration> {
        let mut t = self.tables();
        if let Some(d) = t.trusted(user, device) {
            return t.devices.fail(&d, now);
        }
        let a = t.users.fail(&user.to_string(), now);
        let b = t.addrs.fail(&addr, now);
        a.max(b)
    }

    /// A login of `user` succeeded on the browser that presented `device`: that device's
    /// failures are forgotten, or, from an untrusted browser, the name's. Answers the
    /// browser's new device token (the old one is forgotten: one token per login).
    pub fn trust(&self, user: &str, device: Option<&str>, now: Instant) -> String {
        let mut t = self.tables();
        match t.trusted(user, device) {
            Some(d) => {
                t.devices.forget(&d);
                t.known.remove(&d);
            }
            None => t.users.forget(&user.to_string()),
        }
        if t.known.len() >= MAX_DEVICES
            && let Some(oldest) = t
                .known
                .iter()
                .min_by_key(|(_, d)| d.trusted)
                .map(|(k, _)| k.clone())
        {
            t.known.remove(&oldest);
        }
        let token = super::auth::token();
        if !token.is_empty() {
            t.known.insert(
                token.clone(),
                Device {
                    user: user.to_string(),
                    trusted: now,
                },
            );
        }
        token
    }
}

#[cfg(test)]
mod tests;
