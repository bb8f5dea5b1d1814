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
