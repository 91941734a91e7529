//! Ctrl-C while `rigctl` follows a job. The job runs on the daemon, not in rigctl, so a
//! Ctrl-C that only ended rigctl would leave the rig moving with nobody told. The first
//! says so at once; a second within [`AGAIN`] cancels the job; with none, rigctl detaches
//! after [`AGAIN`] and the job goes on.

use crate::cli::client::Client;
use crate::daemon::protocol::Request;
use nix::sys::signal::{self, SaFlags, SigAction, SigHandler, SigSet, Signal};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How long a first Ctrl-C waits for a second before rigctl detaches.
pub const AGAIN: Duration = Duration::from_secs(5);
/// The exit status of a process ended by Ctrl-C (128 + SIGINT).
pub const DETACHED_STATUS: i32 = 130;

static INTERRUPTS: AtomicU32 = AtomicU32::new(0);

extern "C" fn on_sigint(_: nix::libc::c_int) {
    // Async-signal-safe: only an atomic add. The watcher thread does the rest.
    INTERRUPTS.fetch_add(1, Ordering::SeqCst);
}

/// Ctrl-C taken over while it lives; the default comes back when it is dropped.
pub struct Watch {
    done: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// Take over Ctrl-C while job `id` (on the daemon at `socket`) is followed.
pub fn watch(socket: PathBuf, id: u64) -> Watch {
    INTERRUPTS.store(0, Ordering::SeqCst);
    let action = SigAction::new(
        SigHandler::Handler(on_sigint),
        SaFlags::SA_RESTART,
        SigSet::empty(),
    );
    // SAFETY: the handler only touches an atomic.
    if let Err(e) = unsafe { signal::sigaction(Signal::SIGINT, &action) } {
        tracing::debug!("Ctrl-C stays the default: {e}");
    }
    let done = Arc::new(AtomicBool::new(false));
    let thread = std::thread::spawn({
        let done = done.clone();
        move || watcher(&socket, id, &done)
    });
    Watch {
        done,
        thread: Some(thread),
    }
}

fn watcher(socket: &std::path::Path, id: u64, done: &AtomicBool) {
    let mut first: Option<Instant> = None;
    while !done.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_millis(50));
        for _ in 0..INTERRUPTS.swap(0, Ordering::SeqCst) {
            match first {
                Some(t) if t.elapsed() < AGAIN => {
                    cancel(socket, id);
                    first = None;
                }
                _ => {
                    eprintln!(
                        "\njob {id} keeps running on the daemon: Ctrl-C again within {} s \
                         cancels it (or `rigctl cancel {id}`; `rigctl watch {id}` follows it)",
                        AGAIN.as_secs()
                    );
                    first = Some(Instant::now());
                }
            }
        }
        if first.is_some_and(|t| t.elapsed() >= AGAIN) {
            eprintln!("detached from job {id}: it keeps running (`rigctl watch {id}`)");
            std::process::exit(DETACHED_STATUS);
        }
    }
}

/// Cancel on a connection of its own: the one following the job is blocked reading.
fn cancel(socket: &std::path::Path, id: u64) {
    let sent = Client::connect(socket).and_then(|mut c| c.request(&Request::Cancel { job_id: id }));
    match sent {
        Ok(_) => eprintln!("cancelling job {id}"),
        Err(e) => {
            let why = crate::text::error_chain(e.chain());
            eprintln!("could not cancel job {id}: {why} (try `rigctl cancel {id}`)");
            std::process::exit(DETACHED_STATUS);
        }
    }
}

impl Drop for Watch {
    fn drop(&mut self) {
        self.done.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        // SAFETY: restoring the default disposition.
        let _ = unsafe { signal::signal(Signal::SIGINT, SigHandler::SigDfl) };
    }
}
