//! `results.csv`: a processed run's measurements as one flat table beside `result.json`, one
//! row per (run, case, repeat, target), for the spreadsheets and data frames a lab reads.
//!
//! The columns and their units are docs/sessions.md's. Numbers are written in the shortest
//! form that reads back to the same `f64`; a figure that is not known (no nominal, no
//! uncertainty) is an empty cell. A run that failed has no row (its error is in
//! `result.json`). Written by the daemon when it closes a session, by `rigctl process --out`,
//! and by anything else that writes a `result.json` ([`write`]).

use crate::acquisition::study::RunResult;
use crate::atomic_file::{self, AtomicWriteError};
use crate::pipeline::ProcessResult;
use crate::text::wire_name;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The file's name, beside `result.json`.
pub const FILE: &str = "results.csv";

/// One target measured in one run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Row {
    pub run: u32,
    pub case: String,
    pub repeat: u32,
    /// The board's name of the target, else `#N` (its place in the run's result).
    pub target: String,
    /// Inner centre minus outer centre, µm on the board.
    pub dx_um: f64,
    pub dy_um: f64,
    /// The standard uncertainty of dx_um, dy_um: the combined `u_um` (type A and B, GUM)
    /// when the result has it, else (results before it) `sigma_um`.
    pub u_dx_um: Option<f64>,
    pub u_dy_um: Option<f64>,
    /// The board's nominal offset.
    pub nominal_dx_um: Option<f64>,
    pub nominal_dy_um: Option<f64>,
    /// Measured minus nominal.
    pub bias_dx_um: Option<f64>,
    pub bias_dy_um: Option<f64>,
    /// Frames that contributed to the target's measurement.
    pub frames: usize,
    pub k: u32,
    pub estimator: String,
    pub combine: String,
    pub registration: String,
}

