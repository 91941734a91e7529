//! A job checked against the rig and expanded into runs, before anything moves. Every
//! reason the job could fail on later is checked here: shape, limits, the disk, and each
//! run's complete processing options (the pipeline validates them, so a job with a `k` it
//! cannot reconstruct is refused at submit, not after the rig has moved).

use crate::acquisition::budget;
use crate::acquisition::job::{
    combine_for, CaseScan, JobRegistration, JobSpec, Processing, StageKind,
};
use crate::acquisition::rig::RigInfo;
use crate::pipeline::{ProcessOptions, ValidOptions};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Most frames one job may ask for.
pub const MAX_FRAMES: u32 = 100_000;
/// Longest `interval_s` between repeats' starts: a week.
pub const MAX_INTERVAL_S: f64 = 7.0 * 86_400.0;
/// Longest settle a step may ask for: longer is a typo, not a rig (a minute).
pub const MAX_SETTLE_MS: u64 = 60_000;

/// A job the plan refuses, with the reason naming the field.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct PlanError(pub String);

fn rejected(msg: impl Into<String>) -> PlanError {
    PlanError(msg.into())
}

/// A length for a message: plain up to a kilometre, scientific beyond (no 309-digit
/// numbers in a refusal).
pub fn um(v: f64) -> String {
    crate::text::short_um(v)
}

/// One scan of one case in one repeat.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunPlan {
    pub run: u32,
    pub case: CaseScan,
    pub repeat: u32,
    /// Commanded position of every frame on the job's stage (`JobSpec::stages`).
    pub positions_um: Vec<f64>,
    /// A plan that moves the piezo besides the axis (a grid, a list of both): the piezo's
    /// commanded position of every frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub piezo_um: Option<Vec<f64>>,
    /// The complete processing options of this run, validated by the pipeline at submit
    /// (`None`: the job does not process; absent from sessions recorded before rigd 0.2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub processing: Option<ValidOptions>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    pub runs: Vec<RunPlan>,
    /// Frames of the whole plan (those before `first_index` included).
    pub total_frames: u32,
    /// The plan index of the first frame this job takes: 0, or a resumed session's first
    /// missing frame (`daemon::resuming`); the frames before it are the original's.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub first_index: u32,
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

/// The processing options of one scan of `spec` (resolved: see `JobSpec::with_defaults`),
/// checked by the pipeline. The image moves along the job's stage's direction and, in a
/// plan that moves the piezo besides, along the piezo's too.
pub fn run_options(spec: &JobSpec, k: u32, rig: &RigInfo) -> Result<ValidOptions, PlanError> {
    let (stage, moves_piezo) = spec.stages();
    ProcessOptions {
        scale_um_per_px: rig.scale_um_per_px,
        k,
        estimator: spec.estimator.unwrap_or_default(),
        combine: spec.combine.unwrap_or(combine_for(k)),
        registration: spec.registration.unwrap_or_default().pipeline(),
        axis_dir: rig.dir(stage),
        piezo_dir: moves_piezo.then(|| rig.dir(StageKind::Piezo)),
        whole_frame: spec.whole_frame.unwrap_or(false),
        response: rig.response,
        ink_prior: rig.ink_prior,
        calibration_ink: true,
    }
    .validate()
    .map_err(|e| rejected(e.to_string()))
}

/// The scans a job asks for, checked for shape.
fn cases(spec: &JobSpec) -> Result<Vec<CaseScan>, PlanError> {
    match &spec.study {
        Some(study) => {
            if spec.step_um.is_some() || spec.steps.is_some() || spec.k.is_some() {
                return Err(rejected(
                    "give either `study` or `step_um`/`steps`/`k`, not both",
                ));
            }
            if study.is_empty() {
                return Err(rejected("`study` names no case"));
            }
            Ok(study.iter().map(|c| c.scan()).collect())
        }
        None => {
            let steps = spec
                .steps
                .ok_or_else(|| rejected("`steps` is missing (or give a `study`)"))?;
            let step_um = spec.step_um.unwrap_or(0.0);
            if steps > 1 && spec.step_um.is_none() {
                return Err(rejected("`step_um` is missing"));
            }
            Ok(vec![CaseScan {
                name: "scan".into(),
                frames: steps,
                step_um,
                k: spec.k.unwrap_or(1),
            }])
        }
    }
}

