//! The cell file: what one gateway serves, how each link is carried, and the settings both ends
//! of each link must agree on.
//!
//! A cell file is TOML. Every key is optional where a sensible default exists, and unknown keys
//! are errors (a misspelt key would otherwise be silently ignored). Reading a file happens in
//! two steps:
//!
//! 1. parsing (TOML syntax, key names, value types), whose errors come from the toml crate one at
//!    a time, with the line and the key;
//! 2. validation against the manuals (ranges, combinations, names), which reports *every* error
//!    at once, each naming its key path (`machines.mill-1.tw`), the value, what is allowed and
//!    the manual section.
//!
//! Sections are cited as "§4.5" for the FANUC remote-buffer manual (B-63322EN-1) and as
//! "FFU120B §4-3" for the Fuji MICREX-F general interface module manual (FEH087b).

use std::collections::HashMap;
use std::fmt::{self, Write as _};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::bus::BusConfig;
use crate::fanuc::sat::{ParamRangeError, Params};
use crate::fanuc::{CodeSystem, EndCode, Protocol};
use crate::telemetry::TelemetryConfig;
use crate::transport::{DataBits, LineSettings, Parity, StopBits};

// ---------------------------------------------------------------------------------------------
// The cell
// ---------------------------------------------------------------------------------------------

/// A whole cell file, validated.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct CellConfig {
    /// Cell id: `[A-Za-z0-9_-]+`. It becomes the key chunk `C` of every key `P/C/...`.
    pub cell: String,
    pub bus: BusConfig,
    pub telemetry: TelemetryConfig,
    pub programs: ProgramsConfig,
    pub machines: Vec<MachineConfig>,
    pub plcs: Vec<PlcConfig>,
}

/// `[programs]`: where submitted NC programs are kept, and what becomes of punched ones.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ProgramsConfig {
    /// Directory of stored programs; a relative path is taken from the working directory.
    pub dir: PathBuf,
    /// Largest program accepted, bytes.
    pub max_size: u64,
    /// Store every program a CNC punches out in the library, under a new name
    /// `<machine>-<O-number>-<UTC time>` (Protocol B family).
    pub store_punched: bool,
    /// Remote request patterns: a punched program that holds nothing but one comment
    /// matching one of these asks for the library program `O<n>` to be sent to the machine.
    /// `{n}` stands for the program number's digits. Empty: punched programs are never
    /// requests.
    pub requests: Vec<String>,
}

impl ProgramsConfig {
    pub const DEFAULT_MAX_SIZE: u64 = 512 * 1024 * 1024;

    /// The default remote request patterns.
    pub fn default_requests() -> Vec<String> {
        crate::jobs::punch::DEFAULT_REQUEST_PATTERNS
            .iter()
            .map(ToString::to_string)
            .collect()
    }
}

impl Default for ProgramsConfig {
    fn default() -> Self {
        ProgramsConfig {
            dir: PathBuf::from("programs"),
            max_size: Self::DEFAULT_MAX_SIZE,
            store_punched: true,
            requests: Self::default_requests(),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Transports
// ---------------------------------------------------------------------------------------------

/// What carries a link's bytes (`transport` table of a machine or PLC), selected by `kind`.
///
/// `line` holds the character framing of the serial line, also for a TCP device server (whose
/// serial side sets the pace) and for the simulated line (paced at that baud rate).
///
/// Serialized with serde's internal tagging. It is read through a flat table of optional
/// keys rather than serde's buffered internally-tagged form, so that parse errors point at the
/// exact line and a key of another kind is reported with every other validation error.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", try_from = "RawTransport")]
pub enum TransportConfig {
    /// A serial port of this computer.
    Serial {
        /// Device path, e.g. `/dev/ttyS0` or `COM3`.
        path: String,
        line: LineSettings,
    },
    /// A raw TCP connection to a serial device server.
    Tcp {
        /// `host:port` of the device server.
        address: String,
        line: LineSettings,
        /// Bytes handed to the device server and not yet on the line, at most.
        window: u32,
        /// First wait before reconnecting, ms; doubles on each failure.
        reconnect_min_ms: u64,
        /// Longest wait between reconnection attempts, ms.
        reconnect_max_ms: u64,
    },
    /// An in-memory line to a simulated device.
    Sim { line: LineSettings },
}

/// `kind` of a transport table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TransportKind {
    Serial,
    Tcp,
    Sim,
}

impl TransportKind {
    pub fn name(self) -> &'static str {
        match self {
            TransportKind::Serial => "serial",
            TransportKind::Tcp => "tcp",
            TransportKind::Sim => "sim",
        }
    }
}

/// A transport table as written: every key optional, whatever the kind.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTransport {
    kind: Option<TransportKind>,
    path: Option<String>,
    address: Option<String>,
    line: Option<LineSettings>,
    window: Option<u32>,
    reconnect_min_ms: Option<u64>,
    reconnect_max_ms: Option<u64>,
}

/// A problem in a transport table before it is a [`TransportConfig`]: `key` (under the
/// table) and what is wrong with it.
struct TransportProblem {
    key: &'static str,
    missing: bool,
    text: String,
}

impl RawTransport {
    /// The keys each kind uses, for "used only with kind = ..." messages.
    const KEYS: [(&'static str, &'static [TransportKind]); 5] = [
        ("path", &[TransportKind::Serial]),
        ("address", &[TransportKind::Tcp]),
        ("window", &[TransportKind::Tcp]),
        ("reconnect_min_ms", &[TransportKind::Tcp]),
        ("reconnect_max_ms", &[TransportKind::Tcp]),
    ];

    fn present(&self, key: &str) -> bool {
        match key {
            "path" => self.path.is_some(),
            "address" => self.address.is_some(),
            "window" => self.window.is_some(),
            "reconnect_min_ms" => self.reconnect_min_ms.is_some(),
            "reconnect_max_ms" => self.reconnect_max_ms.is_some(),
            _ => false,
        }
    }

    /// Builds the transport, or lists every problem.
    fn build(&self) -> Result<TransportConfig, Vec<TransportProblem>> {
        let Some(kind) = self.kind else {
            return Err(vec![TransportProblem {
                key: "kind",
                missing: true,
                text: "one of \"serial\", \"tcp\" or \"sim\"".to_string(),
            }]);
        };
        let mut problems = Vec::new();
        for (key, kinds) in Self::KEYS {
            if self.present(key) && !kinds.contains(&kind) {
                let only: Vec<String> = kinds.iter().map(|k| format!("\"{}\"", k.name())).collect();
                problems.push(TransportProblem {
                    key,
                    missing: false,
                    text: format!(
                        "used only with kind = {}, not \"{}\"; remove the key",
                        only.join(" or "),
                        kind.name()
                    ),
                });
            }
        }
        let line = self.line.unwrap_or_default();
        let config = match kind {
            TransportKind::Serial => self
                .path
                .clone()
                .map(|path| TransportConfig::Serial { path, line }),
            TransportKind::Tcp => self.address.clone().map(|address| TransportConfig::Tcp {
                address,
                line,
                window: self.window.unwrap_or(TransportConfig::DEFAULT_WINDOW),
                reconnect_min_ms: self
                    .reconnect_min_ms
                    .unwrap_or(TransportConfig::DEFAULT_RECONNECT_MIN_MS),
                reconnect_max_ms: self
                    .reconnect_max_ms
                    .unwrap_or(TransportConfig::DEFAULT_RECONNECT_MAX_MS),
            }),
            TransportKind::Sim => Some(TransportConfig::Sim { line }),
        };
        match config {
            None => problems.push(match kind {
                TransportKind::Serial => TransportProblem {
                    key: "path",
                    missing: true,
                    text: "a serial transport names its device, e.g. path = \"/dev/ttyS0\""
                        .to_string(),
                },
                _ => TransportProblem {
                    key: "address",
                    missing: true,
                    text: "a tcp transport names its device server, e.g. \
                           address = \"192.0.2.10:4001\""
                        .to_string(),
                },
            }),
            Some(config) if problems.is_empty() => return Ok(config),
            Some(_) => {}
        }
        Err(problems)
    }
}

impl From<&TransportConfig> for RawTransport {
    fn from(t: &TransportConfig) -> Self {
        match t.clone() {
            TransportConfig::Serial { path, line } => RawTransport {
                kind: Some(TransportKind::Serial),
                path: Some(path),
                line: Some(line),
                ..RawTransport::default()
            },
            TransportConfig::Tcp {
                address,
                line,
                window,
                reconnect_min_ms,
                reconnect_max_ms,
            } => RawTransport {
                kind: Some(TransportKind::Tcp),
                address: Some(address),
                line: Some(line),
                window: Some(window),
                reconnect_min_ms: Some(reconnect_min_ms),
                reconnect_max_ms: Some(reconnect_max_ms),
                ..RawTransport::default()
            },
            TransportConfig::Sim { line } => RawTransport {
                kind: Some(TransportKind::Sim),
                line: Some(line),
                ..RawTransport::default()
            },
        }
    }
}

impl TryFrom<RawTransport> for TransportConfig {
    type Error = String;
    fn try_from(raw: RawTransport) -> Result<Self, String> {
        raw.build().map_err(|problems| {
            let texts: Vec<String> = problems
                .into_iter()
                .map(|p| {
                    if p.missing {
                        format!("missing `{}`: {}", p.key, p.text)
                    } else {
                        format!("`{}`: {}", p.key, p.text)
                    }
                })
                .collect();
            texts.join("; ")
        })
    }
}

impl TransportConfig {
    pub const DEFAULT_WINDOW: u32 = 256;
    pub const DEFAULT_RECONNECT_MIN_MS: u64 = 100;
    pub const DEFAULT_RECONNECT_MAX_MS: u64 = 5_000;

    /// The character framing of the line.
    pub fn line(&self) -> &LineSettings {
        match self {
            TransportConfig::Serial { line, .. }
            | TransportConfig::Tcp { line, .. }
            | TransportConfig::Sim { line } => line,
        }
    }

    /// `"serial"`, `"tcp"` or `"sim"`.
    pub fn kind(&self) -> TransportKind {
        match self {
            TransportConfig::Serial { .. } => TransportKind::Serial,
            TransportConfig::Tcp { .. } => TransportKind::Tcp,
            TransportConfig::Sim { .. } => TransportKind::Sim,
        }
    }

