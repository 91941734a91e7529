//! A job's `plan` (a line, a grid over the axis and the piezo, a list of positions) checked
//! against the rig and expanded into frames, one run per repeat. Every refusal names the
//! field it comes from (`plan.grid.inner.steps`, `plan.list[3].piezo_um`).
//!
//! A run's frames are on its stage (`RunPlan::positions_um`: the axis, unless the plan moves
//! the piezo alone) and, in a plan that moves both, on the piezo (`RunPlan::piezo_um`).

use crate::acquisition::job::{CaseScan, Grid, JobSpec, Line, ListPoint, ScanPlan, StageKind};
use crate::acquisition::plan::{run_options, um, PlanError, RunPlan, MAX_FRAMES};
use crate::acquisition::rig::RigInfo;

fn rejected(msg: impl Into<String>) -> PlanError {
    PlanError(msg.into())
}

/// One repeat's frames: on the job's stage, and on the piezo when it moves besides.
struct Frames {
    stage: Vec<f64>,
    piezo: Option<Vec<f64>>,
}

/// The runs of a job with a `plan`, checked for shape, soft limits and `max_step_um`
/// between every two frames (snake turns, row returns, list jumps and the return from one
/// repeat to the next included).
pub fn runs(spec: &JobSpec, plan: &ScanPlan, rig: &RigInfo) -> Result<Vec<RunPlan>, PlanError> {
    check_exclusive(spec)?;
    let (stage, moves_piezo) = spec.stages();
    let one = frames(plan, rig)?;
    let n = one.stage.len() as u64;
    if n * spec.repeats as u64 > MAX_FRAMES as u64 {
        return Err(rejected(format!(
            "the job asks for more than {MAX_FRAMES} frames ({n} a repeat, {} repeats)",
            spec.repeats
        )));
    }
    let k = spec.k.unwrap_or(1);
    let processing = match spec.process {
        true => Some(run_options(spec, k, rig)?),
        false => None,
    };
    let step_um = match plan {
        ScanPlan::Line(l) => l.step_um,
        ScanPlan::Grid(g) => g.inner.step_um,
        ScanPlan::List(_) => 0.0,
    };
    let runs: Vec<RunPlan> = (0..spec.repeats)
        .map(|repeat| RunPlan {
            run: repeat,
            case: CaseScan {
                name: plan.name().into(),
                frames: n as u32,
                step_um,
                k,
            },
            repeat,
            positions_um: one
                .stage
                .iter()
                .map(|p| p + repeat as f64 * spec.repeat_shift_um)
                .collect(),
            piezo_um: one.piezo.clone(),
            processing: processing.clone(),
        })
        .collect();
    check_runs(&runs, plan, rig, (stage, moves_piezo))?;
    Ok(runs)
}

/// A plan says where every frame is: the single-scan fields would contradict it.
fn check_exclusive(spec: &JobSpec) -> Result<(), PlanError> {
    let given = [
        ("step_um", spec.step_um.is_some()),
        ("steps", spec.steps.is_some()),
        ("study", spec.study.is_some()),
        ("start_um", spec.start_um.is_some()),
        ("stage", spec.stage != StageKind::Axis),
    ];
    match given.iter().find(|(_, g)| *g) {
        Some((name, _)) => Err(rejected(format!(
            "give either `plan` or `{name}`, not both (a plan names its stages, steps and starts)"
        ))),
        None => Ok(()),
    }
}

/// The frames of one repeat, checked for shape.
fn frames(plan: &ScanPlan, rig: &RigInfo) -> Result<Frames, PlanError> {
    match plan {
        ScanPlan::Line(l) => {
            let stage = line(l, "plan.line", rig)?;
            Ok(Frames { stage, piezo: None })
        }
        ScanPlan::Grid(g) => grid(g, rig),
        ScanPlan::List(points) => list(points),
    }
}