/// What a job of `frames` frames of `frame_size` may write: frames are written as PNG, and
/// an 8-bit RGB frame's raw size bounds its PNG closely enough for noisy images (they
/// barely compress); 4 KiB a frame for its steps.csv row and file-system slack, 1 MiB for
/// the manifest, result and images.
pub fn estimated_bytes(frames: u64, frame_size: (u32, u32)) -> u64 {
    let (w, h) = frame_size;
    frames.saturating_mul(w as u64 * h as u64 * 3 + 4096) + (1 << 20)
}

fn mb(bytes: u64) -> u64 {
    bytes >> 20
}

fn disk_message(
    frames: u32,
    (need, images): (u64, u64),
    committed: u64,
    root: &Path,
    free: u64,
) -> String {
    let root = root.display();
    let need = match images >= 1 << 20 {
        true => format!(
            "{} MB ({} MB of them the reconstructions' images)",
            mb(need),
            mb(images)
        ),
        false => format!("{} MB", mb(need)),
    };
    if committed == 0 {
        format!(
            "{frames} frames need about {need} but {root} has {} MB free",
            mb(free)
        )
    } else {
        format!(
            "{frames} frames need about {need}, {} MB are already committed to queued and \
             running jobs, and {root} has {} MB free",
            mb(committed),
            mb(free)
        )
    }
}

/// Check `spec` against the rig and the disk and expand it into runs. `committed_bytes`:
/// what the jobs already queued or running are still expected to write (their
/// [`estimated_bytes`] for the frames they have left), which the free space must also hold.
pub fn plan(
    spec: &JobSpec,
    rig: &RigInfo,
    data_root: &Path,
    committed_bytes: u64,
) -> Result<Plan, PlanError> {
    let plan = expand(spec, rig)?;
    check_disk(&plan, rig, data_root, committed_bytes)?;
    Ok(plan)
}

/// Every check of [`plan`] but the disk's (shape, limits, `max_step_um` between frames,
/// settle, processing options), and the runs. A resumed job is expanded with this, then
/// checked against the disk for the frames it has left.
pub fn expand(spec: &JobSpec, rig: &RigInfo) -> Result<Plan, PlanError> {
    check_job(spec, rig)?;
    if let Some(shape) = &spec.plan {
        let runs = super::shapes::runs(spec, shape, rig)?;
        let total_frames = runs.iter().map(|r| r.positions_um.len() as u32).sum();
        return Ok(Plan {
            runs,
            total_frames,
            first_index: 0,
        });
    }
    let cases = cases(spec)?;
    let bounds = rig
        .bounds(spec.stage)
        .ok_or_else(|| rejected(format!("this rig has no {} stage", spec.stage)))?;
    let limits = bounds.limits_um;
    let start = spec.start_um.unwrap_or(match spec.stage {
        StageKind::Axis => rig.default_start_um,
        StageKind::Piezo => limits[0],
    });
    let mut runs = Vec::new();
    let mut total: u64 = 0;
    for repeat in 0..spec.repeats {
        for c in &cases {
            check_case(c)?;
            total += c.frames as u64;
            if total > MAX_FRAMES as u64 {
                return Err(rejected(format!(
                    "the job asks for more than {MAX_FRAMES} frames"
                )));
            }
            let first = start + repeat as f64 * spec.repeat_shift_um;
            let positions_um: Vec<f64> = (0..c.frames)
                .map(|i| first + i as f64 * c.step_um)
                .collect();
            check_limits(&positions_um, limits, spec.stage, &c.name, repeat)?;
            let processing = match spec.process {
                true => Some(run_options(spec, c.k, rig).map_err(|e| in_case(&c.name, e))?),
                false => None,
            };
            runs.push(RunPlan {
                run: runs.len() as u32,
                case: c.clone(),
                repeat,
                positions_um,
                piezo_um: None,
                processing,
            });
        }
    }
    let plan = Plan {
        runs,
        total_frames: total as u32,
        first_index: 0,
    };
    if let Some(max) = bounds.max_step_um {
        check_steps(&plan, max, spec.stage)?;
    }
    Ok(plan)
}

