//! One Expansion Protocol A transmission: the data packets the host sends after a GTD, back to
//! back, under the board's monitor packets (§5.2, §5.3; protocol notes 9, 10).
//!
//! Packets are numbered 30h..39h, cycling; the last packet of the program (and a lone packet)
//! carries FFh instead of its number. Each packet sent is kept with its *slot*, the cycling
//! number it has or would have had, so that a NAK can name any of the last ten, the end packet
//! included: §5.2 2 b says a damaged end packet is NAKed with "the before packet No. + 1", which
//! is the end packet's slot, and a damaged lone packet with packet No. 0, its slot 30h.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use crate::fanuc::packet::{
    DUMMY_PACKET, END_PACKET, FIRST_PACKET, Monitor, data_len, encode_data_packet, next_packet_no,
};

use crate::fanuc::program::Program;

/// Packets kept for retransmission: the ten numbers 30h..39h name at most ten packets.
pub(crate) const HISTORY: usize = 10;

/// The byte that fills the last packet after EOR, the end packet of a stopped transmission and
/// dummy packets: NUL, the feed character. The CNC ignores data after EOR (§8.2) and skips
/// feed on ISO and EIA tape alike; NUL has even parity, so it is a valid ISO character, and it
/// can be neither EOR nor an end of block, so no stray block can arise from it.
pub const PAD: u8 = 0x00;

/// How a transmission ended, as far as the program is concerned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum RunOutcome {
    /// Packets of the program are still to go.
    Sending,
    /// The end packet carried the program's EOR: done once the board speaks Protocol A again.
    Delivered,
    /// Stopped (CAN, cancel, error): the program was already reported aborted.
    Stopped,
}

/// A packet handed to the line.
#[derive(Debug)]
pub(crate) struct OutPacket {
    pub bytes: Vec<u8>,
    /// Program bytes sent for the first time in this packet (its data without padding).
    pub program: Vec<u8>,
    /// The packet number on the line (for logs).
    pub no: u8,
}

#[derive(Debug)]
pub(crate) struct PacketRun {
    pub n: u8,
    next_slot: u8,
    /// The last packets sent: slot, bytes, program bytes sent for the first time in it.
    history: VecDeque<(u8, Vec<u8>, u64)>,
    /// Program bytes of packets that left `history`. Past the NAK window, but not acknowledged:
    /// Expansion A has no positive acknowledgement (§5.3), and a board that lost the packet
    /// boundary or a NAK that was lost on the line leaves no trace here, so only the end of
    /// the transmission acknowledges (see `unacked_program_bytes`).
    evicted: u64,
    resend: VecDeque<Vec<u8>>,
    /// DC3 received: hold until the next monitor packet (§5.3 3).
    pub paused: bool,
    /// Send the end packet next, whatever else is pending, even when paused (§5.3 1).
    pub stop: bool,
    pub end_sent: bool,
    pub outcome: RunOutcome,
    /// When the last packet went out (or the GTD came): the board's To runs from it (§5.4 note).
    pub last_packet_at: Instant,
    /// The dummy-packet deadline passed and no packet went out since.
    pub dummy_due: bool,
    pub packets_sent: u64,
}

/// A NAK named a packet that is not kept.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct UnknownPacket(pub u8);

impl PacketRun {
    pub(crate) fn new(n: u8, now: Instant) -> Self {
        PacketRun {
            n,
            next_slot: FIRST_PACKET,
            history: VecDeque::with_capacity(HISTORY),
            evicted: 0,
            resend: VecDeque::new(),
            paused: false,
            stop: false,
            end_sent: false,
            outcome: RunOutcome::Sending,
            last_packet_at: now,
            dummy_due: false,
            packets_sent: 0,
        }
    }

    /// Bytes held for retransmission.
    pub(crate) fn held_bytes(&self) -> usize {
        self.history.iter().map(|(_, b, _)| b.len()).sum::<usize>()
            + self.resend.iter().map(Vec::len).sum::<usize>()
    }

    /// Applies a monitor packet other than CAN (which the engine handles: it aborts the
    /// program). Any monitor packet ends a DC3 pause (§5.3 3: "wait until the next monitor
    /// packet is received").
    pub(crate) fn on_monitor(&mut self, m: Monitor) -> Result<(), UnknownPacket> {
        match m {
            Monitor::Pause => {
                self.paused = true;
                Ok(())
            }
            Monitor::Resume => {
                self.paused = false;
                Ok(())
            }
            Monitor::Stop => {
                self.paused = false;
                if !self.end_sent {
                    self.stop = true;
                }
                // An end packet already on its way need not be sent again (§5.3 1).
                self.resend.clear();
                Ok(())
            }
            Monitor::Retransmit(no) => {
                self.paused = false;
                if self.stop && !self.end_sent {
                    // Stopping anyway: the end packet goes next and its data is dummy.
                    return Ok(());
                }
                // "Packet No. 0" names a damaged lone packet (§5.2 2 b note); its slot is 30h.
                let slot = if no == 0 { FIRST_PACKET } else { no };
                let i = self
                    .history
                    .iter()
                    .rposition(|(s, _, _)| *s == slot)
                    .ok_or(UnknownPacket(no))?;
                self.resend = self
                    .history
                    .iter()
                    .skip(i)
                    .map(|(_, b, _)| b.clone())
                    .collect();
                Ok(())
            }
        }
    }

