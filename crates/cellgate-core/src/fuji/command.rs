//! The command-set text of modes 1–3 (FFU120B §5-3, §5-4, §7; FFU120B notes 1–5, 8).
//!
//! Every text, request or reply, is a five-byte header and a body (the §7-2 sample
//! `:000000010400000200` reads `00 00 00 01 04 | 00 00 02 00`):
//!
//! ```text
//!   request: CMND RSNO MODE MOLN BYTEN body      RSNO: station, BCD 00–99 (00 in mode 1)
//!   reply:   CMND STA  MODE MOLN BYTEN body      MODE | 80h in modes 2 and 3 (§5-4 note)
//! ```
//!
//! BYTEN counts the body's bytes. The bodies (relative address and count low byte first,
//! §5-4 "L H"):
//!
//! | text | request body | reply body |
//! |---|---|---|
//! | read 00/00 | address(2) count(2) | address(2) count(2) ATTR data — BYTEN = 5 + N |
//! | write 01/00 | address(2) count(2) data | address(2) count(2) |
//! | clear 01/05 | — | — |
//! | transfer 90/00 (PC → PLC) | data (MOLN = message number) | — |
//! | transfer 90/00 (PLC → PC) | data, unsolicited, no answer (FFU120B notes 8) | |
//!
//! An error reply is the header alone with BYTEN 00 and the STA code (FFU120B notes 2). The relative
//! address counts words of the module; the count is in bytes and must be whole words (2 for
//! 16-bit areas, 4 for 32-bit), else STA 21 (FFU120B notes 3). Read at most 212 bytes, write and
//! transfer at most 220 (§5-3-2).
//!
//! Byte order of the data (§5-3-6, notes 4): 16-bit areas (attribute 01) high byte first;
//! 32-bit areas (02 BCD, 04 DI) and SI files (03) low byte first.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use super::frame::MIN_COMMAND_TEXT;
use crate::codes::BusCode;
use crate::pb;

/// Most bytes one read may ask for (§5-3-2).
pub const MAX_READ: usize = 212;
/// Most data bytes one write carries (§5-3-2).
pub const MAX_WRITE: usize = 220;
/// Most data bytes one transfer carries (§5-3-2).
pub const MAX_TRANSFER: usize = 220;

/// CMND codes (§5-3-2).
pub const CMND_READ: u8 = 0x00;
/// CMND of a write or a clear (01).
pub const CMND_WRITE: u8 = 0x01;
/// CMND of a transfer (90).
pub const CMND_TRANSFER: u8 = 0x90;
/// MODE codes (§5-3-2).
pub const MODE_ADDRESS: u8 = 0x00;
/// MODE of a clear (05).
pub const MODE_CLEAR: u8 = 0x05;
/// The bit replies carry in MODE in modes 2 and 3 (§5-4 note).
pub const MODE_MULTI_DROP: u8 = 0x80;

/// Module attribute (§5-3-4): what a word of the module is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Attribute {
    /// 01: 16-bit data except SI files; high byte first.
    Word16,
    /// 02: BCD 8 digits (32 bits); low byte first.
    Bcd32,
    /// 03: SI file (16 bits); low byte first.
    Si,
    /// 04: DI file (32 bits); low byte first.
    Di,
}

impl Attribute {
    /// The ATTR code (§5-3-4).
    pub fn code(self) -> u8 {
        match self {
            Attribute::Word16 => 0x01,
            Attribute::Bcd32 => 0x02,
            Attribute::Si => 0x03,
            Attribute::Di => 0x04,
        }
    }

    /// The attribute of ATTR code `code`; `None` for a code other than 01–04.
    pub fn from_code(code: u8) -> Option<Attribute> {
        match code {
            0x01 => Some(Attribute::Word16),
            0x02 => Some(Attribute::Bcd32),
            0x03 => Some(Attribute::Si),
            0x04 => Some(Attribute::Di),
            _ => None,
        }
    }

    /// Bytes of one word: 2 or 4.
    pub fn word_bytes(self) -> usize {
        match self {
            Attribute::Word16 | Attribute::Si => 2,
            Attribute::Bcd32 | Attribute::Di => 4,
        }
    }

    /// Whether a word travels low byte first (§5-3-6, FFU120B notes 4).
    pub fn low_byte_first(self) -> bool {
        !matches!(self, Attribute::Word16)
    }
}

/// The type a file W30–W109 was defined with (§5-3-3: SI 16 bits, DI and BD 32 bits).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "UPPERCASE")]
pub enum FileType {
    /// SI: 16-bit words, attribute 03; the default.
    #[default]
    Si,
    /// DI: 32-bit words, attribute 04.
    Di,
    /// BD: BCD 8 digits (32 bits), attribute 02.
    Bd,
}

