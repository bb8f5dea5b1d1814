//! The client side of the cell PLC: `cellgate plc read|write|clear|send|status` and
//! `cellgate tag get|set`, over the keys of `crate::bus::route_plc` and `route_tag`.

use std::fmt::Write as _;
use std::time::Duration;

use clap::Subcommand;
use serde_json::{Value, json};

use super::cli::{ClientCommand, ConnectArgs, Io};
use super::{Client, ClientError};
use crate::bus::keys::{PlcKey, is_plain_chunk};
use crate::bus::payload::{BusMessage, encoding};
use crate::pb;

/// How long a PLC request may wait: the master's reply time-out (at most 600 s in the cell
/// file) times its attempts, behind the requests queued before it.
pub const PLC_TIMEOUT: Duration = Duration::from_secs(60);

fn chunk_arg(what: &str, v: &str) -> Result<(), ClientError> {
    if is_plain_chunk(v) {
        Ok(())
    } else {
        Err(ClientError::InvalidArgument {
            what: format!("{what} {v:?}"),
            reason: "one key chunk, without '/', '*', '$', '?' or '#'".to_string(),
        })
    }
}

fn payload<M: BusMessage>(m: &M) -> Option<(Vec<u8>, zenoh::bytes::Encoding)> {
    Some((m.encode_to_vec(), encoding::<M>()))
}

/// A number as the CLI takes it: decimal, or 0x.. hex.
pub fn parse_word(text: &str) -> Result<u32, String> {
    let t = text.trim();
    let r = match t.strip_prefix("0x").or_else(|| t.strip_prefix("0X")) {
        Some(h) => u32::from_str_radix(h, 16),
        None => t.parse(),
    };
    r.map_err(|_| format!("{text:?} is not a number (decimal or 0x hex)"))
}

impl Client {
    /// Reads `count` words of `module` from `address` at `station` of PLC `plc`.
    pub async fn plc_read(
        &self,
        plc: &str,
        station: u8,
        module: &str,
        address: u16,
        count: usize,
    ) -> Result<pb::PlcWords, ClientError> {
        chunk_arg("PLC", plc)?;
        chunk_arg("module", module)?;
        let key = self.keys().plc_mem(plc, station, module, Some(address));
        let selector = format!("{key}?count={count}");
        self.get_one_pub(
            &format!("read of {module}{address} on {plc}"),
            &selector,
            None,
        )
        .await
    }

    /// Writes words (or clears the module, with `words` empty and `clear`).
    pub async fn plc_write(
        &self,
        plc: &str,
        station: u8,
        module: &str,
        address: Option<u16>,
        write: pb::PlcWrite,
    ) -> Result<pb::PlcWritten, ClientError> {
        chunk_arg("PLC", plc)?;
        chunk_arg("module", module)?;
        let key = self.keys().plc_mem(plc, station, module, address);
        self.get_one_pub(
            &format!("write to {module} on {plc}"),
            &key,
            payload(&write),
        )
        .await
    }

    /// Sends a transfer to the PLC (mode 1).
    pub async fn plc_send(
        &self,
        plc: &str,
        message: u8,
        data: Vec<u8>,
    ) -> Result<pb::PlcTransferred, ClientError> {
        chunk_arg("PLC", plc)?;
        let key = self.keys().plc_transfer(plc, message);
        let t = pb::PlcTransfer {
            plc: plc.to_string(),
            message: u32::from(message),
            data,
            from_plc: false,
            unix_ms: 0,
        };
        self.get_one_pub(&format!("transfer {message} to {plc}"), &key, payload(&t))
            .await
    }

    /// The status of one PLC link or of all.
    pub async fn plc_status(&self, plc: Option<&str>) -> Result<Vec<pb::PlcStatus>, ClientError> {
        let key = match plc {
            Some(p) => {
                chunk_arg("PLC", p)?;
                self.keys().plc_status(p)
            }
            None => self.keys().any_plc_status(),
        };
        let mut all: Vec<pb::PlcStatus> = self
            .get_all_pub("PLC status", &key, None)
            .await?
            .into_iter()
            .map(|(_, m)| m)
            .collect();
        all.sort_by(|a, b| a.plc.cmp(&b.plc));
        Ok(all)
    }

