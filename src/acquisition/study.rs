//! A job's runs reduced to the paper's study: per case, the scatter of each target's
//! offset over the repeats (`pipeline::stats`), and each case's improvement over raw frames.
//! The tables themselves are `report::study_tables`.

use crate::pipeline::stats::{study_stats, CaseRuns, CaseStats, StudyStats};
use crate::pipeline::ProcessResult;
use serde::{Deserialize, Serialize};

/// One run's outcome as the job records it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct RunResult {
    pub run: u32,
    pub case: String,
    pub repeat: u32,
    pub frames: u32,
    pub step_um: f64,
    pub k: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub result: Option<ProcessResult>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// What a job produced: every run's measurement (runs that finished before a fault are
/// kept) and, for a study, its summary. The session's `result.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct JobResult {
    pub runs: Vec<RunResult>,
    pub study: Option<StudySummary>,
    /// The calibration the job applied, or why none (absent from results written before
    /// the daemon kept calibrations).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<crate::calibration_note::CalibrationNote>,
    /// A calibration job's record.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibrated: Option<crate::calibration_note::Calibrated>,
}

/// One line of the study's summary (what `rigctl demo --json` lists as `cases`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct CaseLine {
    pub name: String,
    pub frames: u32,
    pub step_um: f64,
    pub k: u32,
    /// RMS over targets of the per-target standard deviation over repeats (null, NaN in
    /// memory, with a single repeat).
    #[serde(deserialize_with = "crate::pipeline::stats::nan_if_null")]
    #[schemars(with = "Option<f64>")]
    pub rms_std_um: f64,
    /// rms_std_um of the single-frame case over this case's.
    pub improvement: Option<f64>,
    pub runs_ok: usize,
    pub runs_failed: usize,
    /// RMS over targets of |bias| (mean minus the board's nominal offset: the truth on the
    /// sim), µm; null when no target has a nominal.
    #[serde(default, deserialize_with = "crate::pipeline::stats::nan_if_null")]
    #[schemars(with = "Option<f64>")]
    pub rms_bias_um: f64,
    /// With a calibration applied: the same two figures at the global scale
    /// (`offset_global_um`), the uncalibrated measurement of the same frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rms_std_global_um: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rms_bias_global_um: Option<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct StudySummary {
    pub cases: Vec<CaseLine>,
    pub stats: StudyStats,
    /// With a calibration applied: `stats` of the same runs at the global scale
    /// (each object's `offset_global_um`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub global: Option<StudyStats>,
}

/// The paper's RMS std per case (Alzarok et al., Table 3), µm.
pub const PAPER_RMS_STD_UM: [(&str, f64); 3] = [("case1", 281.5), ("case2", 96.6), ("case3", 69.9)];

/// RMS over a case's targets of |bias|, µm (NaN: none has one).
fn rms_bias_um(c: &CaseStats) -> f64 {
    let b: Vec<f64> = c
        .targets
        .iter()
        .map(|t| t.bias_um)
        .filter(|b| b.is_finite())
        .collect();
    (b.iter().map(|x| x * x).sum::<f64>() / b.len() as f64).sqrt()
}

/// The runs with each object's global-scale offset in place of its calibrated one; None
/// when no object was calibrated.
fn at_global_scale(case_runs: &[CaseRuns]) -> Option<Vec<CaseRuns>> {
    let calibrated = case_runs
        .iter()
        .flat_map(|c| c.runs.iter().flatten())
        .any(|o| o.offset_global_um.is_some());
    calibrated.then(|| {
        let mut global = case_runs.to_vec();
        for o in global.iter_mut().flat_map(|c| c.runs.iter_mut().flatten()) {
            o.offset_um = o.offset_global_um.unwrap_or(o.offset_um);
        }
        global
    })
}

/// Reduce a job's runs, grouped by case in the order they first ran. `names` are the
/// board's target names, in table order.
pub fn summarize(runs: &[RunResult], names: &[&str], scale_um_per_px: f64) -> StudySummary {
    let mut order: Vec<&str> = Vec::new();
    for r in runs {
        if !order.contains(&r.case.as_str()) {
            order.push(&r.case);
        }
    }
    let case_runs: Vec<CaseRuns> = order
        .iter()
        .map(|&case| {
            let of: Vec<&RunResult> = runs.iter().filter(|r| r.case == case).collect();
            CaseRuns {
                name: case.to_string(),
                frames: of[0].frames as usize,
                step_um: of[0].step_um,
                k: of[0].k,
                runs: of
                    .iter()
                    .filter_map(|r| r.result.as_ref().map(|x| x.objects.clone()))
                    .collect(),
            }
        })
        .collect();
    let stats = study_stats(&case_runs, names, scale_um_per_px);
    let global = at_global_scale(&case_runs).map(|g| study_stats(&g, names, scale_um_per_px));
    let raw = stats
        .cases
        .iter()
        .find(|c| c.frames == 1)
        .map(|c| c.rms_std_um)
        .filter(|x| x.is_finite() && *x > 0.0);
    let cases = stats
        .cases
        .iter()
        .zip(&case_runs)
        .enumerate()
        .map(|(i, (c, cr))| {
            let total = runs.iter().filter(|r| r.case == c.name).count();
            let g = global.as_ref().map(|g| &g.cases[i]);
            CaseLine {
                name: c.name.clone(),
                frames: c.frames as u32,
                step_um: c.step_um,
                k: c.k,
                rms_std_um: c.rms_std_um,
                improvement: raw
                    .filter(|_| c.rms_std_um.is_finite() && c.rms_std_um > 0.0)
                    .map(|r| r / c.rms_std_um),
                runs_ok: cr.runs.len(),
                runs_failed: total - cr.runs.len(),
                rms_bias_um: rms_bias_um(c),
                rms_std_global_um: g.map(|g| g.rms_std_um),
                rms_bias_global_um: g.map(rms_bias_um),
            }
        })
        .collect();
    StudySummary {
        cases,
        stats,
        global,
    }
}

