//! The live view: `snap` (one fresh frame) and `preview` (the latest frame, at most at the
//! client's rate, never a backlog), each with the targets found in it (docs/protocol.md,
//! "Live view").
//!
//! Frames come from two places: during a job, the job's own frames, tapped on the engine's
//! thread as they go to the recorder (`tap`: a pointer into a one-frame slot, nothing
//! more: the engine never waits for the live view); outside a job, the worker grabs them on
//! the rig's thread at the rate the watchers need (`idle`), and not at all when no one
//! watches. One analyser thread (`analyser`) takes the latest frame from the slot (older
//! ones are dropped), finds its targets once and renders it for each watcher due; a
//! preview's line goes to the subscriber's latest-value slot (`tokio::sync::watch`), which
//! its connection forwards one line at a time (`client`).

pub mod analyser;
pub mod client;
pub mod idle;
pub mod render;
pub mod tap;
pub mod wire;

use crate::acquisition::record::StepRecord;
use crate::daemon::outbox::Line;
use crate::daemon::protocol::ProtoError;
use crate::hw::Frame;
use crate::rig::RigInfo;
use render::Shown;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, SystemTime};
use tokio::sync::{oneshot, watch, Notify};
use wire::{SnapReply, StagePositions};

/// A frame offered to the live view.
pub struct LiveFrame {
    /// The job whose frame it is (none: grabbed by the live view).
    pub job_id: Option<u64>,
    pub image: FrameImage,
    pub stage_um: StagePositions,
}

/// The frame's pixels: a job's record (shared, not copied) or a frame of the live view's.
pub enum FrameImage {
    Step(Arc<StepRecord>),
    Own(Frame),
}

impl LiveFrame {
    pub fn frame(&self) -> &Frame {
        match &self.image {
            FrameImage::Step(r) => &r.frame,
            FrameImage::Own(f) => f,
        }
    }
    fn index(&self) -> Option<u32> {
        match &self.image {
            FrameImage::Step(r) => Some(r.index),
            FrameImage::Own(_) => None,
        }
    }
}

/// One preview subscriber.
struct Sub {
    id: u64,
    shown: Shown,
    interval: Duration,
    /// The exposure time of the last frame rendered for it.
    last: Option<SystemTime>,
    tx: watch::Sender<Option<Line>>,
    /// Its forwarder took the last line rendered (false from a render until then).
    taken: Arc<AtomicBool>,
}

/// A `snap` waiting for its frame.
struct SnapWaiter {
    /// The frame must be exposed at or after this (the request's arrival).
    after: SystemTime,
    shown: Shown,
    reply: oneshot::Sender<Result<SnapReply, ProtoError>>,
}

#[derive(Default)]
struct State {
    /// The latest frame not yet taken by the analyser.
    frame: Option<LiveFrame>,
    subs: Vec<Sub>,
    snaps: Vec<SnapWaiter>,
    next_id: u64,
    /// The exposure time of the last frame the worker grabbed for the live view.
    last_grab: Option<SystemTime>,
    /// No idle grab before this (after a failed one).
    retry_at: Option<SystemTime>,
    failures: u32,
    closed: bool,
}

struct Inner {
    info: RigInfo,
    state: Mutex<State>,
    /// Wakes the analyser: a frame was offered, or the live view closed.
    offered: Condvar,
    /// Wakes the worker: a watcher came (or went).
    watchers_changed: Notify,
    /// Subscribers plus waiting snaps: taps offer frames only when someone watches.
    watchers: AtomicUsize,
}

impl Inner {
    fn state(&self) -> MutexGuard<'_, State> {
        // Plain data: consistent whatever panicked.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Recount the watchers (with the state locked) and tell the worker.
    fn recount(&self, st: &State) {
        self.watchers
            .store(st.subs.len() + st.snaps.len(), Ordering::SeqCst);
        self.watchers_changed.notify_one();
    }
}

