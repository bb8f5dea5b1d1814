//! What the agent knows of a cell before any observation: its machines and PLCs, as the cell
//! file names them. The gateway's agent reads its own cell file; a site agent reads each
//! gateway's `@admin` document where its role may (`admin.read`), else what the statuses
//! show (`status.read` is all it needs).

use serde::Deserialize;

use crate::config::{CellConfig, TagType};
use crate::fanuc::Protocol;
use crate::pb;

/// A cell as the agent models it.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct CellDesc {
    /// The cell's name (`cell` of the cell file).
    pub cell: String,
    /// Its machines, in the cell file's order.
    pub machines: Vec<MachineDesc>,
    /// Its PLCs, in the cell file's order.
    pub plcs: Vec<PlcDesc>,
}

/// A FANUC CNC behind a remote buffer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MachineDesc {
    /// The machine's name in the cell file.
    pub name: String,
    /// The remote-buffer protocol: the A family has DI/DO (§4.4.2), the B family none.
    pub protocol: Protocol,
    /// `part_counter`: the PLC and tag that count this machine's parts.
    pub part_counter: Option<(String, String)>,
    /// Whether the machine takes G05 streams (`[machines.g05]`, §9).
    pub g05: bool,
    /// Its nameplate (`identification`), as far as the cell file gives it.
    pub identification: crate::config::Identification,
}

/// A Fuji MICREX-F PLC behind FFU120B modules.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlcDesc {
    /// The PLC's name in the cell file.
    pub name: String,
    /// Its stations (RS-485 addresses; the one station of a 1:1 link is 0).
    pub stations: Vec<u32>,
    /// Its named tags.
    pub tags: Vec<TagDesc>,
}

/// A named PLC tag.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TagDesc {
    /// The tag's name in the cell file.
    pub name: String,
    /// Where it lives, as the PLC names it: `D0`, `M0.3` (module, word, bit), with the station
    /// first when it is not 0 (`2:D10`); empty when unknown.
    pub native: String,
    /// What it is in MTConnect (`[[plcs.tags]] mtconnect`): `None` is a VARIABLE.
    pub typed: Option<crate::mtconnect::types::TagType>,
    /// Its units, for a SAMPLE: the cell file's, else the type's.
    pub units: Option<&'static str>,
}

/// The type and units of a tag's `mtconnect` setting, as the agent can show them: an unknown
/// type (a newer gateway's) is a VARIABLE, unknown units the type's own.
fn typed(
    kind: Option<&str>,
    units: Option<&str>,
) -> (
    Option<crate::mtconnect::types::TagType>,
    Option<&'static str>,
) {
    use crate::mtconnect::types;
    let Some(t) = kind.and_then(types::tag_type) else {
        return (None, None);
    };
    (
        Some(t),
        units
            .and_then(types::units)
            .or(t.units)
            .filter(|_| t.units.is_some()),
    )
}

fn protocol_of(p: pb::Protocol) -> Protocol {
    match p {
        pb::Protocol::ExpansionA => Protocol::ExpansionA,
        pb::Protocol::B => Protocol::B,
        pb::Protocol::ExpansionB => Protocol::ExpansionB,
        pb::Protocol::A | pb::Protocol::Unspecified => Protocol::A,
    }
}

fn native(station: u32, module: &str, address: u32, bit: Option<u32>) -> String {
    let mut s = if station == 0 {
        String::new()
    } else {
        format!("{station}:")
    };
    s.push_str(module);
    s.push_str(&address.to_string());
    if let Some(b) = bit {
        s.push('.');
        s.push_str(&b.to_string());
    }
    s
}

fn part_counter(text: Option<&str>) -> Option<(String, String)> {
    let (plc, tag) = text?.split_once('/')?;
    Some((plc.to_string(), tag.to_string()))
}

/// The machines and PLCs of the cell file part of an `@admin` document (the running
/// configuration): only the keys the agent needs, the others ignored.
#[derive(Deserialize)]
struct AdminConfig {
    #[serde(default)]
    machines: Vec<AdminMachine>,
    #[serde(default)]
    plcs: Vec<AdminPlc>,
}

#[derive(Deserialize)]
struct AdminMachine {
    name: String,
    protocol: Protocol,
    #[serde(default)]
    part_counter: Option<String>,
    #[serde(default)]
    g05: Option<serde_json::Value>,
    #[serde(default)]
    identification: Option<crate::config::Identification>,
}

#[derive(Deserialize)]
struct AdminPlc {
    name: String,
    #[serde(default)]
    stations: Vec<u32>,
    #[serde(default)]
    tags: Vec<AdminTag>,
}

#[derive(Deserialize)]
struct AdminTag {
    name: String,
    #[serde(default)]
    station: u32,
    #[serde(default)]
    module: String,
    #[serde(default)]
    address: u32,
    #[serde(rename = "type")]
    kind: TagType,
    #[serde(default)]
    bit: Option<u32>,
    #[serde(default)]
    mtconnect: Option<AdminTagMtconnect>,
}

