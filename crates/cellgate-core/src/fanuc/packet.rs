//! Expansion Protocol A packets (§5.2, §5.3; protocol notes 9, 10).
//!
//! Data packet, host → board: `[packet no][256·n data][checksum 2][CR]`, the checksum being
//! the lower 8 bits of packet no + every data byte as two hex digits. Packet numbers run
//! 30h..39h and wrap; FFh marks the end packet, and a lone packet. Any other number is an
//! invalid (dummy) packet that keeps the link alive while data is late.
//!
//! Monitor packet, board → host, 5 bytes: `[code][20h or packet no][checksum 2][CR]`, the
//! checksum over the first two bytes. Codes: CAN (stop), NAK (retransmit from packet no),
//! DC3 (pause), DC1 (resume); each accepted with or without the parity bit.

use super::code::{CAN, CR, DC1, DC3, NAK};
use super::message::{hex2, parse_hex2, sum8};

/// The first packet number of the cycle (30h).
pub const FIRST_PACKET: u8 = 0x30;
/// The last packet number of the cycle (39h); the next is 30h again.
pub const LAST_CYCLING_PACKET: u8 = 0x39;
/// The packet number of the end packet (FFh), also of a lone packet.
pub const END_PACKET: u8 = 0xFF;
/// The packet number of an invalid (dummy) packet: anything outside 30h..39h and FFh.
pub const DUMMY_PACKET: u8 = 0x20;
/// Bytes in a monitor packet.
pub const MONITOR_LEN: usize = 5;

/// Data bytes in a packet for packet length parameter n (§5.2 1).
pub fn data_len(n: u8) -> usize {
    256 * usize::from(n)
}

/// Bytes on the line of one data packet for packet length parameter n.
pub fn packet_len(n: u8) -> usize {
    data_len(n) + 4
}

/// The packet number after `no` (39h wraps to 30h).
pub fn next_packet_no(no: u8) -> u8 {
    if (FIRST_PACKET..LAST_CYCLING_PACKET).contains(&no) {
        no + 1
    } else {
        FIRST_PACKET
    }
}

/// What a packet number says (§5.2 2).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PacketKind {
    /// 30h..39h.
    Effective(u8),
    /// FFh: the last packet (its data counts), or the only one.
    End,
    /// Anything else: ignored by the board.
    Invalid,
}

/// What packet number `no` says (§5.2 2).
pub fn packet_kind(no: u8) -> PacketKind {
    match no {
        FIRST_PACKET..=LAST_CYCLING_PACKET => PacketKind::Effective(no),
        END_PACKET => PacketKind::End,
        _ => PacketKind::Invalid,
    }
}

/// Appends a data packet to `out`. `data` must be exactly `data_len(n)` bytes; the caller pads
/// the last packet (the CNC ignores what follows EOR, §8.2).
pub fn encode_data_packet(no: u8, data: &[u8], out: &mut Vec<u8>) {
    out.reserve(data.len() + 4);
    out.push(no);
    out.extend_from_slice(data);
    let ck = no.wrapping_add(sum8(data));
    out.extend_from_slice(&hex2(ck));
    out.push(CR);
}

/// Why a data packet was refused by its receiver.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum PacketError {
    /// The packet is not `packet_len(n)` bytes long.
    #[error("packet of {len} bytes, expected {expected} for n = {n} (§5.2)")]
    Length {
        /// The packet's length, bytes.
        len: usize,
        /// The length it must have for `n`, bytes.
        expected: usize,
        /// The packet length parameter n.
        n: u8,
    },
    /// The packet's last byte is not CR.
    #[error("packet {no:#04x} does not end in CR (§5.2 4)")]
    EndCode {
        /// The packet number.
        no: u8,
    },
    /// The checksum does not match the packet number and data.
    #[error(
        "packet {no:#04x} checksum error: says {received:?}, data sums to {computed:02X} (§5.2 3)"
    )]
    Checksum {
        /// The packet number.
        no: u8,
        /// The two checksum digits the packet carries.
        received: [u8; 2],
        /// The checksum of the packet number and data.
        computed: u8,
    },
    /// The monitor packet's code is not CAN, NAK, DC3 or DC1.
    #[error("monitor packet code {code:#04x} is none of CAN, NAK, DC3, DC1 (§5.3)")]
    MonitorCode {
        /// The code, parity bit stripped.
        code: u8,
    },
    /// The monitor packet's checksum does not match its first two bytes.
    #[error("monitor packet checksum error: says {received:?}, bytes sum to {computed:02X} (§5.3)")]
    MonitorChecksum {
        /// The two checksum digits the packet carries, parity bits stripped.
        received: [u8; 2],
        /// The checksum of the first two bytes.
        computed: u8,
    },
    /// The monitor packet's last byte is not CR.
    #[error("monitor packet does not end in CR (§5.3)")]
    MonitorEnd,
}

