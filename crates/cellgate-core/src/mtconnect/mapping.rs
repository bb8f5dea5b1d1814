//! From the bus contract's messages to data item values: what each one can honestly say of
//! a CNC fed through its remote buffer, or of a PLC. docs/mtconnect.md justifies each row
//! from the manuals.
//!
//! Each device keeps a view of what it was told; after every message the view gives the
//! value every data item should show ([`Wanted`]), and the agent records only what changed.

use std::sync::Arc;

use super::buffer::{Cond, Level, Value};
use super::model::Role;
use crate::history;
use crate::pb;

/// What a data item should show now.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Wanted {
    /// An event's value, or UNAVAILABLE.
    Value(Value),
    /// A condition: these active faults and warnings (none: Normal); `None`: UNAVAILABLE.
    Conditions(Option<Vec<Cond>>),
}

/// cellgate's own native codes, for what the CNC or the link reports without a manual
/// number (docs/mtconnect.md lists them): the bus contract's, one list.
pub use crate::codes::alarm as codes;

fn text(s: impl Into<Arc<str>>) -> Value {
    Value::Text(s.into())
}

fn fault(code: &str, what: &str) -> Cond {
    Cond {
        level: Level::Fault,
        native_code: code.into(),
        text: what.into(),
    }
}

/// How the last job on a machine ended, while nothing newer started.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum JobEnd {
    /// The whole program through EOR is on the remote buffer.
    Completed,
    /// It failed or was cancelled.
    Interrupted,
}

/// What the agent was told of one machine.
#[derive(Debug, Clone, Default)]
pub struct MachineView {
    /// Whether the cell's gateway is there (its liveliness token).
    pub gateway_up: bool,
    status: Option<pb::MachineStatus>,
    program: Option<String>,
    /// The last block the remote buffer took whole, of the job running or the last one.
    block: Option<String>,
    job: Option<String>,
    job_end: Option<(String, JobEnd)>,
    part_count: Option<i64>,
    g05_taken: Option<u64>,
    /// Whether the machine's G05 stream is open (priming, streaming, ending).
    g05_open: bool,
}

impl MachineView {
    /// Takes a status.
    pub fn status(&mut self, s: pb::MachineStatus) {
        // A reset ends the program (§6.4, RST §4.4.1): how the last job ended is history.
        if history::activity(&s) == pb::MachineActivity::Reset {
            self.job_end = None;
        }
        self.status = Some(s);
    }

    /// Takes a job event.
    pub fn job(&mut self, e: &pb::JobEvent) {
        use pb::job_event::Kind;
        let name = e.origin.as_ref().map(|o| {
            o.program
                .as_ref()
                .map(|p| p.library.clone())
                .filter(|l| !l.is_empty())
                .unwrap_or_else(|| o.name.clone())
        });
        match &e.kind {
            Some(Kind::Started(_)) => {
                self.job = Some(e.job_id.clone());
                self.job_end = None;
                self.block = None;
                if let Some(n) = name.filter(|n| !n.is_empty()) {
                    self.program = Some(n);
                }
            }
            Some(Kind::Progress(p)) => {
                if self.job.is_none() {
                    self.job = Some(e.job_id.clone());
                }
                if !p.block.is_empty() && self.job.as_deref() == Some(e.job_id.as_str()) {
                    self.block = Some(p.block.clone());
                }
            }
            Some(k @ (Kind::Completed(_) | Kind::Failed(_) | Kind::Cancelled(_))) => {
                // A waiting job cancelled says nothing of the one running.
                if self.job.as_deref().is_some_and(|j| j != e.job_id) {
                    return;
                }
                let end = if matches!(k, Kind::Completed(_)) {
                    JobEnd::Completed
                } else {
                    JobEnd::Interrupted
                };
                // A job that had started counts though the agent did not see it start (one
                // failed by a restart of its gateway, read when the agent starts); one that
                // never started (cancelled while waiting) says nothing of the machine.
                let started = e.origin.as_ref().is_some_and(|o| o.started_unix_ms > 0);
                if self.job.is_some() || end == JobEnd::Completed || started {
                    self.job_end = Some((e.job_id.clone(), end));
                }
                self.job = None;
                if let Some(n) = name.filter(|n| !n.is_empty())
                    && self.program.is_none()
                {
                    self.program = Some(n);
                }
            }
            _ => {}
        }
    }

