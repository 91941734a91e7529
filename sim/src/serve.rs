//! The pty service loop shared by the controller emulators, and their fault injection.
//!
//! A [`Controller`] (GRBL, GCS) only turns bytes into replies; this loop owns the pty: it
//! notices a driver opening the port (the board "resets"), feeds it input, runs its timers,
//! and delivers its output through the fault plan (dropped, late or garbled replies, the
//! port vanishing). Protocol parsing stays in the controllers.

use crate::pty::{PollResult, Pty, PtyLink};
use std::collections::VecDeque;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// One piece of controller output.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Out {
    /// The answer to a command (subject to the reply faults).
    Reply(Vec<u8>),
    /// Unsolicited output (banner, alarm, message): delivered as is.
    Push(Vec<u8>),
}

/// Output collected during one step of the controller.
#[derive(Debug, Default)]
pub struct Outbox {
    items: Vec<Out>,
}

impl Outbox {
    pub fn reply(&mut self, bytes: impl Into<Vec<u8>>) {
        self.items.push(Out::Reply(bytes.into()));
    }
    pub fn push(&mut self, bytes: impl Into<Vec<u8>>) {
        self.items.push(Out::Push(bytes.into()));
    }
    pub fn take(&mut self) -> Vec<Out> {
        std::mem::take(&mut self.items)
    }
}

/// A controller's protocol behind the pty.
pub trait Controller: Send + 'static {
    /// A client opened the port (a real board resets on DTR).
    fn on_open(&mut self, now: Instant, out: &mut Outbox);
    /// The client closed the port.
    fn on_close(&mut self) {}
    /// Bytes from the client.
    fn on_bytes(&mut self, bytes: &[u8], now: Instant, out: &mut Outbox);
    /// Timers (motion done, dwell over, alarm due); returns when it wants the next tick.
    fn tick(&mut self, now: Instant, out: &mut Outbox) -> Option<Instant>;
    /// The line terminator used for injected garbage lines.
    fn line_end(&self) -> &'static [u8];
}

/// Faults to inject, shared between the emulator thread and whoever drives the test.
/// Counts apply to the next N replies; the `*_every` fields repeat (standalone binaries).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FaultPlan {
    /// Drop the next N replies.
    pub drop_replies: u32,
    /// Deliver the next N replies `late_by` late.
    pub late_replies: u32,
    pub late_by: Duration,
    /// Put a line of garbage bytes before each of the next N replies.
    pub garbage_replies: u32,
    /// Interrupt the current or next move halfway with the controller's fault (GRBL:
    /// ALARM:1 hard limit; GCS: motion error, servo off).
    pub alarm_mid_move: bool,
    /// Drop every Nth reply (0 = never).
    pub drop_every: u32,
    /// Garbage before every Nth reply (0 = never).
    pub garbage_every: u32,
    /// Mangle the next N status reports (`<…>` replies): their closing `>` garbled, as a
    /// noisy line or grbl-sim's racing output does now and then.
    pub mangle_reports: u32,
    /// The controller's feed-hold button, pressed (GRBL: taken as `!` on the emulator's next
    /// turn; a person at the machine, not the client).
    pub feed_hold: bool,
}

#[derive(Debug, Default)]
struct FaultState {
    plan: FaultPlan,
    replies_seen: u64,
    vanish: bool,
    restore: bool,
}

/// Handle on the faults of one emulator.
#[derive(Debug, Clone, Default)]
pub struct Faults {
    inner: Arc<Mutex<FaultState>>,
}