/// A line's positions, its fields checked (`field`: where it sits in the plan).
fn line(l: &Line, field: &str, rig: &RigInfo) -> Result<Vec<f64>, PlanError> {
    if l.steps == 0 {
        return Err(rejected(format!("`{field}.steps` must be at least 1")));
    }
    if l.steps > MAX_FRAMES {
        return Err(rejected(format!(
            "`{field}.steps` must be at most {MAX_FRAMES}, got {}",
            l.steps
        )));
    }
    if !l.step_um.is_finite() || (l.steps > 1 && l.step_um == 0.0) {
        return Err(rejected(format!(
            "`{field}.step_um` must be a non-zero finite number for {} frames, got {}",
            l.steps,
            um(l.step_um)
        )));
    }
    let limits = rig
        .limits_um(l.stage)
        .ok_or_else(|| rejected(format!("`{field}.stage`: this rig has no {}", l.stage)))?;
    let start = match l.start_um {
        Some(s) if !s.is_finite() => {
            return Err(rejected(format!(
                "`{field}.start_um` must be a finite number"
            )))
        }
        Some(s) => s,
        None => match l.stage {
            StageKind::Axis => rig.default_start_um,
            StageKind::Piezo => limits[0],
        },
    };
    Ok((0..l.steps).map(|i| start + i as f64 * l.step_um).collect())
}

fn grid(g: &Grid, rig: &RigInfo) -> Result<Frames, PlanError> {
    if g.inner.stage == g.outer.stage {
        return Err(rejected(format!(
            "`plan.grid.outer.stage` must be the other stage than `plan.grid.inner.stage` \
             (one of them the axis, the other the piezo), both are the {}",
            g.inner.stage
        )));
    }
    let inner = line(&g.inner, "plan.grid.inner", rig)?;
    let outer = line(&g.outer, "plan.grid.outer", rig)?;
    if inner.len() as u64 * outer.len() as u64 > MAX_FRAMES as u64 {
        return Err(rejected(format!(
            "`plan.grid` asks for {} x {} frames, more than {MAX_FRAMES}",
            inner.len(),
            outer.len()
        )));
    }
    let mut a = Vec::with_capacity(inner.len() * outer.len());
    let mut b = Vec::with_capacity(a.capacity());
    for (row, &o) in outer.iter().enumerate() {
        let backwards = g.snake && row % 2 == 1;
        for j in 0..inner.len() {
            let j = if backwards { inner.len() - 1 - j } else { j };
            a.push(inner[j]);
            b.push(o);
        }
    }
    // The job's stage is the axis: its positions first.
    let (stage, piezo) = match g.inner.stage {
        StageKind::Axis => (a, b),
        StageKind::Piezo => (b, a),
    };
    Ok(Frames {
        stage,
        piezo: Some(piezo),
    })
}

fn list(points: &[ListPoint]) -> Result<Frames, PlanError> {
    if points.is_empty() {
        return Err(rejected("`plan.list` has no point"));
    }
    for (i, p) in points.iter().enumerate() {
        for (name, v) in [("axis_um", p.axis_um), ("piezo_um", p.piezo_um)] {
            if v.is_some_and(|v| !v.is_finite()) {
                return Err(rejected(format!(
                    "`plan.list[{i}].{name}` must be a finite number"
                )));
            }
        }
    }
    let filled = |get: fn(&ListPoint) -> Option<f64>| -> Option<Vec<f64>> {
        let mut last = points.iter().find_map(get)?;
        Some(
            points
                .iter()
                .map(|p| {
                    last = get(p).unwrap_or(last);
                    last
                })
                .collect(),
        )
    };
    match (filled(|p| p.axis_um), filled(|p| p.piezo_um)) {
        (Some(axis), piezo) => Ok(Frames { stage: axis, piezo }),
        (None, Some(piezo)) => Ok(Frames {
            stage: piezo,
            piezo: None,
        }),
        (None, None) => Err(rejected(
            "`plan.list` gives no position (each point has `axis_um`, `piezo_um` or both)",
        )),
    }
}

