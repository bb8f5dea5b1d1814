//! `[[plcs]]`: one Fuji MICREX-F PLC through an FFU120B module, the initial-file settings
//! both ends must agree on (FFU120B §4-3), and their checks.

use serde::{Deserialize, Serialize};

use super::error::ConfigErrors;
use super::error::{Checker, ConfigError, list_u32, q, toml_name};
use super::transport::{
    RawTransport, TransportConfig, built_transport, check_transport, transport_of,
};
use crate::fuji::command::Module;

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
    /// Named values polled from the PLC (`[[plcs.tags]]`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub tags: Vec<TagConfig>,
    /// What the simulated PLC does by itself (`[plcs.sim]`, sim transport only).
    #[serde(skip_serializing_if = "PlcSimConfig::is_empty")]
    pub sim: PlcSimConfig,
}

impl PlcConfig {
    pub const DEFAULT_TIMEOUT_MS: u32 = 2000;
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
    #[serde(default)]
    tags: Vec<RawTag>,
    sim: Option<PlcSimConfig>,
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

impl From<&PlcConfig> for RawPlc {
    fn from(c: &PlcConfig) -> Self {
        RawPlc {
            name: Some(c.name.clone()),
            mode: c.mode,
            stations: c.stations.clone(),
            start_code: c.start_code,
            start_codes: c.start_codes.clone(),
            end_code: c.end_code,
            end_codes: c.end_codes.clone(),
            bcc: c.bcc,
            bcc_range: c.bcc_range,
            bcc_calc: c.bcc_calc,
            bcc_code: c.bcc_code,
            transposition: c.transposition,
            timeout_ms: c.timeout_ms,
            transport: Some(RawTransport::from(&c.transport)),
            tags: c.tags.iter().map(RawTag::from).collect(),
            sim: (c.sim != PlcSimConfig::default()).then(|| c.sim.clone()),
        }
    }
}

impl RawPlc {
    /// The validated PLC; `label` names it in the errors of a key still absent.
    pub(super) fn into_config(self, label: &str) -> Result<PlcConfig, ConfigErrors> {
        let missing = |path: String| ConfigError::Missing {
            path,
            hint: "required".to_string(),
        };
        let first = self.stations.first().copied().unwrap_or(0);
        Ok(PlcConfig {
            name: self.name.ok_or_else(|| missing(format!("{label}.name")))?,
            mode: self.mode,
            stations: self.stations,
            start_code: self.start_code,
            start_codes: self.start_codes,
            end_code: self.end_code,
            end_codes: self.end_codes,
            bcc: self.bcc,
            bcc_range: self.bcc_range,
            bcc_calc: self.bcc_calc,
            bcc_code: self.bcc_code,
            transposition: self.transposition,
            timeout_ms: self.timeout_ms,
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
    U16,
    I16,
    /// In a 16-bit area: two words, the low word at `address` (the MICREX-F's 32-bit data
    /// layout); in a 32-bit area: one word.
    U32,
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
    pub module: Module,
    /// Relative address: words of the module (protocol notes 3).
    pub address: u16,
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
}

impl TagConfig {
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
    #[serde(default)]
    pub station: u8,
    pub module: Module,
    pub address: u16,
    pub every_ms: u32,
    #[serde(default)]
    pub add: u32,
    #[serde(default)]
    pub xor: u32,
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
        }
    }
}
