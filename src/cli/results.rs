//! What `rigctl submit` prints when its job finishes: each target's offset per case, its
//! spread over repeats, its combined standard uncertainty `u` (GUM: the frames' scatter
//! and the scale's or calibration's), the board's nominal and the bias from it, then which
//! calibration converted the offsets and where the session is on disk.

use crate::acquisition::study::{JobResult, RunResult};
use crate::text::{fixed, Table};

/// One line per case and target, in the order they first appear: the mean offset over the
/// runs that measured it, the standard deviation over them (`—` with one run), the mean of
/// the runs' combined uncertainty `u_um`, the board's nominal and the mean's bias from it
/// (`—` where unknown).
pub fn results_table(r: &JobResult) -> Table {
    let mut t = Table::new(&[
        "case", "target", ">runs", ">dx µm", ">dy µm", ">std dx", ">std dy", ">u dx", ">u dy",
        ">nom dx", ">nom dy", ">bias dx", ">bias dy",
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
        let u = |a: usize| {
            let s: Vec<f64> = found.iter().filter_map(|o| o.u_um.map(|u| u[a])).collect();
            mean(&s)
        };
        let nominal = found.iter().find_map(|o| o.nominal_um);
        let (x, y) = (axis(0), axis(1));
        let (mx, my) = (mean(&x), mean(&y));
        let nom = |a: usize| nominal.map(|n| n[a]);
        let bias = |m: Option<f64>, a: usize| Some(m? - nom(a)?);
        t.row(vec![
            case.clone(),
            target,
            found.len().to_string(),
            fixed(mx, 1),
            fixed(my, 1),
            fixed(std(&x), 2),
            fixed(std(&y), 2),
            fixed(u(0), 2),
            fixed(u(1), 2),
            fixed(nom(0), 1),
            fixed(nom(1), 1),
            fixed(bias(mx, 0), 2),
            fixed(bias(my, 1), 2),
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

    /// A target's name, offset and combined uncertainty.
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
                    .map(|(n, off, u)| ObjectResult {
                        name: Some((*n).into()),
                        centre_px: [0.0; 2],
                        offset_px: [0.0; 2],
                        offset_um: *off,
                        u_um: *u,
                        nominal_um: (*n == "A").then_some([1000.0, 0.0]),
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
    fn one_line_per_case_and_target_with_spread_u_nominal_and_bias() {
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
            [
                "scan", "A", "2", "1001.0", "-3.0", "1.41", "1.41", "1.00", "1.00", "1000.0",
                "0.0", "1.00", "-3.00"
            ]
        );
        // One run of B: no spread, no uncertainty given, no nominal.
        assert_eq!(
            cells(lines[2]),
            [
                "scan", "B", "1", "0.0", "500.0", "—", "—", "—", "—", "—", "—", "—", "—"
            ]
        );
    }
}
