//! The simulated FFU120B + MICREX-F as a TCP serial device server (`cellgate sim fuji`).
//!
//! One connection at a time is the line: each new connection powers a fresh module on (its
//! memory empty) and replaces the previous connection. The module's output is paced at the
//! configured line rate, as a device server's serial side would deliver it; the host's input
//! is taken as it comes. Every event goes to stdout as one JSON object per line (shown here
//! with its fields in a readable order; the output sorts them):
//!
//! ```text
//! {"addr":"127.0.0.1:4002","baud":19200,"event":"listening","mode":3,"stations":[1,2],…}
//! {"event":"connected","peer":"127.0.0.1:50312"}
//! {"cmnd":"00","event":"request","hex":"000100050400000200","mode":"00","moln":"05","station":1}
//! {"event":"read","station":1,"module":"D","address":0,"bytes":2}
//! {"event":"reply","station":1,"sta":"00","line_bytes":30}
//! {"event":"written","station":2,"module":"D","address":10,"words":[4660]}
//! {"event":"refused","station":1,"cmnd":"90","mode":"00","moln":"02","sta":"A7","meaning":"…"}
//! {"event":"transfer-received","station":0,"message":1,"hex":"48656C6C6F"}
//! {"event":"transfer-sent","message":5,"line_bytes":20}
//! ```
//!
//! The options carry the names of the `[[plcs]]` keys (`--start-code`, `--bcc-range`, …, with
//! the same values), so a module and a gateway entry are set up alike; modes 4 and 5
//! (non-procedure) too, where the gateway is the module's external device.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use serde::de::IntoDeserializer;
use serde_json::{Value, json};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::broadcast;

use super::micrex_handle::MicrexHandle;
use super::server::{EventSink, PacedLine, serve_one_at_a_time};
use crate::transport::parity::GatewayParity;
use crate::transport::{DataBits, LineSettings, Parity, StopBits};
use cellgate_core::config::{PlcConfig, PlcSimConfig, TransportConfig};
use cellgate_core::engine::parity::{ParityBy, ParityCodec};
use cellgate_core::fuji::command::{FileType, Sta};
use cellgate_core::fuji::frame::{
    BccCalc, BccCode, BccKind, BccRange, EndCode as PlcEndCode, FrameSettings,
    StartCode as PlcStartCode, TransmissionCode,
};
use cellgate_core::fuji::master::OperationMode;
use cellgate_core::sim::micrex::{MicrexCommand, MicrexConfig, MicrexConfigError, MicrexEvent};

/// A value written as in the cell file (`--bcc-range start+text`, `--stop-bits 1.5`).
fn cell_value<T: serde::de::DeserializeOwned>(text: &str) -> Result<T, String> {
    let d: serde::de::value::StrDeserializer<'_, serde::de::value::Error> =
        text.into_deserializer();
    T::deserialize(d).map_err(|e| format!("{text:?}: {e}"))
}

fn byte(text: &str) -> Result<u8, String> {
    let t = text.trim();
    let parsed = match t.strip_prefix("0x").or_else(|| t.strip_prefix("0X")) {
        Some(hex) => u8::from_str_radix(hex, 16),
        None => t.parse(),
    };
    parsed.map_err(|_| format!("{text:?} is not a byte (0–255 or 0x00–0xFF)"))
}

fn mode(text: &str) -> Result<OperationMode, String> {
    let n: u8 = text
        .parse()
        .map_err(|_| format!("{text:?} is not a mode number"))?;
    OperationMode::from_dial(n).ok_or_else(|| format!("mode {n}: the MODE dial takes 1 to 5"))
}

/// A file module W30–W109: `30:DI:256` (number, type SI / DI / BD, words).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FileArg {
    pub number: u8,
    pub file_type: FileType,
    pub words: u32,
}

fn file(text: &str) -> Result<FileArg, String> {
    let parts: Vec<&str> = text.split(':').collect();
    let [n, t, w] = parts[..] else {
        return Err(format!(
            "{text:?}: write a file as NUMBER:TYPE:WORDS, e.g. 30:DI:256"
        ));
    };
    let number: u8 = n
        .trim_start_matches(['W', 'w'])
        .parse()
        .map_err(|_| format!("{text:?}: {n:?} is not a file number"))?;
    let file_type = cell_value::<FileType>(&t.to_uppercase())?;
    let words = w
        .parse()
        .map_err(|_| format!("{text:?}: {w:?} is not a number of words"))?;
    Ok(FileArg {
        number,
        file_type,
        words,
    })
}

