//! A camera on a frame clock, buffered like V4L2.
//!
//! Frame `i` is exposed from `epoch + i·period` for `exposure_ms`. A light clock thread
//! samples the line of sight (`TruePosition`) as each of `motion_samples` instants spread
//! over the exposure passes, and at the end of the exposure queues that record in a
//! small ring (`buffer_frames`); when the ring is full the oldest frame is dropped, as a
//! V4L2 driver recycles buffers nobody dequeued. Pixels are rendered only when a frame is
//! dequeued, so an idle camera costs nothing, and frame `i` depends only on the seed, `i`
//! and where the line of sight was during its exposure — not on which thread renders it
//! or when.
//!
//! A frame exposed while the axis moves averages the sub-exposure renders: it shows the
//! motion. A driver that takes the queued (stale) frame after a move instead of waiting for
//! a fresh one sees the old position, or a smear.

use crate::frames::FrameRenderer;
use crate::motion::TruePosition;
use image::RgbImage;
use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

/// One delivered frame.
#[derive(Debug, Clone)]
pub struct SimFrame {
    pub image: RgbImage,
    /// Frame-clock sequence number (from 0 at start; gaps are dropped frames).
    pub sequence: u64,
    /// Start of the exposure.
    pub exposed_at: Instant,
    /// The same instant on the system clock (what V4L2 would timestamp).
    pub timestamp: SystemTime,
    /// Mean true line of sight over the exposure, µm (for checks; a camera does not know it).
    pub mean_los_um: [f64; 2],
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ClockError {
    #[error("no frame within {timeout_ms} ms")]
    Timeout { timeout_ms: u64 },
    #[error("the camera is stopped")]
    Stopped,
}

/// A frame exposed but not yet dequeued: where the scene was, not its pixels.
#[derive(Debug, Clone)]
struct Exposure {
    sequence: u64,
    start: Instant,
    los_um: Vec<[f64; 2]>,
}

struct Queue {
    pending: VecDeque<Exposure>,
    dropped: u64,
    stopped: bool,
    /// Dequeue calls so far (1-based count of the last one).
    grabs: u64,
    /// The dequeue call from which the stream stalls (fault injection).
    stall_at: Option<u64>,
    /// The stream has stalled: exposures are not queued until a restart.
    stalled: bool,
}

struct Shared {
    renderer: FrameRenderer,
    source: Arc<dyn TruePosition>,
    period: Duration,
    exposure: Duration,
    samples: u32,
    capacity: usize,
    epoch: Instant,
    epoch_sys: SystemTime,
    queue: Mutex<Queue>,
    ready: Condvar,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn frame_start(&self, seq: u64) -> Instant {
        self.epoch + self.period.mul_f64(seq as f64)
    }

    /// Sampling instant `k` of an exposure starting at `start` (midpoints of equal
    /// sub-windows).
    fn sample_instant(&self, start: Instant, k: usize) -> Instant {
        let n = self.samples.max(1) as f64;
        start + self.exposure.mul_f64((k as f64 + 0.5) / n)
    }

    fn run_clock(&self) {
        let n = self.samples.max(1) as usize;
        let mut seq = 0u64;
        let mut los: Vec<[f64; 2]> = Vec::with_capacity(n);
        let mut q = self.lock();
        loop {
            if q.stopped {
                return;
            }
            let start = self.frame_start(seq);
            // Next event: the next sampling instant, or the end of the exposure.
            let due = if los.len() < n {
                self.sample_instant(start, los.len())
            } else {
                start + self.exposure
            };
            let now = Instant::now();
            if now < due {
                q = self
                    .ready
                    .wait_timeout(q, due - now)
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
                continue;
            }
            if los.len() < n {
                // Sampled as the instant passes (late by our wake-up latency at most), so a
                // move commanded later does not change what this frame saw.
                drop(q);
                los.push(self.source.true_position_um(due));
                q = self.lock();
                continue;
            }
            let los_um = std::mem::replace(&mut los, Vec::with_capacity(n));
            if q.stalled {
                // A stalled stream exposes nothing anyone can dequeue.
                seq += 1;
                continue;
            }
            q.pending.push_back(Exposure {
                sequence: seq,
                start,
                los_um,
            });
            while q.pending.len() > self.capacity {
                q.pending.pop_front();
                q.dropped += 1;
            }
            self.ready.notify_all();
            seq += 1;
        }
    }