    /// One line for logs and `check-config`: "serial /dev/ttyS0, 19200 8N2".
    pub fn describe(&self) -> String {
        match self {
            TransportConfig::Serial { path, line } => format!("serial {path}, {line}"),
            TransportConfig::Tcp {
                address,
                line,
                window,
                reconnect_min_ms,
                reconnect_max_ms,
            } => format!(
                "tcp {address}, serial side {line}, window {window} bytes, \
                 reconnect every {reconnect_min_ms}..{reconnect_max_ms} ms"
            ),
            TransportConfig::Sim { line } => format!("sim, {line}"),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// FANUC machines
// ---------------------------------------------------------------------------------------------

/// Electrical interface of the remote buffer board (§2.1; parameter 5000#0).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Interface {
    /// RS-232-C: 50–19200 baud.
    #[serde(rename = "rs232c", alias = "rs-232-c")]
    Rs232c,
    /// RS-422: 50–86400 baud; above 38400 the reception clock must be synchronized (TT/RT).
    #[serde(rename = "rs422", alias = "rs-422")]
    Rs422,
}

impl Interface {
    pub fn name(self) -> &'static str {
        match self {
            Interface::Rs232c => "RS-232-C",
            Interface::Rs422 => "RS-422",
        }
    }
    /// Highest baud rate of the interface (§2.1).
    pub fn max_baud(self) -> u32 {
        match self {
            Interface::Rs232c => 19_200,
            Interface::Rs422 => 86_400,
        }
    }
}

/// The simulated remote-buffer board and CNC behind a `kind = "sim"` transport (`sim` table).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BoardSimConfig {
    /// Size of the board's receive buffer, bytes (the board has 8 KiB, §12.2).
    pub buffer_size: u32,
    /// Bytes per second the CNC takes out of the buffer while it runs a program.
    pub consume_rate: u32,
    /// Axes of one G05 binary block (parameter 7635, §9).
    pub axes: u8,
}

impl BoardSimConfig {
    pub const DEFAULT: BoardSimConfig = BoardSimConfig {
        buffer_size: 8192,
        consume_rate: 2000,
        axes: 3,
    };
}

impl Default for BoardSimConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// One FANUC CNC behind a remote buffer (`[[machines]]`).
///
/// Optional settings are kept as written (`None` = not in the file) so that validation can
/// tell a key that does not belong to the protocol; the `effective_*` methods give the value
/// in force.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct MachineConfig {
    /// Machine id, `[A-Za-z0-9_-]+`, unique in the cell (a key chunk).
    pub name: String,
    /// Protocol selected on the CNC by parameter 5074 / 5084 (§2.2).
    pub protocol: Protocol,
    /// Code of the control part (parameter 5000#2, §10.2).
    pub code: CodeSystem,
    /// Protocol A family: message end code (parameter 5000#3, §10.2). Default CR.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub end_code: Option<EndCode>,
    /// Protocol B family: the board sends SYN on CNC reset and NAK on a CNC alarm
    /// (parameter 5000#3 / 5003#3, §6.4). Default off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub notify_alarm_reset: Option<bool>,
    /// Expansion Protocol A packet length n: packets carry 256·n bytes (§5.2). Default 1 for
    /// Expansion A, 0 (plain Protocol A) otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub packet_n: Option<u8>,
    /// Electrical interface (§2.1). Default RS-422 above 19200 baud or for the expansion
    /// protocols, RS-232-C otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub interface: Option<Interface>,
    /// §4.5 parameters; `None` keeps the value on turning on power.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nb: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub no: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ne: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tp: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub to: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ti: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tx: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tw: Option<u16>,
    /// Protocol A family: read the DI image (RDI, §4.4.1) every this many ms and publish it.
    /// `None`: DI is read only when asked.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub di_poll_ms: Option<u32>,
    pub transport: TransportConfig,
    /// Board simulation settings; only with `transport.kind = "sim"`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sim: Option<BoardSimConfig>,
}

impl MachineConfig {
    /// The §4.5 parameters: the file's values over the power-on values.
    pub fn params(&self) -> Params {
        params_of([
            self.nb, self.no, self.ne, self.tp, self.to, self.ti, self.tx, self.tw,
        ])
    }

    pub fn effective_end_code(&self) -> EndCode {
        self.end_code.unwrap_or_default()
    }

    pub fn effective_notify_alarm_reset(&self) -> bool {
        self.notify_alarm_reset.unwrap_or(false)
    }

    /// n of §5.2: 1, 2 or 4 for Expansion Protocol A, 0 for every other protocol.
    pub fn effective_packet_n(&self) -> u8 {
        default_packet_n(self.protocol, self.packet_n)
    }

    pub fn effective_interface(&self) -> Interface {
        default_interface(self.protocol, self.transport.line().baud, self.interface)
    }

    /// Board simulation settings in force (defaults when the `sim` table is absent).
    pub fn board_sim(&self) -> BoardSimConfig {
        self.sim.unwrap_or_default()
    }

    /// The value of parameter 5000#3 this configuration expects on the CNC (§10.2): the end
    /// code (ETX = 1) for the A family, reset/alarm notification for the B family.
    pub fn param_5000_bit3(&self) -> u8 {
        if self.protocol.is_a_family() {
            u8::from(self.effective_end_code() == EndCode::Etx)
        } else {
            u8::from(self.effective_notify_alarm_reset())
        }
    }
}

fn params_of(v: [Option<u16>; 8]) -> Params {
    let p = Params::POWER_ON;
    let [nb, no, ne, tp, to, ti, tx, tw] = v;
    Params {
        nb: nb.unwrap_or(p.nb),
        no: no.unwrap_or(p.no),
        ne: ne.unwrap_or(p.ne),
        tp: tp.unwrap_or(p.tp),
        to: to.unwrap_or(p.to),
        ti: ti.unwrap_or(p.ti),
        tx: tx.unwrap_or(p.tx),
        tw: tw.unwrap_or(p.tw),
    }
}

fn default_packet_n(protocol: Protocol, n: Option<u8>) -> u8 {
    match protocol {
        Protocol::ExpansionA => n.unwrap_or(1),
        _ => 0,
    }
}

fn default_interface(protocol: Protocol, baud: u32, interface: Option<Interface>) -> Interface {
    interface.unwrap_or(
        if baud > 19_200 || matches!(protocol, Protocol::ExpansionA | Protocol::ExpansionB) {
            Interface::Rs422
        } else {
            Interface::Rs232c
        },
    )
}

fn protocol_title(p: Protocol) -> &'static str {
    match p {
        Protocol::A => "Protocol A",
        Protocol::ExpansionA => "Expansion Protocol A",
        Protocol::B => "Protocol B",
        Protocol::ExpansionB => "Expansion Protocol B",
    }
}

// ---------------------------------------------------------------------------------------------
// Fuji PLCs
// ---------------------------------------------------------------------------------------------

/// Start code of a text (FFU120B §4-3 item 16).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub enum PlcStartCode {
    #[serde(rename = "none")]
    None,
    #[serde(rename = "stx")]
    Stx,
    /// `:` — the manual's usual choice.
    #[default]
    #[serde(rename = ":", alias = "colon")]
    Colon,
    #[serde(rename = "::", alias = "double-colon")]
    DoubleColon,
    /// One byte given in `start_codes`.
    #[serde(rename = "set1")]
    Set1,
    /// Two bytes given in `start_codes`.
    #[serde(rename = "set2")]
    Set2,
}

impl PlcStartCode {
    /// The bytes of the code, `custom` being `start_codes` for Set 1 / Set 2.
    pub fn bytes(self, custom: &[u8]) -> &[u8] {
        match self {
            PlcStartCode::None => &[],
            PlcStartCode::Stx => &[0x02],
            PlcStartCode::Colon => b":",
            PlcStartCode::DoubleColon => b"::",
            PlcStartCode::Set1 | PlcStartCode::Set2 => custom,
        }
    }
}

/// End code of a text (FFU120B §4-3 item 17). "No end code" is an initial error (§4-7 F5),
/// so there is no `none`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum PlcEndCode {
    Etx,
    /// CR — the manual's usual choice.
    #[default]
    Cr,
    Lf,
    CrLf,
    DleEtx,
    /// One byte given in `end_codes`.
    Set1,
    /// Two bytes given in `end_codes`.
    Set2,
}

impl PlcEndCode {
    /// The bytes of the code, `custom` being `end_codes` for Set 1 / Set 2.
    pub fn bytes(self, custom: &[u8]) -> &[u8] {
        match self {
            PlcEndCode::Etx => &[0x03],
            PlcEndCode::Cr => b"\r",
            PlcEndCode::Lf => b"\n",
            PlcEndCode::CrLf => b"\r\n",
            PlcEndCode::DleEtx => &[0x10, 0x03],
            PlcEndCode::Set1 | PlcEndCode::Set2 => custom,
        }
    }
}

/// Whether a BCC is sent, and its byte order (FFU120B §4-3 item 20).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum BccKind {
    #[default]
    None,
    /// High byte (character) of the BCC first.
    Set1,
    /// Low byte (character) of the BCC first.
    Set2,
}

/// Location of the BCC and the range it is computed over (FFU120B §4-3 item 21). A range
/// that contains the end code puts the BCC after the end code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub enum BccRange {
    #[default]
    #[serde(rename = "text")]
    Text,
    #[serde(rename = "text+end")]
    TextEnd,
    #[serde(rename = "start+text")]
    StartText,
    #[serde(rename = "start+text+end")]
    StartTextEnd,
}

impl BccRange {
    /// The range contains the end code, so the BCC follows it.
    pub fn includes_end(self) -> bool {
        matches!(self, BccRange::TextEnd | BccRange::StartTextEnd)
    }
    pub fn includes_start(self) -> bool {
        matches!(self, BccRange::StartText | BccRange::StartTextEnd)
    }
}

/// How the BCC is calculated (FFU120B §4-3 item 22).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub enum BccCalc {
    /// Sum of the bytes, mod 256.
    #[default]
    #[serde(rename = "add")]
    Add,
    /// Sum of the bytes XOR FFh.
    #[serde(rename = "add-invert")]
    AddInvert,
    /// XOR of the bytes.
    #[serde(rename = "eor")]
    Eor,
    /// CRC-16, x¹⁶ + x¹⁵ + x² + 1.
    #[serde(rename = "crc16", alias = "crc-16")]
    Crc16,
}

