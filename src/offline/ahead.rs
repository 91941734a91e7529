//! Which frame a decoder takes next: the next one in order not yet taken, by whichever
//! decoder is free, never more than `ahead` frames beyond the one being pushed. (Each
//! decoder taking every W-th frame instead stalls the run whenever one of them falls
//! behind: the others wait with their frames decoded while the pusher waits for it.)

use std::sync::{Condvar, Mutex};

#[derive(Debug)]
struct State {
    next: usize,
    consumed: usize,
    stopped: bool,
}

/// The frames `0..n` handed out in order; see the module docs.
#[derive(Debug)]
pub struct Ahead {
    n: usize,
    ahead: usize,
    state: Mutex<State>,
    moved: Condvar,
}

impl Ahead {
    /// # Panics
    /// If `ahead` is 0 (no frame could ever be taken).
    pub fn new(n: usize, ahead: usize) -> Ahead {
        assert!(ahead > 0, "at least one frame ahead");
        Ahead {
            n,
            ahead,
            state: Mutex::new(State {
                next: 0,
                consumed: 0,
                stopped: false,
            }),
            moved: Condvar::new(),
        }
    }

    /// The next frame to decode, waiting while `ahead` frames past the last one consumed
    /// are already taken; `None` when every frame is taken or the run stopped.
    pub fn take(&self) -> Option<usize> {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            if s.stopped || s.next >= self.n {
                return None;
            }
            if s.next < s.consumed + self.ahead {
                s.next += 1;
                return Some(s.next - 1);
            }
            s = self.moved.wait(s).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// Frames `0..=i` are pushed: room for more to be decoded.
    pub fn consumed(&self, i: usize) {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        s.consumed = s.consumed.max(i + 1);
        self.moved.notify_all();
    }

    /// No more frames are wanted (the run ended, or failed): waiting decoders return.
    pub fn stop(&self) {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        s.stopped = true;
        self.moved.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    #[test]
    fn frames_come_in_order_and_never_too_far_ahead() {
        let a = Ahead::new(5, 2);
        assert_eq!((a.take(), a.take()), (Some(0), Some(1)));
        // Two taken past nothing consumed: a third waits until frame 0 is pushed.
        let taken = AtomicUsize::new(usize::MAX);
        std::thread::scope(|s| {
            s.spawn(|| taken.store(a.take().unwrap(), Ordering::SeqCst));
            std::thread::sleep(std::time::Duration::from_millis(50));
            assert_eq!(taken.load(Ordering::SeqCst), usize::MAX, "waited");
            a.consumed(0);
        });
        assert_eq!(taken.into_inner(), 2);
        a.consumed(2);
        assert_eq!((a.take(), a.take(), a.take()), (Some(3), Some(4), None));
    }

    #[test]
    fn stop_releases_a_waiting_decoder() {
        let a = Ahead::new(5, 1);
        assert_eq!(a.take(), Some(0));
        std::thread::scope(|s| {
            let waiter = s.spawn(|| a.take());
            std::thread::sleep(std::time::Duration::from_millis(20));
            a.stop();
            assert_eq!(waiter.join().unwrap(), None);
        });
    }
}
