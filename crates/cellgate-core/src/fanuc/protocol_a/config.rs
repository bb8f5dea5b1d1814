//! The host link's settings (§4.5, §10.2) and the problems `validate` finds in them.

use std::time::Duration;

use crate::fanuc::message::{Framing, MAX_DAT_DATA};
use crate::fanuc::sat::{ParamRangeError, Params, effective_packet_n};

/// Settings of a Protocol A / Expansion Protocol A host link.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProtocolAConfig {
    /// Code (ISO/ASCII, parameter 5000#2) and end code (CR/ETX, 5000#3) of the messages.
    pub framing: Framing,
    /// The remote-buffer parameters the host sets with SET (§4.5).
    pub params: Params,
    /// Expansion Protocol A packet length n: 0 = plain Protocol A; 1, 2, 4 = packets of
    /// 256·n bytes, selected with SET (§5.2 1; protocol notes 5).
    pub packet_n: u8,
    /// Code conversion the board applies to NC data, (from, to) (SET bytes 45–48, §4.4.2).
    /// `None` sets no conversion (00, 00).
    pub conversion: Option<(u8, u8)>,
    /// How long a GTD may wait for late program data before the host answers WAT (or, in
    /// Protocol A, a shorter DAT with what it has). Must be well below To.
    pub wat_grace: Duration,
    /// Expansion A: while data is late, an invalid (dummy) packet goes out this long after the
    /// last packet (§5.2 2 c). Must be well below To.
    pub dummy_interval: Duration,
    /// Most program bytes held at once;
    /// [`HostEngine::data_wanted`](crate::fanuc::host::HostEngine::data_wanted) is the free space.
    /// 16 KiB by default: two seconds of an 86400-baud line, asked for again at half, and at
    /// least four full DATs; a thousand busy links each hold it.
    pub max_buffer: usize,
    /// Line time of one character (the transport's `LineSettings::char_time`), so that time-out
    /// supervision starts after a long DAT has left the line. Zero when unknown.
    pub char_time: Duration,
    /// The transport carries the board's RS (our CS): a serial port or the simulated line
    /// does, and messages are then handed out in pieces of No so that CS off stops the host
    /// within No bytes (§4.3 (5)). A TCP device server does not (its own RTS/CTS flow control
    /// is what honours CS there): each message goes out whole, one write instead of one per
    /// No bytes.
    pub cs_visible: bool,
}

impl Default for ProtocolAConfig {
    fn default() -> Self {
        ProtocolAConfig {
            framing: Framing::default(),
            params: Params::POWER_ON,
            packet_n: 0,
            conversion: None,
            wat_grace: Duration::from_secs(1),
            dummy_interval: Duration::from_secs(5),
            max_buffer: 16 * 1024,
            char_time: Duration::ZERO,
            cs_visible: true,
        }
    }
}

/// One problem with a [`ProtocolAConfig`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ProtocolAProblem {
    /// A remote-buffer parameter outside its §4.5 range.
    #[error("parameter {0}")]
    Param(#[from] ParamRangeError),
    /// `packet_n` is none of 0, 1, 2 and 4 (§5.2 1).
    #[error(
        "packet_n = {n}: Expansion Protocol A takes n = 1, 2 or 4, and 0 selects Protocol A (§5.2 1)"
    )]
    PacketN {
        /// The `packet_n` given.
        n: u8,
    },
    /// `wat_grace` is not below half the time-out To (§4.3 (3)).
    #[error(
        "wat_grace = {grace:?} must be below half the time-out To = {to} s, so that WAT goes out before the board gives up (§4.3 (3))"
    )]
    WatGrace {
        /// The `wat_grace` given.
        grace: Duration,
        /// The time-out parameter To, seconds.
        to: u16,
    },
    /// `dummy_interval` is zero or not below half the time-out To (§5.4 7).
    #[error(
        "dummy_interval = {interval:?} must be above zero and below half the time-out To = {to} s (§5.4 7)"
    )]
    DummyInterval {
        /// The `dummy_interval` given.
        interval: Duration,
        /// The time-out parameter To, seconds.
        to: u16,
    },
    /// `max_buffer` cannot hold one full DAT data part.
    #[error("max_buffer = {len} must hold at least one full DAT data part ({min} bytes)")]
    MaxBuffer {
        /// The `max_buffer` given, bytes.
        len: usize,
        /// The smallest `max_buffer` allowed: a full DAT data part, bytes.
        min: usize,
    },
}

/// A [`ProtocolAConfig`] that cannot run, with every problem found.
pub type InvalidConfig = crate::engine::InvalidSettings<ProtocolAProblem>;

impl ProtocolAConfig {
    /// The settings of a link with these framing, parameters, packet length and character
    /// time. The WAT grace and the dummy-packet interval stay within a quarter of To, so
    /// that every To of §4.5 (1..=999 s) gives settings that validate.
    pub fn for_link(framing: Framing, params: Params, packet_n: u8, char_time: Duration) -> Self {
        let defaults = ProtocolAConfig::default();
        let quarter_to = Duration::from_secs(u64::from(params.to)) / 4;
        ProtocolAConfig {
            framing,
            params,
            packet_n,
            char_time,
            wat_grace: defaults.wat_grace.min(quarter_to),
            dummy_interval: defaults.dummy_interval.min(quarter_to),
            ..defaults
        }
    }

    /// Every problem of these settings.
    pub fn validate(&self) -> Vec<ProtocolAProblem> {
        let mut problems: Vec<ProtocolAProblem> = self
            .params
            .validate()
            .into_iter()
            .map(ProtocolAProblem::Param)
            .collect();
        if effective_packet_n(self.packet_n) != self.packet_n {
            problems.push(ProtocolAProblem::PacketN { n: self.packet_n });
        }
        let half_to = Duration::from_secs(u64::from(self.params.to)) / 2;
        if self.wat_grace >= half_to {
            problems.push(ProtocolAProblem::WatGrace {
                grace: self.wat_grace,
                to: self.params.to,
            });
        }
        if self.dummy_interval.is_zero() || self.dummy_interval >= half_to {
            problems.push(ProtocolAProblem::DummyInterval {
                interval: self.dummy_interval,
                to: self.params.to,
            });
        }
        if self.max_buffer < MAX_DAT_DATA {
            problems.push(ProtocolAProblem::MaxBuffer {
                len: self.max_buffer,
                min: MAX_DAT_DATA,
            });
        }
        problems
    }
}
