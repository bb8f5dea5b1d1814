//! `[[plcs]]`: one Fuji MICREX-F PLC through an FFU120B module, the initial-file settings
//! both ends must agree on (FFU120B §4-3), and their checks.

use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::error::ConfigErrors;
use super::error::{Checker, ConfigError, list_u32, q, toml_name};
use super::transport::{
    RawTransport, TransportConfig, built_transport, check_transport, transport_of,
};
use crate::engine::line::DataBits;
use crate::fuji::command::Module;
use crate::fuji::frame::{
    BccCalc, BccCode, BccKind, BccRange, Crc16, EndCode, FrameProblem, FrameSettings, StartCode,
    TransmissionCode,
};
use crate::fuji::master::{MasterSettings, OperationMode};

/// One Fuji MICREX-F PLC reached through an FFU120B general interface module (`[[plcs]]`):
/// in command-set mode 1, 2 or 3 the gateway is the host that reads and writes its memory; in
/// non-procedure mode 4 or 5 it is the module's external device, and messages go both ways
/// (§1-3, §5-5; FFU120B notes 9). The settings mirror the module's initial file (§4-3): both
/// ends must agree on them.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct PlcConfig {
    /// PLC id, `[A-Za-z0-9_-]+`, unique among the cell's machines and PLCs.
    pub name: String,
    /// Operation mode set on the module's MODE dial: 1 (1:1), 2 or 3 (1:N, RS-485) with the
    /// command set; 4 (RS-232C 1:1) or 5 (RS-485) non-procedure (§1-3, §4-2).
    pub mode: u8,
    /// RS-485 station numbers (RSNO, BCD 00–99) of the modules this link polls; mode 1 uses 00.
    pub stations: Vec<u8>,
    /// The framing items of the initial file (§4-3 items 14, 16–23), as the FFU120B engines
    /// take them; in the cell file they are keys of the `[[plcs]]` entry itself.
    #[serde(flatten)]
    pub frame: FrameSettings,
    /// How long the host waits for a reply after its request has been sent, ms.
    pub timeout_ms: u32,
    /// Modes 4–5: the fixed message length N, 1–216 bytes (item 15); `None`: variable length,
    /// a message ends at the end code.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fixed_length: Option<u16>,
    /// Modes 4–5: the module's receive message number (item 3), where the PLC finds what the
    /// gateway sends; 0 in modes 1–3.
    #[serde(skip_serializing_if = "is_zero")]
    pub receive_message: u8,
    /// How the host reaches the FFU120B: a serial port, a TCP device server or a simulation.
    pub transport: TransportConfig,
    /// Named values polled from the PLC (`[[plcs.tags]]`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub tags: Vec<TagConfig>,
    /// What the simulated PLC does by itself (`[plcs.sim]`, sim transport only).
    #[serde(skip_serializing_if = "PlcSimConfig::is_empty")]
    pub sim: PlcSimConfig,
}

fn is_zero(n: &u8) -> bool {
    *n == 0
}

impl PlcConfig {
    /// The reply time-out when the entry sets none, ms.
    pub const DEFAULT_TIMEOUT_MS: u32 = 2000;

    /// Whether the entry is a non-procedure link (mode 4 or 5): messages, no command set.
    pub fn is_non_procedure(&self) -> bool {
        !self.operation_mode().is_command_set()
    }

    /// The operation mode of a validated entry (1–5).
    pub fn operation_mode(&self) -> OperationMode {
        OperationMode::from_dial(self.mode).unwrap_or(OperationMode::One)
    }

