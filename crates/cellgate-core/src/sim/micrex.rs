//! A simulated FFU120B general interface module with its MICREX-F behind it: the device side
//! of the command-set modes 1–3 and the non-procedure modes 4–5 (FEH087b §5), sans-IO.
//!
//! [`Micrex`] implements [`Engine`]. It reuses [`crate::fuji::frame`] and
//! [`crate::fuji::command`] for the wire format only; what the module does with a request is
//! its own:
//!
//! - memory per module of the §5-3-3 table, sized by [`MicrexConfig::words`] (the manual gives
//!   no sizes: the defaults are the simulator's), files W30–W109 as configured
//!   ([`MicrexConfig::files`]); WL, W21–W23 and W120–W123 only with a P-link card;
//! - checks in the order command (STA 20), module (24), interlock (22), parameters (21),
//!   memory size (32), write protection (12); a transfer to a message number that is not
//!   registered, or in modes 2/3, is STA A7;
//! - receive errors (§5-6) are counted and reported as events, and get no reply (FFU120B notes 6);
//! - the reply leaves [`MicrexConfig::processing_delay`] after the request's last byte;
//! - several stations on one line: one engine answers for every number in
//!   [`MicrexConfig::stations`], each with its own memory, and stays silent for the others;
//! - mode 1: transfers the "PLC" sends ([`MicrexCommand::QueueTransfer`]) go out between
//!   exchanges as `90 00 00 MSGNO BYTEN data`, unanswered (FFU120B notes 8);
//! - modes 4–5: messages in both directions, fixed length or variable with end code (§5-5);
//! - fault hooks: corrupt the next BCC, stay silent, drop bytes of the next reply, refuse the
//!   next request with a given STA.
//!
//! With start code "none" a silence of [`MicrexConfig::frame_gap`] ends any partial text.

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use crate::engine::{Engine, LineError, LineSettings, ModemIn};
use crate::fuji::command::{
    CMND_READ, CMND_TRANSFER, CMND_WRITE, CommandText, FileType, MAX_READ, MAX_TRANSFER, MAX_WRITE,
    MODE_ADDRESS, MODE_CLEAR, MODE_MULTI_DROP, Module, Sta, decode_words, encode_words, from_bcd,
};
use crate::fuji::frame::{
    FrameDecoder, FrameProblem, FrameSettings, MAX_NON_PROCEDURE_TEXT, ReceiveCounts, ReceiveError,
    ReceiveErrorKind, StartCode,
};
use crate::fuji::master::OperationMode;

/// Most write-protected ranges per station.
pub const MAX_PROTECTED: usize = 64;
/// Most replies being processed at once; requests beyond are dropped as receive error 1.
pub const MAX_PENDING: usize = 16;
/// Longest processing delay or frame gap.
pub const MAX_DELAY: Duration = Duration::from_secs(3600);
/// Most transfers the "PLC" holds for sending.
pub const MAX_QUEUED_TRANSFERS: usize = 64;

/// How the simulated module and PLC are set up.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MicrexConfig {
    /// The operation mode on the module's MODE dial.
    pub mode: OperationMode,
    /// The framing items of the module's initial file (§4-3).
    pub frame: FrameSettings,
    /// Character framing of the line.
    pub line: LineSettings,
    /// Station numbers (RSNO, 0–99) this engine answers for; mode 1 answers whatever RSNO
    /// says, as the first station.
    pub stations: Vec<u8>,
    /// Time from a request's last byte to the reply's first.
    pub processing_delay: Duration,
    /// A P-link card is mounted: WL, W21–W23, W120–W123 exist (§5-3-3 note).
    pub p_link: bool,
    /// Words of the fixed modules, by MOLN, over [`default_words`].
    pub words: BTreeMap<u8, u32>,
    /// Defined files: number (30–109), type, words.
    pub files: Vec<(u8, FileType, u32)>,
    /// Message numbers registered for transfers from the PC (§5-3-2 "preregister a message
    /// module"); others get STA A7.
    pub messages: Vec<u8>,
    /// Modes 4–5: fixed message length, or variable with end code.
    pub fixed_length: Option<usize>,
    /// Modes 4–5: the receive message number of the initial file (item 3) events carry.
    pub receive_message: u8,
    /// Silence after which a partial text is forgotten.
    pub frame_gap: Duration,
}

