//! The cell's key expressions, built and parsed in one place.
//!
//! With `P` = `bus.prefix`, `C` = the cell, `M` = a machine, `ID` = a job id:
//!
//! | key | |
//! |---|---|
//! | `P/C/gateway` | liveliness token while the gateway runs |
//! | `P/C/@admin` | the gateway's admin document (a verbatim chunk: `P/C/**` does not match it) |
//! | `P/C/@admin/reload` | `ReloadRequest` → `ReloadResult`: read the cell file again, apply what changed |
//! | `P/C/reload` | every reload's `ReloadResult`, taken or refused, however it was asked for |
//! | `P/C/machine/M` | liveliness token while the machine's link is up |
//! | `P/C/machine/M/status` | `MachineStatus` |
//! | `P/C/machine/M/job` | the queue (`JobQueue`) |
//! | `P/C/machine/M/submit` | job requests (`JobRequest` → `JobAccepted`) |
//! | `P/C/machine/M/job/ID` | `JobEvent`s of one job; a delete cancels it |
//! | `P/C/machine/M/job/ID/cancel` | a get cancels the job and answers its end |
//! | `P/C/machine/M/di` | `DiImage` |
//! | `P/C/machine/M/do` | `DoCommand` |
//! | `P/C/machine/M/alarm` | `AlarmEvent` |
//! | `P/C/machine/M/punch` | `PunchedProgram`s the CNC punched out (Protocol B) |
//! | `P/C/machine/M/g05` | G05 streams are opened here (`G05Open` → `G05Opened`) |
//! | `P/C/machine/M/g05/S` | a stream's `G05Status`; a delete cancels it |
//! | `P/C/machine/M/g05/S/blocks` | the stream's `G05Batch`es |
//! | `P/C/machine/M/g05/S/producer` | the producer's liveliness token |
//! | `P/C/program/NAME` | a program of the library, read |
//! | `P/C/program/NAME/write` | stores (`ProgramWrite`, a put of its bytes) or removes (a delete) it |
//! | `P/C/program/NAME/revisions` | its kept revisions (`ProgramRevisions`), read |
//! | `P/C/program/NAME/rev/REV` | one revision's bytes (REV: a number or a SHA-256), read |
//! | `P/C/program/NAME/diff` | two revisions compared (`ProgramDiff`), read |
//! | `P/C/program/NAME/release` | `ProgramRelease` changes a revision's state |
//! | `P/C/history` | the cell's history (`HistoryPage`), read |
//! | `P/C/audit` | the audit trail (`HistoryPage`), read |
//! | `P/C/audit/note` | an `AuditRecord` a console adds: a request it refused itself |
//! | `P/C/utilisation` | time shares per machine (`Utilisation`), read |
//! | `P/C/plc/L/status` | `PlcStatus` of a PLC link: its stations, counters, tags |
//! | `P/C/plc/L/station/S` | liveliness token while station S answers |
//! | `P/C/plc/L/mem/S/MODULE/ADDR` | words of a module at station S (`PlcWords`), read |
//! | `P/C/plc/L/mem/S/MODULE/ADDR/write` | `PlcWrite` writes them |
//! | `P/C/plc/L/mem/S/MODULE/write` | `PlcWrite { clear }` clears the module |
//! | `P/C/plc/L/transfer/MSGNO` | `PlcTransfer`s from the PLC |
//! | `P/C/plc/L/transfer/MSGNO/send` | a `PlcTransfer` sent to it |
//! | `P/C/plc/L/message` | `PlcMessage`s the PLC sends (modes 4–5) |
//! | `P/C/plc/L/message/send` | a `PlcMessage` sent to the PLC (modes 4–5) |
//! | `P/C/plc/L/tag/NAME` | a tag's `TagValue` on change, read |
//! | `P/C/plc/L/tag/NAME/set` | `TagWrite` writes it |
//! | `P/C/sim/M/state` | a simulated machine's `SimState`, read |
//! | `P/C/sim/M/<control>` | `di`, `alarm`, `reset`, `read`, `hold`, `autostart`, `punch`: what an operator does at a simulated CNC |
//!
//! Every write has a key of its own (zenoh's access control sees keys and operations, never
//! payloads): a role that may read a key may never write through it.
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

