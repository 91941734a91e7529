//! The job as the rig runs it: which stage, which scans, how to process them.
//!
//! These are the domain's types. They are serde documents because sessions record them (the
//! manifest's `job`) and the protocol carries them (`submit`'s `job`), but they hold no wire
//! concern: the protocol (`daemon::protocol`) wraps them in its own requests and events.

use crate::pipeline::{Combine, Estimator, Registration};
use serde::{Deserialize, Serialize};

/// Which stage a job steps.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
    Default,
    clap::ValueEnum,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum StageKind {
    /// The numerically controlled axis (GRBL).
    #[default]
    Axis,
    /// The piezo flexure (PI GCS).
    Piezo,
}

impl std::fmt::Display for StageKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            StageKind::Axis => "axis",
            StageKind::Piezo => "piezo",
        })
    }
}

/// The paper's three cases (Alzarok et al., section 4).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum PaperCase {
    /// One raw frame.
    Case1,
    /// Ten frames 100 µm apart, reconstructed at k = 5.
    Case2,
    /// Twenty frames 50 µm apart, reconstructed at k = 10.
    Case3,
}

impl PaperCase {
    pub const ALL: [PaperCase; 3] = [PaperCase::Case1, PaperCase::Case2, PaperCase::Case3];

    pub fn scan(self) -> CaseScan {
        let (name, frames, step_um, k) = match self {
            PaperCase::Case1 => ("case1", 1, 0.0, 1),
            PaperCase::Case2 => ("case2", 10, 100.0, 5),
            PaperCase::Case3 => ("case3", 20, 50.0, 10),
        };
        CaseScan {
            name: name.to_string(),
            frames,
            step_um,
            k,
        }
    }
}

/// Where a job's per-frame displacements come from.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Serialize,
    Deserialize,
    Default,
    clap::ValueEnum,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum JobRegistration {
    /// Measured in the image (the paper's).
    #[default]
    Image,
    /// From the commanded positions (the config's and `rigctl process`'s "positions").
    #[serde(alias = "positions")]
    #[value(alias = "positions")]
    Commanded,
    /// From the interferometer's reading at each frame (the job fails at a frame without one).
    Interferometer,
}

impl From<Registration> for JobRegistration {
    fn from(r: Registration) -> JobRegistration {
        match r {
            Registration::Image => JobRegistration::Image,
            Registration::Positions => JobRegistration::Commanded,
        }
    }
}

impl JobRegistration {
    /// What the pipeline registers by: the image, or the positions it is handed (commanded
    /// or interferometer readings, chosen by the engine per frame).
    pub fn pipeline(self) -> Registration {
        match self {
            JobRegistration::Image => Registration::Image,
            JobRegistration::Commanded | JobRegistration::Interferometer => Registration::Positions,
        }
    }
}

/// One scan of a job: `frames` frames `step_um` apart, reconstructed at `k`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaseScan {
    pub name: String,
    pub frames: u32,
    pub step_um: f64,
    pub k: u32,
}

fn default_settle_ms() -> u64 {
    20
}
fn default_one() -> u32 {
    1
}
fn default_true() -> bool {
    true
}

/// One stage stepped: `steps` frames `step_um` apart from `start_um` (default: the axis's
/// scan start, the piezo's lower soft limit).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Line {
    #[serde(default)]
    pub stage: StageKind,
    pub step_um: f64,
    pub steps: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_um: Option<f64>,
}

/// A 2-D grid over the axis and the piezo: for each of the outer line's positions, every
/// position of the inner line (with `snake`, every other row backwards, so no row ends
/// with a return to its start).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Grid {
    pub inner: Line,
    pub outer: Line,
    #[serde(default)]
    pub snake: bool,
}

/// One frame of a `list` plan. A stage left out stays where the previous point put it
/// (before the first point that gives it: at its first given position).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ListPoint {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_um: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub piezo_um: Option<f64>,
}

/// Where a job's frames are taken (docs/protocol.md, "Plans"): a line on one stage, a
/// grid over the axis and the piezo, or a list of positions. Without one, a job's
/// `step_um`/`steps` (or `study`) are a line on its `stage`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum ScanPlan {
    Line(Line),
    Grid(Grid),
    List(Vec<ListPoint>),
}

impl ScanPlan {
    /// The name of the plan's runs (`line`, `grid`, `list`).
    pub fn name(&self) -> &'static str {
        match self {
            ScanPlan::Line(_) => "line",
            ScanPlan::Grid(_) => "grid",
            ScanPlan::List(_) => "list",
        }
    }
}