impl FileType {
    /// The attribute a file of this type has (§5-3-4).
    pub fn attribute(self) -> Attribute {
        match self {
            FileType::Si => Attribute::Si,
            FileType::Di => Attribute::Di,
            FileType::Bd => Attribute::Bcd32,
        }
    }
}

/// A module of the MICREX-F's memory, by its number (MOLN) and attribute (§5-3-3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct Module {
    number: u8,
    attribute: Attribute,
}

/// First and last file module: W30 (1Eh) to W109 (6Dh).
pub const FIRST_FILE: u8 = 30;
/// The last file module, W109 (6Dh).
pub const LAST_FILE: u8 = 109;

/// The fixed part of the module table (§5-3-3), by symbol.
const TABLE: [(&str, u8, Attribute); 21] = [
    ("B", 0x00, Attribute::Word16),
    ("M", 0x01, Attribute::Word16),
    ("K", 0x02, Attribute::Word16),
    ("F", 0x03, Attribute::Word16),
    ("A", 0x04, Attribute::Word16),
    ("D", 0x05, Attribute::Word16),
    ("W9", 0x09, Attribute::Bcd32),
    ("TS", 0x0A, Attribute::Bcd32),
    ("TR", 0x0B, Attribute::Bcd32),
    ("CS", 0x0C, Attribute::Bcd32),
    ("CR", 0x0D, Attribute::Bcd32),
    ("BD", 0x0E, Attribute::Bcd32),
    ("WL", 0x14, Attribute::Word16),
    ("W21", 0x15, Attribute::Word16),
    ("W22", 0x16, Attribute::Word16),
    ("W23", 0x17, Attribute::Word16),
    ("W24", 0x18, Attribute::Word16),
    ("W120", 0x78, Attribute::Word16),
    ("W121", 0x79, Attribute::Word16),
    ("W122", 0x7A, Attribute::Word16),
    ("W123", 0x7B, Attribute::Word16),
];

/// The module table's names, as a refusal lists them.
pub const MODULE_NAMES: &str = "B, M, K, F, A, D, W9, TS, TR, CS, CR, BD, WL, W21–W24, \
     W30–W109 (files: W30:DI, W31:BD), W120–W123";

/// The modules there are, after `did you mean TR or TS?` for a name near some of them.
fn modules_hint(name: &str) -> String {
    let symbols: Vec<&str> = TABLE.iter().map(|(s, _, _)| *s).collect();
    let near = crate::near::nearest(name.trim(), &symbols, 3);
    match near.split_last() {
        Some((last, first)) => {
            let first = if first.is_empty() {
                String::new()
            } else {
                format!("{} or ", first.join(", "))
            };
            format!("did you mean {first}{last}? Its modules are {MODULE_NAMES}")
        }
        None => format!("its modules are {MODULE_NAMES}"),
    }
}

impl Module {
    /// `B`: MOLN 00h, 16-bit words.
    pub const B: Module = Module::fixed(0x00, Attribute::Word16);
    /// `M`: MOLN 01h, 16-bit words.
    pub const M: Module = Module::fixed(0x01, Attribute::Word16);
    /// `K`: MOLN 02h, 16-bit words.
    pub const K: Module = Module::fixed(0x02, Attribute::Word16);
    /// `F`: MOLN 03h, 16-bit words.
    pub const F: Module = Module::fixed(0x03, Attribute::Word16);
    /// `A`: MOLN 04h, 16-bit words.
    pub const A: Module = Module::fixed(0x04, Attribute::Word16);
    /// `D`: MOLN 05h, 16-bit words.
    pub const D: Module = Module::fixed(0x05, Attribute::Word16);
    /// `W9`: MOLN 09h, BCD 8 digits (32 bits).
    pub const W9: Module = Module::fixed(0x09, Attribute::Bcd32);
    /// `TS`: MOLN 0Ah, BCD 8 digits (32 bits).
    pub const TS: Module = Module::fixed(0x0A, Attribute::Bcd32);
    /// `TR`: MOLN 0Bh, BCD 8 digits (32 bits).
    pub const TR: Module = Module::fixed(0x0B, Attribute::Bcd32);
    /// `CS`: MOLN 0Ch, BCD 8 digits (32 bits).
    pub const CS: Module = Module::fixed(0x0C, Attribute::Bcd32);
    /// `CR`: MOLN 0Dh, BCD 8 digits (32 bits).
    pub const CR: Module = Module::fixed(0x0D, Attribute::Bcd32);
    /// `BD`: MOLN 0Eh, BCD 8 digits (32 bits).
    pub const BD: Module = Module::fixed(0x0E, Attribute::Bcd32);
    /// `WL`: MOLN 14h, 16-bit words; only with a P-link card in an F120H.
    pub const WL: Module = Module::fixed(0x14, Attribute::Word16);
    /// `W24`: MOLN 18h, 16-bit words.
    pub const W24: Module = Module::fixed(0x18, Attribute::Word16);

