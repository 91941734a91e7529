//! Many sessions reprocessed without a daemon: each on a thread of a rayon pool (and each
//! run's pipeline on the same pool's threads), its outputs written inside the session under
//! `processed/<settings>/` (no new session, no frame copied), its rows added to a results
//! index. A session that fails is reported by name and the others go on.

use super::index::{rows_of, Index, SessionFacts};
use super::outputs::{registration_name, settings_dir, write_outputs, Settings};
use super::overrides::Overrides;
use super::session_runs::process_session;
use crate::board::Board;
use crate::session::{unix_s, Session};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// How to reprocess.
#[derive(Debug, Clone)]
pub struct Reprocess {
    pub overrides: Overrides,
    /// A board overriding each session's rig board.
    pub board: Option<Board>,
    /// A calibration converting every run's offsets (its id joins the settings' name).
    /// Without one, each session's job's own (`recorded_calibration`), unless
    /// `no_calibration`: the global scale.
    pub calibration: Option<crate::calibration_file::Applied>,
    pub no_calibration: bool,
    /// Sessions processed at once (rayon threads); the pipeline shares the pool.
    pub threads: usize,
    /// Where rows go: one index for every session, else `<session's parent>/index.sqlite`;
    /// `None` inside: no index.
    pub index: IndexTarget,
}

#[derive(Debug, Clone)]
pub enum IndexTarget {
    /// `<data root>/index.sqlite`, the data root being each session's parent folder.
    DataRoot,
    File(PathBuf),
    None,
}

/// One session's outcome.
#[derive(Debug)]
pub struct Done {
    pub session: PathBuf,
    /// The result folder, or why the session failed.
    pub outcome: Result<Summary, String>,
}

#[derive(Debug, Clone)]
pub struct Summary {
    pub out: PathBuf,
    pub runs: usize,
    pub runs_failed: usize,
    pub rows: usize,
}

/// Reprocess `sessions`, calling `report` as each ends (from the pool's threads).
pub fn reprocess(
    sessions: &[PathBuf],
    how: &Reprocess,
    report: &(dyn Fn(&Done) + Sync),
) -> anyhow::Result<Vec<Done>> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(how.threads.max(1))
        .build()?;
    let indexes: Mutex<Vec<(PathBuf, Index)>> = Mutex::new(Vec::new());
    let done = pool.install(|| {
        sessions
            .par_iter()
            .map(|dir| {
                let outcome =
                    one(dir, how, &indexes).map_err(|e| crate::text::error_chain(e.chain()));
                let d = Done {
                    session: dir.clone(),
                    outcome,
                };
                report(&d);
                d
            })
            .collect::<Vec<_>>()
    });
    Ok(done)
}

/// One session: process, write `processed/<settings>/`, index.
fn one(
    dir: &Path,
    how: &Reprocess,
    indexes: &Mutex<Vec<(PathBuf, Index)>>,
) -> anyhow::Result<Summary> {
    let s = Session::open(dir)?;
    let calibration = match (&how.calibration, how.no_calibration) {
        (Some(c), _) => Some(c.clone()),
        (None, true) => None,
        (None, false) => super::session_runs::recorded_calibration(&s)?,
    };
    let name = match &calibration {
        Some(c) => format!("{}-{}", how.overrides.settings_name(), c.calibration.id),
        None => how.overrides.settings_name(),
    };
    // One decoder thread per session: the pool runs sessions side by side.
    let done = process_session(
        &s,
        &how.overrides,
        how.board.clone(),
        calibration.as_ref(),
        None,
        true,
        1,
    )?;
    let settings = Settings {
        name: name.clone(),
        overrides: how.overrides,
        runs: done.runs.clone(),
        rigd: env!("CARGO_PKG_VERSION").into(),
        processed_unix_s: unix_s(std::time::SystemTime::now()),
    };
    let out = settings_dir(&s.dir, &name)?;
    // The single call site of the result files (result.json and results.csv).
    let registration = registration_name(&settings.overrides, &s);
    write_outputs(
        &out,
        &done.result,
        &done.images,
        &settings,
        registration.as_deref(),
    )?;
    let facts = SessionFacts::of_session(&s);
    let rows = rows_of(&facts, &name, &done.result);
    if let Some(path) = index_path(dir, &how.index) {
        let mut all = indexes.lock().unwrap_or_else(|e| e.into_inner());
        if !all.iter().any(|(p, _)| *p == path) {
            all.push((path.clone(), Index::open(&path)?));
        }
        let index = &mut all.iter_mut().find(|(p, _)| *p == path).expect("added").1;
        index.replace(&facts.session, &name, &rows)?;
    }
    let runs_failed = done
        .result
        .runs
        .iter()
        .filter(|r| r.error.is_some())
        .count();
    Ok(Summary {
        out,
        runs: done.result.runs.len(),
        runs_failed,
        rows: rows.len(),
    })
}

fn index_path(session: &Path, target: &IndexTarget) -> Option<PathBuf> {
    match target {
        IndexTarget::None => None,
        IndexTarget::File(p) => Some(p.clone()),
        IndexTarget::DataRoot => {
            let parent = session.parent().filter(|p| !p.as_os_str().is_empty());
            Some(
                parent
                    .unwrap_or(Path::new("."))
                    .join(super::index::INDEX_FILE),
            )
        }
    }
}
