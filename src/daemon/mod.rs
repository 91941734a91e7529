//! The daemon: owns the rig, serves clients over a Unix socket, runs one job at a time and
//! records each as a session. Laid out after tokio's mini-redis:
//! - `ownership`: the socket, data root and device locks claimed before anything else;
//!   `notify`: systemd readiness;
//! - `protocol`: the JSON-lines wire format (docs/protocol.md);
//! - `server`: the socket and the accept loop; `connection`: one client;
//! - `commands`: what each request does; `jobs`: the job table and queue;
//! - `worker`: takes jobs off the queue onto a blocking thread and runs each through the
//!   step engine (`acquisition`) with the recorder and processor as its sinks;
//! - `recorder`: the session as a step sink; `session`: the crash-safe session folder;
//!   `frame_png`: a frame's PNG with its scale, position and time in it;
//! - `replay`: a session's job run again (on `rig::replay`); `events`: the event bus;
//! - `rig_state`: the rig's `ready`/`busy`/`fault` state; `rig_commands`: `unlock`, `home`,
//!   `reconnect`, run by the worker beside the job queue; `manual`: `position`, `move`,
//!   `stop` outside jobs; `pausing`: `pause`/`resume` and the `paused`/`resumed` events;
//! - `calibration`: the calibration a job applies (the data root's current one, checked)
//!   and the record a calibration job makes;
//! - `live_view`: `snap` and `preview` (the job's frames, or frames the worker grabs
//!   between jobs, with the targets found in them).
//!
//! The rig a job runs on is `crate::rig`; the daemon's settings are `config::DaemonSettings`.

mod accept;
mod calibration;
mod commands;
mod connection;
mod events;
mod job_ids;
mod jobs;
mod listing;
pub mod live_view;
mod manual;
pub mod notify;
mod outbox;
mod pausing;
pub mod protocol;
mod recorder;
mod replay;
mod resuming;
mod rig_commands;
mod rig_state;
pub mod schema;
pub mod server;
mod strict_json;
mod timing;
mod worker;

use crate::config::DaemonSettings;
use crate::rig::RigInfo;
use events::EventBus;
use jobs::Jobs;
use rig_state::{RigCondition, RigState};
use std::sync::{Mutex, MutexGuard};
use tokio::sync::Notify;

/// State shared by the server, the connections and the worker.
pub struct Shared {
    pub settings: DaemonSettings,
    pub rig_info: RigInfo,
    jobs: Mutex<Jobs>,
    pub events: EventBus,
    /// Wakes the worker when a job is queued or the daemon stops.
    pub wake: Notify,
    pub shutting_down: std::sync::atomic::AtomicBool,
    /// The rig's fault and the rig request running.
    rig: Mutex<RigCondition>,
    /// Rig requests to the worker; the worker takes the receiver when it starts.
    pub rig_requests: rig_commands::Sender,
    rig_requests_rx: Mutex<Option<rig_commands::Receiver>>,
    /// `snap` and `preview`: the frames' slot, the watchers, the analyser thread.
    pub live: live_view::LiveView,
    /// Manual moves' stop flag and last poll.
    pub manual: manual::ManualState,
}

impl Shared {
    pub fn new(settings: DaemonSettings, rig_info: RigInfo, ids: job_ids::JobIds) -> Shared {
        let (tx, rx) = tokio::sync::mpsc::channel(rig_commands::QUEUE);
        Shared {
            rig: Mutex::new(RigCondition {
                starting: true,
                ..RigCondition::default()
            }),
            rig_requests: tx,
            rig_requests_rx: Mutex::new(Some(rx)),
            manual: manual::ManualState::default(),
            settings,
            live: live_view::LiveView::new(rig_info.clone()),
            rig_info,
            jobs: Mutex::new(Jobs::new(ids)),
            events: EventBus::default(),
            wake: Notify::new(),
            shutting_down: std::sync::atomic::AtomicBool::new(false),
        }
    }

    pub fn jobs(&self) -> MutexGuard<'_, Jobs> {
        // The table stays consistent across a panic (plain data updated in place).
        self.jobs.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The rig's condition (never held together with the job table).
    pub fn rig(&self) -> MutexGuard<'_, RigCondition> {
        self.rig.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The rig state clients see.
    pub fn rig_state(&self) -> RigState {
        let running = self.jobs().running();
        self.rig_state_with(running)
    }

    /// The rig state given the running job (for a caller that holds the job table), with
    /// the rig requests waiting.
    pub fn rig_state_with(&self, running: Option<u64>) -> RigState {
        let mut state = self.rig().state(running);
        if let RigState::Busy { waiting, .. } = &mut state {
            let n = rig_commands::QUEUE - self.rig_requests.capacity();
            *waiting = (n > 0).then_some(n);
        }
        state
    }

    /// The rig requests' receiver, for the worker (once).
    pub fn take_rig_requests(&self) -> Option<rig_commands::Receiver> {
        self.rig_requests_rx
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take()
    }
}