/// How the BCC travels (FFU120B §4-3 item 23).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum BccCode {
    /// As hex characters of the transmission code.
    #[default]
    TransmissionCode,
    /// As the raw result byte(s).
    Binary,
}

/// One Fuji MICREX-F PLC reached through an FFU120B general interface module (`[[plcs]]`),
/// in command-set mode 1, 2 or 3. The settings mirror the module's initial file (§4-3): both
/// ends must agree on them.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct PlcConfig {
    /// PLC id, `[A-Za-z0-9_-]+`, unique among the cell's machines and PLCs.
    pub name: String,
    /// Operation mode set on the module's MODE dial: 1 (1:1), 2 or 3 (1:N, RS-485) (§1-3, §4-2).
    pub mode: u8,
    /// RS-485 station numbers (RSNO, BCD 00–99) of the modules this link polls; mode 1 uses 00.
    pub stations: Vec<u8>,
    pub start_code: PlcStartCode,
    /// The bytes of `start_code = "set1"` (one) or `"set2"` (two) (§4-3 item 18).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub start_codes: Vec<u8>,
    pub end_code: PlcEndCode,
    /// The bytes of `end_code = "set1"` (one) or `"set2"` (two) (§4-3 item 19).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub end_codes: Vec<u8>,
    pub bcc: BccKind,
    pub bcc_range: BccRange,
    pub bcc_calc: BccCalc,
    pub bcc_code: BccCode,
    /// Code transposition: every byte travels as two hex characters (§4-3 item 14).
    pub transposition: bool,
    /// How long the host waits for a reply after its request has been sent, ms.
    pub timeout_ms: u32,
    pub transport: TransportConfig,
}

impl PlcConfig {
    pub const DEFAULT_TIMEOUT_MS: u32 = 2000;
}

// ---------------------------------------------------------------------------------------------
// Errors
// ---------------------------------------------------------------------------------------------

/// One thing wrong with a cell file.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{origin}: cannot read the cell file: {reason}")]
    Read { origin: String, reason: String },
    /// TOML syntax, an unknown key or a value of the wrong type; `message` is the toml
    /// crate's, which names the line and the key.
    #[error("{origin}: {message}")]
    Parse { origin: String, message: String },
    /// A required key is absent.
    #[error("{path}: missing; {hint}")]
    Missing { path: String, hint: String },
    /// A §4.5 remote-buffer parameter outside its range; `path` is the machine's
    /// (`machines.mill-1`), `range` names the parameter.
    #[error("{path}.{range}")]
    Param {
        path: String,
        range: ParamRangeError,
    },
    /// A value that is not allowed, alone or with the other settings.
    #[error("{path} = {value}: {reason}{}", cite(.section))]
    Invalid {
        path: String,
        value: String,
        reason: String,
        section: &'static str,
    },
    /// A key that has no meaning with the other settings (e.g. an end code for Protocol B).
    #[error("{path}: {reason}{}", cite(.section))]
    NotApplicable {
        path: String,
        reason: String,
        section: &'static str,
    },
    /// Two links with the same name.
    #[error(
        "{path}: {first} and {second} are both named {name:?}; names must be unique in a cell \
         (each becomes a key chunk)"
    )]
    Duplicate {
        path: String,
        name: String,
        first: String,
        second: String,
    },
}

fn cite(section: &str) -> String {
    if section.is_empty() {
        String::new()
    } else {
        format!(" ({section})")
    }
}

impl ConfigError {
    /// The key path the error is about (`machines.mill-1.tw`), if it is about one.
    pub fn path(&self) -> Option<String> {
        match self {
            ConfigError::Read { .. } | ConfigError::Parse { .. } => None,
            ConfigError::Param { path, range } => Some(format!("{path}.{}", range.name)),
            ConfigError::Missing { path, .. }
            | ConfigError::Invalid { path, .. }
            | ConfigError::NotApplicable { path, .. }
            | ConfigError::Duplicate { path, .. } => Some(path.clone()),
        }
    }
}

/// Every error found in a cell file. Displays one error per line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfigErrors(pub Vec<ConfigError>);

impl ConfigErrors {
    pub fn len(&self) -> usize {
        self.0.len()
    }
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
    pub fn iter(&self) -> std::slice::Iter<'_, ConfigError> {
        self.0.iter()
    }
}

impl fmt::Display for ConfigErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, e) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_char('\n')?;
            }
            write!(f, "{e}")?;
        }
        Ok(())
    }
}

impl std::error::Error for ConfigErrors {}

impl From<ConfigError> for ConfigErrors {
    fn from(e: ConfigError) -> Self {
        ConfigErrors(vec![e])
    }
}

impl<'a> IntoIterator for &'a ConfigErrors {
    type Item = &'a ConfigError;
    type IntoIter = std::slice::Iter<'a, ConfigError>;
    fn into_iter(self) -> Self::IntoIter {
        self.0.iter()
    }
}

// ---------------------------------------------------------------------------------------------
// Reading
// ---------------------------------------------------------------------------------------------

const DEFAULT_CELL: &str = include_str!("default_cell.toml");

impl CellConfig {
    /// Parses and validates a cell file. `origin` names it in parse errors (a file name).
    pub fn from_toml_str(text: &str, origin: &str) -> Result<CellConfig, ConfigErrors> {
        let raw: RawCell = toml::from_str(text).map_err(|e| ConfigError::Parse {
            origin: origin.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        let errors = check(&raw);
        if !errors.is_empty() {
            return Err(ConfigErrors(errors));
        }
        raw.into_config()
    }

    /// Reads, parses and validates the cell file at `path`.
    pub fn load(path: &Path) -> Result<CellConfig, ConfigErrors> {
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| ConfigError::Read {
            origin: origin.clone(),
            reason: e.to_string(),
        })?;
        Self::from_toml_str(&text, &origin)
    }

    /// The cell built into the binary: cell "demo" with three simulated CNCs on loopback.
    pub fn embedded_default() -> CellConfig {
        // The embedded file is part of the program, not input: `embedded_default_is_valid`
        // proves it valid.
        Self::from_toml_str(DEFAULT_CELL, "embedded default cell")
            .expect("the embedded default cell file is valid")
    }

    /// The text of the embedded default cell file.
    pub fn embedded_default_text() -> &'static str {
        DEFAULT_CELL
    }

    /// Checks every rule and reports every broken one.
    pub fn validate(&self) -> Result<(), ConfigErrors> {
        let errors = check(&RawCell::from(self.clone()));
        if errors.is_empty() {
            Ok(())
        } else {
            Err(ConfigErrors(errors))
        }
    }

    /// The configuration as TOML, in a form [`CellConfig::from_toml_str`] reads back.
    pub fn to_toml_string(&self) -> Result<String, toml::ser::Error> {
        toml::to_string(self)
    }

    /// The machine or PLC named `name`, if any.
    pub fn machine(&self, name: &str) -> Option<&MachineConfig> {
        self.machines.iter().find(|m| m.name == name)
    }

    pub fn plc(&self, name: &str) -> Option<&PlcConfig> {
        self.plcs.iter().find(|p| p.name == name)
    }

    /// A human-readable view of the validated configuration, with the values in force
    /// (defaults filled in) and the CNC parameter values they imply.
    pub fn summary(&self) -> String {
        let mut s = String::new();
        let _ = self.write_summary(&mut s);
        s
    }

    fn write_summary(&self, s: &mut String) -> fmt::Result {
        writeln!(s, "cell {}", self.cell)?;
        let b = &self.bus;
        let list = |v: &[String]| {
            if v.is_empty() {
                "none".to_string()
            } else {
                v.join(", ")
            }
        };
        writeln!(
            s,
            "bus: {} mode, keys under {}/{}, listen {}, connect {}, multicast scouting {}",
            plain_name(&b.mode),
            b.prefix,
            self.cell,
            list(&b.listen),
            list(&b.connect),
            on_off(b.multicast_scouting),
        )?;
        if let Some(z) = &b.zenoh_config {
            writeln!(s, "  zenoh config file {}", z.display())?;
        }
        let t = &self.telemetry;
        writeln!(
            s,
            "telemetry: {} logs, filter {:?}, OTLP export {}",
            plain_name(&t.log_format),
            t.log_filter,
            t.otlp_endpoint.as_deref().map_or_else(
                || "off".to_string(),
                |e| format!("to {e} as {:?}", t.service_name)
            ),
        )?;
        writeln!(
            s,
            "programs: in {}, at most {} each; punched programs {}; remote requests {}",
            self.programs.dir.display(),
            show_size(self.programs.max_size),
            if self.programs.store_punched {
                "stored"
            } else {
                "not stored"
            },
            if self.programs.requests.is_empty() {
                "off".to_string()
            } else {
                self.programs.requests.join(" ")
            }
        )?;
        writeln!(s, "machines: {}", self.machines.len())?;
        for m in &self.machines {
            let p = m.protocol;
            write!(s, "  {}: {}", m.name, protocol_title(p))?;
            if p == Protocol::ExpansionA {
                let n = m.effective_packet_n();
                write!(s, " n = {n} ({}-byte packets)", 256 * u32::from(n))?;
            }
            writeln!(
                s,
                ", {} code (5000#2 = {}), {}",
                match m.code {
                    CodeSystem::Ascii => "ASCII",
                    CodeSystem::Iso => "ISO",
                },
                m.code.param_5000_bit2(p),
                m.effective_interface().name(),
            )?;
            if p.is_a_family() {
                writeln!(
                    s,
                    "    end code {} (5000#3 = {})",
                    match m.effective_end_code() {
                        EndCode::Cr => "CR",
                        EndCode::Etx => "ETX",
                    },
                    m.param_5000_bit3()
                )?;
            } else {
                writeln!(
                    s,
                    "    reset/alarm notification {} (5000#3 = {})",
                    on_off(m.effective_notify_alarm_reset()),
                    m.param_5000_bit3()
                )?;
            }
            writeln!(s, "    transport: {}", m.transport.describe())?;
            if let TransportConfig::Sim { .. } = m.transport {
                let b = m.board_sim();
                writeln!(
                    s,
                    "    simulated board: buffer {} bytes, CNC takes {} bytes/s, {} axes",
                    b.buffer_size, b.consume_rate, b.axes
                )?;
            }
            // SET and the §4.5 timers exist in the Protocol A family only.
            if p.is_a_family() {
                writeln!(s, "    parameters: {}", m.params())?;
            }
        }
        writeln!(s, "plcs: {}", self.plcs.len())?;
        for p in &self.plcs {
            let stations: Vec<String> = p.stations.iter().map(|n| format!("{n:02}")).collect();
            writeln!(
                s,
                "  {}: FFU120B mode {}, stations {}",
                p.name,
                p.mode,
                stations.join(", ")
            )?;
            writeln!(
                s,
                "    start code {}, end code {}, code transposition {}, reply time-out {} ms",
                show_bytes(p.start_code.bytes(&p.start_codes)),
                show_bytes(p.end_code.bytes(&p.end_codes)),
                on_off(p.transposition),
                p.timeout_ms
            )?;
            if p.bcc == BccKind::None {
                writeln!(s, "    BCC none")?;
            } else {
                writeln!(
                    s,
                    "    BCC {} ({}, {}), over {}, as {}",
                    plain_name(&p.bcc_calc),
                    plain_name(&p.bcc),
                    if p.bcc == BccKind::Set1 {
                        "high byte first"
                    } else {
                        "low byte first"
                    },
                    plain_name(&p.bcc_range),
                    plain_name(&p.bcc_code)
                )?;
            }
            writeln!(s, "    transport: {}", p.transport.describe())?;
        }
        Ok(())
    }
}

