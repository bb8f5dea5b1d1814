//! `[[machines]]`: one FANUC CNC behind a remote buffer, the settings its board and the host
//! must agree on, and their checks against the manual.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::error::ConfigErrors;
use super::error::{Checker, ConfigError, list_u32, q, toml_name};
use super::g05::{G05Config, Refill, check_g05};
use super::transport::{
    RawTransport, TransportConfig, built_transport, check_transport, transport_of,
};
use crate::engine::LineSettings;
use crate::engine::line::{DataBits, Parity, StopBits};
use crate::fanuc::message::Framing;
use crate::fanuc::protocol_a::{ProtocolAConfig, ProtocolAProblem};
use crate::fanuc::protocol_b::{OVERRUN_B, OVERRUN_EXPANSION_B, ProtocolBConfig};
use crate::fanuc::sat::{Params, effective_packet_n};
use crate::fanuc::{CodeSystem, EndCode, Protocol};
use crate::program::scan::ProgramRules;

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
    /// The interface's name as the manual writes it (`RS-232-C`, `RS-422`).
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
    /// Controlled axes of the simulated CNC: a `g05` table may name at most these (§10.3).
    pub axes: u8,
}

impl BoardSimConfig {
    /// The default settings: an 8 KiB buffer, 2000 bytes/s consumed, 3 controlled axes.
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
    /// No: maximum overrun on reception, bytes (2..=2000).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub no: Option<u16>,
    /// Ne: retry count on a transmission error (0..=100).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ne: Option<u16>,
    /// Tp: polling interval of SAT, seconds (1..=99).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tp: Option<u16>,
    /// To: response time-out, seconds (1..=999).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub to: Option<u16>,
    /// Ti: minimum interval between transmitted bytes, ms (0..=10, in 2 ms steps).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ti: Option<u16>,
    /// Tx: minimum switch time from reception to transmission, ms (0..=100).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tx: Option<u16>,
    /// Tw: wait after WAT before the board asks again, seconds (0..=Tp).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tw: Option<u16>,
    /// Protocol A family: read the DI image (RDI, §4.4.1) every this many ms and publish it.
    /// `None`: DI is read only when asked.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub di_poll_ms: Option<u32>,
    /// How the host reaches the board: a serial port, a TCP device server or a simulation.
    pub transport: TransportConfig,
    /// Board simulation settings; only with `transport.kind = "sim"`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sim: Option<BoardSimConfig>,
    /// G05 binary input (§9); `None`: the machine takes no G05 streams.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub g05: Option<G05Config>,
    /// Which library revisions the machine takes: any (the default), or only released ones.
    #[serde(skip_serializing_if = "Accept::is_any")]
    pub accept: Accept,
    /// A PLC tag counting the machine's parts, `PLC/NAME` (a tag with `history = true`):
    /// utilisation shows parts made beside the time shares.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_counter: Option<String>,
    /// A folder whose complete files are queued to this machine as jobs (what DNC products
    /// call auto-send); each file goes to `sent/` or `refused/` inside it once taken.
    /// `None` (the default): no drop folder. Whoever may write it holds `job.submit` in effect.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub drop_dir: Option<PathBuf>,
    /// A folder each program the machine punches out is written into as a file, beside the
    /// library's copy. `None` (the default): none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub receive_dir: Option<PathBuf>,
    /// What the machine is, as OPC 40501's Identification shows it (docs/opcua.md); `None`:
    /// defaults that say they are defaults.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub identification: Option<Identification>,
}

/// `identification` of a `[[machines]]` entry: the nameplate OPC 40501 asks for
/// (`MachineToolIdentificationType`), which no remote-buffer message carries.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Identification {
    /// The machine's maker, e.g. "DMG MORI" (the CNC's maker is FANUC; the machine's may not be).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub manufacturer: Option<String>,
    /// The machine's serial number on its nameplate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub serial_number: Option<String>,
    /// A URI unique to this machine worldwide (OPC 10000-100 ProductInstanceUri).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub product_instance_uri: Option<String>,
}

/// Which library revisions a machine takes (`accept` of a `[[machines]]` entry).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Accept {
    /// Any revision, drafts too.
    #[default]
    Any,
    /// Only revisions in state released or locked: a job naming a draft is refused before
    /// anything is queued.
    Released,
}

impl Accept {
    /// Whether it is the default, [`Accept::Any`].
    pub fn is_any(&self) -> bool {
        *self == Accept::Any
    }
}

