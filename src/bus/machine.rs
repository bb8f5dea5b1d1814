//! One machine on the bus: its view (status, DI, recent jobs) kept up to date from its link's
//! and its job manager's events, and [`MachinePublisher`], what each route publishes a
//! machine's messages through. The task that feeds the view and publishes is
//! `machine_task`.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use super::payload;
use crate::jobs::{JobsHandle, JobsSnapshot};
use crate::link::driver::{LinkEvent, LinkHandle};
use crate::link::g05::G05Desk;
use cellgate_core::codes::alarm as codes;
use cellgate_core::config::MachineConfig;
use cellgate_core::fanuc::host::LinkState;
use cellgate_core::pb;

/// What the bus knows of a machine right now.
#[derive(Debug, Default)]
pub(crate) struct View {
    pub status: pb::MachineStatus,
    pub link_state: Option<LinkState>,
    pub last_di: Option<pb::DiImage>,
    /// The last event of each recent job, oldest first.
    pub recent_jobs: VecDeque<pb::JobEvent>,
}

/// A machine of the cell, shared by its task and the routes.
#[derive(Debug)]
pub(crate) struct Machine {
    pub config: MachineConfig,
    pub link: LinkHandle,
    pub jobs: JobsHandle,
    pub g05: Arc<G05Desk>,
    /// The simulated board of a `sim` machine.
    pub sim: Option<crate::sim::BoardControl>,
    /// The latest DI image read on request, and when: held while an RDI is on its way, so
    /// that DI gets at once share one read (`route_io`).
    pub di_read: tokio::sync::Mutex<Option<(tokio::time::Instant, Result<u8, ()>)>>,
    view: Mutex<View>,
}

impl Machine {
    pub(crate) fn new(
        config: MachineConfig,
        link: LinkHandle,
        jobs: JobsHandle,
        g05: Arc<G05Desk>,
        sim: Option<crate::sim::BoardControl>,
    ) -> Self {
        let status = pb::MachineStatus {
            machine: config.name.clone(),
            protocol: payload::protocol(config.protocol) as i32,
            link_state: pb::LinkState::Down as i32,
            counters: Some(pb::LinkCounters::default()),
            ..pb::MachineStatus::default()
        };
        // The jobs the journal kept answer gets by id from the start.
        let recent_jobs = jobs.restored_events().iter().cloned().collect();
        Machine {
            config,
            link,
            jobs,
            g05,
            sim,
            di_read: tokio::sync::Mutex::new(None),
            view: Mutex::new(View {
                status,
                recent_jobs,
                ..View::default()
            }),
        }
    }

    pub(crate) fn name(&self) -> &str {
        &self.config.name
    }

    /// The view; never held across an await.
    pub(crate) fn view(&self) -> MutexGuard<'_, View> {
        // A panic while the lock was held leaves a view that is still usable.
        self.view
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The status as of now.
    pub(crate) fn status(&self) -> pb::MachineStatus {
        let mut s = self.view().status.clone();
        s.unix_ms = pb::now_ms();
        self.line_counters(&mut s);
        s.storage_fault = self.storage_fault();
        s.g05 = self
            .g05
            .current()
            .map(|h| payload::g05_status(&h.status().borrow()));
        s
    }

    /// The link's line counters, which it keeps for telemetry, as of now. They change with
    /// every byte, so they are read when a status goes out, not kept in the view (where each
    /// byte would be a change to publish).
    pub(crate) fn line_counters(&self, s: &mut pb::MachineStatus) {
        // A link that keeps no counters leaves them absent, as the contract says.
        let Some(line) = self.link.line_counts() else {
            return;
        };
        let c = s.counters.get_or_insert_with(pb::LinkCounters::default);
        c.bytes_received = Some(line.bytes_in);
        c.bytes_sent = Some(line.bytes_out);
        c.frames = Some(line.frames_in + line.frames_out);
    }

    /// Why the job journal cannot write, or empty.
    pub(crate) fn storage_fault(&self) -> String {
        self.jobs.journal().fault().unwrap_or_default()
    }

    pub(crate) fn link_up(&self) -> bool {
        self.view().link_state.is_some_and(payload::link_up)
    }