/// A transfer the simulated PLC sends after each connection: `MSGNO:HEXDATA`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TransferArg {
    pub message: u8,
    pub data: Vec<u8>,
}

fn transfer(text: &str) -> Result<TransferArg, String> {
    let (m, d) = text
        .split_once(':')
        .ok_or_else(|| format!("{text:?}: write a transfer as MSGNO:HEXDATA, e.g. 5:48656C6C6F"))?;
    Ok(TransferArg {
        message: byte(m)?,
        data: hex::decode(d).map_err(|e| format!("{text:?}: {e}"))?,
    })
}

/// `cellgate sim fuji`: a simulated FFU120B module with its MICREX-F, served over TCP.
#[derive(Debug, Clone, clap::Args)]
pub struct SimFujiArgs {
    /// Address to listen on; loopback only.
    #[arg(long, default_value = "127.0.0.1:4002")]
    pub listen: SocketAddr,
    /// Operation mode on the MODE dial: 1 (command set, 1:1), 2 or 3 (command set, RS-485
    /// 1:N), 4 or 5 (non-procedure).
    #[arg(long, value_parser = mode, default_value = "1")]
    pub mode: OperationMode,
    /// Station numbers (RSNO, 0–99) this line's modules answer for, e.g. 1,2,3. Mode 1 is
    /// 1:1 and answers as the first.
    #[arg(long, value_delimiter = ',', default_value = "0")]
    pub stations: Vec<u8>,
    /// Baud rate the module's output is paced at.
    #[arg(long, default_value_t = 19200)]
    pub baud: u32,
    /// Data bits: 7 or 8.
    #[arg(long, value_parser = cell_value::<DataBits>, default_value = "8")]
    pub data_bits: DataBits,
    /// Parity: none, odd or even.
    #[arg(long, value_parser = cell_value::<Parity>, default_value = "none")]
    pub parity: Parity,
    /// Stop bits: 1, 1.5 or 2.
    #[arg(long, value_parser = cell_value::<StopBits>, default_value = "2")]
    pub stop_bits: StopBits,
    /// Start code (item 16): none, stx, ":", "::", set1, set2.
    #[arg(long, value_parser = cell_value::<PlcStartCode>, default_value = ":")]
    pub start_code: PlcStartCode,
    /// The bytes of start code set1 / set2, e.g. 0x02 or 0x02,0x05 (item 18).
    #[arg(long, value_delimiter = ',', value_parser = byte)]
    pub start_codes: Vec<u8>,
    /// End code (item 17): etx, cr, lf, cr-lf, dle-etx, set1, set2.
    #[arg(long, value_parser = cell_value::<PlcEndCode>, default_value = "cr")]
    pub end_code: PlcEndCode,
    /// The bytes of end code set1 / set2 (item 19).
    #[arg(long, value_delimiter = ',', value_parser = byte)]
    pub end_codes: Vec<u8>,
    /// Code transposition off (item 14): bytes travel as they are, not as two hex characters.
    #[arg(long)]
    pub no_transposition: bool,
    /// Transmission code (item 13): ascii (JIS) or ebcdic (needs 8 data bits, initial error
    /// F6).
    #[arg(long, value_parser = cell_value::<TransmissionCode>, default_value = "ascii")]
    pub code: TransmissionCode,
    /// BCC (item 20): none, set1 (high character first), set2 (low first).
    #[arg(long, value_parser = cell_value::<BccKind>, default_value = "none")]
    pub bcc: BccKind,
    /// BCC range (item 21): text, text+end, start+text, start+text+end.
    #[arg(long, value_parser = cell_value::<BccRange>, default_value = "text")]
    pub bcc_range: BccRange,
    /// BCC calculation (item 22): add, add-invert, eor, crc16.
    #[arg(long, value_parser = cell_value::<BccCalc>, default_value = "add")]
    pub bcc_calc: BccCalc,
    /// BCC code (item 23): transmission-code or binary.
    #[arg(long, value_parser = cell_value::<BccCode>, default_value = "transmission-code")]
    pub bcc_code: BccCode,
    /// Message numbers registered for transfers from the PC (§5-3-2), e.g. 1,2; others get
    /// STA A7.
    #[arg(long, value_delimiter = ',')]
    pub messages: Vec<u8>,
    /// Time from a request's last byte to the reply's first, ms.
    #[arg(long, default_value_t = 5)]
    pub processing_delay_ms: u64,
    /// A P-link card is mounted: WL, W21–W23 and W120–W123 exist.
    #[arg(long)]
    pub p_link: bool,
    /// A file module, NUMBER:TYPE:WORDS (30–109, SI / DI / BD), e.g. 30:DI:256. Repeatable.
    #[arg(long = "file", value_parser = file, value_name = "N:TYPE:WORDS")]
    pub files: Vec<FileArg>,
    /// Modes 4–5: fixed message length (1–216); without it, variable length with end code.
    #[arg(long)]
    pub fixed_length: Option<usize>,
    /// Modes 4–5: the receive message number of the initial file (item 3).
    #[arg(long, default_value_t = 1)]
    pub receive_message: u8,
    /// A transfer the PLC sends after each connection (modes 1, 4, 5), MSGNO:HEXDATA.
    /// Repeatable.
    #[arg(long = "transfer", value_parser = transfer, value_name = "MSGNO:HEX")]
    pub transfers: Vec<TransferArg>,
    /// How long after a connection the --transfer messages go out, ms.
    #[arg(long, default_value_t = 1000)]
    pub transfer_after_ms: u64,
    /// Where the parity bit of a 7-bit line is made: port (the device server's serial side
    /// is set to the line and passes 7-bit characters) or gateway (it passes whole 8-bit
    /// frames, the parity bit in bit 7, which the module's UART checks: a wrong one is a
    /// parity error and its text a receive error, FFU120B §5-6).
    #[arg(long, value_parser = cell_value::<ParityBy>, default_value = "port")]
    pub parity_by: ParityBy,
    /// A fault on the line, with --parity-by gateway: the module's character numbered N
    /// after each connection (0 first) goes out with its parity bit wrong. Repeatable.
    #[arg(long = "spoil-parity", value_name = "N")]
    pub spoil_parity: Vec<u64>,
}

