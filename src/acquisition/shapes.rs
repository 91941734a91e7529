//! A job's `plan` (a line, a grid over the axis and the piezo, a list of positions) checked
//! against the rig and expanded into frames, one run per repeat. Every refusal names the
//! field it comes from (`plan.grid.inner.steps`, `plan.list[3].piezo_um`).
//!
//! A run's frames are on its stage (`RunPlan::positions_um`: the axis, unless the plan moves
//! the piezo alone) and, in a plan that moves both, on the piezo (`RunPlan::piezo_um`).

use crate::acquisition::job::{CaseScan, Grid, JobSpec, Line, ListPoint, ScanPlan, StageKind};
use crate::acquisition::plan::{run_options, um, PlanError, RunPlan, MAX_FRAMES};
use crate::rig::RigInfo;

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
            return Err(rejected(format!("`{field}.start_um` must be a finite number")))
        }
        Some(s) => s,
        None => match l.stage {
            StageKind::Axis => rig.default_start_um,
            StageKind::Piezo => limits[0],
        },
    };
    Ok((0..l.steps)
        .map(|i| start + i as f64 * l.step_um)
        .collect())
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
                _ => r.piezo_um.as_ref().expect("a run that moves the piezo has its positions"),
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