    const fn fixed(number: u8, attribute: Attribute) -> Module {
        Module { number, attribute }
    }

    /// Every module of the fixed table (not the files W30–W109).
    pub fn fixed_table() -> impl Iterator<Item = Module> {
        TABLE
            .iter()
            .map(|&(_, number, attribute)| Module { number, attribute })
    }

    /// File `Wn`, n in 30..=109, defined as `file_type`.
    pub fn file(n: u8, file_type: FileType) -> Option<Module> {
        (FIRST_FILE..=LAST_FILE).contains(&n).then(|| Module {
            number: n,
            attribute: file_type.attribute(),
        })
    }

    /// The module of this number. Files take the attribute a reply reports (`attribute`),
    /// or SI when none is known; fixed modules take the table's.
    pub fn from_number(number: u8, attribute: Option<Attribute>) -> Option<Module> {
        if (FIRST_FILE..=LAST_FILE).contains(&number) {
            let attribute = match attribute {
                None => Attribute::Si,
                Some(a @ (Attribute::Si | Attribute::Di | Attribute::Bcd32)) => a,
                Some(Attribute::Word16) => return None,
            };
            return Some(Module { number, attribute });
        }
        TABLE
            .iter()
            .find(|(_, n, _)| *n == number)
            .map(|&(_, number, attribute)| Module { number, attribute })
    }

    /// Looks a module up by symbol, as §5-3-3 writes it: `B`, `M`, `K`, `F`, `A`, `D`,
    /// `W9`, `TS`, `TR`, `CS`, `CR`, `BD`, `WL`, `W21`–`W24`, `W120`–`W123`, and the files
    /// `W30`–`W109`, optionally with their type: `W30:SI` (the default), `W31:DI`, `W32:BD`.
    /// Case does not matter.
    pub fn by_name(name: &str) -> Option<Module> {
        let upper = name.trim().to_ascii_uppercase();
        let (symbol, file_type) = match upper.split_once(':') {
            Some((s, t)) => {
                let t = match t {
                    "SI" => FileType::Si,
                    "DI" => FileType::Di,
                    "BD" => FileType::Bd,
                    _ => return None,
                };
                (s, Some(t))
            }
            None => (upper.as_str(), None),
        };
        if let Some(&(_, number, attribute)) = TABLE.iter().find(|(s, _, _)| *s == symbol) {
            return file_type.is_none().then_some(Module { number, attribute });
        }
        let n: u8 = symbol.strip_prefix('W')?.parse().ok()?;
        Module::file(n, file_type.unwrap_or_default())
    }

    /// MOLN.
    pub fn number(self) -> u8 {
        self.number
    }

    /// The module's attribute (§5-3-4).
    pub fn attribute(self) -> Attribute {
        self.attribute
    }

    /// Bytes per word: 2 or 4.
    pub fn word_bytes(self) -> usize {
        self.attribute.word_bytes()
    }

    /// Whether the module is one of the files W30–W109.
    pub fn is_file(self) -> bool {
        (FIRST_FILE..=LAST_FILE).contains(&self.number)
    }

    /// WL, W21–W23 and W120–W123 exist only with a P-link card in an F120H (§5-3-3 note).
    pub fn needs_p_link(self) -> bool {
        matches!(self.number, 0x14..=0x17 | 0x78..=0x7B)
    }

    /// The symbol of §5-3-3 (`D`, `W30`).
    pub fn symbol(self) -> String {
        if self.is_file() {
            return format!("W{}", self.number);
        }
        TABLE
            .iter()
            .find(|(_, n, _)| *n == self.number)
            .map_or_else(
                || format!("module {:02X}h", self.number),
                |(s, _, _)| (*s).to_string(),
            )
    }
}

impl fmt::Display for Module {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.symbol())?;
        match (self.is_file(), self.attribute) {
            (true, Attribute::Di) => f.write_str(":DI"),
            (true, Attribute::Bcd32) => f.write_str(":BD"),
            _ => Ok(()),
        }
    }
}

impl FromStr for Module {
    type Err = CommandError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Module::by_name(s).ok_or_else(|| CommandError::UnknownModule {
            name: s.to_string(),
        })
    }
}

impl TryFrom<String> for Module {
    type Error = CommandError;
    fn try_from(s: String) -> Result<Self, Self::Error> {
        s.parse()
    }
}

impl From<Module> for String {
    fn from(m: Module) -> String {
        m.to_string()
    }
}

/// A processing status other than 00 "end normally" (§5-3-5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
pub enum Sta {
    /// 12: memory write error.
    MemoryWrite,
    /// 20: undefined command.
    UndefinedCommand,
    /// 21: parameter error.
    Parameter,
    /// 22: in interlock.
    Interlock,
    /// 24: module number error.
    ModuleNumber,
    /// 32: over memory size.
    OverMemorySize,
    /// A7: error in a transfer command.
    Transfer,
    /// A code the manual does not list.
    Other(u8),
}

