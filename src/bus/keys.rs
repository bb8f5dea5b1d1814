//! The cell's key expressions, built and parsed in one place.
//!
//! With `P` = `bus.prefix`, `C` = the cell, `M` = a machine, `ID` = a job id:
//!
//! | key | |
//! |---|---|
//! | `P/C/gateway` | liveliness token while the gateway runs |
//! | `P/C/@admin` | the gateway's admin document (a verbatim chunk: `P/C/**` does not match it) |
//! | `P/C/machine/M` | liveliness token while the machine's link is up |
//! | `P/C/machine/M/status` | `MachineStatus` |
//! | `P/C/machine/M/job` | job requests (`JobRequest` → `JobAccepted`), the queue |
//! | `P/C/machine/M/job/ID` | `JobEvent`s of one job; a delete cancels it |
//! | `P/C/machine/M/di` | `DiImage` |
//! | `P/C/machine/M/do` | `DoCommand` |
//! | `P/C/machine/M/alarm` | `AlarmEvent` |
//! | `P/C/machine/M/punch` | `PunchedProgram`s the CNC punched out (Protocol B) |
//! | `P/C/machine/M/g05` | G05 streams are opened here (`G05Open` → `G05Opened`) |
//! | `P/C/machine/M/g05/S` | a stream's `G05Status`; a delete cancels it |
//! | `P/C/machine/M/g05/S/blocks` | the stream's `G05Batch`es |
//! | `P/C/machine/M/g05/S/producer` | the producer's liveliness token |
//! | `P/C/program/NAME` | the program library |
//! | `P/C/plc/L/status` | `PlcStatus` of a PLC link: its stations, counters, tags |
//! | `P/C/plc/L/station/S` | liveliness token while station S answers |
//! | `P/C/plc/L/mem/S/MODULE/ADDR` | words of a module at station S (`PlcWords`; `PlcWrite` writes) |
//! | `P/C/plc/L/mem/S/MODULE` | `PlcWrite { clear }` clears the module |
//! | `P/C/plc/L/transfer/MSGNO` | `PlcTransfer`s from the PLC; one sent to it |
//! | `P/C/plc/L/tag/NAME` | a tag's `TagValue` on change; `TagWrite` writes it |
//!
//! The patterns that access-control rules name (`any_*`) are built here too, so that a route
//! and the rules that guard it cannot drift apart.
//!
//! zenoh's `kedefine!`/`keformat!` macros would declare these formats at compile time, but
//! in zenoh 1.10 they live in `zenoh::key_expr::format`, which exists only with zenoh's
//! `unstable` feature (the macro expands to paths under that module, so depending on
//! `zenoh-keyexpr` alone does not help). Turning `unstable` on would opt the whole gateway
//! into APIs zenoh may change in any release, for eight fixed formats. [`CellKeys`] does the
//! same job in plain code: every key is built here and nowhere else, every variable chunk is
//! checked to be one non-wild chunk, and [`CellKeys::parse`] reads a key back into a
//! [`CellKey`].

use zenoh::key_expr::{KeyExpr, keyexpr};

/// The leaf keys under `P/C/machine/M/`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MachineLeaf {
    Status,
    Job,
    Di,
    Do,
    Alarm,
    Punch,
    G05,
}

impl MachineLeaf {
    pub const ALL: [MachineLeaf; 7] = [
        MachineLeaf::Status,
        MachineLeaf::Job,
        MachineLeaf::Di,
        MachineLeaf::Do,
        MachineLeaf::Alarm,
        MachineLeaf::Punch,
        MachineLeaf::G05,
    ];

    pub fn chunk(self) -> &'static str {
        match self {
            MachineLeaf::Status => "status",
            MachineLeaf::Job => "job",
            MachineLeaf::Di => "di",
            MachineLeaf::Do => "do",
            MachineLeaf::Alarm => "alarm",
            MachineLeaf::Punch => "punch",
            MachineLeaf::G05 => "g05",
        }
    }

    fn from_chunk(chunk: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|l| l.chunk() == chunk)
    }
}

/// Which key of a G05 stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum G05Part {
    /// `P/C/machine/M/g05/S`: its status.
    Status,
    /// `…/S/blocks`: its batches.
    Blocks,
    /// `…/S/producer`: its producer's liveliness token.
    Producer,
}

impl G05Part {
    fn suffix(self) -> &'static str {
        match self {
            G05Part::Status => "",
            G05Part::Blocks => "/blocks",
            G05Part::Producer => "/producer",
        }
    }
}