impl SimFujiArgs {
    pub fn line_settings(&self) -> LineSettings {
        LineSettings {
            baud: self.baud,
            data_bits: self.data_bits,
            parity: self.parity,
            stop_bits: self.stop_bits,
            ..LineSettings::default()
        }
    }

    /// The simulated module these options describe, checked.
    pub fn micrex_config(&self) -> Result<MicrexConfig, MicrexConfigError> {
        // The framing goes through the same mapping as a `[[plcs]]` entry.
        let entry = PlcConfig {
            name: "sim".to_string(),
            mode: self.mode.dial(),
            stations: self.stations.clone(),
            frame: FrameSettings {
                start_code: self.start_code,
                start_codes: self.start_codes.clone(),
                end_code: self.end_code,
                end_codes: self.end_codes.clone(),
                bcc: self.bcc,
                bcc_range: self.bcc_range,
                bcc_calc: self.bcc_calc,
                bcc_code: self.bcc_code,
                transposition: !self.no_transposition,
                code: self.code,
                ..FrameSettings::default()
            },
            timeout_ms: PlcConfig::DEFAULT_TIMEOUT_MS,
            fixed_length: self.fixed_length.and_then(|n| u16::try_from(n).ok()),
            receive_message: self.receive_message,
            transport: TransportConfig::Sim {
                line: self.line_settings(),
            },
            tags: Vec::new(),
            sim: PlcSimConfig {
                messages: self.messages.clone(),
                ticks: Vec::new(),
            },
        };
        let mut c = MicrexConfig::for_plc(&entry);
        c.mode = self.mode;
        c.processing_delay = Duration::from_millis(self.processing_delay_ms);
        c.p_link = self.p_link;
        c.files = self
            .files
            .iter()
            .map(|f| (f.number, f.file_type, f.words))
            .collect();
        c.fixed_length = self.fixed_length;
        c.receive_message = self.receive_message;
        // Checked here, so a bad option fails at start and not at the first connection.
        cellgate_core::sim::micrex::Micrex::new(c.clone())?;
        Ok(c)
    }
}