fn in_case(name: &str, e: PlanError) -> PlanError {
    rejected(format!("{name}: {}", e.0))
}

/// What concerns the whole job, whatever its scans.
fn check_job(spec: &JobSpec, rig: &RigInfo) -> Result<(), PlanError> {
    if spec.repeats == 0 {
        return Err(rejected("`repeats` must be at least 1"));
    }
    if spec.settle_ms > MAX_SETTLE_MS {
        return Err(rejected(format!(
            "`settle_ms` must be at most {MAX_SETTLE_MS} ms, got {}",
            spec.settle_ms
        )));
    }
    if spec.registration == Some(JobRegistration::Interferometer) && !rig.interferometer {
        return Err(rejected(
            "`registration`: \"interferometer\" needs an interferometer, and this rig has none \
             (no [xl80] section in its configuration)",
        ));
    }
    for (name, v) in [
        ("start_um", spec.start_um.unwrap_or(0.0)),
        ("repeat_shift_um", spec.repeat_shift_um),
    ] {
        if !v.is_finite() {
            return Err(rejected(format!("`{name}` must be a finite number")));
        }
    }
    match spec.interval_s {
        Some(s) if !(s > 0.0 && s <= MAX_INTERVAL_S) => Err(rejected(format!(
            "`interval_s` must be more than 0 and at most {MAX_INTERVAL_S} s (a week), got {s}"
        ))),
        _ => Ok(()),
    }
}

fn check_case(c: &CaseScan) -> Result<(), PlanError> {
    if c.frames == 0 {
        return Err(rejected(format!("{}: `steps` must be at least 1", c.name)));
    }
    if !c.step_um.is_finite() || (c.frames > 1 && c.step_um == 0.0) {
        return Err(rejected(format!(
            "{}: `step_um` must be a non-zero finite number for {} frames, got {}",
            c.name,
            c.frames,
            um(c.step_um)
        )));
    }
    Ok(())
}

fn check_limits(
    positions_um: &[f64],
    limits: [f64; 2],
    stage: StageKind,
    case: &str,
    repeat: u32,
) -> Result<(), PlanError> {
    // Positions are monotonic within a scan: its ends bound it.
    for &p in [positions_um[0], positions_um[positions_um.len() - 1]].iter() {
        if !(p >= limits[0] && p <= limits[1]) {
            return Err(rejected(format!(
                "{case} repeat {repeat}: position {} µm leaves the {stage} soft limits [{}, {}] µm",
                um(p),
                um(limits[0]),
                um(limits[1])
            )));
        }
    }
    Ok(())
}

/// Every move between two frames (within a scan, and from one run's last frame to the next
/// run's first) within the stage's `max_step_um`. The first move, from wherever the stage
/// is, is the driver's to check.
fn check_steps(plan: &Plan, max_step_um: f64, stage: StageKind) -> Result<(), PlanError> {
    let all = plan
        .runs
        .iter()
        .flat_map(|r| r.positions_um.iter().copied());
    let mut prev: Option<f64> = None;
    for p in all {
        if let Some(q) = prev.filter(|q| (p - q).abs() > max_step_um) {
            return Err(rejected(format!(
                "the move from {} µm to {} µm is longer than the {stage}'s max_step_um ({} µm)",
                um(q),
                um(p),
                um(max_step_um)
            )));
        }
        prev = Some(p);
    }
    Ok(())
}

