//! At submit: the steps of a plan that the axis cannot make exactly. A stepper controller
//! moves in whole motor steps (GRBL: 1000/`$100` µm), so a commanded step between two of
//! them comes out as the two whole-step moves around it, in turn. The job still runs: its
//! frames record where the axis went (`axis_um`), and registration by positions uses that.

use super::job::JobSpec;
use super::plan::Plan;
use super::StageKind;
use crate::hw::devices::StageMachine;

/// One warning per distinct step between a run's frames on the axis that is not a whole
/// number of `machine`'s motor steps, naming the moves the axis will really make.
pub fn warnings(job: &JobSpec, plan: &Plan, machine: &StageMachine) -> Vec<String> {
    if job.stages().0 != StageKind::Axis {
        return Vec::new();
    }
    let mut seen: Vec<f64> = Vec::new();
    for run in &plan.runs {
        for pair in run.positions_um.windows(2) {
            let step = (pair[1] - pair[0]).abs();
            if step > 0.0 && !seen.iter().any(|s| (s - step).abs() < 1e-6) {
                seen.push(step);
            }
        }
    }
    seen.into_iter()
        .filter_map(|step| {
            let (lo, hi) = machine.uneven_step_um(step)?;
            Some(format!(
                "a {step} µm step is {:.2} motor steps of the axis ({} µm each, {} \
                 steps/mm): it moves {lo} or {hi} µm at a time; each frame records where it \
                 went (axis_um), and registration by positions uses that",
                machine.steps(step),
                machine.motor_step_um,
                1000.0 / machine.motor_step_um
            ))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquisition::plan::RunPlan;

    fn plan(positions_um: Vec<f64>) -> Plan {
        let run: RunPlan = serde_json::from_value(serde_json::json!({
            "run": 0, "case": {"name": "A", "frames": 3, "step_um": 50.0, "k": 1},
            "repeat": 0, "positions_um": positions_um,
        }))
        .unwrap();
        Plan {
            runs: vec![run],
            total_frames: 3,
            first_index: 0,
        }
    }

    #[test]
    fn a_step_between_motor_steps_is_named_once_with_the_moves_the_axis_makes() {
        let grbl = StageMachine {
            controller: "grbl".into(),
            motor_step_um: 4.0,
            max_rate_um_s: 8333.0,
            accel_um_s2: 10_000.0,
        };
        let job = JobSpec::default();
        let w = warnings(&job, &plan(vec![1000.0, 1050.0, 1100.0]), &grbl);
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].contains("a 50 µm step is 12.50 motor steps"),
            "{}",
            w[0]
        );
        assert!(w[0].contains("48 or 52 µm"), "{}", w[0]);
        assert!(warnings(&job, &plan(vec![1000.0, 1100.0, 1200.0]), &grbl).is_empty());
    }
}
