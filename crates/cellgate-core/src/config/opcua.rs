//! `[opcua]`: the OPC UA server the gateway serves (docs/opcua.md).

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::error::{Checker, q};

/// `[opcua]`: where the OPC UA server (OPC 40501 Machine Tools) listens and where it keeps its
/// certificates. Without the section the gateway serves none.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OpcuaConfig {
    /// `ADDRESS:PORT` of the server's `opc.tcp` endpoint.
    pub listen: String,
    /// The PKI folder: the server's own certificate (`own/cert.der`, `private/private.pem`,
    /// made on first start), client certificates to trust (`trusted/`) and those refused
    /// (`rejected/`). Default: `pki` beside the job journal.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pki_dir: Option<PathBuf>,
    /// The server's certificate (DER), given instead of the one made on first start; with
    /// `private_key`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub certificate: Option<PathBuf>,
    /// The certificate's private key (PEM).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub private_key: Option<PathBuf>,
}

impl Default for OpcuaConfig {
    fn default() -> Self {
        OpcuaConfig {
            listen: Self::DEFAULT_LISTEN.to_string(),
            pki_dir: None,
            certificate: None,
            private_key: None,
        }
    }
}

impl OpcuaConfig {
    /// Where the server listens unless the cell file says otherwise (4840: OPC UA's port).
    pub const DEFAULT_LISTEN: &'static str = "127.0.0.1:4840";

    /// Whether `listen` is a loopback address.
    pub fn is_loopback(&self) -> bool {
        self.listen
            .parse::<std::net::SocketAddr>()
            .is_ok_and(|a| a.ip().is_loopback())
    }

    /// A server reachable beyond this host on a cell without users: anybody who reaches it
    /// reads the cell (it never writes).
    pub fn warnings(&self, has_users: bool) -> Vec<String> {
        if has_users || self.is_loopback() {
            return Vec::new();
        }
        vec![format!(
            "opcua.listen {:?} is reachable beyond this host and the cell has no users file: \
             anyone who reaches it may read the cell's state anonymously (it never writes); \
             listen on 127.0.0.1 or add [security] users",
            self.listen
        )]
    }
}

pub(super) fn check_opcua(c: &mut Checker, o: &OpcuaConfig) {
    if o.listen.parse::<std::net::SocketAddr>().is_err() {
        c.invalid(
            "opcua.listen".to_string(),
            q(&o.listen),
            "must be ADDRESS:PORT, e.g. \"127.0.0.1:4840\" or \"[::1]:4840\"".to_string(),
            "",
        );
    }
    if o.certificate.is_some() != o.private_key.is_some() {
        c.invalid(
            "opcua.certificate".to_string(),
            "one of certificate and private_key".to_string(),
            "give both the certificate and its private key, or neither (one is made on first \
             start)"
                .to_string(),
            "",
        );
    }
}

#[cfg(test)]
mod tests {
    use crate::config::{CellConfig, OpcuaConfig};

    const CELL: &str = "cell = \"c\"\n[[machines]]\nname = \"m1\"\nprotocol = \"a\"\n\
                        transport = { kind = \"sim\", line = { baud = 9600 } }\n";

    fn errors_of(text: &str) -> Vec<String> {
        match CellConfig::from_toml_str(text, "t") {
            Ok(_) => Vec::new(),
            Err(e) => e.to_string().lines().map(str::to_string).collect(),
        }
    }

    #[test]
    fn opcua_takes_an_address_and_both_halves_of_a_certificate() {
        let with = |section: &str| format!("{CELL}[opcua]\n{section}\n");
        let cfg = CellConfig::from_toml_str(&with(""), "t").unwrap();
        assert_eq!(cfg.opcua, Some(OpcuaConfig::default()));
        assert!(cfg.warnings().is_empty(), "{:?}", cfg.warnings());
        let e = errors_of(&with("listen = \"localhost\"\ncertificate = \"c.der\""));
        assert!(e.iter().any(|m| m.contains("opcua.listen")), "{e:?}");
        assert!(e.iter().any(|m| m.contains("opcua.certificate")), "{e:?}");
        // Beyond loopback without users: allowed (it only reads), and warned of.
        let cfg = CellConfig::from_toml_str(&with("listen = \"0.0.0.0:4840\""), "t").unwrap();
        assert!(
            cfg.warnings().iter().any(|w| w.contains("opcua.listen")),
            "{:?}",
            cfg.warnings()
        );
        let back = CellConfig::from_toml_str(&cfg.to_toml_string().unwrap(), "t").unwrap();
        assert_eq!(back.opcua, cfg.opcua);
    }

    #[test]
    fn a_machines_identification_is_short_and_printable() {
        let with = |id: &str| {
            CELL.replace(
                "protocol = \"a\"\n",
                &format!("protocol = \"a\"\nidentification = {id}\n"),
            )
        };
        let cfg = CellConfig::from_toml_str(
            &with("{ manufacturer = \"Okuma\", serial_number = \"MB-1\" }"),
            "t",
        )
        .unwrap();
        let id = cfg.machines[0].identification.clone().unwrap();
        assert_eq!(id.manufacturer.as_deref(), Some("Okuma"));
        assert_eq!(id.product_instance_uri, None);
        let long = "x".repeat(300);
        let e = errors_of(&with(&format!(
            "{{ manufacturer = \"{long}\", serial_number = \"a\\nb\" }}"
        )));
        assert!(
            e.iter().any(|m| m.contains("identification.manufacturer")),
            "{e:?}"
        );
        assert!(
            e.iter().any(|m| m.contains("identification.serial_number")),
            "{e:?}"
        );
        let e = errors_of(&with("{ maker = \"x\" }"));
        assert!(e.iter().any(|m| m.contains("maker")), "{e:?}");
    }
}
