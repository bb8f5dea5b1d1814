//! The sequence buffer (MTConnect Part 1, "Buffer"): every observation numbered from 1 without
//! gaps, the latest `size` kept in a ring, and the state of every data item, so that
//! `/current`, `/current?at=` and `/sample` answer from memory.
//!
//! Memory is bounded by `size`: each slot is an [`Observation`] (`size_of` is printed by the
//! `mtconnect` benchmark) plus its value's text.

use std::collections::VecDeque;
use std::sync::Arc;

/// A condition's level (Part 3, "Condition").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Level {
    /// No fault (with a native code: that one cleared).
    Normal,
    /// Attention needed, the device still runs.
    Warning,
    /// A failure: the device needs someone.
    Fault,
}

impl Level {
    /// The element name in a Streams document.
    pub fn element(self) -> &'static str {
        match self {
            Level::Normal => "Normal",
            Level::Warning => "Warning",
            Level::Fault => "Fault",
        }
    }
}

/// A condition's state.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Cond {
    /// Its level.
    pub level: Level,
    /// The source's code (`SR0945`, cellgate's own `CG-…`): never empty but for a Normal
    /// that clears every fault.
    pub native_code: Arc<str>,
    /// What happened, in words.
    pub text: Arc<str>,
}

/// An observed value.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Value {
    /// Nothing can be said (Part 3: `UNAVAILABLE`).
    Unavailable,
    /// An event's or sample's value, as text.
    Text(Arc<str>),
    /// A condition.
    Cond(Cond),
}

/// One observation: a data item's value at a time, numbered.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Observation {
    /// Its sequence number.
    pub seq: u64,
    /// The data item (index into the model's items).
    pub item: u32,
    /// When the agent observed it: microseconds since the Unix epoch.
    pub time_us: u64,
    /// The value.
    pub value: Value,
}

/// The state of one data item: its last observation and, for a condition, every fault or
/// warning active (by native code).
#[derive(Debug, Clone, Default)]
pub struct ItemState {
    /// The last observation.
    pub last: Option<Observation>,
    /// A condition's active warnings and faults.
    pub active: Vec<Observation>,
}

impl ItemState {
    fn apply(&mut self, o: &Observation) {
        if let Value::Cond(c) = &o.value {
            match c.level {
                Level::Normal if c.native_code.is_empty() => self.active.clear(),
                Level::Normal => self.active.retain(|a| code(a) != Some(&c.native_code)),
                _ => {
                    if let Some(a) = self
                        .active
                        .iter_mut()
                        .find(|a| code(a) == Some(&c.native_code))
                    {
                        *a = o.clone();
                    } else {
                        self.active.push(o.clone());
                    }
                }
            }
        } else {
            self.active.clear();
        }
        self.last = Some(o.clone());
    }

    /// What `/current` shows of it: the active conditions, else the last observation.
    pub fn shown(&self) -> Vec<&Observation> {
        if self.active.is_empty() {
            self.last.iter().collect()
        } else {
            self.active.iter().collect()
        }
    }
}

fn code(o: &Observation) -> Option<&Arc<str>> {
    match &o.value {
        Value::Cond(c) => Some(&c.native_code),
        _ => None,
    }
}

/// The ring of observations and the state of every data item.
#[derive(Debug, Clone)]
pub struct SequenceBuffer {
    size: usize,
    ring: VecDeque<Observation>,
    next: u64,
    /// The state just before the first observation in the ring (for `at`).
    base: Vec<ItemState>,
    /// The state after the last.
    latest: Vec<ItemState>,
}

/// Why a sequence number or count was refused (Part 1: `OUT_OF_RANGE`).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("'{param}' must be between {min} and {max}; {value} is not")]
pub struct OutOfRange {
    /// The query parameter.
    pub param: &'static str,
    /// Its value.
    pub value: i64,
    /// The least it may be.
    pub min: i64,
    /// The most it may be.
    pub max: i64,
}

impl SequenceBuffer {
    /// An empty buffer of `size` slots; the first observation is number 1.
    pub fn new(size: usize) -> Self {
        SequenceBuffer {
            size: size.max(1),
            ring: VecDeque::with_capacity(size.min(1 << 16)),
            next: 1,
            base: Vec::new(),
            latest: Vec::new(),
        }
    }