impl MachineConfig {
    /// Default `transport.window` of a Protocol A family machine behind a device server, bytes.
    /// There the host engine itself bounds what can follow a stop code: a Protocol A message
    /// waits for the board's answer, and an Expansion A data packet is handed out only once
    /// the one before has left the line (§5.3 3; protocol notes 17). So the window only sizes
    /// the writes: twice the largest packet's data, so that a packet goes out in one write
    /// instead of a write every half of [`TransportConfig::DEFAULT_TCP_WINDOW`] (docs/performance.md,
    /// "What each change bought").
    pub const A_FAMILY_WINDOW: u32 = 2048;

    /// The `transport.window` in force for a `tcp` transport: the file's, else the protocol's
    /// default ([`Self::A_FAMILY_WINDOW`]; [`TransportConfig::DEFAULT_TCP_WINDOW`] for Protocol B
    /// and Expansion B, whose overrun after DC3 bounds it, §6.3, §7).
    pub fn tcp_window(&self) -> u32 {
        self.transport.window_or(if self.protocol.is_a_family() {
            Self::A_FAMILY_WINDOW
        } else {
            TransportConfig::DEFAULT_TCP_WINDOW
        })
    }

    /// The §4.5 parameters: the file's values over the power-on values.
    pub fn params(&self) -> Params {
        params_of([
            self.nb, self.no, self.ne, self.tp, self.to, self.ti, self.tx, self.tw,
        ])
    }

    /// The message end code in force: the file's, else CR.
    pub fn effective_end_code(&self) -> EndCode {
        self.end_code.unwrap_or_default()
    }

    /// Whether the board sends SYN on CNC reset and NAK on a CNC alarm: the file's, else off.
    pub fn effective_notify_alarm_reset(&self) -> bool {
        self.notify_alarm_reset.unwrap_or(false)
    }

    /// n of §5.2: 1, 2 or 4 for Expansion Protocol A, 0 for every other protocol.
    pub fn effective_packet_n(&self) -> u8 {
        default_packet_n(self.protocol, self.packet_n)
    }

    /// The electrical interface in force: the file's, else RS-422 above 19200 baud or for the
    /// expansion protocols, RS-232-C otherwise.
    pub fn effective_interface(&self) -> Interface {
        default_interface(self.protocol, self.transport.line().baud, self.interface)
    }

    /// How this machine's board is refilled while a G05 stream runs (see [`Refill`]): with the
    /// cell file's §4.5 values and n, which the host sets by SET before a stream may start
    /// (protocol notes 19).
    pub fn g05_refill(&self) -> Option<Refill> {
        Refill::of(
            self.protocol,
            self.params(),
            self.effective_packet_n(),
            self.transport.line(),
        )
    }

    /// Board simulation settings in force (defaults when the `sim` table is absent).
    pub fn board_sim(&self) -> BoardSimConfig {
        self.sim.unwrap_or_default()
    }

    /// What this machine's link can carry, with `programs.max_size`.
    pub fn program_rules(&self, max_size: u64) -> ProgramRules {
        ProgramRules {
            protocol: self.protocol,
            end_code: self.effective_end_code(),
            max_size,
        }
    }

    /// The settings of this machine's host engine, Protocol A family. A TCP device server
    /// carries no modem lines, so the board's RS is not seen there (§4.3 (5)).
    pub fn protocol_a_config(&self) -> Option<ProtocolAConfig> {
        self.protocol.is_a_family().then(|| ProtocolAConfig {
            cs_visible: !matches!(self.transport, TransportConfig::Tcp { .. }),
            ..ProtocolAConfig::for_link(
                Framing::new(self.code, self.effective_end_code()),
                self.params(),
                self.effective_packet_n(),
                self.transport.line().char_time(),
            )
        })
    }

