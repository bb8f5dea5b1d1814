//! `[mtconnect]`: the MTConnect agent the gateway serves (docs/mtconnect.md).

use serde::{Deserialize, Serialize};

use super::error::{Checker, q};

/// `[mtconnect]`: where the MTConnect agent listens, how many observations it keeps, and the
/// SHDR adapter's port. Without the section the gateway serves no agent.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MtconnectConfig {
    /// `ADDRESS:PORT` of the agent's HTTP interface (MTConnect Part 1: `/probe`, `/current`,
    /// `/sample`, `/assets`). Plain HTTP: the standard's clients speak it, and the agent only
    /// reads.
    pub listen: String,
    /// Observations the agent keeps (`bufferSize` of every document): 1 024 to 1 048 576.
    pub buffer_size: u32,
    /// `ADDRESS:PORT` of an SHDR adapter (the line format an existing agent takes from an
    /// adapter), or none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shdr_listen: Option<String>,
}

impl Default for MtconnectConfig {
    fn default() -> Self {
        MtconnectConfig {
            listen: Self::DEFAULT_LISTEN.to_string(),
            buffer_size: Self::DEFAULT_BUFFER_SIZE,
            shdr_listen: None,
        }
    }
}

impl MtconnectConfig {
    /// Where the agent listens unless the cell file says otherwise (5000: the port MTConnect
    /// agents listen on by convention).
    pub const DEFAULT_LISTEN: &'static str = "127.0.0.1:5000";
    /// Observations kept unless the cell file says otherwise: 2¹⁷, as a reference agent keeps.
    pub const DEFAULT_BUFFER_SIZE: u32 = 131_072;

    /// Whether `listen` (and the SHDR port, if any) are loopback addresses.
    pub fn is_loopback(&self) -> bool {
        let lo = |a: &str| {
            a.parse::<std::net::SocketAddr>()
                .is_ok_and(|a| a.ip().is_loopback())
        };
        lo(&self.listen) && self.shdr_listen.as_deref().is_none_or(lo)
    }

    /// Ports reachable beyond this host: neither the MTConnect interface nor SHDR has a
    /// login, so whoever reaches them reads the cell's state (neither writes).
    pub fn warnings(&self) -> Vec<String> {
        let beyond = |a: &str| {
            a.parse::<std::net::SocketAddr>()
                .is_ok_and(|a| !a.ip().is_loopback())
        };
        let mut out = Vec::new();
        if beyond(&self.listen) {
            out.push(format!(
                "mtconnect.listen {:?} is reachable beyond this host: the MTConnect interface has \
                 no login (the standard's clients use none), so anyone who reaches it may read \
                 the cell's state; it never writes",
                self.listen
            ));
        }
        if let Some(shdr) = self.shdr_listen.as_deref().filter(|a| beyond(a)) {
            out.push(format!(
                "mtconnect.shdr_listen {shdr:?} is reachable beyond this host: the SHDR protocol \
                 has no login, so anyone who reaches the port may read every observation (16 \
                 connections at most); listen on 127.0.0.1 beside the agent, or let only the \
                 agent's host reach it"
            ));
        }
        out
    }
}

pub(super) fn check_mtconnect(c: &mut Checker, m: &MtconnectConfig) {
    for (key, value) in [
        ("mtconnect.listen", Some(&m.listen)),
        ("mtconnect.shdr_listen", m.shdr_listen.as_ref()),
    ] {
        if let Some(v) = value
            && v.parse::<std::net::SocketAddr>().is_err()
        {
            c.invalid(
                key.to_string(),
                q(v),
                "must be ADDRESS:PORT, e.g. \"127.0.0.1:5000\" or \"[::1]:5000\"".to_string(),
                "",
            );
        }
    }
    c.range(
        || "mtconnect.buffer_size".to_string(),
        m.buffer_size,
        1024,
        1 << 20,
        " observations",
        "",
    );
}