impl MicrexConfig {
    /// The simulated module of a `[[plcs]]` entry on a `sim` line: the same framing, mode and
    /// stations, and the transfer message numbers of `[plcs.sim]`.
    pub fn for_plc(p: &crate::config::PlcConfig) -> Self {
        let mut c = MicrexConfig::new(p.operation_mode());
        c.frame = p.frame.clone();
        c.line = *p.transport.line();
        c.stations = p.stations.clone();
        c.messages = p.sim.messages.clone();
        c.fixed_length = p.fixed_length.map(usize::from);
        c.receive_message = p.receive_message;
        c
    }

    /// Settings for station 0 in `mode`: initial framing, default line, a 5 ms processing delay,
    /// no P-link card, default module sizes, no files, no registered messages, a 50 ms frame gap.
    pub fn new(mode: OperationMode) -> Self {
        MicrexConfig {
            mode,
            frame: FrameSettings::default(),
            line: LineSettings::default(),
            stations: vec![0],
            processing_delay: Duration::from_millis(5),
            p_link: false,
            words: BTreeMap::new(),
            files: Vec::new(),
            messages: Vec::new(),
            fixed_length: None,
            receive_message: 1,
            frame_gap: Duration::from_millis(50),
        }
    }

    /// Words of `module`, or `None` when this PLC has no such module.
    pub fn module_words(&self, module: Module) -> Option<u32> {
        if module.is_file() {
            return self
                .files
                .iter()
                .find(|(n, t, _)| *n == module.number() && t.attribute() == module.attribute())
                .map(|(_, _, w)| *w);
        }
        if module.needs_p_link() && !self.p_link {
            return None;
        }
        self.words
            .get(&module.number())
            .copied()
            .or_else(|| default_words(module))
    }

    fn module(&self, moln: u8) -> Option<(Module, u32)> {
        let module = if (30..=109).contains(&moln) {
            let (n, t, _) = self.files.iter().find(|(n, _, _)| *n == moln)?;
            Module::file(*n, *t)?
        } else {
            Module::from_number(moln, None)?
        };
        Some((module, self.module_words(module)?))
    }
}

/// The simulator's default module sizes, in words. The manual gives none; these are round
/// numbers of the F120H's order.
pub fn default_words(module: Module) -> Option<u32> {
    Some(match module.number() {
        0x00 => 128,         // B
        0x01 => 512,         // M
        0x02 => 64,          // K
        0x03 => 128,         // F
        0x04 => 512,         // A
        0x05 => 64,          // D
        0x09 => 256,         // W9
        0x0A..=0x0B => 512,  // TS, TR
        0x0C..=0x0D => 256,  // CS, CR
        0x0E => 4096,        // BD
        0x14..=0x18 => 1024, // WL, W21–W24
        0x78..=0x7B => 512,  // W120–W123
        _ => return None,
    })
}

/// Why a [`MicrexConfig`] cannot be simulated.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum MicrexConfigError {
    /// The framing items would be refused (§4-7).
    #[error("simulated FFU120B: {0}")]
    Frame(FrameProblem),
    /// A station number outside 0–99.
    #[error("simulated FFU120B: station {station} is not 0–99 (FFU120B §3-8 channel dials)")]
    Station {
        /// The station number given.
        station: u8,
    },
    /// No station, or more than 31.
    #[error("simulated FFU120B: {count} stations; a line carries 1 to 31 (FFU120B §2-2)")]
    Stations {
        /// Stations given.
        count: usize,
    },
    /// A file outside W30–W109.
    #[error("simulated FFU120B: file W{n} is not one of W30–W109 (FFU120B §5-3-3)")]
    File {
        /// The file number given.
        n: u8,
    },
    /// A processing delay or frame gap longer than [`MAX_DELAY`].
    #[error("simulated FFU120B: processing delay and frame gap must be at most an hour")]
    Delay,
    /// A fixed message length in a command-set mode, or outside 1–216 bytes.
    #[error(
        "simulated FFU120B: fixed length {n} must be 1–216 in mode 4 or 5 (FFU120B §4-3 item 15)"
    )]
    FixedLength {
        /// The fixed length given, bytes.
        n: usize,
    },
}

