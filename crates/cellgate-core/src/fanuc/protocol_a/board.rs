//! What the board's messages mean to the host: SAT's status (§4.4.1, §4.5), RTY (§4.6),
//! the Expansion A monitor packet (§5.2), and a program's bytes acknowledged.

use std::time::Instant;

use bytes::Bytes;

use super::expansion::{PacketRun, RunOutcome};
use super::{EodFor, MIN_NOISY_DAT, ProtocolAHost, Request};
use crate::fanuc::error::{AbortReason, LinkAlarm, ProtocolError};
use crate::fanuc::host::{Confirmation, EngineEvent};
use crate::fanuc::message::Message;
use crate::fanuc::packet::{MONITOR_LEN, Monitor};
use crate::fanuc::sat::{AlarmCause, BufferStatus, StatusData, effective_packet_n};

impl ProtocolAHost {
    /// The read an owed EOD was for is over (CNC reset or alarm).
    pub(super) fn drop_stale_eod(&mut self) {
        if matches!(self.eod_owed, Some(EodFor::Cleanup | EodFor::Delivered)) {
            self.eod_owed = None;
        }
    }

    /// Decodes a SAT: Status event, the board's n, alarm status transitions.
    pub(super) fn on_sat(&mut self, data: &[u8]) -> Option<StatusData> {
        let sd = match StatusData::decode(data) {
            Ok(sd) => sd,
            Err(e) => {
                self.protocol_error(ProtocolError::Status(e), false);
                return None;
            }
        };
        self.emit(EngineEvent::Status(sd));
        if sd.params.is_some() {
            self.sat = Some(sd);
        } else {
            // Keep the last known parameters when a short SAT does not carry them.
            let params = self.sat.and_then(|s| s.params);
            self.sat = Some(StatusData { params, ..sd });
        }
        if let Some(n) = sd.packet_n {
            self.board_n = effective_packet_n(n);
        }
        // A board that does not report its buffer cannot be waited for.
        if self.drain_wait && sd.buffered.is_none_or(|b| b == 0) {
            self.drain_wait = false;
        }
        if self.eod_owed == Some(EodFor::Delivered) && sd.buffered == Some(0) {
            // The CNC has read the last program through its EOR: its read is over, and a
            // GTD from now on is the next read's (§8.2; protocol notes 18).
            tracing::debug!("the EOD owed to the last read is dropped: its buffer is empty");
            self.eod_owed = None;
        }
        if let Some(status) = sd.status {
            let alarm = status == BufferStatus::Alarm;
            if alarm {
                let cause = sd.alarm_cause.unwrap_or(AlarmCause::NcAlarm);
                if !self.board_in_alarm {
                    self.alarm(LinkAlarm::BoardAlarm { cause });
                }
                // A board in alarm took nothing it was sent since its last exchange: reception
                // errors (retry over, command errors) raise SR0945/SR0947/SR0948 and drop the
                // received data (§4.6 2), so this SAT acknowledges no DAT, and a program under
                // way cannot go on while the CNC is in alarm.
                self.abort_program(AbortReason::BoardAlarm(cause), false, false, true);
            }
            self.board_in_alarm = alarm;
        }
        Some(sd)
    }

    pub(super) fn on_rty(&mut self, now: Instant, msg: &Message) {
        self.retries = self.retries.saturating_add(1);
        if self.dat_unacked > 0 {
            self.dat_limit = (self.dat_len_now() / 2).max(MIN_NOISY_DAT);
            self.clean_dats = 0;
        }
        let ne = self.ne();
        if self.retries > ne {
            self.retry_over(now);
            return;
        }
        let Some(bytes) = self.last_sent.clone() else {
            self.protocol_error(ProtocolError::RtyNothingSent, false);
            return;
        };
        self.protocol_error(
            ProtocolError::RtyReceived {
                reason: msg.data.first().copied(),
                count: self.retries,
                ne,
            },
            true,
        );
        // A retransmission counts no program bytes and no DO again.
        self.queue(bytes, Bytes::new(), None);
    }

    pub(super) fn on_monitor(&mut self, now: Instant, packet: [u8; MONITOR_LEN]) {
        let monitor = match Monitor::decode(&packet) {
            Ok(m) => m,
            Err(e) => {
                self.protocol_error(ProtocolError::Monitor(e), false);
                return;
            }
        };
        if self.run.is_none()
            && monitor == Monitor::Stop
            && self.board_n != 0
            && matches!(self.owed, Some(Request::Gtd { .. }))
        {
            // CAN between the GTD and the host's answer: no packet is under way, so the end
            // packet (dummy data) goes at once and answers the GTD; anything else is an
            // unexpected command to a board awaiting it (§5.3 1; protocol notes 16).
            tracing::debug!("CAN before the first packet: end packet at once");
            self.owed = None;
            self.last_activity = now;
            let mut run = PacketRun::new(self.board_n, now);
            run.stop = true;
            run.outcome = RunOutcome::Stopped;
            self.run = Some(run);
            self.abort_program(AbortReason::CncStop, false, false, true);
            return;
        }
        let Some(run) = self.run.as_mut() else {
            self.protocol_error(ProtocolError::StrayMonitor { monitor }, false);
            return;
        };
        tracing::debug!(?monitor, "monitor packet");
        self.last_activity = now;
        match run.on_monitor(monitor) {
            Ok(()) => {
                if monitor == Monitor::Stop {
                    self.abort_program(AbortReason::CncStop, false, false, true);
                }
            }
            Err(unknown) => {
                // The board lost a packet the host no longer has: end the transmission, the
                // program is broken (its data on the board is cleared afterwards).
                self.abort_program(
                    AbortReason::UnknownPacket { no: unknown.0 },
                    false,
                    true,
                    false,
                );
            }
        }
    }

    /// The transmission is over: the board spoke Protocol A after the end packet, so no
    /// packet can be asked for again (§5.2 2 b): the rest of the program is acknowledged.
    pub(super) fn finish_run(&mut self) {
        if let Some(run) = self.run.take() {
            tracing::debug!(packets = run.packets_sent, "Expansion A transmission ended");
            if run.outcome == RunOutcome::Delivered {
                self.ack(run.unacked_program_bytes());
                tracing::info!(
                    bytes = self.acked,
                    "program delivered (end packet acknowledged)"
                );
                self.drain_wait = true;
                self.emit(EngineEvent::ProgramDone {
                    confirmation: Confirmation::Acknowledged,
                });
            }
        }
    }

    /// `bytes` more program bytes are acknowledged.
    pub(super) fn ack(&mut self, bytes: u64) {
        if bytes > 0 {
            self.acked += bytes;
            self.emit(EngineEvent::Acked { offset: self.acked });
        }
    }
}