/// The plan's frames and reconstructions ([`budget::disk_bytes`]) next to `committed_bytes`
/// against the free space under `data_root` (a replay is checked with this too).
pub fn check_disk(
    plan: &Plan,
    rig: &RigInfo,
    data_root: &Path,
    committed_bytes: u64,
) -> Result<(), PlanError> {
    let need = budget::disk_bytes(plan, rig);
    let images = budget::reconstruction_bytes(plan, rig);
    match free_bytes(data_root) {
        Some(free) if need.saturating_add(committed_bytes) > free => Err(rejected(disk_message(
            plan.frames_to_capture(),
            (need, images),
            committed_bytes,
            data_root,
            free,
        ))),
        _ => Ok(()),
    }
}

impl Plan {
    /// The frames this job takes: those from `first_index` on.
    pub fn frames_to_capture(&self) -> u32 {
        self.total_frames.saturating_sub(self.first_index)
    }

    /// This plan for a replay of a session that holds `frames` frames from the plan's
    /// `first_index` on (a resumed session's are its own): cut to them, `k` and processing
    /// overridden, every run's options rebuilt and checked as at submit.
    pub fn for_replay(
        &self,
        frames: usize,
        spec: &JobSpec,
        ov: &Processing,
        rig: &RigInfo,
    ) -> Result<Plan, PlanError> {
        let mut plan = self.clone();
        let end = self.first_index as usize + frames;
        let mut left = end;
        plan.runs.retain(|r| {
            let keep = left > 0;
            left = left.saturating_sub(r.positions_um.len());
            keep
        });
        let mut left = end;
        for r in &mut plan.runs {
            let n = r.positions_um.len().min(left);
            r.positions_um.truncate(n);
            if let Some(p) = r.piezo_um.as_mut() {
                p.truncate(n);
            }
            r.case.frames = n as u32;
            left -= n;
            if let Some(k) = ov.k {
                r.case.k = k;
            }
            r.processing =
                Some(run_options(spec, r.case.k, rig).map_err(|e| in_case(&r.case.name, e))?);
        }
        plan.total_frames = plan.runs.iter().map(|r| r.positions_um.len() as u32).sum();
        Ok(plan)
    }
}

