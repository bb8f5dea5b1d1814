//! The `transport` table of a machine or PLC: what carries a link's bytes.

use serde::{Deserialize, Serialize};

use super::error::{Checker, ConfigErrors, q};
use crate::engine::LineSettings;
use crate::engine::line::{DataBits, Parity};
use crate::engine::parity::ParityBy;

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
    /// A serial port of this computer. A port that cannot be opened, or goes away (a USB
    /// adapter pulled), is opened again with backoff; meanwhile the line reads as cut.
    Serial {
        /// Device path, e.g. `/dev/ttyS0` or `COM3`.
        path: String,
        /// Character framing of the serial line.
        line: LineSettings,
        /// Who makes and checks the parity bit of a 7-bit line: the port's UART (`None`, the
        /// default) or the gateway, on a port opened with 8 data bits and no parity.
        #[serde(skip_serializing_if = "Option::is_none")]
        parity_by: Option<ParityBy>,
        /// First wait before opening the port again, ms; doubles on each failure.
        reconnect_min_ms: u64,
        /// Longest wait between attempts, ms.
        reconnect_max_ms: u64,
    },
    /// A raw TCP connection to a serial device server.
    Tcp {
        /// `host:port` of the device server.
        address: String,
        /// Character framing of the device server's serial side, which sets the pace.
        line: LineSettings,
        /// Who makes and checks the parity bit of a 7-bit line: the device server's UART
        /// (`None`, the default) or the gateway, the device server passing 8-bit frames.
        #[serde(skip_serializing_if = "Option::is_none")]
        parity_by: Option<ParityBy>,
        /// Bytes handed to the device server and not yet on the line, at most; `None`: the
        /// link's default ([`TransportConfig::DEFAULT_TCP_WINDOW`], or the machine's protocol's,
        /// see `MachineConfig::tcp_window`).
        #[serde(skip_serializing_if = "Option::is_none")]
        window: Option<u32>,
        /// First wait before reconnecting, ms; doubles on each failure.
        reconnect_min_ms: u64,
        /// Longest wait between reconnection attempts, ms.
        reconnect_max_ms: u64,
    },
    /// An in-memory line to a simulated device.
    Sim {
        /// Character framing of the simulated line, paced at its baud rate.
        line: LineSettings,
    },
}

/// `kind` of a transport table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TransportKind {
    /// `kind = "serial"`: a serial port of this computer.
    Serial,
    /// `kind = "tcp"`: a raw TCP connection to a serial device server.
    Tcp,
    /// `kind = "sim"`: an in-memory line to a simulated device.
    Sim,
}

impl TransportKind {
    /// The name the cell file uses for this kind.
    pub fn name(self) -> &'static str {
        match self {
            TransportKind::Serial => "serial",
            TransportKind::Tcp => "tcp",
            TransportKind::Sim => "sim",
        }
    }
}

impl RawTransport {
    /// `kind = "sim"`.
    pub(super) fn is_sim(&self) -> bool {
        self.kind == Some(TransportKind::Sim)
    }
}

/// A transport table as written: every key optional, whatever the kind.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawTransport {
    kind: Option<TransportKind>,
    path: Option<String>,
    address: Option<String>,
    line: Option<LineSettings>,
    parity_by: Option<ParityBy>,
    window: Option<u32>,
    reconnect_min_ms: Option<u64>,
    reconnect_max_ms: Option<u64>,
}

/// A problem in a transport table before it is a [`TransportConfig`]: `key` (under the
/// table) and what is wrong with it.
pub(super) struct TransportProblem {
    key: &'static str,
    missing: bool,
    text: String,
}

impl RawTransport {
    /// The keys each kind uses, for "used only with kind = ..." messages.
    const KEYS: [(&'static str, &'static [TransportKind]); 6] = [
        ("path", &[TransportKind::Serial]),
        ("address", &[TransportKind::Tcp]),
        ("window", &[TransportKind::Tcp]),
        ("parity_by", &[TransportKind::Serial, TransportKind::Tcp]),
        (
            "reconnect_min_ms",
            &[TransportKind::Serial, TransportKind::Tcp],
        ),
        (
            "reconnect_max_ms",
            &[TransportKind::Serial, TransportKind::Tcp],
        ),
    ];

