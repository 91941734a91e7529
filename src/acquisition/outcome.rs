//! How a job ended, as typed values: where the stage was left, which device or file failed.
//! `Display` gives the one-line reason clients have always read; events and manifests carry
//! the fields too (`EndDetail`), so nothing has to parse a message back.

use crate::hw::{HwError, MotionState};
use serde::{Deserialize, Serialize};
use std::fmt;

/// Where a stage was left after the job stopped it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct StoppedAt {
    pub device: String,
    /// The reported position after the stop; `None` if the stage did not report.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub position_um: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state: Option<MotionState>,
    /// Why the stop command failed, if it did.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_error: Option<String>,
    /// Why the stage did not report after the stop, if it did not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub status_error: Option<String>,
}

impl fmt::Display for StoppedAt {
    /// `"; axis stopped at 123.400 µm (idle)"`, the suffix of every stopped job's reason.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let d = &self.device;
        let here = match (self.position_um, self.state) {
            (Some(p), Some(s)) => Some(format!("{p:.3} µm ({})", state_name(s))),
            _ => None,
        };
        match (&self.stop_error, here, &self.status_error) {
            (None, Some(h), _) => write!(f, "; {d} stopped at {h}"),
            (None, None, Some(e)) => write!(f, "; {d} did not report after the stop: {e}"),
            (Some(s), Some(h), _) => write!(f, "; {d} did not stop ({s}); it reports {h}"),
            (Some(s), None, e) => write!(
                f,
                "; {d} did not stop ({s}) and did not report ({})",
                e.as_deref().unwrap_or("no status")
            ),
            (None, None, None) => Ok(()),
        }
    }
}

pub fn state_name(s: MotionState) -> &'static str {
    match s {
        MotionState::Idle => "idle",
        MotionState::Moving => "moving",
        MotionState::Holding => "holding",
        MotionState::Homing => "homing",
        MotionState::Alarm => "alarm",
    }
}

fn at(stopped: &Option<StoppedAt>) -> String {
    stopped.as_ref().map(|s| s.to_string()).unwrap_or_default()
}

/// The part of a step a stop arrived in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    Move,
    Settle,
    Grab,
}

/// Who asked a job to stop.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StopCause {
    Client,
    Shutdown,
}

/// A job stopped on request.
#[derive(Debug, Clone, PartialEq)]
pub struct Stop {
    pub cause: StopCause,
    /// The step it arrived in and that step's commanded position; `None` between steps.
    pub during: Option<(Phase, f64)>,
    pub stopped: Option<StoppedAt>,
}

impl fmt::Display for Stop {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.cause {
            StopCause::Client => f.write_str("cancelled by a client")?,
            StopCause::Shutdown => f.write_str("the daemon is shutting down")?,
        }
        match self.during {
            Some((Phase::Move, t)) => write!(f, " during the move to {t} µm")?,
            Some((Phase::Settle, t)) => write!(f, " while settling at {t} µm")?,
            Some((Phase::Grab, t)) => write!(f, " while grabbing at {t} µm (frame discarded)")?,
            None => {}
        }
        f.write_str(&at(&self.stopped))
    }
}

/// Why a job failed.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// A device failed (move, status, grab).
    #[error("{source}{}", at(stopped))]
    Hardware {
        source: HwError,
        stopped: Option<StoppedAt>,
    },
    /// A session file could not be written. `earlier`: the job's own reason, if it had
    /// already stopped for another one when the write failed.
    #[error("{}disk: {message}{}", earlier.as_ref().map(|e| format!("{e}; ")).unwrap_or_default(), at(stopped))]
    Disk {
        file: Option<String>,
        disk_full: bool,
        message: String,
        stopped: Option<StoppedAt>,
        earlier: Option<String>,
    },
    #[error("frame {index}: no interferometer reading at its time (registration: interferometer needs one){}", at(stopped))]
    NoInterferometerReading {
        index: u32,
        stopped: Option<StoppedAt>,
    },
    /// The processing thread failed (a panic, with its message).
    #[error("processing failed: {message}{}", at(stopped))]
    Processing {
        message: String,
        stopped: Option<StoppedAt>,
    },
    /// The job could not start (a replay's session unreadable, the session not created).
    #[error("{message}")]
    Setup { message: String },
    /// A fault in the daemon itself (a panic, with its message), not of the rig or the disk.
    #[error("internal error: {message}{}", at(stopped))]
    Internal {
        message: String,
        stopped: Option<StoppedAt>,
    },
}

