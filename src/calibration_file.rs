//! A calibration record on disk: JSON (`rigctl calibrate --out FILE`), read back by
//! `rigctl process --calibration FILE`, `rigctl reprocess --calibration FILE`.

use crate::calibration::{Calibration, CALIBRATION_VERSION};
use anyhow::Context;
use std::path::Path;
use std::sync::Arc;

/// Read and check a calibration file: errors name the file.
pub fn load(path: &Path) -> anyhow::Result<Arc<Calibration>> {
    let bytes = std::fs::read(path)
        .with_context(|| format!("{}: cannot read the calibration", path.display()))?;
    parse(&bytes, path)
}

/// Check and decode a calibration record read from `path` (errors name it).
pub fn parse(bytes: &[u8], path: &Path) -> anyhow::Result<Arc<Calibration>> {
    let v: serde_json::Value = serde_json::from_slice(bytes)
        .with_context(|| format!("{}: not a calibration record (JSON)", path.display()))?;
    let version = v.get("version").and_then(|x| x.as_u64());
    if version != Some(CALIBRATION_VERSION as u64) {
        anyhow::bail!(
            "{}: calibration record version {}: this rigd reads version {CALIBRATION_VERSION}",
            path.display(),
            version.map_or("missing".into(), |v| v.to_string())
        );
    }
    let cal: Calibration = serde_json::from_value(v)
        .with_context(|| format!("{}: not a calibration record", path.display()))?;
    Ok(Arc::new(cal))
}

/// Write a calibration as pretty JSON, atomically.
pub fn save(path: &Path, cal: &Calibration) -> anyhow::Result<()> {
    let mut text = serde_json::to_string_pretty(cal)?;
    text.push('\n');
    crate::atomic_file::write(path, text.as_bytes())
        .with_context(|| format!("{}: cannot write the calibration", path.display()))
}

/// A calibration as a run applies it: the record and the file it came from.
#[derive(Debug, Clone)]
pub struct Applied {
    pub calibration: Arc<Calibration>,
    pub source: String,
}

impl Applied {
    /// Read `path` ([`load`]).
    pub fn load(path: &Path) -> anyhow::Result<Applied> {
        Ok(Applied {
            calibration: load(path)?,
            source: path.display().to_string(),
        })
    }

    /// Hand it to a run's pipeline.
    pub fn apply(&self, pipeline: &mut crate::pipeline::Pipeline) {
        pipeline.set_calibration(Some(self.calibration.clone()), Some(self.source.clone()));
    }
}