/// What a test (or an operator) does to the simulated PLC.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum MicrexCommand {
    /// Sets words of a module, as the sequence program would.
    SetWords {
        /// The station.
        station: u8,
        /// The module.
        module: Module,
        /// Relative address of the first word.
        address: u16,
        /// The values, one per word.
        words: Vec<u32>,
    },
    /// Writes to these words are refused with STA 12 ("program area").
    Protect {
        /// The station.
        station: u8,
        /// The module.
        module: Module,
        /// Relative address of the first word protected.
        address: u16,
        /// Words protected.
        words: u32,
    },
    /// Removes every write protection of the station.
    Unprotect {
        /// The station.
        station: u8,
    },
    /// While on, reads, writes and clears get STA 22.
    SetInterlock {
        /// The station.
        station: u8,
        /// Whether the interlock is on.
        on: bool,
    },
    /// The PLC sends this transfer to the PC (mode 1: `90 00 00 MSGNO`; modes 4–5: the data).
    QueueTransfer {
        /// The message number MSGNO (mode 1).
        message: u8,
        /// The bytes to transfer.
        data: Vec<u8>,
    },
    /// The station stops (or resumes) answering.
    SetSilent {
        /// The station.
        station: u8,
        /// Whether the station is silent.
        on: bool,
    },
    /// The station's next reply goes out with a wrong BCC (or a spoilt text without BCC).
    CorruptNextBcc {
        /// The station.
        station: u8,
    },
    /// The station's next reply goes out without its last `count` bytes.
    DropReplyBytes {
        /// The station.
        station: u8,
        /// Bytes left off the end of the reply.
        count: usize,
    },
    /// The station refuses its next request for MOLN `moln` (a module or message number)
    /// with this STA, whatever it asks: for codes a correct host cannot provoke (20 undefined
    /// command, 21 parameter error, unlisted codes). 00 is ignored.
    ForceNextSta {
        /// The station.
        station: u8,
        /// The MOLN of the request to refuse.
        moln: u8,
        /// The STA code to reply with.
        sta: u8,
    },
}

/// What the simulated module saw and did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MicrexEvent {
    /// A command-set request addressed to one of this engine's stations: its text (header and
    /// body, as decoded from the line).
    Request {
        /// The station addressed.
        station: u8,
        /// CMND.
        cmnd: u8,
        /// MODE.
        mode: u8,
        /// MOLN.
        moln: u8,
        /// The whole text, header and body.
        text: Vec<u8>,
    },
    /// A reply went onto the line: its STA and its size on the line (start code to BCC).
    Replied {
        /// The station that replied.
        station: u8,
        /// The STA code of the reply.
        sta: u8,
        /// Bytes of the reply on the line.
        line_bytes: usize,
    },
    /// A read was answered.
    Read {
        /// The station.
        station: u8,
        /// The module read.
        module: Module,
        /// Relative address of the first word.
        address: u16,
        /// Bytes read.
        bytes: u16,
    },
    /// A write went into memory.
    Written {
        /// The station.
        station: u8,
        /// The module written.
        module: Module,
        /// Relative address of the first word.
        address: u16,
        /// The values written, one per word.
        words: Vec<u32>,
    },
    /// A module was cleared.
    Cleared {
        /// The station.
        station: u8,
        /// The module cleared.
        module: Module,
    },
    /// A transfer from the PC, stored in message module `message` (modes 4–5: the receive
    /// message number).
    TransferReceived {
        /// The station.
        station: u8,
        /// The message number.
        message: u8,
        /// The bytes transferred.
        data: Vec<u8>,
    },
    /// A transfer of the PLC went onto the line.
    TransferSent {
        /// The message number.
        message: u8,
        /// Bytes of the transfer on the line.
        bytes: usize,
    },
    /// A request refused with an STA code.
    Refused {
        /// The station.
        station: u8,
        /// CMND of the request.
        cmnd: u8,
        /// MODE of the request.
        mode: u8,
        /// MOLN of the request.
        moln: u8,
        /// The STA code the reply carries.
        sta: Sta,
    },
    /// A received text dropped without reply (§5-6).
    ReceiveError {
        /// Why the text was dropped.
        error: ReceiveError,
    },
    /// A UART error the line reported.
    LineError {
        /// The UART's error.
        error: LineError,
    },
    /// A reply was held back or spoilt by a fault hook.
    Fault {
        /// The station.
        station: u8,
        /// What the fault hook did (e.g. "silent: no reply").
        what: &'static str,
    },
    /// A command the simulator could not carry out.
    CommandRefused {
        /// Why the command could not be carried out.
        reason: String,
    },
}