#[derive(Deserialize)]
struct AdminTagMtconnect {
    #[serde(rename = "type")]
    kind: String,
    #[serde(default)]
    units: Option<String>,
}

impl CellDesc {
    /// The cell of a cell file.
    pub fn from_config(config: &CellConfig) -> CellDesc {
        CellDesc {
            cell: config.cell.clone(),
            machines: config
                .machines
                .iter()
                .map(|m| MachineDesc {
                    name: m.name.clone(),
                    protocol: m.protocol,
                    part_counter: part_counter(m.part_counter.as_deref()),
                    g05: m.g05.is_some(),
                    identification: m.identification.clone().unwrap_or_default(),
                })
                .collect(),
            plcs: config
                .plcs
                .iter()
                .map(|p| PlcDesc {
                    name: p.name.clone(),
                    stations: p.stations.iter().map(|&s| u32::from(s)).collect(),
                    tags: p
                        .tags
                        .iter()
                        .map(|t| {
                            let (typed, units) = typed(
                                t.mtconnect.as_ref().map(|m| m.kind.as_str()),
                                t.mtconnect.as_ref().and_then(|m| m.units.as_deref()),
                            );
                            TagDesc {
                                name: t.name.clone(),
                                typed,
                                units,
                                native: native(
                                    u32::from(t.station),
                                    &t.module.symbol(),
                                    u32::from(t.address),
                                    (t.kind == TagType::Bit).then(|| u32::from(t.bit.unwrap_or(0))),
                                ),
                            }
                        })
                        .collect(),
                })
                .collect(),
        }
    }

    /// The cell of a gateway's `@admin` document; `None` when the document does not show the
    /// configuration (a role without `admin.read`) or shows one the agent cannot read.
    pub fn from_admin(cell: &str, admin: &serde_json::Value) -> Option<CellDesc> {
        let config = AdminConfig::deserialize(admin.get("config")?).ok()?;
        Some(CellDesc {
            cell: cell.to_string(),
            machines: config
                .machines
                .into_iter()
                .map(|m| MachineDesc {
                    part_counter: part_counter(m.part_counter.as_deref()),
                    g05: m.g05.is_some_and(|g| !g.is_null()),
                    identification: m.identification.unwrap_or_default(),
                    name: m.name,
                    protocol: m.protocol,
                })
                .collect(),
            plcs: config
                .plcs
                .into_iter()
                .map(|p| PlcDesc {
                    stations: if p.stations.is_empty() {
                        vec![0]
                    } else {
                        p.stations
                    },
                    tags: p
                        .tags
                        .into_iter()
                        .map(|t| {
                            let (typed, units) = typed(
                                t.mtconnect.as_ref().map(|m| m.kind.as_str()),
                                t.mtconnect.as_ref().and_then(|m| m.units.as_deref()),
                            );
                            TagDesc {
                                typed,
                                units,
                                native: native(
                                    t.station,
                                    &t.module,
                                    t.address,
                                    (t.kind == TagType::Bit).then(|| t.bit.unwrap_or(0)),
                                ),
                                name: t.name,
                            }
                        })
                        .collect(),
                    name: p.name,
                })
                .collect(),
        })
    }

    /// This cell with the machines and PLCs `partial` names (a description read from
    /// statuses, [`CellDesc::from_status`]): those it names anew from it, the others as they
    /// were, so that what the statuses cannot show (part counters, tag addresses) is kept.
    pub fn with_names_of(&self, partial: &CellDesc) -> CellDesc {
        CellDesc {
            cell: self.cell.clone(),
            machines: partial
                .machines
                .iter()
                .map(|m| {
                    self.machines
                        .iter()
                        .find(|o| o.name == m.name)
                        .unwrap_or(m)
                        .clone()
                })
                .collect(),
            plcs: partial
                .plcs
                .iter()
                .map(|p| {
                    self.plcs
                        .iter()
                        .find(|o| o.name == p.name)
                        .unwrap_or(p)
                        .clone()
                })
                .collect(),
        }
    }

    /// The cell as its statuses show it (what `status.read` sees): no part counters, no tag
    /// addresses, G05 only where a stream was seen.
    pub fn from_status(cell: &str, machines: &[pb::MachineStatus], plcs: &[pb::PlcStatus]) -> Self {
        CellDesc {
            cell: cell.to_string(),
            machines: machines
                .iter()
                .map(|m| MachineDesc {
                    name: m.machine.clone(),
                    protocol: protocol_of(m.protocol()),
                    part_counter: None,
                    g05: m.g05.is_some(),
                    identification: Default::default(),
                })
                .collect(),
            plcs: plcs
                .iter()
                .map(|p| PlcDesc {
                    name: p.plc.clone(),
                    stations: p.stations.iter().map(|s| s.station).collect(),
                    tags: p
                        .tags
                        .iter()
                        .map(|t| TagDesc {
                            name: t.name.clone(),
                            native: String::new(),
                            typed: None,
                            units: None,
                        })
                        .collect(),
                })
                .collect(),
        }
    }
}