    /// How long to wait for the board to answer RDI or to output SDO: the host speaks at
    /// the next SAT or GTD, and the board sends SAT every Tp seconds (§4.4, §4.5). Right after
    /// an exchange that next SAT is a whole poll plus the board's turnaround away, so allow
    /// one missed poll: 2·Tp + 1 s.
    pub(crate) fn exchange_timeout(&self) -> Duration {
        Duration::from_secs(2 * u64::from(self.config.params().tp) + 1)
    }

    pub(super) fn counters(view: &mut View) -> &mut pb::LinkCounters {
        view.status
            .counters
            .get_or_insert_with(pb::LinkCounters::default)
    }

    /// Folds a link event into the view; returns what to publish besides the status.
    pub(super) fn on_link_event(&self, event: &LinkEvent) -> Option<Extra> {
        let mut view = self.view();
        match event {
            LinkEvent::State { state } => {
                view.link_state = Some(*state);
                // A CNC in alarm stays so until a reset, a SAT without alarm or the CNC
                // reading again ([`end_alarm`]): the link going idle after the alarm's ALM or
                // NAK (§4.4.1, §6.4) does not end it. A link that goes down does.
                let cnc_alarm = view.status.link_state == pb::LinkState::Alarm as i32
                    && view
                        .status
                        .last_alarm
                        .as_ref()
                        .is_some_and(|a| a.kind() == pb::AlarmKind::CncAlarm);
                if !cnc_alarm || !payload::link_up(*state) {
                    view.status.link_state = payload::link_state(*state) as i32;
                }
                None
            }
            LinkEvent::Status { status } => {
                let sat = payload::sat(status);
                if sat.buffer_status() != pb::BufferStatus::Alarm {
                    end_alarm(&mut view);
                }
                view.status.sat = Some(sat);
                None
            }
            LinkEvent::Di { value } => {
                let di = pb::DiImage {
                    machine: self.name().to_string(),
                    value: u32::from(*value),
                    unix_ms: pb::now_ms(),
                };
                view.status.di_image = Some(u32::from(*value));
                view.last_di = Some(di.clone());
                Some(Extra::Di(di))
            }
            LinkEvent::Do { value } => {
                view.status.do_image = Some(u32::from(*value));
                None
            }
            LinkEvent::Waiting {
                what,
                since_unix_ms,
            } => {
                view.status.waiting_for = what.unwrap_or_default().to_string();
                view.status.waiting_since_unix_ms = if what.is_some() { *since_unix_ms } else { 0 };
                None
            }
            LinkEvent::ProtocolError { error, retried } => {
                let c = Self::counters(&mut view);
                c.protocol_errors += 1;
                if *retried {
                    c.retries += 1;
                }
                if error.is_checksum() {
                    c.checksum_errors += 1;
                }
                None
            }
            LinkEvent::Alarm(error) => {
                // A SAT in alarm status is the CNC's side (§4.4.2 1): a CNC alarm, not one
                // of the link's, on every surface.
                let kind = if error.is_cnc_side() {
                    pb::AlarmKind::CncAlarm
                } else {
                    Self::counters(&mut view).link_alarms += 1;
                    pb::AlarmKind::LinkAlarm
                };
                view.status.link_state = pb::LinkState::Alarm as i32;
                let alarm = error.cnc_alarm();
                let message = match alarm {
                    Some(a) => format!("{}: {error}", a.message()),
                    None => error.to_string(),
                };
                let event = self.alarm_event(
                    kind,
                    alarm.map(|a| a.number()).unwrap_or_default(),
                    error.code(),
                    message,
                );
                view.status.last_alarm = Some(event.clone());
                Some(Extra::Alarm(event))
            }
            LinkEvent::CncAlarm => {
                view.status.link_state = pb::LinkState::Alarm as i32;
                let (how, code) = if self.config.protocol.is_a_family() {
                    ("the CNC raised an alarm (ALM; §4.4.1)", codes::ALM)
                } else {
                    ("the CNC raised an alarm (NAK; §6.4)", codes::NAK)
                };
                let event = self.alarm_event(pb::AlarmKind::CncAlarm, "", code, how.to_string());
                view.status.last_alarm = Some(event.clone());
                Some(Extra::Alarm(event))
            }
            LinkEvent::CncReset => {
                // The last SAT is as old as Tp, or older while the CNC reads (no SAT then,
                // §4.4.1): a reset is news it cannot have had.
                set_buffer_status(&mut view, pb::BufferStatus::Reset);
                end_alarm(&mut view);
                let how = if self.config.protocol.is_a_family() {
                    "the CNC was reset (RST; §4.4.1)"
                } else {
                    "the CNC was reset (SYN; §6.4)"
                };
                let event = self.alarm_event(pb::AlarmKind::CncReset, "", "", how.to_string());
                view.status.last_alarm = Some(event.clone());
                Some(Extra::Alarm(event))
            }
            // A CNC that takes program data is operating, whatever the last SAT said (no SAT
            // comes while it reads).
            LinkEvent::Progress { sent, .. } if *sent > 0 => {
                end_alarm(&mut view);
                let status = view.status.sat.as_ref().map(pb::Sat::buffer_status);
                if matches!(
                    status,
                    Some(pb::BufferStatus::Alarm | pb::BufferStatus::Reset)
                ) {
                    set_buffer_status(&mut view, pb::BufferStatus::Operating);
                }
                None
            }
            LinkEvent::Stopped { .. } => {
                view.link_state = None;
                view.status.link_state = pb::LinkState::Down as i32;
                None
            }
            _ => None,
        }
    }