/// The live view's hub, one per daemon (in `Shared`).
/// A preview subscriber's flag: its forwarder took the last line rendered for it. Until
/// then no frame is grabbed or rendered for it; setting it wakes the worker's idle grabs.
#[derive(Clone)]
pub struct Taken {
    flag: Arc<AtomicBool>,
    inner: Arc<Inner>,
}

impl Taken {
    pub fn set(&self) {
        self.flag.store(true, Ordering::SeqCst);
        self.inner.watchers_changed.notify_one();
    }
}

pub struct LiveView {
    inner: Arc<Inner>,
    analyser: Mutex<Option<std::thread::JoinHandle<()>>>,
}

impl LiveView {
    pub fn new(info: RigInfo) -> LiveView {
        let inner = Arc::new(Inner {
            info,
            state: Mutex::new(State::default()),
            offered: Condvar::new(),
            watchers_changed: Notify::new(),
            watchers: AtomicUsize::new(0),
        });
        LiveView {
            analyser: Mutex::new(Some(analyser::spawn(inner.clone()))),
            inner,
        }
    }

    pub fn info(&self) -> &RigInfo {
        &self.inner.info
    }

    /// Whether anyone watches (a subscriber or a waiting snap).
    pub fn watched(&self) -> bool {
        self.inner.watchers.load(Ordering::SeqCst) > 0
    }

    /// Offer a frame: it replaces any the analyser has not taken yet. Never blocks for long
    /// (a lock held only to swap the slot).
    pub fn offer(&self, frame: LiveFrame) {
        let mut st = self.inner.state();
        st.frame = Some(frame);
        drop(st);
        self.inner.offered.notify_one();
    }

    /// Register a preview subscriber; its id (to remove it), its latest-line slot, and the
    /// flag its forwarder sets once it took the slot's line: until then no frame is grabbed
    /// or rendered for it (a client that reads nothing costs nothing).
    pub fn subscribe(
        &self,
        shown: Shown,
        max_fps: f64,
    ) -> (u64, watch::Receiver<Option<Line>>, Taken) {
        let taken = Taken {
            flag: Arc::new(AtomicBool::new(true)),
            inner: self.inner.clone(),
        };
        let (tx, rx) = watch::channel(None);
        // `check_fps` bounds the rate; a rate outside it still gets a finite interval.
        let interval = Duration::try_from_secs_f64(1.0 / max_fps)
            .unwrap_or(Duration::from_secs_f64(1.0 / wire::MIN_FPS));
        let mut st = self.inner.state();
        st.next_id += 1;
        let id = st.next_id;
        st.subs.push(Sub {
            id,
            shown,
            interval,
            last: None,
            tx,
            taken: taken.flag.clone(),
        });
        self.inner.recount(&st);
        (id, rx, taken)
    }

    pub fn unsubscribe(&self, id: u64) {
        let mut st = self.inner.state();
        st.subs.retain(|s| s.id != id);
        self.inner.recount(&st);
    }

    /// Wait for a snap: the first frame exposed at or after `after`.
    pub fn snap(
        &self,
        after: SystemTime,
        shown: Shown,
    ) -> oneshot::Receiver<Result<SnapReply, ProtoError>> {
        let (reply, rx) = oneshot::channel();
        let mut st = self.inner.state();
        st.snaps.push(SnapWaiter {
            after,
            shown,
            reply,
        });
        self.inner.recount(&st);
        rx
    }

    /// Stop: the analyser ends, waiting snaps are refused.
    pub fn close(&self) {
        let mut st = self.inner.state();
        st.closed = true;
        for s in st.snaps.drain(..) {
            let _ = s.reply.send(Err(shutting_down()));
        }
        drop(st);
        self.inner.offered.notify_one();
        let handle = self
            .analyser
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take();
        if let Some(h) = handle {
            let _ = h.join();
        }
    }
}

impl Drop for LiveView {
    fn drop(&mut self) {
        self.close();
    }
}

fn shutting_down() -> ProtoError {
    ProtoError::new(
        crate::daemon::protocol::ErrorCode::Unavailable,
        "the daemon is shutting down",
    )
}

fn unix_s(t: SystemTime) -> f64 {
    crate::timestamps::unix_s(t)
}