impl Sta {
    /// The status of a STA byte; `None` for 00, end normally.
    pub fn from_code(code: u8) -> Option<Sta> {
        Some(match code {
            0x00 => return None,
            0x12 => Sta::MemoryWrite,
            0x20 => Sta::UndefinedCommand,
            0x21 => Sta::Parameter,
            0x22 => Sta::Interlock,
            0x24 => Sta::ModuleNumber,
            0x32 => Sta::OverMemorySize,
            0xA7 => Sta::Transfer,
            other => Sta::Other(other),
        })
    }

    /// The STA byte of this status.
    pub fn code(self) -> u8 {
        match self {
            Sta::MemoryWrite => 0x12,
            Sta::UndefinedCommand => 0x20,
            Sta::Parameter => 0x21,
            Sta::Interlock => 0x22,
            Sta::ModuleNumber => 0x24,
            Sta::OverMemorySize => 0x32,
            Sta::Transfer => 0xA7,
            Sta::Other(c) => c,
        }
    }

    /// What the manual says the code means (§5-3-5).
    pub fn meaning(self) -> &'static str {
        match self {
            Sta::MemoryWrite => "memory write error: the data would go into the program area",
            Sta::UndefinedCommand => "undefined command: the module has no such command code",
            Sta::Parameter => {
                "parameter error: the request does not agree with its command (e.g. a byte \
                 count that is not whole words of the area)"
            }
            Sta::Interlock => "module in interlock: only the loader may read or write now",
            Sta::ModuleNumber => "module number error: no such module in this PLC",
            Sta::OverMemorySize => "over memory size: the address lies beyond the module",
            Sta::Transfer => {
                "transfer command error (is a message module registered for this number?)"
            }
            Sta::Other(_) => "status code the manual does not list",
        }
    }
}

impl fmt::Display for Sta {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} (STA {:02X}, FFU120B §5-3-5)",
            self.meaning(),
            Sta::code(*self)
        )
    }
}

/// An error reply: the module processed the request and refused it (§5-3-5).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "{sta}; station {station:02}, command {cmnd:02X}/{mode:02X}, {}{}",
    moln_name(*.cmnd, *.module),
    address.map(|a| format!(", address {a}")).unwrap_or_default()
)]
pub struct StaError {
    /// The processing status the module replied.
    pub sta: Sta,
    /// The station that replied.
    pub station: u8,
    /// CMND of the request.
    pub cmnd: u8,
    /// MODE of the request.
    pub mode: u8,
    /// MOLN: the module, or the message number of a transfer.
    pub module: u8,
    /// The relative address of a read or a write; `None` for the other requests.
    pub address: Option<u16>,
}

/// What MOLN names: the message number of a transfer, else the module.
fn moln_name(cmnd: u8, moln: u8) -> String {
    if cmnd == CMND_TRANSFER {
        format!("message {moln}")
    } else {
        format!("module {}", module_name(moln))
    }
}

fn module_name(moln: u8) -> String {
    match Module::from_number(moln, None) {
        Some(m) => format!("{} ({moln:02X}h)", m.symbol()),
        None => format!("{moln:02X}h"),
    }
}

