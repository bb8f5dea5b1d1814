//! `[console]`: the web console the gateway serves (docs/console.md).

use serde::{Deserialize, Serialize};

use super::error::{Checker, q};

/// `[console]`: where the console listens and how long a login lasts. Without the section
/// the gateway serves no console.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ConsoleConfig {
    /// `ADDRESS:PORT` to listen on. With `[security.tls]` the console speaks HTTPS with the
    /// cell's certificate and takes client certificates of the cell's CA; else HTTP.
    pub listen: String,
    /// Minutes a session lasts without a request.
    pub session_idle_minutes: u32,
    /// Hours a session lasts at most, however busy.
    pub session_hours: u32,
    /// Sessions one user holds at most (browsers, tablets): a new one ends that user's
    /// oldest, never another user's.
    pub sessions_per_user: u32,
    /// Listen beyond loopback on a cell without `[security]` (anyone who reaches the port
    /// may then do anything): off by default, and warned of when on.
    pub allow_remote: bool,
    /// Host names the console is reached by, beside its addresses and `localhost` (a
    /// request for any other name is refused: a page of another site whose name was pointed
    /// at this address must not be served).
    pub host_names: Vec<String>,
}

impl Default for ConsoleConfig {
    fn default() -> Self {
        ConsoleConfig {
            listen: Self::DEFAULT_LISTEN.to_string(),
            session_idle_minutes: 30,
            session_hours: 12,
            sessions_per_user: 16,
            allow_remote: false,
            host_names: Vec::new(),
        }
    }
}

impl ConsoleConfig {
    /// Where the console listens unless the cell file says otherwise.
    pub const DEFAULT_LISTEN: &'static str = "127.0.0.1:7480";

    /// Whether `listen` is a loopback address.
    pub fn is_loopback(&self) -> bool {
        self.listen
            .parse::<std::net::SocketAddr>()
            .is_ok_and(|a| a.ip().is_loopback())
    }
}

pub(super) fn check_console(c: &mut Checker, console: &ConsoleConfig, secured: bool) {
    if console.listen.parse::<std::net::SocketAddr>().is_err() {
        c.invalid(
            "console.listen".to_string(),
            q(&console.listen),
            "must be ADDRESS:PORT, e.g. \"127.0.0.1:7480\" or \"[::1]:7480\"".to_string(),
            "",
        );
    } else if !secured && !console.is_loopback() && !console.allow_remote {
        c.invalid(
            "console.listen".to_string(),
            q(&console.listen),
            "reaches beyond this host on a cell without [security]: anyone who reaches it \
             could do anything. Listen on 127.0.0.1, add [security] (TLS, users, roles), or \
             set console.allow_remote = true"
                .to_string(),
            "",
        );
    }
    for name in &console.host_names {
        let plain = !name.is_empty()
            && name.len() <= 253
            && name.split('.').all(|l| {
                !l.is_empty() && l.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-')
            });
        if !plain {
            c.invalid(
                "console.host_names".to_string(),
                q(name),
                "must be a DNS name without port or scheme, e.g. \"cell3.plant.example\" \
                 (addresses and localhost are always taken)"
                    .to_string(),
                "",
            );
        }
    }
    c.range(
        || "console.session_idle_minutes".to_string(),
        console.session_idle_minutes,
        1,
        24 * 60,
        " minutes",
        "",
    );
    c.range(
        || "console.sessions_per_user".to_string(),
        console.sessions_per_user,
        1,
        1024,
        "",
        "",
    );
    c.range(
        || "console.session_hours".to_string(),
        console.session_hours,
        1,
        24 * 14,
        " hours",
        "",
    );
}
