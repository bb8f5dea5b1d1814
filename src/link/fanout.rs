//! Events to every subscriber, each with a bounded backlog that costs memory only while it
//! holds something.
//!
//! `tokio::sync::broadcast` keeps one ring for all its receivers, every slot allocated up
//! front: a link's 256 events and a machine's 1024 job events were 55 KiB a link, idle or
//! busy, at a thousand links (docs/performance.md, "Where a link's memory goes"). Here each
//! subscriber has its own bounded queue (`tokio::sync::mpsc`, whose slots come in blocks of 32
//! as they fill), so an idle link holds a block per subscriber and a backlog is paid for only
//! while it lasts. A subscriber that falls `capacity` events behind loses the newest ones
//! instead of the oldest, and is told how many with [`RecvError::Lagged`] at the point where
//! they are missing, as a broadcast receiver would be: every event carries its number, and a
//! receiver that has read all it holds compares its count with the sender's, so that events
//! lost at the end of a burst are told too, before it waits.

use std::sync::{Arc, Mutex, PoisonError, Weak};

use tokio::sync::mpsc;

pub use tokio::sync::broadcast::error::{RecvError, TryRecvError};

/// Sends to every receiver subscribed. Cheap to clone; the receivers see `Closed` once every
/// sender is dropped.
#[derive(Debug)]
pub struct Sender<T> {
    shared: Arc<Mutex<Shared<T>>>,
}

impl<T> Clone for Sender<T> {
    fn clone(&self) -> Self {
        Sender {
            shared: Arc::clone(&self.shared),
        }
    }
}

#[derive(Debug)]
struct Shared<T> {
    /// The number the next event gets.
    next: u64,
    capacity: usize,
    subscribers: Vec<mpsc::Sender<(u64, T)>>,
}

/// One subscriber's events.
#[derive(Debug)]
pub struct Receiver<T> {
    events: mpsc::Receiver<(u64, T)>,
    /// The senders' side, for the count of events sent (weak: the receiver must not keep
    /// the channel open).
    shared: Weak<Mutex<Shared<T>>>,
    /// The number of the event expected next.
    next: u64,
    /// The event that arrived after a gap, given after the gap was told.
    after_gap: Option<T>,
}

/// A sender and its first receiver; each receiver holds at most `capacity` events unread.
pub fn channel<T: Clone>(capacity: usize) -> (Sender<T>, Receiver<T>) {
    let sender = Sender {
        shared: Arc::new(Mutex::new(Shared {
            next: 0,
            capacity: capacity.max(1),
            subscribers: Vec::new(),
        })),
    };
    let first = sender.subscribe();
    (sender, first)
}

impl<T: Clone> Sender<T> {
    /// Gives `event` to every receiver with room for it; a receiver without loses it (and
    /// hears of it). Returns how many receivers took it; never waits.
    pub fn send(&self, event: T) -> usize {
        let mut shared = self.shared.lock().unwrap_or_else(PoisonError::into_inner);
        let n = shared.next;
        shared.next += 1;
        let mut taken = 0;
        shared
            .subscribers
            .retain(|s| match s.try_send((n, event.clone())) {
                Ok(()) => {
                    taken += 1;
                    true
                }
                Err(mpsc::error::TrySendError::Full(_)) => true,
                Err(mpsc::error::TrySendError::Closed(_)) => false,
            });
        taken
    }

    /// A receiver of the events sent from now on.
    pub fn subscribe(&self) -> Receiver<T> {
        let mut shared = self.shared.lock().unwrap_or_else(PoisonError::into_inner);
        let (tx, rx) = mpsc::channel(shared.capacity);
        shared.subscribers.push(tx);
        Receiver {
            events: rx,
            shared: Arc::downgrade(&self.shared),
            next: shared.next,
            after_gap: None,
        }
    }
}

impl<T> Receiver<T> {
    /// The next event; `Lagged(n)` where `n` events were lost for want of room, then the
    /// event after them; `Closed` once every sender is gone and every event was read.
    pub async fn recv(&mut self) -> Result<T, RecvError> {
        match self.try_recv() {
            Ok(event) => Ok(event),
            Err(TryRecvError::Lagged(n)) => Err(RecvError::Lagged(n)),
            Err(TryRecvError::Closed) => Err(RecvError::Closed),
            Err(TryRecvError::Empty) => {
                let Some((n, event)) = self.events.recv().await else {
                    return Err(RecvError::Closed);
                };
                self.gap_before(n, event).map_err(RecvError::Lagged)
            }
        }
    }