    /// A tag, by `NAME` (searched in every PLC) or `PLC/NAME`.
    pub async fn tag_get(&self, tag: &str) -> Result<pb::TagValue, ClientError> {
        let key = self.tag_key(tag)?;
        let mut found: Vec<(String, pb::TagValue)> =
            self.get_all_pub(&format!("tag {tag}"), &key, None).await?;
        found.sort_by(|a, b| a.0.cmp(&b.0));
        match found.len() {
            0 => Err(ClientError::Refused {
                what: format!("tag {tag}"),
                code: pb::ErrorCode::NotFound,
                message: format!("no PLC of the cell has a tag {tag:?} (no answer on {key})"),
            }),
            1 => Ok(found.remove(0).1),
            _ => Err(ClientError::InvalidArgument {
                what: format!("tag {tag}"),
                reason: format!(
                    "several PLCs have it ({}); name one as PLC/NAME",
                    found
                        .iter()
                        .map(|(_, t)| t.plc.clone())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            }),
        }
    }

    /// Writes a tag (found as [`Self::tag_get`] finds it).
    pub async fn tag_set(&self, tag: &str, value: f64) -> Result<pb::TagWritten, ClientError> {
        let current = self.tag_get(tag).await?;
        let key = self.keys().plc_tag(&current.plc, &current.name);
        self.get_one_pub(
            &format!("write of tag {tag}"),
            &key,
            payload(&pb::TagWrite { value }),
        )
        .await
    }

    fn tag_key(&self, tag: &str) -> Result<String, ClientError> {
        let (plc, name) = match tag.split_once('/') {
            Some((p, n)) => {
                chunk_arg("PLC", p)?;
                (p, n)
            }
            None => ("*", tag),
        };
        chunk_arg("tag", name)?;
        let key = self.keys().plc_tag(plc, name);
        debug_assert!(matches!(
            self.keys().parse_plc(&key),
            Some(PlcKey::Tag { .. })
        ));
        Ok(key)
    }
}

/// A tag in one line: `plc-1/parts = 42 (good, 12:00:01.250)`.
pub fn tag_text(t: &pb::TagValue) -> String {
    let value = match t.value {
        Some(v) => format!("{v}"),
        None => "-".to_string(),
    };
    format!(
        "{}/{} = {} ({}{})",
        t.plc,
        t.name,
        value,
        quality_name(t.quality()),
        if t.writable { ", writable" } else { "" }
    )
}

pub fn quality_name(q: pb::TagQuality) -> &'static str {
    match q {
        pb::TagQuality::Good => "good",
        pb::TagQuality::Stale => "stale",
        pb::TagQuality::StationDown => "station down",
        pb::TagQuality::Unspecified => "?",
    }
}

pub fn tag_json(t: &pb::TagValue) -> Value {
    json!({
        "plc": t.plc, "name": t.name, "value": t.value, "raw": t.raw,
        "unix_ms": t.unix_ms, "quality": quality_name(t.quality()), "writable": t.writable,
    })
}

/// The stations of every PLC link, one line each.
pub fn status_text(plcs: &[pb::PlcStatus]) -> String {
    let mut s = String::new();
    if plcs.is_empty() {
        return s;
    }
    let _ = writeln!(
        s,
        "{:<12} {:>7} {:<5} {:>9} {:>9} {:>8} {:>7} {:>4}  LAST ERROR",
        "PLC", "STATION", "STATE", "REQUESTS", "REPLIES", "TIMEOUTS", "RETRIES", "BCC"
    );
    for p in plcs {
        for st in &p.stations {
            let _ = writeln!(
                s,
                "{:<12} {:>7} {:<5} {:>9} {:>9} {:>8} {:>7} {:>4}  {}",
                p.plc,
                format!("{:02}", st.station),
                if st.up { "up" } else { "down" },
                st.requests,
                st.replies,
                st.timeouts,
                st.retries,
                st.bcc_errors,
                st.last_error
            );
        }
    }
    s
}

// ---- commands ----------------------------------------------------------------------------------

/// `cellgate plc`.
#[derive(Debug, Clone, Subcommand)]
pub enum PlcCommand {
    /// Read words of a module (16-bit words, 32-bit words or BCD words as stored).
    Read {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The PLC (its name in the cell file).
        plc: String,
        /// The module: B, M, K, F, A, D, W9, TS, TR, CS, CR, BD, WL, W21–W24, W30–W109
        /// (files: W30:DI, W31:BD), W120–W123 (FFU120B §5-3-3).
        module: String,
        /// Relative word address.
        address: u16,
        /// Words to read (at most 212 bytes' worth).
        #[arg(short = 'n', long, default_value_t = 1)]
        count: usize,
        /// The RS-485 station (modes 2, 3); 0 in mode 1.
        #[arg(long, default_value_t = 0)]
        station: u8,
        #[arg(long)]
        json: bool,
    },
    /// Write words to a module, confirmed by the module's reply.
    Write {
        #[command(flatten)]
        connect: ConnectArgs,
        plc: String,
        module: String,
        address: u16,
        /// The words: decimal or 0x hex.
        #[arg(required = true, value_parser = parse_word)]
        values: Vec<u32>,
        #[arg(long, default_value_t = 0)]
        station: u8,
    },
    /// Clear a whole module (01/05).
    Clear {
        #[command(flatten)]
        connect: ConnectArgs,
        plc: String,
        module: String,
        #[arg(long, default_value_t = 0)]
        station: u8,
    },
    /// Send a transfer to the PLC's message module MSGNO (mode 1 only).
    Send {
        #[command(flatten)]
        connect: ConnectArgs,
        plc: String,
        message: u8,
        /// The data, in hex (e.g. 48656C6C6F).
        data: String,
    },
    /// The PLC links' stations and counters.
    Status {
        #[command(flatten)]
        connect: ConnectArgs,
        plc: Option<String>,
        #[arg(long)]
        json: bool,
    },
}