/// Why `cellgate sim fuji` cannot run.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SimFujiError {
    #[error("{0}")]
    Config(#[from] MicrexConfigError),
    #[error(
        "simulator listen address {addr} is not loopback: simulators bind 127.0.0.1 or ::1 only"
    )]
    NotLoopback { addr: SocketAddr },
    #[error("simulator cannot listen on {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error("simulator: {0}")]
    Io(#[source] std::io::Error),
    #[error(
        "--parity-by gateway carries the parity bit in bit 7 of each byte: it needs --data-bits 7 \
         and --parity odd or even, not {line} (FFU120B §4-3 items 5-6)"
    )]
    ParityBy { line: LineSettings },
}

/// Serves the module on `args.listen` until `shutdown` completes, printing one JSON event per
/// line on stdout.
pub async fn serve_fuji(
    args: SimFujiArgs,
    shutdown: impl Future<Output = ()>,
) -> Result<(), SimFujiError> {
    let config = args.micrex_config()?;
    if !args.listen.ip().is_loopback() {
        return Err(SimFujiError::NotLoopback { addr: args.listen });
    }
    let listener = TcpListener::bind(args.listen)
        .await
        .map_err(|source| SimFujiError::Bind {
            addr: args.listen,
            source,
        })?;
    let sink: EventSink = Arc::new(|v: &Value| {
        use std::io::Write;
        let mut out = std::io::stdout().lock();
        // A closed stdout must not stop the simulator.
        let _ = writeln!(out, "{v}").and_then(|()| out.flush());
    });
    let plan = SessionPlan {
        transfers: args.transfers.clone(),
        after: Duration::from_millis(args.transfer_after_ms),
        parity_by: args.parity_by,
        spoil_parity: args.spoil_parity.clone(),
    };
    serve_fuji_on(listener, config, plan, sink, shutdown).await
}

/// What each connection gets: the transfers the simulated PLC sends, and how the device
/// server passes the line.
#[derive(Debug, Clone, Default)]
pub struct SessionPlan {
    /// Transfers sent `after` each connection.
    pub transfers: Vec<TransferArg>,
    pub after: Duration,
    /// Where a 7-bit line's parity bit is made (see [`SimFujiArgs::parity_by`]).
    pub parity_by: ParityBy,
    /// Characters of the module's output sent with a wrong parity bit (with
    /// [`ParityBy::Gateway`]), counted from 0 in each connection.
    pub spoil_parity: Vec<u64>,
}

/// Serves the module on a bound listener (tests bind port 0), sending JSON events to `sink`.
pub async fn serve_fuji_on(
    listener: TcpListener,
    config: MicrexConfig,
    plan: SessionPlan,
    sink: EventSink,
    shutdown: impl Future<Output = ()>,
) -> Result<(), SimFujiError> {
    cellgate_core::sim::micrex::Micrex::new(config.clone())?;
    let line = config.line;
    if plan.parity_by == ParityBy::Gateway
        && (line.data_bits != DataBits::Seven || line.parity == Parity::None)
    {
        return Err(SimFujiError::ParityBy { line });
    }
    let addr = listener.local_addr().map_err(SimFujiError::Io)?;
    sink(&json!({
        "event": "listening",
        "addr": addr.to_string(),
        "mode": config.mode.dial(),
        "stations": config.stations,
        "baud": line.baud,
        "line": line.to_string(),
        "parity_by": plan.parity_by.name(),
        "messages": config.messages,
    }));
    serve_one_at_a_time(
        listener,
        shutdown,
        &sink,
        "simulated FFU120B",
        |stream, peer| run_session(stream, peer, config.clone(), plan.clone(), sink.clone()),
    )
    .await;
    Ok(())
}