/// A request refused before anything was sent: the module would refuse it, or it cannot be
/// written as a text.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum CommandError {
    /// A module name that is not in the module table.
    #[error(
        "no module {name:?} in the module table (FFU120B §5-3-3); {}",
        modules_hint(name)
    )]
    UnknownModule {
        /// The name given.
        name: String,
    },
    /// A byte count that is not a whole number of the module's words (STA 21).
    #[error(
        "{bytes} bytes is not a whole number of {word_bytes}-byte words of module {module}: the module would answer STA 21 (FFU120B §5-3, §5-3-5)"
    )]
    ByteCount {
        /// The module.
        module: Module,
        /// The byte count given.
        bytes: usize,
        /// Bytes per word of the module: 2 or 4.
        word_bytes: usize,
    },
    /// More bytes than one request carries (§5-3-2).
    #[error("{what} of {bytes} bytes exceeds {max} (FFU120B §5-3-2)")]
    TooMany {
        /// The request: `read`, `write` or `transfer`.
        what: &'static str,
        /// The bytes asked for.
        bytes: usize,
        /// The most the request carries.
        max: usize,
    },
    /// A read or write of no bytes.
    #[error("{what} of no bytes: give at least one word (FFU120B §5-3)")]
    Empty {
        /// The request: `read` or `write`.
        what: &'static str,
    },
    /// Words that run past relative address 65535 (§5-4).
    #[error(
        "words {address}..{address}+{words} of module {module} lie beyond relative address 65535 (FFU120B §5-4)"
    )]
    AddressRange {
        /// The module.
        module: Module,
        /// The first word's relative address.
        address: u16,
        /// Words asked for.
        words: usize,
    },
    /// A value wider than a word of the module.
    #[error("value {value:#x} does not fit a {bits}-bit word of module {module} (FFU120B §5-3-3)")]
    ValueTooWide {
        /// The module.
        module: Module,
        /// The value given.
        value: u32,
        /// Bits in a word of the module.
        bits: u32,
    },
    /// A station number that two BCD digits cannot carry.
    #[error(
        "station {station} is not a station number: RSNO is two BCD digits, 00–99 (FFU120B §5-3)"
    )]
    Station {
        /// The station number given.
        station: u8,
    },
    /// A request the link's operation mode does not have.
    #[error("{what} is not available in mode {mode} (FFU120B {section})")]
    NotInMode {
        /// What was asked for (e.g. "the transfer command").
        what: &'static str,
        /// The operation mode (1–5, as the MODE dial shows it).
        mode: u8,
        /// The manual section that says so.
        section: &'static str,
    },
    /// A non-procedure message of a length the module does not take (§5-5, §4-3 item 15).
    #[error(
        "non-procedure message of {bytes} bytes: the module takes {want} (FFU120B §5-5, §4-3 item 15)"
    )]
    MessageLength {
        /// Bytes in the message.
        bytes: usize,
        /// The lengths the module takes, as text (e.g. "1 to 216").
        want: String,
    },
    /// A variable-length message without code transposition whose data holds the end code:
    /// the module would end the message there (§4-3 items 14, 15, 17; FFU120B notes 9).
    #[error(
        "non-procedure message byte {offset} starts the end code {end:02X?}: without code transposition a variable-length message ends at it (FFU120B §4-3 items 14, 17; use fixed length or transposition)"
    )]
    EndCodeInMessage {
        /// Where in the message the end code starts.
        offset: usize,
        /// The end code's bytes.
        end: Vec<u8>,
    },
}

/// The header and body of a command-set text, request or reply (§5-3-1).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CommandText {
    /// CMND.
    pub cmnd: u8,
    /// RSNO in a request (BCD), STA in a reply.
    pub second: u8,
    /// MODE; a reply in modes 2 and 3 carries [`MODE_MULTI_DROP`] as well.
    pub mode: u8,
    /// MOLN: module number, or message number of a transfer.
    pub moln: u8,
    /// The bytes after BYTEN.
    pub body: Vec<u8>,
}

impl CommandText {
    /// Splits a decoded text; BYTEN must count the body exactly (else the module's receive
    /// error 7, text form unidentified, §5-6).
    pub fn parse(text: &[u8]) -> Result<CommandText, super::frame::TextForm> {
        use super::frame::TextForm;
        let [cmnd, second, mode, moln, byten, body @ ..] = text else {
            return Err(TextForm::TooShort {
                len: text.len(),
                min: MIN_COMMAND_TEXT,
            });
        };
        if usize::from(*byten) != body.len() {
            return Err(TextForm::Byten {
                byten: *byten,
                actual: body.len(),
            });
        }
        Ok(CommandText {
            cmnd: *cmnd,
            second: *second,
            mode: *mode,
            moln: *moln,
            body: body.to_vec(),
        })
    }

    /// The text's bytes. A body is at most 255 bytes: longer ones are cut (callers check
    /// their limits first).
    pub fn encode(&self) -> Vec<u8> {
        let body = self.body.get(..255).unwrap_or(&self.body);
        let mut t = Vec::with_capacity(MIN_COMMAND_TEXT + body.len());
        t.extend_from_slice(&[
            self.cmnd,
            self.second,
            self.mode,
            self.moln,
            u8::try_from(body.len()).unwrap_or(u8::MAX),
        ]);
        t.extend_from_slice(body);
        t
    }

    /// A reply's MODE without the multi-drop bit.
    pub fn plain_mode(&self) -> u8 {
        self.mode & !MODE_MULTI_DROP
    }
}

/// A request of the command set (§5-3-2).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Request {
    /// Read `bytes` bytes from word `address` of `module` (00/00).
    Read {
        /// The module to read.
        module: Module,
        /// The first word's relative address.
        address: u16,
        /// Bytes to read, whole words.
        bytes: u16,
    },
    /// Write `data` (as it travels, see [`encode_words`]) from word `address` (01/00).
    Write {
        /// The module to write.
        module: Module,
        /// The first word's relative address.
        address: u16,
        /// The bytes to write, whole words in the module's byte order.
        data: Vec<u8>,
    },
    /// Clear the module (01/05).
    Clear {
        /// The module to clear.
        module: Module,
    },
    /// Transfer `data` to the PLC's message module `message` (90/00, mode 1 only).
    Transfer {
        /// The message number (MOLN).
        message: u8,
        /// The bytes to transfer.
        data: Vec<u8>,
    },
}