/// The leaf keys under `P/C/machine/M/`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MachineLeaf {
    /// `status`: the machine's `MachineStatus`.
    Status,
    /// `job`: the queue (`JobQueue`), read only.
    Job,
    /// `submit`: job requests (`JobRequest` → `JobAccepted`), the write of `job`.
    Submit,
    /// `di`: the `DiImage`.
    Di,
    /// `do`: `DoCommand`s.
    Do,
    /// `alarm`: `AlarmEvent`s.
    Alarm,
    /// `punch`: `PunchedProgram`s the CNC punched out (Protocol B).
    Punch,
    /// `g05`: G05 streams are opened here (`G05Open` → `G05Opened`).
    G05,
}

impl MachineLeaf {
    /// Every leaf.
    pub const ALL: [MachineLeaf; 8] = [
        MachineLeaf::Status,
        MachineLeaf::Job,
        MachineLeaf::Submit,
        MachineLeaf::Di,
        MachineLeaf::Do,
        MachineLeaf::Alarm,
        MachineLeaf::Punch,
        MachineLeaf::G05,
    ];

    /// The leaf's key chunk (`status`, `job`, ...).
    pub fn chunk(self) -> &'static str {
        match self {
            MachineLeaf::Status => "status",
            MachineLeaf::Job => "job",
            MachineLeaf::Submit => "submit",
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

/// The keys of a simulated machine, `P/C/sim/M/<leaf>`: its state, and one key for each
/// thing an operator does at its CNC (every control a write of its own).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SimLeaf {
    /// `state`: the simulated board's and CNC's `SimState`, read only.
    State,
    /// `di`: sets the DI image the board reports (`SimDi`).
    Di,
    /// `alarm`: raises a CNC alarm.
    Alarm,
    /// `reset`: resets the CNC (its alarm cleared, its buffer emptied).
    Reset,
    /// `read`: cycle start: the CNC reads from the buffer.
    Read,
    /// `hold`: feed hold: the CNC stops reading.
    Hold,
    /// `autostart`: whether the operator starts reads and resets alarms by himself
    /// (`SimAutostart`).
    Autostart,
    /// `punch`: the CNC punches a program out to the host (`SimPunch`; Protocol B family).
    Punch,
}

impl SimLeaf {
    /// Every leaf.
    pub const ALL: [SimLeaf; 8] = [
        SimLeaf::State,
        SimLeaf::Di,
        SimLeaf::Alarm,
        SimLeaf::Reset,
        SimLeaf::Read,
        SimLeaf::Hold,
        SimLeaf::Autostart,
        SimLeaf::Punch,
    ];

    /// The leaf's key chunk (`state`, `di`, ...).
    pub fn chunk(self) -> &'static str {
        match self {
            SimLeaf::State => "state",
            SimLeaf::Di => "di",
            SimLeaf::Alarm => "alarm",
            SimLeaf::Reset => "reset",
            SimLeaf::Read => "read",
            SimLeaf::Hold => "hold",
            SimLeaf::Autostart => "autostart",
            SimLeaf::Punch => "punch",
        }
    }

    fn from_chunk(chunk: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|l| l.chunk() == chunk)
    }
}

/// The areas of a PLC link, `P/C/plc/L/<area>/...`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PlcArea {
    /// `mem`: words of a module at a station (`…/mem/S/MODULE/ADDR`).
    Mem,
    /// `transfer`: message transfers (`…/transfer/MSGNO`).
    Transfer,
    /// `message`: non-procedure messages of modes 4–5 (`…/message`, `…/message/send`).
    Message,
    /// `tag`: tag values (`…/tag/NAME`).
    Tag,
}

impl PlcArea {
    /// The area's key chunk (`mem`, `transfer`, `message`, `tag`).
    pub fn chunk(self) -> &'static str {
        match self {
            PlcArea::Mem => "mem",
            PlcArea::Transfer => "transfer",
            PlcArea::Message => "message",
            PlcArea::Tag => "tag",
        }
    }
}