    /// The host settings of the entry.
    pub fn master_settings(&self) -> MasterSettings {
        let mut s = MasterSettings::new(self.operation_mode());
        s.frame = self.frame.clone();
        s.line = *self.transport.line();
        s.reply_timeout = Duration::from_millis(u64::from(self.timeout_ms));
        s.probe_interval = s.probe_interval.max(s.reply_timeout * 2);
        // Every tag read of every station may be waiting at once (31 stations, §2-2).
        s.queue_limit = 1024;
        s.fixed_length = self.fixed_length.map(usize::from);
        s
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawPlc {
    pub(super) name: Option<String>,
    #[serde(default = "default_mode")]
    mode: u8,
    #[serde(default = "default_stations")]
    stations: Vec<u8>,
    #[serde(default)]
    start_code: StartCode,
    #[serde(default)]
    start_codes: Vec<u8>,
    #[serde(default)]
    end_code: EndCode,
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
    #[serde(default)]
    crc16: Crc16,
    #[serde(default = "default_true")]
    transposition: bool,
    #[serde(default)]
    code: TransmissionCode,
    #[serde(default = "default_timeout_ms")]
    timeout_ms: u32,
    #[serde(default)]
    fixed_length: u16,
    receive_message: Option<u8>,
    transport: Option<RawTransport>,
    #[serde(default)]
    tags: Vec<RawTag>,
    sim: Option<PlcSimConfig>,
}

impl RawPlc {
    /// Whether the PLC has a tag `name`, and if so whether it keeps history.
    pub(super) fn tag_history(&self, name: &str) -> Option<bool> {
        self.tags
            .iter()
            .find(|t| t.name.as_deref() == Some(name))
            .map(|t| t.history)
    }
}

pub(super) fn default_mode() -> u8 {
    1
}

pub(super) fn default_stations() -> Vec<u8> {
    vec![0]
}

pub(super) fn default_true() -> bool {
    true
}

pub(super) fn default_timeout_ms() -> u32 {
    PlcConfig::DEFAULT_TIMEOUT_MS
}

/// Baud rates of the FFU120B (FFU120B §3-2, §4-3 item 4).
pub const FUJI_BAUD_RATES: [u32; 7] = [300, 600, 1200, 2400, 4800, 9600, 19200];

/// Most modules on one RS-485 line (FFU120B §2-2 note 1).
pub const FUJI_MAX_STATIONS: usize = 31;

pub(super) fn check_plc(c: &mut Checker, label: &str, p: &RawPlc) {
    match transport_of(c, label, p.transport.as_ref()) {
        None => {}
        Some(t) => {
            let tpath = format!("{label}.transport");
            check_transport(c, &tpath, &t);
            if p.code == TransmissionCode::Ebcdic && t.line().data_bits == DataBits::Seven {
                c.invalid(
                    format!("{label}.code"),
                    "\"ebcdic\"".to_string(),
                    format!(
                        "EBCDIC (item 13) is an 8-bit code: set {tpath}.line.data_bits = 8 \
                         (item 5), or code = \"ascii\" (initial error F6)"
                    ),
                    "FFU120B §4-3 items 5, 13, §4-7",
                );
            }
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

    if !(1..=5).contains(&p.mode) {
        c.invalid(
            format!("{label}.mode"),
            p.mode.to_string(),
            "must be 1 (1:1), 2 or 3 (1:N over RS-485) with the command set, or 4 (RS-232C \
             1:1) or 5 (RS-485) non-procedure: the MODE dial's settings"
                .to_string(),
            "FFU120B §1-3, §4-2",
        );
    }
    non_procedure_checks(c, label, p);

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

    frame_checks(c, label, p);

    check_tags(c, label, p);

    c.range(
        || format!("{label}.timeout_ms"),
        p.timeout_ms,
        10,
        600_000,
        " ms",
        "",
    );
}

/// What modes 4 and 5 take and what only they take (§4-3 items 3 and 15, §5-5; FFU120B
/// notes 9).
fn non_procedure_checks(c: &mut Checker, label: &str, p: &RawPlc) {
    let non_procedure = matches!(p.mode, 4 | 5);
    if non_procedure {
        if p.stations.as_slice() != [0] {
            c.invalid(
                format!("{label}.stations"),
                format!("{:?}", p.stations),
                "modes 4 and 5 address no station: a message carries no RSNO (leave stations \
                 out)"
                    .to_string(),
                "FFU120B §5-5",
            );
        }
        if !p.tags.is_empty() {
            c.not_applicable(
                format!("{label}.tags"),
                "tags are read with the command set of modes 1–3; modes 4 and 5 only carry \
                 messages (remove the [[plcs.tags]])"
                    .to_string(),
                "FFU120B §1-3, §5-5",
            );
        }
        if usize::from(p.fixed_length) > crate::fuji::frame::MAX_NON_PROCEDURE_TEXT {
            c.invalid(
                format!("{label}.fixed_length"),
                p.fixed_length.to_string(),
                "must be 0 (variable length, the message ends at the end code) or 1..=216 \
                 bytes"
                    .to_string(),
                "FFU120B §4-3 item 15",
            );
        }
        if p.receive_message == Some(0) {
            c.invalid(
                format!("{label}.receive_message"),
                "0".to_string(),
                "the module's receive message number (item 3): 1..=255".to_string(),
                "FFU120B §4-3 item 3, §5-5",
            );
        }
    } else {
        if p.fixed_length != 0 {
            c.not_applicable(
                format!("{label}.fixed_length"),
                "a non-procedure setting of modes 4 and 5: in modes 1–3 item 15 is 0 (remove \
                 the key)"
                    .to_string(),
                "FFU120B §4-3 item 15",
            );
        }
        if p.receive_message.is_some() {
            c.not_applicable(
                format!("{label}.receive_message"),
                "a non-procedure setting of modes 4 and 5: in modes 1–3 item 3 is 0 (remove \
                 the key)"
                    .to_string(),
                "FFU120B §4-3 item 3",
            );
        }
    }
}

/// The framing items: the module's own rules (§4-7), as the engines apply them
/// ([`FrameSettings::validate`]), each reported on its key with the cell file's advice.
fn frame_checks(c: &mut Checker, label: &str, p: &RawPlc) {
    let show = |v: &[u8]| {
        let s: Vec<String> = v.iter().map(u8::to_string).collect();
        format!("[{}]", s.join(", "))
    };
    // Start and end codes of Set 1 / Set 2 come as bytes (items 18, 19); other codes take none.
    let set_bytes =
        |c: &mut Checker, key: &str, code: String, want: Option<usize>, bytes: &[u8]| {
            let path = format!("{label}.{key}s");
            match want {
                Some(n) => c.invalid(
                    path,
                    show(bytes),
                    format!(
                        "{key} = {code} needs exactly {n} byte{}, e.g. {key}s = [{}]",
                        if n == 1 { "" } else { "s" },
                        if n == 1 { "0x2A" } else { "0x2A, 0x2A" }
                    ),
                    "FFU120B §4-3 items 18, 19",
                ),
                None => c.not_applicable(
                    path,
                    format!("used only with {key} = \"set1\" or \"set2\"; remove the key"),
                    "FFU120B §4-3 items 18, 19",
                ),
            }
        };
    if p.start_code.set_bytes().is_none() && !p.start_codes.is_empty() {
        set_bytes(c, "start_code", String::new(), None, &p.start_codes);
    }
    if p.end_code.set_bytes().is_none() && !p.end_codes.is_empty() {
        set_bytes(c, "end_code", String::new(), None, &p.end_codes);
    }
    let before_end = "must follow the end code: use \"text+end\" or \"start+text+end\"";
    for problem in p.frame().validate() {
        match problem {
            FrameProblem::StartCodeBytes { want, .. } => {
                let code = toml_name(&p.start_code);
                set_bytes(c, "start_code", code, Some(want), &p.start_codes);
            }
            FrameProblem::EndCodeBytes { want, .. } => {
                let code = toml_name(&p.end_code);
                set_bytes(c, "end_code", code, Some(want), &p.end_codes);
            }
            FrameProblem::NoEndCode { code } => {
                let want = code.set_bytes().unwrap_or(1);
                c.invalid(
                    format!("{label}.end_codes"),
                    "[]".to_string(),
                    format!(
                        "end_code = {} sets no end code: give its {want} byte(s), e.g. end_codes = [0x0D] (item 19; initial error F5)",
                        toml_name(&code)
                    ),
                    "FFU120B §4-3 items 17, 19, §4-7",
                );
            }
            FrameProblem::BinaryBccBeforeEnd { range } => c.invalid(
                format!("{label}.bcc_range"),
                toml_name(&range),
                format!("a binary BCC (item 23; initial error F1) {before_end} (item 21)"),
                "FFU120B §4-3 items 21, 23, §4-7",
            ),
            FrameProblem::CrcBeforeEnd { range } => c.invalid(
                format!("{label}.bcc_range"),
                toml_name(&range),
                format!("a CRC-16 BCC (item 22; initial error F2) {before_end} (item 21)"),
                "FFU120B §4-3 items 21, 22, §4-7",
            ),
            FrameProblem::CrcInTransmissionCode => c.invalid(
                format!("{label}.bcc_code"),
                toml_name(&p.bcc_code),
                "a CRC-16 BCC (item 22) travels in binary: set bcc_code = \"binary\" (item 23; initial error F3)"
                    .to_string(),
                "FFU120B §4-3 items 22, 23, §4-7",
            ),
            other => {
                let key = if matches!(other, FrameProblem::CodeIsTextCharacter { which, .. } if which == "start code")
                {
                    "start_codes"
                } else {
                    "end_codes"
                };
                c.not_applicable(format!("{label}.{key}"), other.to_string(), "");
            }
        }
    }
}

impl From<&PlcConfig> for RawPlc {
    fn from(c: &PlcConfig) -> Self {
        RawPlc {
            name: Some(c.name.clone()),
            mode: c.mode,
            stations: c.stations.clone(),
            start_code: c.frame.start_code,
            start_codes: c.frame.start_codes.clone(),
            end_code: c.frame.end_code,
            end_codes: c.frame.end_codes.clone(),
            bcc: c.frame.bcc,
            bcc_range: c.frame.bcc_range,
            bcc_calc: c.frame.bcc_calc,
            bcc_code: c.frame.bcc_code,
            crc16: c.frame.crc16,
            transposition: c.frame.transposition,
            code: c.frame.code,
            timeout_ms: c.timeout_ms,
            fixed_length: c.fixed_length.unwrap_or(0),
            receive_message: (c.receive_message != 0).then_some(c.receive_message),
            transport: Some(RawTransport::from(&c.transport)),
            tags: c.tags.iter().map(RawTag::from).collect(),
            sim: (c.sim != PlcSimConfig::default()).then(|| c.sim.clone()),
        }
    }
}

impl RawPlc {
    /// The framing items as the engines take them.
    fn frame(&self) -> FrameSettings {
        FrameSettings {
            start_code: self.start_code,
            start_codes: self.start_codes.clone(),
            end_code: self.end_code,
            end_codes: self.end_codes.clone(),
            transposition: self.transposition,
            code: self.code,
            bcc: self.bcc,
            bcc_range: self.bcc_range,
            bcc_calc: self.bcc_calc,
            bcc_code: self.bcc_code,
            crc16: self.crc16,
        }
    }

    /// The validated PLC; `label` names it in the errors of a key still absent.
    pub(super) fn into_config(self, label: &str) -> Result<PlcConfig, ConfigErrors> {
        let missing = |path: String| ConfigError::Missing {
            path,
            hint: "required".to_string(),
        };
        let first = self.stations.first().copied().unwrap_or(0);
        let frame = self.frame();
        Ok(PlcConfig {
            name: self.name.ok_or_else(|| missing(format!("{label}.name")))?,
            mode: self.mode,
            stations: self.stations,
            frame,
            timeout_ms: self.timeout_ms,
            fixed_length: (self.fixed_length != 0 && matches!(self.mode, 4 | 5))
                .then_some(self.fixed_length),
            receive_message: if matches!(self.mode, 4 | 5) {
                self.receive_message.unwrap_or(1)
            } else {
                0
            },
            transport: built_transport(self.transport.as_ref(), label)?,
            tags: {
                let mut tags = Vec::with_capacity(self.tags.len());
                for t in self.tags {
                    tags.push(t.into_config(label, first)?);
                }
                tags
            },
            sim: self.sim.unwrap_or_default(),
        })
    }
}

/// A real number of the cell file (a tag's scale, deadband). Compared bit for bit, so that
/// the configuration stays `Eq`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, Default)]
#[serde(transparent)]
pub struct Real(pub f64);

impl PartialEq for Real {
    fn eq(&self, other: &Self) -> bool {
        self.0.to_bits() == other.0.to_bits()
    }
}

impl Eq for Real {}

/// How a tag reads its word(s) (`type` of `[[plcs.tags]]`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TagType {
    /// One bit (`bit` = 0–15 of a 16-bit word, 0–31 of a 32-bit one).
    Bit,
    /// An unsigned 16-bit word; not in a module of 32-bit words.
    U16,
    /// A signed (two's complement) 16-bit word; not in a module of 32-bit words.
    I16,
    /// In a 16-bit area: two words, the low word at `address` (the MICREX-F's 32-bit data
    /// layout); in a 32-bit area: one word.
    U32,
    /// As `u32`, signed (two's complement).
    I32,
    /// Binary-coded decimal: 4 digits of a 16-bit word, 8 digits of a 32-bit one.
    Bcd,
}

impl TagType {
    /// Words of `module` the tag takes.
    pub fn words(self, module: Module) -> u16 {
        match self {
            TagType::U32 | TagType::I32 if module.word_bytes() == 2 => 2,
            _ => 1,
        }
    }
}

/// A named value of the PLC (`[[plcs.tags]]`): where it lives, how it reads, how often it is
/// polled and when a change is worth publishing.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct TagConfig {
    /// `[A-Za-z0-9_-]+`, unique in its PLC: the key chunk of `P/C/plc/L/tag/NAME`.
    pub name: String,
    /// The station (RSNO) it lives at; default the PLC's first station.
    pub station: u8,
    /// The memory module it lives in, e.g. `D` (FFU120B §5-3-3).
    pub module: Module,
    /// Relative address: words of the module (FFU120B notes 3).
    pub address: u16,
    /// How it reads its word(s) (`type` in the cell file).
    #[serde(rename = "type")]
    pub kind: TagType,
    /// The bit of a `bit` tag (0 = least significant).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bit: Option<u8>,
    /// Value = raw × scale (a write divides by it).
    pub scale: Real,
    /// The poll group: tags with the same interval are read together, ms.
    pub poll_ms: u32,
    /// A change smaller than this (after scaling) is not published.
    pub deadband: Real,
    /// Whether a put may write it.
    pub writable: bool,
    /// Keep its values in the cell's history (`[history] tag_values` of them at most), so a
    /// client that was away can ask for what it missed, and utilisation can count parts.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub history: bool,
    /// What the tag is in MTConnect (`mtconnect = { type = "TEMPERATURE", units = "CELSIUS" }`);
    /// `None`: a VARIABLE event.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mtconnect: Option<TagMtconnect>,
}

/// A tag's MTConnect data item type and units (docs/mtconnect.md).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TagMtconnect {
    /// One of [`super::mtconnect_types::TAG_TYPES`], as the standard spells it.
    #[serde(rename = "type")]
    pub kind: String,
    /// The units the tag's value (after `scale`) is in, for a SAMPLE type: one of the
    /// standard's; default the type's own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub units: Option<String>,
}

impl TagConfig {
    /// The poll interval when the tag sets none, ms.
    pub const DEFAULT_POLL_MS: u32 = 1000;
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawTag {
    name: Option<String>,
    station: Option<u8>,
    module: Option<String>,
    address: Option<u16>,
    #[serde(rename = "type")]
    kind: Option<TagType>,
    bit: Option<u8>,
    scale: Option<f64>,
    poll_ms: Option<u32>,
    deadband: Option<f64>,
    #[serde(default)]
    writable: bool,
    #[serde(default)]
    history: bool,
    mtconnect: Option<TagMtconnect>,
}

/// What the simulated PLC of a `transport.kind = "sim"` link does by itself (`[plcs.sim]`),
/// so that its tags change without an operator.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct PlcSimConfig {
    /// Message numbers registered for transfers from the PC (others get STA A7, §5-3-5).
    #[serde(default)]
    pub messages: Vec<u8>,
    /// Words the simulated sequence program changes periodically.
    #[serde(default, rename = "tick")]
    pub ticks: Vec<SimTick>,
}

impl PlcSimConfig {
    /// Whether nothing is set: no messages and no ticks.
    pub fn is_empty(&self) -> bool {
        *self == PlcSimConfig::default()
    }
}

/// One word the simulated PLC changes every `every_ms`: adds `add` (wrapping at the word
/// size) and/or flips the bits of `xor`. Not a MICREX-F feature: the simulator's stand-in for
/// a sequence program.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimTick {
    /// The station (RSNO) of the word; default 00.
    #[serde(default)]
    pub station: u8,
    /// The memory module of the word, e.g. `D`.
    pub module: Module,
    /// The word's relative address in the module.
    pub address: u16,
    /// How often the word changes, ms (10..=3600000).
    pub every_ms: u32,
    /// Added to the word each time, wrapping at the word size (default 0).
    #[serde(default)]
    pub add: u32,
    /// Bits flipped each time, after the addition (default 0).
    #[serde(default)]
    pub xor: u32,
}

