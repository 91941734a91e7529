//! One client's output queue, bounded in bytes (not lines: one line can be a 60 kB job).
//!
//! - Replies are never dropped: the connection stops reading requests while the queue is
//!   full ([`Outbox::wait_for_room`]), so replies add at most one line past the bound, and a
//!   client that reads none of them is disconnected once the queue stays full.
//! - Events are dropped while the queue is full. Once the client has caught up (the queue
//!   is down to half the bound) it gets one notice saying how many it lost, then events
//!   again: no event after the gap arrives before the notice.
//!
//! Lines are shared (`Arc<[u8]>`): an event is encoded once for all its subscribers.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tokio::sync::Notify;

/// One line to write, newline included.
pub type Line = Arc<[u8]>;

/// Makes the notice line for `n` lost events.
pub type Notice = fn(u64) -> Line;

pub struct Outbox {
    limit_bytes: usize,
    notice: Notice,
    state: Mutex<State>,
    /// Wakes the writer: a line was queued, or the outbox closed.
    queued: Notify,
    /// Wakes the reader waiting for room: the writer took a line.
    taken: Notify,
    /// Wakes every live-view forwarder: the writer finished writing a line.
    written: Notify,
    /// Wakes the connection: a line it must deliver stalled, the client is dropped.
    abandoned: Notify,
}

#[derive(Default)]
struct State {
    lines: VecDeque<Line>,
    bytes: usize,
    /// Events dropped since the queue filled; a notice is owed once it drains.
    dropped_events: u64,
    closed: bool,
    /// The client stalled on a line: the connection ends ([`Outbox::give_up`]).
    given_up: bool,
}

/// The queue stayed full: the client reads nothing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stalled {
    pub queued_bytes: usize,
}

impl Outbox {
    pub fn new(limit_bytes: usize, notice: Notice) -> Outbox {
        Outbox {
            limit_bytes: limit_bytes.max(1),
            notice,
            state: Mutex::new(State::default()),
            queued: Notify::new(),
            taken: Notify::new(),
            written: Notify::new(),
            abandoned: Notify::new(),
        }
    }

    /// The client took nothing for too long (a live-view line waited past the stall time):
    /// its connection ends ([`Outbox::given_up`]).
    pub fn give_up(&self) {
        self.state().given_up = true;
        self.abandoned.notify_waiters();
    }

    /// Resolves once [`Outbox::give_up`] was called.
    pub async fn given_up(&self) {
        loop {
            // Registered before the flag is read: a give_up in between still wakes it.
            let wake = self.abandoned.notified();
            if self.state().given_up {
                return;
            }
            wake.await;
        }
    }

    fn state(&self) -> MutexGuard<'_, State> {
        // Plain counters and a queue: consistent whatever panicked.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queue a reply (always: the reader keeps replies bounded by waiting for room).
    pub fn reply(&self, line: Line) {
        let mut st = self.state();
        st.bytes += line.len();
        st.lines.push_back(line);
        drop(st);
        self.queued.notify_one();
    }

    /// Queue an event, or drop it if the queue is full or still draining after a drop.
    /// Returns whether it was queued.
    pub fn event(&self, line: Line) -> bool {
        let mut st = self.state();
        if st.closed {
            return false;
        }
        if st.dropped_events > 0 || st.bytes + line.len() > self.limit_bytes {
            st.dropped_events += 1;
            return false;
        }
        st.bytes += line.len();
        st.lines.push_back(line);
        drop(st);
        self.queued.notify_one();
        true
    }

    /// Queue a latest-value line (a live-view frame) if it fits under the bound, or the
    /// queue is empty (a frame larger than the bound goes out alone, like a reply); never
    /// counted as lost (a newer frame replaces it). Returns whether it was queued.
    pub fn offer(&self, line: Line) -> bool {
        let mut st = self.state();
        let fits = st.bytes == 0 || st.bytes + line.len() <= self.limit_bytes;
        if st.closed || st.dropped_events > 0 || !fits {
            return false;
        }
        st.bytes += line.len();
        st.lines.push_back(line);
        drop(st);
        self.queued.notify_one();
        true
    }

