//! Whether the addresses `cellgate run` listens on are free, asked before anything starts:
//! an address in use (another gateway, a second `cellgate run`) is one clear line, and the
//! run has created nothing (no journal, history or library index) and logged nothing.

use std::net::{TcpListener, ToSocketAddrs};

use cellgate_core::config::CellConfig;

/// The first address of `config` that another process listens on, as the line that says so
/// and what to change; `None` when each could be bound a moment ago. Only "in use" is
/// reported here: any other failure is the listener's own to report.
pub fn first_in_use(config: &CellConfig) -> Option<String> {
    for endpoint in &config.bus.listen {
        if let Some(address) = tcp_address(endpoint)
            && in_use(address)
        {
            return Some(bus_in_use(endpoint));
        }
    }
    let mut others: Vec<(&str, &str, &str)> = Vec::new();
    if let Some(c) = &config.console {
        others.push((&c.listen, "the console", "[console] listen or --console"));
    }
    if let Some(m) = &config.mtconnect {
        others.push((
            &m.listen,
            "the MTConnect agent",
            "[mtconnect] listen or --mtconnect",
        ));
        if let Some(shdr) = &m.shdr_listen {
            others.push((shdr, "the SHDR adapter", "[mtconnect] shdr_listen"));
        }
    }
    others
        .into_iter()
        .find(|(a, ..)| in_use(a))
        .map(|(address, what, setting)| {
            format!(
                "cannot listen on {address} for {what}: the address is in use (another \
             gateway?) — choose another with {setting}"
            )
        })
}

/// The line for a bus endpoint in use.
pub fn bus_in_use(endpoint: &str) -> String {
    format!(
        "cannot listen on {endpoint}: the address is in use (another gateway?) — choose \
         another with [bus] listen or --listen"
    )
}

/// `HOST:PORT` of a `tcp/` or `tls/` endpoint (without zenoh's `?` and `#` options).
fn tcp_address(endpoint: &str) -> Option<&str> {
    let (proto, rest) = endpoint.split_once('/')?;
    if !matches!(proto, "tcp" | "tls") {
        return None;
    }
    rest.split(['?', '#']).next()
}

/// Whether some address `address` names refuses a bind as in use. Port 0 takes a free one.
fn in_use(address: &str) -> bool {
    let Ok(addrs) = address.to_socket_addrs() else {
        return false;
    };
    addrs.filter(|a| a.port() != 0).any(
        |a| matches!(TcpListener::bind(a), Err(e) if e.kind() == std::io::ErrorKind::AddrInUse),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_give_their_tcp_address() {
        assert_eq!(tcp_address("tcp/127.0.0.1:7447"), Some("127.0.0.1:7447"));
        assert_eq!(
            tcp_address("tls/gw.example:7447?iface=eth0"),
            Some("gw.example:7447")
        );
        assert_eq!(tcp_address("tcp/[::1]:7447#rel=1"), Some("[::1]:7447"));
        assert_eq!(tcp_address("unixsock-stream/run/cellgate.sock"), None);
        assert_eq!(tcp_address("udp/127.0.0.1:7447"), None);
    }

    #[test]
    fn a_port_someone_listens_on_is_in_use() {
        let taken = TcpListener::bind("127.0.0.1:0").unwrap();
        let address = taken.local_addr().unwrap().to_string();
        assert!(in_use(&address));
        drop(taken);
        assert!(!in_use(&address));
        assert!(!in_use("127.0.0.1:0"));
    }
}
