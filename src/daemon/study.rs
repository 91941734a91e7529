//! The study summary: per case, the scatter of each target's measured offset over the
//! repeats (the paper's Table 3), its mean against the nominal offset (Table 1), and the
//! improvement over raw frames (Table 2). Built from the per-run results of one job.

use crate::pipeline::ProcessResult;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// One run's outcome as the job records it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
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

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TargetStats {
    pub name: String,
    pub nominal_um: Option<f64>,
    /// Mean measured offset over the repeats (along the nominal direction).
    pub mean_um: f64,
    /// Standard deviation over the repeats (n - 1).
    pub std_um: f64,
    pub repeats: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaseSummary {
    pub name: String,
    pub frames: u32,
    pub step_um: f64,
    pub k: u32,
    /// RMS over targets of the per-target standard deviation.
    pub rms_std_um: f64,
    /// rms_std_um of the single-frame case divided by this case's (1 for raw frames).
    pub improvement: Option<f64>,
    pub runs_ok: usize,
    pub runs_failed: usize,
    pub targets: Vec<TargetStats>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StudySummary {
    pub cases: Vec<CaseSummary>,
}

/// The measured offset of a target along its nominal direction (its length if no nominal).
fn offset_along(o: &crate::pipeline::ObjectResult) -> f64 {
    match o.nominal_um {
        Some(n) if n[0].hypot(n[1]) > 0.0 => {
            let l = n[0].hypot(n[1]);
            (o.offset_um[0] * n[0] + o.offset_um[1] * n[1]) / l
        }
        _ => o.offset_um[0].hypot(o.offset_um[1]),
    }
}

pub fn summarize(runs: &[RunResult]) -> StudySummary {
    let mut order: Vec<String> = Vec::new();
    for r in runs {
        if !order.contains(&r.case) {
            order.push(r.case.clone());
        }
    }
    let mut cases: Vec<CaseSummary> = order
        .iter()
        .map(|case| {
            let of_case: Vec<&RunResult> = runs.iter().filter(|r| &r.case == case).collect();
            let first = of_case[0];
            let mut per: BTreeMap<String, (Option<f64>, Vec<f64>)> = BTreeMap::new();
            let mut ok = 0;
            for r in &of_case {
                let Some(res) = &r.result else { continue };
                ok += 1;
                for (i, o) in res.objects.iter().enumerate() {
                    let name = o.name.clone().unwrap_or_else(|| format!("#{i}"));
                    let nominal = o.nominal_um.map(|n| n[0].hypot(n[1]));
                    per.entry(name)
                        .or_insert((nominal, Vec::new()))
                        .1
                        .push(offset_along(o));
                }
            }
            let targets: Vec<TargetStats> = per
                .into_iter()
                .map(|(name, (nominal_um, v))| {
                    let n = v.len() as f64;
                    let mean = v.iter().sum::<f64>() / n.max(1.0);
                    let var = if v.len() > 1 {
                        v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)
                    } else {
                        0.0
                    };
                    TargetStats {
                        name,
                        nominal_um,
                        mean_um: mean,
                        std_um: var.sqrt(),
                        repeats: v.len(),
                    }
                })
                .collect();
            let rms = if targets.is_empty() {
                f64::NAN
            } else {
                (targets.iter().map(|t| t.std_um.powi(2)).sum::<f64>() / targets.len() as f64)
                    .sqrt()
            };
            CaseSummary {
                name: case.clone(),
                frames: first.frames,
                step_um: first.step_um,
                k: first.k,
                rms_std_um: rms,
                improvement: None,
                runs_ok: ok,
                runs_failed: of_case.len() - ok,
                targets,
            }
        })
        .collect();
    let raw = cases
        .iter()
        .find(|c| c.frames == 1)
        .map(|c| c.rms_std_um)
        .filter(|x| x.is_finite() && *x > 0.0);
    for c in &mut cases {
        c.improvement = raw
            .filter(|_| c.rms_std_um.is_finite() && c.rms_std_um > 0.0)
            .map(|r| r / c.rms_std_um);
    }
    StudySummary { cases }
}

/// The paper's three tables as text.
pub fn tables(s: &StudySummary) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let names: Vec<String> = {
        let mut v: Vec<String> = Vec::new();
        for c in &s.cases {
            for t in &c.targets {
                if !v.contains(&t.name) {
                    v.push(t.name.clone());
                }
            }
        }
        v
    };
    let cell = |c: &CaseSummary, n: &str, f: &dyn Fn(&TargetStats) -> f64| {
        c.targets
            .iter()
            .find(|t| t.name == n)
            .map(|t| format!("{:>10.1}", f(t)))
            .unwrap_or_else(|| format!("{:>10}", "-"))
    };
    let head = |out: &mut String, first: &str| {
        let _ = write!(out, "{first:<8}");
        for c in &s.cases {
            let _ = write!(out, "{:>10}", c.name);
        }
        out.push('\n');
    };
    out.push_str("Table 1: nominal and measured offsets (µm, mean over repeats)\n");
    let _ = write!(out, "{:<8}{:>10}", "target", "nominal");
    for c in &s.cases {
        let _ = write!(out, "{:>10}", c.name);
    }
    out.push('\n');
    for n in &names {
        let nominal = s
            .cases
            .iter()
            .flat_map(|c| &c.targets)
            .find(|t| &t.name == n)
            .and_then(|t| t.nominal_um);
        let _ = write!(
            out,
            "{n:<8}{:>10}",
            nominal.map(|x| format!("{x:.0}")).unwrap_or("-".into())
        );
        for c in &s.cases {
            out.push_str(&cell(c, n, &|t| t.mean_um));
        }
        out.push('\n');
    }
    out.push_str("\nTable 2: improvement over raw frames (RMS std of case 1 / RMS std of case)\n");
    head(&mut out, "");
    let _ = write!(out, "{:<8}", "ratio");
    for c in &s.cases {
        let _ = write!(
            out,
            "{:>10}",
            c.improvement
                .map(|x| format!("{x:.2}"))
                .unwrap_or("-".into())
        );
    }
    out.push_str("\n\nTable 3: standard deviation of the measured offsets over repeats (µm)\n");
    head(&mut out, "target");
    for n in &names {
        let _ = write!(out, "{n:<8}");
        for c in &s.cases {
            out.push_str(&cell(c, n, &|t| t.std_um));
        }
        out.push('\n');
    }
    let _ = write!(out, "{:<8}", "RMS");
    for c in &s.cases {
        let _ = write!(out, "{:>10.1}", c.rms_std_um);
    }
    out.push('\n');
    let _ = write!(out, "{:<8}", "frames");
    for c in &s.cases {
        let _ = write!(out, "{:>10}", format!("{}@{}", c.frames, c.step_um));
    }
    out.push('\n');
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
                }],
                skipped: vec![],
                steps: vec![],
            }),
            error: None,
        }
    }

    #[test]
    fn std_over_repeats_and_improvement_over_raw_frames() {
        let runs = vec![
            run("case1", 1, 0, 80.0),
            run("case1", 1, 1, 120.0),
            run("case2", 10, 0, 95.0),
            run("case2", 10, 1, 105.0),
        ];
        let s = summarize(&runs);
        assert_eq!(s.cases.len(), 2);
        // std of {80, 120} (n-1) = 28.28; of {95, 105} = 7.07.
        assert!((s.cases[0].rms_std_um - 28.284).abs() < 1e-2);
        assert!((s.cases[1].rms_std_um - 7.071).abs() < 1e-2);
        assert!((s.cases[1].improvement.unwrap() - 4.0).abs() < 1e-9);
        assert!((s.cases[0].targets[0].mean_um - 100.0).abs() < 1e-9);
        let t = tables(&s);
        assert!(t.contains("Table 3") && t.contains("4.00"), "{t}");
    }
}