/// A data packet as the board receives it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DataPacket<'a> {
    /// The packet number.
    pub no: u8,
    /// The packet's NC data, `data_len(n)` bytes.
    pub data: &'a [u8],
}

/// Decodes one complete data packet of length `packet_len(n)`.
pub fn decode_data_packet(bytes: &[u8], n: u8) -> Result<DataPacket<'_>, PacketError> {
    let expected = packet_len(n);
    if bytes.len() != expected {
        return Err(PacketError::Length {
            len: bytes.len(),
            expected,
            n,
        });
    }
    let no = bytes[0];
    let data = &bytes[1..expected - 3];
    let received = [bytes[expected - 3], bytes[expected - 2]];
    if bytes[expected - 1] != CR {
        return Err(PacketError::EndCode { no });
    }
    let computed = no.wrapping_add(sum8(data));
    if parse_hex2(received) != Some(computed) {
        return Err(PacketError::Checksum {
            no,
            received,
            computed,
        });
    }
    Ok(DataPacket { no, data })
}

/// A monitor packet (§5.3).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Monitor {
    /// CAN: finish the current packet, send the end packet, back to Protocol A.
    Stop,
    /// NAK: retransmit from this packet number.
    Retransmit(u8),
    /// DC3: pause after the current packet.
    Pause,
    /// DC1: resume with the next packet.
    Resume,
}

impl Monitor {
    fn bytes2(self) -> [u8; 2] {
        match self {
            Monitor::Stop => [CAN, 0x20],
            Monitor::Retransmit(no) => [NAK, no],
            // The manual prints DC3 with its parity bit (93h) and the others without.
            Monitor::Pause => [DC3 | 0x80, 0x20],
            Monitor::Resume => [DC1, 0x20],
        }
    }

    /// The 5 bytes of this monitor packet on the line.
    pub fn encode(self) -> [u8; MONITOR_LEN] {
        let [a, b] = self.bytes2();
        let [c, d] = hex2(a.wrapping_add(b));
        [a, b, c, d, CR]
    }

    /// Whether `b` can start a monitor packet (with or without parity).
    pub fn is_code(b: u8) -> bool {
        matches!(b & 0x7F, CAN | NAK | DC3 | DC1)
    }

    /// Decodes a 5-byte monitor packet: its end code, checksum and code.
    pub fn decode(bytes: &[u8; MONITOR_LEN]) -> Result<Monitor, PacketError> {
        let [code, arg, c0, c1, end] = *bytes;
        if end & 0x7F != CR {
            return Err(PacketError::MonitorEnd);
        }
        let computed = code.wrapping_add(arg);
        let received = [c0 & 0x7F, c1 & 0x7F];
        if parse_hex2(received) != Some(computed) {
            return Err(PacketError::MonitorChecksum { received, computed });
        }
        match code & 0x7F {
            CAN => Ok(Monitor::Stop),
            NAK => Ok(Monitor::Retransmit(arg)),
            DC3 => Ok(Monitor::Pause),
            DC1 => Ok(Monitor::Resume),
            code => Err(PacketError::MonitorCode { code }),
        }
    }
}

#[cfg(test)]
mod tests;