/// The name of a unit enum value as the file spells it, without quotes.
fn plain_name<T: Serialize>(v: &T) -> String {
    match toml::Value::try_from(v) {
        Ok(toml::Value::String(s)) => s,
        Ok(other) => other.to_string(),
        Err(_) => "?".to_string(),
    }
}

fn show_size(bytes: u64) -> String {
    const MIB: u64 = 1024 * 1024;
    if bytes >= MIB && bytes % MIB == 0 {
        format!("{} MiB", bytes / MIB)
    } else if bytes >= 1024 && bytes % 1024 == 0 {
        format!("{} KiB", bytes / 1024)
    } else {
        format!("{bytes} bytes")
    }
}

fn on_off(b: bool) -> &'static str {
    if b { "on" } else { "off" }
}

fn show_bytes(b: &[u8]) -> String {
    if b.is_empty() {
        return "none".to_string();
    }
    let names: Vec<String> = b
        .iter()
        .map(|&c| match c {
            0x02 => "STX".to_string(),
            0x03 => "ETX".to_string(),
            0x0A => "LF".to_string(),
            0x0D => "CR".to_string(),
            0x10 => "DLE".to_string(),
            0x21..=0x7E => format!("'{}'", char::from(c)),
            _ => format!("{c:02X}h"),
        })
        .collect();
    names.join(" ")
}

