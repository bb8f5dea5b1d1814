//! Every key the gateway publishes on, one [`Publication`] each: the other half of the
//! route table ([`routes`](super::routes) holds what arrives). Each row gives the key as a
//! subscriber names it (the core's grammar), the message, the QoS it goes out with, and the
//! permissions whose rules let a client subscribe to it: [`acl`](super::acl) takes the keys
//! of its publication grants from here, and a test checks the key tables of docs/bus.md
//! and docs/plc.md against both tables. A new publication is a row here; its publisher takes its QoS from
//! [`Published::congestion`] and [`Published::priority`].
//!
//! Liveliness tokens (the gateway's, each machine's and PLC station's, a G05 producer's) are
//! presence, not publications: [`acl`](super::acl) grants them apart.

use zenoh::qos::{CongestionControl, Priority};

use super::keys::{CellKeys, MachineLeaf};
use cellgate_core::config::Permission;

/// What the gateway publishes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Published {
    /// `P/C/machine/M/status`: on change.
    MachineStatus,
    /// `P/C/machine/M/di`: whenever DI is read.
    Di,
    /// `P/C/machine/M/alarm`: CNC alarms and resets, link alarms with the manual's number
    /// (SR0855, SR0856, SR0944–SR0948), punched programs lost, remote requests that could
    /// not be served, G05 starvation.
    Alarm,
    /// `P/C/machine/M/punch`: each program the CNC punched out.
    Punch,
    /// `P/C/machine/M/job/ID`: a job's events.
    JobEvent,
    /// `P/C/machine/M/do/out`: a DO a get asked for, once it went out.
    DoOut,
    /// `P/C/program/NAME/changed`: a store, adoption or removal on disk.
    ProgramChanged,
    /// `P/C/program/@events`: what the library's folder could not take.
    LibraryEvent,
    /// `P/C/machine/M/g05/S`: a G05 stream's status.
    G05Status,
    /// `P/C/plc/L/status`: a PLC link's status.
    PlcStatus,
    /// `P/C/plc/L/tag/NAME`: a tag's value, on change.
    TagValue,
    /// `P/C/plc/L/transfer/MSGNO`: a transfer the PLC sent.
    PlcTransfer,
    /// `P/C/plc/L/message`: a message the PLC sent (modes 4–5).
    PlcMessage,
    /// `P/C/reload`: what each reload did.
    Reload,
}

/// One row of what the gateway publishes.
pub(crate) struct Publication {
    pub(crate) what: Published,
    /// The key as a subscriber to every instance names it.
    pub(crate) key: fn(&CellKeys) -> String,
    /// The protobuf message it carries: what the docs' row must name (checked by the
    /// tests; the publishers' own types carry it in the code).
    #[cfg_attr(not(test), allow(dead_code))]
    pub(crate) message: &'static str,
    /// Block where a lost sample is a lost fact (an alarm, a job's end, a punched program);
    /// Drop where the next supersedes it (status, DI).
    pub(crate) congestion: CongestionControl,
    pub(crate) priority: Priority,
    /// The permissions whose rules let a client subscribe to it.
    pub(crate) readers: &'static [Permission],
}

use Permission::{G05Stream, JobCancel, JobSubmit, ProgramRead, StatusRead};

