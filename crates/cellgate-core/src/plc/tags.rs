//! Named tags of a PLC link, sans-IO: the poll plan (which reads cover which tags), the
//! decoding of what a read returns, publish-on-change with a deadband, quality, and the
//! words a tag write puts into the PLC.
//!
//! Tags with the same `poll_ms` make a poll group. Within a group, the tags of one station and
//! module are read together: adjacent (or nearly adjacent) addresses share one read request
//! for as long as the span stays within the 212 bytes a read may return (FFU120B §5-3-2), so
//! a group costs the line as few requests as the limit allows.

use std::collections::BTreeMap;
use std::time::{Duration, SystemTime};

use crate::codes::BusCode;
use crate::config::{TagConfig, TagType};
use crate::fuji::command::{MAX_READ, Module, from_bcd8, to_bcd8};
use crate::pb;

/// How far a tag's value can be trusted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Quality {
    /// The last read of the tag succeeded.
    Good,
    /// Not read yet, or the last read failed (time-out, STA error, unreadable value): the
    /// value is the last good one.
    Stale,
    /// The tag's station is marked down (FFU120B §5-3 RSNO; the master's auto-demotion).
    StationDown,
}

/// A tag's value as the bus sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct TagValue {
    /// The tag's name.
    pub name: String,
    /// The scaled value of the last good read, `None` before the first.
    pub value: Option<f64>,
    /// The raw value (before scaling) of the last good read.
    pub raw: Option<i64>,
    /// When the value was read.
    pub time: Option<SystemTime>,
    /// How far the value can be trusted.
    pub quality: Quality,
    /// Whether the tag may be written (`writable` of its `[[plcs.tags]]`).
    pub writable: bool,
}

/// One read request of a poll group.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PollRead {
    /// The station read.
    pub station: u8,
    /// The module read.
    pub module: Module,
    /// The first word's relative address.
    pub address: u16,
    /// Words read, at most [`MAX_READ`] bytes' worth.
    pub words: u16,
    /// Indices of the tags it covers.
    tags: Vec<usize>,
}

/// The tags polled at one interval, and the reads that cover them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PollGroup {
    /// How often the group is read (`poll_ms`).
    pub interval: Duration,
    /// The reads that cover the group's tags.
    pub reads: Vec<PollRead>,
}

#[derive(Debug, Clone)]
struct TagState {
    config: TagConfig,
    value: TagValue,
    /// The value last published (the deadband is measured from it).
    published: Option<TagValue>,
}

/// Why a tag write is refused before anything is sent.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum TagError {
    /// The PLC has no tag of this name.
    #[error("PLC {plc} has no tag {name:?}; its tags are: {known}")]
    Unknown {
        /// The PLC's name.
        plc: String,
        /// The tag name asked for.
        name: String,
        /// The PLC's tag names, comma-separated (`none` without tags).
        known: String,
    },
    /// The tag is read-only (`writable = false`): nothing was sent.
    #[error("tag {name} is read-only (writable = false in its [[plcs.tags]]): nothing was sent")]
    ReadOnly {
        /// The tag's name.
        name: String,
    },
    /// The value, scale undone, does not fit the tag's type.
    #[error(
        "tag {name}: {value} is out of range for a {kind} tag ({min}..={max} after scale {scale})"
    )]
    OutOfRange {
        /// The tag's name.
        name: String,
        /// The value given, before the scale is undone.
        value: f64,
        /// The tag's type: `bit`, `u16`, `i16`, `u32`, `i32` or `bcd`.
        kind: &'static str,
        /// The least raw value of the type.
        min: f64,
        /// The greatest raw value of the type.
        max: f64,
        /// The tag's scale.
        scale: f64,
    },
}

/// What a tag write puts into the PLC.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TagWrite {
    /// The tag written.
    pub name: String,
    /// The raw value written (before the scale), which the tag reads as once the module
    /// confirmed the write.
    pub raw: i64,
    /// The tag's scale, for [`TagWrite::value`].
    pub scale: crate::config::Real,
    /// The tag's station.
    pub station: u8,
    /// The tag's module.
    pub module: Module,
    /// The relative address of the tag's first word.
    pub address: u16,
    /// What goes into the word(s) there.
    pub op: WriteOp,
}