/// The areas of a PLC link, `P/C/plc/L/<area>/...`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PlcArea {
    Mem,
    Transfer,
    Tag,
}

impl PlcArea {
    pub fn chunk(self) -> &'static str {
        match self {
            PlcArea::Mem => "mem",
            PlcArea::Transfer => "transfer",
            PlcArea::Tag => "tag",
        }
    }
}

/// A key under `P/C/plc/`, read back; chunks as they appear (numbers still text).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlcKey<'a> {
    Status {
        plc: &'a str,
    },
    Station {
        plc: &'a str,
        station: &'a str,
    },
    Mem {
        plc: &'a str,
        station: &'a str,
        module: &'a str,
        address: Option<&'a str>,
    },
    Transfer {
        plc: &'a str,
        message: &'a str,
    },
    Tag {
        plc: &'a str,
        name: &'a str,
    },
}

impl PlcKey<'_> {
    pub fn plc(&self) -> &str {
        match self {
            PlcKey::Status { plc }
            | PlcKey::Station { plc, .. }
            | PlcKey::Mem { plc, .. }
            | PlcKey::Transfer { plc, .. }
            | PlcKey::Tag { plc, .. } => plc,
        }
    }
}

/// A key of the cell, read back. Chunks are as they appear in the key: in a query's key they
/// may be wildcards.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CellKey<'a> {
    /// `P/C/gateway`
    Gateway,
    /// `P/C/@admin`
    Admin,
    /// `P/C/machine/M`
    Machine { machine: &'a str },
    /// `P/C/machine/M/<leaf>`
    Leaf { machine: &'a str, leaf: MachineLeaf },
    /// `P/C/machine/M/job/ID`
    JobEvents { machine: &'a str, job: &'a str },
    /// `P/C/machine/M/g05/S`, `…/S/blocks`, `…/S/producer`
    G05 {
        machine: &'a str,
        stream: &'a str,
        part: G05Part,
    },
    /// `P/C/program/NAME`
    Program { name: &'a str },
}

/// A prefix or cell that cannot start a key.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("key prefix {root:?} (bus.prefix / cell) is not a valid key without wildcards: {reason}")]
pub struct KeyError {
    pub root: String,
    pub reason: String,
}

/// Builds the keys of one cell.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CellKeys {
    /// `P/C`
    root: String,
}

/// Whether `chunk` is one key chunk without wildcards (machine names, job ids and library
/// names are all checked to be, before they get here).
pub fn is_plain_chunk(chunk: &str) -> bool {
    !chunk.contains('/') && keyexpr::new(chunk).is_ok_and(|k| !k.is_wild())
}

impl CellKeys {
    pub fn new(prefix: &str, cell: &str) -> Result<Self, KeyError> {
        let root = format!("{prefix}/{cell}");
        match keyexpr::new(root.as_str()) {
            Ok(k) if !k.is_wild() && is_plain_chunk(cell) => Ok(CellKeys { root }),
            Ok(_) => Err(KeyError {
                root,
                reason: "it contains a wildcard or the cell is more than one chunk".to_string(),
            }),
            Err(e) => Err(KeyError {
                root,
                reason: e.to_string(),
            }),
        }
    }

    /// `P/C`
    pub fn root(&self) -> &str {
        &self.root
    }

    /// `P/C/gateway`: the gateway's liveliness token.
    pub fn gateway(&self) -> String {
        format!("{}/gateway", self.root)
    }

    /// `P/C/@admin`: the gateway's admin document.
    pub fn admin(&self) -> String {
        format!("{}/{ADMIN_CHUNK}", self.root)
    }

    /// `P/C/**`: everything the cell publishes (the admin key aside).
    pub fn all(&self) -> String {
        format!("{}/**", self.root)
    }

    /// `P/C/machine/M`: the machine's liveliness token.
    pub fn machine(&self, machine: &str) -> String {
        format!("{}/machine/{machine}", self.root)
    }

    /// `P/C/machine/M/<leaf>`
    pub fn leaf(&self, machine: &str, leaf: MachineLeaf) -> String {
        format!("{}/machine/{machine}/{}", self.root, leaf.chunk())
    }

    /// `P/C/machine/M/job/ID`
    pub fn job_events(&self, machine: &str, job: &str) -> String {
        format!("{}/machine/{machine}/job/{job}", self.root)
    }

    /// `P/C/machine/M/g05/S`, `…/blocks`, `…/producer`
    pub fn g05(&self, machine: &str, stream: &str, part: G05Part) -> String {
        format!(
            "{}/machine/{machine}/g05/{stream}{}",
            self.root,
            part.suffix()
        )
    }

    /// `P/C/machine/*/g05/*` (and its `blocks` or `producer`)
    pub fn any_g05(&self, part: G05Part) -> String {
        self.g05("*", "*", part)
    }

    /// `P/C/program/NAME`
    pub fn program(&self, name: &str) -> String {
        format!("{}/program/{name}", self.root)
    }

    /// `P/C/machine/*/<leaf>`: every machine's leaf.
    pub fn any_leaf(&self, leaf: MachineLeaf) -> String {
        self.leaf("*", leaf)
    }

    /// `P/C/machine/*/job/*`
    pub fn any_job_events(&self) -> String {
        self.job_events("*", "*")
    }

    /// `P/C/program/*`
    pub fn any_program(&self) -> String {
        self.program("*")
    }

    /// `P/C/machine/*`: every machine's liveliness token.
    pub fn any_machine(&self) -> String {
        self.machine("*")
    }

    /// `P/C/machine/*/g05/**`: every machine's G05 keys (`**` also takes in `.../g05`).
    pub fn every_g05_key(&self) -> String {
        format!("{}/**", self.leaf("*", MachineLeaf::G05))
    }

    /// `P/C/plc/L/<area>`
    pub fn plc_area(&self, link: &str, area: PlcArea) -> String {
        format!("{}/plc/{link}/{}", self.root, area.chunk())
    }

    /// `P/C/plc/L/status`
    pub fn plc_status(&self, link: &str) -> String {
        format!("{}/plc/{link}/status", self.root)
    }

    /// `P/C/plc/*/status`
    pub fn any_plc_status(&self) -> String {
        self.plc_status("*")
    }

    /// `P/C/plc/L/station/S`: the station's liveliness token.
    pub fn plc_station(&self, link: &str, station: u8) -> String {
        format!("{}/plc/{link}/station/{station}", self.root)
    }

    /// `P/C/plc/L/mem/S/MODULE[/ADDR]`
    pub fn plc_mem(&self, link: &str, station: u8, module: &str, address: Option<u16>) -> String {
        let base = format!("{}/{station}/{module}", self.plc_area(link, PlcArea::Mem));
        match address {
            Some(a) => format!("{base}/{a}"),
            None => base,
        }
    }

    /// `P/C/plc/L/transfer/MSGNO`
    pub fn plc_transfer(&self, link: &str, message: u8) -> String {
        format!("{}/{message}", self.plc_area(link, PlcArea::Transfer))
    }

    /// `P/C/plc/L/tag/NAME`
    pub fn plc_tag(&self, link: &str, name: &str) -> String {
        format!("{}/{name}", self.plc_area(link, PlcArea::Tag))
    }

    /// Reads a key under `P/C/plc/` back.
    pub fn parse_plc<'k>(&self, key: &'k str) -> Option<PlcKey<'k>> {
        let rest = key
            .strip_prefix(self.root.as_str())?
            .strip_prefix("/plc/")?;
        let chunks: Vec<&str> = rest.split('/').collect();
        match chunks.as_slice() {
            [plc, "status"] => Some(PlcKey::Status { plc }),
            [plc, "station", s] => Some(PlcKey::Station { plc, station: s }),
            [plc, "mem", s, m] => Some(PlcKey::Mem {
                plc,
                station: s,
                module: m,
                address: None,
            }),
            [plc, "mem", s, m, a] => Some(PlcKey::Mem {
                plc,
                station: s,
                module: m,
                address: Some(a),
            }),
            [plc, "transfer", n] => Some(PlcKey::Transfer { plc, message: n }),
            [plc, "tag", n] => Some(PlcKey::Tag { plc, name: n }),
            _ => None,
        }
    }

    /// `P/C/plc/*/<area>/**`: one area of every PLC link.
    pub fn any_plc_area(&self, area: PlcArea) -> String {
        format!("{}/**", self.plc_area("*", area))
    }

    /// `P/C/plc/**`: everything of the cell's PLC links.
    pub fn any_plc(&self) -> String {
        format!("{}/plc/**", self.root)
    }

    /// Reads a key of this cell back; `None` for a key that is not one.
    pub fn parse<'k>(&self, key: &'k str) -> Option<CellKey<'k>> {
        let rest = key.strip_prefix(self.root.as_str())?.strip_prefix('/')?;
        let chunks: Vec<&'k str> = rest.split('/').collect();
        match chunks.as_slice() {
            ["gateway"] => Some(CellKey::Gateway),
            [ADMIN_CHUNK] => Some(CellKey::Admin),
            ["machine", m] => Some(CellKey::Machine { machine: m }),
            ["machine", m, leaf] => Some(CellKey::Leaf {
                machine: m,
                leaf: MachineLeaf::from_chunk(leaf)?,
            }),
            ["machine", m, "job", id] => Some(CellKey::JobEvents {
                machine: m,
                job: id,
            }),
            ["machine", m, "g05", id, rest @ ..] => Some(CellKey::G05 {
                machine: m,
                stream: id,
                part: match rest {
                    [] => G05Part::Status,
                    ["blocks"] => G05Part::Blocks,
                    ["producer"] => G05Part::Producer,
                    _ => return None,
                },
            }),
            ["program", name] => Some(CellKey::Program { name }),
            _ => None,
        }
    }
}