    /// An alarm of this machine: its manual `number` (or empty) and the `code` every surface
    /// shows ([`pb::AlarmEvent::code`]).
    pub(super) fn alarm_event(
        &self,
        kind: pb::AlarmKind,
        number: &str,
        code: &str,
        message: String,
    ) -> pb::AlarmEvent {
        pb::AlarmEvent {
            machine: self.name().to_string(),
            kind: kind as i32,
            alarm_number: number.to_string(),
            message,
            unix_ms: pb::now_ms(),
            code: code.to_string(),
        }
    }

    pub(super) fn on_jobs_snapshot(&self, snapshot: &JobsSnapshot) {
        let mut view = self.view();
        view.status.current_job_id = snapshot.active.clone().unwrap_or_default();
        view.status.jobs_waiting = u32::try_from(snapshot.waiting).unwrap_or(u32::MAX);
        let c = Self::counters(&mut view);
        c.nc_bytes_sent = snapshot.nc_bytes_sent;
        c.jobs_completed = snapshot.jobs_completed;
        c.jobs_failed = snapshot.jobs_failed;
    }

    /// Keeps `event` as the latest of its job, and at most `keep` jobs.
    pub(crate) fn remember_job_event(&self, event: &pb::JobEvent, keep: usize) {
        let mut view = self.view();
        let recent = &mut view.recent_jobs;
        if let Some(i) = recent.iter().position(|e| e.job_id == event.job_id) {
            recent.remove(i);
        }
        recent.push_back(event.clone());
        while recent.len() > keep {
            recent.pop_front();
        }
    }
}

/// A reset, or a SAT that is not in alarm, ends the alarm an alarm event put the view in:
/// the link shows its own state again (it has none of its own for a CNC in alarm).
fn end_alarm(view: &mut View) {
    if view.status.link_state == pb::LinkState::Alarm as i32 {
        view.status.link_state =
            view.link_state
                .map_or(pb::LinkState::Down, payload::link_state) as i32;
    }
}

/// The buffer status of the view's SAT, as the link's own messages show it since that SAT.
fn set_buffer_status(view: &mut View, status: pb::BufferStatus) {
    if let Some(sat) = view.status.sat.as_mut() {
        sat.buffer_status = status as i32;
        sat.buffer_status_digit = Some(match status {
            pb::BufferStatus::Reset => 1,
            pb::BufferStatus::Operating => 2,
            _ => sat.buffer_status_digit.unwrap_or(0),
        });
    }
}

/// What a link event adds to a machine's view beyond its status, for the task to publish.
pub(super) enum Extra {
    Di(pb::DiImage),
    Alarm(pb::AlarmEvent),
}
