//! The analyser thread: takes the latest offered frame, works out who is due for it (each
//! subscriber at most once per its interval of exposure time, each snap waiting for a frame
//! this recent), finds its targets once and renders it for each, the targets found while
//! the views are encoded. It runs at a lower priority than the job's threads, with its own
//! niced pool of two, so the processor's pool and the engine never wait for it; when it is
//! busy, frames offered meanwhile replace each other and only the latest is seen.

use super::render::{self, Shown};
use super::wire::{SnapReply, ViewFrame, ViewTarget};
use super::{unix_s, Inner, LiveFrame, SnapWaiter};
use crate::daemon::outbox::Line;
use crate::daemon::protocol::{encode, Event, EventBody, ServerLine, PROTOCOL_VERSION};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use tokio::sync::watch;

/// What one frame is rendered for.
struct Due {
    subs: Vec<(Shown, watch::Sender<Option<Line>>)>,
    snaps: Vec<SnapWaiter>,
}

/// The analyser's threads: the targets measured on one while the image is encoded on the
/// other.
const THREADS: usize = 2;

pub(super) fn spawn(inner: Arc<Inner>) -> std::thread::JoinHandle<()> {
    std::thread::Builder::new()
        .name("rigd-live-view".into())
        .spawn(move || run(&inner))
        .expect("spawning the live view's thread")
}

fn run(inner: &Inner) {
    lower_priority();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(THREADS)
        .thread_name(|_| "rigd-live-detect".into())
        .start_handler(|_| lower_priority())
        .build()
        .expect("the live view's pool");
    while let Some((frame, due)) = next(inner) {
        // Each distinct view rendered once, whoever shares it.
        let mut shown: Vec<Shown> = Vec::new();
        for s in due
            .subs
            .iter()
            .map(|(s, _)| *s)
            .chain(due.snaps.iter().map(|w| w.shown))
        {
            if !shown.contains(&s) {
                shown.push(s);
            }
        }
        let img = &frame.frame().image;
        // The targets found on one thread while the views are encoded on the other.
        let (targets, images) = pool.install(|| {
            rayon::join(
                || render::targets(img, &inner.info),
                || {
                    shown
                        .iter()
                        .map(|s| render::png_base64(img, s))
                        .collect::<Vec<_>>()
                },
            )
        });
        let view = |s: Shown| -> ViewFrame {
            let i = shown.iter().position(|x| *x == s).expect("rendered above");
            view_frame(&frame, &s, images[i].clone(), &targets)
        };
        for (s, tx) in due.subs {
            let line = encode(&ServerLine::Event(Event {
                v: PROTOCOL_VERSION,
                job_id: frame.job_id.unwrap_or(0),
                body: EventBody::Preview(Box::new(view(s))),
            }));
            tx.send_replace(Some(line.into()));
        }
        for w in due.snaps {
            let _ = w.reply.send(Ok(SnapReply {
                job_id: frame.job_id,
                frame: view(w.shown),
            }));
        }
    }
}

/// Wait for a frame someone is due for; `None` once the live view closes.
fn next(inner: &Inner) -> Option<(LiveFrame, Due)> {
    let mut st = inner.state();
    loop {
        if st.closed {
            return None;
        }
        let Some(frame) = st.frame.take() else {
            st = inner.offered.wait(st).unwrap_or_else(|e| e.into_inner());
            continue;
        };
        let t = frame.frame().timestamp;
        let mut due = Due {
            subs: Vec::new(),
            snaps: Vec::new(),
        };
        for s in st.subs.iter_mut() {
            let ready = s.taken.load(Ordering::SeqCst)
                && s.last
                    .is_none_or(|last| t.duration_since(last).is_ok_and(|d| d >= s.interval));
            if ready {
                s.last = Some(t);
                s.taken.store(false, Ordering::SeqCst);
                due.subs.push((s.shown, s.tx.clone()));
            }
        }
        let (now, later): (Vec<_>, Vec<_>) = std::mem::take(&mut st.snaps)
            .into_iter()
            .partition(|w| t >= w.after);
        st.snaps = later;
        due.snaps = now;
        if !due.snaps.is_empty() {
            inner.recount(&st);
        }
        if due.subs.is_empty() && due.snaps.is_empty() {
            continue;
        }
        return Some((frame, due));
    }
}

fn view_frame(
    frame: &LiveFrame,
    shown: &Shown,
    (png_base64, width, height): (String, u32, u32),
    targets: &[ViewTarget],
) -> ViewFrame {
    let f = frame.frame();
    ViewFrame {
        index: frame.index(),
        t_unix_s: unix_s(f.timestamp),
        sequence: f.sequence,
        stage_um: frame.stage_um,
        frame_size: [f.image.width(), f.image.height()],
        crop: shown.crop,
        scale: shown.scale,
        width,
        height,
        png_base64,
        targets: targets.to_vec(),
    }
}

/// Nice this thread (Linux: per thread) so it yields the CPU to the job's.
fn lower_priority() {
    // SAFETY: two syscalls with plain integer arguments (this thread's own id); a failure
    // only leaves the priority as it was.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, 10);
    }
}