/// Every publication of the gateway.
pub(crate) const PUBLICATIONS: &[Publication] = &[
    Publication {
        what: Published::MachineStatus,
        key: |k| k.any_leaf(MachineLeaf::Status),
        message: "MachineStatus",
        congestion: CongestionControl::Drop,
        priority: Priority::Data,
        readers: &[StatusRead],
    },
    Publication {
        what: Published::Di,
        key: |k| k.any_leaf(MachineLeaf::Di),
        message: "DiImage",
        congestion: CongestionControl::Drop,
        priority: Priority::Data,
        readers: &[StatusRead],
    },
    Publication {
        what: Published::Alarm,
        key: |k| k.any_leaf(MachineLeaf::Alarm),
        message: "AlarmEvent",
        congestion: CongestionControl::Block,
        priority: Priority::Data,
        readers: &[StatusRead],
    },
    Publication {
        what: Published::Punch,
        key: |k| k.any_leaf(MachineLeaf::Punch),
        message: "PunchedProgram",
        congestion: CongestionControl::Block,
        priority: Priority::Data,
        readers: &[StatusRead],
    },
    Publication {
        what: Published::JobEvent,
        key: |k| k.any_job_events(),
        message: "JobEvent",
        congestion: CongestionControl::Block,
        priority: Priority::Data,
        readers: &[StatusRead, JobSubmit, JobCancel],
    },
    Publication {
        what: Published::DoOut,
        key: |k| k.do_out("*"),
        message: "DoCommand",
        congestion: CongestionControl::Block,
        priority: Priority::Data,
        readers: &[StatusRead],
    },
    Publication {
        what: Published::ProgramChanged,
        key: |k| k.program_changed("*"),
        message: "ProgramInfo",
        congestion: CongestionControl::Block,
        priority: Priority::Data,
        readers: &[ProgramRead],
    },
    Publication {
        what: Published::LibraryEvent,
        key: |k| k.program_events(),
        message: "LibraryEvent",
        congestion: CongestionControl::Block,
        priority: Priority::Data,
        readers: &[ProgramRead],
    },
    Publication {
        what: Published::G05Status,
        key: |k| k.any_g05(super::keys::G05Part::Status),
        message: "G05Status",
        // At least every 100 ms while a stream is open: the next supersedes a lost one (its
        // last one goes reliably). High priority: the producer paces its batches by it.
        congestion: CongestionControl::Drop,
        priority: Priority::InteractiveHigh,
        readers: &[StatusRead, G05Stream],
    },
    Publication {
        what: Published::PlcStatus,
        key: |k| k.any_plc_status(),
        message: "PlcStatus",
        congestion: CongestionControl::Drop,
        priority: Priority::Data,
        readers: &[StatusRead],
    },
    Publication {
        what: Published::TagValue,
        key: |k| k.any_plc_tag(),
        message: "TagValue",
        congestion: CongestionControl::Block,
        priority: Priority::Data,
        readers: &[StatusRead],
    },
    Publication {
        what: Published::PlcTransfer,
        key: |k| k.any_plc_transfer(),
        message: "PlcTransfer",
        congestion: CongestionControl::Block,
        priority: Priority::Data,
        readers: &[StatusRead],
    },
    Publication {
        what: Published::PlcMessage,
        key: |k| k.plc_message("*"),
        message: "PlcMessage",
        congestion: CongestionControl::Block,
        priority: Priority::Data,
        readers: &[StatusRead],
    },
    Publication {
        what: Published::Reload,
        key: |k| k.reloads(),
        message: "ReloadResult",
        congestion: CongestionControl::Block,
        priority: Priority::Data,
        readers: &[StatusRead],
    },
];

impl Published {
    /// Its row.
    pub(crate) fn row(self) -> &'static Publication {
        PUBLICATIONS
            .iter()
            .find(|p| p.what == self)
            // Every variant has a row: `every_publication_has_one_row` checks it.
            .unwrap_or(&PUBLICATIONS[0])
    }

    pub(crate) fn congestion(self) -> CongestionControl {
        self.row().congestion
    }

    pub(crate) fn priority(self) -> Priority {
        self.row().priority
    }
}

/// The publications a machine's own publisher declares once (`MachinePublisher`), on a
/// leaf of the machine's key.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum MachinePublication {
    Status,
    Di,
    Alarm,
    Punch,
}

impl MachinePublication {
    pub(crate) fn leaf(self) -> MachineLeaf {
        match self {
            MachinePublication::Status => MachineLeaf::Status,
            MachinePublication::Di => MachineLeaf::Di,
            MachinePublication::Alarm => MachineLeaf::Alarm,
            MachinePublication::Punch => MachineLeaf::Punch,
        }
    }

    pub(crate) fn published(self) -> Published {
        match self {
            MachinePublication::Status => Published::MachineStatus,
            MachinePublication::Di => Published::Di,
            MachinePublication::Alarm => Published::Alarm,
            MachinePublication::Punch => Published::Punch,
        }
    }
}