/// What a tag write does to the words at its address.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WriteOp {
    /// Whole words.
    Words(Vec<u32>),
    /// One bit of a word: the word is read, the bit changed, the word written back. The
    /// command set has no bit write (§5-3-2), so a bit another writer changes between the
    /// read and the write is lost.
    Bit {
        /// The bit of the word (0 = least significant).
        bit: u8,
        /// `true` sets the bit, `false` clears it.
        on: bool,
    },
}

/// The tags of one PLC link.
#[derive(Debug, Clone)]
pub struct TagTable {
    plc: String,
    tags: Vec<TagState>,
    groups: Vec<PollGroup>,
}

fn type_name(kind: TagType) -> &'static str {
    match kind {
        TagType::Bit => "bit",
        TagType::U16 => "u16",
        TagType::I16 => "i16",
        TagType::U32 => "u32",
        TagType::I32 => "i32",
        TagType::Bcd => "bcd",
    }
}

impl TagWrite {
    /// The value the tag reads as once written: `raw` times the scale, so a value finer than
    /// the scale comes back rounded (12.34 to a tag of scale 0.1 is 12.3).
    pub fn value(&self) -> f64 {
        self.raw as f64 * self.scale.0
    }
}

/// The raw range of a tag type in a module.
fn raw_range(kind: TagType, module: Module) -> (i64, i64) {
    let wide = module.word_bytes() == 4;
    match kind {
        TagType::Bit => (0, 1),
        TagType::U16 => (0, 0xFFFF),
        TagType::I16 => (-0x8000, 0x7FFF),
        TagType::U32 => (0, 0xFFFF_FFFF),
        TagType::I32 => (-0x8000_0000, 0x7FFF_FFFF),
        TagType::Bcd if wide => (0, 99_999_999),
        TagType::Bcd => (0, 9_999),
    }
}

/// The raw value of `kind` at the start of `words`; `None` for a BCD word with a nibble over 9.
pub fn decode(kind: TagType, module: Module, bit: u8, words: &[u32]) -> Option<i64> {
    let w0 = *words.first()?;
    let wide = module.word_bytes() == 4;
    Some(match kind {
        TagType::Bit => i64::from((w0 >> bit) & 1),
        TagType::U16 => i64::from(w0 & 0xFFFF),
        TagType::I16 => i64::from((w0 & 0xFFFF) as u16 as i16),
        TagType::U32 | TagType::I32 => {
            let v = if wide {
                w0
            } else {
                // Two 16-bit words, the low word first.
                (w0 & 0xFFFF) | ((*words.get(1)? & 0xFFFF) << 16)
            };
            if kind == TagType::U32 {
                i64::from(v)
            } else {
                i64::from(v as i32)
            }
        }
        TagType::Bcd => i64::from(from_bcd8(if wide { w0 } else { w0 & 0xFFFF })?),
    })
}

/// The words a raw value of `kind` takes (inverse of [`decode`], bit tags aside).
pub fn encode(kind: TagType, module: Module, raw: i64) -> Vec<u32> {
    let wide = module.word_bytes() == 4;
    let v = raw as u32;
    match kind {
        TagType::Bit | TagType::U16 | TagType::I16 => vec![v & 0xFFFF],
        TagType::U32 | TagType::I32 if wide => vec![v],
        TagType::U32 | TagType::I32 => vec![v & 0xFFFF, v >> 16],
        TagType::Bcd => vec![to_bcd8(v).unwrap_or(0)],
    }
}

impl TagTable {
    /// The tags of PLC `plc` and their poll plan; every value stale until read.
    pub fn new(plc: &str, configs: &[TagConfig]) -> TagTable {
        let tags: Vec<TagState> = configs
            .iter()
            .map(|c| TagState {
                value: TagValue {
                    name: c.name.clone(),
                    value: None,
                    raw: None,
                    time: None,
                    quality: Quality::Stale,
                    writable: c.writable,
                },
                config: c.clone(),
                published: None,
            })
            .collect();
        let groups = plan(configs);
        TagTable {
            plc: plc.to_string(),
            tags,
            groups,
        }
    }

    /// The poll groups, with the reads of each.
    pub fn groups(&self) -> &[PollGroup] {
        &self.groups
    }

    /// How many tags the table holds.
    pub fn len(&self) -> usize {
        self.tags.len()
    }

    /// Whether the table holds no tags.
    pub fn is_empty(&self) -> bool {
        self.tags.is_empty()
    }

