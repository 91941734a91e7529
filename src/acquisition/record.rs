//! What one step produced: the step engine's one record per frame, handed to every sink.

use crate::hw::Frame;
use crate::hw::{LogSample, LogSource};
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// Time spent in each phase of one step, milliseconds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default, schemars::JsonSchema)]
pub struct StepTimings {
    pub move_ms: f64,
    pub settle_ms: f64,
    pub grab_ms: f64,
}

pub fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// One captured step.
#[derive(Debug, Clone)]
pub struct StepRecord {
    /// Index over the whole job (the session's `steps.csv` index).
    pub index: u32,
    pub run: u32,
    pub case: String,
    pub repeat: u32,
    pub commanded_um: f64,
    /// Where the stage reported itself settled.
    pub axis_um: f64,
    /// The interferometer's reading at the frame's exposure time (filled in behind the
    /// engine, by `acquisition::interferometer::ReadLog`).
    pub interferometer_um: Option<f64>,
    /// The position the pipeline registers this frame by when the job registers by
    /// positions: the commanded one, or the interferometer's reading.
    pub registration_um: f64,
    /// A plan that moves the piezo besides the axis: the piezo's commanded position and
    /// where it reported itself settled (the fields above are the axis's).
    pub piezo_commanded_um: Option<f64>,
    pub piezo_um: Option<f64>,
    /// Interferometer samples read since the previous step (oldest first).
    pub samples: Vec<LogSample>,
    /// The log's source facts as of this step (its clock estimate moves as it grows).
    pub log_source: Option<LogSource>,
    pub frame: Frame,
    pub timings: StepTimings,
    pub total_frames: u32,
}
