//! The accept loop's manners: a connection limit with a polite refusal, a back-off on
//! accept errors (out of file descriptors, out of memory), and logs at a bounded rate.
//!
//! The limit is kept below the process's file-descriptor limit with room to spare
//! ([`RESERVED_FDS`]), so a flood of clients cannot take the fds the running job needs for
//! its frames and logs. Clients over the limit are accepted, told why in one line, and
//! closed at once; they hold no fd after that.

use crate::daemon::protocol::{encode, ErrorCode, ProtoError, Reply, ServerLine};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// File descriptors kept for the daemon itself whatever the clients do: the serial ports
/// and emulator ptys, the interferometer log, a job's steps.csv, interferometer.csv, the
/// frame being written and its folder, a `list` reading sessions, the runtime's own.
pub const RESERVED_FDS: u64 = 128;
/// First and longest pause after an accept error.
pub const BACKOFF_FIRST: Duration = Duration::from_millis(10);
pub const BACKOFF_MAX: Duration = Duration::from_secs(1);

/// The connection limit to enforce: `configured`, lowered to what the fd limit leaves
/// after [`RESERVED_FDS`] (at least 1). Returns the limit and, when lowered, why.
pub fn effective_limit(configured: usize, fd_soft_limit: Option<u64>) -> (usize, Option<String>) {
    let Some(soft) = fd_soft_limit else {
        return (configured.max(1), None);
    };
    let room = soft.saturating_sub(RESERVED_FDS).max(1);
    match (configured as u64) <= room {
        true => (configured.max(1), None),
        false => (
            room as usize,
            Some(format!(
                "[daemon] max_connections = {configured} lowered to {room}: the open-file \
                 limit is {soft} and {RESERVED_FDS} are kept for the rig and the running job"
            )),
        ),
    }
}

/// The soft RLIMIT_NOFILE, if it can be read and is finite.
pub fn fd_soft_limit() -> Option<u64> {
    let (soft, _hard) =
        nix::sys::resource::getrlimit(nix::sys::resource::Resource::RLIMIT_NOFILE).ok()?;
    (soft != nix::sys::resource::RLIM_INFINITY).then_some(soft)
}

/// Counts open connections against the limit.
#[derive(Clone)]
pub struct Gate {
    max: usize,
    open: Arc<AtomicUsize>,
}

/// One admitted connection; dropping it frees its place.
pub struct Permit(Arc<AtomicUsize>);

impl Drop for Permit {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

impl Gate {
    pub fn new(max: usize) -> Gate {
        Gate {
            max,
            open: Arc::new(AtomicUsize::new(0)),
        }
    }

    pub fn max(&self) -> usize {
        self.max
    }

    /// A place for one more connection, if the limit allows.
    pub fn admit(&self) -> Option<Permit> {
        self.open
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < self.max).then_some(n + 1)
            })
            .ok()
            .map(|_| Permit(self.open.clone()))
    }
}

/// The line a client over the limit gets before it is closed.
pub fn refusal(max: usize) -> Vec<u8> {
    encode(&ServerLine::Reply(Reply::err(
        None,
        ProtoError::new(
            ErrorCode::Unavailable,
            format!(
                "too many connections ({max} open, the daemon's [daemon] max_connections): \
                 try again later"
            ),
        ),
    )))
}

/// Pauses after accept errors: [`BACKOFF_FIRST`], doubling to [`BACKOFF_MAX`]; back to the
/// first after a successful accept.
#[derive(Debug)]
pub struct Backoff {
    next: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Backoff {
            next: BACKOFF_FIRST,
        }
    }
}

impl Backoff {
    /// The pause to take now.
    pub fn failed(&mut self) -> Duration {
        let d = self.next;
        self.next = (self.next * 2).min(BACKOFF_MAX);
        d
    }

    pub fn succeeded(&mut self) {
        self.next = BACKOFF_FIRST;
    }
}

/// One log line per `period` at most; the ones held back are counted into the next.
#[derive(Debug)]
pub struct RateLimited {
    period: Duration,
    last: Option<Instant>,
    suppressed: u64,
}

impl RateLimited {
    pub fn per(period: Duration) -> RateLimited {
        RateLimited {
            period,
            last: None,
            suppressed: 0,
        }
    }

    /// Whether to log this occurrence now: `Some(n)`, with `n` occurrences held back since
    /// the last line; `None` to stay quiet.
    pub fn allow(&mut self, now: Instant) -> Option<u64> {
        match self.last {
            Some(t) if now.duration_since(t) < self.period => {
                self.suppressed += 1;
                None
            }
            _ => {
                self.last = Some(now);
                Some(std::mem::take(&mut self.suppressed))
            }
        }
    }
}

/// Whether an accept error is the system running out of something (back off) rather than
/// one client's connection failing (go on at once).
pub fn is_resource_error(e: &std::io::Error) -> bool {
    matches!(
        e.raw_os_error(),
        Some(libc::EMFILE | libc::ENFILE | libc::ENOBUFS | libc::ENOMEM)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_limit_leaves_room_for_the_rig_under_the_fd_limit() {
        assert_eq!(effective_limit(64, Some(1024)), (64, None));
        let (n, why) = effective_limit(5000, Some(1024));
        assert_eq!(n, 896);
        assert!(why.unwrap().contains("open-file limit is 1024"));
        assert_eq!(effective_limit(64, Some(100)).0, 1);
        assert_eq!(effective_limit(0, None).0, 1);
    }

    #[test]
    fn the_gate_admits_up_to_its_limit_and_frees_places() {
        let g = Gate::new(2);
        let a = g.admit().unwrap();
        let _b = g.admit().unwrap();
        assert!(g.admit().is_none());
        drop(a);
        assert!(g.admit().is_some());
    }

    #[test]
    fn backoff_doubles_to_a_second_and_resets() {
        let mut b = Backoff::default();
        let ms: Vec<u128> = (0..9).map(|_| b.failed().as_millis()).collect();
        assert_eq!(ms, [10, 20, 40, 80, 160, 320, 640, 1000, 1000]);
        b.succeeded();
        assert_eq!(b.failed(), BACKOFF_FIRST);
    }

    #[test]
    fn at_most_one_line_a_second_with_the_count_held_back() {
        let mut r = RateLimited::per(Duration::from_secs(1));
        let t = Instant::now();
        assert_eq!(r.allow(t), Some(0));
        for i in 1..=500 {
            assert_eq!(r.allow(t + Duration::from_micros(i)), None);
        }
        assert_eq!(r.allow(t + Duration::from_millis(1001)), Some(500));
    }

    #[test]
    fn the_refusal_is_one_unavailable_line_naming_the_limit() {
        let line = refusal(64);
        assert_eq!(line.iter().filter(|&&b| b == b'\n').count(), 1);
        let v: serde_json::Value = serde_json::from_slice(&line).unwrap();
        assert_eq!(v["error"]["code"], "unavailable");
        assert!(v["error"]["message"]
            .as_str()
            .unwrap()
            .starts_with("too many connections (64"));
    }
}
