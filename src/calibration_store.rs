//! The calibrations a daemon keeps in its data root: `<data_root>/calibrations/<id>.json`
//! (the record, as `rigctl calibrate --out` writes it) and `calibrations/current`, a
//! pointer file naming the record jobs apply (`<id>.json`), replaced atomically. Nothing is
//! read through a symlink (`nofollow`), as everywhere under the data root.

use crate::bounds;
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
    bounds::one_component("calibration id", &cal.id).map_err(anyhow::Error::msg)?;
    crate::nofollow::create_dir(&d).with_context(|| format!("{}: cannot create", d.display()))?;
    let name = format!("{}.json", cal.id);
    let path = d.join(&name);
    crate::calibration_file::save(&path, cal)?;
    let pointer = d.join(CURRENT);
    crate::atomic_file::write(&pointer, format!("{name}\n").as_bytes())
        .with_context(|| format!("{}: cannot write", pointer.display()))?;
    Ok(path)
}

/// The longest `current` read: a record's name and a newline.
const MAX_POINTER_BYTES: u64 = 4096;
/// How much of a bad pointer an error quotes.
const QUOTED_CHARS: usize = 64;

/// The current calibration, when `current` names one; an error, naming the file, when the
/// pointer or the record it names cannot be read or is not a calibration record. Both are
/// read bounded (a pointer of at most 4 KiB, a record of [`bounds::MAX_DOCUMENT_BYTES`]), and
/// an error quotes at most the start of a bad pointer.
pub fn current(data_root: &Path) -> anyhow::Result<Option<Applied>> {
    let d = dir(data_root);
    let pointer = d.join(CURRENT);
    let rel = Path::new(DIR).join(CURRENT);
    let bytes = match crate::nofollow::read_in_max(data_root, rel, MAX_POINTER_BYTES) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("{}: cannot read", pointer.display())),
    };
    let text = String::from_utf8_lossy(&bytes);
    let name = text.trim();
    let plain = bounds::one_component("record", name).is_ok();
    if !plain || !name.ends_with(".json") {
        anyhow::bail!(
            "{}: names no calibration record (want `<id>.json`, got {})",
            pointer.display(),
            excerpt(name)
        );
    }
    let path = d.join(name);
    let bytes = crate::nofollow::read_in_max(&d, name, bounds::MAX_DOCUMENT_BYTES)
        .with_context(|| format!("{}: cannot read the calibration", path.display()))?;
    let calibration = crate::calibration_file::parse(&bytes, &path)?;
    Ok(Some(Applied {
        calibration,
        source: path.display().to_string(),
    }))
}

/// `text` quoted, cut to its first [`QUOTED_CHARS`] characters (saying how long it was).
fn excerpt(text: &str) -> String {
    let n = text.chars().count();
    if n <= QUOTED_CHARS {
        return format!("{text:?}");
    }
    let start: String = text.chars().take(QUOTED_CHARS).collect();
    format!("{start:?}… ({n} characters)")
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

    #[test]
    fn a_huge_pointer_is_refused_unread_and_a_long_one_quoted_in_part() {
        let root = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir(root.path())).unwrap();
        let pointer = dir(root.path()).join(CURRENT);
        // 200 MB (sparse: nothing is written).
        std::fs::File::create(&pointer)
            .unwrap()
            .set_len(200 << 20)
            .unwrap();
        let e = format!("{:#}", current(root.path()).unwrap_err());
        assert!(
            e.len() < 400 && e.contains("over the 4096-byte limit"),
            "{e}"
        );
        std::fs::write(&pointer, "y".repeat(3000)).unwrap();
        let e = format!("{:#}", current(root.path()).unwrap_err());
        assert!(e.len() < 400 && e.contains("(3000 characters)"), "{e}");
    }
}
