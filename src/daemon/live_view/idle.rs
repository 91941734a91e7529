//! The worker's side of the live view outside jobs: grab a fresh frame on the rig's thread
//! when a watcher is due for one (a snap now; a subscriber one interval after its last
//! frame, at the highest rate any asks), never when no one watches. Jobs and rig requests
//! go first: the worker grabs only when neither waits, one frame at a time.

use super::wire::StagePositions;
use super::{FrameImage, LiveFrame, LiveView, State};
use crate::daemon::protocol::{ErrorCode, ProtoError};
use crate::rig::{HwError, Rig};
use std::time::{Duration, SystemTime};

/// After a failed grab the next waits this long, doubling up to [`MAX_BACKOFF`].
const BACKOFF: Duration = Duration::from_millis(500);
const MAX_BACKOFF: Duration = Duration::from_secs(8);

impl LiveView {
    /// When the next idle grab is due, and the exposure time its frame must not precede;
    /// `None` when no one watches.
    fn due(&self) -> Option<(SystemTime, SystemTime)> {
        let st = self.inner.state();
        due_in(&st, SystemTime::now())
    }

    /// Whether an idle grab is due now.
    pub fn grab_due(&self) -> bool {
        self.due().is_some_and(|(at, _)| at <= SystemTime::now())
    }

    /// Wait until an idle grab is due (cancel-safe: the worker selects on it).
    pub async fn wait_due(&self) {
        loop {
            let changed = self.inner.watchers_changed.notified();
            match self.due() {
                None => changed.await,
                Some((at, _)) => {
                    let wait = at.duration_since(SystemTime::now()).unwrap_or_default();
                    if wait.is_zero() {
                        return;
                    }
                    tokio::select! {
                        _ = tokio::time::sleep(wait) => return,
                        _ = changed => {}
                    }
                }
            }
        }
    }
}

fn due_in(st: &State, now: SystemTime) -> Option<(SystemTime, SystemTime)> {
    let snap = st.snaps.iter().map(|s| s.after).min();
    // A subscriber whose last frame is still waiting for its client gets no other.
    let sub = st
        .subs
        .iter()
        .filter(|s| s.taken.load(std::sync::atomic::Ordering::SeqCst))
        .map(|s| {
            // One interval after its last frame, and after the last grab's frame.
            let last = s.last.max(st.last_grab);
            last.map_or(now, |l| l + s.interval)
        })
        .min();
    let not_before = match (snap, sub) {
        (None, None) => return None,
        (Some(a), Some(b)) => a.min(b),
        (a, b) => a.or(b)?,
    };
    let at = not_before.max(st.retry_at.unwrap_or(now));
    Some((at, not_before))
}

/// Grab one frame for the live view on the rig's blocking thread and offer it.
pub async fn grab(live: &std::sync::Arc<crate::daemon::Shared>, rig: Rig) -> Rig {
    let Some((_, not_before)) = live.live.due() else {
        return rig;
    };
    let timeout = Duration::from_millis(rig.info.grab_timeout_ms);
    let handle = tokio::task::spawn_blocking(move || {
        let mut rig = rig;
        let r =
            crate::hw::devices::panic_free("camera", || grab_now(&mut rig, not_before, timeout));
        (rig, r)
    });
    let (rig, result) = match handle.await {
        Ok(r) => r,
        Err(e) => panic!("live view grab thread panicked: {e}"),
    };
    live.live.grabbed(result);
    rig
}

/// A fresh frame (exposed at or after `not_before`), then where the stages are.
fn grab_now(
    rig: &mut Rig,
    not_before: SystemTime,
    timeout: Duration,
) -> Result<LiveFrame, HwError> {
    // Fresh: nothing queued from before now (the frame must still be due's).
    let not_before = not_before.max(SystemTime::now());
    let frame = rig.camera.grab_fresh(not_before, timeout)?;
    let stage_um = StagePositions {
        axis_um: rig.axis.position_um().ok(),
        piezo_um: rig.piezo.as_mut().and_then(|p| p.position_um().ok()),
    };
    Ok(LiveFrame {
        job_id: None,
        image: FrameImage::Own(frame),
        stage_um,
    })
}

impl LiveView {
    /// A grab for the live view ended (the idle worker's, or a paused job's): its frame
    /// offered, or the failure handed to the waiting snaps.
    pub fn grabbed(&self, result: Result<LiveFrame, HwError>) {
        match result {
            Ok(frame) => {
                let mut st = self.inner.state();
                st.last_grab = Some(frame.frame().timestamp);
                st.retry_at = None;
                st.failures = 0;
                drop(st);
                self.offer(frame);
            }
            Err(e) => self.grab_failed(&e),
        }
    }

    /// A grab failed: the waiting snaps get the error, the next grab backs off.
    fn grab_failed(&self, e: &HwError) {
        let mut st = self.inner.state();
        let backoff = (BACKOFF * 2u32.saturating_pow(st.failures.min(8))).min(MAX_BACKOFF);
        st.failures += 1;
        st.retry_at = Some(SystemTime::now() + backoff);
        if st.failures == 1 {
            tracing::warn!("live view: cannot grab a frame: {e}");
        }
        for s in st.snaps.drain(..) {
            let _ = s.reply.send(Err(ProtoError::new(
                ErrorCode::Hardware,
                format!("snap failed: {e}"),
            )));
        }
        self.inner.recount(&st);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nothing_is_due_without_watchers_and_a_subscriber_waits_its_interval() {
        let now = SystemTime::now();
        let mut st = State::default();
        assert_eq!(due_in(&st, now), None);
        let (tx, _rx) = tokio::sync::watch::channel(None);
        st.subs.push(super::super::Sub {
            id: 1,
            shown: super::super::render::Shown {
                crop: [0, 0, 1, 1],
                scale: 1.0,
            },
            interval: Duration::from_millis(100),
            last: None,
            tx,
            taken: std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true)),
        });
        assert_eq!(due_in(&st, now), Some((now, now)));
        st.last_grab = Some(now);
        let next = now + Duration::from_millis(100);
        assert_eq!(due_in(&st, now), Some((next, next)));
        st.retry_at = Some(now + Duration::from_secs(1));
        assert_eq!(due_in(&st, now).unwrap().0, now + Duration::from_secs(1));
    }
}