/// A finite figure, or none (an empty cell).
fn known(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// The rows of one run's result. `registration` names where the displacements came from
/// when the caller knows more than the pipeline (`commanded`/`interferometer` rather than
/// `positions`); `None` takes the pipeline's option.
pub fn rows_of(
    (run, case, repeat): (u32, &str, u32),
    r: &ProcessResult,
    registration: Option<&str>,
) -> Vec<Row> {
    let registration = registration
        .map(str::to_string)
        .unwrap_or_else(|| wire_name(&r.options.registration));
    r.objects
        .iter()
        .enumerate()
        .map(|(i, o)| {
            let nominal = o.nominal_um.map(|n| n.map(known));
            let bias = |a: usize| {
                let n = o.nominal_um?[a];
                known(o.offset_um[a] - n)
            };
            Row {
                run,
                case: case.to_string(),
                repeat,
                target: o.name.clone().unwrap_or_else(|| format!("#{i}")),
                dx_um: o.offset_um[0],
                dy_um: o.offset_um[1],
                u_dx_um: o.u_um.or(o.sigma_um).and_then(|s| known(s[0])),
                u_dy_um: o.u_um.or(o.sigma_um).and_then(|s| known(s[1])),
                nominal_dx_um: nominal.and_then(|n| n[0]),
                nominal_dy_um: nominal.and_then(|n| n[1]),
                bias_dx_um: bias(0),
                bias_dy_um: bias(1),
                frames: o.frames,
                k: r.options.k,
                estimator: wire_name(&r.options.estimator),
                combine: wire_name(&r.options.combine),
                registration: registration.clone(),
            }
        })
        .collect()
}

/// The rows of every run that has a result, in run order.
pub fn rows(runs: &[RunResult], registration: Option<&str>) -> Vec<Row> {
    runs.iter()
        .filter_map(|r| {
            let res = r.result.as_ref()?;
            Some(rows_of((r.run, &r.case, r.repeat), res, registration))
        })
        .flatten()
        .collect()
}

/// The table as CSV text, header first (a header alone when there is no row).
pub fn to_bytes(rows: &[Row]) -> Vec<u8> {
    let mut w = csv::WriterBuilder::new()
        .has_headers(false)
        .from_writer(Vec::with_capacity(128 * (rows.len() + 1)));
    // Written by hand so that an empty table still says what its columns are.
    w.write_record(HEADER).expect("writes to memory");
    for r in rows {
        w.serialize(r).expect("rows serialise to memory");
    }
    w.into_inner().expect("writes to memory")
}

/// The columns, in order (the same as [`Row`]'s fields).
pub const HEADER: [&str; 17] = [
    "run",
    "case",
    "repeat",
    "target",
    "dx_um",
    "dy_um",
    "u_dx_um",
    "u_dy_um",
    "nominal_dx_um",
    "nominal_dy_um",
    "bias_dx_um",
    "bias_dy_um",
    "frames",
    "k",
    "estimator",
    "combine",
    "registration",
];

/// Write `results.csv` for `runs` into `dir` (beside its `result.json`), atomically.
pub fn write(
    dir: &Path,
    runs: &[RunResult],
    registration: Option<&str>,
) -> Result<PathBuf, AtomicWriteError> {
    let path = dir.join(FILE);
    atomic_file::write(&path, &to_bytes(&rows(runs, registration)))?;
    Ok(path)
}

/// Read a `results.csv` back (tests, `rigctl report`). Errors name the file and the row.
pub fn read(path: &Path) -> Result<Vec<Row>, String> {
    let mut rd = csv::Reader::from_path(path).map_err(|e| format!("{}: {e}", path.display()))?;
    rd.deserialize()
        .enumerate()
        .map(|(i, r)| r.map_err(|e| format!("{}: row {}: {e}", path.display(), i + 1)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::{ObjectResult, ProcessOptions};

    fn result() -> ProcessResult {
        let obj = |name: Option<&str>, dx: f64, sigma, nominal| ObjectResult {
            name: name.map(str::to_string),
            centre_px: [0.0; 2],
            offset_px: [0.0; 2],
            offset_um: [dx, -0.1],
            sigma_um: sigma,
            nominal_um: nominal,
            outer_radius_px: 1.0,
            inner_radius_px: 1.0,
            frames: 20,
            effective_pixel_um: 77.4,
            ..Default::default()
        };
        ProcessResult {
            options: ProcessOptions {
                k: 10,
                ..ProcessOptions::default()
            },
            frames: 20,
            width: 1,
            height: 1,
            objects: vec![
                obj(Some("B"), 1000.1, Some([0.3, 0.25]), Some([1000.0, 0.0])),
                obj(None, 0.1 + 0.2, None, None),
            ],
            skipped: vec![],
            steps: vec![],
            step_summary: Default::default(),
            calibration: None,
        }
    }

    #[test]
    fn a_row_per_target_with_empty_cells_for_what_is_unknown_and_exact_numbers() {
        let run = |run, result: Option<ProcessResult>| RunResult {
            run,
            case: "case3".into(),
            repeat: run,
            frames: 20,
            step_um: 50.0,
            k: 10,
            error: result.is_none().then(|| "no target".to_string()),
            result,
        };
        let runs = [run(0, Some(result())), run(1, None), run(2, Some(result()))];
        let text = String::from_utf8(to_bytes(&rows(&runs, Some("interferometer")))).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], HEADER.join(","));
        assert_eq!(lines.len(), 1 + 4, "{text}");
        // 1000.1 - 1000 is 0.10000000000002274 in f64: written so it reads back the same.
        assert_eq!(
            lines[1],
            "0,case3,0,B,1000.1,-0.1,0.3,0.25,1000.0,0.0,0.10000000000002274,-0.1,20,10,fit,mean,interferometer"
        );
        assert_eq!(
            lines[2],
            "0,case3,0,#1,0.30000000000000004,-0.1,,,,,,,20,10,fit,mean,interferometer"
        );
        assert!(lines[3].starts_with("2,case3,2,B,"), "{text}");
        let d = tempfile::tempdir().unwrap();
        let path = write(d.path(), &runs, None).unwrap();
        let back = read(&path).unwrap();
        assert_eq!(back, rows(&runs, None));
        assert_eq!(back[0].registration, "image");
        assert_eq!(back[1].dx_um, 0.1 + 0.2);
    }

    #[test]
    fn an_empty_table_still_has_its_header_and_a_bad_file_is_named() {
        assert_eq!(
            String::from_utf8(to_bytes(&[])).unwrap().trim_end(),
            HEADER.join(",")
        );
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join(FILE);
        std::fs::write(&p, format!("{}\n0,c,0,A,x\n", HEADER.join(","))).unwrap();
        let e = read(&p).unwrap_err();
        assert!(e.contains("results.csv") && e.contains("row 1"), "{e}");
    }
}