/// The admin chunk: verbatim, so that wildcards never match it.
const ADMIN_CHUNK: &str = "@admin";

/// `P/<cell>/@admin` for discovery, where `cell` may be `*` (any cell under `prefix`).
pub fn admin_selector(prefix: &str, cell: &str) -> String {
    format!("{prefix}/{cell}/{ADMIN_CHUNK}")
}

/// `P/<cell>/gateway` for discovery, where `cell` may be `*` (any cell under `prefix`).
pub fn gateway_selector(prefix: &str, cell: &str) -> String {
    format!("{prefix}/{cell}/gateway")
}

/// The cell of a gateway's liveliness token `P/<cell>/gateway` under `prefix`.
pub fn cell_of_gateway_key<'k>(prefix: &str, key: &'k str) -> Option<&'k str> {
    key.strip_prefix(prefix)?
        .strip_prefix('/')?
        .strip_suffix("/gateway")
        .filter(|cell| is_plain_chunk(cell))
}

/// The cell of an admin key `P/<cell>/@admin` under `prefix`.
pub fn cell_of_admin_key<'k>(prefix: &str, key: &'k str) -> Option<&'k str> {
    key.strip_prefix(prefix)?
        .strip_prefix('/')?
        .strip_suffix(ADMIN_CHUNK)?
        .strip_suffix('/')
        .filter(|cell| is_plain_chunk(cell))
}

