//! Opening the gateway's Zenoh session from `[bus]` and `[security]` of the cell file.
//!
//! The session starts from zenoh's defaults, or from the json5 file `bus.zenoh_config`,
//! and the keys of [`BusConfig`] are then written over it. That keeps the gateway on the
//! endpoints the cell file names: a zenoh peer with no explicit listen endpoint would
//! listen on every interface, and one with multicast scouting on would announce itself
//! to the whole network. `[security]` then sets TLS, the user-password dictionary and the
//! access-control rules of the roles (merged with the file's own rules, [`super::acl`]).

use std::path::Path;

use super::acl;
use super::error::BusError;
use super::keys::CellKeys;
use cellgate_core::config::{BusConfig, CellConfig};

/// The zenoh configuration the gateway opens its session with: the json5 file (if any),
/// then every key of `cfg` on top.
pub fn zenoh_config(cfg: &BusConfig) -> Result<zenoh::Config, BusError> {
    let mut config = match &cfg.zenoh_config {
        Some(path) => zenoh::Config::from_file(path).map_err(|source| BusError::ConfigFile {
            path: path.clone(),
            source,
        })?,
        None => zenoh::Config::default(),
    };
    let settings: [(&'static str, &'static str, String); 4] = [
        ("mode", "mode", json(cfg.mode.as_str())),
        (
            "multicast_scouting",
            "scouting/multicast/enabled",
            json(&cfg.multicast_scouting),
        ),
        ("listen", "listen/endpoints", json(&cfg.listen)),
        ("connect", "connect/endpoints", json(&cfg.connect)),
    ];
    for (field, key, value) in settings {
        config
            .insert_json5(key, &value)
            .map_err(|source| BusError::ConfigValue {
                field,
                value,
                source,
            })?;
    }
    Ok(config)
}

/// A path as zenoh's configuration takes it (a JSON string).
fn path_json(field: &'static str, path: &Path) -> Result<String, BusError> {
    path.to_str().map(json).ok_or_else(|| BusError::Path {
        field,
        path: path.to_path_buf(),
    })
}

fn insert(
    config: &mut zenoh::Config,
    field: &'static str,
    key: &str,
    value: &str,
) -> Result<(), BusError> {
    config
        .insert_json5(key, value)
        .map_err(|source| BusError::SecurityValue { field, source })
}

/// The zenoh configuration of the gateway of `cell`: [`zenoh_config`] of its `[bus]`, then its
/// `[security]`: TLS on listeners and connections, the user-password dictionary, and the
/// roles as access-control rules added to those of the zenoh file, if any.
pub fn cell_zenoh_config(cell: &CellConfig) -> Result<zenoh::Config, BusError> {
    let mut config = zenoh_config(&cell.bus)?;
    let security = &cell.security;
    if let Some(tls) = &security.tls {
        const TLS: &str = "transport/link/tls";
        let ca = path_json("security.tls.ca", &tls.ca)?;
        let certificate = path_json("security.tls.certificate", &tls.certificate)?;
        let key = path_json("security.tls.private_key", &tls.private_key)?;
        for (field, name, value) in [
            ("security.tls.ca", "root_ca_certificate", &ca),
            (
                "security.tls.certificate",
                "listen_certificate",
                &certificate,
            ),
            ("security.tls.private_key", "listen_private_key", &key),
            // A router that asks for client certificates gets the gateway's own.
            (
                "security.tls.certificate",
                "connect_certificate",
                &certificate,
            ),
            ("security.tls.private_key", "connect_private_key", &key),
            (
                "security.tls.require_client_certificates",
                "enable_mtls",
                &json(&tls.require_client_certificates),
            ),
            (
                "security.tls.verify_name_on_connect",
                "verify_name_on_connect",
                &json(&tls.verify_name_on_connect),
            ),
        ] {
            insert(&mut config, field, &format!("{TLS}/{name}"), value)?;
        }
    }
    if let Some(users) = &security.users_file {
        let value = path_json("security.users_file", users)?;
        insert(
            &mut config,
            "security.users_file",
            "transport/auth/usrpwd/dictionary_file",
            &value,
        )?;
    }
    let keys = CellKeys::new(&cell.bus.prefix, &cell.cell)?;
    if let Some(ours) = acl::access_control(security, &keys, &cell.bus.prefix) {
        let theirs = config
            .get_json("access_control")
            .ok()
            .and_then(|text| serde_json::from_str(&text).ok())
            .unwrap_or(serde_json::Value::Null);
        let merged = acl::merge(&theirs, ours)?;
        insert(
            &mut config,
            "security.roles",
            "access_control",
            &merged.to_string(),
        )?;
    }
    Ok(config)
}

/// Opens the gateway's Zenoh session for `cell` ([`cell_zenoh_config`]). Must run on a
/// multi-thread Tokio runtime; close it with `session.close().await` before the runtime ends.
pub async fn open_cell(cell: &CellConfig) -> Result<zenoh::Session, BusError> {
    let config = cell_zenoh_config(cell)?;
    zenoh::open(config).await.map_err(|source| BusError::Open {
        listen: cell.bus.listen.clone(),
        connect: cell.bus.connect.clone(),
        source,
    })
}

/// Opens a Zenoh session from `[bus]` alone (no `[security]`). Must run on a multi-thread
/// Tokio runtime (zenoh panics on a current-thread one). Close it with
/// `session.close().await` before the runtime ends.
pub async fn open(cfg: &BusConfig) -> Result<zenoh::Session, BusError> {
    let config = zenoh_config(cfg)?;
    zenoh::open(config).await.map_err(|source| BusError::Open {
        listen: cfg.listen.clone(),
        connect: cfg.connect.clone(),
        source,
    })
}

/// A value as json5 text for `insert_json5` (JSON is valid json5).
fn json<T: serde::Serialize + ?Sized>(value: &T) -> String {
    // Serialising a &str, a bool or a Vec<String> cannot fail.
    serde_json::to_string(value).unwrap_or_default()
}

#[cfg(test)]
mod tests;