#[derive(Debug, Default)]
struct StationState {
    memory: BTreeMap<u8, Vec<u32>>,
    protected: Vec<(u8, u32, u32)>,
    interlock: bool,
    silent: bool,
    corrupt_next: bool,
    drop_next: usize,
    force_sta: Option<(u8, Sta)>,
}

/// A simulated FFU120B + MICREX-F (sans-IO).
#[derive(Debug)]
pub struct Micrex {
    config: MicrexConfig,
    decoder: FrameDecoder,
    stations: BTreeMap<u8, StationState>,
    /// Replies being processed: due time, station, text.
    pending: VecDeque<(Instant, u8, Vec<u8>)>,
    transfers: VecDeque<(u8, Vec<u8>)>,
    tx: VecDeque<Vec<u8>>,
    events: VecDeque<MicrexEvent>,
    last_rx: Option<Instant>,
    /// Receive errors found after the decoder (BYTEN that does not count the body).
    extra_receive: ReceiveCounts,
}

impl Micrex {
    /// A module and PLC set up as `config` says, memory all zero; the first problem otherwise.
    pub fn new(config: MicrexConfig) -> Result<Micrex, MicrexConfigError> {
        if let Some(p) = config
            .frame
            .validate_with_line(&config.line)
            .into_iter()
            .next()
        {
            return Err(MicrexConfigError::Frame(p));
        }
        if config.stations.is_empty() || config.stations.len() > 31 {
            return Err(MicrexConfigError::Stations {
                count: config.stations.len(),
            });
        }
        if let Some(&station) = config.stations.iter().find(|s| **s > 99) {
            return Err(MicrexConfigError::Station { station });
        }
        if let Some(&(n, _, _)) = config
            .files
            .iter()
            .find(|(n, _, _)| !(30..=109).contains(n))
        {
            return Err(MicrexConfigError::File { n });
        }
        if config.processing_delay > MAX_DELAY || config.frame_gap > MAX_DELAY {
            return Err(MicrexConfigError::Delay);
        }
        if let Some(n) = config.fixed_length
            && (config.mode.is_command_set() || !(1..=MAX_NON_PROCEDURE_TEXT).contains(&n))
        {
            return Err(MicrexConfigError::FixedLength { n });
        }
        let decoder = if config.mode.is_command_set() {
            FrameDecoder::command_set(&config.frame)
        } else {
            FrameDecoder::non_procedure(&config.frame, config.fixed_length)
        };
        let stations = config
            .stations
            .iter()
            .map(|n| (*n, StationState::default()))
            .collect();
        Ok(Micrex {
            config,
            decoder,
            stations,
            pending: VecDeque::new(),
            transfers: VecDeque::new(),
            tx: VecDeque::new(),
            events: VecDeque::new(),
            last_rx: None,
            extra_receive: ReceiveCounts::default(),
        })
    }

    /// The settings the simulator was set up with.
    pub fn config(&self) -> &MicrexConfig {
        &self.config
    }

    /// Receive errors so far, by §5-6 kind.
    pub fn receive_counts(&self) -> ReceiveCounts {
        self.decoder.counts().merged(&self.extra_receive)
    }

    /// `count` words of `module` from `address` at `station`, `None` beyond the module.
    pub fn words(
        &self,
        station: u8,
        module: Module,
        address: u16,
        count: usize,
    ) -> Option<Vec<u32>> {
        let size = self.config.module_words(module)?;
        let end = usize::from(address).checked_add(count)?;
        if end > size as usize {
            return None;
        }
        let st = self.stations.get(&station)?;
        let mem = st.memory.get(&module.number());
        Some(
            (usize::from(address)..end)
                .map(|i| mem.and_then(|m| m.get(i)).copied().unwrap_or(0))
                .collect(),
        )
    }

