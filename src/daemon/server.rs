//! The socket and the accept loop, and a clean stop: on SIGTERM, SIGINT or SIGHUP the
//! server stops accepting, the running job stops at once with the axis stopped, queued
//! jobs are cancelled, the session is closed and the socket removed; the caller then drops
//! the rig and its [`Ownership`] (the locks).

use crate::config::DaemonSettings;
use crate::daemon::protocol::EventBody;
use crate::daemon::{accept, connection, notify, worker, Shared};
use crate::ownership::{Ownership, OwnershipError};
use crate::rig::Rig;
use crate::session;
use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use tokio::net::UnixListener;

#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("socket {path}: {message}")]
    Socket { path: String, message: String },
    #[error("data root: {0}")]
    Session(#[from] session::SessionError),
    #[error(transparent)]
    Ownership(#[from] OwnershipError),
    #[error("data root: {0}")]
    JobIds(#[from] crate::daemon::job_ids::JobIdError),
}

/// Bind the socket: mode 0600, or 0660 with the group from the settings. The path was
/// cleared by [`Ownership::claim`] (only a stale socket is ever removed).
pub fn bind(path: &Path, group: Option<&str>) -> Result<UnixListener, ServerError> {
    let err = |message: String| ServerError::Socket {
        path: path.display().to_string(),
        message,
    };
    let listener = UnixListener::bind(path).map_err(|e| err(e.to_string()))?;
    let mode = if group.is_some() { 0o660 } else { 0o600 };
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode))
        .map_err(|e| err(format!("chmod {mode:o}: {e}")))?;
    if let Some(g) = group {
        let gid = group_id(g).ok_or_else(|| err(format!("no group {g:?}")))?;
        std::os::unix::fs::chown(path, None, Some(gid))
            .map_err(|e| err(format!("chgrp {g}: {e}")))?;
    }
    Ok(listener)
}

fn group_id(name: &str) -> Option<u32> {
    // getgrnam_r: thread-safe; a lookup error counts as no such group.
    let group = nix::unistd::Group::from_name(name).ok()??;
    Some(group.gid.as_raw())
}

/// Run the daemon that `owner` claimed the socket and data root for, until `stop`
/// resolves (or SIGTERM/SIGINT/SIGHUP when `signals`): recover the sessions, bind, call
/// `ready` (systemd's READY=1, or a waiting thread), serve. Returns the rig, stopped, once
/// the running job has ended.
pub async fn run(
    owner: &Ownership,
    rig: Rig,
    stop: impl std::future::Future<Output = ()>,
    signals: bool,
    ready: impl FnOnce(),
) -> Result<Rig, ServerError> {
    let settings = owner.settings().clone();
    // Handlers first: a signal that comes once READY=1 is out must stop us cleanly, not kill.
    let signal = stop_signals(signals);
    let (last_id, marked) = session::recover(&settings.data_root)?;
    for name in &marked {
        tracing::warn!(session = %name, "marked incomplete: the daemon stopped while it ran");
    }
    let listener = bind(&settings.socket, settings.group.as_deref())?;
    tracing::info!(socket = %settings.socket.display(), data_root = %settings.data_root.display(), rig = %rig.info.mode, "rigd listening");
    let ids = crate::daemon::job_ids::JobIds::load(&settings.data_root, last_id)?;
    let shared = Arc::new(Shared::new(settings.clone(), rig.info.clone(), ids));
    ready();
    let worker = tokio::spawn(worker::run(shared.clone(), rig));
    tokio::pin!(stop);
    tokio::pin!(signal);
    let mut accepting = Accepting::new(&settings);
    loop {
        tokio::select! {
            acc = listener.accept() => {
                if let Some(pause) = accepting.handle(acc, &shared) {
                    tokio::select! {
                        _ = tokio::time::sleep(pause) => {},
                        _ = &mut stop => break,
                        _ = &mut signal => { tracing::info!("signal: stopping"); break; }
                    }
                }
            }
            _ = &mut stop => break,
            name = &mut signal => { tracing::info!(signal = name, "stopping"); break; }
        }
    }
    drop(listener);
    let _ = std::fs::remove_file(&settings.socket);
    if signals {
        notify::notify("STOPPING=1");
    }
    // Stop: no new jobs, queued ones cancelled, the running one stops after its step.
    shared.shutting_down.store(true, Ordering::SeqCst);
    let drained = shared.jobs().drain_queue();
    for id in drained {
        shared.events.emit(
            id,
            EventBody::cancelled_in_queue("the daemon is shutting down"),
        );
    }
    {
        let jobs = shared.jobs();
        if let Some(r) = jobs.running().and_then(|id| jobs.get(id)) {
            r.stop.shutdown();
        }
    }
    shared.wake.notify_one();
    let rig = worker.await.map_err(|e| ServerError::Socket {
        path: settings.socket.display().to_string(),
        message: format!("worker ended badly: {e}"),
    })?;
    tracing::info!("rigd stopped");
    Ok(rig)
}

