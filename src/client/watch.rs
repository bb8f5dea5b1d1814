//! Everything the cell publishes, and its liveliness, as one stream of events.

use std::collections::VecDeque;

use prost::Message as _;
use zenoh::Session;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::{Sample, SampleKind};

use super::{Client, ClientError, decode};
use crate::bus::keys::{CellKey, CellKeys, MachineLeaf};
use crate::bus::payload::{BusMessage as _, schema_of};
use cellgate_core::pb;

impl Client {
    /// Subscribes to everything the cell publishes (`P/C/**`) and to its liveliness tokens.
    /// The tokens standing now come first (as `Gateway` / `Link` events with `up`).
    pub async fn watch(&self) -> Result<Watch, ClientError> {
        let all = self.keys.all();
        let data = self
            .session
            .declare_subscriber(all.as_str())
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("subscribe to {all}"),
                source,
            })?;
        let tokens = self
            .session
            .liveliness()
            .declare_subscriber(all.as_str())
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("subscribe to the liveliness tokens {all}"),
                source,
            })?;
        // `@events` is a verbatim chunk: `P/C/**` does not take it in, so it is asked for by
        // its own name.
        let folder_key = self.keys.program_events();
        let folder = self
            .session
            .declare_subscriber(folder_key.as_str())
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("subscribe to {folder_key}"),
                source,
            })?;
        let mut watch = Watch {
            keys: self.keys.clone(),
            data,
            tokens,
            folder,
            pending: VecDeque::new(),
        };
        // The standing tokens, asked for after subscribing so that no change is missed
        // (one may show twice).
        let replies = self
            .session
            .liveliness()
            .get(all.as_str())
            .timeout(self.timeout)
            .await
            .map_err(|source| ClientError::Zenoh {
                what: format!("get the liveliness tokens {all}"),
                source,
            })?;
        let mut standing = Vec::new();
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result()
                && let Some(event) = watch.token_event(sample)
            {
                standing.push(event);
            }
        }
        // The gateway first, then the machines by name.
        standing.sort_by_key(|e| match e {
            WatchEvent::Link { machine, .. } => (1, machine.clone()),
            _ => (0, String::new()),
        });
        watch.pending.extend(standing);
        Ok(watch)
    }
}

/// One thing seen on the cell's keys.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum WatchEvent {
    Status(Box<pb::MachineStatus>),
    Job(pb::JobEvent),
    Alarm(pb::AlarmEvent),
    Di(pb::DiImage),
    /// A program the CNC punched out (and the remote request it carried, if any).
    Punched(Box<pb::PunchedProgram>),
    /// A `DoCommand` put by some client.
    DoCommand {
        machine: String,
        command: pb::DoCommand,
    },
    /// A delete on a job key: a cancel request.
    CancelRequested {
        machine: String,
        job_id: String,
    },
    /// A G05 stream ended.
    G05(pb::G05Status),
    /// A program put into the library.
    ProgramPut {
        name: String,
        size: u64,
    },
    /// A delete on a program: removal requested.
    ProgramDeleted {
        name: String,
    },
    /// The gateway's word that a library program changed (stored, adopted or removed, on
    /// disk), however it was asked for; `by`: who asked, as they said.
    ProgramChanged {
        info: Box<pb::ProgramInfo>,
        by: Option<pb::RequestOrigin>,
    },
    /// The gateway's word that a DO output asked for with a get went out (SDO).
    DoOutput {
        machine: String,
        command: pb::DoCommand,
        by: Option<pb::RequestOrigin>,
    },
    /// A machine's liveliness token: its link came up (`up`) or went down.
    Link {
        machine: String,
        up: bool,
    },
    /// The gateway's liveliness token.
    Gateway {
        up: bool,
    },
    /// A PLC tag changed.
    Tag(pb::TagValue),
    /// A transfer: from the PLC (published by the gateway), or one a client put to it.
    Transfer(pb::PlcTransfer),
    /// A non-procedure message (modes 4–5): from the PLC, or one a client put to it.
    PlcMessage(pb::PlcMessage),
    /// A PLC station's liveliness token: it answers (`up`) or was marked down.
    PlcStation {
        plc: String,
        station: String,
        up: bool,
    },
    /// A reload of the cell file, taken or refused.
    Reload(pb::ReloadResult),
    /// The library's folder: a file refused (two files giving one name, a locked revision's
    /// edit, a link), the folder unreadable or readable again.
    Library(pb::LibraryEvent),
    /// A sample on the cell's keys that is not what the contract puts there.
    Unexpected {
        key: String,
        detail: String,
    },
}