impl Request {
    /// Read `words` words from `address`.
    pub fn read_words(module: Module, address: u16, words: usize) -> Result<Request, CommandError> {
        let bytes = words.saturating_mul(module.word_bytes());
        let r = Request::Read {
            module,
            address,
            bytes: u16::try_from(bytes).unwrap_or(u16::MAX),
        };
        r.check()?;
        Ok(r)
    }

    /// Write `values` from `address`, each as one word of the module in its byte order.
    pub fn write_words(
        module: Module,
        address: u16,
        values: &[u32],
    ) -> Result<Request, CommandError> {
        let r = Request::Write {
            module,
            address,
            data: encode_words(module, values)?,
        };
        r.check()?;
        Ok(r)
    }

    /// The request's CMND.
    pub fn cmnd(&self) -> u8 {
        match self {
            Request::Read { .. } => CMND_READ,
            Request::Write { .. } | Request::Clear { .. } => CMND_WRITE,
            Request::Transfer { .. } => CMND_TRANSFER,
        }
    }

    /// The request's MODE.
    pub fn mode(&self) -> u8 {
        match self {
            Request::Clear { .. } => MODE_CLEAR,
            _ => MODE_ADDRESS,
        }
    }

    /// MOLN: the module, or the message number.
    pub fn moln(&self) -> u8 {
        match self {
            Request::Read { module, .. }
            | Request::Write { module, .. }
            | Request::Clear { module } => module.number(),
            Request::Transfer { message, .. } => *message,
        }
    }

    /// The request's name in messages: `read`, `write`, `clear` or `transfer`.
    pub fn name(&self) -> &'static str {
        match self {
            Request::Read { .. } => "read",
            Request::Write { .. } => "write",
            Request::Clear { .. } => "clear",
            Request::Transfer { .. } => "transfer",
        }
    }

    /// The relative address of a read or a write; `None` for the other requests.
    pub fn address(&self) -> Option<u16> {
        match self {
            Request::Read { address, .. } | Request::Write { address, .. } => Some(*address),
            _ => None,
        }
    }

    /// Refuses what the module would refuse with STA 21, or what cannot be a text.
    pub fn check(&self) -> Result<(), CommandError> {
        let span = |what: &'static str, module: Module, address: u16, bytes: usize, max: usize| {
            if bytes == 0 {
                return Err(CommandError::Empty { what });
            }
            if bytes > max {
                return Err(CommandError::TooMany { what, bytes, max });
            }
            let word_bytes = module.word_bytes();
            if bytes % word_bytes != 0 {
                return Err(CommandError::ByteCount {
                    module,
                    bytes,
                    word_bytes,
                });
            }
            let words = bytes / word_bytes;
            if usize::from(address) + words > 0x1_0000 {
                return Err(CommandError::AddressRange {
                    module,
                    address,
                    words,
                });
            }
            Ok(())
        };
        match self {
            Request::Read {
                module,
                address,
                bytes,
            } => span("read", *module, *address, usize::from(*bytes), MAX_READ),
            Request::Write {
                module,
                address,
                data,
            } => span("write", *module, *address, data.len(), MAX_WRITE),
            Request::Clear { .. } => Ok(()),
            Request::Transfer { data, .. } => {
                if data.len() > MAX_TRANSFER {
                    Err(CommandError::TooMany {
                        what: "transfer",
                        bytes: data.len(),
                        max: MAX_TRANSFER,
                    })
                } else {
                    Ok(())
                }
            }
        }
    }

    /// The request's text for `station` (0–99, sent as BCD).
    pub fn to_text(&self, station: u8) -> Result<CommandText, CommandError> {
        self.check()?;
        let rsno = to_bcd(station).ok_or(CommandError::Station { station })?;
        let body = match self {
            Request::Read { address, bytes, .. } => {
                let mut b = address.to_le_bytes().to_vec();
                b.extend_from_slice(&bytes.to_le_bytes());
                b
            }
            Request::Write { address, data, .. } => {
                let mut b = address.to_le_bytes().to_vec();
                b.extend_from_slice(&u16::try_from(data.len()).unwrap_or(0).to_le_bytes());
                b.extend_from_slice(data);
                b
            }
            Request::Clear { .. } => Vec::new(),
            Request::Transfer { data, .. } => data.clone(),
        };
        Ok(CommandText {
            cmnd: self.cmnd(),
            second: rsno,
            mode: self.mode(),
            moln: self.moln(),
            body,
        })
    }

    /// The request's text for `station`, as bytes (see [`Request::to_text`]).
    pub fn encode(&self, station: u8) -> Result<Vec<u8>, CommandError> {
        Ok(self.to_text(station)?.encode())
    }

    /// Whether `reply` answers this request: same CMND, MODE (multi-drop bit aside) and MOLN.
    pub fn answered_by(&self, reply: &CommandText) -> bool {
        reply.cmnd == self.cmnd() && reply.plain_mode() == self.mode() && reply.moln == self.moln()
    }

    /// Reads `reply`, which [answers](Request::answered_by) this request to `station`.
    pub fn parse_reply(&self, station: u8, reply: &CommandText) -> Result<Reply, ReplyError> {
        if let Some(sta) = Sta::from_code(reply.second) {
            return Err(ReplyError::Sta(StaError {
                sta,
                station,
                cmnd: self.cmnd(),
                mode: self.mode(),
                module: self.moln(),
                address: self.address(),
            }));
        }
        let malformed = |problem| ReplyError::Malformed {
            station,
            request: self.name(),
            problem,
        };
        let echo = |body: &[u8], address: u16, bytes: u16| -> Result<(), ReplyError> {
            let (a, n) = match body {
                [a0, a1, n0, n1, ..] => (
                    u16::from_le_bytes([*a0, *a1]),
                    u16::from_le_bytes([*n0, *n1]),
                ),
                _ => {
                    return Err(malformed(Malformed::Body {
                        len: body.len(),
                        want: 4,
                    }));
                }
            };
            if a != address {
                return Err(malformed(Malformed::Echo {
                    field: "relative address",
                    want: address,
                    got: a,
                }));
            }
            if n != bytes {
                return Err(malformed(Malformed::Echo {
                    field: "byte count",
                    want: bytes,
                    got: n,
                }));
            }
            Ok(())
        };
        match self {
            Request::Read {
                module,
                address,
                bytes,
            } => {
                let Some((&attr, data)) = reply.body.get(4..).and_then(|r| r.split_first()) else {
                    return Err(malformed(Malformed::Body {
                        len: reply.body.len(),
                        want: 5 + usize::from(*bytes),
                    }));
                };
                echo(&reply.body, *address, *bytes)?;
                if attr != module.attribute().code() {
                    return Err(malformed(Malformed::Attribute {
                        want: module.attribute().code(),
                        got: attr,
                    }));
                }
                if data.len() != usize::from(*bytes) {
                    return Err(malformed(Malformed::Body {
                        len: reply.body.len(),
                        want: 5 + usize::from(*bytes),
                    }));
                }
                Ok(Reply::Read {
                    module: *module,
                    address: *address,
                    words: decode_words(module.attribute(), data),
                    data: data.to_vec(),
                })
            }
            Request::Write {
                module,
                address,
                data,
            } => {
                let bytes = u16::try_from(data.len()).unwrap_or(0);
                if reply.body.len() != 4 {
                    return Err(malformed(Malformed::Body {
                        len: reply.body.len(),
                        want: 4,
                    }));
                }
                echo(&reply.body, *address, bytes)?;
                Ok(Reply::Written {
                    module: *module,
                    address: *address,
                    bytes,
                })
            }
            Request::Clear { module } => {
                if !reply.body.is_empty() {
                    return Err(malformed(Malformed::Body {
                        len: reply.body.len(),
                        want: 0,
                    }));
                }
                Ok(Reply::Cleared { module: *module })
            }
            Request::Transfer { message, .. } => {
                if !reply.body.is_empty() {
                    return Err(malformed(Malformed::Body {
                        len: reply.body.len(),
                        want: 0,
                    }));
                }
                Ok(Reply::Transferred { message: *message })
            }
        }
    }
}

