//! `rigctl report SESSION [--out DIR]`: a processed session's figures (PNG and SVG) and
//! `report.txt`, offline, from its `result.json` and `steps.csv` (whose `interferometer_um`
//! is each frame's reading, interpolated from `interferometer.csv`). `rigctl demo` writes
//! the same into its session.

use crate::acquisition::study::{tables, JobResult};
use crate::atomic_file;
use crate::figures;
use crate::session::{Session, RESULT};
use crate::text::{fixed, Table};
use anyhow::Context;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct ReportArgs {
    /// The session folder (one a job or a replay recorded, processed: with result.json).
    pub session: PathBuf,
    /// Where the figures and report.txt are written [default: the session folder].
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
}

pub fn run(a: ReportArgs) -> anyhow::Result<()> {
    let out = a.out.clone().unwrap_or_else(|| a.session.clone());
    for path in write(&a.session, &out)? {
        println!("{}", path.display());
    }
    Ok(())
}

/// The session's `result.json`, read back; the error names the file.
pub fn read_result(session: &Path) -> anyhow::Result<JobResult> {
    let path = session.join(RESULT);
    let text = crate::nofollow::read_in_max(session, RESULT, crate::bounds::MAX_STEPS_BYTES)
        .with_context(|| {
            format!(
                "{}: cannot read the session's result (is it a processed session?)",
                path.display()
            )
        })?;
    serde_json::from_slice(&text)
        .with_context(|| format!("{}: not a session's result", path.display()))
}

/// Write the session's figures (`NAME.png`, `NAME.svg`) and `report.txt` into `out`, each
/// atomically; the paths written, report.txt first.
pub fn write(session: &Path, out: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let result = read_result(session)?;
    let charts = charts_of(session, &result)?;
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;
    let save = |name: String, bytes: &[u8]| -> anyhow::Result<PathBuf> {
        let path = out.join(name);
        atomic_file::write(&path, bytes)?;
        Ok(path)
    };
    let mut written = vec![save("report.txt".into(), text(&result).as_bytes())?];
    for (stem, chart) in charts {
        let png = chart
            .png()
            .map_err(|e| anyhow::anyhow!("{stem}.png: {e}"))?;
        written.push(save(format!("{stem}.png"), &png)?);
        let svg = chart
            .svg()
            .map_err(|e| anyhow::anyhow!("{stem}.svg: {e}"))?;
        written.push(save(format!("{stem}.svg"), svg.as_bytes())?);
    }
    atomic_file::sync_dir(out)?;
    Ok(written)
}

/// The session's charts by file stem (`figures::charts`), from its `result.json` and
/// `steps.csv`.
pub fn charts(session: &Path) -> anyhow::Result<Vec<(String, crate::plot::Chart)>> {
    charts_of(session, &read_result(session)?)
}

fn charts_of(
    session: &Path,
    result: &JobResult,
) -> anyhow::Result<Vec<(String, crate::plot::Chart)>> {
    let steps = Session::open(session)?.steps;
    Ok(figures::charts(result, &steps))
}

/// The study's tables (when the job processed), then a line per run: its targets and the
/// RMS of its per-step residual (image against the positions it registered by), or its error.
pub fn text(result: &JobResult) -> String {
    let mut s = result.study.as_ref().map(tables).unwrap_or_default();
    let mut t = Table::new(&[
        "run",
        "case",
        "repeat",
        "frames",
        "targets",
        "rms residual x µm",
        "rms residual y µm",
        "error",
    ]);
    for r in &result.runs {
        let (targets, rms, error) = match &r.result {
            Some(x) => (
                x.objects.len().to_string(),
                x.step_summary.rms_residual_um,
                "",
            ),
            None => ("0".into(), [f64::NAN; 2], r.error.as_deref().unwrap_or("")),
        };
        t.row(vec![
            r.run.to_string(),
            r.case.clone(),
            r.repeat.to_string(),
            r.frames.to_string(),
            targets,
            fixed(Some(rms[0]), 2),
            fixed(Some(rms[1]), 2),
            error.to_string(),
        ]);
    }
    s.push_str("\nRuns (per-step residual: the image's displacement against the positions it was registered by):\n");
    s.push_str(&t.render());
    s
}