/// Whether a query's key expression `query` takes in the concrete key `key`.
pub fn intersects(query: &KeyExpr<'_>, key: &str) -> bool {
    keyexpr::new(key).is_ok_and(|k| query.intersects(k))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_built_and_read_back() {
        let k = CellKeys::new("cellgate", "line-3").unwrap();
        assert_eq!(k.machine("mill-1"), "cellgate/line-3/machine/mill-1");
        assert_eq!(
            k.leaf("mill-1", MachineLeaf::Status),
            "cellgate/line-3/machine/mill-1/status"
        );
        assert_eq!(
            k.job_events("mill-1", "mill-1-t0-7"),
            "cellgate/line-3/machine/mill-1/job/mill-1-t0-7"
        );
        assert_eq!(k.program("O1234"), "cellgate/line-3/program/O1234");
        assert_eq!(k.any_leaf(MachineLeaf::Do), "cellgate/line-3/machine/*/do");
        for leaf in MachineLeaf::ALL {
            let key = k.leaf("m", leaf);
            assert_eq!(k.parse(&key), Some(CellKey::Leaf { machine: "m", leaf }));
        }
        assert_eq!(
            k.parse(&k.job_events("m", "j")),
            Some(CellKey::JobEvents {
                machine: "m",
                job: "j"
            })
        );
        assert_eq!(
            k.parse(&k.program("p")),
            Some(CellKey::Program { name: "p" })
        );
        assert_eq!(
            k.parse(&k.machine("m")),
            Some(CellKey::Machine { machine: "m" })
        );
        assert_eq!(k.gateway(), "cellgate/line-3/gateway");
        assert_eq!(k.admin(), "cellgate/line-3/@admin");
        assert_eq!(k.parse(&k.gateway()), Some(CellKey::Gateway));
        assert_eq!(k.parse(&k.admin()), Some(CellKey::Admin));
        assert_eq!(admin_selector("cellgate", "*"), "cellgate/*/@admin");
        assert_eq!(
            cell_of_admin_key("cellgate", "cellgate/line-3/@admin"),
            Some("line-3")
        );
        assert_eq!(cell_of_admin_key("cellgate", "cellgate/a/b/@admin"), None);
        assert_eq!(cell_of_admin_key("cellgate", "other/line-3/@admin"), None);
        for part in [G05Part::Status, G05Part::Blocks, G05Part::Producer] {
            let key = k.g05("m", "s1", part);
            assert_eq!(
                k.parse(&key),
                Some(CellKey::G05 {
                    machine: "m",
                    stream: "s1",
                    part
                })
            );
        }
        assert_eq!(
            k.g05("m", "s1", G05Part::Blocks),
            "cellgate/line-3/machine/m/g05/s1/blocks"
        );
        assert_eq!(k.parse("cellgate/line-3/machine/m/g05/s1/other"), None);
        assert_eq!(k.parse("cellgate/line-3/machine/m/nope"), None);
        assert_eq!(k.parse("cellgate/line-30/program/p"), None);
        assert_eq!(k.parse("other/line-3/program/p"), None);
    }

    #[test]
    fn every_built_key_is_a_valid_key_expression() {
        let k = CellKeys::new("factory/a", "c1").unwrap();
        let keys = [
            k.machine("m"),
            k.leaf("m", MachineLeaf::Alarm),
            k.job_events("m", "m-x-1"),
            k.program("O1.nc"),
            k.any_leaf(MachineLeaf::Status),
            k.any_job_events(),
            k.any_program(),
            k.gateway(),
            k.admin(),
            k.all(),
            k.any_machine(),
            k.leaf("m", MachineLeaf::G05),
            k.g05("m", "s", G05Part::Blocks),
            k.any_g05(G05Part::Status),
            k.every_g05_key(),
            k.plc_area("plc-1", PlcArea::Tag),
            k.any_plc_area(PlcArea::Mem),
            k.any_plc(),
            gateway_selector("factory/a", "*"),
        ];
        for key in keys {
            assert!(keyexpr::new(key.as_str()).is_ok(), "{key}");
        }
    }

    #[test]
    fn wild_or_malformed_roots_are_refused() {
        assert!(CellKeys::new("cellgate", "*").is_err());
        assert!(CellKeys::new("a/**", "c").is_err());
        assert!(CellKeys::new("a//b", "c").is_err());
        assert!(CellKeys::new("a", "b/c").is_err());
        assert!(is_plain_chunk("mill-1"));
        assert!(!is_plain_chunk("a/b"));
        assert!(!is_plain_chunk("*"));
        assert!(!is_plain_chunk(""));
    }

    #[test]
    fn route_patterns_take_in_their_keys_and_no_others() {
        let k = CellKeys::new("cellgate", "c").unwrap();
        let includes = |pattern: &str, key: &str| {
            keyexpr::new(pattern)
                .unwrap()
                .includes(keyexpr::new(key).unwrap())
        };
        let g05 = k.every_g05_key();
        assert!(includes(&g05, &k.leaf("m1", MachineLeaf::G05)));
        assert!(includes(&g05, &k.g05("m1", "s-7", G05Part::Status)));
        assert!(includes(&g05, &k.g05("m1", "s-7", G05Part::Blocks)));
        assert!(includes(&g05, &k.g05("m1", "s-7", G05Part::Producer)));
        assert!(!includes(&g05, &k.leaf("m1", MachineLeaf::Do)));
        let tags = k.any_plc_area(PlcArea::Tag);
        assert!(includes(&tags, "cellgate/c/plc/plc-1/tag/door"));
        assert!(!includes(&tags, "cellgate/c/plc/plc-1/mem/D/100"));
        assert!(includes(&k.any_plc(), "cellgate/c/plc/plc-1/mem/D/100"));
        assert!(includes(&k.any_machine(), &k.machine("m1")));
        assert!(!includes(
            &k.any_machine(),
            &k.leaf("m1", MachineLeaf::Status)
        ));
        assert_eq!(gateway_selector("cellgate", "c"), k.gateway());
        assert_eq!(cell_of_gateway_key("cellgate", &k.gateway()), Some("c"));
        assert_eq!(
            cell_of_gateway_key("cellgate", "cellgate/a/b/gateway"),
            None
        );
    }

    #[test]
    fn wildcard_queries_take_in_matching_keys() {
        let k = CellKeys::new("cellgate", "c").unwrap();
        let q = KeyExpr::new("cellgate/c/machine/*/status").unwrap();
        assert!(intersects(&q, &k.leaf("m1", MachineLeaf::Status)));
        assert!(!intersects(&q, &k.leaf("m1", MachineLeaf::Di)));
        let all = KeyExpr::new("cellgate/c/**").unwrap();
        assert!(intersects(&all, &k.program("p")));
    }
}