    fn event(&mut self, e: MicrexEvent) {
        self.events.push_back(e);
    }

    fn refuse_command(&mut self, reason: String) {
        tracing::debug!(%reason, "simulated FFU120B command refused");
        self.event(MicrexEvent::CommandRefused { reason });
    }

    fn station_mut(&mut self, station: u8) -> Option<&mut StationState> {
        if !self.stations.contains_key(&station) {
            self.refuse_command(format!("station {station:02} is not simulated here"));
        }
        self.stations.get_mut(&station)
    }

    /// The station a request addressed, or `None` when it is not ours.
    fn addressed(&self, rsno: u8) -> Option<u8> {
        if !self.config.mode.is_multi_drop() {
            // Mode 1 is 1:1: RSNO is 00 and not checked (§5-3).
            return self.config.stations.first().copied();
        }
        let n = from_bcd(rsno)?;
        self.stations.contains_key(&n).then_some(n)
    }

    fn on_request(&mut self, now: Instant, text: &[u8]) {
        let req = match CommandText::parse(text) {
            Ok(r) => r,
            Err(form) => {
                // BYTEN that does not count the body: receive error 7, no reply (§5-6).
                self.extra_receive.add(ReceiveErrorKind::TextForm);
                self.event(MicrexEvent::ReceiveError {
                    error: ReceiveError::TextForm(form),
                });
                return;
            }
        };
        let Some(station) = self.addressed(req.second) else {
            return;
        };
        self.event(MicrexEvent::Request {
            station,
            cmnd: req.cmnd,
            mode: req.mode,
            moln: req.moln,
            text: text.to_vec(),
        });
        if self.pending.len() >= MAX_PENDING {
            // A host that does not wait for replies: the module's buffer is full (§5-6).
            self.extra_receive.add(ReceiveErrorKind::BufferFull);
            self.event(MicrexEvent::ReceiveError {
                error: ReceiveError::BufferFull {
                    dropped: text.len(),
                },
            });
            return;
        }
        let mode_out = if self.config.mode.is_multi_drop() {
            req.mode | MODE_MULTI_DROP
        } else {
            req.mode
        };
        let forced = self.stations.get_mut(&station).and_then(|st| {
            let (moln, sta) = st.force_sta?;
            (moln == req.moln).then(|| {
                st.force_sta = None;
                sta
            })
        });
        let processed = match forced {
            Some(sta) => Err(sta),
            None => self.process(station, &req),
        };
        let (sta, body) = match processed {
            Ok(body) => (0, body),
            Err(sta) => {
                self.event(MicrexEvent::Refused {
                    station,
                    cmnd: req.cmnd,
                    mode: req.mode,
                    moln: req.moln,
                    sta,
                });
                // An error reply is the header alone, BYTEN 00 (FFU120B notes 2).
                (sta.code(), Vec::new())
            }
        };
        let reply = CommandText {
            cmnd: req.cmnd,
            second: sta,
            mode: mode_out,
            moln: req.moln,
            body,
        };
        let due = now + self.config.processing_delay;
        self.pending.push_back((due, station, reply.encode()));
    }

    /// Carries out a request; the reply's body, or the STA that refuses it.
    fn process(&mut self, station: u8, req: &CommandText) -> Result<Vec<u8>, Sta> {
        match (req.cmnd, req.mode) {
            (CMND_READ, MODE_ADDRESS) => self.read(station, req),
            (CMND_WRITE, MODE_ADDRESS) => self.write(station, req),
            (CMND_WRITE, MODE_CLEAR) => self.clear(station, req),
            (CMND_TRANSFER, MODE_ADDRESS) => self.transfer_in(station, req),
            _ => Err(Sta::UndefinedCommand),
        }
    }

    fn module_for(&self, station: u8, moln: u8) -> Result<(Module, u32), Sta> {
        let (module, words) = self.config.module(moln).ok_or(Sta::ModuleNumber)?;
        if self.stations.get(&station).is_some_and(|s| s.interlock) {
            return Err(Sta::Interlock);
        }
        Ok((module, words))
    }

