//! A machine's waiting jobs: higher priority first, arrival order among equals.

use std::cmp::Reverse;
use std::collections::BTreeMap;

/// Waiting items ordered by priority (higher first), then by arrival.
#[derive(Debug)]
pub struct PriorityQueue<T> {
    items: BTreeMap<(Reverse<i32>, u64), T>,
    arrivals: u64,
}

impl<T> Default for PriorityQueue<T> {
    fn default() -> Self {
        PriorityQueue {
            items: BTreeMap::new(),
            arrivals: 0,
        }
    }
}

impl<T> PriorityQueue<T> {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds an item; returns how many items are ahead of it.
    pub fn push(&mut self, priority: i32, item: T) -> usize {
        let key = (Reverse(priority), self.arrivals);
        self.arrivals += 1;
        let ahead = self.items.range(..key).count();
        self.items.insert(key, item);
        ahead
    }

    /// Takes the item that runs next.
    pub fn pop(&mut self) -> Option<T> {
        self.items.pop_first().map(|(_, item)| item)
    }

    /// Takes the first item (in run order) that `matches`.
    pub fn remove_first(&mut self, mut matches: impl FnMut(&T) -> bool) -> Option<T> {
        let key = *self.items.iter().find(|(_, item)| matches(item))?.0;
        self.items.remove(&key)
    }

    /// The items in the order they will run.
    pub fn iter(&self) -> impl Iterator<Item = &T> {
        self.items.values()
    }

    pub fn len(&self) -> usize {
        self.items.len()
    }

    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    /// Takes every item, in run order.
    pub fn drain(&mut self) -> Vec<T> {
        std::mem::take(&mut self.items).into_values().collect()
    }
}

#[cfg(test)]
mod tests;
