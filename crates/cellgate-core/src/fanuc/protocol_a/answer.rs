//! What the host answers: the board's exchange after DATs, the answer to SAT and GTD (SET,
//! DAT, EOD, SDO, WAT), and the line supervision that follows each message (§4.4, §4.5).

use std::time::{Duration, Instant};

use bytes::Bytes;

use super::expansion::PacketRun;
use super::{CLEAN_DATS_TO_GROW, EodFor, Phase, ProtocolAHost, Request, SAT_PROBES};
use crate::fanuc::error::{AbortReason, LinkAlarm};
use crate::fanuc::host::{Confirmation, EngineEvent};
use crate::fanuc::message::{Command, MAX_DAT_DATA, Message};
use crate::fanuc::packet::data_len;
use crate::fanuc::program::ProgramSendError;
use crate::fanuc::sat::{StatusData, effective_packet_n};

impl ProtocolAHost {
    /// The board's exchange after DATs (SAT, GTD, SDI: not RTY, RST, ALM or SYN) shows that
    /// they arrived (§4.4.1); the one after the final DAT completes the program.
    pub(super) fn on_exchange(&mut self) {
        let bytes = std::mem::take(&mut self.dat_unacked);
        if bytes > 0 && self.dat_limit < MAX_DAT_DATA {
            self.clean_dats += 1;
            if self.clean_dats >= CLEAN_DATS_TO_GROW {
                self.clean_dats = 0;
                self.dat_limit = (self.dat_limit * 2).min(MAX_DAT_DATA);
            }
        }
        self.ack(bytes);
        if self.final_sent && self.eod_owed == Some(EodFor::Done) {
            self.final_sent = false;
            // The EOD still goes to the next GTD of this read, but the program is the board's.
            self.eod_owed = Some(EodFor::Delivered);
            tracing::info!(
                bytes = self.acked,
                "program delivered (final DAT acknowledged)"
            );
            self.drain_wait = true;
            self.emit(EngineEvent::ProgramDone {
                confirmation: Confirmation::Acknowledged,
            });
        }
    }

    // ---- answers ----

    pub(super) fn try_answer(&mut self, now: Instant) {
        if self.phase != Phase::Ready || !self.line_up {
            return;
        }
        let Some(req) = self.owed.take() else {
            return;
        };
        match req {
            Request::Sat { data, after_sdi } => {
                if self.read_di && !after_sdi {
                    self.read_di = false;
                    self.rdi_for = Some(Request::Sat { data, after_sdi });
                    self.send(Command::Rdi);
                } else if let Some(v) = (!after_sdi).then(|| self.set_do.pop_front()).flatten() {
                    self.send_sdo(v);
                } else if self.clb_owed {
                    self.clb_owed = false;
                    self.drain_wait = false;
                    self.send(Command::Clb);
                } else {
                    let msg = self.set_message(data.as_ref());
                    self.send_with(&msg, Bytes::new(), None);
                }
            }
            Request::Gtd { at, after_sdi } => {
                if self.read_di && !after_sdi {
                    self.read_di = false;
                    self.rdi_for = Some(req);
                    self.send(Command::Rdi);
                } else if let Some(v) = (!after_sdi).then(|| self.set_do.pop_front()).flatten() {
                    self.send_sdo(v);
                } else if self.probe_for_sat() {
                    self.send(Command::Eod);
                } else if !self.answer_gtd(now, at) {
                    self.owed = Some(req);
                }
            }
        }
    }

    /// Whether to answer a GTD with EOD so that the board polls with SAT (protocol notes 19).
    /// A board whose CNC was reading when the link came up asks with GTD and never polls,
    /// so the SET with the cell file's parameters and n cannot go. EOD ("the transmission
    /// has been completed", §4.4.1) tells it the host has nothing under way; a board that
    /// then polls with SAT gets its SET. Tried [`SAT_PROBES`] times before any program data
    /// of this read went out; past that the host says so and carries on without the SET.
    pub(super) fn probe_for_sat(&mut self) -> bool {
        if self.sat_seen || self.program_started() || self.eod_owed.is_some() {
            return false;
        }
        if self.sat_probes < SAT_PROBES {
            self.sat_probes += 1;
            tracing::info!(
                probe = self.sat_probes,
                "GTD before any SAT since the link initialised: EOD, so that the board polls with SAT"
            );
            return true;
        }
        if !self.params_alarmed {
            self.params_alarmed = true;
            self.alarm(LinkAlarm::ParamsNotApplied {
                probes: self.sat_probes,
            });
        }
        if self.streaming && self.program.is_some() {
            // The board's packet length and timing are unknown: a G05 stream could starve
            // the CNC (§9.2), so it is refused rather than sent as it might go.
            self.abort_program(AbortReason::ParamsNotApplied, false, false, false);
        }
        false
    }