    /// Takes the machine's queue, read when the agent starts: the running job's name.
    pub fn queue(&mut self, q: &pb::JobQueue) {
        if let Some(a) = &q.active {
            self.job = Some(a.job_id.clone());
            if !a.name.is_empty() {
                self.program = Some(a.name.clone());
            }
        }
    }

    /// Takes the value of the PLC tag that counts the machine's parts.
    pub fn count_parts(&mut self, t: &pb::TagValue) {
        self.part_count = match (t.quality(), t.value) {
            (pb::TagQuality::Good, Some(v)) => Some(v.round() as i64),
            _ => None,
        };
    }

    /// Takes a G05 stream's status.
    pub fn g05(&mut self, g: &pb::G05Status) {
        self.g05_taken = Some(g.on_line.saturating_sub(g.cnc_buffer));
        self.g05_open = matches!(
            g.state(),
            pb::G05State::Priming | pb::G05State::Streaming | pb::G05State::Ending
        );
    }

    pub(crate) fn up(&self) -> Option<&pb::MachineStatus> {
        let s = self.status.as_ref()?;
        let down = matches!(
            s.link_state(),
            pb::LinkState::Unspecified | pb::LinkState::Down | pb::LinkState::Connecting
        );
        (self.gateway_up && !down).then_some(s)
    }

    /// The program of the job running or of the last one (its library name, else the
    /// inline job's name).
    pub(crate) fn program(&self) -> Option<&str> {
        self.program.as_deref()
    }

    /// Whether a job is being sent.
    pub(crate) fn job_running(&self) -> bool {
        self.job.is_some()
    }

    /// How the last job ended while nothing newer started: `Some(true)` completed,
    /// `Some(false)` failed or cancelled.
    pub(crate) fn job_completed(&self) -> Option<bool> {
        self.job_end.as_ref().map(|(_, e)| *e == JobEnd::Completed)
    }

    /// The machine's part count, from its counter tag.
    pub(crate) fn part_count(&self) -> Option<i64> {
        self.part_count
    }

    /// EXECUTION (Part 2 "EXECUTION"), as far as a host that feeds the program can know it.
    fn execution(&self) -> Value {
        let Some(s) = self.up() else {
            return Value::Unavailable;
        };
        let buffered = s
            .sat
            .as_ref()
            .and_then(|sat| sat.bytes_buffered)
            .unwrap_or(0);
        let v = match history::activity(s) {
            pb::MachineActivity::Alarm => "INTERRUPTED",
            // The CNC takes the program's blocks from the remote buffer as it runs them (DNC
            // operation, §1): it runs the program.
            pb::MachineActivity::Reading => "ACTIVE",
            // Blocks still in the remote buffer (SAT bytes 5–8, §4.4.2): the CNC reads on.
            pb::MachineActivity::Idle if buffered > 0 && self.job_end.is_some() => "ACTIVE",
            // A reset ends the program (§6.4); the CNC waits for the next one.
            pb::MachineActivity::Reset => "READY",
            pb::MachineActivity::Idle => match self.job_end {
                // The CNC read the program through its EOR (§8.2).
                Some((_, JobEnd::Completed)) => "PROGRAM_COMPLETED",
                Some((_, JobEnd::Interrupted)) => "INTERRUPTED",
                None => "READY",
            },
            // Punching out (§6.1) is no program run.
            pb::MachineActivity::Punching => "READY",
            pb::MachineActivity::LinkDown | pb::MachineActivity::Unspecified => {
                return Value::Unavailable;
            }
        };
        text(v)
    }