    /// Address and byte count of a read or write; checks whole words, limits and size.
    fn span(
        module: Module,
        size: u32,
        address: u16,
        bytes: u16,
        max: usize,
    ) -> Result<(usize, usize), Sta> {
        let n = module.word_bytes();
        let bytes = usize::from(bytes);
        if bytes == 0 || bytes % n != 0 || bytes > max {
            return Err(Sta::Parameter);
        }
        let words = bytes / n;
        let start = usize::from(address);
        if start + words > size as usize {
            return Err(Sta::OverMemorySize);
        }
        Ok((start, words))
    }

    fn read(&mut self, station: u8, req: &CommandText) -> Result<Vec<u8>, Sta> {
        let (module, size) = self.module_for(station, req.moln)?;
        let [a0, a1, n0, n1] = req.body[..] else {
            return Err(Sta::Parameter);
        };
        let (address, bytes) = (u16::from_le_bytes([a0, a1]), u16::from_le_bytes([n0, n1]));
        let (_, words) = Self::span(module, size, address, bytes, MAX_READ)?;
        let values = self
            .words(station, module, address, words)
            .unwrap_or_default();
        let data = encode_words(module, &values).map_err(|_| Sta::Parameter)?;
        let mut body = req.body.clone();
        body.push(module.attribute().code());
        body.extend(data);
        self.event(MicrexEvent::Read {
            station,
            module,
            address,
            bytes,
        });
        Ok(body)
    }

    fn write(&mut self, station: u8, req: &CommandText) -> Result<Vec<u8>, Sta> {
        let (module, size) = self.module_for(station, req.moln)?;
        let [a0, a1, n0, n1, data @ ..] = &req.body[..] else {
            return Err(Sta::Parameter);
        };
        let (address, bytes) = (
            u16::from_le_bytes([*a0, *a1]),
            u16::from_le_bytes([*n0, *n1]),
        );
        if usize::from(bytes) != data.len() {
            return Err(Sta::Parameter);
        }
        let (start, words) = Self::span(module, size, address, bytes, MAX_WRITE)?;
        let st = self.stations.get_mut(&station).ok_or(Sta::ModuleNumber)?;
        let end = (start + words) as u32;
        if st
            .protected
            .iter()
            .any(|(m, from, n)| *m == module.number() && (start as u32) < from + n && *from < end)
        {
            return Err(Sta::MemoryWrite);
        }
        let values = decode_words(module.attribute(), data);
        let mem = st.memory.entry(module.number()).or_default();
        if mem.len() < start + words {
            mem.resize(start + words, 0);
        }
        for (slot, v) in mem.iter_mut().skip(start).zip(&values) {
            *slot = *v;
        }
        self.event(MicrexEvent::Written {
            station,
            module,
            address,
            words: values,
        });
        Ok(req.body.get(..4).unwrap_or_default().to_vec())
    }

    fn clear(&mut self, station: u8, req: &CommandText) -> Result<Vec<u8>, Sta> {
        let (module, _) = self.module_for(station, req.moln)?;
        if !req.body.is_empty() {
            return Err(Sta::Parameter);
        }
        let st = self.stations.get_mut(&station).ok_or(Sta::ModuleNumber)?;
        if st.protected.iter().any(|(m, _, _)| *m == module.number()) {
            return Err(Sta::MemoryWrite);
        }
        st.memory.remove(&module.number());
        self.event(MicrexEvent::Cleared { station, module });
        Ok(Vec::new())
    }

    fn transfer_in(&mut self, station: u8, req: &CommandText) -> Result<Vec<u8>, Sta> {
        // Transfers are refused over RS-485 (§5-3 RSNO, §5-4 iii) and without a registered
        // message module (§5-3-2).
        if self.config.mode.is_multi_drop() || !self.config.messages.contains(&req.moln) {
            return Err(Sta::Transfer);
        }
        if req.body.len() > MAX_TRANSFER {
            return Err(Sta::Parameter);
        }
        self.event(MicrexEvent::TransferReceived {
            station,
            message: req.moln,
            data: req.body.clone(),
        });
        Ok(Vec::new())
    }

