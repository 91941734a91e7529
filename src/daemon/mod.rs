//! The daemon: owns the rig, serves clients over a Unix socket, runs one job at a time and
//! records each as a session. Laid out after tokio's mini-redis:
//! - `protocol`: the JSON-lines wire format (docs/protocol.md);
//! - `server`: the socket and the accept loop; `connection`: one client;
//! - `commands`: what each request does; `jobs`: the job table and queue;
//! - `worker`: takes jobs off the queue onto a blocking thread; `runner`: runs one job;
//! - `plan`: checks a job before anything moves; `session`: the crash-safe session folder;
//! - `replay`: a session as a rig; `simrig`: the simulated rig; `study`: Tables 1-3;
//! - `events`: the event bus; `rig`: the hardware a job uses.

pub mod commands;
pub mod connection;
pub mod events;
pub mod hwrig;
pub mod interferometer;
pub mod jobs;
pub mod plan;
pub mod protocol;
pub mod replay;
pub mod rig;
pub mod runner;
pub mod server;
pub mod session;
pub mod simrig;
pub mod simxl80;
pub mod study;
pub mod worker;

use events::EventBus;
use jobs::Jobs;
use rig::RigInfo;
use std::path::PathBuf;
use std::sync::{Mutex, MutexGuard};
use tokio::sync::Notify;

/// The `[daemon]` part of the configuration.
#[derive(Debug, Clone, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct DaemonSettings {
    /// Path of the Unix socket.
    pub socket: PathBuf,
    /// Group that may use the socket (mode 0660); none: the daemon's own group.
    #[serde(default)]
    pub group: Option<String>,
    /// Where sessions are written.
    pub data_root: PathBuf,
}

/// State shared by the server, the connections and the worker.
pub struct Shared {
    pub settings: DaemonSettings,
    pub rig_info: RigInfo,
    jobs: Mutex<Jobs>,
    pub events: EventBus,
    /// Wakes the worker when a job is queued or the daemon stops.
    pub wake: Notify,
    pub shutting_down: std::sync::atomic::AtomicBool,
}

impl Shared {
    pub fn new(settings: DaemonSettings, rig_info: RigInfo, last_job_id: u64) -> Shared {
        Shared {
            settings,
            rig_info,
            jobs: Mutex::new(Jobs::starting_after(last_job_id)),
            events: EventBus::default(),
            wake: Notify::new(),
            shutting_down: std::sync::atomic::AtomicBool::new(false),
        }
    }

    pub fn jobs(&self) -> MutexGuard<'_, Jobs> {
        // The table stays consistent across a panic (plain data updated in place).
        self.jobs.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The socket path when neither the command line nor a config names one:
/// `$RIGD_SOCKET`, else `$XDG_RUNTIME_DIR/rigd.sock`, else `/tmp/rigd-<uid>.sock`.
pub fn default_socket() -> PathBuf {
    if let Some(p) = std::env::var_os("RIGD_SOCKET") {
        return PathBuf::from(p);
    }
    if let Some(d) = std::env::var_os("XDG_RUNTIME_DIR") {
        return PathBuf::from(d).join("rigd.sock");
    }
    let uid = nix::unistd::getuid();
    PathBuf::from(format!("/tmp/rigd-{uid}.sock"))
}

/// Read the `[daemon]` table of a rig configuration file.
pub fn settings_from_config(text: &str, origin: &str) -> Result<DaemonSettings, String> {
    let v: toml::Table = toml::from_str(text).map_err(|e| format!("{origin}: {e}"))?;
    let d = v
        .get("daemon")
        .cloned()
        .ok_or_else(|| format!("{origin}: no [daemon] table"))?;
    d.try_into()
        .map_err(|e: toml::de::Error| format!("{origin}: [daemon]: {e}"))
}