/// The cell's publications, as [`Client::watch`] subscribed to them.
pub struct Watch {
    keys: CellKeys,
    data: Subscriber<FifoChannelHandler<Sample>>,
    tokens: Subscriber<FifoChannelHandler<Sample>>,
    /// The library's folder events (`P/C/program/@events`).
    folder: Subscriber<FifoChannelHandler<Sample>>,
    pending: VecDeque<WatchEvent>,
}

impl Watch {
    /// The next event; `None` when the session closed.
    pub async fn next(&mut self) -> Option<WatchEvent> {
        if let Some(e) = self.pending.pop_front() {
            return Some(e);
        }
        loop {
            let event = tokio::select! {
                s = self.tokens.recv_async() => self.token_event(&s.ok()?),
                s = self.data.recv_async() => self.data_event(&s.ok()?),
                s = self.folder.recv_async() => {
                    let s = s.ok()?;
                    let key = s.key_expr().as_str();
                    let bytes = s.payload().to_bytes();
                    Some(
                        decode(key, key, &bytes, s.encoding())
                            .map(WatchEvent::Library)
                            .unwrap_or_else(|e| WatchEvent::Unexpected {
                                key: key.to_string(),
                                detail: e.to_string(),
                            }),
                    )
                }
            };
            if let Some(e) = event {
                return Some(e);
            }
        }
    }

    fn token_event(&self, sample: &Sample) -> Option<WatchEvent> {
        let up = sample.kind() == SampleKind::Put;
        let key = sample.key_expr().as_str();
        if let Some(crate::bus::keys::PlcKey::Station { plc, station }) = self.keys.parse_plc(key) {
            return Some(WatchEvent::PlcStation {
                plc: plc.to_string(),
                station: station.to_string(),
                up,
            });
        }
        match self.keys.parse(key) {
            Some(CellKey::Gateway) => Some(WatchEvent::Gateway { up }),
            Some(CellKey::Machine { machine }) => Some(WatchEvent::Link {
                machine: machine.to_string(),
                up,
            }),
            _ => None,
        }
    }