    /// `bufferSize`.
    pub fn size(&self) -> usize {
        self.size
    }

    /// `nextSequence`: the number the next observation gets.
    pub fn next(&self) -> u64 {
        self.next
    }

    /// `firstSequence`: the oldest observation kept.
    pub fn first(&self) -> u64 {
        self.ring.front().map_or(self.next, |o| o.seq)
    }

    /// `lastSequence`: the newest observation.
    pub fn last(&self) -> u64 {
        self.next.saturating_sub(1)
    }

    /// The state of data item `item` now.
    pub fn state(&self, item: usize) -> Option<&ItemState> {
        self.latest.get(item)
    }

    /// Every data item's state now.
    pub fn latest(&self) -> &[ItemState] {
        &self.latest
    }

    /// Appends an observation of `item` and returns its number; the oldest one goes when the
    /// ring is full.
    pub fn push(&mut self, item: u32, time_us: u64, value: Value) -> u64 {
        let i = item as usize;
        if self.latest.len() <= i {
            self.latest.resize_with(i + 1, ItemState::default);
            self.base.resize_with(i + 1, ItemState::default);
        }
        let seq = self.next;
        self.next += 1;
        let o = Observation {
            seq,
            item,
            time_us,
            value,
        };
        self.latest[i].apply(&o);
        if self.ring.len() == self.size
            && let Some(old) = self.ring.pop_front()
        {
            self.base[old.item as usize].apply(&old);
        }
        self.ring.push_back(o);
        seq
    }

    /// Checks `at` for `/current?at=` (firstSequence ≤ at ≤ lastSequence).
    pub fn check_at(&self, at: i64) -> Result<u64, OutOfRange> {
        let (min, max) = (self.first() as i64, self.last() as i64);
        if at < min || at > max {
            return Err(OutOfRange {
                param: "at",
                value: at,
                min,
                max,
            });
        }
        Ok(at as u64)
    }

    /// The state of every data item as of observation `at` (already checked).
    pub fn state_at(&self, at: u64) -> Vec<ItemState> {
        let mut state = self.base.clone();
        state.resize_with(self.latest.len(), ItemState::default);
        for o in self.ring.iter().take_while(|o| o.seq <= at) {
            state[o.item as usize].apply(o);
        }
        state
    }

    /// Checks `from` for `/sample` (firstSequence ≤ from ≤ nextSequence).
    pub fn check_from(&self, from: i64) -> Result<u64, OutOfRange> {
        let (min, max) = (self.first() as i64, self.next as i64);
        if from < min || from > max {
            return Err(OutOfRange {
                param: "from",
                value: from,
                min,
                max,
            });
        }
        Ok(from as u64)
    }

    /// Checks `count` for `/sample`: not 0, at most `bufferSize` either way (a negative count
    /// takes the newest observations, Part 1 "sample").
    pub fn check_count(&self, count: i64) -> Result<i64, OutOfRange> {
        let max = self.size as i64;
        if count == 0 || count.unsigned_abs() > max as u64 {
            return Err(OutOfRange {
                param: "count",
                value: count,
                min: -max,
                max,
            });
        }
        Ok(count)
    }

    /// Up to `count` observations from `from` that `wanted` takes, and the `nextSequence` to
    /// ask from after them. With a negative count, the last `-count` that `wanted` takes.
    pub fn sample(
        &self,
        from: u64,
        count: i64,
        wanted: impl Fn(u32) -> bool,
    ) -> (Vec<&Observation>, u64) {
        let first = self.first();
        if count < 0 {
            let mut out: Vec<&Observation> = self
                .ring
                .iter()
                .rev()
                .filter(|o| wanted(o.item))
                .take(count.unsigned_abs() as usize)
                .collect();
            out.reverse();
            return (out, self.next);
        }
        let start = from.saturating_sub(first) as usize;
        let mut out = Vec::new();
        let mut next = self.next;
        for o in self.ring.iter().skip(start) {
            if out.len() as i64 == count {
                next = o.seq;
                break;
            }
            if wanted(o.item) {
                out.push(o);
            }
        }
        (out, next)
    }
}