    /// Hands due replies to the line, through the fault hooks.
    fn release(&mut self, now: Instant) {
        while let Some((due, station, text)) = self.pending.front().cloned() {
            if due > now {
                break;
            }
            self.pending.pop_front();
            let Some(st) = self.stations.get_mut(&station) else {
                continue;
            };
            if st.silent {
                self.event(MicrexEvent::Fault {
                    station,
                    what: "silent: no reply",
                });
                continue;
            }
            let mut line = self.config.frame.encode(&text);
            let mut fault = None;
            if std::mem::take(&mut st.corrupt_next) {
                corrupt(&self.config.frame, &mut line);
                fault = Some("reply sent with a corrupted BCC");
            }
            let drop = std::mem::take(&mut st.drop_next);
            if drop > 0 {
                line.truncate(line.len().saturating_sub(drop));
                fault = Some("reply sent without its last bytes");
            }
            if let Some(what) = fault {
                self.event(MicrexEvent::Fault { station, what });
            }
            self.event(MicrexEvent::Replied {
                station,
                sta: text.get(1).copied().unwrap_or(0),
                line_bytes: line.len(),
            });
            self.tx.push_back(line);
        }
        // The PLC's own transfers go out between exchanges.
        if self.pending.is_empty() && !self.decoder.in_text() {
            while let Some((message, data)) = self.transfers.pop_front() {
                let line = if self.config.mode.is_command_set() {
                    let text = CommandText {
                        cmnd: CMND_TRANSFER,
                        second: 0,
                        mode: MODE_ADDRESS,
                        moln: message,
                        body: data,
                    };
                    self.config.frame.encode(&text.encode())
                } else if self.config.fixed_length.is_some() {
                    // Fixed length: only the data; start, end and BCC are not added (appendix),
                    // but item 14 still makes each byte two hex characters (§4-3).
                    self.config.frame.encode_bare(&data)
                } else {
                    self.config.frame.encode(&data)
                };
                self.event(MicrexEvent::TransferSent {
                    message,
                    bytes: line.len(),
                });
                self.tx.push_back(line);
            }
        }
    }
}

/// Spoils a reply as transmitted: its BCC, or without one a text character.
fn corrupt(frame: &FrameSettings, line: &mut [u8]) {
    let bcc_len = frame.bcc().len();
    let end_len = frame.end_bytes().len();
    let idx = if bcc_len == 0 {
        // The first text byte, made a character the transmission code does not have.
        frame.start_bytes().len()
    } else if frame.bcc_range.includes_end() {
        line.len().saturating_sub(1)
    } else {
        line.len().saturating_sub(end_len + 1)
    };
    if let Some(b) = line.get_mut(idx) {
        *b = match *b {
            b'0'..=b'8' | b'A'..=b'E' => *b + 1,
            b'9' => b'0',
            b'F' => b'A',
            _ if bcc_len == 0 && frame.transposition => b'Z',
            other => other ^ 0xFF,
        };
    }
}

impl Engine for Micrex {
    type Command = MicrexCommand;
    type Event = MicrexEvent;

    fn handle_input(&mut self, now: Instant, bytes: &[u8]) {
        if bytes.is_empty() {
            return;
        }
        let gap = self
            .last_rx
            .is_some_and(|t| now.saturating_duration_since(t) >= self.config.frame_gap);
        if gap && self.config.frame.start_code == StartCode::None {
            self.decoder.clear();
        }
        self.last_rx = Some(now);
        let decoded = self.decoder.decode(bytes);
        self.on_decoded(now, decoded);
    }

    fn handle_line_error(&mut self, now: Instant, error: LineError) {
        self.event(MicrexEvent::LineError { error });
        // The module's receiving ends in error (§5-6): the text the character belonged to
        // gets no reply, is not stored, and the next one is read as usual.
        let spoilt = self.decoder.spoil(error);
        self.on_decoded(now, spoilt);
    }

    fn handle_modem(&mut self, _now: Instant, _modem: ModemIn) {}

