//! The client side of the cell PLC: `cellgate plc read|write|clear|send|status` and
//! `cellgate tag get|set`, over the keys of `crate::bus::route_plc` and `route_tag`.

use std::time::Duration;

use clap::Subcommand;
use serde_json::{Value, json};

use super::cli::{ClientCommand, ConnectArgs, Io};
use super::render::{plc_status_text, tag_json, tag_text};
use super::{Client, ClientError, chunk_arg};
use crate::bus::keys::PlcKey;
use crate::bus::payload::{BusMessage, encoding};
use cellgate_core::pb;

/// How long a PLC request may wait: the master's reply time-out (at most 600 s in the cell
/// file) times its attempts, behind the requests queued before it.
pub const PLC_TIMEOUT: Duration = Duration::from_secs(60);

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
        let key = self.keys().plc_mem_write(plc, station, module, address);
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
        let key = self.keys().plc_transfer_send(plc, message);
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

    /// Sends a non-procedure message to the PLC (modes 4–5): it goes to the module's receive
    /// message number.
    pub async fn plc_message(
        &self,
        plc: &str,
        data: Vec<u8>,
    ) -> Result<pb::PlcMessageSent, ClientError> {
        chunk_arg("PLC", plc)?;
        let key = self.keys().plc_message_send(plc);
        let m = pb::PlcMessage {
            plc: plc.to_string(),
            data,
            ..pb::PlcMessage::default()
        };
        self.get_one_pub(&format!("message to {plc}"), &key, payload(&m))
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

    /// The tags of the cell file, `PLC/NAME`, as the gateway's admin document shows them;
    /// `None` when it shows no configuration (a gateway that enforces roles hides it).
    pub fn configured_tags(&self) -> Option<Vec<String>> {
        let plcs = self.admin()["config"]["plcs"].as_array()?;
        Some(
            plcs.iter()
                .flat_map(|p| {
                    let plc = p["name"].as_str().unwrap_or_default();
                    p["tags"]
                        .as_array()
                        .into_iter()
                        .flatten()
                        .filter_map(move |t| t["name"].as_str().map(|n| format!("{plc}/{n}")))
                })
                .collect(),
        )
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
                message: format!(
                    "no PLC of the cell has a tag {tag:?} (no answer on {key}){}",
                    self.configured_tags()
                        .map(|known| {
                            // Named as it was asked: PLC/NAME, or NAME alone.
                            let mut known: Vec<&str> = known
                                .iter()
                                .map(|k| match k.split_once('/') {
                                    Some((_, name)) if !tag.contains('/') => name,
                                    _ => k.as_str(),
                                })
                                .collect();
                            known.sort_unstable();
                            known.dedup();
                            cellgate_core::near::hint(tag, &known, "tags", "`cellgate plc status`")
                        })
                        .unwrap_or_default()
                ),
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
        // PLC/NAME needs no read first: a role that may write tags need not read them.
        let (plc, name) = match tag.split_once('/') {
            Some((p, n)) => {
                chunk_arg("PLC", p)?;
                chunk_arg("tag", n)?;
                (p.to_string(), n.to_string())
            }
            None => {
                let current = self.tag_get(tag).await?;
                (current.plc, current.name)
            }
        };
        let key = self.keys().plc_tag_set(&plc, &name);
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
        /// Print JSON (plc, station, module, address, words).
        #[arg(long)]
        json: bool,
    },
    /// Write words to a module, confirmed by the module's reply.
    Write {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The PLC (its name in the cell file).
        plc: String,
        /// The module: D, W9, B, M, ... (as for `plc read`).
        module: String,
        /// Relative word address of the first word.
        address: u16,
        /// The words: decimal or 0x hex.
        #[arg(required = true, value_parser = parse_word)]
        values: Vec<u32>,
        /// The RS-485 station (modes 2, 3); 0 in mode 1.
        #[arg(long, default_value_t = 0)]
        station: u8,
        /// Print JSON (the module's confirmation) instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Clear a whole module (01/05).
    Clear {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The PLC (its name in the cell file).
        plc: String,
        /// The module to clear: D, W9, B, M, ... (as for `plc read`).
        module: String,
        /// The RS-485 station (modes 2, 3); 0 in mode 1.
        #[arg(long, default_value_t = 0)]
        station: u8,
        /// Print JSON (the module's confirmation) instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Send a transfer to the PLC's message module MSGNO (mode 1 only).
    Send {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The PLC (its name in the cell file).
        plc: String,
        /// The message number MSGNO the PLC's sequence program registered.
        message: u8,
        /// The data, in hex (e.g. 48656C6C6F).
        data: String,
        /// Print JSON (the module's confirmation) instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Send a message to a PLC in mode 4 or 5 (non-procedure): it goes to the module's
    /// receive message number (FFU120B §5-5).
    Message {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The PLC link, as the cell file names it (in mode 4 or 5).
        plc: String,
        /// The data, in hex (e.g. 4C4F542D37); 1 to 216 bytes, or exactly the fixed length.
        data: String,
        /// Print JSON (a PlcMessageSent).
        #[arg(long)]
        json: bool,
    },
    /// The PLC links' stations and counters.
    Status {
        #[command(flatten)]
        connect: ConnectArgs,
        /// One PLC; default every PLC of the cell.
        plc: Option<String>,
        /// Print JSON (an array: each PLC's stations, counters and tags).
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
            | PlcCommand::Message { connect, .. }
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
                json,
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
                if *json {
                    let _ = writeln!(io.out, "{}", written_json(&w));
                } else {
                    let _ = writeln!(
                        io.out,
                        "{}: {} word(s) written to {}{}",
                        w.plc, w.words, w.module, w.address
                    );
                }
            }
            PlcCommand::Clear {
                plc,
                module,
                station,
                json,
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
                if *json {
                    let _ = writeln!(io.out, "{}", written_json(&w));
                } else {
                    let _ = writeln!(io.out, "{}: module {} cleared", w.plc, w.module);
                }
            }
            PlcCommand::Send {
                plc,
                message,
                data,
                json,
                ..
            } => {
                let bytes = hex::decode(data.trim()).map_err(|e| ClientError::InvalidArgument {
                    what: format!("data {data:?}"),
                    reason: format!("not hex: {e}"),
                })?;
                let t = client.plc_send(plc, *message, bytes).await?;
                if *json {
                    let v = json!({ "plc": t.plc, "message": t.message, "bytes": t.bytes });
                    let _ = writeln!(io.out, "{v}");
                } else {
                    let _ = writeln!(
                        io.out,
                        "{}: transfer {} taken, {} bytes",
                        t.plc, t.message, t.bytes
                    );
                }
            }
            PlcCommand::Message {
                plc, data, json, ..
            } => {
                let bytes = hex::decode(data.trim()).map_err(|e| ClientError::InvalidArgument {
                    what: format!("data {data:?}"),
                    reason: format!("not hex: {e}"),
                })?;
                let m = client.plc_message(plc, bytes).await?;
                if *json {
                    let _ = writeln!(io.out, "{}", serde_json::to_string(&m).unwrap_or_default());
                    return Ok(0);
                }
                let _ = writeln!(
                    io.out,
                    "{}: message of {} bytes sent ({} on the line) to receive message {}",
                    m.plc, m.bytes, m.line_bytes, m.receive_message
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
                                    "error_replies": super::render::error_replies_json(s),
                                    "last_error": s.last_error,
                                    "last_error_unix_ms": s.last_error_unix_ms,
                                })).collect::<Vec<_>>(),
                                "tags": p.tags.iter().map(tag_json).collect::<Vec<_>>(),
                            })
                        })
                        .collect();
                    let _ = writeln!(io.out, "{}", Value::Array(v));
                } else {
                    let now = cellgate_core::pb::now_ms();
                    let _ = write!(io.out, "{}", plc_status_text(&all, now));
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

/// A confirmed memory write or clear as JSON.
fn written_json(w: &pb::PlcWritten) -> Value {
    json!({
        "plc": w.plc, "station": w.station, "module": w.module,
        "address": w.address, "words": w.words, "cleared": w.cleared,
    })
}

/// `cellgate tag`.
#[derive(Debug, Clone, Subcommand)]
pub enum TagCommand {
    /// The latest value of a tag: NAME, or PLC/NAME when several PLCs have one.
    Get {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The tag: NAME, or PLC/NAME when several PLCs have one.
        name: String,
        /// Print JSON (plc, name, value, raw, unix_ms, quality, writable).
        #[arg(long)]
        json: bool,
    },
    /// Write a writable tag (the scale is undone and the range checked by the gateway).
    Set {
        #[command(flatten)]
        connect: ConnectArgs,
        /// The tag: NAME, or PLC/NAME when several PLCs have one.
        name: String,
        /// The value in the tag's units (its scale is undone by the gateway).
        #[arg(allow_negative_numbers = true)]
        value: f64,
        /// Print JSON (plc, name, value) instead of text.
        #[arg(long)]
        json: bool,
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
            TagCommand::Set {
                name, value, json, ..
            } => {
                let w = client.tag_set(name, *value).await?;
                if *json {
                    let v = json!({ "plc": w.plc, "name": w.name, "value": w.value });
                    let _ = writeln!(io.out, "{v}");
                } else {
                    let _ = writeln!(io.out, "{}/{} = {} written", w.plc, w.name, w.value);
                }
            }
        }
        Ok(0)
    }
}