// ---------------------------------------------------------------------------------------------
// The file as written: required keys may be absent, so that validation can name every missing
// one together with every other error.
// ---------------------------------------------------------------------------------------------

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCell {
    cell: Option<String>,
    #[serde(default)]
    bus: BusConfig,
    #[serde(default)]
    telemetry: TelemetryConfig,
    #[serde(default)]
    programs: ProgramsConfig,
    #[serde(default)]
    machines: Vec<RawMachine>,
    #[serde(default)]
    plcs: Vec<RawPlc>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMachine {
    name: Option<String>,
    protocol: Option<Protocol>,
    #[serde(default)]
    code: CodeSystem,
    end_code: Option<EndCode>,
    notify_alarm_reset: Option<bool>,
    packet_n: Option<u8>,
    interface: Option<Interface>,
    nb: Option<u16>,
    no: Option<u16>,
    ne: Option<u16>,
    tp: Option<u16>,
    to: Option<u16>,
    ti: Option<u16>,
    tx: Option<u16>,
    tw: Option<u16>,
    di_poll_ms: Option<u32>,
    transport: Option<RawTransport>,
    sim: Option<BoardSimConfig>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPlc {
    name: Option<String>,
    #[serde(default = "default_mode")]
    mode: u8,
    #[serde(default = "default_stations")]
    stations: Vec<u8>,
    #[serde(default)]
    start_code: PlcStartCode,
    #[serde(default)]
    start_codes: Vec<u8>,
    #[serde(default)]
    end_code: PlcEndCode,
    #[serde(default)]
    end_codes: Vec<u8>,
    #[serde(default)]
    bcc: BccKind,
    #[serde(default)]
    bcc_range: BccRange,
    #[serde(default)]
    bcc_calc: BccCalc,
    #[serde(default)]
    bcc_code: BccCode,
    #[serde(default = "default_true")]
    transposition: bool,
    #[serde(default = "default_timeout_ms")]
    timeout_ms: u32,
    transport: Option<RawTransport>,
}

fn default_mode() -> u8 {
    1
}
fn default_stations() -> Vec<u8> {
    vec![0]
}
fn default_true() -> bool {
    true
}
fn default_timeout_ms() -> u32 {
    PlcConfig::DEFAULT_TIMEOUT_MS
}

impl From<CellConfig> for RawCell {
    fn from(c: CellConfig) -> Self {
        RawCell {
            cell: Some(c.cell),
            bus: c.bus,
            telemetry: c.telemetry,
            programs: c.programs,
            machines: c
                .machines
                .into_iter()
                .map(|m| RawMachine {
                    name: Some(m.name),
                    protocol: Some(m.protocol),
                    code: m.code,
                    end_code: m.end_code,
                    notify_alarm_reset: m.notify_alarm_reset,
                    packet_n: m.packet_n,
                    interface: m.interface,
                    nb: m.nb,
                    no: m.no,
                    ne: m.ne,
                    tp: m.tp,
                    to: m.to,
                    ti: m.ti,
                    tx: m.tx,
                    tw: m.tw,
                    di_poll_ms: m.di_poll_ms,
                    transport: Some(RawTransport::from(&m.transport)),
                    sim: m.sim,
                })
                .collect(),
            plcs: c
                .plcs
                .into_iter()
                .map(|p| RawPlc {
                    name: Some(p.name),
                    mode: p.mode,
                    stations: p.stations,
                    start_code: p.start_code,
                    start_codes: p.start_codes,
                    end_code: p.end_code,
                    end_codes: p.end_codes,
                    bcc: p.bcc,
                    bcc_range: p.bcc_range,
                    bcc_calc: p.bcc_calc,
                    bcc_code: p.bcc_code,
                    transposition: p.transposition,
                    timeout_ms: p.timeout_ms,
                    transport: Some(RawTransport::from(&p.transport)),
                })
                .collect(),
        }
    }
}

/// The transport of link `label`, or the errors that keep it from being built.
fn built_transport(
    raw: Option<&RawTransport>,
    label: &str,
) -> Result<TransportConfig, ConfigErrors> {
    let mut c = Checker { errors: Vec::new() };
    match transport_of(&mut c, label, raw) {
        Some(t) => Ok(t),
        None => Err(ConfigErrors(c.errors)),
    }
}

impl RawCell {
    /// Builds the typed configuration; only called once `check` found nothing, so every
    /// required key is there. Should one still be absent, it is reported, not unwrapped.
    fn into_config(self) -> Result<CellConfig, ConfigErrors> {
        let missing = |path: String| ConfigError::Missing {
            path,
            hint: "required".to_string(),
        };
        let cell = self.cell.ok_or_else(|| missing("cell".to_string()))?;
        let mut machines = Vec::with_capacity(self.machines.len());
        for (i, m) in self.machines.into_iter().enumerate() {
            let label = format!("machines[{}]", i + 1);
            machines.push(MachineConfig {
                name: m.name.ok_or_else(|| missing(format!("{label}.name")))?,
                protocol: m
                    .protocol
                    .ok_or_else(|| missing(format!("{label}.protocol")))?,
                code: m.code,
                end_code: m.end_code,
                notify_alarm_reset: m.notify_alarm_reset,
                packet_n: m.packet_n,
                interface: m.interface,
                nb: m.nb,
                no: m.no,
                ne: m.ne,
                tp: m.tp,
                to: m.to,
                ti: m.ti,
                tx: m.tx,
                tw: m.tw,
                di_poll_ms: m.di_poll_ms,
                transport: built_transport(m.transport.as_ref(), &label)?,
                sim: m.sim,
            });
        }
        let mut plcs = Vec::with_capacity(self.plcs.len());
        for (i, p) in self.plcs.into_iter().enumerate() {
            let label = format!("plcs[{}]", i + 1);
            plcs.push(PlcConfig {
                name: p.name.ok_or_else(|| missing(format!("{label}.name")))?,
                mode: p.mode,
                stations: p.stations,
                start_code: p.start_code,
                start_codes: p.start_codes,
                end_code: p.end_code,
                end_codes: p.end_codes,
                bcc: p.bcc,
                bcc_range: p.bcc_range,
                bcc_calc: p.bcc_calc,
                bcc_code: p.bcc_code,
                transposition: p.transposition,
                timeout_ms: p.timeout_ms,
                transport: built_transport(p.transport.as_ref(), &label)?,
            });
        }
        Ok(CellConfig {
            cell,
            bus: self.bus,
            telemetry: self.telemetry,
            programs: self.programs,
            machines,
            plcs,
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Validation
// ---------------------------------------------------------------------------------------------

/// Baud rates of parameters 5073 (RS-422, settings 1–15) and 5083 (RS-232-C, 1–12) (§10.2).
pub const FANUC_BAUD_RATES: [u32; 15] = [
    50, 100, 110, 150, 200, 300, 600, 1200, 2400, 4800, 9600, 19200, 38400, 76800, 86400,
];

/// Baud rates of the FFU120B (FFU120B §3-2, §4-3 item 4).
pub const FUJI_BAUD_RATES: [u32; 7] = [300, 600, 1200, 2400, 4800, 9600, 19200];

/// Most modules on one RS-485 line (FFU120B §2-2 note 1).
pub const FUJI_MAX_STATIONS: usize = 31;

fn list_u32(v: &[u32]) -> String {
    let s: Vec<String> = v.iter().map(u32::to_string).collect();
    s.join(", ")
}

fn q(s: &str) -> String {
    format!("{s:?}")
}

/// The serde name of a unit enum value, quoted as in the file (`"expansion-a"`).
fn toml_name<T: Serialize>(v: &T) -> String {
    q(&plain_name(v))
}

fn valid_name(s: &str) -> bool {
    !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

struct Checker {
    errors: Vec<ConfigError>,
}

impl Checker {
    fn invalid(&mut self, path: String, value: String, reason: String, section: &'static str) {
        self.errors.push(ConfigError::Invalid {
            path,
            value,
            reason,
            section,
        });
    }

    fn not_applicable(&mut self, path: String, reason: String, section: &'static str) {
        self.errors.push(ConfigError::NotApplicable {
            path,
            reason,
            section,
        });
    }

    fn missing(&mut self, path: String, hint: &str) {
        self.errors.push(ConfigError::Missing {
            path,
            hint: hint.to_string(),
        });
    }

    /// `value` within `min..=max`, else an error stating the range and `why`.
    fn range<T: PartialOrd + fmt::Display>(
        &mut self,
        path: impl FnOnce() -> String,
        value: T,
        min: T,
        max: T,
        why: &str,
        section: &'static str,
    ) {
        if value < min || value > max {
            self.invalid(
                path(),
                value.to_string(),
                format!("must be within {min}..={max}{why}"),
                section,
            );
        }
    }
}

fn check(raw: &RawCell) -> Vec<ConfigError> {
    let mut c = Checker { errors: Vec::new() };
    match &raw.cell {
        None => c.missing(
            "cell".to_string(),
            "name the cell, e.g. cell = \"line-3\" (it becomes the key chunk after the bus prefix)",
        ),
        Some(name) => check_name(&mut c, "cell".to_string(), name),
    }
    check_bus(&mut c, &raw.bus);
    check_telemetry(&mut c, &raw.telemetry);
    check_programs(&mut c, &raw.programs);

    // Names are unique over machines and PLCs together: both are links of the cell.
    let mut seen: HashMap<&str, String> = HashMap::new();
    let mut labels = Vec::new();
    for (i, m) in raw.machines.iter().enumerate() {
        labels.push(link_label(
            &mut c,
            &mut seen,
            "machines",
            i,
            m.name.as_deref(),
        ));
    }
    for (i, p) in raw.plcs.iter().enumerate() {
        labels.push(link_label(&mut c, &mut seen, "plcs", i, p.name.as_deref()));
    }
    let (machine_labels, plc_labels) = labels.split_at(raw.machines.len());
    for (m, label) in raw.machines.iter().zip(machine_labels) {
        check_machine(&mut c, label, m);
    }
    for (p, label) in raw.plcs.iter().zip(plc_labels) {
        check_plc(&mut c, label, p);
    }
    c.errors
}

/// Checks a link's name and returns the path prefix its errors use: `machines.mill-1`, or
/// `machines[2]` (counting from 1) when the name is absent, unusable or taken.
fn link_label<'a>(
    c: &mut Checker,
    seen: &mut HashMap<&'a str, String>,
    table: &str,
    index: usize,
    name: Option<&'a str>,
) -> String {
    let position = format!("[[{table}]] #{}", index + 1);
    let fallback = format!("{table}[{}]", index + 1);
    let Some(name) = name else {
        c.missing(
            format!("{fallback}.name"),
            &format!("every {position} table needs a name"),
        );
        return fallback;
    };
    check_name(c, format!("{fallback}.name"), name);
    if !valid_name(name) {
        return fallback;
    }
    let label = format!("{table}.{name}");
    if let Some(first) = seen.get(name) {
        c.errors.push(ConfigError::Duplicate {
            path: label,
            name: name.to_string(),
            first: first.clone(),
            second: position,
        });
        // The second one's own errors are told apart by position.
        return fallback;
    }
    seen.insert(name, position);
    label
}

fn check_name(c: &mut Checker, path: String, name: &str) {
    if !valid_name(name) {
        c.invalid(
            path,
            q(name),
            "use only letters, digits, '_' and '-', at least one (the name becomes a Zenoh key \
             chunk)"
                .to_string(),
            "",
        );
    }
}

fn check_bus(c: &mut Checker, bus: &BusConfig) {
    let prefix = &bus.prefix;
    if prefix.is_empty()
        || prefix.split('/').any(|chunk| {
            chunk.is_empty() || chunk.contains(['*', '$', '?', '#']) || chunk.trim() != chunk
        })
    {
        c.invalid(
            "bus.prefix".to_string(),
            q(prefix),
            "must be one or more '/'-separated key chunks, none empty, without wildcards \
             ('*', '$', '?', '#') or surrounding spaces"
                .to_string(),
            "",
        );
    }
    for (key, list) in [("listen", &bus.listen), ("connect", &bus.connect)] {
        for (i, ep) in list.iter().enumerate() {
            let ok = ep
                .split_once('/')
                .is_some_and(|(proto, addr)| !proto.is_empty() && !addr.is_empty());
            if !ok {
                c.invalid(
                    format!("bus.{key}[{}]", i + 1),
                    q(ep),
                    "a Zenoh endpoint is PROTOCOL/ADDRESS, e.g. \"tcp/127.0.0.1:7447\"".to_string(),
                    "",
                );
            }
        }
    }
}

fn check_telemetry(c: &mut Checker, t: &TelemetryConfig) {
    if let Err(e) = tracing_subscriber::EnvFilter::try_new(&t.log_filter) {
        c.invalid(
            "telemetry.log_filter".to_string(),
            q(&t.log_filter),
            format!("not a log filter directive like \"info,cellgate=debug\": {e}"),
            "",
        );
    }
    if let Some(ep) = &t.otlp_endpoint
        && !(ep.starts_with("http://") || ep.starts_with("https://"))
    {
        c.invalid(
            "telemetry.otlp_endpoint".to_string(),
            q(ep),
            "an OTLP/gRPC endpoint is an http:// or https:// URL, e.g. \"http://127.0.0.1:4317\""
                .to_string(),
            "",
        );
    }
    if t.service_name.trim().is_empty() {
        c.invalid(
            "telemetry.service_name".to_string(),
            q(&t.service_name),
            "must not be empty".to_string(),
            "",
        );
    }
}

fn check_programs(c: &mut Checker, p: &ProgramsConfig) {
    if p.dir.as_os_str().is_empty() {
        c.invalid(
            "programs.dir".to_string(),
            "\"\"".to_string(),
            "must name a directory".to_string(),
            "",
        );
    }
    if p.max_size == 0 {
        c.invalid(
            "programs.max_size".to_string(),
            "0".to_string(),
            "must be at least 1 byte".to_string(),
            "",
        );
    }
    for (i, pattern) in p.requests.iter().enumerate() {
        if let Err(e) = crate::jobs::punch::RequestPatterns::parse(std::slice::from_ref(pattern)) {
            let crate::jobs::punch::PatternError::Invalid { reason, .. } = e;
            c.invalid(
                format!("programs.requests[{i}]"),
                q(pattern),
                reason.to_string(),
                "",
            );
        }
    }
}

/// Checks common to every transport: the path, the address, the window and the backoff.
fn check_transport(c: &mut Checker, path: &str, t: &TransportConfig) {
    match t {
        TransportConfig::Serial { path: dev, .. } => {
            if dev.trim().is_empty() {
                c.invalid(
                    format!("{path}.path"),
                    q(dev),
                    "must name the serial device, e.g. \"/dev/ttyS0\"".to_string(),
                    "",
                );
            }
        }
        TransportConfig::Tcp {
            address,
            window,
            reconnect_min_ms,
            reconnect_max_ms,
            ..
        } => {
            if !valid_address(address) {
                c.invalid(
                    format!("{path}.address"),
                    q(address),
                    "must be host:port of the device server, e.g. \"192.0.2.10:4001\", port \
                     1..=65535"
                        .to_string(),
                    "",
                );
            }
            c.range(
                || format!("{path}.window"),
                *window,
                1,
                65_536,
                " bytes",
                "",
            );
            c.range(
                || format!("{path}.reconnect_min_ms"),
                *reconnect_min_ms,
                1,
                3_600_000,
                "",
                "",
            );
            c.range(
                || format!("{path}.reconnect_max_ms"),
                *reconnect_max_ms,
                (*reconnect_min_ms).max(1),
                3_600_000,
                " (reconnect_min_ms or more)",
                "",
            );
        }
        TransportConfig::Sim { .. } => {}
    }
}

fn valid_address(a: &str) -> bool {
    if a.parse::<std::net::SocketAddr>().is_ok() {
        return true;
    }
    let Some((host, port)) = a.rsplit_once(':') else {
        return false;
    };
    !host.is_empty()
        && !host.contains([':', '/', ' ', '[', ']'])
        && port.parse::<u16>().is_ok_and(|p| p != 0)
}

fn check_machine(c: &mut Checker, label: &str, m: &RawMachine) {
    let Some(protocol) = m.protocol else {
        c.missing(
            format!("{label}.protocol"),
            "one of \"a\", \"expansion-a\", \"b\", \"expansion-b\" as set on the CNC by \
             parameter 5074 / 5084 (§2.2, §10.2)",
        );
        // Without the protocol, only the protocol-independent checks can run.
        check_params(c, label, m);
        if let Some(t) = transport_of(c, label, m.transport.as_ref()) {
            check_transport(c, &format!("{label}.transport"), &t);
        }
        return;
    };
    let title = protocol_title(protocol);

    // Protocol A family: end code; Protocol B family: reset/alarm notification (5000#3).
    if let Some(end) = m.end_code
        && !protocol.is_a_family()
    {
        c.not_applicable(
            format!("{label}.end_code"),
            format!(
                "{title} has no message end code (end_code = {}): only Protocol A and \
                 Expansion Protocol A messages end with CR or ETX; remove the key",
                toml_name(&end)
            ),
            "§10.2, parameter 5000#3",
        );
    }
    if m.notify_alarm_reset.is_some() && protocol.is_a_family() {
        c.not_applicable(
            format!("{label}.notify_alarm_reset"),
            format!(
                "{title} does not post CNC reset/alarm with SYN/NAK: only Protocol B and \
                 Expansion Protocol B do; remove the key"
            ),
            "§6.4, §10.2 parameter 5000#3",
        );
    }

    // Expansion Protocol A packet length (§5.2).
    match (protocol, m.packet_n) {
        (Protocol::ExpansionA, Some(0)) => c.invalid(
            format!("{label}.packet_n"),
            "0".to_string(),
            "n = 0 is plain Protocol A; Expansion Protocol A needs n = 1, 2 or 4 \
             (packets of 256·n bytes), or set protocol = \"a\""
                .to_string(),
            "§5.2",
        ),
        (Protocol::ExpansionA, Some(n)) if !matches!(n, 1 | 2 | 4) => c.invalid(
            format!("{label}.packet_n"),
            n.to_string(),
            "must be 1, 2 or 4 (packets of 256·n bytes); the board takes any other value \
             as 0, i.e. plain Protocol A"
                .to_string(),
            "§5.2",
        ),
        (Protocol::A, Some(n)) if n != 0 => c.invalid(
            format!("{label}.packet_n"),
            n.to_string(),
            "Protocol A sends NC data in DAT messages (n = 0); for packets of 256·n bytes \
             set protocol = \"expansion-a\""
                .to_string(),
            "§5.2",
        ),
        (Protocol::B | Protocol::ExpansionB, Some(_)) => c.not_applicable(
            format!("{label}.packet_n"),
            format!("{title} has no data packets: packet_n belongs to Expansion Protocol A"),
            "§5.2",
        ),
        _ => {}
    }

    // DI is read with RDI, a Protocol A command (§4.4.1); Protocol B has no DI/DO.
    if let Some(ms) = m.di_poll_ms {
        if protocol.is_a_family() {
            c.range(
                || format!("{label}.di_poll_ms"),
                ms,
                100,
                3_600_000,
                " ms",
                "§4.4.1",
            );
        } else {
            c.not_applicable(
                format!("{label}.di_poll_ms"),
                format!(
                    "{title} has no RDI/SDI commands: DI can be read only over Protocol A and \
                     Expansion Protocol A; remove the key"
                ),
                "§4.4.1",
            );
        }
    }

    check_params(c, label, m);

    let Some(transport) = &transport_of(c, label, m.transport.as_ref()) else {
        return;
    };
    let tpath = format!("{label}.transport");
    check_transport(c, &tpath, transport);
    let line = transport.line();

    // Interface and baud rate (§2.1, §2.2, §10.2 parameters 5073 / 5083).
    let baud = line.baud;
    let interface = default_interface(protocol, baud, m.interface);
    let baud_path = || format!("{tpath}.line.baud");
    if !FANUC_BAUD_RATES.contains(&baud) {
        c.invalid(
            baud_path(),
            baud.to_string(),
            format!(
                "must be one of the rates of parameters 5073 / 5083: {}",
                list_u32(&FANUC_BAUD_RATES)
            ),
            "§10.2",
        );
    } else if baud > interface.max_baud() {
        c.invalid(
            baud_path(),
            baud.to_string(),
            format!(
                "{} carries 50..={} baud; set interface = \"rs422\" for faster rates",
                interface.name(),
                interface.max_baud()
            ),
            "§2.1",
        );
    } else if protocol == Protocol::B && baud > 19_200 {
        c.invalid(
            baud_path(),
            baud.to_string(),
            "Protocol B runs at 19200 baud at most; Expansion Protocol B is the protocol for \
             RS-422 speeds"
                .to_string(),
            "§2.2, §6.3",
        );
    }
    if interface == Interface::Rs232c
        && matches!(protocol, Protocol::ExpansionA | Protocol::ExpansionB)
    {
        c.invalid(
            format!("{label}.interface"),
            q("rs232c"),
            format!("{title} runs on RS-422 only"),
            "§2.2",
        );
    }

    // Character framing: 8 data bits, then even parity + 1 stop bit or 2 stop bits (§3.1).
    let framing_ok = line.data_bits == DataBits::Eight
        && matches!(
            (line.parity, line.stop_bits),
            (Parity::Even, StopBits::One) | (Parity::None, StopBits::Two)
        );
    if !framing_ok {
        c.invalid(
            format!("{tpath}.line"),
            q(&line.to_string()),
            "the remote buffer frames characters as 8 data bits with even parity and 1 stop \
             bit (\"8E1\") or with no parity and 2 stop bits (\"8N2\")"
                .to_string(),
            "§3.1, parameters 5072 / 5082",
        );
    }

    // A device server cannot take back bytes already handed to it, so its window must fit
    // in the overrun the board allows after DC3 (§6.3; Expansion B: protocol notes 12).
    if let TransportConfig::Tcp { window, .. } = transport {
        let limit = match protocol {
            Protocol::B => Some((511, "less than 512 characters", "§6.3")),
            Protocol::ExpansionB => Some((1280, "1280 characters at most", "§7")),
            _ => None,
        };
        if let Some((max, words, section)) = limit
            && *window > max
        {
            c.invalid(
                format!("{tpath}.window"),
                window.to_string(),
                format!(
                    "must be within 1..={max}: the allowable overrun after DC3 is {words}, and \
                     bytes handed to the device server cannot be called back"
                ),
                section,
            );
        }
    }

    // The simulated board.
    match (transport, &m.sim) {
        (TransportConfig::Sim { .. }, Some(sim)) => check_board_sim(c, label, sim),
        (_, Some(_)) => c.not_applicable(
            format!("{label}.sim"),
            format!(
                "board simulation settings are used only with transport kind = \"sim\", not \
                 \"{}\"; remove the table",
                transport.kind().name()
            ),
            "",
        ),
        _ => {}
    }
}

/// Builds the transport of link `label`, reporting a missing table, a missing key or a key
/// of another kind.
fn transport_of(
    c: &mut Checker,
    label: &str,
    raw: Option<&RawTransport>,
) -> Option<TransportConfig> {
    let Some(raw) = raw else {
        c.missing(
            format!("{label}.transport"),
            "add a transport table with kind = \"serial\", \"tcp\" or \"sim\"",
        );
        return None;
    };
    match raw.build() {
        Ok(t) => Some(t),
        Err(problems) => {
            for p in problems {
                let path = format!("{label}.transport.{}", p.key);
                if p.missing {
                    c.missing(path, &p.text);
                } else {
                    c.not_applicable(path, p.text, "");
                }
            }
            None
        }
    }
}

fn check_params(c: &mut Checker, label: &str, m: &RawMachine) {
    let params = params_of([m.nb, m.no, m.ne, m.tp, m.to, m.ti, m.tx, m.tw]);
    for range in params.validate() {
        c.errors.push(ConfigError::Param {
            path: label.to_string(),
            range,
        });
    }
}

fn check_board_sim(c: &mut Checker, label: &str, sim: &BoardSimConfig) {
    // A DAT carries up to 4096 bytes (§4.1) and Protocol B sends DC1 only with 4096
    // characters vacant (§6.3): a smaller buffer could never take them.
    c.range(
        || format!("{label}.sim.buffer_size"),
        sim.buffer_size,
        4096,
        1 << 20,
        " bytes (a DAT carries up to 4096 bytes; DC1 needs 4096 vacant characters)",
        "§4.1, §6.3",
    );
    c.range(
        || format!("{label}.sim.consume_rate"),
        sim.consume_rate,
        1,
        10_000_000,
        " bytes/s",
        "",
    );
    c.range(
        || format!("{label}.sim.axes"),
        sim.axes,
        1,
        24,
        " (axes of a G05 block, parameter 7635)",
        "§9",
    );
}

fn check_plc(c: &mut Checker, label: &str, p: &RawPlc) {
    match transport_of(c, label, p.transport.as_ref()) {
        None => {}
        Some(t) => {
            let tpath = format!("{label}.transport");
            check_transport(c, &tpath, &t);
            let baud = t.line().baud;
            if !FUJI_BAUD_RATES.contains(&baud) {
                c.invalid(
                    format!("{tpath}.line.baud"),
                    baud.to_string(),
                    format!("must be one of {}", list_u32(&FUJI_BAUD_RATES)),
                    "FFU120B §3-2, §4-3 item 4",
                );
            }
        }
    }

    // Modes 4 and 5 are non-procedure modes, where the PLC is the master (§1-3).
    if !(1..=3).contains(&p.mode) {
        c.invalid(
            format!("{label}.mode"),
            p.mode.to_string(),
            "must be 1 (1:1), 2 or 3 (1:N over RS-485): the command-set modes; modes 4 and 5 \
             are non-procedure modes that the gateway does not speak"
                .to_string(),
            "FFU120B §1-3, §4-2",
        );
    }

    // Stations: RSNO, BCD 00–99; 00 in mode 1; at most 31 modules on one RS-485 line.
    let spath = || format!("{label}.stations");
    let show = |v: &[u8]| {
        let s: Vec<String> = v.iter().map(u8::to_string).collect();
        format!("[{}]", s.join(", "))
    };
    if p.stations.is_empty() {
        c.invalid(
            spath(),
            "[]".to_string(),
            "list at least one station number".to_string(),
            "FFU120B §5-3",
        );
    }
    if p.mode == 1 && p.stations.as_slice() != [0] && !p.stations.is_empty() {
        c.invalid(
            spath(),
            show(&p.stations),
            "mode 1 is a 1:1 link and addresses station 00 only: use stations = [0]".to_string(),
            "FFU120B §5-3 RSNO",
        );
    }
    for &n in &p.stations {
        if n > 99 {
            c.invalid(
                spath(),
                show(&p.stations),
                format!("station {n} is not a station number: RSNO is two BCD digits, 0..=99"),
                "FFU120B §5-3",
            );
        }
    }
    let mut sorted = p.stations.clone();
    sorted.sort_unstable();
    if sorted.windows(2).any(|w| w[0] == w[1]) {
        c.invalid(
            spath(),
            show(&p.stations),
            "each station number may appear once".to_string(),
            "",
        );
    }
    if p.stations.len() > FUJI_MAX_STATIONS {
        c.invalid(
            spath(),
            format!("{} stations", p.stations.len()),
            format!("one RS-485 line carries at most {FUJI_MAX_STATIONS} modules"),
            "FFU120B §2-2",
        );
    }

    // Start and end codes of Set 1 / Set 2 come as bytes (items 18, 19).
    let codes = |c: &mut Checker, key: &str, bytes: &[u8], want: Option<(usize, &str)>| {
        let path = format!("{label}.{key}");
        match want {
            Some((n, kind)) if bytes.len() != n => c.invalid(
                path,
                show(bytes),
                format!(
                    "{kind} needs exactly {n} byte{}, e.g. {key} = [{}]",
                    if n == 1 { "" } else { "s" },
                    if n == 1 { "0x2A" } else { "0x2A, 0x2A" }
                ),
                "FFU120B §4-3 items 18, 19",
            ),
            None if !bytes.is_empty() => c.not_applicable(
                path,
                format!(
                    "used only with {kind_key} = \"set1\" or \"set2\"; remove the key",
                    kind_key = key.trim_end_matches('s')
                ),
                "FFU120B §4-3 items 18, 19",
            ),
            _ => {}
        }
    };
    let start_want = match p.start_code {
        PlcStartCode::Set1 => Some((1, "start_code = \"set1\"")),
        PlcStartCode::Set2 => Some((2, "start_code = \"set2\"")),
        _ => None,
    };
    codes(c, "start_codes", &p.start_codes, start_want);
    let end_want = match p.end_code {
        PlcEndCode::Set1 => Some((1, "end_code = \"set1\"")),
        PlcEndCode::Set2 => Some((2, "end_code = \"set2\"")),
        _ => None,
    };
    codes(c, "end_codes", &p.end_codes, end_want);

    // Combinations the module rejects with an initial error (§4-7 F1, F2, F3).
    if !p.bcc_range.includes_end() {
        let mut why = Vec::new();
        if p.bcc_code == BccCode::Binary {
            why.push("a binary BCC (initial error F1)");
        }
        if p.bcc_calc == BccCalc::Crc16 {
            why.push("a CRC-16 BCC (initial error F2)");
        }
        if !why.is_empty() {
            c.invalid(
                format!("{label}.bcc_range"),
                toml_name(&p.bcc_range),
                format!(
                    "{} must follow the end code: use \"text+end\" or \"start+text+end\"",
                    why.join(" and ")
                ),
                "FFU120B §4-3 item 23, §4-7",
            );
        }
    }
    if p.bcc_calc == BccCalc::Crc16 && p.bcc_code == BccCode::TransmissionCode {
        c.invalid(
            format!("{label}.bcc_code"),
            toml_name(&p.bcc_code),
            "a CRC-16 BCC travels in binary: set bcc_code = \"binary\" (initial error F3)"
                .to_string(),
            "FFU120B §4-3 item 23, §4-7",
        );
    }

    c.range(
        || format!("{label}.timeout_ms"),
        p.timeout_ms,
        10,
        600_000,
        " ms",
        "",
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = r#"
cell = "c1"
[[machines]]
name = "m1"
protocol = "a"
transport = { kind = "sim" }
"#;

    fn errors_of(text: &str) -> Vec<String> {
        match CellConfig::from_toml_str(text, "test.toml") {
            Ok(_) => Vec::new(),
            Err(e) => e.iter().map(ToString::to_string).collect(),
        }
    }

    #[test]
    fn request_patterns_are_checked() {
        let with = |requests: &str| format!("{MINIMAL}\n[programs]\nrequests = {requests}\n");
        assert!(errors_of(&with(r#"["(CALL {n})", "(PRG={n})"]"#)).is_empty());
        assert!(errors_of(&with("[]")).is_empty());
        let e = errors_of(&with(r#"["(REQ O{n})", "(REQ)", "({n}%)"]"#));
        assert_eq!(e.len(), 2, "{e:?}");
        assert!(
            e[0].contains("programs.requests[1]") && e[0].contains("{n}"),
            "{e:?}"
        );
        assert!(
            e[1].contains("programs.requests[2]") && e[1].contains("EOR"),
            "{e:?}"
        );
        let cfg = CellConfig::from_toml_str(MINIMAL, "t").unwrap();
        assert!(cfg.programs.store_punched);
        assert_eq!(cfg.programs.requests, ["(REQ O{n})", "(PRG={n})"]);
    }

    #[test]
    fn minimal_file_takes_defaults() {
        let cfg = CellConfig::from_toml_str(MINIMAL, "t").unwrap();
        let m = &cfg.machines[0];
        assert_eq!(m.params(), Params::POWER_ON);
        assert_eq!(m.effective_end_code(), EndCode::Cr);
        assert_eq!(m.effective_packet_n(), 0);
        assert_eq!(m.effective_interface(), Interface::Rs232c);
        assert_eq!(m.transport.line(), &LineSettings::default());
        assert_eq!(m.board_sim(), BoardSimConfig::DEFAULT);
        assert_eq!(cfg.programs, ProgramsConfig::default());
        assert_eq!(cfg.bus, BusConfig::default());
    }

    #[test]
    fn embedded_default_is_valid() {
        let cfg = CellConfig::embedded_default();
        assert_eq!(cfg.cell, "demo");
        let names: Vec<&str> = cfg.machines.iter().map(|m| m.name.as_str()).collect();
        assert_eq!(names, ["mill-1", "mill-2", "lathe-1"]);
        assert!(cfg.bus.listen == ["tcp/127.0.0.1:7447"] && !cfg.bus.multicast_scouting);
        let mill2 = cfg.machine("mill-2").unwrap();
        assert_eq!(mill2.effective_packet_n(), 2);
        assert_eq!(mill2.effective_interface(), Interface::Rs422);
        assert!(cfg.validate().is_ok());
    }

    #[test]
    fn interface_default_follows_baud_and_protocol() {
        assert_eq!(
            default_interface(Protocol::A, 19_200, None),
            Interface::Rs232c
        );
        assert_eq!(
            default_interface(Protocol::A, 38_400, None),
            Interface::Rs422
        );
        assert_eq!(
            default_interface(Protocol::ExpansionB, 9600, None),
            Interface::Rs422
        );
        assert_eq!(
            default_interface(Protocol::B, 9600, Some(Interface::Rs422)),
            Interface::Rs422
        );
    }

    #[test]
    fn param_errors_carry_the_machine_path() {
        let errs = errors_of(&format!("{MINIMAL}tw = 12\n"));
        assert_eq!(
            errs,
            ["machines.m1.tw = 12: must be within 0..=5 (tp = 5) (§4.5)"]
        );
    }

    #[test]
    fn packet_n_rules() {
        let file = |protocol: &str, n: &str| {
            format!(
                "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"{protocol}\"\n{n}\n\
                 transport = {{ kind = \"sim\", line = {{ baud = 86400 }} }}\n"
            )
        };
        assert!(errors_of(&file("expansion-a", "packet_n = 4")).is_empty());
        assert!(errors_of(&file("expansion-a", "")).is_empty());
        assert!(errors_of(&file("a", "packet_n = 0")).is_empty());
        let e = errors_of(&file("expansion-a", "packet_n = 3"));
        assert_eq!(e.len(), 1);
        assert!(e[0].starts_with("machines.m.packet_n = 3: must be 1, 2 or 4"));
        assert!(e[0].ends_with("(§5.2)"));
        let e = errors_of(&file("expansion-a", "packet_n = 0"));
        assert!(e[0].contains("n = 0 is plain Protocol A"), "{e:?}");
        let e = errors_of(&file("a", "packet_n = 2"));
        assert!(e[0].starts_with("machines.m.packet_n = 2: Protocol A sends NC data"));
        let e = errors_of(&file("expansion-b", "packet_n = 1"));
        assert!(e[0].starts_with("machines.m.packet_n: Expansion Protocol B has no data packets"));
    }

    #[test]
    fn di_poll_rules() {
        let file = |protocol: &str, key: &str| {
            format!(
                "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"{protocol}\"\n{key}\n\
                 transport = {{ kind = \"sim\", line = {{ baud = 19200 }} }}\n"
            )
        };
        assert!(errors_of(&file("a", "di_poll_ms = 500")).is_empty());
        let e = errors_of(&file("a", "di_poll_ms = 10"));
        assert_eq!(e.len(), 1);
        assert!(e[0].starts_with("machines.m.di_poll_ms = 10: must be within 100..=3600000"));
        let e = errors_of(&file("b", "di_poll_ms = 500"));
        assert_eq!(e.len(), 1);
        assert!(
            e[0].starts_with("machines.m.di_poll_ms: Protocol B has no RDI/SDI"),
            "{e:?}"
        );
        let c = CellConfig::from_toml_str(&file("a", "di_poll_ms = 500"), "t").unwrap();
        assert_eq!(c.machines[0].di_poll_ms, Some(500));
        let back = CellConfig::from_toml_str(&c.to_toml_string().unwrap(), "t").unwrap();
        assert_eq!(back, c);
    }

    #[test]
    fn family_specific_keys() {
        let b = |extra: &str| {
            format!(
                "cell = \"c\"\n[[machines]]\nname = \"l\"\nprotocol = \"b\"\n{extra}\n\
                 transport = {{ kind = \"sim\" }}\n"
            )
        };
        assert!(errors_of(&b("notify_alarm_reset = true")).is_empty());
        let e = errors_of(&b("end_code = \"etx\""));
        assert_eq!(e.len(), 1);
        assert!(e[0].starts_with("machines.l.end_code: Protocol B has no message end code"));
        let e = errors_of(&format!("{MINIMAL}notify_alarm_reset = true\n"));
        assert!(e[0].starts_with("machines.m1.notify_alarm_reset: Protocol A does not post"));
    }

    #[test]
    fn baud_rates_and_interfaces() {
        let f = |protocol: &str, baud: u32, interface: &str| {
            format!(
                "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"{protocol}\"\n{interface}\n\
                 transport = {{ kind = \"sim\", line = {{ baud = {baud} }} }}\n"
            )
        };
        assert!(errors_of(&f("a", 19200, "")).is_empty());
        assert!(errors_of(&f("a", 86400, "")).is_empty());
        assert!(errors_of(&f("expansion-b", 76800, "")).is_empty());
        let e = errors_of(&f("a", 115_200, ""));
        assert!(e[0].starts_with("machines.m.transport.line.baud = 115200: must be one of"));
        assert!(e[0].ends_with("76800, 86400 (§10.2)"));
        let e = errors_of(&f("a", 38_400, "interface = \"rs232c\""));
        assert_eq!(
            e,
            [
                "machines.m.transport.line.baud = 38400: RS-232-C carries 50..=19200 baud; \
                 set interface = \"rs422\" for faster rates (§2.1)"
            ]
        );
        let e = errors_of(&f("b", 38_400, ""));
        assert!(
            e[0].contains("Protocol B runs at 19200 baud at most"),
            "{e:?}"
        );
        let e = errors_of(&f("expansion-a", 19_200, "interface = \"rs232c\""));
        assert_eq!(
            e,
            [
                "machines.m.interface = \"rs232c\": Expansion Protocol A runs on RS-422 only \
                 (§2.2)"
            ]
        );
    }

    #[test]
    fn fanuc_framing() {
        let f = |line: &str| {
            format!(
                "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"a\"\n\
                 transport = {{ kind = \"sim\", line = {{ {line} }} }}\n"
            )
        };
        assert!(errors_of(&f("parity = \"even\", stop_bits = \"1\"")).is_empty());
        assert!(errors_of(&f("parity = \"none\", stop_bits = \"2\"")).is_empty());
        let e = errors_of(&f("parity = \"none\", stop_bits = \"1\""));
        assert_eq!(e.len(), 1);
        assert!(e[0].starts_with("machines.m.transport.line = \"9600 8N1\": the remote buffer"));
        assert!(errors_of(&f("data_bits = \"7\"")).len() == 1);
        assert!(errors_of(&f("parity = \"odd\", stop_bits = \"1\"")).len() == 1);
    }

    #[test]
    fn tcp_transport_checks() {
        let f = |protocol: &str, t: &str| {
            format!(
                "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"{protocol}\"\n\
                 transport = {{ kind = \"tcp\", {t} }}\n"
            )
        };
        assert!(errors_of(&f("a", "address = \"127.0.0.1:4001\"")).is_empty());
        assert!(errors_of(&f("a", "address = \"moxa-3.local:4001\"")).is_empty());
        assert!(errors_of(&f("a", "address = \"[::1]:4001\"")).is_empty());
        let e = errors_of(&f("a", "address = \"moxa-3\""));
        assert!(e[0].starts_with("machines.m.transport.address = \"moxa-3\": must be host:port"));
        let e = errors_of(&f("b", "address = \"h:1\", window = 1024"));
        assert_eq!(e.len(), 1);
        assert!(e[0].starts_with("machines.m.transport.window = 1024: must be within 1..=511"));
        assert!(errors_of(&f("expansion-b", "address = \"h:1\", window = 1024")).is_empty());
        let e = errors_of(&f(
            "a",
            "address = \"h:1\", reconnect_min_ms = 500, reconnect_max_ms = 100",
        ));
        assert_eq!(
            e,
            [
                "machines.m.transport.reconnect_max_ms = 100: must be within 500..=3600000 \
                 (reconnect_min_ms or more)"
            ]
        );
    }

    #[test]
    fn transport_tables() {
        let e = errors_of(&MINIMAL.replace("{ kind = \"sim\" }", "{}"));
        assert_eq!(
            e,
            ["machines.m1.transport.kind: missing; one of \"serial\", \"tcp\" or \"sim\""]
        );
        let e = errors_of(&MINIMAL.replace("{ kind = \"sim\" }", "{ kind = \"tcp\" }"));
        assert!(e[0].starts_with("machines.m1.transport.address: missing; a tcp transport"));

        // Read on its own, a transport reports its problems through serde.
        let t: TransportConfig =
            toml::from_str("kind = \"tcp\"\naddress = \"h:1\"\nline = { baud = 19200 }").unwrap();
        assert_eq!(
            t,
            TransportConfig::Tcp {
                address: "h:1".to_string(),
                line: LineSettings::with_baud(19_200),
                window: 256,
                reconnect_min_ms: 100,
                reconnect_max_ms: 5000,
            }
        );
        let err = toml::from_str::<TransportConfig>("kind = \"sim\"\npath = \"/dev/x\"")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("`path`: used only with kind = \"serial\", not \"sim\""),
            "{err}"
        );
    }

    #[test]
    fn sim_table_only_with_sim_transport() {
        let text = "cell = \"c\"\n[[machines]]\nname = \"m\"\nprotocol = \"a\"\n\
                    transport = { kind = \"serial\", path = \"/dev/ttyS0\" }\n\
                    [machines.sim]\nbuffer_size = 8192\n";
        let e = errors_of(text);
        assert_eq!(e.len(), 1);
        assert!(e[0].starts_with("machines.m.sim: board simulation settings"));
        let e = errors_of(&format!(
            "{MINIMAL}[machines.sim]\nbuffer_size = 100\naxes = 0\n"
        ));
        assert_eq!(e.len(), 2, "{e:?}");
        assert!(e[0].starts_with("machines.m1.sim.buffer_size = 100: must be within 4096..="));
        assert!(e[1].starts_with("machines.m1.sim.axes = 0: must be within 1..=24"));
    }

    #[test]
    fn names_must_be_key_chunks_and_unique_across_links() {
        let text = r#"
cell = "my cell"
[[machines]]
name = "m/1"
protocol = "a"
transport = { kind = "sim" }
[[machines]]
name = "x"
protocol = "a"
transport = { kind = "sim" }
[[plcs]]
name = "x"
transport = { kind = "sim" }
"#;
        let e = errors_of(text);
        assert_eq!(e.len(), 3, "{e:?}");
        assert!(e[0].starts_with("cell = \"my cell\": use only letters"));
        assert!(e[1].starts_with("machines[1].name = \"m/1\": use only letters"));
        assert_eq!(
            e[2],
            "plcs.x: [[machines]] #2 and [[plcs]] #1 are both named \"x\"; names must be \
             unique in a cell (each becomes a key chunk)"
        );
    }

    #[test]
    fn plc_defaults_and_initial_errors() {
        let f = |extra: &str| {
            format!(
                "cell = \"c\"\n[[plcs]]\nname = \"p\"\n{extra}\n\
                 transport = {{ kind = \"sim\" }}\n"
            )
        };
        let cfg = CellConfig::from_toml_str(&f(""), "t").unwrap();
        let p = &cfg.plcs[0];
        assert_eq!((p.mode, p.stations.as_slice()), (1, &[0u8][..]));
        assert_eq!(p.start_code.bytes(&p.start_codes), b":");
        assert_eq!(p.end_code.bytes(&p.end_codes), b"\r");
        assert!(p.transposition);

        // F1: binary BCC before the end code.
        let e = errors_of(&f("bcc = \"set1\"\nbcc_code = \"binary\""));
        assert_eq!(e.len(), 1);
        assert!(e[0].starts_with("plcs.p.bcc_range = \"text\": a binary BCC (initial error F1)"));
        // F2 + F3.
        let e = errors_of(&f("bcc = \"set1\"\nbcc_calc = \"crc16\""));
        assert_eq!(e.len(), 2, "{e:?}");
        assert!(e[0].contains("a CRC-16 BCC (initial error F2)"));
        assert!(e[1].starts_with("plcs.p.bcc_code = \"transmission-code\": a CRC-16 BCC"));
        assert!(
            errors_of(&f(
                "bcc = \"set2\"\nbcc_calc = \"crc16\"\nbcc_code = \"binary\"\nbcc_range = \"start+text+end\""
            ))
            .is_empty()
        );
    }

    #[test]
    fn plc_stations_modes_and_codes() {
        let f = |extra: &str| {
            format!(
                "cell = \"c\"\n[[plcs]]\nname = \"p\"\n{extra}\n\
                 transport = {{ kind = \"sim\", line = {{ baud = 19200 }} }}\n"
            )
        };
        assert!(errors_of(&f("mode = 2\nstations = [1, 2, 31]")).is_empty());
        let e = errors_of(&f("stations = [1]"));
        assert!(e[0].starts_with("plcs.p.stations = [1]: mode 1 is a 1:1 link"));
        let e = errors_of(&f("mode = 3\nstations = [5, 120, 5]"));
        assert_eq!(e.len(), 2, "{e:?}");
        assert!(e[0].contains("station 120 is not a station number"));
        assert!(e[1].contains("each station number may appear once"));
        let e = errors_of(&f("mode = 4"));
        assert!(e[0].starts_with("plcs.p.mode = 4: must be 1 (1:1), 2 or 3"));
        let e = errors_of(&f("end_code = \"set2\"\nend_codes = [0x0D]"));
        assert_eq!(
            e,
            [
                "plcs.p.end_codes = [13]: end_code = \"set2\" needs exactly 2 bytes, e.g. \
                 end_codes = [0x2A, 0x2A] (FFU120B §4-3 items 18, 19)"
            ]
        );
        let e = errors_of(&f("start_codes = [0x02]"));
        assert!(e[0].starts_with("plcs.p.start_codes: used only with start_code = \"set1\""));
        assert!(errors_of(&f("start_code = \"set1\"\nstart_codes = [0x2A]")).is_empty());
    }

    #[test]
    fn plc_baud_rates() {
        let text = "cell = \"c\"\n[[plcs]]\nname = \"p\"\n\
                    transport = { kind = \"tcp\", address = \"h:1\", line = { baud = 38400 } }\n";
        assert_eq!(
            errors_of(text),
            [
                "plcs.p.transport.line.baud = 38400: must be one of 300, 600, 1200, 2400, 4800, \
                 9600, 19200 (FFU120B §3-2, §4-3 item 4)"
            ]
        );
    }

    #[test]
    fn bus_and_telemetry_checks() {
        let text = "cell = \"c\"\n[bus]\nprefix = \"a//b\"\nlisten = [\"127.0.0.1:7447\"]\n\
                    [telemetry]\notlp_endpoint = \"127.0.0.1:4317\"\n";
        let e = errors_of(text);
        assert_eq!(e.len(), 3, "{e:?}");
        assert!(e[0].starts_with("bus.prefix = \"a//b\""));
        assert!(e[1].starts_with("bus.listen[1] = \"127.0.0.1:7447\""));
        assert!(e[2].starts_with("telemetry.otlp_endpoint"));
    }

    #[test]
    fn missing_keys_are_validation_errors() {
        let text = "[[machines]]\ntw = 9\n[[plcs]]\nname = \"p\"\n";
        let e = errors_of(text);
        assert_eq!(e.len(), 6, "{e:?}");
        assert!(e[0].starts_with("cell: missing;"));
        assert_eq!(
            e[1],
            "machines[1].name: missing; every [[machines]] #1 table needs a name"
        );
        assert!(e[2].starts_with("machines[1].protocol: missing;"));
        assert_eq!(
            e[3],
            "machines[1].tw = 9: must be within 0..=5 (tp = 5) (§4.5)"
        );
        assert!(e[4].starts_with("machines[1].transport: missing;"));
        assert!(e[5].starts_with("plcs.p.transport: missing;"));
    }

    #[test]
    fn summary_shows_values_in_force() {
        let s = CellConfig::embedded_default().summary();
        assert!(s.starts_with("cell demo\n"), "{s}");
        assert!(
            s.contains("mill-2: Expansion Protocol A n = 2 (512-byte packets)"),
            "{s}"
        );
        assert!(
            s.contains("lathe-1: Protocol B, ISO code (5000#2 = 0), RS-232-C"),
            "{s}"
        );
        assert!(s.contains("Nb=2000 No=50"), "{s}");
    }
}