    /// The SYSTEM condition: the CNC's alarms (§11), by number where the link gives one.
    pub(crate) fn cnc_alarm(&self) -> Option<Vec<Cond>> {
        let s = self.up()?;
        let last = s.last_alarm.as_ref();
        if s.link_state() == pb::LinkState::Alarm
            && let Some(a) = last.filter(|a| a.kind() == pb::AlarmKind::CncAlarm)
        {
            // The gateway's own code where it gives one (a gateway of this version always
            // does); before, the code is told from the number and the protocol.
            let code = if !a.code.is_empty() {
                a.code.as_str()
            } else if !a.alarm_number.is_empty() {
                a.alarm_number.as_str()
            } else if matches!(s.protocol(), pb::Protocol::B | pb::Protocol::ExpansionB) {
                codes::NAK
            } else {
                codes::ALM
            };
            return Some(vec![fault(code, &a.message)]);
        }
        if s.link_state() == pb::LinkState::Idle
            && let Some(sat) = &s.sat
            && sat.buffer_status() == pb::BufferStatus::Alarm
        {
            let (code, what) = match sat.alarm_cause() {
                pb::AlarmCause::NcAlarm => (codes::SAT_NC, "NC alarm (SAT byte 3 = 0, §4.4.2)"),
                pb::AlarmCause::ChecksumRetryOver => (
                    "SR0945",
                    "checksum error, retry over (SAT byte 3 = 1, §4.4.2)",
                ),
                pb::AlarmCause::OverrunRetryOver => (
                    "SR0945",
                    "overrun error, retry over (SAT byte 3 = A, §4.4.2)",
                ),
                pb::AlarmCause::CommandError => (
                    "SR0947",
                    "unexpected response received (SAT byte 3 = 6, §4.4.2)",
                ),
                pb::AlarmCause::Unknown | pb::AlarmCause::Other => {
                    (codes::SAT_OTHER, "remote buffer in alarm status (§4.4.2)")
                }
            };
            return Some(vec![fault(code, what)]);
        }
        Some(Vec::new())
    }

    /// The COMMUNICATIONS condition: the link's own faults.
    pub(crate) fn link_fault(&self) -> Option<Vec<Cond>> {
        if !self.gateway_up {
            return None;
        }
        let s = self.status.as_ref()?;
        match s.link_state() {
            pb::LinkState::Down => Some(vec![fault(
                codes::DOWN,
                "the link's transport is not open; the gateway retries",
            )]),
            pb::LinkState::Alarm => {
                let a = s
                    .last_alarm
                    .as_ref()
                    .filter(|a| a.kind() == pb::AlarmKind::LinkAlarm);
                Some(a.map_or_else(Vec::new, |a| {
                    let code = if !a.code.is_empty() {
                        a.code.as_str()
                    } else if a.alarm_number.is_empty() {
                        codes::LINK
                    } else {
                        a.alarm_number.as_str()
                    };
                    vec![fault(code, &a.message)]
                }))
            }
            pb::LinkState::Unspecified | pb::LinkState::Connecting => None,
            _ => Some(Vec::new()),
        }
    }

    /// The MOTION_PROGRAM condition of a G05 stream: a Warning while the open stream has
    /// starved the CNC (unit times without a block, §9.2: the gateway's G05 alarm).
    pub(crate) fn g05_starved(&self) -> Option<Vec<Cond>> {
        let s = self.up()?;
        let alarm = s
            .last_alarm
            .as_ref()
            .filter(|a| a.kind() == pb::AlarmKind::G05 && self.g05_open);
        Some(alarm.map_or_else(Vec::new, |a| {
            vec![Cond {
                level: Level::Warning,
                native_code: codes::G05.into(),
                text: a.message.as_str().into(),
            }]
        }))
    }