    /// The writer has written a line (and dropped it).
    pub fn wrote(&self) {
        self.written.notify_waiters();
    }

    /// Resolves at the writer's next [`Outbox::wrote`] after this call.
    pub fn written(&self) -> tokio::sync::futures::Notified<'_> {
        self.written.notified()
    }

    /// Bytes queued now.
    pub fn queued_bytes(&self) -> usize {
        self.state().bytes
    }

    /// The writer's next line; `None` once closed and empty.
    pub async fn next(&self) -> Option<Line> {
        loop {
            let wait = self.queued.notified();
            {
                let mut st = self.state();
                if let Some(line) = st.lines.pop_front() {
                    st.bytes -= line.len();
                    if st.dropped_events > 0 && st.bytes <= self.limit_bytes / 2 {
                        let n = std::mem::take(&mut st.dropped_events);
                        let notice = (self.notice)(n);
                        st.bytes += notice.len();
                        st.lines.push_back(notice);
                    }
                    drop(st);
                    self.taken.notify_one();
                    return Some(line);
                }
                if st.closed {
                    return None;
                }
            }
            wait.await;
        }
    }

    /// Wait until the queue is below its bound; `Stalled` if it does not get there within
    /// `patience` of the writer last taking a line (each line taken restarts the wait).
    pub async fn wait_for_room(&self, patience: Duration) -> Result<(), Stalled> {
        loop {
            let wait = self.taken.notified();
            let bytes = self.queued_bytes();
            if bytes < self.limit_bytes {
                return Ok(());
            }
            if tokio::time::timeout(patience, wait).await.is_err() {
                return Err(Stalled {
                    queued_bytes: bytes,
                });
            }
        }
    }

    /// No more lines will be queued; the writer ends once the queue is empty.
    pub fn close(&self) {
        self.state().closed = true;
        self.queued.notify_one();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(n: usize) -> Line {
        vec![b'x'; n].into()
    }

    fn notice(n: u64) -> Line {
        format!("lost {n}\n").into_bytes().into()
    }

    #[tokio::test]
    async fn events_are_dropped_when_full_and_one_notice_follows_once_drained() {
        let o = Outbox::new(100, notice);
        for _ in 0..4 {
            assert!(o.event(line(25)));
        }
        // Full: these are lost, even a small one that would fit after the writer takes one.
        assert!(!o.event(line(25)));
        assert!(!o.event(line(1)));
        o.reply(line(30));
        assert_eq!(o.queued_bytes(), 130);
        assert_eq!(o.next().await.unwrap().len(), 25);
        // 105 queued, above half: still dropping.
        assert!(!o.event(line(1)));
        assert_eq!(o.next().await.unwrap().len(), 25);
        // 80 left: the next take gets it to 55, then 30 <= 50: the notice is queued.
        assert_eq!(o.next().await.unwrap().len(), 25);
        assert_eq!(o.next().await.unwrap().len(), 25);
        assert_eq!(o.next().await.unwrap().len(), 30);
        assert_eq!(&*o.next().await.unwrap(), b"lost 3\n");
        assert!(o.event(line(10)));
        o.close();
        assert_eq!(o.next().await.unwrap().len(), 10);
        assert_eq!(o.next().await, None);
    }

    #[tokio::test]
    async fn a_full_queue_nobody_drains_stalls_and_a_drained_one_makes_room() {
        let o = Arc::new(Outbox::new(100, notice));
        o.reply(line(150));
        let e = o
            .wait_for_room(Duration::from_millis(30))
            .await
            .unwrap_err();
        assert_eq!(e.queued_bytes, 150);
        let o2 = o.clone();
        let writer = tokio::spawn(async move { o2.next().await });
        o.wait_for_room(Duration::from_secs(5)).await.unwrap();
        assert_eq!(writer.await.unwrap().unwrap().len(), 150);
    }
}