/// Which field of the plan put frame `i` (of a repeat) on `stage` where it is.
fn field_of(plan: &ScanPlan, stage: StageKind, i: usize) -> String {
    match plan {
        ScanPlan::Line(_) => "plan.line".into(),
        ScanPlan::Grid(g) if g.inner.stage == stage => "plan.grid.inner".into(),
        ScanPlan::Grid(_) => "plan.grid.outer".into(),
        ScanPlan::List(_) => format!(
            "plan.list[{i}].{}",
            match stage {
                StageKind::Axis => "axis_um",
                StageKind::Piezo => "piezo_um",
            }
        ),
    }
}

/// Why the move onto frame `i` (of a repeat, 0: from the previous repeat's last frame) on
/// `stage` is as long as it is.
fn move_cause(plan: &ScanPlan, stage: StageKind, i: usize) -> String {
    if i == 0 {
        return "`repeats` (the return to the first frame, shifted by `repeat_shift_um`)".into();
    }
    match plan {
        ScanPlan::Line(_) => "`plan.line.step_um`".into(),
        ScanPlan::Grid(g) if g.inner.stage == stage => match i % g.inner.steps as usize {
            0 => "`plan.grid.inner` (the return to a row's start; `snake` avoids it)".into(),
            _ => "`plan.grid.inner.step_um`".into(),
        },
        ScanPlan::Grid(_) => "`plan.grid.outer.step_um`".into(),
        ScanPlan::List(_) => format!("`plan.list[{i}]`"),
    }
}

