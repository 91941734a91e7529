//! Acquisition: the job as the rig runs it, checked before anything moves, and the step
//! engine that runs it.
//!
//! - `job`: the domain's job (stage, scans, processing choices) and its defaults;
//! - `plan`: a job checked against the rig and the disk and expanded into runs, each with
//!   its complete, validated processing options; every reason to refuse a job lives here
//!   (`shapes`: a job's `plan`, a line, a 2-D grid or a list, checked and expanded);
//! - `engine`: move, settle, grab, one `StepRecord` per step; `interferometer`: the
//!   position log read behind it, filling in each record's reading;
//! - `sink`: the engine's consumers (`StepSink`), and `Threaded` to keep them off the
//!   motion path; `processor`: the pipeline as a sink;
//! - `pause`: a job's pause switch (a client's pause, a controller's feed hold);
//! - `outcome`: how a job ended, typed; `study`: a job's runs reduced to the paper's tables;
//! - `calibration_job`: the calibration job's scan (`job.calibrate`) and its checks;
//! - `tests` (test builds only): the engine on scripted devices (`tests::fake`), without
//!   hardware or time.

pub mod budget;
pub mod calibration_job;
pub mod engine;
pub mod interferometer;
pub mod job;
pub mod motor_steps;
pub mod outcome;
pub mod pause;
pub mod plan;
pub mod processor;
pub mod record;
pub mod rig;
pub mod shapes;
pub mod sink;
pub mod study;
#[cfg(test)]
mod tests;

pub use engine::{Devices, Engine, EngineSettings, StopFlag};
pub use job::{
    CaseScan, Grid, JobRegistration, JobSpec, Line, ListPoint, PaperCase, Processing, ScanPlan,
    StageKind,
};
pub use outcome::{EndDetail, JobError, Outcome, Stop, StopCause, StoppedAt};
pub use pause::{HoldPolicy, PauseCause, PauseEvent, PauseState};
pub use plan::{Plan, PlanError, RunPlan};
pub use record::{StepRecord, StepTimings};
pub use sink::{SinkError, StepSink, Threaded};
