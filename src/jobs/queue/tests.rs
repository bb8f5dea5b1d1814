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