    fn data_event(&self, sample: &Sample) -> Option<WatchEvent> {
        let key = sample.key_expr().as_str();
        let bytes = sample.payload().to_bytes();
        let enc = sample.encoding();
        let put = sample.kind() == SampleKind::Put;
        if let Some(plc_key) = self.keys.parse_plc(key) {
            use crate::bus::keys::PlcKey;
            let schema = schema_of(enc);
            let event = match plc_key {
                PlcKey::Tag { .. } if put && schema.as_deref() == Some(pb::TagValue::SCHEMA) => {
                    decode(key, key, &bytes, enc).map(WatchEvent::Tag)
                }
                PlcKey::Transfer { .. }
                    if put && schema.as_deref() == Some(pb::PlcTransfer::SCHEMA) =>
                {
                    decode(key, key, &bytes, enc).map(WatchEvent::Transfer)
                }
                PlcKey::Message { .. }
                    if put && schema.as_deref() == Some(pb::PlcMessage::SCHEMA) =>
                {
                    decode(key, key, &bytes, enc).map(WatchEvent::PlcMessage)
                }
                // Status every few seconds, writes by other clients: not shown.
                _ => return None,
            };
            return Some(event.unwrap_or_else(|e| WatchEvent::Unexpected {
                key: key.to_string(),
                detail: e.to_string(),
            }));
        }
        if let Some((program, name)) = self.keys.parse_event(key) {
            let by = sample
                .attachment()
                .and_then(|a| pb::RequestOrigin::decode(a.to_bytes().as_ref()).ok());
            let event = if program {
                decode(key, key, &bytes, enc).map(|info| WatchEvent::ProgramChanged {
                    info: Box::new(info),
                    by,
                })
            } else {
                decode(key, key, &bytes, enc).map(|command| WatchEvent::DoOutput {
                    machine: name.to_string(),
                    command,
                    by,
                })
            };
            return Some(event.unwrap_or_else(|e| WatchEvent::Unexpected {
                key: key.to_string(),
                detail: e.to_string(),
            }));
        }
        let parsed = self.keys.parse(key)?;
        let event = match parsed {
            CellKey::Leaf { leaf, machine } if put => match leaf {
                MachineLeaf::Status => {
                    decode(key, key, &bytes, enc).map(|s| WatchEvent::Status(Box::new(s)))
                }
                MachineLeaf::Alarm => decode(key, key, &bytes, enc).map(WatchEvent::Alarm),
                MachineLeaf::Di => decode(key, key, &bytes, enc).map(WatchEvent::Di),
                MachineLeaf::Punch => {
                    decode(key, key, &bytes, enc).map(|p| WatchEvent::Punched(Box::new(p)))
                }
                MachineLeaf::Do => {
                    decode(key, key, &bytes, enc).map(|command| WatchEvent::DoCommand {
                        machine: machine.to_string(),
                        command,
                    })
                }
                // Job requests and G05 opens are gets, not puts.
                MachineLeaf::Job | MachineLeaf::Submit | MachineLeaf::G05 => return None,
            },
            // A stream's status comes ten times a second: only its end is shown.
            CellKey::G05 {
                part: crate::bus::keys::G05Part::Status,
                ..
            } if put => match decode::<pb::G05Status>(key, key, &bytes, enc) {
                Ok(s)
                    if s.state() == pb::G05State::Completed
                        || s.state() == pb::G05State::Failed =>
                {
                    Ok(WatchEvent::G05(s))
                }
                Ok(_) => return None,
                Err(e) => Err(e),
            },
            CellKey::JobEvents { .. } if put => decode(key, key, &bytes, enc).map(WatchEvent::Job),
            CellKey::JobEvents { machine, job } => Ok(WatchEvent::CancelRequested {
                machine: machine.to_string(),
                job_id: job.to_string(),
            }),
            CellKey::ProgramWrite { name } if put => Ok(WatchEvent::ProgramPut {
                name: name.to_string(),
                size: bytes.len() as u64,
            }),
            CellKey::ProgramWrite { name } => Ok(WatchEvent::ProgramDeleted {
                name: name.to_string(),
            }),
            CellKey::Reloaded if put => decode(key, key, &bytes, enc).map(WatchEvent::Reload),
            _ => return None,
        };
        Some(event.unwrap_or_else(|e| WatchEvent::Unexpected {
            key: key.to_string(),
            detail: e.to_string(),
        }))
    }

    /// Undeclares the subscriptions.
    pub async fn close(self) {
        let _ = self.data.undeclare().await;
        let _ = self.tokens.undeclare().await;
        let _ = self.folder.undeclare().await;
    }
}

/// Subscribes on `session` to each of `keys`, handing every sample to `tx`. A full channel
/// drops the sample rather than block zenoh: a later update of the same key says it again.
/// The subscriptions last as long as the returned handles.
pub(crate) async fn subscribe_into(
    session: &Session,
    keys: impl IntoIterator<Item = String>,
    tx: &tokio::sync::mpsc::Sender<Sample>,
) -> zenoh::Result<Vec<Subscriber<()>>> {
    let mut subscribers = Vec::new();
    for key in keys {
        let tx = tx.clone();
        let sub = session
            .declare_subscriber(key)
            .callback(move |s| {
                let _ = tx.try_send(s);
            })
            .await?;
        subscribers.push(sub);
    }
    Ok(subscribers)
}
