//! FANUC remote buffer (B-63322EN-1): the host computer's side of Protocol A, Expansion
//! Protocol A, Protocol B and Expansion Protocol B.
//!
//! Everything here is sans-IO: it imports [`crate::engine`] and its own codecs, and nothing
//! of the async runtime, the link drivers or the transports.
//!
//! - [`code`]: ISO / ASCII character codes, the control codes, significant characters and EOR
//!   (§4.2, §6.2; protocol notes 8);
//! - [`message`]: Protocol A message framing: checksum, command, data part, end code (§4.1);
//! - [`sat`]: the SAT/SET data part and the remote-buffer parameters Nb..Tw (§4.4.2, §4.5);
//! - [`packet`]: Expansion Protocol A data packets and monitor packets (§5.2, §5.3);
//! - [`program`]: the program being sent, a bounded window of it up to its EOR (§8.2);
//! - [`host`]: the host engines' contract: commands, events, [`host::HostEngine`];
//! - [`error`]: protocol errors, link alarms and abort reasons, typed (§4.6, §6.4, §11);
//! - [`protocol_a`]: the sans-IO host engine for Protocol A and Expansion Protocol A (§4, §5);
//! - [`protocol_b`]: the sans-IO host engine for Protocol B and Expansion Protocol B (§6, §7);
//! - [`g05`]: G05 binary input operation: settings, block codec, the `G05` block (§9), and a
//!   stream's rules ([`g05::stream`]: credits, priming, the CNC's estimated buffer);
//! - [`alarm`]: the CNC alarm numbers of §11 that a link can raise.

pub mod alarm;
pub mod code;
pub mod error;
pub mod g05;
pub mod host;
pub mod message;
pub mod packet;
pub mod program;
pub mod protocol_a;
pub mod protocol_b;
pub mod sat;

use serde::{Deserialize, Serialize};

/// The four remote-buffer protocols (§2.2), selected on the CNC by parameter 5074 / 5084.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Protocol {
    /// Protocol A: handshake of messages (§4).
    A,
    /// Expansion Protocol A: Protocol A with NC data in packets of 256·n bytes (§5).
    ExpansionA,
    /// Protocol B: flow control by DC1/DC3 from the remote buffer (§6).
    B,
    /// Expansion Protocol B: Protocol B at RS-422 speeds, overrun ≤ 1280 characters (§7).
    ExpansionB,
}

impl Protocol {
    /// Whether the protocol is Protocol A or Expansion Protocol A.
    pub fn is_a_family(self) -> bool {
        matches!(self, Protocol::A | Protocol::ExpansionA)
    }
    /// The protocol's name in messages: `A`, `expansion-a`, `B` or `expansion-b`.
    pub fn name(self) -> &'static str {
        match self {
            Protocol::A => "A",
            Protocol::ExpansionA => "expansion-a",
            Protocol::B => "B",
            Protocol::ExpansionB => "expansion-b",
        }
    }
    /// The protocol's name in prose, as the manual writes it: `Protocol A`,
    /// `Expansion Protocol A`, `Protocol B` or `Expansion Protocol B`.
    pub fn title(self) -> &'static str {
        match self {
            Protocol::A => "Protocol A",
            Protocol::ExpansionA => "Expansion Protocol A",
            Protocol::B => "Protocol B",
            Protocol::ExpansionB => "Expansion Protocol B",
        }
    }
}

/// Communication code of the control part (parameter 5000#2 "TCC", §10.2).
///
/// The parameter has opposite polarity for the two families: for Protocol A, 0 = ASCII and
/// 1 = ISO; for Protocol B, 0 = ISO and 1 = ASCII. Configuration therefore names the code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum CodeSystem {
    /// 7-bit code with bit 7 clear, the default.
    #[default]
    Ascii,
    /// 7-bit code with even parity in bit 7.
    Iso,
}

impl CodeSystem {
    /// The value of parameter 5000#2 that selects this code for `protocol`.
    pub fn param_5000_bit2(self, protocol: Protocol) -> u8 {
        match (self, protocol.is_a_family()) {
            (CodeSystem::Ascii, true) | (CodeSystem::Iso, false) => 0,
            (CodeSystem::Iso, true) | (CodeSystem::Ascii, false) => 1,
        }
    }
}

/// End code of a Protocol A message (parameter 5000#3 "ETX" for Protocol A, §10.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum EndCode {
    /// CR (0Dh), the default (parameter 5000#3 = 0).
    #[default]
    Cr,
    /// ETX (03h) (parameter 5000#3 = 1).
    Etx,
}