    /// SET: full when the board's values must change, else with an empty data part.
    pub(super) fn set_message(&mut self, sat: Option<&StatusData>) -> Message {
        let conversion = self.cfg.conversion.unwrap_or((0, 0));
        // n changes only between programs (protocol notes 5).
        let want_n = if self.program_started() {
            self.board_n
        } else {
            effective_packet_n(self.cfg.packet_n)
        };
        // Byte 1 is echoed; without it, a full SET could switch the CNC to tape operation.
        let Some((sat, remote)) = sat.and_then(|s| s.remote.map(|r| (s, r))) else {
            return Message::new(Command::Set);
        };
        let differs = self.set_needed
            || sat.params.is_some_and(|p| p != self.cfg.params)
            || sat.conversion.is_some_and(|c| c != conversion)
            || sat
                .packet_n
                .is_some_and(|n| effective_packet_n(n) != want_n);
        if !differs {
            return Message::new(Command::Set);
        }
        self.set_needed = false;
        self.board_n = want_n;
        let data = StatusData {
            remote: Some(remote),
            status: None,
            alarm_cause: None,
            buffered: None,
            params: Some(self.cfg.params),
            boring_unit: sat.boring_unit,
            conversion: Some(conversion),
            packet_n: Some(want_n),
        };
        tracing::debug!(params = %self.cfg.params, n = want_n, ?conversion, "SET with parameters");
        Message::with_data(Command::Set, data.to_bytes())
    }

    /// The data answer to a GTD; false when it should wait for data a little longer.
    pub(super) fn answer_gtd(&mut self, now: Instant, at: Instant) -> bool {
        let grace_over = now >= at + self.cfg.wat_grace
            || (self.streaming && self.program.as_ref().is_some_and(|p| p.buffered() > 0));
        if self.eod_owed.is_none() && !self.clb_owed && self.board_n == 0 {
            // A DAT must not carry the end code (§4.1): refuse the program here too, for
            // programs that were meant for packets.
            let len = self.dat_len();
            let end = self.cfg.framing.end_byte();
            if let Some(offset) = self.program.as_ref().and_then(|p| p.find_in_next(len, end)) {
                let e = ProgramSendError::EndCodeInData { offset, end };
                self.abort_program(AbortReason::Program(e), false, true, false);
            }
        }
        match self.eod_owed {
            Some(EodFor::Cleanup | EodFor::Delivered) => {
                self.eod_owed = None;
                self.send(Command::Eod);
                return true;
            }
            // The final DAT is not acknowledged yet: EOD waits for the exchange that does.
            Some(EodFor::Done) => {
                self.send(Command::Wat);
                return true;
            }
            None => {}
        }
        if self.clb_owed {
            // New data waits until the board's buffer has been cleared (CLB at the next SAT).
            self.send(Command::Wat);
            return true;
        }
        if self.drain_wait {
            self.send(Command::Eod);
            return true;
        }
        let n = self.board_n;
        if n != 0 {
            let ready = self
                .program
                .as_ref()
                .is_some_and(|p| p.buffered() >= data_len(n) || p.complete());
            if ready {
                tracing::debug!(n, "Expansion A transmission starts");
                self.run = Some(PacketRun::new(n, now));
                return true;
            }
        } else {
            let len = self.dat_len_now();
            if let Some(p) = self.program.as_mut()
                && (p.can_fill(len) || (grace_over && p.buffered() > 0))
            {
                let data = p.take(len);
                let done = p.all_sent();
                let program = Bytes::copy_from_slice(&data);
                self.send_with(&Message::with_data(Command::Dat, data), program, None);
                if done {
                    self.program = None;
                    self.eod_owed = Some(EodFor::Done);
                    if let Some(last) = self.tx.back_mut() {
                        last.last_of_program = true;
                    }
                }
                return true;
            }
        }
        if grace_over {
            self.send(Command::Wat);
            return true;
        }
        false
    }

    pub(super) fn supervision_deadline(&self) -> Option<Instant> {
        if !self.line_up || self.phase == Phase::SynWait || self.owed.is_some() {
            return None;
        }
        if self.run.as_ref().is_some_and(|r| !r.end_sent) {
            return None;
        }
        Some(self.last_activity + self.supervision_interval())
    }

    pub(super) fn line_time(&self, len: usize) -> Duration {
        self.cfg
            .char_time
            .saturating_mul(u32::try_from(len).unwrap_or(u32::MAX))
    }

    pub(super) fn sent_at(&mut self, now: Instant, len: usize) {
        let t = now + self.line_time(len);
        self.last_activity = self.last_activity.max(t);
    }
}
