//! What `rigctl submit` prints when its job finishes: each target's offset per case, with
//! its spread over repeats or the fit's own uncertainty, and where the session is on disk.

use crate::acquisition::study::{JobResult, RunResult};
use crate::cli::text::{fixed, Table};

/// One line per case and target, in the order they first appear: the mean offset over the
/// runs that measured it, the standard deviation over them (`—` with one run), the fit's
/// mean uncertainty when it gives one.
pub fn results_table(r: &JobResult) -> Table {
    let mut t = Table::new(&[
        "case", "target", ">runs", ">dx µm", ">dy µm", ">std dx", ">std dy", ">σ dx", ">σ dy",
    ]);
    let mut keys: Vec<(String, String)> = Vec::new();
    for run in &r.runs {
        for (i, o) in objects(run).enumerate() {
            let key = (run.case.clone(), name(o, i));
            if !keys.contains(&key) {
                keys.push(key);
            }
        }
    }
    for (case, target) in keys {
        let found: Vec<&crate::pipeline::ObjectResult> = r
            .runs
            .iter()
            .filter(|run| run.case == case)
            .flat_map(|run| {
                objects(run)
                    .enumerate()
                    .filter(|(i, o)| name(o, *i) == target)
            })
            .map(|(_, o)| o)
            .collect();
        let axis = |a: usize| found.iter().map(|o| o.offset_um[a]).collect::<Vec<f64>>();
        let sigma = |a: usize| {
            let s: Vec<f64> = found
                .iter()
                .filter_map(|o| o.sigma_um.map(|s| s[a]))
                .collect();
            (!s.is_empty()).then(|| s.iter().sum::<f64>() / s.len() as f64)
        };
        let (x, y) = (axis(0), axis(1));
        t.row(vec![
            case.clone(),
            target,
            found.len().to_string(),
            fixed(mean(&x), 1),
            fixed(mean(&y), 1),
            fixed(std(&x), 2),
            fixed(std(&y), 2),
            fixed(sigma(0), 2),
            fixed(sigma(1), 2),
        ]);
    }
    t
}

fn objects(run: &RunResult) -> impl Iterator<Item = &crate::pipeline::ObjectResult> {
    run.result.iter().flat_map(|r| r.objects.iter())
}

fn name(o: &crate::pipeline::ObjectResult, i: usize) -> String {
    o.name.clone().unwrap_or_else(|| format!("#{i}"))
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Sample standard deviation (n - 1); none for fewer than two.
fn std(v: &[f64]) -> Option<f64> {
    let m = mean(v)?;
    (v.len() > 1)
        .then(|| (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::{ObjectResult, ProcessOptions, ProcessResult};

    /// A target's name, offset and the fit's uncertainty.
    type Found<'a> = (&'a str, [f64; 2], Option<[f64; 2]>);

    fn run(case: &str, offsets: &[Found<'_>]) -> RunResult {
        RunResult {
            run: 0,
            case: case.into(),
            repeat: 0,
            frames: 1,
            step_um: 0.0,
            k: 1,
            result: Some(ProcessResult {
                options: ProcessOptions::default(),
                frames: 1,
                width: 1,
                height: 1,
                objects: offsets
                    .iter()
                    .map(|(n, off, sigma)| ObjectResult {
                        name: Some((*n).into()),
                        centre_px: [0.0; 2],
                        offset_px: [0.0; 2],
                        offset_um: *off,
                        sigma_um: *sigma,
                        nominal_um: None,
                        outer_radius_px: 1.0,
                        inner_radius_px: 1.0,
                        frames: 1,
                        effective_pixel_um: 774.0,
                        ..Default::default()
                    })
                    .collect(),
                skipped: vec![],
                steps: vec![],
                step_summary: Default::default(),
                calibration: None,
            }),
            error: None,
        }
    }

    #[test]
    fn one_line_per_case_and_target_with_the_spread_over_repeats() {
        let r = JobResult {
            runs: vec![
                run(
                    "scan",
                    &[
                        ("A", [1000.0, -2.0], Some([1.5, 1.0])),
                        ("B", [0.0, 500.0], None),
                    ],
                ),
                run("scan", &[("A", [1002.0, -4.0], Some([0.5, 1.0]))]),
            ],
            study: None,
            calibration: None,
            calibrated: None,
        };
        let text = results_table(&r).render();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 3, "{text}");
        let cells = |l: &str| l.split_whitespace().map(String::from).collect::<Vec<_>>();
        assert_eq!(
            cells(lines[1]),
            ["scan", "A", "2", "1001.0", "-3.0", "1.41", "1.41", "1.00", "1.00"]
        );
        // One run of B: no spread, and no fit uncertainty given.
        assert_eq!(
            cells(lines[2]),
            ["scan", "B", "1", "0.0", "500.0", "—", "—", "—", "—"]
        );
    }
}