    /// What data item `role` of this machine should show.
    pub fn wanted(&self, role: &Role) -> Option<Wanted> {
        let up = self.up();
        Some(match role {
            Role::Availability => Wanted::Value(text(if up.is_some() {
                "AVAILABLE"
            } else {
                "UNAVAILABLE"
            })),
            Role::Execution => Wanted::Value(self.execution()),
            Role::Program => Wanted::Value(match (&self.program, up) {
                (Some(p), Some(_)) => text(p.as_str()),
                _ => Value::Unavailable,
            }),
            Role::BlockFed => Wanted::Value(match (&self.block, up) {
                (Some(b), Some(_)) => text(b.as_str()),
                _ => Value::Unavailable,
            }),
            Role::PartCount => Wanted::Value(match (self.part_count, self.gateway_up) {
                (Some(n), true) => text(n.to_string()),
                _ => Value::Unavailable,
            }),
            Role::Di => Wanted::Value(
                up.and_then(|s| s.di_image)
                    .map_or(Value::Unavailable, |v| text(v.to_string())),
            ),
            Role::Do => Wanted::Value(
                up.and_then(|s| s.do_image)
                    .map_or(Value::Unavailable, |v| text(v.to_string())),
            ),
            Role::G05Blocks => Wanted::Value(match (self.g05_taken, up) {
                (Some(n), Some(_)) => text(n.to_string()),
                _ => Value::Unavailable,
            }),
            Role::CncAlarm => Wanted::Conditions(self.cnc_alarm()),
            Role::G05Starved => Wanted::Conditions(self.g05_starved()),
            Role::LinkFault => Wanted::Conditions(self.link_fault()),
            _ => return None,
        })
    }
}

/// What the agent was told of one PLC.
#[derive(Debug, Clone, Default)]
pub struct PlcView {
    /// Whether the cell's gateway is there.
    pub gateway_up: bool,
    stations: Vec<(u32, bool, String)>,
    tags: Vec<(String, Option<String>)>,
}

impl PlcView {
    /// Takes the PLC's status (its stations, and its tags' values).
    pub fn status(&mut self, s: &pb::PlcStatus) {
        self.stations = s
            .stations
            .iter()
            .map(|st| (st.station, st.up, st.last_error.clone()))
            .collect();
        for t in &s.tags {
            self.tag(t);
        }
    }

    /// Takes a tag's value.
    pub fn tag(&mut self, t: &pb::TagValue) {
        // A value read now is the tag's; a stale one or a station down is not (the value
        // would be the last good one, FFU120B §5-6).
        let v = match (t.quality(), t.value) {
            (pb::TagQuality::Good, Some(v)) => Some(number(v)),
            _ => None,
        };
        match self.tags.iter_mut().find(|(n, _)| *n == t.name) {
            Some(slot) => slot.1 = v,
            None => self.tags.push((t.name.clone(), v)),
        }
    }

    /// What data item `role` of this PLC should show.
    pub fn wanted(&self, role: &Role) -> Option<Wanted> {
        let any_up = self.stations.iter().any(|s| s.1);
        Some(match role {
            Role::Availability => Wanted::Value(text(if self.gateway_up && any_up {
                "AVAILABLE"
            } else {
                "UNAVAILABLE"
            })),
            Role::Station(n) => Wanted::Conditions(if !self.gateway_up {
                None
            } else {
                self.stations
                    .iter()
                    .find(|s| s.0 == *n)
                    .map(|(_, up, err)| {
                        if *up {
                            Vec::new()
                        } else {
                            let what = if err.is_empty() {
                                format!("station {n} does not answer")
                            } else {
                                format!("station {n} does not answer: {err}")
                            };
                            vec![fault(codes::STATION, &what)]
                        }
                    })
            }),
            Role::Tag(name) => Wanted::Value(
                self.tags
                    .iter()
                    .find(|(n, _)| n == name)
                    .and_then(|(_, v)| v.clone())
                    .filter(|_| self.gateway_up)
                    .map_or(Value::Unavailable, text),
            ),
            _ => return None,
        })
    }
}

/// A number as an observation shows it: integers without a fraction.
pub fn number(v: f64) -> String {
    if v.fract() == 0.0 && v.abs() < 1e15 {
        format!("{}", v as i64)
    } else {
        format!("{v}")
    }
}