/// The keys of the publications `p` lets a client subscribe to.
pub(crate) fn read_by(keys: &CellKeys, p: Permission) -> Vec<String> {
    PUBLICATIONS
        .iter()
        .filter(|r| r.readers.contains(&p))
        .map(|r| (r.key)(keys))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_publication_has_one_row() {
        use Published::*;
        let all = [
            MachineStatus,
            Di,
            Alarm,
            Punch,
            JobEvent,
            DoOut,
            ProgramChanged,
            LibraryEvent,
            G05Status,
            PlcStatus,
            TagValue,
            PlcTransfer,
            PlcMessage,
            Reload,
        ];
        // The match makes a new variant fail to compile here until it is listed above.
        for w in all {
            match w {
                MachineStatus | Di | Alarm | Punch | JobEvent | DoOut | ProgramChanged
                | LibraryEvent | G05Status | PlcStatus | TagValue | PlcTransfer | PlcMessage
                | Reload => {}
            }
            assert_eq!(
                PUBLICATIONS.iter().filter(|r| r.what == w).count(),
                1,
                "{w:?}"
            );
        }
        assert_eq!(PUBLICATIONS.len(), all.len());
    }

    /// The keys of the first column of the key tables of a page of docs/ (`…/alarm` after
    /// a full key is that key's sibling).
    fn documented(page: &str) -> Vec<String> {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("docs")
            .join(page);
        let text = std::fs::read_to_string(path).unwrap();
        let mut out = Vec::new();
        for line in text.lines().filter(|l| l.starts_with("| `P/C/")) {
            let first = line.split(" | ").next().unwrap_or_default();
            let mut last = String::new();
            for token in first.split('`').skip(1).step_by(2) {
                let token = token.split('[').next().unwrap_or_default();
                let key = match token.strip_prefix("…/") {
                    Some(leaf) => match last.rsplit_once('/') {
                        Some((parent, _)) => format!("{parent}/{leaf}"),
                        None => continue,
                    },
                    None => token.to_string(),
                };
                last.clone_from(&key);
                out.push(key);
            }
        }
        out
    }

    /// A key of the tables as the docs write it: each wildcard chunk by the placeholder its
    /// place takes (machine `M`, job `ID`, stream `S`, program `NAME`, revision `REV`, PLC
    /// link `L`, station `S`, module `MODULE`, address `ADDR`, message `MSGNO`, tag `NAME`).
    fn as_documented(key: &str) -> String {
        let mut out: Vec<&str> = Vec::new();
        let chunks: Vec<&str> = key.split('/').collect();
        for (i, c) in chunks.iter().enumerate() {
            let before = if i > 0 { chunks[i - 1] } else { "" };
            let two_before = if i > 1 { chunks[i - 2] } else { "" };
            out.push(match (*c, before, two_before) {
                ("*", "machine" | "sim", _) => "M",
                ("*", "job", _) => "ID",
                ("*", "g05", _) => "S",
                ("*", "program", _) => "NAME",
                ("*", "rev", _) => "REV",
                ("*", "plc", _) => "L",
                ("*", "station" | "mem", _) => "S",
                ("*", _, "mem") => "MODULE",
                ("*", "transfer", _) => "MSGNO",
                ("*", "tag", _) => "NAME",
                ("*", _, _) if i > 3 && chunks[i - 3] == "mem" => "ADDR",
                (c, _, _) => c,
            });
        }
        out.join("/")
    }

    /// docs/bus.md (and, for the PLC's keys, docs/plc.md) names every key the route table
    /// serves and every publication, and names no key that is neither: the page and the
    /// tables cannot drift apart.
    #[test]
    fn the_docs_key_tables_are_the_route_table_and_the_publications() {
        let keys = CellKeys::new("P", "C").unwrap();
        let mut docs = documented("bus.md");
        docs.extend(documented("plc.md"));
        let mut ours: Vec<String> = Vec::new();
        // The rows a role may reach (the misdirected writes' rows, which only refuse, aside).
        fn reached<C>(routes: Vec<crate::bus::routes::Route<C>>) -> Vec<String> {
            routes
                .into_iter()
                .flat_map(|r| r.rows)
                .filter(|row| row.permission.is_some())
                .map(|row| row.key)
                .collect()
        }
        ours.extend(reached(crate::bus::routes::cell(&keys)));
        ours.extend(reached(vec![crate::bus::routes::g05(&keys)]));
        ours.extend(reached(vec![crate::bus::routes::sim(&keys)]));
        ours.extend(reached(crate::bus::routes::plc(&keys)));
        ours.extend(PUBLICATIONS.iter().map(|p| (p.key)(&keys)));
        // Served apart from the route table: the admin document and the reload.
        ours.push(keys.admin());
        ours.push(keys.reload());
        // A documented key (placeholders as plain chunks) that a key of ours takes in.
        let includes = |ours: &str, doc: &str| {
            zenoh::key_expr::keyexpr::new(ours)
                .is_ok_and(|o| zenoh::key_expr::keyexpr::new(doc).is_ok_and(|d| o.includes(d)))
        };
        let mut missing = Vec::new();
        for key in &ours {
            let doc = as_documented(key);
            // A wildcard get is documented as itself (`P/C/program/*`), by its placeholders,
            // or by the keys it serves (`P/C/sim/*/*` as `P/C/sim/M/state`, ...).
            let found = docs
                .iter()
                .any(|d| *d == doc || d == key || includes(key, d));
            if !found {
                missing.push(format!("{key} (as {doc})"));
            }
        }
        assert!(
            missing.is_empty(),
            "not in docs/bus.md or docs/plc.md: {missing:#?}"
        );
        // Every key the page names is served, published or a liveliness token.
        let tokens = [
            keys.gateway(),
            keys.machine("M"),
            keys.g05("M", "S", super::super::keys::G05Part::Producer),
            keys.plc_station("L", 0).replace("/0", "/S"),
        ];
        let stray: Vec<&String> = docs
            .iter()
            .filter(|d| {
                !tokens.contains(d)
                    && !d.ends_with("/...")
                    && !ours
                        .iter()
                        .any(|k| as_documented(k) == **d || k == *d || includes(k, d))
            })
            .collect();
        assert!(
            stray.is_empty(),
            "named by the docs, served by nothing: {stray:#?}"
        );
        // Each publication's row names its message.
        let pages: String = ["bus.md", "plc.md"]
            .iter()
            .map(|p| {
                std::fs::read_to_string(
                    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                        .join("docs")
                        .join(p),
                )
                .unwrap()
            })
            .collect();
        for p in PUBLICATIONS {
            let row = format!("| `{}`", as_documented(&(p.key)(&keys)));
            let line = pages
                .lines()
                .find(|l| l.starts_with(&row))
                .unwrap_or_else(|| panic!("no row {row}"));
            assert!(line.contains(p.message), "{row} does not say {}", p.message);
        }
    }
}