/// Resolves with the signal's name on SIGTERM, SIGINT or SIGHUP (never when `!signals`).
/// The handlers are installed now, not when the future is first polled. All three stop
/// cleanly: SIGHUP (a closed terminal; there is no reload) must not kill the daemon with a
/// session left `running` and the socket behind.
fn stop_signals(signals: bool) -> impl std::future::Future<Output = &'static str> {
    use tokio::signal::unix::{signal, SignalKind};
    let handlers = signals.then(|| {
        (
            signal(SignalKind::terminate()),
            signal(SignalKind::interrupt()),
            signal(SignalKind::hangup()),
        )
    });
    async move {
        match handlers {
            Some((Ok(mut t), Ok(mut i), Ok(mut h))) => {
                tokio::select! {
                    _ = t.recv() => "SIGTERM",
                    _ = i.recv() => "SIGINT",
                    _ = h.recv() => "SIGHUP",
                }
            }
            _ => std::future::pending().await,
        }
    }
}

/// The accept loop's state: the connection limit, the back-off and the rate-limited logs.
struct Accepting {
    gate: accept::Gate,
    backoff: accept::Backoff,
    refused_log: accept::RateLimited,
    error_log: accept::RateLimited,
}

impl Accepting {
    fn new(settings: &DaemonSettings) -> Accepting {
        let (max, lowered) =
            accept::effective_limit(settings.max_connections, accept::fd_soft_limit());
        if let Some(why) = lowered {
            tracing::warn!("{why}");
        }
        let second = std::time::Duration::from_secs(1);
        Accepting {
            gate: accept::Gate::new(max),
            backoff: accept::Backoff::default(),
            refused_log: accept::RateLimited::per(second),
            error_log: accept::RateLimited::per(second),
        }
    }

    /// Serve, refuse or count one accept; the pause to take before the next, if any.
    fn handle(
        &mut self,
        acc: std::io::Result<(tokio::net::UnixStream, tokio::net::unix::SocketAddr)>,
        shared: &Arc<Shared>,
    ) -> Option<std::time::Duration> {
        let now = std::time::Instant::now();
        let stream = match acc {
            Ok((stream, _)) => stream,
            Err(e) => {
                let resource = accept::is_resource_error(&e);
                if let Some(held) = self.error_log.allow(now) {
                    tracing::warn!(error = %e, suppressed = held, "accept failed");
                }
                return resource.then(|| self.backoff.failed());
            }
        };
        self.backoff.succeeded();
        match self.gate.admit() {
            Some(permit) => {
                tokio::spawn(connection::serve(stream, shared.clone(), permit));
            }
            None => {
                // One line, without waiting on the client; then the fd is closed.
                let _ = stream.try_write(&accept::refusal(self.gate.max()));
                if let Some(held) = self.refused_log.allow(now) {
                    tracing::warn!(
                        limit = self.gate.max(),
                        suppressed = held,
                        "refused a client: too many connections"
                    );
                }
            }
        }
        None
    }
}

/// A daemon running on its own thread and runtime (the demo's, and tests').
pub struct Background {
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<Result<Rig, ServerError>>>,
    pub socket: std::path::PathBuf,
}

impl Background {
    /// Claim the socket and data root (no devices: the rig is already open), then serve;
    /// returns once this daemon's socket is bound.
    pub fn start(settings: DaemonSettings, rig: Rig) -> Result<Background, ServerError> {
        let owner = Ownership::claim(&settings, &[], "rigd (in-process)")?;
        Background::start_owned(owner, rig)
    }

    /// Serve what `owner` claimed; returns once this daemon's socket is bound (not merely
    /// when something answers at the path: that could be another daemon).
    pub fn start_owned(owner: Ownership, rig: Rig) -> Result<Background, ServerError> {
        let socket = owner.settings().socket.clone();
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let (ready_tx, ready_rx) = std::sync::mpsc::channel::<()>();
        let thread = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
                .map_err(|e| ServerError::Socket {
                    path: owner.settings().socket.display().to_string(),
                    message: format!("runtime: {e}"),
                })?;
            let stop = async move {
                let _ = stop_rx.await;
            };
            // The locks are released when `owner` drops, after the daemon has stopped.
            rt.block_on(run(&owner, rig, stop, false, move || {
                let _ = ready_tx.send(());
            }))
        });
        let mut bg = Background {
            stop: Some(stop_tx),
            thread: Some(thread),
            socket: socket.clone(),
        };
        if ready_rx
            .recv_timeout(std::time::Duration::from_secs(10))
            .is_err()
        {
            // The thread ended (its error says why) or the daemon did not come up in time.
            return Err(bg.stop().err().unwrap_or(ServerError::Socket {
                path: socket.display().to_string(),
                message: "the daemon did not start".into(),
            }));
        }
        Ok(bg)
    }

    /// Stop as on SIGTERM and wait: returns the rig.
    pub fn stop(&mut self) -> Result<Rig, ServerError> {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(r)) => r,
            Some(Err(_)) => Err(ServerError::Socket {
                path: self.socket.display().to_string(),
                message: "the daemon thread panicked".into(),
            }),
            None => Err(ServerError::Socket {
                path: self.socket.display().to_string(),
                message: "already stopped".into(),
            }),
        }
    }
}

impl Drop for Background {
    fn drop(&mut self) {
        if self.thread.is_some() {
            let _ = self.stop();
        }
    }
}