/// A key under `P/C/plc/`, read back; chunks as they appear (numbers still text).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlcKey<'a> {
    /// `P/C/plc/L/status`: the link's `PlcStatus`.
    Status {
        /// The PLC link (`L`).
        plc: &'a str,
    },
    /// `P/C/plc/L/station/S`: a station's liveliness token.
    Station {
        /// The PLC link (`L`).
        plc: &'a str,
        /// The station number (`S`).
        station: &'a str,
    },
    /// `P/C/plc/L/mem/S/MODULE/ADDR`, or `P/C/plc/L/mem/S/MODULE` for the whole module.
    Mem {
        /// The PLC link (`L`).
        plc: &'a str,
        /// The station number (`S`).
        station: &'a str,
        /// The module's name (`MODULE`).
        module: &'a str,
        /// The relative address (`ADDR`); `None` for the module's own key.
        address: Option<&'a str>,
        /// `…/write`: the key that writes (or, on the module's own key, clears); the key
        /// without it only reads.
        write: bool,
    },
    /// `P/C/plc/L/transfer/MSGNO`: transfers of one message number.
    Transfer {
        /// The PLC link (`L`).
        plc: &'a str,
        /// The message number (`MSGNO`).
        message: &'a str,
        /// `…/send`: the key a transfer to the PLC goes to; the key without it carries the
        /// PLC's transfers.
        send: bool,
    },
    /// `P/C/plc/L/message`: non-procedure messages (modes 4–5).
    Message {
        /// The PLC link (`L`).
        plc: &'a str,
        /// `…/send`: the key a message to the PLC goes to; the key without it carries the
        /// PLC's messages.
        send: bool,
    },
    /// `P/C/plc/L/tag/NAME`: a tag's value.
    Tag {
        /// The PLC link (`L`).
        plc: &'a str,
        /// The tag's name (`NAME`).
        name: &'a str,
        /// `…/set`: the key that writes the tag; the key without it only reads.
        set: bool,
    },
}