/// A capture job. Either a single scan (`step_um`, `steps`, `k`), a study of the paper's
/// cases (`study`) or a `plan` (line, grid, list), repeated `repeats` times.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    #[serde(default)]
    pub stage: StageKind,
    /// Distance between frames of a scan.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_um: Option<f64>,
    /// Number of frames of a scan.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steps: Option<u32>,
    /// Upsampling factor of a scan's reconstruction.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub k: Option<u32>,
    /// Run these of the paper's cases instead of a single scan.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub study: Option<Vec<PaperCase>>,
    /// Wait after each move before grabbing.
    #[serde(default = "default_settle_ms")]
    pub settle_ms: u64,
    /// Processing left out (None) takes the rig's `[pipeline]` default, else the protocol's;
    /// the daemon records the values it resolved (docs/protocol.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimator: Option<Estimator>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub combine: Option<Combine>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub registration: Option<JobRegistration>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub whole_frame: Option<bool>,
    #[serde(default = "default_one")]
    pub repeats: u32,
    /// Where the frames are taken, instead of `step_um`/`steps`/`study`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plan: Option<ScanPlan>,
    /// Each repeat starts this long after the previous one started (a stability run); a
    /// repeat that takes longer is followed at once.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub interval_s: Option<f64>,
    /// Absolute start of the first scan; default: where the stage is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_um: Option<f64>,
    /// Each repeat starts this much further than the previous one (sub-pixel start phases).
    #[serde(default)]
    pub repeat_shift_um: f64,
    /// Process the frames while capturing (false: capture and record only).
    #[serde(default = "default_true")]
    pub process: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub label: Option<String>,
    /// A calibration job (docs/calibration.md): this scan on the axis, fitted into a record
    /// in the data root that later jobs apply. It sets the scan and processing itself.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibrate: Option<Box<crate::acquisition::calibration_job::CalibrationScan>>,
}

impl Default for JobSpec {
    fn default() -> Self {
        JobSpec {
            stage: StageKind::Axis,
            step_um: None,
            steps: None,
            k: None,
            study: None,
            settle_ms: default_settle_ms(),
            estimator: None,
            combine: None,
            registration: None,
            whole_frame: None,
            repeats: 1,
            plan: None,
            interval_s: None,
            start_um: None,
            repeat_shift_um: 0.0,
            process: true,
            label: None,
            calibrate: None,
        }
    }
}

/// Processing settings, each optional: a replay's overrides of the recorded ones, and a
/// rig's `[pipeline]` defaults for what a job leaves out.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Processing {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub k: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimator: Option<Estimator>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub combine: Option<Combine>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub registration: Option<JobRegistration>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub whole_frame: Option<bool>,
}

impl JobSpec {
    /// The stage the job's positions are on (a grid's, or a list's with axis positions:
    /// the axis), and whether it moves the piezo besides (a grid, a list of both).
    pub fn stages(&self) -> (StageKind, bool) {
        match &self.plan {
            None => (self.stage, false),
            Some(ScanPlan::Line(l)) => (l.stage, false),
            Some(ScanPlan::Grid(_)) => (StageKind::Axis, true),
            Some(ScanPlan::List(points)) => {
                let piezo = points.iter().any(|p| p.piezo_um.is_some());
                match points.iter().any(|p| p.axis_um.is_some()) {
                    true => (StageKind::Axis, piezo),
                    false => (StageKind::Piezo, false),
                }
            }
        }
    }

    /// This job with every processing field it leaves out filled in: from the rig's
    /// `[pipeline]` defaults `d` where the config sets them, else the protocol's own. A
    /// study's cases keep their own k, and without a configured `combine` each case combines
    /// by its k (interp above 1, else mean), so a study's `k` and possibly `combine` stay
    /// unset.
    pub fn with_defaults(&self, d: &Processing) -> JobSpec {
        let mut s = self.clone();
        crate::acquisition::calibration_job::resolve(&mut s);
        s.estimator = s.estimator.or(d.estimator).or(Some(Estimator::default()));
        s.combine = s.combine.or(d.combine);
        if s.study.is_none() {
            let k = *s.k.get_or_insert(d.k.unwrap_or(1));
            s.combine.get_or_insert(combine_for(k));
        }
        s.registration = s
            .registration
            .or(d.registration)
            .or(Some(JobRegistration::Image));
        s.whole_frame = s.whole_frame.or(d.whole_frame).or(Some(false));
        s
    }

    /// This job with a replay's overrides applied (fields the overrides leave out keep the
    /// recorded values). `k` is a per-run setting: see `Plan::with_k`.
    pub fn overridden(&self, ov: &Processing) -> JobSpec {
        let mut s = self.clone();
        s.estimator = ov.estimator.or(s.estimator);
        s.combine = ov.combine.or(s.combine);
        s.registration = ov.registration.or(s.registration);
        s.whole_frame = ov.whole_frame.or(s.whole_frame);
        s
    }
}

/// The combine a scan of upsampling `k` uses when nothing chooses one.
pub fn combine_for(k: u32) -> Combine {
    if k > 1 {
        Combine::Interp
    } else {
        Combine::Mean
    }
}
