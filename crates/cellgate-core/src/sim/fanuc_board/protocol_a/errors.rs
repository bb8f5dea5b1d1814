//! The simulated board's errors (§4.6): an alarm raised, an unexpected or undefined command,
//! a reception error, a line error, each as the board reports it and what it does next.

use std::time::Instant;

use super::{Phase, ProtocolA};
use crate::fanuc::alarm::CncAlarm;
use crate::fanuc::message::Command;
use crate::fanuc::sat::AlarmCause;
use crate::sim::cnc::Cnc;
use crate::sim::fanuc_board::{BoardEvent, BoardLinkState, Outbox};

impl ProtocolA {
    pub(super) fn raise(
        &mut self,
        now: Instant,
        alarm: CncAlarm,
        cause: AlarmCause,
        detail: String,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        tracing::warn!(alarm = alarm.number(), %detail, "simulated board alarm");
        out.event(BoardEvent::Alarm {
            alarm,
            cause,
            detail,
        });
        let was_reading = cnc.reading();
        cnc.raise_alarm(now, cause);
        if was_reading {
            out.event(BoardEvent::ReadingStopped);
        }
    }

    pub(super) fn unexpected(
        &mut self,
        now: Instant,
        cmd: Command,
        context: &str,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        let detail = format!("unexpected {cmd} {context} (§4.6 2 (2))");
        self.command_error(now, CncAlarm::Sr0947InvalidResponse, detail, cnc, out);
    }

    /// A command error (§4.6 2 (2)): alarm cause 6. Ignored during initialisation.
    pub(super) fn command_error(
        &mut self,
        now: Instant,
        alarm: CncAlarm,
        detail: String,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        if !self.initialised() {
            out.event(BoardEvent::ProtocolError { detail });
            return;
        }
        self.reception_error(now, alarm, AlarmCause::CommandError, detail, cnc, out);
    }

    /// A reception error (§4.6 2): raise the alarm, ignore the received data and go back to
    /// SAT polling; during data packets, stop them with CAN first.
    pub(super) fn reception_error(
        &mut self,
        now: Instant,
        alarm: CncAlarm,
        cause: AlarmCause,
        detail: String,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        if self.in_packets() {
            self.abort_packets(now, Some((alarm, cause, detail)), cnc, out);
            return;
        }
        self.raise(now, alarm, cause, detail, cnc, out);
        self.rx.clear();
        self.discarding = false;
        self.queued = None;
        self.complete(now);
    }

    /// A line error (§4.6 1): raise `alarm` (when the link was up) and re-initialise after
    /// the first-request delay.
    pub(super) fn line_error(
        &mut self,
        now: Instant,
        alarm: Option<CncAlarm>,
        cause: AlarmCause,
        detail: String,
        cnc: &mut Cnc,
        out: &mut Outbox,
    ) {
        match alarm {
            Some(alarm) if self.initialised() => self.raise(now, alarm, cause, detail, cnc, out),
            _ => out.event(BoardEvent::ProtocolError {
                detail: format!("line error: {detail}; re-initialising"),
            }),
        }
        self.rx.clear();
        self.discarding = false;
        self.queued = None;
        self.retries = 0;
        self.phase = Phase::Off {
            until: Some(now + self.first_request_delay),
        };
        self.set_link(BoardLinkState::Initialising, out);
    }
}