    /// Every tag's current value.
    pub fn values(&self) -> Vec<TagValue> {
        self.tags.iter().map(|t| t.value.clone()).collect()
    }

    /// The value of tag `name`, if the PLC has one.
    pub fn get(&self, name: &str) -> Option<&TagValue> {
        self.tags
            .iter()
            .find(|t| t.config.name == name)
            .map(|t| &t.value)
    }

    /// The settings of tag `name`, if the PLC has one.
    pub fn config(&self, name: &str) -> Option<&TagConfig> {
        self.tags
            .iter()
            .find(|t| t.config.name == name)
            .map(|t| &t.config)
    }

    /// The poll group and read that cover tag `name`.
    pub fn read_of(&self, name: &str) -> Option<(usize, usize)> {
        let i = self.tags.iter().position(|t| t.config.name == name)?;
        self.groups.iter().enumerate().find_map(|(g, group)| {
            group
                .reads
                .iter()
                .position(|r| r.tags.contains(&i))
                .map(|r| (g, r))
        })
    }

    fn unknown(&self, name: &str) -> TagError {
        let names: Vec<&str> = self.tags.iter().map(|t| t.config.name.as_str()).collect();
        TagError::Unknown {
            plc: self.plc.clone(),
            name: name.to_string(),
            known: if names.is_empty() {
                "none".to_string()
            } else {
                names.join(", ")
            },
        }
    }

    /// The tag's value or why there is none.
    pub fn value(&self, name: &str) -> Result<&TagValue, TagError> {
        self.get(name).ok_or_else(|| self.unknown(name))
    }

    /// What writing `value` to tag `name` puts into the PLC: scale undone, range checked.
    /// A read-only tag is refused here, so its write never reaches the line.
    pub fn plan_write(&self, name: &str, value: f64) -> Result<TagWrite, TagError> {
        let c = self.config(name).ok_or_else(|| self.unknown(name))?;
        if !c.writable {
            return Err(TagError::ReadOnly {
                name: name.to_string(),
            });
        }
        let (min, max) = raw_range(c.kind, c.module);
        let scaled = value / c.scale.0;
        let raw = scaled.round();
        let out_of_range = || TagError::OutOfRange {
            name: name.to_string(),
            value,
            kind: type_name(c.kind),
            min: min as f64,
            max: max as f64,
            scale: c.scale.0,
        };
        // The value as given must lie in the type's range, not only once rounded: -0.4 is no
        // value of an unsigned tag, though it rounds to 0. (A hair of slack for the scale's
        // binary fractions: 6553.5 / 0.1 is 65535.000000000007.)
        const SLACK: f64 = 1e-6;
        if !raw.is_finite() || scaled < min as f64 - SLACK || scaled > max as f64 + SLACK {
            return Err(out_of_range());
        }
        let raw = raw as i64;
        let op = if c.kind == TagType::Bit {
            WriteOp::Bit {
                bit: c.bit.unwrap_or(0),
                on: raw != 0,
            }
        } else {
            WriteOp::Words(encode(c.kind, c.module, raw))
        };
        Ok(TagWrite {
            name: name.to_string(),
            raw,
            scale: c.scale,
            station: c.station,
            module: c.module,
            address: c.address,
            op,
        })
    }

    /// A read of group `group` ended: with the words read, or failed. Returns the tags whose
    /// change is worth publishing.
    pub fn apply_read(
        &mut self,
        group: usize,
        read: usize,
        words: Option<&[u32]>,
        time: SystemTime,
    ) -> Vec<TagValue> {
        let Some(r) = self.groups.get(group).and_then(|g| g.reads.get(read)) else {
            return Vec::new();
        };
        let (address, members) = (r.address, r.tags.clone());
        let mut out = Vec::new();
        for i in members {
            let t = &mut self.tags[i];
            let offset = usize::from(t.config.address - address);
            let raw = words.and_then(|w| {
                decode(
                    t.config.kind,
                    t.config.module,
                    t.config.bit.unwrap_or(0),
                    w.get(offset..)?,
                )
            });
            match raw {
                Some(raw) => {
                    t.value.raw = Some(raw);
                    t.value.value = Some(raw as f64 * t.config.scale.0);
                    t.value.time = Some(time);
                    t.value.quality = Quality::Good;
                }
                None => {
                    if words.is_some() {
                        tracing::debug!(tag = %t.config.name, "tag value unreadable (BCD digit over 9?)");
                    }
                    // A tag of a station marked down keeps saying so until a read succeeds.
                    if t.value.quality != Quality::StationDown {
                        t.value.quality = Quality::Stale;
                    }
                }
            }
            if let Some(v) = t.changed() {
                out.push(v);
            }
        }
        out
    }

