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
mod tests {
    use super::*;
    use crate::fanuc::packet::{DUMMY_PACKET, data_len, encode_data_packet};

    fn pkt(no: u8, fill: u8) -> Vec<u8> {
        let mut v = Vec::new();
        encode_data_packet(no, &vec![fill; data_len(1)], &mut v);
        v
    }

    fn spoiled(no: u8) -> Vec<u8> {
        let mut v = pkt(no, b'x');
        v[5] ^= 0x01;
        v
    }

    fn is_data(v: &Verdict) -> bool {
        matches!(v, Verdict::Data(_))
    }

    #[test]
    fn in_order_dummy_and_end() {
        let mut g = GtdRx::new(1);
        assert!(is_data(&g.judge(&pkt(0x30, b'a'))));
        assert!(matches!(g.judge(&pkt(DUMMY_PACKET, 0)), Verdict::Ignore(_)));
        for no in 0x31..=0x39 {
            assert!(is_data(&g.judge(&pkt(no, b'b'))));
        }
        assert!(is_data(&g.judge(&pkt(0x30, b'c'))), "39h wraps to 30h");
        assert_eq!(
            g.judge(&pkt(0xFF, b'e')),
            Verdict::End(Some(vec![b'e'; 256]))
        );
    }

    #[test]
    fn corrupted_packet_is_nakked_and_in_flight_ones_ignored() {
        let mut g = GtdRx::new(1);
        assert!(is_data(&g.judge(&pkt(0x30, b'a'))));
        assert!(matches!(
            g.judge(&spoiled(0x31)),
            Verdict::Nak { from: 0x31, .. }
        ));
        // Already on the line when the host saw the NAK.
        assert!(matches!(g.judge(&pkt(0x32, b'c')), Verdict::Ignore(_)));
        assert!(matches!(g.judge(&pkt(0xFF, b'd')), Verdict::Ignore(_)));
        // The retransmission.
        assert!(is_data(&g.judge(&pkt(0x31, b'b'))));
        assert!(is_data(&g.judge(&pkt(0x32, b'c'))));
        assert!(matches!(g.judge(&pkt(0xFF, b'd')), Verdict::End(Some(_))));
        assert_eq!(g.naks, 0);
    }

    #[test]
    fn corrupted_end_packet_asks_previous_plus_one() {
        let mut g = GtdRx::new(1);
        assert!(is_data(&g.judge(&pkt(0x30, b'a'))));
        assert!(matches!(
            g.judge(&spoiled(0xFF)),
            Verdict::Nak { from: 0x31, .. }
        ));
        assert!(matches!(g.judge(&pkt(0xFF, b'z')), Verdict::End(Some(_))));
    }

    #[test]
    fn lone_packet_spoiled_asks_packet_zero() {
        let mut g = GtdRx::new(1);
        assert!(matches!(
            g.judge(&spoiled(0xFF)),
            Verdict::Nak { from: 0x30, .. }
        ));
        assert!(matches!(g.judge(&pkt(0xFF, b'z')), Verdict::End(Some(_))));
    }

    #[test]
    fn first_packet_must_be_30h_and_order_is_checked() {
        let mut g = GtdRx::new(1);
        assert!(matches!(
            g.judge(&pkt(0x31, b'a')),
            Verdict::Nak { from: 0x30, .. }
        ));
        assert!(is_data(&g.judge(&pkt(0x30, b'a'))));
        assert!(matches!(
            g.judge(&pkt(0x33, b'a')),
            Verdict::Nak { from: 0x31, .. }
        ));
        assert_eq!(g.naks, 1);
    }

    #[test]
    fn after_can_only_the_end_packet_counts() {
        let mut g = GtdRx::new(1);
        assert!(is_data(&g.judge(&pkt(0x30, b'a'))));
        g.cancelled = true;
        assert!(matches!(g.judge(&pkt(0x31, b'a')), Verdict::Ignore(_)));
        assert!(matches!(g.judge(&spoiled(0x32)), Verdict::Ignore(_)));
        assert!(matches!(g.judge(&spoiled(0xFF)), Verdict::Nak { .. }));
        assert_eq!(g.judge(&pkt(0xFF, b'a')), Verdict::End(None));
    }
}