    fn handle_command(&mut self, now: Instant, command: MicrexCommand) {
        match command {
            MicrexCommand::SetWords {
                station,
                module,
                address,
                words,
            } => {
                let Some(size) = self.config.module_words(module) else {
                    self.refuse_command(format!("module {module} does not exist in this PLC"));
                    return;
                };
                let start = usize::from(address);
                if start + words.len() > size as usize {
                    self.refuse_command(format!(
                        "{} words at {module} {address} exceed its {size} words",
                        words.len()
                    ));
                    return;
                }
                let mask = if module.attribute().word_bytes() == 2 {
                    0xFFFF
                } else {
                    u32::MAX
                };
                if let Some(st) = self.station_mut(station) {
                    let mem = st.memory.entry(module.number()).or_default();
                    if mem.len() < start + words.len() {
                        mem.resize(start + words.len(), 0);
                    }
                    for (slot, v) in mem.iter_mut().skip(start).zip(&words) {
                        *slot = v & mask;
                    }
                }
            }
            MicrexCommand::Protect {
                station,
                module,
                address,
                words,
            } => {
                if let Some(st) = self.station_mut(station) {
                    if st.protected.len() >= MAX_PROTECTED {
                        self.refuse_command(format!("at most {MAX_PROTECTED} protected ranges"));
                    } else {
                        st.protected
                            .push((module.number(), u32::from(address), words));
                    }
                }
            }
            MicrexCommand::Unprotect { station } => {
                if let Some(st) = self.station_mut(station) {
                    st.protected.clear();
                }
            }
            MicrexCommand::SetInterlock { station, on } => {
                if let Some(st) = self.station_mut(station) {
                    st.interlock = on;
                }
            }
            MicrexCommand::SetSilent { station, on } => {
                if let Some(st) = self.station_mut(station) {
                    st.silent = on;
                }
            }
            MicrexCommand::CorruptNextBcc { station } => {
                if let Some(st) = self.station_mut(station) {
                    st.corrupt_next = true;
                }
            }
            MicrexCommand::ForceNextSta { station, moln, sta } => {
                if let Some(st) = self.station_mut(station) {
                    st.force_sta = Sta::from_code(sta).map(|s| (moln, s));
                }
            }
            MicrexCommand::DropReplyBytes { station, count } => {
                if let Some(st) = self.station_mut(station) {
                    st.drop_next = count;
                }
            }
            MicrexCommand::QueueTransfer { message, data } => {
                let max = if self.config.mode.is_command_set() {
                    MAX_TRANSFER
                } else {
                    MAX_NON_PROCEDURE_TEXT
                };
                if self.config.mode.is_multi_drop() {
                    self.refuse_command(
                        "transfers work in mode 1, 4 and 5 only (FFU120B §5-2)".to_string(),
                    );
                } else if data.len() > max || data.is_empty() && !self.config.mode.is_command_set()
                {
                    self.refuse_command(format!("a transfer carries 1 to {max} bytes"));
                } else if self.transfers.len() >= MAX_QUEUED_TRANSFERS {
                    self.refuse_command(format!("at most {MAX_QUEUED_TRANSFERS} transfers wait"));
                } else {
                    self.transfers.push_back((message, data));
                }
            }
        }
        self.release(now);
    }

    fn handle_timeout(&mut self, now: Instant) {
        self.release(now);
    }

    fn poll_transmit(&mut self, now: Instant) -> Option<Vec<u8>> {
        self.release(now);
        self.tx.pop_front()
    }

    fn poll_event(&mut self) -> Option<MicrexEvent> {
        self.events.pop_front()
    }

    fn poll_timeout(&self) -> Option<Instant> {
        self.pending.front().map(|(due, _, _)| *due)
    }
}

impl Micrex {
    /// Acts on what the decoder made of the line: requests, messages, receive errors.
    fn on_decoded(&mut self, now: Instant, decoded: Vec<crate::fuji::frame::Decoded>) {
        for decoded in decoded {
            match decoded {
                Ok(text) if self.config.mode.is_command_set() => self.on_request(now, &text),
                Ok(data) => {
                    let (station, message) = (
                        self.config.stations.first().copied().unwrap_or(0),
                        self.config.receive_message,
                    );
                    self.event(MicrexEvent::TransferReceived {
                        station,
                        message,
                        data,
                    });
                }
                Err(error) => self.event(MicrexEvent::ReceiveError { error }),
            }
        }
        self.release(now);
    }
}

#[cfg(test)]
mod tests;