    /// A write the module confirmed: the tag now holds what was written, so a read right
    /// after the write answers it rather than the value of the last poll. Returns the value
    /// to publish if it changed past the deadband.
    pub fn apply_written(&mut self, write: &TagWrite, time: SystemTime) -> Option<TagValue> {
        let t = self.tags.iter_mut().find(|t| t.config.name == write.name)?;
        t.value.raw = Some(write.raw);
        t.value.value = Some(write.raw as f64 * t.config.scale.0);
        t.value.time = Some(time);
        t.value.quality = Quality::Good;
        t.changed()
    }

    /// The master marked `station` down (or up again: its tags turn good at their next read).
    pub fn station_down(&mut self, station: u8) -> Vec<TagValue> {
        let mut out = Vec::new();
        for t in &mut self.tags {
            if t.config.station == station {
                t.value.quality = Quality::StationDown;
                if let Some(v) = t.changed() {
                    out.push(v);
                }
            }
        }
        out
    }
}

impl TagState {
    /// The value to publish if it changed enough since the last one published: any change
    /// of quality, the first value, or a change of at least the deadband (and above zero).
    fn changed(&mut self) -> Option<TagValue> {
        let publish = match &self.published {
            None => self.value.value.is_some() || self.value.quality != Quality::Stale,
            Some(p) if p.quality != self.value.quality => true,
            Some(p) => match (p.value, self.value.value) {
                (Some(a), Some(b)) => {
                    let d = (a - b).abs();
                    d > 0.0 && d >= self.config.deadband.0
                }
                (None, Some(_)) => true,
                _ => false,
            },
        };
        publish.then(|| {
            self.published = Some(self.value.clone());
            self.value.clone()
        })
    }
}

/// The poll groups of `tags`: one per interval; in each, the fewest reads of at most
/// [`MAX_READ`] bytes that cover every tag of a station and module.
pub fn plan(tags: &[TagConfig]) -> Vec<PollGroup> {
    let mut by_interval: BTreeMap<u32, BTreeMap<(u8, Module), Vec<usize>>> = BTreeMap::new();
    for (i, t) in tags.iter().enumerate() {
        by_interval
            .entry(t.poll_ms)
            .or_default()
            .entry((t.station, t.module))
            .or_default()
            .push(i);
    }
    by_interval
        .into_iter()
        .map(|(ms, areas)| {
            let mut reads: Vec<PollRead> = Vec::new();
            for ((station, module), mut members) in areas {
                members.sort_by_key(|&i| tags[i].address);
                let max_words = (MAX_READ / module.word_bytes()) as u32;
                let mut current: Option<PollRead> = None;
                for i in members {
                    let t = &tags[i];
                    let start = u32::from(t.address);
                    let end = start + u32::from(t.kind.words(module));
                    match &mut current {
                        Some(r) if end - u32::from(r.address) <= max_words => {
                            let r_end = u32::from(r.address) + u32::from(r.words);
                            r.words = (end.max(r_end) - u32::from(r.address)) as u16;
                            r.tags.push(i);
                        }
                        _ => {
                            if let Some(r) = current.take() {
                                reads.push(r);
                            }
                            current = Some(PollRead {
                                station,
                                module,
                                address: t.address,
                                words: (end - start) as u16,
                                tags: vec![i],
                            });
                        }
                    }
                }
                reads.extend(current);
            }
            PollGroup {
                interval: Duration::from_millis(u64::from(ms)),
                reads,
            }
        })
        .collect()
}

impl BusCode for TagError {
    fn code(&self) -> pb::ErrorCode {
        match self {
            TagError::Unknown { .. } => pb::ErrorCode::NotFound,
            TagError::ReadOnly { .. } => pb::ErrorCode::NotSupported,
            TagError::OutOfRange { .. } => pb::ErrorCode::InvalidRequest,
        }
    }
}

#[cfg(test)]
mod tests;
