//! `rigctl submit`'s plan flags: a line, a 2-D grid over the axis and the piezo, or a plan
//! file (any `plan` of docs/protocol.md as JSON), and `--interval-s` between repeats.

use crate::acquisition::{Grid, Line, ScanPlan, StageKind};

#[derive(clap::Args, Debug, Default)]
pub struct PlanArgs {
    /// A line on one stage, STAGE:STEP_UM:STEPS[:START_UM] (e.g. piezo:20:10), instead of
    /// --stage/--step-um/--steps.
    #[arg(long, value_name = "STAGE:STEP_UM:STEPS[:START_UM]", value_parser = parse_line,
          conflicts_with_all = ["grid_inner", "plan_file"])]
    pub line: Option<Line>,
    /// A 2-D grid's inner line (stepped fastest), STAGE:STEP_UM:STEPS[:START_UM], e.g.
    /// axis:50:20; needs --grid-outer on the other stage.
    #[arg(long, value_name = "STAGE:STEP_UM:STEPS[:START_UM]", value_parser = parse_line,
          requires = "grid_outer", conflicts_with = "plan_file")]
    pub grid_inner: Option<Line>,
    /// A 2-D grid's outer line, e.g. piezo:155:4.
    #[arg(long, value_name = "STAGE:STEP_UM:STEPS[:START_UM]", value_parser = parse_line,
          requires = "grid_inner")]
    pub grid_outer: Option<Line>,
    /// Step every other row of the grid backwards (no return to a row's start).
    #[arg(long, requires = "grid_inner")]
    pub snake: bool,
    /// A plan from a JSON file: {"line": {..}}, {"grid": {..}} or {"list": [..]}
    /// (docs/protocol.md, "Plans").
    #[arg(long = "plan", value_name = "FILE.json", value_parser = read_plan)]
    pub plan_file: Option<ScanPlan>,
    /// Start each repeat this many seconds after the previous one started (a stability
    /// run; a repeat that takes longer is followed at once).
    #[arg(long, value_name = "SECONDS", value_parser = crate::cli::process::finite)]
    pub interval_s: Option<f64>,
}

impl PlanArgs {
    /// The plan the flags describe, if any.
    pub fn plan(&self) -> Option<ScanPlan> {
        if let Some(p) = &self.plan_file {
            return Some(p.clone());
        }
        if let (Some(inner), Some(outer)) = (&self.grid_inner, &self.grid_outer) {
            return Some(ScanPlan::Grid(Grid {
                inner: inner.clone(),
                outer: outer.clone(),
                snake: self.snake,
            }));
        }
        self.line.clone().map(ScanPlan::Line)
    }
}

/// `STAGE:STEP_UM:STEPS[:START_UM]`.
pub fn parse_line(s: &str) -> Result<Line, String> {
    let parts: Vec<&str> = s.split(':').map(str::trim).collect();
    let (stage, step, steps, start) = match parts[..] {
        [a, b, c] => (a, b, c, None),
        [a, b, c, d] => (a, b, c, Some(d)),
        _ => return Err(format!("want STAGE:STEP_UM:STEPS[:START_UM], got `{s}`")),
    };
    let stage = match stage {
        "axis" => StageKind::Axis,
        "piezo" => StageKind::Piezo,
        _ => return Err(format!("`{stage}`: the stage is axis or piezo")),
    };
    let num = |what: &str, v: &str| {
        v.parse::<f64>()
            .map_err(|_| format!("{what} `{v}` is not a number"))
    };
    Ok(Line {
        stage,
        step_um: num("STEP_UM", step)?,
        steps: steps
            .parse()
            .map_err(|_| format!("STEPS `{steps}` is not a whole number"))?,
        start_um: start.map(|v| num("START_UM", v)).transpose()?,
    })
}

/// A plan file, read and decoded when the command line is parsed.
fn read_plan(path: &str) -> Result<ScanPlan, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{path}: {e}"))?;
    serde_json::from_str(&text).map_err(|e| format!("{path}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        plan: PlanArgs,
    }

    fn parse(args: &[&str]) -> Result<PlanArgs, String> {
        let argv = ["rigctl"].iter().chain(args).copied();
        Cli::try_parse_from(argv)
            .map(|c| c.plan)
            .map_err(|e| e.to_string())
    }

    #[test]
    fn grid_flags_and_plan_files_make_the_plan() {
        let a = parse(&[
            "--grid-inner",
            "axis:50:20",
            "--grid-outer",
            "piezo:155:4",
            "--snake",
        ])
        .unwrap();
        let Some(ScanPlan::Grid(g)) = a.plan() else {
            panic!("{:?}", a.plan())
        };
        assert!(g.snake && g.inner.steps == 20 && g.outer.stage == StageKind::Piezo);
        let e = parse(&["--grid-inner", "axis:50:20"]).unwrap_err();
        assert!(e.contains("--grid-outer"), "{e}");
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("plan.json");
        std::fs::write(&f, r#"{"list": [{"axis_um": 1000}, {"piezo_um": 3}]}"#).unwrap();
        let a = parse(&["--plan", f.to_str().unwrap(), "--interval-s", "60"]).unwrap();
        assert!(matches!(a.plan(), Some(ScanPlan::List(p)) if p.len() == 2));
        assert_eq!(a.interval_s, Some(60.0));
        std::fs::write(&f, r#"{"gird": {}}"#).unwrap();
        let e = parse(&["--plan", f.to_str().unwrap()]).unwrap_err();
        assert!(
            e.contains("plan.json") && e.contains("unknown variant `gird`"),
            "{e}"
        );
        assert!(parse(&[]).unwrap().plan().is_none());
    }

    #[test]
    fn a_line_is_stage_step_steps_and_an_optional_start() {
        let l = parse_line("piezo:155:4").unwrap();
        assert_eq!(
            (l.stage, l.step_um, l.steps, l.start_um),
            (StageKind::Piezo, 155.0, 4, None)
        );
        let l = parse_line("axis:-50:20:3000").unwrap();
        assert_eq!((l.step_um, l.start_um), (-50.0, Some(3000.0)));
        for (bad, says) in [
            ("axis:50", "want STAGE:STEP_UM:STEPS"),
            ("x:50:2", "axis or piezo"),
            ("axis:fifty:2", "STEP_UM `fifty`"),
            ("axis:50:2.5", "STEPS `2.5`"),
        ] {
            let e = parse_line(bad).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }
}
