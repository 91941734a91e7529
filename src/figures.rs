//! A processed session's figures and report: the paper's Figure 4 (each target's measured
//! offset per repeat, one chart per case) and Figure 5 (the standard deviation over repeats
//! per case), and the per-step residuals (the displacement measured in the image, and the
//! interferometer's, against the commanded one). Read from the session's `result.json` and
//! `steps.csv`; written by `rigctl report` and `rigctl demo` (docs/paper-tables.md).

use crate::acquisition::study::{JobResult, RunResult};
use crate::pipeline::stats::StudyStats;
use crate::plot::{Chart, Series, Style};
use crate::session::StepRow;

/// Figure 4 for case `case` of a study: each target's offset along its nominal direction
/// minus the nominal (so every target shares one axis), against the repeat.
pub fn figure4(st: &StudyStats, case: usize) -> Chart {
    let c = &st.cases[case];
    let series = c
        .targets
        .iter()
        .map(|t| Series {
            label: format!("{} (nominal {} µm)", t.name, t.nominal_um),
            points: t
                .per_run_um
                .iter()
                .enumerate()
                .map(|(i, v)| ((i + 1) as f64, v - t.nominal_um))
                .collect(),
            style: Style::Lines,
            y_u: Vec::new(),
        })
        .collect();
    Chart {
        title: format!(
            "Figure 4, {}: {} frame(s) {} µm apart, k = {}",
            c.name, c.frames, c.step_um, c.k
        ),
        x_label: "repeat (experiment number)".into(),
        y_label: "measured offset − nominal (µm)".into(),
        series,
        x_names: None,
        size: (800, 500),
    }
}

/// Figure 5: the standard deviation of each target's offset over the repeats, and their
/// RMS over the targets (Table 3's RMS row), per case.
pub fn figure5(st: &StudyStats) -> Chart {
    let mut names: Vec<&str> = Vec::new();
    for c in &st.cases {
        for t in &c.targets {
            if !names.contains(&t.name.as_str()) {
                names.push(&t.name);
            }
        }
    }
    let x = |i: usize| (i + 1) as f64;
    let mut series = vec![Series {
        label: "RMS over targets".into(),
        points: st
            .cases
            .iter()
            .enumerate()
            .map(|(i, c)| (x(i), c.rms_std_um))
            .collect(),
        style: Style::Lines,
        y_u: Vec::new(),
    }];
    series.extend(names.iter().map(|&n| {
        Series {
            label: format!("target {n}"),
            points: st
                .cases
                .iter()
                .enumerate()
                .filter_map(|(i, c)| Some((x(i), c.targets.iter().find(|t| t.name == n)?.std_um)))
                .collect(),
            style: Style::Points,
            y_u: Vec::new(),
        }
    }));
    Chart {
        title: "Figure 5: standard deviation over repeats per averaging case".into(),
        x_label: "averaging case (frames, k)".into(),
        y_label: "standard deviation over repeats (µm)".into(),
        series,
        x_names: Some(
            st.cases
                .iter()
                .map(|c| format!("{} ({}, k = {})", c.name, c.frames, c.k))
                .collect(),
        ),
        size: (800, 500),
    }
}

/// Per step: the displacement from the run's first frame measured in the image, read by the
/// interferometer and reported by the axis, each minus the commanded displacement (µm of
/// travel of the job's stage), against the frame's index in the session. A run lists its
/// first 1000 steps in `result.json`: later steps of a longer run are not drawn.
pub fn residuals(runs: &[RunResult], steps: &[StepRow]) -> Chart {
    let mut image = Vec::new();
    let mut laser = Vec::new();
    let mut axis = Vec::new();
    for run in runs {
        let Some(r) = &run.result else { continue };
        let rows: Vec<&StepRow> = steps.iter().filter(|s| s.run == run.run).collect();
        let Some(first) = rows.first() else { continue };
        let o = &r.options;
        let dir = o.axis_dir;
        let piezo_dir = o.piezo_dir.unwrap_or(dir);
        let norm2 = dir[0] * dir[0] + dir[1] * dir[1];
        for st in &r.steps {
            let Some(row) = rows.get(st.index) else {
                continue;
            };
            let x = row.index as f64;
            let commanded = row.position_um - first.position_um;
            // The image shift less the piezo's part, along the stage's direction, in µm.
            let mut shift = st.image_shift_px;
            if let (Some(p), Some(p0)) = (row.piezo_commanded_um, first.piezo_commanded_um) {
                let d = (p - p0) / o.scale_um_per_px;
                shift = [shift[0] - d * piezo_dir[0], shift[1] - d * piezo_dir[1]];
            }
            let along = (shift[0] * dir[0] + shift[1] * dir[1]) / norm2;
            image.push((x, along * o.scale_um_per_px - commanded));
            if let (Some(i), Some(i0)) = (row.interferometer_um, first.interferometer_um) {
                laser.push((x, i - i0 - commanded));
            }
            axis.push((x, row.axis_um - first.axis_um - commanded));
        }
    }
    let series = [
        ("image − commanded", image),
        ("interferometer − commanded", laser),
        ("axis (reported) − commanded", axis),
    ]
    .into_iter()
    .filter(|(_, p)| !p.is_empty())
    .map(|(label, points)| Series {
        label: label.into(),
        points,
        style: Style::Points,
        y_u: Vec::new(),
    })
    .collect();
    Chart {
        title: "Per-step residuals: displacement from each run's first frame − commanded".into(),
        x_label: "frame (index in the session)".into(),
        y_label: "displacement − commanded (µm)".into(),
        series,
        x_names: None,
        size: (900, 500),
    }
}

/// A file name from a case's name: letters, digits, `-` and `_` kept, the rest `-`.
fn file_stem(name: &str) -> String {
    name.chars()
        .map(
            |c| match c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                true => c,
                false => '-',
            },
        )
        .collect()
}

/// Every chart of a session, by file stem: Figure 4 per case, Figure 5 and the residuals.
pub fn charts(result: &JobResult, steps: &[StepRow]) -> Vec<(String, Chart)> {
    let mut out = Vec::new();
    if let Some(study) = &result.study {
        for (i, c) in study.stats.cases.iter().enumerate() {
            out.push((
                format!("figure4-{}", file_stem(&c.name)),
                figure4(&study.stats, i),
            ));
        }
        out.push(("figure5".to_string(), figure5(&study.stats)));
    }
    out.push(("residuals".to_string(), residuals(&result.runs, steps)));
    out
}
