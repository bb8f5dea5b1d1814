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
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn higher_priority_first_fifo_among_equals() {
        let mut q = PriorityQueue::new();
        assert_eq!(q.push(0, "a"), 0);
        assert_eq!(q.push(0, "b"), 1);
        assert_eq!(q.push(5, "urgent"), 0);
        assert_eq!(q.push(-1, "later"), 3);
        assert_eq!(q.push(0, "c"), 3);
        let order: Vec<_> = q.iter().copied().collect();
        assert_eq!(order, ["urgent", "a", "b", "c", "later"]);
        assert_eq!(q.remove_first(|x| *x == "b"), Some("b"));
        assert_eq!(q.pop(), Some("urgent"));
        assert_eq!(q.drain(), ["a", "c", "later"]);
        assert!(q.is_empty());
    }

    proptest! {
        #[test]
        fn pops_in_priority_then_arrival_order(prios in proptest::collection::vec(-3i32..3, 0..50)) {
            let mut q = PriorityQueue::new();
            for (i, p) in prios.iter().enumerate() {
                let ahead = q.push(*p, (*p, i));
                // Ahead of it: everything of higher priority, and equal priority before it.
                let expect = prios[..i].iter().filter(|&&o| o >= *p).count();
                prop_assert_eq!(ahead, expect);
            }
            let mut expected: Vec<(i32, usize)> = prios.iter().copied().zip(0..).collect();
            expected.sort_by_key(|&(p, i)| (Reverse(p), i));
            let mut popped = Vec::new();
            while let Some(x) = q.pop() {
                popped.push(x);
            }
            prop_assert_eq!(popped, expected);
        }
    }
}