/// A tag's `mtconnect`: a type a tag may be, units of the standard's for a SAMPLE only, and no
/// bit reported as a measurement.
fn check_tag_mtconnect(c: &mut Checker, tl: &str, kind: TagType, m: &TagMtconnect) {
    use super::mtconnect_types::{self as types, TagCategory as Category};
    let Some(t) = types::tag_type(&m.kind) else {
        c.invalid(
            format!("{tl}.mtconnect.type"),
            q(&m.kind),
            format!(
                "not a type a tag may be in MTConnect: {}",
                types::TAG_TYPES
                    .iter()
                    .map(|t| t.name)
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
            "MTConnect Part 2",
        );
        return;
    };
    if t.category == Category::Sample && kind == TagType::Bit {
        c.invalid(
            format!("{tl}.mtconnect.type"),
            q(&m.kind),
            "a bit is no measurement: a bit tag is a VARIABLE".to_string(),
            "MTConnect Part 2",
        );
    }
    match (&m.units, t.category) {
        (Some(u), Category::Sample) if types::units(u).is_none() => c.invalid(
            format!("{tl}.mtconnect.units"),
            q(u),
            "not one of the standard's units (e.g. CELSIUS, PASCAL, REVOLUTION/MINUTE, PERCENT)"
                .to_string(),
            "MTConnect Part 2 UnitsEnum",
        ),
        (Some(_), Category::Event) => c.not_applicable(
            format!("{tl}.mtconnect.units"),
            format!("{} is an EVENT, which has no units", t.name),
            "",
        ),
        _ => {}
    }
}

fn check_tags(c: &mut Checker, label: &str, p: &RawPlc) {
    let mut seen = std::collections::HashSet::new();
    for (i, t) in p.tags.iter().enumerate() {
        let tl = match &t.name {
            Some(n) => format!("{label}.tags.{n}"),
            None => format!("{label}.tags[{}]", i + 1),
        };
        match &t.name {
            None => c.missing(format!("{tl}.name"), "every [[plcs.tags]] needs a name"),
            Some(n) => {
                if !super::valid_name(n) {
                    c.invalid(
                        format!("{tl}.name"),
                        q(n),
                        "use only letters, digits, '_' and '-' (the name becomes a Zenoh key chunk)"
                            .to_string(),
                        "",
                    );
                }
                if !seen.insert(n.as_str()) {
                    c.invalid(
                        format!("{tl}.name"),
                        q(n),
                        "each tag name may appear once in its PLC".to_string(),
                        "",
                    );
                }
            }
        }
        if let Some(s) = t.station
            && !p.stations.contains(&s)
        {
            c.invalid(
                format!("{tl}.station"),
                s.to_string(),
                "not one of the PLC's stations".to_string(),
                "FFU120B §5-3 RSNO",
            );
        }
        let module = match &t.module {
            None => {
                c.missing(
                    format!("{tl}.module"),
                    "e.g. module = \"D\" (FFU120B §5-3-3)",
                );
                None
            }
            Some(m) => match Module::by_name(m) {
                Some(m) => Some(m),
                None => {
                    c.invalid(
                        format!("{tl}.module"),
                        q(m),
                        "no such module in the module table (B, M, K, F, A, D, W9, TS, TR, CS, CR, BD, WL, W21–W24, W30–W109, W120–W123)".to_string(),
                        "FFU120B §5-3-3",
                    );
                    None
                }
            },
        };
        if t.address.is_none() {
            c.missing(
                format!("{tl}.address"),
                "the relative word address (FFU120B §5-4)",
            );
        }
        let Some(kind) = t.kind else {
            c.missing(
                format!("{tl}.type"),
                "one of \"bit\", \"u16\", \"i16\", \"u32\", \"i32\", \"bcd\"",
            );
            continue;
        };
        if let Some(m) = module {
            let bits = m.word_bytes() * 8;
            match (kind, t.bit) {
                (TagType::Bit, None) => c.missing(
                    format!("{tl}.bit"),
                    "the bit of the word, 0 = least significant",
                ),
                (TagType::Bit, Some(b)) if usize::from(b) >= bits => c.invalid(
                    format!("{tl}.bit"),
                    b.to_string(),
                    format!("a word of module {m} has {bits} bits: 0..={}", bits - 1),
                    "FFU120B §5-3-3",
                ),
                (TagType::Bit, _) => {}
                (_, Some(_)) => c.not_applicable(
                    format!("{tl}.bit"),
                    "used only with type = \"bit\"".to_string(),
                    "",
                ),
                (_, None) => {}
            }
            if matches!(kind, TagType::U16 | TagType::I16) && bits == 32 {
                c.invalid(
                    format!("{tl}.type"),
                    toml_name(&kind),
                    format!("module {m} has 32-bit words: use u32, i32, bcd or bit"),
                    "FFU120B §5-3-3",
                );
            }
            if let Some(a) = t.address
                && u32::from(a) + u32::from(kind.words(m)) > 0x1_0000
            {
                c.invalid(
                    format!("{tl}.address"),
                    a.to_string(),
                    "the tag's words lie beyond relative address 65535".to_string(),
                    "FFU120B §5-4",
                );
            }
        }
        if let Some(m) = &t.mtconnect {
            check_tag_mtconnect(c, &tl, kind, m);
        }
        if let Some(s) = t.scale
            && (!s.is_finite() || s == 0.0)
        {
            c.invalid(
                format!("{tl}.scale"),
                s.to_string(),
                "must be a finite number other than 0".to_string(),
                "",
            );
        }
        if let Some(d) = t.deadband
            && (!d.is_finite() || d < 0.0)
        {
            c.invalid(
                format!("{tl}.deadband"),
                d.to_string(),
                "must be a finite number ≥ 0".to_string(),
                "",
            );
        }
        if let Some(ms) = t.poll_ms {
            c.range(|| format!("{tl}.poll_ms"), ms, 10, 3_600_000, " ms", "");
        }
    }
    let is_sim = p.transport.as_ref().is_some_and(RawTransport::is_sim);
    if let Some(sim) = &p.sim {
        if !is_sim {
            c.not_applicable(
                format!("{label}.sim"),
                "used only with transport.kind = \"sim\"; remove the table".to_string(),
                "",
            );
        }
        for (i, t) in sim.ticks.iter().enumerate() {
            let path = format!("{label}.sim.tick[{}]", i + 1);
            if !p.stations.contains(&t.station) {
                c.invalid(
                    format!("{path}.station"),
                    t.station.to_string(),
                    "not one of the PLC's stations".to_string(),
                    "",
                );
            }
            c.range(
                || format!("{path}.every_ms"),
                t.every_ms,
                10,
                3_600_000,
                " ms",
                "",
            );
        }
    }
}

impl RawTag {
    fn into_config(self, label: &str, first_station: u8) -> Result<TagConfig, ConfigErrors> {
        let missing = |path: String| ConfigError::Missing {
            path,
            hint: "required".to_string(),
        };
        let name = self
            .name
            .ok_or_else(|| missing(format!("{label}.tags.name")))?;
        let module_name = self
            .module
            .ok_or_else(|| missing(format!("{label}.tags.{name}.module")))?;
        Ok(TagConfig {
            station: self.station.unwrap_or(first_station),
            module: Module::by_name(&module_name)
                .ok_or_else(|| missing(format!("{label}.tags.{name}.module")))?,
            address: self
                .address
                .ok_or_else(|| missing(format!("{label}.tags.{name}.address")))?,
            kind: self
                .kind
                .ok_or_else(|| missing(format!("{label}.tags.{name}.type")))?,
            bit: self.bit,
            scale: Real(self.scale.unwrap_or(1.0)),
            poll_ms: self.poll_ms.unwrap_or(TagConfig::DEFAULT_POLL_MS),
            deadband: Real(self.deadband.unwrap_or(0.0)),
            writable: self.writable,
            history: self.history,
            mtconnect: self.mtconnect,
            name,
        })
    }
}

impl From<&TagConfig> for RawTag {
    fn from(t: &TagConfig) -> Self {
        RawTag {
            name: Some(t.name.clone()),
            station: Some(t.station),
            module: Some(t.module.to_string()),
            address: Some(t.address),
            kind: Some(t.kind),
            bit: t.bit,
            scale: Some(t.scale.0),
            poll_ms: Some(t.poll_ms),
            deadband: Some(t.deadband.0),
            writable: t.writable,
            history: t.history,
            mtconnect: t.mtconnect.clone(),
        }
    }
}