impl PlcKey<'_> {
    /// The PLC link the key is under (`L`).
    pub fn plc(&self) -> &str {
        match self {
            PlcKey::Status { plc }
            | PlcKey::Station { plc, .. }
            | PlcKey::Mem { plc, .. }
            | PlcKey::Transfer { plc, .. }
            | PlcKey::Message { plc, .. }
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
    /// `P/C/@admin/reload`: a reload asked for.
    Reload,
    /// `P/C/reload`: what each reload did.
    Reloaded,
    /// `P/C/machine/M`
    Machine {
        /// The machine (`M`).
        machine: &'a str,
    },
    /// `P/C/machine/M/<leaf>`
    Leaf {
        /// The machine (`M`).
        machine: &'a str,
        /// Which leaf.
        leaf: MachineLeaf,
    },
    /// `P/C/machine/M/job/ID`
    JobEvents {
        /// The machine (`M`).
        machine: &'a str,
        /// The job id (`ID`).
        job: &'a str,
    },
    /// `P/C/machine/M/job/ID/cancel`: cancels the job, answering its end.
    JobCancel {
        /// The machine (`M`).
        machine: &'a str,
        /// The job id (`ID`).
        job: &'a str,
    },
    /// `P/C/machine/M/g05/S`, `…/S/blocks`, `…/S/producer`
    G05 {
        /// The machine (`M`).
        machine: &'a str,
        /// The stream (`S`).
        stream: &'a str,
        /// Which key of the stream.
        part: G05Part,
    },
    /// `P/C/program/NAME`: reads the program.
    Program {
        /// The program's name in the library (`NAME`).
        name: &'a str,
    },
    /// `P/C/program/NAME/write`: stores or removes the program.
    ProgramWrite {
        /// The program's name in the library (`NAME`).
        name: &'a str,
    },
    /// `P/C/program/NAME/revisions`: its kept revisions.
    ProgramRevisions {
        /// The program's name in the library (`NAME`).
        name: &'a str,
    },
    /// `P/C/program/NAME/rev/REV`: one revision's bytes.
    ProgramRevision {
        /// The program's name in the library (`NAME`).
        name: &'a str,
        /// The revision: a number or a SHA-256 (`REV`).
        revision: &'a str,
    },
    /// `P/C/program/NAME/diff`: two revisions compared.
    ProgramDiff {
        /// The program's name in the library (`NAME`).
        name: &'a str,
    },
    /// `P/C/program/NAME/release`: a revision's state changed.
    ProgramRelease {
        /// The program's name in the library (`NAME`).
        name: &'a str,
    },
    /// `P/C/history`
    History,
    /// `P/C/audit`
    Audit,
    /// `P/C/audit/note`
    AuditNote,
    /// `P/C/utilisation`
    Utilisation,
    /// `P/C/sim/M/<leaf>`: a simulated machine's state or one of its controls.
    Sim {
        /// The machine (`M`).
        machine: &'a str,
        /// Which key.
        leaf: SimLeaf,
    },
}

/// A prefix or cell that cannot start a key.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("key prefix {root:?} (bus.prefix / cell) is not a valid key without wildcards: {reason}")]
pub struct KeyError {
    /// The refused root, `bus.prefix/cell`.
    pub root: String,
    /// Why it is not a valid key.
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
///
/// Such a chunk is non-empty and holds none of `/`, `*`, `$`, `?` and `#`: zenoh's wildcards
/// (`*`, `**`, `$*`) and the two characters a key expression may not contain, so it is a
/// valid key expression of its own and matches only itself (zenoh's own parser agrees: the
/// gateway's `bus::keys` tests check it).
pub fn is_plain_chunk(chunk: &str) -> bool {
    !chunk.is_empty() && !chunk.contains(['/', '*', '$', '?', '#'])
}

impl CellKeys {
    /// The keys of `cell` under `prefix`; a [`KeyError`] unless `cell` is one plain chunk and
    /// `prefix` is made of plain chunks ([`is_plain_chunk`]).
    pub fn new(prefix: &str, cell: &str) -> Result<Self, KeyError> {
        let root = format!("{prefix}/{cell}");
        let reason = if !is_plain_chunk(cell) {
            Some("the cell is not one chunk without wildcards")
        } else if !prefix.split('/').all(is_plain_chunk) {
            Some("the prefix has an empty chunk, a wildcard or one of '$', '?', '#'")
        } else {
            None
        };
        match reason {
            None => Ok(CellKeys { root }),
            Some(reason) => Err(KeyError {
                root,
                reason: reason.to_string(),
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

    /// `P/C/@admin/reload`: where a reload of the cell file is asked for (a write key of
    /// its own, under the verbatim admin chunk, so that no wildcard of the cell's data
    /// reaches it).
    pub fn reload(&self) -> String {
        format!("{}/{ADMIN_CHUNK}/reload", self.root)
    }

    /// `P/C/reload`: what each reload did (`ReloadResult`), published.
    pub fn reloads(&self) -> String {
        format!("{}/reload", self.root)
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

    /// `P/C/program/NAME/write`: where the program is stored or removed.
    pub fn program_write(&self, name: &str) -> String {
        format!("{}/program/{name}/write", self.root)
    }

    /// `P/C/program/*/write`
    pub fn any_program_write(&self) -> String {
        self.program_write("*")
    }

    /// `P/C/program/NAME/revisions`: the program's kept revisions.
    pub fn program_revisions(&self, name: &str) -> String {
        format!("{}/program/{name}/revisions", self.root)
    }

    /// `P/C/program/NAME/rev/REV`: one revision's bytes.
    pub fn program_revision(&self, name: &str, revision: &str) -> String {
        format!("{}/program/{name}/rev/{revision}", self.root)
    }

    /// `P/C/program/NAME/diff`: two revisions compared.
    pub fn program_diff(&self, name: &str) -> String {
        format!("{}/program/{name}/diff", self.root)
    }

    /// `P/C/program/NAME/release`: where a revision's state is changed.
    pub fn program_release(&self, name: &str) -> String {
        format!("{}/program/{name}/release", self.root)
    }

    /// `P/C/program/NAME/changed`: the gateway publishes the program's `ProgramInfo` once a
    /// store, adoption or removal of it is on disk, whoever asked (a get or a put on its
    /// write key, the console); the requester's `RequestOrigin` is the sample's attachment.
    pub fn program_changed(&self, name: &str) -> String {
        format!("{}/program/{name}/changed", self.root)
    }

    /// `P/C/machine/M/do/out`: the gateway publishes a `DoCommand` once its SDO went out on
    /// a get (a put on `…/do` is itself the event); the requester's `RequestOrigin` is the
    /// sample's attachment.
    pub fn do_out(&self, machine: &str) -> String {
        format!("{}/out", self.leaf(machine, MachineLeaf::Do))
    }

    /// Which of the two event keys above `key` is: `(true, NAME)` for a program's, `(false,
    /// M)` for a machine's DO output.
    pub fn parse_event<'k>(&self, key: &'k str) -> Option<(bool, &'k str)> {
        let rest = key.strip_prefix(self.root.as_str())?.strip_prefix('/')?;
        match rest.split('/').collect::<Vec<_>>().as_slice() {
            ["program", name, "changed"] => Some((true, name)),
            ["machine", m, "do", "out"] => Some((false, m)),
            _ => None,
        }
    }

    /// `P/C/program/@events`: what happens to the library (`LibraryEvent`). `@` makes the
    /// chunk verbatim: no program name is spelt so, and no `*` or `**` takes it.
    pub fn program_events(&self) -> String {
        format!("{}/program/@events", self.root)
    }

    /// Every key that reads the library: `P/C/program/*`, `…/*/revisions`, `…/*/rev/*`,
    /// `…/*/diff`.
    pub fn any_program_read(&self) -> Vec<String> {
        vec![
            self.any_program(),
            self.program_revisions("*"),
            self.program_revision("*", "*"),
            self.program_diff("*"),
        ]
    }

    /// `P/C/history`: the cell's history.
    pub fn history(&self) -> String {
        format!("{}/history", self.root)
    }

    /// `P/C/audit`: the audit trail.
    pub fn audit(&self) -> String {
        format!("{}/audit", self.root)
    }

    /// `P/C/audit/note`: where a console adds what it refused itself to the audit trail.
    pub fn audit_note(&self) -> String {
        format!("{}/audit/note", self.root)
    }

    /// `P/C/utilisation`: time shares per machine.
    pub fn utilisation(&self) -> String {
        format!("{}/utilisation", self.root)
    }

    /// `P/C/machine/*/<leaf>`: every machine's leaf.
    pub fn any_leaf(&self, leaf: MachineLeaf) -> String {
        self.leaf("*", leaf)
    }

    /// `P/C/machine/*/job/*`
    pub fn any_job_events(&self) -> String {
        self.job_events("*", "*")
    }

    /// `P/C/machine/M/job/ID/cancel`: a get cancels the job and answers how it ended.
    pub fn job_cancel(&self, machine: &str, job: &str) -> String {
        format!("{}/cancel", self.job_events(machine, job))
    }

    /// `P/C/machine/*/job/*/cancel`
    pub fn any_job_cancel(&self) -> String {
        self.job_cancel("*", "*")
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

    /// `P/C/sim/M/<leaf>`
    pub fn sim(&self, machine: &str, leaf: SimLeaf) -> String {
        format!("{}/sim/{machine}/{}", self.root, leaf.chunk())
    }

    /// `P/C/sim/*/*`: every simulated machine's keys.
    pub fn any_sim(&self) -> String {
        format!("{}/sim/*/*", self.root)
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

    /// `P/C/plc/L/mem/S/MODULE[/ADDR]/write`: writes the words (or clears the module).
    pub fn plc_mem_write(
        &self,
        link: &str,
        station: u8,
        module: &str,
        address: Option<u16>,
    ) -> String {
        format!("{}/write", self.plc_mem(link, station, module, address))
    }

    /// `P/C/plc/*/mem/**/write`: every memory write key.
    pub fn any_plc_mem_write(&self) -> String {
        format!("{}/**/write", self.plc_area("*", PlcArea::Mem))
    }

    /// `P/C/plc/L/transfer/MSGNO`: the PLC's transfers of one message number.
    pub fn plc_transfer(&self, link: &str, message: u8) -> String {
        format!("{}/{message}", self.plc_area(link, PlcArea::Transfer))
    }

    /// `P/C/plc/*/transfer/*`: every PLC's transfers, as published.
    pub fn any_plc_transfer(&self) -> String {
        format!("{}/*", self.plc_area("*", PlcArea::Transfer))
    }

    /// `P/C/plc/L/transfer/MSGNO/send`: where a transfer to the PLC goes.
    pub fn plc_transfer_send(&self, link: &str, message: u8) -> String {
        format!("{}/send", self.plc_transfer(link, message))
    }

    /// `P/C/plc/*/transfer/*/send`
    pub fn any_plc_transfer_send(&self) -> String {
        format!("{}/*/send", self.plc_area("*", PlcArea::Transfer))
    }

    /// `P/C/plc/L/message`: the PLC's non-procedure messages (modes 4–5).
    pub fn plc_message(&self, link: &str) -> String {
        self.plc_area(link, PlcArea::Message)
    }

    /// `P/C/plc/L/message/send`: where a message to the PLC goes (modes 4–5).
    pub fn plc_message_send(&self, link: &str) -> String {
        format!("{}/send", self.plc_message(link))
    }

    /// `P/C/plc/*/message/send`
    pub fn any_plc_message_send(&self) -> String {
        self.plc_message_send("*")
    }

    /// `P/C/plc/L/tag/NAME`: the tag's value.
    pub fn plc_tag(&self, link: &str, name: &str) -> String {
        format!("{}/{name}", self.plc_area(link, PlcArea::Tag))
    }

    /// `P/C/plc/L/tag/NAME/set`: where the tag is written.
    pub fn plc_tag_set(&self, link: &str, name: &str) -> String {
        format!("{}/set", self.plc_tag(link, name))
    }

    /// `P/C/plc/*/tag/*`: every tag's value.
    pub fn any_plc_tag(&self) -> String {
        self.plc_tag("*", "*")
    }

    /// `P/C/plc/*/tag/*/set`
    pub fn any_plc_tag_set(&self) -> String {
        self.plc_tag_set("*", "*")
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
            [plc, "mem", s, m, rest @ ..] => {
                let (address, write) = match rest {
                    [] => (None, false),
                    ["write"] => (None, true),
                    [a] => (Some(*a), false),
                    [a, "write"] => (Some(*a), true),
                    _ => return None,
                };
                Some(PlcKey::Mem {
                    plc,
                    station: s,
                    module: m,
                    address,
                    write,
                })
            }
            [plc, "transfer", n] => Some(PlcKey::Transfer {
                plc,
                message: n,
                send: false,
            }),
            [plc, "transfer", n, "send"] => Some(PlcKey::Transfer {
                plc,
                message: n,
                send: true,
            }),
            [plc, "message"] => Some(PlcKey::Message { plc, send: false }),
            [plc, "message", "send"] => Some(PlcKey::Message { plc, send: true }),
            [plc, "tag", n] => Some(PlcKey::Tag {
                plc,
                name: n,
                set: false,
            }),
            [plc, "tag", n, "set"] => Some(PlcKey::Tag {
                plc,
                name: n,
                set: true,
            }),
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
            [ADMIN_CHUNK, "reload"] => Some(CellKey::Reload),
            ["reload"] => Some(CellKey::Reloaded),
            ["machine", m] => Some(CellKey::Machine { machine: m }),
            ["machine", m, leaf] => Some(CellKey::Leaf {
                machine: m,
                leaf: MachineLeaf::from_chunk(leaf)?,
            }),
            ["machine", m, "job", id] => Some(CellKey::JobEvents {
                machine: m,
                job: id,
            }),
            ["machine", m, "job", id, "cancel"] => Some(CellKey::JobCancel {
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
            ["program", name, "write"] => Some(CellKey::ProgramWrite { name }),
            ["program", name, "revisions"] => Some(CellKey::ProgramRevisions { name }),
            ["program", name, "rev", revision] => Some(CellKey::ProgramRevision { name, revision }),
            ["program", name, "diff"] => Some(CellKey::ProgramDiff { name }),
            ["program", name, "release"] => Some(CellKey::ProgramRelease { name }),
            ["history"] => Some(CellKey::History),
            ["audit"] => Some(CellKey::Audit),
            ["audit", "note"] => Some(CellKey::AuditNote),
            ["utilisation"] => Some(CellKey::Utilisation),
            ["sim", m, leaf] => Some(CellKey::Sim {
                machine: m,
                leaf: SimLeaf::from_chunk(leaf)?,
            }),
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

#[cfg(test)]
mod tests;