    fn deliver(&self, e: Exposure) -> SimFrame {
        let image = self.renderer.render(e.sequence, &e.los_um);
        let n = e.los_um.len() as f64;
        let mean = e
            .los_um
            .iter()
            .fold([0.0, 0.0], |a, p| [a[0] + p[0], a[1] + p[1]]);
        SimFrame {
            image,
            sequence: e.sequence,
            exposed_at: e.start,
            timestamp: self.epoch_sys + (e.start - self.epoch),
            mean_los_um: [mean[0] / n, mean[1] / n],
        }
    }
}

/// The frame-clock camera. Streaming starts on `start` and stops on drop.
pub struct FrameClockCamera {
    shared: Arc<Shared>,
    clock: Mutex<Option<JoinHandle<()>>>,
}

impl FrameClockCamera {
    /// Start streaming: frame 0 is exposed now. Clock parameters come from the renderer's
    /// camera model (`frame_period_ms`, `exposure_ms`, `motion_samples`, `buffer_frames`).
    pub fn start(renderer: FrameRenderer, source: Arc<dyn TruePosition>) -> FrameClockCamera {
        let cam = renderer.camera().clone();
        let shared = Arc::new(Shared {
            period: Duration::from_secs_f64(cam.frame_period_ms / 1000.0),
            exposure: Duration::from_secs_f64(cam.exposure_ms / 1000.0),
            samples: cam.motion_samples,
            capacity: cam.buffer_frames.max(1) as usize,
            renderer,
            source,
            epoch: Instant::now(),
            epoch_sys: SystemTime::now(),
            queue: Mutex::new(Queue {
                pending: VecDeque::new(),
                dropped: 0,
                stopped: false,
                grabs: 0,
                stall_at: None,
                stalled: false,
            }),
            ready: Condvar::new(),
        });
        let s = Arc::clone(&shared);
        let clock = std::thread::Builder::new()
            .name("sim-frame-clock".into())
            .spawn(move || s.run_clock())
            .expect("spawn the frame clock thread");
        FrameClockCamera {
            shared,
            clock: Mutex::new(Some(clock)),
        }
    }

    pub fn renderer(&self) -> &FrameRenderer {
        &self.shared.renderer
    }

    pub fn size(&self) -> (u32, u32) {
        let c = self.shared.renderer.camera();
        (c.width, c.height)
    }

    /// Frames dropped so far because the ring was full.
    pub fn dropped(&self) -> u64 {
        self.shared.lock().dropped
    }

    /// Frames queued now.
    pub fn queued(&self) -> usize {
        self.shared.lock().pending.len()
    }

    /// When streaming started (frame 0's exposure start), on both clocks.
    pub fn epoch(&self) -> (Instant, SystemTime) {
        (self.shared.epoch, self.shared.epoch_sys)
    }

    /// The instant on the monotonic clock of a system-clock time (clamped to the epoch).
    pub fn instant_of(&self, t: SystemTime) -> Instant {
        match t.duration_since(self.shared.epoch_sys) {
            Ok(d) => self.shared.epoch + d,
            Err(_) => self.shared.epoch,
        }
    }

    /// Fault injection: the stream stalls from the `n`-th dequeue (`next_frame` or
    /// `fresh_frame`, 1-based, counted since streaming started) on. Queued frames are lost
    /// and no new ones arrive, so that dequeue and every later one time out, until
    /// [`restart_stream`](Self::restart_stream). `n` at or below the dequeues already made
    /// stalls the next one.
    pub fn stall_from_grab(&self, n: u64) {
        self.shared.lock().stall_at = Some(n.max(1));
    }

    /// Whether the stream is stalled now.
    pub fn is_stalled(&self) -> bool {
        self.shared.lock().stalled
    }

    /// Dequeue calls so far.
    pub fn grabs(&self) -> u64 {
        self.shared.lock().grabs
    }

    /// Restart streaming (STREAMOFF/STREAMON): queued frames are discarded and a stalled
    /// stream delivers again from the next exposure.
    pub fn restart_stream(&self) {
        let mut q = self.shared.lock();
        q.pending.clear();
        q.stalled = false;
    }

    /// The oldest queued frame, waiting up to `timeout` for one.
    pub fn next_frame(&self, timeout: Duration) -> Result<SimFrame, ClockError> {
        self.next_matching(None, timeout)
    }

    /// The first frame whose exposure started at or after `not_before`; older queued frames
    /// are dropped (the fresh-frame rule after a move).
    pub fn fresh_frame(
        &self,
        not_before: Instant,
        timeout: Duration,
    ) -> Result<SimFrame, ClockError> {
        self.next_matching(Some(not_before), timeout)
    }

    fn next_matching(
        &self,
        not_before: Option<Instant>,
        timeout: Duration,
    ) -> Result<SimFrame, ClockError> {
        let deadline = Instant::now() + timeout;
        let mut q = self.shared.lock();
        q.grabs += 1;
        if q.stall_at.is_some_and(|n| q.grabs >= n) {
            q.stall_at = None;
            q.stalled = true;
            q.pending.clear();
        }
        loop {
            if q.stopped {
                return Err(ClockError::Stopped);
            }
            while let Some(e) = q.pending.pop_front() {
                if not_before.is_some_and(|nb| e.start < nb) {
                    continue;
                }
                drop(q);
                return Ok(self.shared.deliver(e));
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(ClockError::Timeout {
                    timeout_ms: timeout.as_millis() as u64,
                });
            }
            q = self
                .shared
                .ready
                .wait_timeout(q, deadline - now)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    /// Stop streaming (also on drop). Queued frames are discarded.
    pub fn stop(&self) {
        {
            let mut q = self.shared.lock();
            q.stopped = true;
            q.pending.clear();
        }
        self.shared.ready.notify_all();
        let handle = self.clock.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(h) = handle {
            let _ = h.join();
        }
    }
}

impl Drop for FrameClockCamera {
    fn drop(&mut self) {
        self.stop();
    }
}
