//! The cell's PLCs: Fuji MICREX-F through FFU120B modules (`[[plcs]]`), each a link task
//! running the sans-IO [`crate::fuji::master::Master`] over a transport.
//!
//! - [`tags`]: named tags, sans-IO: poll plan, decoding, publish on change, writes;
//! - [`link`]: the thin async link task ([`link::spawn`], [`link::PlcHandle`]);
//! - this file: the settings a `[[plcs]]` entry gives the master and the simulated module.

pub mod link;
pub mod tags;

use std::time::Duration;

use crate::config::{BccCalc, BccCode, BccKind, BccRange, PlcConfig, PlcEndCode, PlcStartCode};
use crate::fuji::frame::{self, FrameSettings};
use crate::fuji::master::{MasterSettings, OperationMode};
use crate::sim::micrex::MicrexConfig;

pub use link::{PlcCommand, PlcEvent, PlcHandle, PlcLinkError, PlcSnapshot, TagWriteError};
pub use tags::{Quality, TagError, TagTable, TagValue};

/// The initial-file framing of a `[[plcs]]` entry (FFU120B §4-3 items 14–23).
pub fn frame_settings(p: &PlcConfig) -> FrameSettings {
    FrameSettings {
        start_code: match p.start_code {
            PlcStartCode::None => frame::StartCode::None,
            PlcStartCode::Stx => frame::StartCode::Stx,
            PlcStartCode::Colon => frame::StartCode::Colon,
            PlcStartCode::DoubleColon => frame::StartCode::DoubleColon,
            PlcStartCode::Set1 => frame::StartCode::Set1,
            PlcStartCode::Set2 => frame::StartCode::Set2,
        },
        start_codes: p.start_codes.clone(),
        end_code: match p.end_code {
            PlcEndCode::Etx => frame::EndCode::Etx,
            PlcEndCode::Cr => frame::EndCode::Cr,
            PlcEndCode::Lf => frame::EndCode::Lf,
            PlcEndCode::CrLf => frame::EndCode::CrLf,
            PlcEndCode::DleEtx => frame::EndCode::DleEtx,
            PlcEndCode::Set1 => frame::EndCode::Set1,
            PlcEndCode::Set2 => frame::EndCode::Set2,
        },
        end_codes: p.end_codes.clone(),
        transposition: p.transposition,
        bcc: match p.bcc {
            BccKind::None => frame::BccKind::None,
            BccKind::Set1 => frame::BccKind::Set1,
            BccKind::Set2 => frame::BccKind::Set2,
        },
        bcc_range: match p.bcc_range {
            BccRange::Text => frame::BccRange::Text,
            BccRange::TextEnd => frame::BccRange::TextEnd,
            BccRange::StartText => frame::BccRange::StartText,
            BccRange::StartTextEnd => frame::BccRange::StartTextEnd,
        },
        bcc_calc: match p.bcc_calc {
            BccCalc::Add => frame::BccCalc::Add,
            BccCalc::AddInvert => frame::BccCalc::AddInvert,
            BccCalc::Eor => frame::BccCalc::Eor,
            BccCalc::Crc16 => frame::BccCalc::Crc16,
        },
        bcc_code: match p.bcc_code {
            BccCode::TransmissionCode => frame::BccCode::TransmissionCode,
            BccCode::Binary => frame::BccCode::Binary,
        },
        ..FrameSettings::default()
    }
}

/// The operation mode of a validated entry (1–3).
pub fn mode(p: &PlcConfig) -> OperationMode {
    OperationMode::from_dial(p.mode).unwrap_or(OperationMode::One)
}

/// The host settings of a `[[plcs]]` entry.
pub fn master_settings(p: &PlcConfig) -> MasterSettings {
    let mut s = MasterSettings::new(mode(p));
    s.frame = frame_settings(p);
    s.line = *p.transport.line();
    s.reply_timeout = Duration::from_millis(u64::from(p.timeout_ms));
    s.probe_interval = s.probe_interval.max(s.reply_timeout * 2);
    // Every tag read of every station may be waiting at once (31 stations, §2-2).
    s.queue_limit = 1024;
    s
}

/// The simulated module of a `sim` entry: same framing, mode and stations, the transfer
/// message numbers of `[plcs.sim]`.
pub fn micrex_config(p: &PlcConfig) -> MicrexConfig {
    let mut c = MicrexConfig::new(mode(p));
    c.frame = frame_settings(p);
    c.line = *p.transport.line();
    c.stations = p.stations.clone();
    c.messages = p.sim.messages.clone();
    c
}
