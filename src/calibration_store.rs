//! The calibrations a daemon keeps in its data root: `<data_root>/calibrations/<id>.json`
//! (the record, as `rigctl calibrate --out` writes it) and `calibrations/current`, a
//! pointer file naming the record jobs apply (`<id>.json`), replaced atomically. Nothing is
//! read through a symlink (`nofollow`), as everywhere under the data root.

use crate::calibration::Calibration;
use crate::calibration_file::Applied;
use anyhow::Context;
use std::path::{Path, PathBuf};

/// The folder under the data root.
pub const DIR: &str = "calibrations";
/// The pointer file in it.
pub const CURRENT: &str = "current";

/// `<data_root>/calibrations`.
pub fn dir(data_root: &Path) -> PathBuf {
    data_root.join(DIR)
}

/// Write `cal` as `calibrations/<id>.json`, then point `current` at it (each atomically, in
/// that order: `current` never names a record that is not whole on disk). The record's path.
pub fn save_current(data_root: &Path, cal: &Calibration) -> anyhow::Result<PathBuf> {
    let d = dir(data_root);
    crate::nofollow::create_dir(&d).with_context(|| format!("{}: cannot create", d.display()))?;
    let name = format!("{}.json", cal.id);
    let path = d.join(&name);
    crate::calibration_file::save(&path, cal)?;
    let pointer = d.join(CURRENT);
    crate::atomic_file::write(&pointer, format!("{name}\n").as_bytes())
        .with_context(|| format!("{}: cannot write", pointer.display()))?;
    Ok(path)
}

/// The current calibration, when `current` names one; an error, naming the file, when the
/// pointer or the record it names cannot be read or is not a calibration record.
pub fn current(data_root: &Path) -> anyhow::Result<Option<Applied>> {
    let d = dir(data_root);
    let pointer = d.join(CURRENT);
    let bytes = match crate::nofollow::read_in(data_root, Path::new(DIR).join(CURRENT)) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("{}: cannot read", pointer.display())),
    };
    let name = String::from_utf8(bytes).unwrap_or_default();
    let name = name.trim();
    if name.is_empty() || name.contains('/') || !name.ends_with(".json") || name.starts_with('.') {
        anyhow::bail!(
            "{}: names no calibration record (want `<id>.json`, got {name:?})",
            pointer.display()
        );
    }
    let path = d.join(name);
    let bytes = crate::nofollow::read_in(&d, name)
        .with_context(|| format!("{}: cannot read the calibration", path.display()))?;
    let calibration = crate::calibration_file::parse(&bytes, &path)?;
    Ok(Some(Applied {
        calibration,
        source: path.display().to_string(),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_pointer_is_no_calibration_and_a_bad_pointer_names_itself() {
        let root = tempfile::tempdir().unwrap();
        assert!(current(root.path()).unwrap().is_none());
        std::fs::create_dir(dir(root.path())).unwrap();
        std::fs::write(dir(root.path()).join(CURRENT), "../x.json\n").unwrap();
        let e = format!("{:#}", current(root.path()).unwrap_err());
        assert!(e.contains("calibrations/current"), "{e}");
        std::fs::write(dir(root.path()).join(CURRENT), "cal-1.json\n").unwrap();
        std::fs::write(dir(root.path()).join("cal-1.json"), "{not json").unwrap();
        let e = format!("{:#}", current(root.path()).unwrap_err());
        assert!(
            e.contains("cal-1.json") && e.contains("not a calibration"),
            "{e}"
        );
    }
}