    /// The next event if one is there, without waiting; as [`Receiver::recv`] otherwise.
    pub fn try_recv(&mut self) -> Result<T, TryRecvError> {
        if let Some(event) = self.after_gap.take() {
            return Ok(event);
        }
        let (n, event) = match self.events.try_recv() {
            Ok(next) => next,
            Err(mpsc::error::TryRecvError::Disconnected) => return Err(TryRecvError::Closed),
            Err(mpsc::error::TryRecvError::Empty) => {
                // Looked at again under the senders' lock, where every send happens: empty
                // there, an event numbered below the senders' count is lost, not under way.
                let Some(shared) = self.shared.upgrade() else {
                    return self.events.try_recv().map_or_else(
                        |_| Err(TryRecvError::Closed),
                        |(n, event)| self.gap_before(n, event).map_err(TryRecvError::Lagged),
                    );
                };
                let shared = shared.lock().unwrap_or_else(PoisonError::into_inner);
                match self.events.try_recv() {
                    Ok(next) => next,
                    Err(mpsc::error::TryRecvError::Disconnected) => {
                        return Err(TryRecvError::Closed);
                    }
                    Err(mpsc::error::TryRecvError::Empty) => {
                        let missed = shared.next.saturating_sub(self.next);
                        self.next = shared.next;
                        return Err(if missed > 0 {
                            TryRecvError::Lagged(missed)
                        } else {
                            TryRecvError::Empty
                        });
                    }
                }
            }
        };
        self.gap_before(n, event).map_err(TryRecvError::Lagged)
    }

    /// `event`, numbered `n`, unless events are missing before it: then their count, and
    /// `event` is kept for the next call.
    fn gap_before(&mut self, n: u64, event: T) -> Result<T, u64> {
        let missed = n.saturating_sub(self.next);
        self.next = n + 1;
        if missed > 0 {
            self.after_gap = Some(event);
            return Err(missed);
        }
        Ok(event)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn every_receiver_gets_every_event_in_order() {
        let (tx, mut a) = channel(4);
        let mut b = tx.subscribe();
        for i in 0..3 {
            assert_eq!(tx.send(i), 2);
        }
        for i in 0..3 {
            assert_eq!(a.recv().await, Ok(i));
            assert_eq!(b.recv().await, Ok(i));
        }
    }

    #[tokio::test]
    async fn a_receiver_subscribed_later_starts_from_then() {
        let (tx, _first) = channel(4);
        tx.send(1);
        let mut late = tx.subscribe();
        tx.send(2);
        assert_eq!(late.recv().await, Ok(2));
    }

    #[tokio::test]
    async fn a_full_receiver_is_told_what_it_lost_where_it_lost_it() {
        let (tx, mut slow) = channel(2);
        let mut fast = tx.subscribe();
        for i in 0..5 {
            tx.send(i);
            assert_eq!(fast.recv().await, Ok(i));
        }
        // 0 and 1 fitted; 2, 3 and 4 did not.
        assert_eq!(slow.recv().await, Ok(0));
        tx.send(5);
        assert_eq!(slow.recv().await, Ok(1));
        assert_eq!(slow.recv().await, Err(RecvError::Lagged(3)));
        assert_eq!(slow.recv().await, Ok(5));
        assert_eq!(slow.try_recv(), Err(TryRecvError::Empty));
        tx.send(6);
        assert_eq!(slow.try_recv(), Ok(6));
    }

    #[tokio::test]
    async fn events_lost_at_the_end_of_a_burst_are_told_before_waiting() {
        let (tx, mut rx) = channel(2);
        for i in 0..4 {
            tx.send(i);
        }
        assert_eq!(rx.recv().await, Ok(0));
        assert_eq!(rx.recv().await, Ok(1));
        // 2 and 3 found no room, and nothing came after them.
        assert_eq!(rx.recv().await, Err(RecvError::Lagged(2)));
        assert_eq!(rx.try_recv(), Err(TryRecvError::Empty));
        tx.send(4);
        assert_eq!(rx.recv().await, Ok(4));
    }

    #[tokio::test]
    async fn receivers_hear_closed_after_the_last_event_once_the_senders_are_gone() {
        let (tx, mut rx) = channel(2);
        let other = tx.clone();
        tx.send(7);
        drop(tx);
        drop(other);
        assert_eq!(rx.recv().await, Ok(7));
        assert_eq!(rx.recv().await, Err(RecvError::Closed));
    }

    #[tokio::test]
    async fn a_dropped_receiver_is_forgotten() {
        let (tx, rx) = channel::<u8>(2);
        drop(rx);
        assert_eq!(tx.send(1), 0);
        assert!(tx.shared.lock().unwrap().subscribers.is_empty());
    }
}
