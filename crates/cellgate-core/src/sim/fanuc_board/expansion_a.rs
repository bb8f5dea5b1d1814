//! Expansion Protocol A from the remote buffer's side: judging the data packets that answer a
//! GTD (§5.2, §5.4; protocol notes 9).
//!
//! Packet numbers must run 30h, 31h, ... 39h, 30h, ...; FFh is the end packet (or a lone
//! packet); any other number is an invalid (dummy) packet, ignored. On a checksum error, a
//! missing CR, or a packet out of order the board sends NAK with the number of the packet it
//! expected in that position, which is where the host resends from. That one rule covers the
//! manual's special cases: a corrupted end packet gets "the before packet No. + 1", and a
//! corrupted lone FFh packet gets "packet No. 0" (30h, the first position).
//!
//! After a NAK the host finishes the packet it is sending and resends from the NAKed one, so
//! packets already on their way are ignored until the expected number comes back. An FFh
//! packet during that wait is the resent end packet only when the NAKed packet itself was the
//! end packet; otherwise it is the old end packet still in flight.

use crate::fanuc::packet::{self, END_PACKET, FIRST_PACKET, PacketKind};

/// The board's side of one GTD: Protocol A (n = 0) or the packets of Expansion A.
#[derive(Debug)]
pub(super) struct GtdRx {
    /// Packet length parameter n in force when the GTD went out; 0 = DAT.
    pub n: u8,
    /// A data packet (valid or not) arrived for this GTD.
    pub started: bool,
    /// The packet number the next packet must carry.
    pub expected: u8,
    /// Waiting for the retransmission after a NAK; `true` when the NAKed packet was FFh.
    resync: Option<bool>,
    /// CAN was sent: only the end packet is awaited, its data ignored (§5.3 1).
    pub cancelled: bool,
    /// DC3 is in force (the host pauses; To supervision is suspended).
    pub dc3: bool,
    /// Packets received since the DC3 went out: only the one under way may come (§5.3 3;
    /// protocol notes 17).
    pub after_dc3: u32,
    /// NAKs since the last packet taken in order, counted against Ne.
    pub naks: u16,
}

/// What to do with one received packet.
#[derive(Debug, PartialEq, Eq)]
pub(super) enum Verdict {
    /// An effective packet in order: its data goes to the buffer.
    Data(Vec<u8>),
    /// The end packet: its data (`None` after CAN), then back to Protocol A.
    End(Option<Vec<u8>>),
    /// Nothing to do (dummy packet, packet in flight after a NAK, data after CAN).
    Ignore(String),
    /// Ask the host to resend from this packet number.
    Nak { from: u8, why: String },
}

impl GtdRx {
    pub fn new(n: u8) -> Self {
        GtdRx {
            n,
            started: false,
            expected: FIRST_PACKET,
            resync: None,
            cancelled: false,
            dc3: false,
            after_dc3: 0,
            naks: 0,
        }
    }

    fn nak(&mut self, why: String) -> Verdict {
        self.naks = self.naks.saturating_add(1);
        Verdict::Nak {
            from: self.expected,
            why,
        }
    }

    /// Judges one packet of exactly `packet::packet_len(self.n)` bytes.
    pub fn judge(&mut self, raw: &[u8]) -> Verdict {
        self.started = true;
        let no = raw.first().copied().unwrap_or(0);
        match packet::decode_data_packet(raw, self.n) {
            Ok(p) => self.judge_valid(p.no, p.data),
            Err(e) => {
                if self.cancelled {
                    // Only the end packet matters now; ask for it again if it was spoiled.
                    return if no == END_PACKET {
                        self.nak(e.to_string())
                    } else {
                        Verdict::Ignore(format!("after CAN: {e}"))
                    };
                }
                match self.resync {
                    None => {
                        self.resync = Some(no == END_PACKET);
                        self.nak(e.to_string())
                    }
                    Some(end_resent) if no == self.expected || (end_resent && no == END_PACKET) => {
                        self.nak(format!("retransmitted packet spoiled: {e}"))
                    }
                    Some(_) => Verdict::Ignore(format!("packet in flight after NAK: {e}")),
                }
            }
        }
    }

    fn judge_valid(&mut self, no: u8, data: &[u8]) -> Verdict {
        if self.cancelled {
            return if no == END_PACKET {
                Verdict::End(None)
            } else {
                Verdict::Ignore(format!("packet {no:02X}h after CAN"))
            };
        }
        if let Some(end_resent) = self.resync {
            let wanted = no == self.expected || (end_resent && no == END_PACKET);
            if !wanted {
                return Verdict::Ignore(format!(
                    "packet {no:02X}h in flight after NAK {:02X}h",
                    self.expected
                ));
            }
            self.resync = None;
        }
        match packet::packet_kind(no) {
            PacketKind::Invalid => Verdict::Ignore(format!("invalid (dummy) packet {no:02X}h")),
            PacketKind::End => {
                self.naks = 0;
                Verdict::End(Some(data.to_vec()))
            }
            PacketKind::Effective(x) if x == self.expected => {
                self.expected = packet::next_packet_no(x);
                self.naks = 0;
                Verdict::Data(data.to_vec())
            }
            PacketKind::Effective(x) => {
                self.resync = Some(false);
                let why = format!(
                    "packet {x:02X}h out of order, expected {:02X}h (§5.2 2)",
                    self.expected
                );
                self.nak(why)
            }
        }
    }
}

#[cfg(test)]
mod tests;