/// Free bytes for an unprivileged writer on the filesystem holding `path`.
pub fn free_bytes(path: &Path) -> Option<u64> {
    let st = nix::sys::statvfs::statvfs(path).ok()?;
    #[allow(clippy::unnecessary_cast)] // the field types differ between targets
    Some(st.blocks_available() as u64 * st.fragment_size() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquisition::job::PaperCase;
    use crate::pipeline::Registration;
    use crate::pipeline::{Combine, Estimator};

    fn rig() -> RigInfo {
        RigInfo {
            mode: crate::acquisition::rig::RigMode::Sim,
            axis_limits_um: [0.0, 10_000.0],
            piezo_limits_um: None,
            axis_max_step_um: None,
            piezo_max_step_um: None,
            axis_settle_ms: None,
            piezo_settle_ms: None,
            default_start_um: 1000.0,
            scale_um_per_px: 774.0,
            axis_dir: [-1.0, 0.0],
            piezo_dir: None,
            frame_size: (64, 48),
            response: Default::default(),
            ink_prior: None,
            interferometer: false,
            axis_machine: None,
            board: None,
            config: serde_json::Value::Null,
            job_defaults: Processing::default(),
            grab_timeout_ms: 5000,
        }
    }

    #[test]
    fn omitted_processing_takes_the_rigs_defaults_and_explicit_values_win() {
        let scan = JobSpec {
            steps: Some(3),
            step_um: Some(10.0),
            ..JobSpec::default()
        };
        // No configured defaults (rigd --sim): the protocol's own, k-dependent combine.
        let r = scan.with_defaults(&Processing::default());
        assert_eq!(
            (r.k, r.estimator, r.combine, r.registration, r.whole_frame),
            (
                Some(1),
                Some(Estimator::Fit),
                Some(Combine::Mean),
                Some(JobRegistration::Image),
                Some(false)
            )
        );
        let k4 = JobSpec {
            k: Some(4),
            ..scan.clone()
        }
        .with_defaults(&Processing::default());
        assert_eq!(k4.combine, Some(Combine::Interp));
        let rig = Processing {
            k: Some(6),
            estimator: Some(Estimator::Paper),
            combine: None,
            // The config names the commanded positions "positions".
            registration: Some(Registration::Positions.into()),
            whole_frame: Some(true),
        };
        let r = scan.with_defaults(&rig);
        assert_eq!(
            (r.k, r.estimator, r.combine, r.registration, r.whole_frame),
            (
                Some(6),
                Some(Estimator::Paper),
                Some(Combine::Interp),
                Some(JobRegistration::Commanded),
                Some(true)
            )
        );
        // ...and processing runs with them.
        let o = run_options(&r, 6, &super::tests::rig()).unwrap();
        assert_eq!(
            (o.k, o.estimator, o.combine, o.registration, o.whole_frame),
            (
                6,
                Estimator::Paper,
                Combine::Interp,
                Registration::Positions,
                true
            )
        );
        let explicit = JobSpec {
            k: Some(1),
            estimator: Some(Estimator::Fit),
            combine: Some(Combine::Splat),
            registration: Some(JobRegistration::Interferometer),
            whole_frame: Some(false),
            ..scan.clone()
        };
        assert_eq!(explicit.with_defaults(&rig), explicit);
        // A study's cases keep their own k (and combine by it when nothing is configured).
        let study = JobSpec {
            study: Some(PaperCase::ALL.to_vec()),
            ..JobSpec::default()
        };
        let s = study.with_defaults(&rig);
        assert_eq!(
            (s.k, s.combine, s.estimator),
            (None, None, Some(Estimator::Paper))
        );
        assert!(plan(&s, &super::tests::rig(), Path::new("/tmp"), 0).is_ok());
    }

    #[test]
    fn the_disk_check_counts_what_queued_jobs_will_write() {
        let t = Path::new("/tmp");
        let free = free_bytes(t).expect("statvfs of /tmp");
        // Frames of about a tenth of the free space each: six of them fit, but not next to
        // six more already queued.
        let rig = RigInfo {
            frame_size: (1000, (free / 30_000).max(1) as u32),
            ..rig()
        };
        let six = JobSpec {
            steps: Some(6),
            step_um: Some(10.0),
            ..JobSpec::default()
        };
        let need = estimated_bytes(6, rig.frame_size);
        assert!(plan(&six, &rig, t, 0).is_ok());
        let e = plan(&six, &rig, t, need).unwrap_err();
        let m = e.0;
        assert!(m.starts_with("6 frames need about "), "{m}");
        assert!(
            m.contains(&format!(
                ", {} MB are already committed to queued",
                need >> 20
            )),
            "{m}"
        );
        assert!(m.contains("/tmp has ") && m.ends_with(" MB free"), "{m}");
        // Nothing queued, too big alone: the single-job message.
        let e = plan(
            &JobSpec {
                steps: Some(12),
                ..six.clone()
            },
            &rig,
            t,
            0,
        )
        .unwrap_err();
        assert!(e.0.contains(" MB but /tmp has "), "{}", e.0);
        assert_eq!(estimated_bytes(2, (10, 10)), 2 * (300 + 4096) + (1 << 20));
    }

    #[test]
    fn moves_longer_than_the_stages_max_step_are_refused_and_numbers_stay_short() {
        let rig = RigInfo {
            axis_max_step_um: Some(5000.0),
            ..rig()
        };
        let t = Path::new("/tmp");
        let job = |step_um: f64| JobSpec {
            steps: Some(2),
            step_um: Some(step_um),
            ..JobSpec::default()
        };
        assert!(plan(&job(5000.0), &rig, t, 0).is_ok());
        let e = plan(&job(5000.5), &rig, t, 0).unwrap_err();
        assert_eq!(
            e.0,
            "the move from 1000 µm to 6000.5 µm is longer than the axis's max_step_um (5000 µm)"
        );
        // A repeat's return to its start counts too: 1000, 3600, 6200, then back to 1000.
        let back = JobSpec {
            steps: Some(3),
            step_um: Some(2600.0),
            repeats: 2,
            ..JobSpec::default()
        };
        let e = plan(&back, &rig, t, 0).unwrap_err();
        assert!(
            e.0.starts_with("the move from 6200 µm to 1000 µm"),
            "{}",
            e.0
        );
        let huge = plan(&job(1e300), &rig, t, 0).unwrap_err().0;
        assert!(huge.len() < 200 && huge.contains("e300"), "{huge}");
        let settle = JobSpec {
            settle_ms: MAX_SETTLE_MS + 1,
            ..job(10.0)
        };
        assert!(plan(&settle, &rig, t, 0)
            .unwrap_err()
            .0
            .contains("`settle_ms` must be at most"));
    }

    #[test]
    fn a_k_the_pipeline_refuses_is_refused_at_submit_naming_the_case() {
        let job = JobSpec {
            steps: Some(3),
            step_um: Some(10.0),
            k: Some(40),
            ..JobSpec::default()
        };
        let e = plan(&job, &rig(), Path::new("/tmp"), 0).unwrap_err();
        assert_eq!(e.0, "scan: `k` must be 1..=32, got 40");
        // Without processing there are no options to refuse.
        let raw = JobSpec {
            process: false,
            ..job
        };
        assert!(plan(&raw, &rig(), Path::new("/tmp"), 0).is_ok());
    }

    #[test]
    fn the_paper_study_expands_to_sixty_runs_of_620_frames() {
        let spec = JobSpec {
            study: Some(PaperCase::ALL.to_vec()),
            repeats: 20,
            repeat_shift_um: 38.7,
            ..JobSpec::default()
        };
        let p = plan(&spec, &rig(), Path::new("/tmp"), 0).unwrap();
        assert_eq!((p.runs.len(), p.total_frames), (60, 620));
        assert_eq!(p.runs[5].positions_um[0], 1000.0 + 38.7);
        assert_eq!(p.runs[2].positions_um[19], 1000.0 + 19.0 * 50.0);
    }

    #[test]
    fn zero_steps_limits_disk_and_missing_stages_are_rejected() {
        let base = JobSpec {
            steps: Some(3),
            step_um: Some(10.0),
            ..JobSpec::default()
        };
        let r = rig();
        let t = Path::new("/tmp");
        let zero = JobSpec {
            step_um: Some(0.0),
            ..base.clone()
        };
        assert!(plan(&zero, &r, t, 0).unwrap_err().0.contains("non-zero"));
        let far = JobSpec {
            step_um: Some(5000.0),
            ..base.clone()
        };
        assert!(plan(&far, &r, t, 0).unwrap_err().0.contains("soft limits"));
        let piezo = JobSpec {
            stage: StageKind::Piezo,
            ..base.clone()
        };
        assert!(plan(&piezo, &r, t, 0).unwrap_err().0.contains("no piezo"));
        let huge = RigInfo {
            frame_size: (100_000, 100_000),
            ..rig()
        };
        let big = JobSpec {
            steps: Some(50),
            step_um: Some(1.0),
            ..base.clone()
        };
        assert!(plan(&big, &huge, t, 0).unwrap_err().0.contains("MB free"));
        assert!(plan(&base, &r, t, 0).is_ok());
        let by_laser = JobSpec {
            registration: Some(JobRegistration::Interferometer),
            ..base.clone()
        };
        let e = plan(&by_laser, &r, t, 0).unwrap_err();
        assert!(e.0.contains("[xl80]"), "{}", e.0);
        let with_laser = RigInfo {
            interferometer: true,
            ..rig()
        };
        assert!(plan(&by_laser, &with_laser, t, 0).is_ok());
    }
}