impl ClientCommand for PlcCommand {
    fn connect_args(&self) -> &ConnectArgs {
        match self {
            PlcCommand::Read { connect, .. }
            | PlcCommand::Write { connect, .. }
            | PlcCommand::Clear { connect, .. }
            | PlcCommand::Send { connect, .. }
            | PlcCommand::Status { connect, .. } => connect,
        }
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        match self {
            PlcCommand::Read {
                plc,
                module,
                address,
                count,
                station,
                json,
                ..
            } => {
                let w = client
                    .plc_read(plc, *station, module, *address, *count)
                    .await?;
                if *json {
                    let v = json!({
                        "plc": w.plc, "station": w.station, "module": w.module,
                        "address": w.address, "words": w.words, "unix_ms": w.unix_ms,
                    });
                    let _ = writeln!(io.out, "{v}");
                } else {
                    for (i, word) in w.words.iter().enumerate() {
                        let hex = if w.attribute == 1 || w.attribute == 3 {
                            format!("{word:04X}")
                        } else {
                            format!("{word:08X}")
                        };
                        let _ = writeln!(
                            io.out,
                            "{}{} = {word} (0x{hex})",
                            w.module,
                            w.address as usize + i
                        );
                    }
                }
            }
            PlcCommand::Write {
                plc,
                module,
                address,
                values,
                station,
                ..
            } => {
                let w = client
                    .plc_write(
                        plc,
                        *station,
                        module,
                        Some(*address),
                        pb::PlcWrite {
                            words: values.clone(),
                            clear: false,
                        },
                    )
                    .await?;
                let _ = writeln!(
                    io.out,
                    "{}: {} word(s) written to {}{}",
                    w.plc, w.words, w.module, w.address
                );
            }
            PlcCommand::Clear {
                plc,
                module,
                station,
                ..
            } => {
                let w = client
                    .plc_write(
                        plc,
                        *station,
                        module,
                        None,
                        pb::PlcWrite {
                            words: Vec::new(),
                            clear: true,
                        },
                    )
                    .await?;
                let _ = writeln!(io.out, "{}: module {} cleared", w.plc, w.module);
            }
            PlcCommand::Send {
                plc, message, data, ..
            } => {
                let bytes = hex::decode(data.trim()).map_err(|e| ClientError::InvalidArgument {
                    what: format!("data {data:?}"),
                    reason: format!("not hex: {e}"),
                })?;
                let t = client.plc_send(plc, *message, bytes).await?;
                let _ = writeln!(
                    io.out,
                    "{}: transfer {} taken, {} bytes",
                    t.plc, t.message, t.bytes
                );
            }
            PlcCommand::Status { plc, json, .. } => {
                let all = client.plc_status(plc.as_deref()).await?;
                if *json {
                    let v: Vec<Value> = all
                        .iter()
                        .map(|p| {
                            json!({
                                "plc": p.plc, "mode": p.mode, "line": p.line,
                                "stations": p.stations.iter().map(|s| json!({
                                    "station": s.station, "up": s.up, "requests": s.requests,
                                    "replies": s.replies, "timeouts": s.timeouts,
                                    "retries": s.retries, "bcc_errors": s.bcc_errors,
                                    "error_replies": s.error_replies, "last_error": s.last_error,
                                })).collect::<Vec<_>>(),
                                "tags": p.tags.iter().map(tag_json).collect::<Vec<_>>(),
                            })
                        })
                        .collect();
                    let _ = writeln!(io.out, "{}", Value::Array(v));
                } else {
                    let _ = write!(io.out, "{}", status_text(&all));
                    for p in &all {
                        for t in &p.tags {
                            let _ = writeln!(io.out, "{}", tag_text(t));
                        }
                    }
                }
            }
        }
        Ok(0)
    }
}

/// `cellgate tag`.
#[derive(Debug, Clone, Subcommand)]
pub enum TagCommand {
    /// The latest value of a tag: NAME, or PLC/NAME when several PLCs have one.
    Get {
        #[command(flatten)]
        connect: ConnectArgs,
        name: String,
        #[arg(long)]
        json: bool,
    },
    /// Write a writable tag (the scale is undone and the range checked by the gateway).
    Set {
        #[command(flatten)]
        connect: ConnectArgs,
        name: String,
        #[arg(allow_negative_numbers = true)]
        value: f64,
    },
}

impl ClientCommand for TagCommand {
    fn connect_args(&self) -> &ConnectArgs {
        match self {
            TagCommand::Get { connect, .. } | TagCommand::Set { connect, .. } => connect,
        }
    }

    async fn run(&self, client: &Client, io: &mut Io<'_>) -> Result<u8, ClientError> {
        match self {
            TagCommand::Get { name, json, .. } => {
                let t = client.tag_get(name).await?;
                if *json {
                    let _ = writeln!(io.out, "{}", tag_json(&t));
                } else {
                    let _ = writeln!(io.out, "{}", tag_text(&t));
                }
            }
            TagCommand::Set { name, value, .. } => {
                let w = client.tag_set(name, *value).await?;
                let _ = writeln!(io.out, "{}/{} = {} written", w.plc, w.name, w.value);
            }
        }
        Ok(0)
    }
}