    /// The settings of this machine's host engine, Protocol B family. A TCP device server
    /// carries no modem lines, so the board's ER is not seen there (§6.4 (1)).
    pub fn protocol_b_config(&self) -> Option<ProtocolBConfig> {
        ProtocolBConfig::for_protocol(
            self.protocol,
            self.code,
            self.effective_notify_alarm_reset(),
        )
        .map(|b| ProtocolBConfig {
            char_time: self.transport.line().char_time(),
            er_visible: !matches!(self.transport, TransportConfig::Tcp { .. }),
            ..b
        })
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

pub(super) fn params_of(v: [Option<u16>; 8]) -> Params {
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

pub(super) fn default_packet_n(protocol: Protocol, n: Option<u8>) -> u8 {
    match protocol {
        Protocol::ExpansionA => n.unwrap_or(1),
        _ => 0,
    }
}

pub(super) fn default_interface(
    protocol: Protocol,
    baud: u32,
    interface: Option<Interface>,
) -> Interface {
    interface.unwrap_or(
        if baud > 19_200 || matches!(protocol, Protocol::ExpansionA | Protocol::ExpansionB) {
            Interface::Rs422
        } else {
            Interface::Rs232c
        },
    )
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawMachine {
    pub(super) name: Option<String>,
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
    g05: Option<G05Config>,
    #[serde(default)]
    accept: Accept,
    pub(super) part_counter: Option<String>,
    pub(super) drop_dir: Option<PathBuf>,
    pub(super) receive_dir: Option<PathBuf>,
    identification: Option<Identification>,
}

/// An identification's texts: shown as they are by OPC UA clients, so short and printable.
fn check_identification(c: &mut Checker, label: &str, id: &Identification) {
    for (key, value) in [
        ("manufacturer", &id.manufacturer),
        ("serial_number", &id.serial_number),
        ("product_instance_uri", &id.product_instance_uri),
    ] {
        if let Some(v) = value
            && (v.is_empty() || v.len() > IDENTIFICATION_MAX || v.chars().any(char::is_control))
        {
            c.invalid(
                format!("{label}.identification.{key}"),
                format!("{v:?}"),
                format!("must be 1 to {IDENTIFICATION_MAX} bytes without control characters"),
                "OPC 40501-1 §8.2",
            );
        }
    }
}

/// The longest text of a machine's `identification`.
pub const IDENTIFICATION_MAX: usize = 256;

/// Baud rates of parameters 5073 (RS-422, settings 1–15) and 5083 (RS-232-C, 1–12) (§10.2).
pub const FANUC_BAUD_RATES: [u32; 15] = [
    50, 100, 110, 150, 200, 300, 600, 1200, 2400, 4800, 9600, 19200, 38400, 76800, 86400,
];

/// A baud rate the board can be set to at all (§10.2 parameters 5073 / 5083).
fn check_fanuc_rate(c: &mut Checker, tpath: &str, baud: u32) {
    if !FANUC_BAUD_RATES.contains(&baud) {
        c.invalid(
            format!("{tpath}.line.baud"),
            baud.to_string(),
            format!(
                "must be one of the rates of parameters 5073 / 5083: {}",
                list_u32(&FANUC_BAUD_RATES)
            ),
            "§10.2",
        );
    }
}

pub(super) fn check_machine(c: &mut Checker, label: &str, m: &RawMachine) {
    if let Some(id) = &m.identification {
        check_identification(c, label, id);
    }
    let Some(protocol) = m.protocol else {
        c.missing(
            format!("{label}.protocol"),
            "one of \"a\", \"expansion-a\", \"b\", \"expansion-b\" as set on the CNC by \
             parameter 5074 / 5084 (§2.2, §10.2)",
        );
        // Without the protocol, only the protocol-independent checks can run: a misspelt
        // `protocol` must not hide a wrong baud rate on the same machine.
        check_params(c, label, m);
        if let Some(t) = transport_of(c, label, m.transport.as_ref()) {
            let tpath = format!("{label}.transport");
            check_transport(c, &tpath, &t);
            check_fanuc_rate(c, &tpath, t.line().baud);
        }
        return;
    };
    check_protocol_keys(c, label, m, protocol);
    check_params(c, label, m);

    let Some(transport) = &transport_of(c, label, m.transport.as_ref()) else {
        return;
    };
    let tpath = format!("{label}.transport");
    check_transport(c, &tpath, transport);
    let line = transport.line();
    check_fanuc_line(c, label, m, protocol, transport);
    check_engine(c, label, m, protocol, line);

    if let Some(g) = &m.g05 {
        // A simulated CNC has the axes of its `sim` table; a real one is not known here.
        let controlled = matches!(transport, TransportConfig::Sim { .. })
            .then(|| m.sim.unwrap_or_default().axes);
        check_g05(c, label, g, protocol, line, controlled);
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

/// The keys that belong to some protocols only, and their values (§5.2, §6.4, §4.4.1,
/// §10.2).
fn check_protocol_keys(c: &mut Checker, label: &str, m: &RawMachine, protocol: Protocol) {
    let title = protocol.title();

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
        (Protocol::ExpansionA, Some(n)) if effective_packet_n(n) != n => c.invalid(
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
}

/// The line of a machine against its protocol: interface, baud rate, framing, and a device
/// server's window (§2, §3.1, §6.3).
fn check_fanuc_line(
    c: &mut Checker,
    label: &str,
    m: &RawMachine,
    protocol: Protocol,
    transport: &TransportConfig,
) {
    let title = protocol.title();
    let tpath = format!("{label}.transport");
    let line = transport.line();
    // Interface and baud rate (§2.1, §2.2, §10.2 parameters 5073 / 5083).
    let baud = line.baud;
    let interface = default_interface(protocol, baud, m.interface);
    let baud_path = || format!("{tpath}.line.baud");
    if !FANUC_BAUD_RATES.contains(&baud) {
        check_fanuc_rate(c, &tpath, baud);
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
    if let TransportConfig::Tcp {
        window: Some(window),
        ..
    } = transport
    {
        let limit = match protocol {
            Protocol::B => Some((
                OVERRUN_B - 1,
                format!("less than {OVERRUN_B} characters"),
                "§6.3",
            )),
            Protocol::ExpansionB => Some((
                OVERRUN_EXPANSION_B,
                format!("{OVERRUN_EXPANSION_B} characters at most"),
                "§7",
            )),
            _ => None,
        };
        if let Some((max, words, section)) = limit
            && *window as usize > max
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
}

/// The host engine's own checks of the machine's settings.
fn check_engine(
    c: &mut Checker,
    label: &str,
    m: &RawMachine,
    protocol: Protocol,
    line: &LineSettings,
) {
    // The host engine's own checks, for whatever the rules above do not name in the file's
    // words (they already report parameters and packet_n).
    if protocol.is_a_family() {
        let settings = ProtocolAConfig::for_link(
            Framing::new(m.code, m.end_code.unwrap_or_default()),
            params_of([m.nb, m.no, m.ne, m.tp, m.to, m.ti, m.tx, m.tw]),
            default_packet_n(protocol, m.packet_n),
            line.char_time(),
        );
        for problem in settings.validate() {
            if !matches!(
                problem,
                ProtocolAProblem::Param(_) | ProtocolAProblem::PacketN { .. }
            ) {
                c.errors.push(ConfigError::ProtocolA {
                    path: label.to_string(),
                    problem,
                });
            }
        }
    } else if let Some(settings) =
        ProtocolBConfig::for_protocol(protocol, m.code, m.notify_alarm_reset.unwrap_or(false))
    {
        for problem in settings.validate() {
            c.errors.push(ConfigError::ProtocolB {
                path: label.to_string(),
                problem,
            });
        }
    }
}

pub(super) fn check_params(c: &mut Checker, label: &str, m: &RawMachine) {
    let params = params_of([m.nb, m.no, m.ne, m.tp, m.to, m.ti, m.tx, m.tw]);
    for range in params.validate() {
        c.errors.push(ConfigError::Param {
            path: label.to_string(),
            range,
        });
    }
}

pub(super) fn check_board_sim(c: &mut Checker, label: &str, sim: &BoardSimConfig) {
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

impl From<&MachineConfig> for RawMachine {
    fn from(c: &MachineConfig) -> Self {
        RawMachine {
            name: Some(c.name.clone()),
            protocol: Some(c.protocol),
            code: c.code,
            end_code: c.end_code,
            notify_alarm_reset: c.notify_alarm_reset,
            packet_n: c.packet_n,
            interface: c.interface,
            nb: c.nb,
            no: c.no,
            ne: c.ne,
            tp: c.tp,
            to: c.to,
            ti: c.ti,
            tx: c.tx,
            tw: c.tw,
            di_poll_ms: c.di_poll_ms,
            transport: Some(RawTransport::from(&c.transport)),
            sim: c.sim,
            g05: c.g05.clone(),
            accept: c.accept,
            part_counter: c.part_counter.clone(),
            drop_dir: c.drop_dir.clone(),
            receive_dir: c.receive_dir.clone(),
            identification: c.identification.clone(),
        }
    }
}

impl RawMachine {
    /// The validated machine; `label` names it in the errors of a key still absent.
    pub(super) fn into_config(self, label: &str) -> Result<MachineConfig, ConfigErrors> {
        let missing = |path: String| ConfigError::Missing {
            path,
            hint: "required".to_string(),
        };
        Ok(MachineConfig {
            name: self.name.ok_or_else(|| missing(format!("{label}.name")))?,
            protocol: self
                .protocol
                .ok_or_else(|| missing(format!("{label}.protocol")))?,
            code: self.code,
            end_code: self.end_code,
            notify_alarm_reset: self.notify_alarm_reset,
            packet_n: self.packet_n,
            interface: self.interface,
            nb: self.nb,
            no: self.no,
            ne: self.ne,
            tp: self.tp,
            to: self.to,
            ti: self.ti,
            tx: self.tx,
            tw: self.tw,
            di_poll_ms: self.di_poll_ms,
            transport: built_transport(self.transport.as_ref(), label)?,
            sim: self.sim,
            g05: self.g05,
            accept: self.accept,
            part_counter: self.part_counter,
            drop_dir: self.drop_dir,
            receive_dir: self.receive_dir,
            identification: self.identification,
        })
    }
}