impl Faults {
    fn lock(&self) -> std::sync::MutexGuard<'_, FaultState> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }
    /// Replace the fault plan.
    pub fn set(&self, plan: FaultPlan) {
        self.lock().plan = plan;
    }
    /// Edit the fault plan in place.
    pub fn update(&self, f: impl FnOnce(&mut FaultPlan)) {
        f(&mut self.lock().plan);
    }
    pub fn plan(&self) -> FaultPlan {
        self.lock().plan.clone()
    }
    /// Close the master now: the port vanishes (like a USB adapter pulled out).
    pub fn vanish(&self) {
        let mut st = self.lock();
        st.vanish = true;
        st.restore = false;
    }
    /// Bring the port back (on a new pty; the stable link points at it).
    pub fn restore(&self) {
        self.lock().restore = true;
    }
    /// Consumed by the GRBL emulator on its next turn.
    pub fn take_feed_hold(&self) -> bool {
        std::mem::take(&mut self.lock().plan.feed_hold)
    }
    /// Consumed by a controller when a move starts.
    /// Whether to mangle this status report (one of `mangle_reports`).
    fn take_mangle(&self) -> bool {
        let p = &mut self.lock().plan;
        let mangle = p.mangle_reports > 0;
        p.mangle_reports = p.mangle_reports.saturating_sub(1);
        mangle
    }
    pub fn take_alarm_mid_move(&self) -> bool {
        std::mem::take(&mut self.lock().plan.alarm_mid_move)
    }
}

/// What to do with one reply.
struct ReplyFate {
    drop: bool,
    garbage: bool,
    late: Option<Duration>,
}

fn fate(faults: &Faults) -> ReplyFate {
    let mut st = faults.lock();
    st.replies_seen += 1;
    let n = st.replies_seen;
    let p = &mut st.plan;
    let mut drop = n.checked_rem(u64::from(p.drop_every)) == Some(0);
    if p.drop_replies > 0 {
        p.drop_replies -= 1;
        drop = true;
    }
    let mut garbage = n.checked_rem(u64::from(p.garbage_every)) == Some(0);
    if p.garbage_replies > 0 {
        p.garbage_replies -= 1;
        garbage = true;
    }
    let late = if p.late_replies > 0 {
        p.late_replies -= 1;
        Some(p.late_by)
    } else {
        None
    };
    ReplyFate {
        drop,
        garbage,
        late,
    }
}

/// Line noise: bytes no controller sends, none of them a line terminator.
pub const GARBAGE: &[u8] = &[0xff, 0xfe, b'#', 0x00, b'%', 0x9c, b'q', 0x81, b'<', 0x7f];