/// One connection: a fresh module on it until it closes; the reason it ended.
async fn run_session(
    stream: TcpStream,
    peer: SocketAddr,
    config: MicrexConfig,
    plan: SessionPlan,
    sink: EventSink,
) -> String {
    // Small texts must not wait for Nagle.
    let _ = stream.set_nodelay(true);
    let line = config.line;
    let codec = ParityCodec::new(line.parity).filter(|_| plan.parity_by == ParityBy::Gateway);
    let spawned = match codec {
        // The device server passes the frames as they are: 8 bits a character on its TCP
        // side, the parity bit in bit 7, made and checked at the module's UART.
        Some(codec) if line.data_bits == DataBits::Seven => {
            let port = LineSettings {
                data_bits: DataBits::Eight,
                parity: Parity::None,
                ..line
            };
            let paced = PacedLine::new(stream, port, format!("tcp {peer} paced at {line}"));
            let mut framed = GatewayParity::new(paced, codec);
            for &i in &plan.spoil_parity {
                framed.spoil_sent(i);
            }
            MicrexHandle::spawn_subscribed(config, Vec::new(), framed)
        }
        _ => {
            let paced = PacedLine::new(stream, line, format!("tcp {peer} paced at {line}"));
            MicrexHandle::spawn_subscribed(config, Vec::new(), paced)
        }
    };
    let (module, mut events) = match spawned {
        Ok(m) => m,
        Err(e) => return e.to_string(),
    };
    let printer = {
        let sink = sink.clone();
        async move {
            loop {
                match events.recv().await {
                    Ok(e) => sink(&event_json(&e)),
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        sink(&json!({"event": "events-lost", "count": n}));
                    }
                    Err(broadcast::error::RecvError::Closed) => break,
                }
            }
        }
    };
    let printer = tokio::spawn(printer);
    if !plan.transfers.is_empty() {
        tokio::time::sleep(plan.after).await;
        for t in &plan.transfers {
            module.command(MicrexCommand::QueueTransfer {
                message: t.message,
                data: t.data.clone(),
            });
        }
    }
    let reason = match module.finished().await {
        Ok(()) => "connection closed".to_string(),
        Err(e) => e.to_string(),
    };
    // The sender is gone with the module: the printer drains what is left and ends.
    let _ = printer.await;
    reason
}

fn sta_json(sta: u8) -> Value {
    Value::String(format!("{sta:02X}"))
}

/// The JSON line of a module event.
pub fn event_json(event: &MicrexEvent) -> Value {
    match event {
        MicrexEvent::Request {
            station,
            cmnd,
            mode,
            moln,
            text,
        } => json!({
            "event": "request",
            "station": station,
            "cmnd": format!("{cmnd:02X}"),
            "mode": format!("{mode:02X}"),
            "moln": format!("{moln:02X}"),
            "hex": hex::encode_upper(text),
        }),
        MicrexEvent::Replied {
            station,
            sta,
            line_bytes,
        } => json!({
            "event": "reply",
            "station": station,
            "sta": sta_json(*sta),
            "line_bytes": line_bytes,
        }),
        MicrexEvent::Read {
            station,
            module,
            address,
            bytes,
        } => json!({
            "event": "read",
            "station": station,
            "module": module.to_string(),
            "address": address,
            "bytes": bytes,
        }),
        MicrexEvent::Written {
            station,
            module,
            address,
            words,
        } => json!({
            "event": "written",
            "station": station,
            "module": module.to_string(),
            "address": address,
            "words": words,
        }),
        MicrexEvent::Cleared { station, module } => json!({
            "event": "cleared",
            "station": station,
            "module": module.to_string(),
        }),
        MicrexEvent::TransferReceived {
            station,
            message,
            data,
        } => json!({
            "event": "transfer-received",
            "station": station,
            "message": message,
            "hex": hex::encode_upper(data),
        }),
        MicrexEvent::TransferSent { message, bytes } => json!({
            "event": "transfer-sent",
            "message": message,
            "line_bytes": bytes,
        }),
        MicrexEvent::Refused {
            station,
            cmnd,
            mode,
            moln,
            sta,
        } => json!({
            "event": "refused",
            "station": station,
            "cmnd": format!("{cmnd:02X}"),
            "mode": format!("{mode:02X}"),
            "moln": format!("{moln:02X}"),
            "sta": sta_json(sta.code()),
            "meaning": Sta::meaning(*sta),
        }),
        MicrexEvent::ReceiveError { error } => json!({
            "event": "receive-error",
            "kind": error.kind().name(),
            "detail": error.to_string(),
        }),
        MicrexEvent::LineError { error } => json!({
            "event": "line-error",
            "error": error.to_string(),
        }),
        MicrexEvent::Fault { station, what } => json!({
            "event": "fault",
            "station": station,
            "what": what,
        }),
        MicrexEvent::CommandRefused { reason } => json!({
            "event": "command-refused",
            "reason": reason,
        }),
    }
}

#[cfg(test)]
mod tests;