/// Soft limits at every frame, `max_step_um` between every two, on each stage moved.
fn check_runs(
    runs: &[RunPlan],
    plan: &ScanPlan,
    rig: &RigInfo,
    (stage, moves_piezo): (StageKind, bool),
) -> Result<(), PlanError> {
    let mut stages = vec![(stage, 0)];
    if moves_piezo {
        stages.push((StageKind::Piezo, 1));
    }
    for (s, which) in stages {
        let b = rig
            .bounds(s)
            .ok_or_else(|| rejected(format!("`{}`: this rig has no {s}", field_of(plan, s, 0))))?;
        let [lo, hi] = b.limits_um;
        let mut prev: Option<f64> = None;
        for r in runs {
            let positions = match which {
                0 => &r.positions_um,
                _ => r
                    .piezo_um
                    .as_ref()
                    .expect("a run that moves the piezo has its positions"),
            };
            for (i, &p) in positions.iter().enumerate() {
                let repeat = match r.repeat {
                    0 => String::new(),
                    n => format!(" (repeat {n})"),
                };
                if !(p >= lo && p <= hi) {
                    return Err(rejected(format!(
                        "`{}`{repeat}: position {} µm leaves the {s} soft limits [{}, {}] µm",
                        field_of(plan, s, i),
                        um(p),
                        um(lo),
                        um(hi)
                    )));
                }
                if let (Some(q), Some(max)) = (prev, b.max_step_um) {
                    if (p - q).abs() > max {
                        return Err(rejected(format!(
                            "{}{repeat}: the {s}'s move from {} µm to {} µm is longer than its \
                             max_step_um ({} µm)",
                            move_cause(plan, s, i),
                            um(q),
                            um(p),
                            um(max)
                        )));
                    }
                }
                prev = Some(p);
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquisition::plan::plan;
    use crate::acquisition::Processing;
    use std::path::Path;

    fn rig() -> RigInfo {
        RigInfo {
            mode: crate::acquisition::rig::RigMode::Sim,
            axis_limits_um: [0.0, 10_000.0],
            piezo_limits_um: Some([0.0, 1_400.0]),
            axis_max_step_um: Some(1_000.0),
            piezo_max_step_um: Some(500.0),
            axis_settle_ms: None,
            piezo_settle_ms: None,
            default_start_um: 1000.0,
            scale_um_per_px: 774.0,
            axis_dir: [-1.0, 0.0],
            piezo_dir: Some([0.0, -1.0]),
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

    fn job(plan_json: &str) -> JobSpec {
        let p: ScanPlan = serde_json::from_str(plan_json).unwrap();
        JobSpec {
            plan: Some(p),
            ..JobSpec::default()
        }
    }

    fn refusal(spec: &JobSpec) -> String {
        plan(spec, &rig(), Path::new("/tmp"), 0).unwrap_err().0
    }

    const GRID: &str = r#"{"grid": {"inner": {"stage": "axis", "step_um": 50, "steps": 3},
        "outer": {"stage": "piezo", "step_um": 155, "steps": 2, "start_um": 100}}}"#;

    #[test]
    fn a_grid_steps_the_inner_line_fastest_and_a_snake_turns_back() {
        let p = plan(&job(GRID), &rig(), Path::new("/tmp"), 0).unwrap();
        assert_eq!((p.runs.len(), p.total_frames), (1, 6));
        let r = &p.runs[0];
        assert_eq!(
            r.positions_um,
            [1000.0, 1050.0, 1100.0, 1000.0, 1050.0, 1100.0]
        );
        assert_eq!(
            r.piezo_um.as_deref(),
            Some(&[100.0, 100.0, 100.0, 255.0, 255.0, 255.0][..])
        );
        assert_eq!((r.case.name.as_str(), r.case.frames), ("grid", 6));
        // Processing registers by both directions.
        let o = r.processing.as_ref().unwrap();
        assert_eq!((o.axis_dir, o.piezo_dir), ([-1.0, 0.0], Some([0.0, -1.0])));
        let snake = job(&GRID.replace("}}}", "}, \"snake\": true}}"));
        let r = &plan(&snake, &rig(), Path::new("/tmp"), 0).unwrap().runs[0];
        assert_eq!(
            r.positions_um,
            [1000.0, 1050.0, 1100.0, 1100.0, 1050.0, 1000.0]
        );
        // The piezo inside: the job's stage is still the axis.
        let swapped = job(
            r#"{"grid": {"inner": {"stage": "piezo", "step_um": 10, "steps": 2},
                "outer": {"stage": "axis", "step_um": 100, "steps": 2}}}"#,
        );
        let r = &plan(&swapped, &rig(), Path::new("/tmp"), 0).unwrap().runs[0];
        assert_eq!(r.positions_um, [1000.0, 1000.0, 1100.0, 1100.0]);
        assert_eq!(r.piezo_um.as_deref(), Some(&[0.0, 10.0, 0.0, 10.0][..]));
        assert_eq!(swapped.stages(), (StageKind::Axis, true));
    }

    #[test]
    fn repeats_are_runs_shifted_on_the_axis() {
        let spec = JobSpec {
            repeats: 3,
            repeat_shift_um: 38.7,
            interval_s: Some(60.0),
            ..job(GRID)
        };
        let p = plan(&spec, &rig(), Path::new("/tmp"), 0).unwrap();
        assert_eq!((p.runs.len(), p.total_frames), (3, 18));
        assert_eq!(p.runs[2].positions_um[0], 1000.0 + 2.0 * 38.7);
        assert_eq!(p.runs[2].piezo_um, p.runs[0].piezo_um);
        assert_eq!(p.runs[2].repeat, 2);
    }

    #[test]
    fn max_step_counts_row_returns_snake_turns_and_list_jumps() {
        // Rows of 1200 µm: the return to a row's start is longer than the axis's 1000 µm.
        let long = job(&GRID.replace("\"steps\": 3", "\"steps\": 25"));
        assert_eq!(
            refusal(&long),
            "`plan.grid.inner` (the return to a row's start; `snake` avoids it): the axis's \
             move from 2200 µm to 1000 µm is longer than its max_step_um (1000 µm)"
        );
        let snake = job(&GRID
            .replace("\"steps\": 3", "\"steps\": 25")
            .replace("}}}", "}, \"snake\": true}}"));
        assert!(plan(&snake, &rig(), Path::new("/tmp"), 0).is_ok());
        let outer = job(&GRID.replace("155", "600"));
        assert!(
            refusal(&outer)
                .starts_with("`plan.grid.outer.step_um`: the piezo's move from 100 µm to 700 µm"),
            "{}",
            refusal(&outer)
        );
        let list = job(
            r#"{"list": [{"axis_um": 1000, "piezo_um": 0}, {"axis_um": 1500},
                {"piezo_um": 600}]}"#,
        );
        assert!(
            refusal(&list).starts_with("`plan.list[2]`: the piezo's move from 0 µm to 600 µm"),
            "{}",
            refusal(&list)
        );
        // A repeat's return to its start counts too.
        let back = JobSpec {
            repeats: 2,
            ..job(r#"{"line": {"stage": "axis", "step_um": 600, "steps": 3}}"#)
        };
        assert!(
            refusal(&back).starts_with("`repeats` (the return to the first frame"),
            "{}",
            refusal(&back)
        );
    }

    #[test]
    fn soft_limits_and_shapes_are_refused_naming_the_field() {
        let far = job(&GRID.replace("\"start_um\": 100", "\"start_um\": 1300"));
        assert_eq!(
            refusal(&far),
            "`plan.grid.outer`: position 1455 µm leaves the piezo soft limits [0, 1400] µm"
        );
        for (plan_json, says) in [
            (
                r#"{"grid": {"inner": {"stage": "axis", "step_um": 50, "steps": 0},
                    "outer": {"stage": "piezo", "step_um": 155, "steps": 2}}}"#,
                "`plan.grid.inner.steps` must be at least 1",
            ),
            (
                r#"{"grid": {"inner": {"stage": "axis", "step_um": 0, "steps": 3},
                    "outer": {"stage": "piezo", "step_um": 155, "steps": 2}}}"#,
                "`plan.grid.inner.step_um` must be a non-zero finite number for 3 frames, got 0",
            ),
            (
                r#"{"grid": {"inner": {"stage": "piezo", "step_um": 5, "steps": 3},
                    "outer": {"stage": "piezo", "step_um": 155, "steps": 2}}}"#,
                "`plan.grid.outer.stage` must be the other stage",
            ),
            (r#"{"list": []}"#, "`plan.list` has no point"),
            (r#"{"list": [{}, {}]}"#, "`plan.list` gives no position"),
            (
                r#"{"list": [{"axis_um": 20000}]}"#,
                "`plan.list[0].axis_um`: position 20000 µm leaves the axis soft limits",
            ),
        ] {
            let e = refusal(&job(plan_json));
            assert!(e.starts_with(says), "{plan_json}: {e}");
        }
        let both = JobSpec {
            steps: Some(3),
            ..job(GRID)
        };
        assert!(refusal(&both).starts_with("give either `plan` or `steps`, not both"));
        let never = JobSpec {
            interval_s: Some(0.0),
            ..job(GRID)
        };
        assert!(refusal(&never).starts_with("`interval_s` must be more than 0"));
        let no_piezo = RigInfo {
            piezo_limits_um: None,
            ..rig()
        };
        let e = plan(&job(GRID), &no_piezo, Path::new("/tmp"), 0)
            .unwrap_err()
            .0;
        assert_eq!(e, "`plan.grid.outer.stage`: this rig has no piezo");
    }

    #[test]
    fn a_list_carries_a_stage_left_out_forward() {
        let p = plan(
            &job(r#"{"list": [{"piezo_um": 5}, {"axis_um": 1200}, {"axis_um": 1300, "piezo_um": 7}]}"#),
            &rig(),
            Path::new("/tmp"),
            0,
        )
        .unwrap();
        let r = &p.runs[0];
        assert_eq!(r.positions_um, [1200.0, 1200.0, 1300.0]);
        assert_eq!(r.piezo_um.as_deref(), Some(&[5.0, 5.0, 7.0][..]));
        // Piezo only: the piezo is the job's stage, along its own direction.
        let only = job(r#"{"list": [{"piezo_um": 5}, {"piezo_um": 9}]}"#);
        assert_eq!(only.stages(), (StageKind::Piezo, false));
        let p = plan(&only, &rig(), Path::new("/tmp"), 0).unwrap();
        assert_eq!(
            (p.runs[0].positions_um.clone(), p.runs[0].piezo_um.clone()),
            (vec![5.0, 9.0], None)
        );
        let o = p.runs[0].processing.as_ref().unwrap();
        assert_eq!((o.axis_dir, o.piezo_dir), ([0.0, -1.0], None));
    }
}