impl JobError {
    fn stopped(&self) -> Option<&StoppedAt> {
        match self {
            JobError::Hardware { stopped, .. }
            | JobError::Disk { stopped, .. }
            | JobError::NoInterferometerReading { stopped, .. }
            | JobError::Processing { stopped, .. }
            | JobError::Internal { stopped, .. } => stopped.as_ref(),
            JobError::Setup { .. } => None,
        }
    }

    /// This disk error as the second of two reasons: the job had already stopped for
    /// `earlier` when the write failed (other errors are returned as they are).
    pub fn after(self, earlier: Option<String>) -> JobError {
        match self {
            JobError::Disk {
                file,
                disk_full,
                message,
                stopped,
                ..
            } => JobError::Disk {
                file,
                disk_full,
                message,
                stopped,
                earlier,
            },
            other => other,
        }
    }

    /// Attach where the stage was left (the engine stops it after any failure).
    pub fn with_stopped(mut self, at: Option<StoppedAt>) -> JobError {
        match &mut self {
            JobError::Hardware { stopped, .. }
            | JobError::Disk { stopped, .. }
            | JobError::NoInterferometerReading { stopped, .. }
            | JobError::Processing { stopped, .. }
            | JobError::Internal { stopped, .. } => *stopped = at,
            JobError::Setup { .. } => {}
        }
        self
    }
}

/// How a job ended.
#[derive(Debug)]
pub enum Outcome {
    Finished,
    Cancelled(Stop),
    Failed(JobError),
}

impl Outcome {
    /// The one-line reason (none for a finished job).
    pub fn reason(&self) -> Option<String> {
        match self {
            Outcome::Finished => None,
            Outcome::Cancelled(s) => Some(s.to_string()),
            Outcome::Failed(e) => Some(e.to_string()),
        }
    }

    /// The reason's fields, for events and the manifest.
    pub fn detail(&self) -> Option<EndDetail> {
        match self {
            Outcome::Finished => None,
            Outcome::Cancelled(s) => Some(EndDetail {
                kind: match s.cause {
                    StopCause::Client => EndKind::Cancelled,
                    StopCause::Shutdown => EndKind::Shutdown,
                },
                phase: s.during.map(|d| d.0),
                target_um: s.during.map(|d| d.1),
                stopped: s.stopped.clone(),
                ..EndDetail::default()
            }),
            Outcome::Failed(e) => Some(e.detail()),
        }
    }
}

impl JobError {
    fn detail(&self) -> EndDetail {
        let mut d = EndDetail {
            stopped: self.stopped().cloned(),
            ..EndDetail::default()
        };
        match self {
            JobError::Hardware { source, .. } => {
                d.kind = EndKind::Hardware;
                d.device = Some(device_of(source).to_string());
            }
            JobError::Disk {
                file, disk_full, ..
            } => {
                d.kind = EndKind::Disk;
                d.file = file.clone();
                d.disk_full = Some(*disk_full);
            }
            JobError::NoInterferometerReading { index, .. } => {
                d.kind = EndKind::Interferometer;
                d.index = Some(*index);
            }
            JobError::Processing { .. } => d.kind = EndKind::Processing,
            JobError::Setup { .. } => d.kind = EndKind::Setup,
            JobError::Internal { .. } => d.kind = EndKind::Internal,
        }
        d
    }
}

/// The device an error names.
pub fn device_of(e: &HwError) -> &str {
    match e {
        HwError::Timeout { device, .. }
        | HwError::PortGone { device, .. }
        | HwError::Alarm { device, .. }
        | HwError::Controller { device, .. }
        | HwError::Protocol { device, .. }
        | HwError::Limit { device, .. }
        | HwError::NotSettled { device, .. }
        | HwError::Other { device, .. } => device,
    }
}

/// What kind of end a job had (besides finishing).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum EndKind {
    Cancelled,
    Shutdown,
    #[default]
    Hardware,
    Disk,
    Interferometer,
    Processing,
    Setup,
    // A fault in the daemon itself (a panic): the daemon goes on.
    Internal,
}

/// A stopped or failed job's reason as fields (events' and the manifest's `detail`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default, schemars::JsonSchema)]
pub struct EndDetail {
    pub kind: EndKind,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub disk_full: Option<bool>,
    /// The frame it concerns (interferometer).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub index: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase: Option<Phase>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_um: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stopped: Option<StoppedAt>,
}
