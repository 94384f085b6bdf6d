//! The bounded hand-over between a headset's connection task and its pipeline thread.
//!
//! When the pipeline falls behind, the *oldest* waiting frame is dropped: live vectors should
//! describe the newest frames, and the queue (so the latency it adds) never grows past its capacity.

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex, MutexGuard};

pub(crate) struct DropOldestQueue<T> {
    state: Mutex<State<T>>,
    ready: Condvar,
    capacity: usize,
}

struct State<T> {
    items: VecDeque<T>,
    closed: bool,
}

/// What `push` did.
#[derive(Debug, PartialEq)]
pub(crate) enum Pushed<T> {
    Queued,
    /// Queued, and this oldest item was dropped to make room.
    DroppedOldest(T),
    /// The queue is closed; the item is handed back.
    Closed(T),
}

impl<T> DropOldestQueue<T> {
    /// A capacity of 0 is taken as 1.
    pub(crate) fn new(capacity: usize) -> Self {
        Self {
            state: Mutex::new(State {
                items: VecDeque::with_capacity(capacity.max(1)),
                closed: false,
            }),
            ready: Condvar::new(),
            capacity: capacity.max(1),
        }
    }

    fn lock(&self) -> MutexGuard<'_, State<T>> {
        // A panic while holding this lock cannot leave the deque inconsistent: keep going.
        self.state
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    pub(crate) fn push(&self, item: T) -> Pushed<T> {
        let mut state = self.lock();
        if state.closed {
            return Pushed::Closed(item);
        }
        let dropped = if state.items.len() >= self.capacity {
            state.items.pop_front()
        } else {
            None
        };
        state.items.push_back(item);
        drop(state);
        self.ready.notify_one();
        match dropped {
            Some(old) => Pushed::DroppedOldest(old),
            None => Pushed::Queued,
        }
    }

    /// The oldest item, waiting for one; `None` once the queue is closed and empty.
    pub(crate) fn pop(&self) -> Option<T> {
        let mut state = self.lock();
        loop {
            if let Some(item) = state.items.pop_front() {
                return Some(item);
            }
            if state.closed {
                return None;
            }
            state = self
                .ready
                .wait(state)
                .unwrap_or_else(|poisoned| poisoned.into_inner());
        }
    }

    /// Refuses further pushes; items already queued are still popped.
    pub(crate) fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_all();
    }

    pub(crate) fn len(&self) -> usize {
        self.lock().items.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn full_queue_drops_the_oldest_and_keeps_the_newest() {
        let q = DropOldestQueue::new(2);
        assert_eq!(q.push(1), Pushed::Queued);
        assert_eq!(q.push(2), Pushed::Queued);
        assert_eq!(q.push(3), Pushed::DroppedOldest(1));
        assert_eq!(q.len(), 2);
        assert_eq!(q.pop(), Some(2));
        assert_eq!(q.pop(), Some(3));
    }

    #[test]
    fn closing_drains_what_is_queued_then_ends_the_consumer() {
        let q = Arc::new(DropOldestQueue::new(4));
        let consumer = {
            let q = Arc::clone(&q);
            std::thread::spawn(move || std::iter::from_fn(|| q.pop()).collect::<Vec<_>>())
        };
        for i in 0..3 {
            assert_eq!(q.push(i), Pushed::Queued);
        }
        q.close();
        assert_eq!(q.push(9), Pushed::Closed(9));
        let seen = consumer.join().expect("consumer ends");
        assert_eq!(seen, vec![0, 1, 2]);
    }
}