/// Per case: RMS std and RMS |bias| of the offsets as measured (calibrated when a
/// calibration was applied) and at the global scale, beside the paper's RMS std.
pub fn calibration_table(s: &StudySummary) -> String {
    use crate::text::fixed;
    let mut out = String::from(
        "\nCalibrated (offset_um) against the global scale (offset_global_um); bias against the \
         board's nominal offsets (the sim's truth):\n",
    );
    out.push_str(&format!(
        "  {:<6} {:>15} {:>15} {:>16} {:>16} {:>15}\n",
        "case",
        "RMS std cal",
        "RMS std global",
        "RMS |bias| cal",
        "RMS |bias| glob",
        "paper RMS std"
    ));
    for c in &s.cases {
        let paper = PAPER_RMS_STD_UM
            .iter()
            .find(|(n, _)| *n == c.name)
            .map(|p| p.1);
        let um = |v: Option<f64>| format!("{} µm", fixed(v.filter(|x| x.is_finite()), 1));
        out.push_str(&format!(
            "  {:<6} {:>15} {:>15} {:>16} {:>16} {:>15}\n",
            c.name,
            um(Some(c.rms_std_um)),
            um(c.rms_std_global_um),
            um(Some(c.rms_bias_um)),
            um(c.rms_bias_global_um),
            um(paper)
        ));
    }
    out
}

/// Tables 1-3 and a line per case with its improvement over raw frames.
pub fn tables(s: &StudySummary) -> String {
    let mut out = crate::report::study_tables(&s.stats);
    out.push_str(
        "\nImprovement over raw frames (RMS std of the single-frame case / the case's):\n",
    );
    for c in &s.cases {
        out.push_str(&format!(
            "  {:<6} {:>3} frames at {:>5} µm, k = {:>2}: RMS std {:>7} µm  {}\n",
            c.name,
            c.frames,
            c.step_um,
            c.k,
            crate::text::fixed(Some(c.rms_std_um), 1),
            c.improvement
                .map(|x| format!("{x:.2}x"))
                .unwrap_or_else(|| "-".into())
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::{ObjectResult, ProcessOptions};

    fn run(case: &str, frames: u32, repeat: u32, offset: f64) -> RunResult {
        RunResult {
            run: 0,
            case: case.into(),
            repeat,
            frames,
            step_um: 0.0,
            k: 1,
            result: Some(ProcessResult {
                options: ProcessOptions::default(),
                frames: frames as usize,
                width: 1,
                height: 1,
                objects: vec![ObjectResult {
                    name: Some("A".into()),
                    centre_px: [0.0; 2],
                    offset_px: [0.0; 2],
                    offset_um: [offset, 3.0],
                    sigma_um: None,
                    nominal_um: Some([100.0, 0.0]),
                    outer_radius_px: 1.0,
                    inner_radius_px: 1.0,
                    frames: frames as usize,
                    effective_pixel_um: 774.0,
                    ..Default::default()
                }],
                skipped: vec![],
                steps: vec![],
                step_summary: Default::default(),
                calibration: None,
            }),
            error: None,
        }
    }

    #[test]
    fn one_repeat_reads_back_with_its_spread_undefined_and_prints_a_dash() {
        // `rigctl demo --repeats 1` and `rigctl fetch N --tables` of a one-repeat job read
        // result.json back: the std of one sample is null there.
        let s = summarize(
            &[run("case1", 1, 0, 1.0), run("case2", 10, 0, 2.0)],
            &["A"],
            774.0,
        );
        let json = serde_json::to_string(&s).unwrap();
        assert!(json.contains(r#""std_um":null"#), "{json}");
        let back: StudySummary = serde_json::from_str(&json).unwrap();
        let t = &back.stats.cases[1].targets[0];
        assert!(t.std_um.is_nan() && back.cases[1].rms_std_um.is_nan());
        assert_eq!(t.mean_um, 2.0);
        let text = tables(&back);
        assert!(!text.contains("NaN"), "{text}");
        assert!(text.contains("RMS std       — µm"), "{text}");
    }

    #[test]
    fn std_over_repeats_and_improvement_over_raw_frames() {
        let mut failed = run("case2", 10, 2, 0.0);
        failed.result = None;
        failed.error = Some("no target".into());
        let runs = vec![
            run("case1", 1, 0, 80.0),
            run("case1", 1, 1, 120.0),
            run("case2", 10, 0, 95.0),
            run("case2", 10, 1, 105.0),
            failed,
        ];
        let s = summarize(&runs, &["A"], 774.0);
        assert_eq!(s.cases.len(), 2);
        // std of {80, 120} (n-1) = 28.28; of {95, 105} = 7.07.
        assert!((s.cases[0].rms_std_um - 28.284).abs() < 1e-2);
        assert!((s.cases[1].rms_std_um - 7.071).abs() < 1e-2);
        assert!((s.cases[1].improvement.unwrap() - 4.0).abs() < 1e-9);
        assert_eq!((s.cases[1].runs_ok, s.cases[1].runs_failed), (2, 1));
        let t = tables(&s);
        assert!(t.contains("Table 3") && t.contains("4.00x"), "{t}");
    }
}