    fn present(&self, key: &str) -> bool {
        match key {
            "path" => self.path.is_some(),
            "address" => self.address.is_some(),
            "window" => self.window.is_some(),
            "parity_by" => self.parity_by.is_some(),
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
        let reconnect_min_ms = self
            .reconnect_min_ms
            .unwrap_or(TransportConfig::DEFAULT_RECONNECT_MIN_MS);
        let reconnect_max_ms = self
            .reconnect_max_ms
            .unwrap_or(TransportConfig::DEFAULT_RECONNECT_MAX_MS);
        let config = match kind {
            TransportKind::Serial => self.path.clone().map(|path| TransportConfig::Serial {
                path,
                line,
                parity_by: self.parity_by,
                reconnect_min_ms,
                reconnect_max_ms,
            }),
            TransportKind::Tcp => self.address.clone().map(|address| TransportConfig::Tcp {
                address,
                line,
                parity_by: self.parity_by,
                window: self.window,
                reconnect_min_ms,
                reconnect_max_ms,
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
            TransportConfig::Serial {
                path,
                line,
                parity_by,
                reconnect_min_ms,
                reconnect_max_ms,
            } => RawTransport {
                kind: Some(TransportKind::Serial),
                path: Some(path),
                line: Some(line),
                parity_by,
                reconnect_min_ms: Some(reconnect_min_ms),
                reconnect_max_ms: Some(reconnect_max_ms),
                ..RawTransport::default()
            },
            TransportConfig::Tcp {
                address,
                line,
                parity_by,
                window,
                reconnect_min_ms,
                reconnect_max_ms,
            } => RawTransport {
                kind: Some(TransportKind::Tcp),
                address: Some(address),
                line: Some(line),
                parity_by,
                window,
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
    /// Default of `window`, bytes, where the link's protocol sets no other: well inside the
    /// 512 characters Protocol B may overrun a DC3 by (§6.3).
    pub const DEFAULT_TCP_WINDOW: u32 = 256;
    /// Default of `reconnect_min_ms`, ms.
    pub const DEFAULT_RECONNECT_MIN_MS: u64 = 100;
    /// Default of `reconnect_max_ms`, ms.
    pub const DEFAULT_RECONNECT_MAX_MS: u64 = 5_000;

    /// The in-flight bound of a `tcp` transport: the file's `window`, else `default` (the
    /// link's: see `MachineConfig::tcp_window`).
    pub fn window_or(&self, default: u32) -> u32 {
        match self {
            TransportConfig::Tcp {
                window: Some(w), ..
            } => *w,
            _ => default,
        }
    }

    /// The character framing of the line.
    pub fn line(&self) -> &LineSettings {
        match self {
            TransportConfig::Serial { line, .. }
            | TransportConfig::Tcp { line, .. }
            | TransportConfig::Sim { line } => line,
        }
    }

    /// Who makes and checks the parity bit: the port's UART unless the file says the
    /// gateway (a `sim` line has no port: its own model makes it).
    pub fn parity_by(&self) -> ParityBy {
        match self {
            TransportConfig::Serial { parity_by, .. } | TransportConfig::Tcp { parity_by, .. } => {
                parity_by.unwrap_or_default()
            }
            TransportConfig::Sim { .. } => ParityBy::Port,
        }
    }

    /// The framing the port itself is set to: the line's, or with the parity made by the
    /// gateway, 8 data bits and no parity with the line's stop bits (the same bits a
    /// character, the parity bit carried as bit 7).
    pub fn port_line(&self) -> LineSettings {
        let line = *self.line();
        match self.parity_by() {
            ParityBy::Port => line,
            ParityBy::Gateway => LineSettings {
                data_bits: DataBits::Eight,
                parity: Parity::None,
                ..line
            },
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
        self.describe_with(Self::DEFAULT_TCP_WINDOW)
    }

    /// [`describe`](Self::describe), with the window a `tcp` transport has where the file sets
    /// none (a machine's: `MachineConfig::tcp_window`).
    pub fn describe_with(&self, default_window: u32) -> String {
        match self {
            TransportConfig::Serial {
                path,
                line,
                reconnect_min_ms,
                reconnect_max_ms,
                ..
            } => format!(
                "serial {path}, {line}{}, reopened every {reconnect_min_ms}..{reconnect_max_ms} \
                 ms while away",
                self.parity_note("the port")
            ),
            TransportConfig::Tcp {
                address,
                line,
                window,
                reconnect_min_ms,
                reconnect_max_ms,
                ..
            } => {
                let window = match window {
                    Some(w) => format!("{w} bytes"),
                    None => format!("{default_window} bytes (default)"),
                };
                format!(
                    "tcp {address}, serial side {line}{}, window {window}, \
                     reconnect every {reconnect_min_ms}..{reconnect_max_ms} ms",
                    self.parity_note("the device server")
                )
            }
            TransportConfig::Sim { line } => format!("sim, {line}"),
        }
    }
}

impl TransportConfig {
    /// Where a 7-bit line's parity bit is made, for [`describe`](Self::describe): empty for
    /// a line without one.
    fn parity_note(&self, port: &str) -> String {
        let line = self.line();
        if line.data_bits != DataBits::Seven || line.parity == Parity::None {
            return String::new();
        }
        match self.parity_by() {
            ParityBy::Port => format!(", parity made and checked by {port}"),
            ParityBy::Gateway => format!(
                ", parity made and checked by the gateway ({port} passes 8-bit frames, {})",
                self.port_line()
            ),
        }
    }

    /// What `check-config` says of a 7-bit line over a device server whose cell file leaves
    /// `parity_by` out: either reading may be right, and only the device server's setting
    /// tells (FFU120B §4-3 items 5–6; FFU120B notes 10).
    pub fn parity_warning(&self, path: &str) -> Option<String> {
        let TransportConfig::Tcp {
            parity_by: None,
            line,
            ..
        } = self
        else {
            return None;
        };
        if line.data_bits != DataBits::Seven {
            return None;
        }
        let parity = match line.parity {
            Parity::None => "no parity",
            Parity::Even => "even parity",
            Parity::Odd => "odd parity",
        };
        Some(format!(
            "{path}: 7 data bits with {parity} over a device server, parity_by left out: the \
             gateway takes the device server's serial side to be set to the line ({line}), \
             making and checking the parity bit itself and passing 7-bit characters. If it \
             passes whole 8-bit frames instead (set to 8N1 on a 7E1 line), the parity bit \
             arrives as bit 7 and every message is lost: then set parity_by = \"gateway\". \
             Set parity_by = \"port\" to say the first is meant (FFU120B §4-3 items 5-6)"
        ))
    }
}

/// The transport of link `label`, or the errors that keep it from being built.
pub(super) fn built_transport(
    raw: Option<&RawTransport>,
    label: &str,
) -> Result<TransportConfig, ConfigErrors> {
    let mut c = Checker {
        errors: Vec::new(),
        files: true,
    };
    match transport_of(&mut c, label, raw) {
        Some(t) => Ok(t),
        None => Err(ConfigErrors(c.errors)),
    }
}

/// Builds the transport of link `label`, reporting a missing table, a missing key or a key
/// of another kind.
pub(super) fn transport_of(
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

/// Checks common to every transport: the path, the address, the window and the backoff.
pub(super) fn check_transport(c: &mut Checker, path: &str, t: &TransportConfig) {
    match t {
        TransportConfig::Serial {
            path: dev,
            reconnect_min_ms,
            reconnect_max_ms,
            ..
        } => {
            if dev.trim().is_empty() {
                c.invalid(
                    format!("{path}.path"),
                    q(dev),
                    "must name the serial device, e.g. \"/dev/ttyS0\"".to_string(),
                    "",
                );
            }
            check_backoff(c, path, *reconnect_min_ms, *reconnect_max_ms);
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
            if let Some(window) = window {
                c.range(
                    || format!("{path}.window"),
                    *window,
                    1,
                    65_536,
                    " bytes",
                    "",
                );
            }
            check_backoff(c, path, *reconnect_min_ms, *reconnect_max_ms);
        }
        TransportConfig::Sim { .. } => {}
    }
    let line = t.line();
    if t.parity_by() == ParityBy::Gateway
        && (line.data_bits != DataBits::Seven || line.parity == Parity::None)
    {
        c.invalid(
            format!("{path}.parity_by"),
            q("gateway"),
            format!(
                "the gateway carries a parity bit in bit 7 of each byte, so the line must have \
                 7 data bits and odd or even parity, not {line}; remove the key or set \
                 line = {{ data_bits = 7, parity = \"even\" }}"
            ),
            "FFU120B §4-3 items 5-6",
        );
    }
}

fn check_backoff(c: &mut Checker, path: &str, min: u64, max: u64) {
    c.range(
        || format!("{path}.reconnect_min_ms"),
        min,
        1,
        3_600_000,
        "",
        "",
    );
    c.range(
        || format!("{path}.reconnect_max_ms"),
        max,
        min.max(1),
        3_600_000,
        " (reconnect_min_ms or more)",
        "",
    );
}

pub(super) fn valid_address(a: &str) -> bool {
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