    fn record(&mut self, slot: u8, bytes: &[u8], program_bytes: u64, now: Instant) {
        if self.history.len() == HISTORY
            && let Some((_, _, acked)) = self.history.pop_front()
        {
            // Ten packets later its number is taken again: the board can no longer ask for
            // it (§5.2 2 b), so it arrived.
            self.evicted += acked;
        }
        self.history
            .push_back((slot, bytes.to_vec(), program_bytes));
        self.next_slot = next_packet_no(slot);
        self.last_packet_at = now;
        self.dummy_due = false;
        self.packets_sent += 1;
    }

    fn packet(&mut self, no: u8, data: &[u8], program_bytes: u64, now: Instant) -> Vec<u8> {
        let len = data_len(self.n);
        let mut padded;
        let data = if data.len() < len {
            padded = Vec::with_capacity(len);
            padded.extend_from_slice(data);
            padded.resize(len, PAD);
            &padded[..]
        } else {
            data
        };
        let mut bytes = Vec::with_capacity(len + 4);
        encode_data_packet(no, data, &mut bytes);
        let slot = self.next_slot;
        self.record(slot, &bytes, program_bytes, now);
        bytes
    }

    /// Program bytes sent in this transmission: what the board's return to Protocol A after
    /// the end packet acknowledges.
    pub(crate) fn unacked_program_bytes(&self) -> u64 {
        self.evicted + self.history.iter().map(|(_, _, p)| p).sum::<u64>()
    }

    /// Whether a packet can go out now (for the deadline: only late data waits).
    pub(crate) fn waiting_for_data(&self, program: Option<&Program>) -> bool {
        !self.paused
            && !self.stop
            && !self.end_sent
            && self.resend.is_empty()
            && program.is_some_and(|p| p.buffered() < data_len(self.n) && !p.complete())
    }

    /// When a dummy packet is due if the data stays late.
    pub(crate) fn dummy_deadline(&self, interval: Duration) -> Instant {
        self.last_packet_at + interval
    }

    /// The next packet to send, if one can go now. Pieces of the program are taken from
    /// `program`; the end packet is sent once the rest of the program fits in it.
    pub(crate) fn next(
        &mut self,
        now: Instant,
        program: Option<&mut Program>,
        dummy_interval: Duration,
    ) -> Option<OutPacket> {
        if self.stop && !self.end_sent {
            // CAN or cancel: finish with an end packet of dummy data (§5.3 1).
            self.resend.clear();
            let bytes = self.packet(END_PACKET, &[], 0, now);
            self.end_sent = true;
            return Some(OutPacket {
                bytes,
                program: Vec::new(),
                no: END_PACKET,
            });
        }
        if self.paused {
            return None;
        }
        if let Some(bytes) = self.resend.pop_front() {
            self.last_packet_at = now;
            self.dummy_due = false;
            let no = bytes.first().copied().unwrap_or(DUMMY_PACKET);
            return Some(OutPacket {
                bytes,
                program: Vec::new(),
                no,
            });
        }
        if self.end_sent || self.stop {
            return None;
        }
        let len = data_len(self.n);
        let program = program?;
        if program.ends_within(len) {
            let data = program.take(len);
            let bytes = self.packet(END_PACKET, &data, data.len() as u64, now);
            self.end_sent = true;
            self.outcome = RunOutcome::Delivered;
            return Some(OutPacket {
                bytes,
                program: data,
                no: END_PACKET,
            });
        }
        if program.buffered() >= len {
            let data = program.take(len);
            let no = self.next_slot;
            let bytes = self.packet(no, &data, data.len() as u64, now);
            return Some(OutPacket {
                bytes,
                program: data,
                no,
            });
        }
        if self.dummy_due || now >= self.dummy_deadline(dummy_interval) {
            // Data is late: an invalid packet keeps the board's To supervision from expiring
            // (§5.2 2 c, §5.4 7). It takes no number and is not kept.
            let mut bytes = Vec::with_capacity(len + 4);
            encode_data_packet(DUMMY_PACKET, &vec![PAD; len], &mut bytes);
            self.last_packet_at = now;
            self.dummy_due = false;
            return Some(OutPacket {
                bytes,
                program: Vec::new(),
                no: DUMMY_PACKET,
            });
        }
        None
    }
}

#[cfg(test)]
mod tests;
