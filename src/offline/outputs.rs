//! A processed session's outputs, written inside the session under
//! `processed/<settings>/`: `result.json` (the daemon's document: every run and the study),
//! `settings.json` (what was overridden and each run's complete options), and the
//! reconstructions under `images/`. Nothing else in the session is touched; nothing is
//! written through a symlink (folders made with `nofollow::create_dir`, files staged with
//! O_EXCL|O_NOFOLLOW and renamed into place, `result.json` last).

use super::overrides::Overrides;
use crate::acquisition::processor::Image16;
use crate::acquisition::study::JobResult;
use crate::atomic_file::{self, AtomicWriteError};
use crate::pipeline::ProcessOptions;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// `processed/` in a session.
pub const PROCESSED: &str = "processed";
pub const SETTINGS: &str = "settings.json";

/// What `settings.json` records.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct Settings {
    /// The folder's name ([`Overrides::settings_name`]).
    pub name: String,
    /// What the command line overrode (the rest is each run's recorded value).
    pub overrides: Overrides,
    /// Each run's complete options as processed.
    pub runs: Vec<RunSettings>,
    pub rigd: String,
    pub processed_unix_s: f64,
}

#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct RunSettings {
    pub run: u32,
    pub case: String,
    pub repeat: u32,
    pub options: ProcessOptions,
}

#[derive(Debug, thiserror::Error)]
#[error("{}: {message}", path.display())]
pub struct OutputError {
    pub path: PathBuf,
    pub message: String,
}

impl From<AtomicWriteError> for OutputError {
    fn from(e: AtomicWriteError) -> OutputError {
        OutputError {
            path: e.path,
            message: format!("{}: {}", e.what, e.source),
        }
    }
}

/// results.csv's `registration`: the command line's, else the session's job's, by its wire
/// name (`commanded`, `interferometer`: the pipeline's `positions`).
pub fn registration_name(
    overrides: &Overrides,
    session: &crate::session::Session,
) -> Option<String> {
    overrides
        .registration
        .or(session.manifest.job.registration)
        .map(|r| crate::text::wire_name(&r))
}

/// `session/processed/<name>`, made if missing (never through a symlink).
pub fn settings_dir(session: &Path, name: &str) -> Result<PathBuf, OutputError> {
    let processed = session.join(PROCESSED);
    // The name is made from flags and a calibration's id: one component below `processed/`.
    crate::bounds::one_component("settings name", name).map_err(|message| OutputError {
        path: processed.clone(),
        message,
    })?;
    let dir = processed.join(name);
    for d in [&processed, &dir] {
        crate::nofollow::create_dir(d).map_err(|e| OutputError {
            path: d.clone(),
            message: format!("cannot create: {e}"),
        })?;
    }
    Ok(dir)
}

/// Write a processed session's outputs into `out` (`processed/<settings>/`): images,
/// `settings.json`, then `result.json` last, each staged and renamed into place once all
/// are written. `results.csv` (the flat table: [`crate::results_csv`]) is staged beside
/// `result.json`; `registration` is its column's value (the job's wire name: `commanded`
/// and `interferometer` are `positions` to the pipeline).
pub fn write_outputs(
    out: &Path,
    result: &JobResult,
    images: &[(String, Image16)],
    settings: &Settings,
    registration: Option<&str>,
) -> Result<Vec<PathBuf>, OutputError> {
    let encode = |path: &Path, e: &dyn std::fmt::Display| OutputError {
        path: path.to_path_buf(),
        message: format!("cannot encode: {e}"),
    };
    let mut staged = Vec::new();
    if !images.is_empty() {
        let dir = out.join("images");
        crate::nofollow::create_dir(&dir).map_err(|e| OutputError {
            path: dir.clone(),
            message: format!("cannot create: {e}"),
        })?;
        for (name, img) in images {
            let path = dir.join(format!("{name}.png"));
            let mut png = Vec::new();
            image::DynamicImage::ImageLuma16(img.clone())
                .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                .map_err(|e| encode(&path, &e))?;
            staged.push(atomic_file::stage(&path, &png)?);
        }
    }
    let settings_path = out.join(SETTINGS);
    let bytes = serde_json::to_vec_pretty(settings).map_err(|e| encode(&settings_path, &e))?;
    staged.push(atomic_file::stage(&settings_path, &bytes)?);
    let csv_path = out.join(crate::results_csv::FILE);
    let rows = crate::results_csv::rows(&result.runs, registration);
    staged.push(atomic_file::stage(
        &csv_path,
        &crate::results_csv::to_bytes(&rows),
    )?);
    let result_path = out.join(crate::session::RESULT);
    let bytes = serde_json::to_vec_pretty(result).map_err(|e| encode(&result_path, &e))?;
    staged.push(atomic_file::stage(&result_path, &bytes)?);
    let written = staged
        .into_iter()
        .map(|s| s.commit())
        .collect::<Result<Vec<_>, _>>()?;
    atomic_file::sync_dir(out)?;
    Ok(written)
}