/// A running emulator: its thread, its port path and its faults. Dropping it stops the
/// thread and closes the port.
pub struct Served {
    path: Arc<Mutex<PathBuf>>,
    faults: Faults,
    /// Bytes read from clients so far: lets a test see that a process sent nothing.
    received: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Served {
    /// The path a driver opens: the stable link if one was asked for, else `/dev/pts/N`
    /// (which changes after the port vanishes and comes back).
    pub fn path(&self) -> PathBuf {
        self.path.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
    pub fn faults(&self) -> &Faults {
        &self.faults
    }
    /// Bytes received from whoever opened the port, since the emulator started.
    pub fn bytes_received(&self) -> u64 {
        self.received.load(Ordering::SeqCst)
    }
    /// Stop serving and wait for the thread.
    pub fn shutdown(mut self) {
        self.stop_thread();
    }
    fn stop_thread(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        self.stop_thread();
    }
}

/// Serve `ctrl` on a new pty, optionally behind a stable symlink at `link`.
pub fn serve<C: Controller>(
    ctrl: C,
    faults: Faults,
    link: Option<&Path>,
    thread_name: &str,
) -> io::Result<Served> {
    let pty = Pty::open()?;
    let link = link.map(PtyLink::new);
    let shown = match &link {
        Some(l) => {
            l.point_to(pty.slave_path())?;
            l.path().to_path_buf()
        }
        None => pty.slave_path().to_path_buf(),
    };
    let path = Arc::new(Mutex::new(shown));
    let stop = Arc::new(AtomicBool::new(false));
    let received = Arc::new(AtomicU64::new(0));
    let mut lp = Loop {
        ctrl,
        faults: faults.clone(),
        received: received.clone(),
        pty: Some(pty),
        link,
        path: path.clone(),
        stop: stop.clone(),
        connected: false,
        delayed: VecDeque::new(),
    };
    let thread = std::thread::Builder::new()
        .name(thread_name.to_string())
        .spawn(move || lp.run())?;
    Ok(Served {
        path,
        faults,
        received,
        stop,
        thread: Some(thread),
    })
}

struct Loop<C: Controller> {
    ctrl: C,
    faults: Faults,
    received: Arc<AtomicU64>,
    pty: Option<Pty>,
    link: Option<PtyLink>,
    path: Arc<Mutex<PathBuf>>,
    stop: Arc<AtomicBool>,
    connected: bool,
    /// Late output: (release time, bytes), in order.
    delayed: VecDeque<(Instant, Vec<u8>)>,
}

/// How long the loop sleeps at most: bounds the latency of timers and of noticing a client.
const IDLE_POLL: Duration = Duration::from_millis(5);

impl<C: Controller> Loop<C> {
    fn run(&mut self) {
        let mut next_tick: Option<Instant> = None;
        let mut buf = [0u8; 512];
        while !self.stop.load(Ordering::SeqCst) {
            if self.handle_vanish() {
                continue;
            }
            let now = Instant::now();
            let mut wake = now + IDLE_POLL;
            if let Some(t) = next_tick {
                wake = wake.min(t);
            }
            if let Some((t, _)) = self.delayed.front() {
                wake = wake.min(*t);
            }
            let Some(pty) = &self.pty else { continue };
            let polled = pty.poll(wake.saturating_duration_since(now));
            let mut out = Outbox::default();
            match polled {
                Ok(PollResult::Hangup) | Err(_) => {
                    if self.connected {
                        self.connected = false;
                        self.delayed.clear();
                        self.ctrl.on_close();
                    }
                    // HUP polls ready at once: do not spin while nobody is connected.
                    std::thread::sleep(Duration::from_millis(2));
                    continue;
                }
                Ok(PollResult::Readable) => {
                    let now = Instant::now();
                    if !self.connected {
                        self.connected = true;
                        self.ctrl.on_open(now, &mut out);
                    }
                    match pty.read(&mut buf) {
                        Ok(n) if n > 0 => {
                            self.received.fetch_add(n as u64, Ordering::SeqCst);
                            self.ctrl.on_bytes(&buf[..n], now, &mut out)
                        }
                        _ => {}
                    }
                }
                Ok(PollResult::Quiet) => {
                    if !self.connected {
                        self.connected = true;
                        self.ctrl.on_open(Instant::now(), &mut out);
                    }
                }
            }
            next_tick = self.ctrl.tick(Instant::now(), &mut out);
            self.deliver(out.take());
            self.release_delayed();
        }
    }

    /// Apply a pending vanish/restore; true while the port is gone.
    fn handle_vanish(&mut self) -> bool {
        let (vanish, restore) = {
            let mut st = self.faults.lock();
            let v = std::mem::take(&mut st.vanish);
            let r = if self.pty.is_none() || v {
                std::mem::take(&mut st.restore)
            } else {
                false
            };
            (v, r)
        };
        if vanish && self.pty.is_some() {
            self.pty = None;
            if let Some(l) = &self.link {
                l.remove();
            }
            self.delayed.clear();
            if self.connected {
                self.connected = false;
                self.ctrl.on_close();
            }
        }
        if self.pty.is_none() {
            if restore {
                if let Ok(pty) = Pty::open() {
                    let shown = match &self.link {
                        Some(l) if l.point_to(pty.slave_path()).is_ok() => l.path().to_path_buf(),
                        _ => pty.slave_path().to_path_buf(),
                    };
                    *self.path.lock().unwrap_or_else(|e| e.into_inner()) = shown;
                    self.pty = Some(pty);
                    return false;
                }
            }
            std::thread::sleep(Duration::from_millis(2));
            return true;
        }
        false
    }

    fn deliver(&mut self, items: Vec<Out>) {
        let now = Instant::now();
        for item in items {
            let (bytes, release) = match item {
                Out::Push(b) => (b, None),
                Out::Reply(b) => {
                    let f = fate(&self.faults);
                    if f.drop {
                        continue;
                    }
                    let mut bytes = Vec::new();
                    if f.garbage {
                        bytes.extend_from_slice(GARBAGE);
                        bytes.extend_from_slice(self.ctrl.line_end());
                    }
                    let at = bytes.len();
                    bytes.extend_from_slice(&b);
                    if b.starts_with(b"<") && self.faults.take_mangle() {
                        if let Some(i) = bytes[at..].iter().rposition(|&c| c == b'>') {
                            bytes[at + i] = b'o';
                        }
                    }
                    (bytes, f.late.map(|d| now + d))
                }
            };
            // Keep order: anything behind a late reply waits for it.
            let behind = self.delayed.back().map(|(t, _)| *t);
            match (release, behind) {
                (None, None) => self.write(&bytes),
                (r, b) => {
                    let t = r.unwrap_or(now).max(b.unwrap_or(now));
                    self.delayed.push_back((t, bytes));
                }
            }
        }
    }

    fn release_delayed(&mut self) {
        let now = Instant::now();
        while let Some((t, _)) = self.delayed.front() {
            if *t > now {
                break;
            }
            let (_, bytes) = self.delayed.pop_front().expect("front exists");
            self.write(&bytes);
        }
    }

    fn write(&self, bytes: &[u8]) {
        if let Some(pty) = &self.pty {
            // A write error means the client went away; the next poll notices.
            let _ = pty.write_all(bytes);
        }
    }
}

/// The fault-injection flags both standalone emulators (`sim-grbl`, `sim-gcs`) take.
#[derive(Debug, Clone, clap::Args)]
pub struct FaultArgs {
    /// Drop every Nth reply (0 = never).
    #[arg(long, default_value_t = 0)]
    pub drop_every: u32,
    /// A garbage line before every Nth reply (0 = never).
    #[arg(long, default_value_t = 0)]
    pub garbage_every: u32,
    /// Deliver every reply this many ms late (0 = on time).
    #[arg(long, default_value_t = 0)]
    pub late_ms: u64,
    /// Make the first move fail halfway (GRBL: ALARM:1; GCS: motion error -1024, servo off).
    #[arg(long)]
    pub alarm_mid_move: bool,
    /// Make the port vanish every N seconds, for a second (0 = never).
    #[arg(long, default_value_t = 0.0)]
    pub vanish_every_s: f64,
}

impl FaultArgs {
    pub fn plan(&self) -> FaultPlan {
        FaultPlan {
            drop_every: self.drop_every,
            garbage_every: self.garbage_every,
            alarm_mid_move: self.alarm_mid_move,
            late_replies: if self.late_ms > 0 { u32::MAX } else { 0 },
            late_by: Duration::from_millis(self.late_ms),
            ..FaultPlan::default()
        }
    }

    /// Arm the plan, print the port path, then serve until killed (vanishing the port on
    /// schedule if asked). `path` is asked again after the port comes back: without a link
    /// the new pty has a new name.
    pub fn serve_forever(&self, faults: &Faults, path: impl Fn() -> PathBuf) -> ! {
        faults.set(self.plan());
        println!("{}", path().display());
        loop {
            if self.vanish_every_s > 0.0 {
                std::thread::sleep(Duration::from_secs_f64(self.vanish_every_s));
                faults.vanish();
                eprintln!("port vanished");
                std::thread::sleep(Duration::from_secs(1));
                faults.restore();
                std::thread::sleep(Duration::from_millis(50));
                eprintln!("port back at {}", path().display());
            } else {
                std::thread::sleep(Duration::from_secs(3600));
            }
        }
    }
}
