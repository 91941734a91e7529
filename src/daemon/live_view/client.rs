//! The connection's side of the live view: `snap` (wait for the frame, answer it), and
//! `preview` / `preview_stop` (one preview subscription per connection; a new `preview`
//! replaces it). A subscription's forwarder puts its latest line into the client's output
//! queue only once the previous one has been written to the socket: a slow client skips
//! frames, it never has more than one waiting, and the queue's byte bound holds.

use super::render::{check_fps, Shown};
use super::wire::{PreviewReply, PreviewStopReply, ViewOptions};
use crate::daemon::outbox::{Line, Outbox};
use crate::daemon::protocol::{ErrorCode, ProtoError, ReplyBody, Request};
use crate::daemon::Shared;
use std::sync::Arc;
use std::time::{Duration, SystemTime};
use tokio::sync::watch;

/// A snap waits at most this long past the rig's grab deadline (a job between frames, a
/// rig request under way).
const SNAP_SLACK: Duration = Duration::from_secs(30);

/// A connection's preview: unregistered and its forwarder stopped when dropped.
pub struct Subscription {
    shared: Arc<Shared>,
    id: u64,
    forwarder: tokio::task::JoinHandle<()>,
}

impl Drop for Subscription {
    fn drop(&mut self) {
        self.forwarder.abort();
        self.shared.live.unsubscribe(self.id);
    }
}

/// Whether the connection hands `req` to [`handle`].
pub fn handles(req: &Request) -> bool {
    matches!(
        req,
        Request::Snap { .. } | Request::Preview { .. } | Request::PreviewStop {}
    )
}

/// `snap`, `preview`, `preview_stop`.
pub async fn handle(
    shared: &Arc<Shared>,
    req: Request,
    outbox: &Arc<Outbox>,
    sub: &mut Option<Subscription>,
) -> Result<ReplyBody, ProtoError> {
    match req {
        Request::Snap { scale, crop } => snap(shared, ViewOptions { scale, crop }).await,
        Request::Preview {
            max_fps,
            scale,
            crop,
        } => preview(shared, max_fps, ViewOptions { scale, crop }, outbox, sub),
        Request::PreviewStop {} => Ok(stop(sub)),
        _ => Err(ProtoError::new(
            ErrorCode::Internal,
            "not a live-view request",
        )),
    }
}

/// `snap`: the first frame exposed after the request arrived, with its targets.
pub async fn snap(shared: &Arc<Shared>, opts: ViewOptions) -> Result<ReplyBody, ProtoError> {
    if shared
        .shutting_down
        .load(std::sync::atomic::Ordering::SeqCst)
    {
        return Err(ProtoError::new(
            ErrorCode::Unavailable,
            "the daemon is shutting down",
        ));
    }
    let shown = Shown::check(&opts, shared.rig_info.frame_size)?;
    let rx = shared.live.snap(SystemTime::now(), shown);
    let wait = Duration::from_millis(shared.rig_info.grab_timeout_ms) + SNAP_SLACK;
    match tokio::time::timeout(wait, rx).await {
        Ok(Ok(r)) => r.map(|s| ReplyBody::Snap(Box::new(s))),
        Ok(Err(_)) => Err(ProtoError::new(
            ErrorCode::Unavailable,
            "the daemon stopped before the frame came",
        )),
        Err(_) => Err(ProtoError::new(
            ErrorCode::Hardware,
            format!("snap: no frame within {} s", wait.as_secs()),
        )),
    }
}

/// `preview`: start (or replace) this connection's subscription.
pub fn preview(
    shared: &Arc<Shared>,
    max_fps: f64,
    opts: ViewOptions,
    outbox: &Arc<Outbox>,
    sub: &mut Option<Subscription>,
) -> Result<ReplyBody, ProtoError> {
    let max_fps = check_fps(max_fps)?;
    let frame = shared.rig_info.frame_size;
    let shown = Shown::check(&opts, frame)?;
    // The old one goes first: one subscription per connection.
    *sub = None;
    let (id, rx, taken) = shared.live.subscribe(shown, max_fps);
    let stall = Duration::from_millis(shared.settings.stalled_client_ms.max(1));
    *sub = Some(Subscription {
        shared: shared.clone(),
        id,
        forwarder: tokio::spawn(forward(rx, taken, outbox.clone(), stall)),
    });
    Ok(ReplyBody::Preview(PreviewReply {
        max_fps,
        scale: shown.scale,
        crop: shown.crop,
        frame_size: [frame.0, frame.1],
    }))
}

/// `preview_stop`.
pub fn stop(sub: &mut Option<Subscription>) -> ReplyBody {
    ReplyBody::PreviewStop(PreviewStopReply {
        stopped: sub.take().is_some(),
    })
}

/// Copy the latest preview line to the client, one in flight at a time. `taken` tells the
/// live view this forwarder took the slot's line (it renders no other meanwhile). A line
/// not written within `stall` (the client reads nothing) ends the connection.
async fn forward(
    mut rx: watch::Receiver<Option<Line>>,
    taken: super::Taken,
    out: Arc<Outbox>,
    stall: Duration,
) {
    let mut in_flight: Option<Line> = None;
    loop {
        // The writer drops a line once it is on the socket: until then, wait.
        loop {
            let written = out.written();
            if in_flight.as_ref().is_none_or(|l| Arc::strong_count(l) <= 1) {
                break;
            }
            if tokio::time::timeout(stall, written).await.is_err() {
                out.give_up();
                return;
            }
        }
        in_flight = None;
        if rx.changed().await.is_err() {
            return;
        }
        let Some(line) = rx.borrow_and_update().clone() else {
            continue;
        };
        taken.set();
        // A copy of its own (the slot keeps the original): once the writer drops it, this
        // is its only holder.
        let line: Line = Arc::from(&line[..]);
        if out.offer(line.clone()) {
            in_flight = Some(line);
        }
    }
}