/// What a request achieved.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum Reply {
    /// The data read, as it travelled, and as words in the module's byte order.
    Read {
        /// The module read.
        module: Module,
        /// The first word's relative address.
        address: u16,
        /// The data as it travelled.
        data: Vec<u8>,
        /// The data as words, in the module's byte order.
        words: Vec<u32>,
    },
    /// The module took the write.
    Written {
        /// The module written.
        module: Module,
        /// The first word's relative address.
        address: u16,
        /// Bytes written.
        bytes: u16,
    },
    /// The module was cleared.
    Cleared {
        /// The module cleared.
        module: Module,
    },
    /// The PLC took the transfer into message module `message`.
    Transferred {
        /// The message number (MOLN).
        message: u8,
    },
    /// A non-procedure message (modes 4–5) went onto the line; nothing answers it (§5-5).
    Sent {
        /// Bytes sent.
        bytes: usize,
    },
}

/// What is wrong with a reply that answers a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum Malformed {
    /// A body of the wrong length.
    #[error("body of {len} bytes, expected {want}")]
    Body {
        /// The body's length, bytes.
        len: usize,
        /// The length it must have, bytes.
        want: usize,
    },
    /// A relative address or byte count echoed other than requested.
    #[error("{field} {got} echoed, {want} requested")]
    Echo {
        /// Which field: `relative address` or `byte count`.
        field: &'static str,
        /// The value requested.
        want: u16,
        /// The value echoed.
        got: u16,
    },
    /// A read reply's ATTR other than the module's attribute.
    #[error(
        "attribute {got:02X} where the module has {want:02X} (§5-3-4; is the file type right?)"
    )]
    Attribute {
        /// The module's ATTR code.
        want: u8,
        /// The ATTR code received.
        got: u8,
    },
}

/// A reply that does not complete its request normally.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ReplyError {
    /// The module refused the request with a STA code (§5-3-5).
    #[error(transparent)]
    Sta(StaError),
    /// The reply does not have the form that answers the request (§5-4).
    #[error("malformed {request} reply from station {station:02}: {problem} (FFU120B §5-4)")]
    Malformed {
        /// The station that replied.
        station: u8,
        /// The request's name: `read`, `write`, `clear` or `transfer`.
        request: &'static str,
        /// What is wrong with the reply.
        problem: Malformed,
    },
}

/// A MICREX-F → PC transfer: `90 00 00 MSGNO BYTEN data`, which expects no answer (§5-4 iv,
/// FFU120B notes 8). `None` when `text` is something else.
pub fn unsolicited_transfer(text: &CommandText) -> Option<(u8, Vec<u8>)> {
    (text.cmnd == CMND_TRANSFER && text.second == 0 && text.plain_mode() == MODE_ADDRESS)
        .then(|| (text.moln, text.body.clone()))
}

/// The words of `data` in `attribute`'s byte order; a trailing partial word is dropped.
pub fn decode_words(attribute: Attribute, data: &[u8]) -> Vec<u32> {
    let n = attribute.word_bytes();
    let low_first = attribute.low_byte_first();
    data.chunks_exact(n)
        .map(|w| {
            let fold = |acc: u32, b: &u8| (acc << 8) | u32::from(*b);
            if low_first {
                w.iter().rev().fold(0, fold)
            } else {
                w.iter().fold(0, fold)
            }
        })
        .collect()
}

/// `values` as the words of `module` travel; a value too wide for a 16-bit word is refused.
pub fn encode_words(module: Module, values: &[u32]) -> Result<Vec<u8>, CommandError> {
    let attribute = module.attribute();
    let n = attribute.word_bytes();
    let mut out = Vec::with_capacity(values.len() * n);
    for &value in values {
        let le = value.to_le_bytes();
        if n == 2 {
            let word = u16::try_from(value).map_err(|_| CommandError::ValueTooWide {
                module,
                value,
                bits: 16,
            })?;
            if attribute.low_byte_first() {
                out.extend_from_slice(&word.to_le_bytes());
            } else {
                out.extend_from_slice(&word.to_be_bytes());
            }
        } else if attribute.low_byte_first() {
            out.extend_from_slice(&le);
        } else {
            out.extend_from_slice(&value.to_be_bytes());
        }
    }
    Ok(out)
}

/// Two BCD digits of `v` (0–99): RSNO (§5-3).
pub fn to_bcd(v: u8) -> Option<u8> {
    (v <= 99).then_some(((v / 10) << 4) | (v % 10))
}

/// The value of two BCD digits, `None` if a nibble is above 9.
pub fn from_bcd(b: u8) -> Option<u8> {
    let (hi, lo) = (b >> 4, b & 0xF);
    (hi <= 9 && lo <= 9).then(|| hi * 10 + lo)
}

/// Eight BCD digits of `v` (0–99 999 999): a word of a BCD area, attribute 02 (§5-3-4).
pub fn to_bcd8(mut v: u32) -> Option<u32> {
    if v > 99_999_999 {
        return None;
    }
    let mut out = 0u32;
    for i in 0..8 {
        out |= (v % 10) << (4 * i);
        v /= 10;
    }
    Some(out)
}

/// The value of eight BCD digits, `None` if a nibble is above 9.
pub fn from_bcd8(raw: u32) -> Option<u32> {
    let mut v = 0u32;
    for i in (0..8).rev() {
        let d = (raw >> (4 * i)) & 0xF;
        if d > 9 {
            return None;
        }
        v = v * 10 + d;
    }
    Some(v)
}

impl BusCode for Sta {
    fn code(&self) -> pb::ErrorCode {
        match self {
            Sta::MemoryWrite => pb::ErrorCode::PlcWriteProtected,
            Sta::UndefinedCommand => pb::ErrorCode::PlcUndefinedCommand,
            Sta::Parameter => pb::ErrorCode::PlcParameter,
            Sta::Interlock => pb::ErrorCode::PlcInterlock,
            Sta::ModuleNumber => pb::ErrorCode::PlcNoModule,
            Sta::OverMemorySize => pb::ErrorCode::PlcOverMemory,
            Sta::Transfer => pb::ErrorCode::PlcTransfer,
            Sta::Other(_) => pb::ErrorCode::PlcOtherSta,
        }
    }
    fn sta(&self) -> Option<u8> {
        Some(Sta::code(*self))
    }
}

#[cfg(test)]
mod tests;
