//! The `rigctl process` folder contract (docs/folder-format.md): `DIR/frames/*.png`
//! (8-bit RGB, in file-name order) and `DIR/steps.csv` with the header `index,position_um`
//! (extra columns allowed), one row per frame, row i for frame i.
//!
//! Outputs go to an output folder through temporary names renamed at the very end, the
//! result file last, so a failed run leaves nothing that looks complete.

use crate::atomic_file;
use crate::pipeline::run::NamedImage;
use crate::pipeline::ProcessResult;
use image::RgbImage;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum FolderError {
    #[error("{path}: {message}")]
    Io { path: PathBuf, message: String },
    #[error("{path}: no frames (*.png)")]
    NoFrames { path: PathBuf },
    #[error("{path}: not a readable PNG: {message}")]
    BadPng { path: PathBuf, message: String },
    #[error("{path}: must be 8-bit RGB, is {found}")]
    NotRgb8 { path: PathBuf, found: String },
    #[error("{path}: header must start with `index,position_um`, found `{found}`")]
    StepsHeader { path: PathBuf, found: String },
    #[error("{path} line {line}: {message}")]
    StepsRow {
        path: PathBuf,
        line: u64,
        message: String,
    },
    #[error("{path}: {rows} rows for {frames} frames: every frame needs its row")]
    StepsCount {
        path: PathBuf,
        rows: usize,
        frames: usize,
    },
}

/// A folder's frames (paths, in processing order) and their positions.
#[derive(Debug, Clone)]
pub struct Folder {
    pub frames: Vec<PathBuf>,
    pub positions_um: Vec<f64>,
}

/// List and check a folder; `limit` keeps the first N frames only. Frames are read later,
/// one at a time ([`load_frame`]).
pub fn open(dir: &Path, limit: Option<usize>) -> Result<Folder, FolderError> {
    let frames_dir = dir.join("frames");
    let rd = std::fs::read_dir(&frames_dir).map_err(|e| FolderError::Io {
        path: frames_dir.clone(),
        message: format!("cannot list the frames folder: {e}"),
    })?;
    let mut frames: Vec<PathBuf> = Vec::new();
    for entry in rd {
        let entry = entry.map_err(|e| FolderError::Io {
            path: frames_dir.clone(),
            message: e.to_string(),
        })?;
        let p = entry.path();
        if p.extension().is_some_and(|x| x.eq_ignore_ascii_case("png")) {
            frames.push(p);
        }
    }
    frames.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    if let Some(n) = limit {
        frames.truncate(n);
    }
    if frames.is_empty() {
        return Err(FolderError::NoFrames { path: frames_dir });
    }
    let steps = dir.join("steps.csv");
    let positions_um = read_steps(&steps)?;
    if positions_um.len() < frames.len() {
        return Err(FolderError::StepsCount {
            path: steps,
            rows: positions_um.len(),
            frames: frames.len(),
        });
    }
    let mut positions_um = positions_um;
    positions_um.truncate(frames.len());
    Ok(Folder {
        frames,
        positions_um,
    })
}

/// Read `steps.csv`: `index,position_um[,...]`, indices 0, 1, 2... in order.
pub fn read_steps(path: &Path) -> Result<Vec<f64>, FolderError> {
    let mut rdr = csv::ReaderBuilder::new()
        .has_headers(true)
        .flexible(false)
        .trim(csv::Trim::All)
        .from_path(path)
        .map_err(|e| FolderError::Io {
            path: path.to_path_buf(),
            message: format!("cannot open: {e}"),
        })?;
    let header = rdr.headers().map_err(|e| FolderError::StepsRow {
        path: path.to_path_buf(),
        line: 1,
        message: e.to_string(),
    })?;
    if header.get(0) != Some("index") || header.get(1) != Some("position_um") {
        return Err(FolderError::StepsHeader {
            path: path.to_path_buf(),
            found: header.iter().collect::<Vec<_>>().join(","),
        });
    }
    let mut out = Vec::new();
    for rec in rdr.records() {
        let rec = rec.map_err(|e| FolderError::StepsRow {
            path: path.to_path_buf(),
            line: e.position().map(|p| p.line()).unwrap_or(0),
            message: e.to_string(),
        })?;
        let line = rec.position().map(|p| p.line()).unwrap_or(0);
        let row_err = |message: String| FolderError::StepsRow {
            path: path.to_path_buf(),
            line,
            message,
        };
        let idx_s = rec.get(0).unwrap_or("");
        let index: usize = idx_s
            .parse()
            .map_err(|_| row_err(format!("index `{idx_s}` is not a whole number")))?;
        if index != out.len() {
            return Err(row_err(format!(
                "index {index} out of order: expected {}",
                out.len()
            )));
        }
        let pos_s = rec.get(1).unwrap_or("");
        let pos: f64 = pos_s
            .parse()
            .ok()
            .filter(|v: &f64| v.is_finite())
            .ok_or_else(|| row_err(format!("position_um `{pos_s}` is not a number")))?;
        out.push(pos);
    }
    Ok(out)
}

/// Read one frame: a PNG holding 8-bit RGB.
pub fn load_frame(path: &Path) -> Result<RgbImage, FolderError> {
    let bytes = std::fs::read(path).map_err(|e| FolderError::Io {
        path: path.to_path_buf(),
        message: format!("cannot read: {e}"),
    })?;
    let img =
        image::load_from_memory_with_format(&bytes, image::ImageFormat::Png).map_err(|e| {
            FolderError::BadPng {
                path: path.to_path_buf(),
                message: e.to_string(),
            }
        })?;
    match img {
        image::DynamicImage::ImageRgb8(rgb) => Ok(rgb),
        other => Err(FolderError::NotRgb8 {
            path: path.to_path_buf(),
            found: format!("{:?}", other.color()),
        }),
    }
}

/// Write the result (`result.json`) and images (`<name>.png`, 16-bit) into `out`:
/// everything to temporary names first, renamed once all are written, the result last.
pub fn write_outputs(
    out: &Path,
    result: &ProcessResult,
    images: &[NamedImage],
) -> Result<Vec<PathBuf>, FolderError> {
    let io = |path: &Path, what: &str, e: &dyn std::fmt::Display| FolderError::Io {
        path: path.to_path_buf(),
        message: format!("{what}: {e}"),
    };
    let atomic = |e: atomic_file::AtomicWriteError| io(&e.path, e.what, &e.source);
    std::fs::create_dir_all(out).map_err(|e| io(out, "cannot create", &e))?;
    // Staged files not committed are removed when `staged` drops.
    let mut staged = Vec::new();
    for img in images {
        let fin = out.join(format!("{}.png", img.name));
        let mut png = Vec::new();
        img.image
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .map_err(|e| io(&fin, "cannot write", &e))?;
        staged.push(atomic_file::stage(&fin, &png).map_err(atomic)?);
    }
    let json = serde_json::to_string_pretty(result).expect("results serialise");
    staged.push(atomic_file::stage(&out.join("result.json"), json.as_bytes()).map_err(atomic)?);
    let written = staged
        .into_iter()
        .map(|s| s.commit().map_err(atomic))
        .collect::<Result<Vec<_>, _>>()?;
    atomic_file::sync_dir(out).map_err(atomic)?;
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn steps(text: &str) -> Result<Vec<f64>, FolderError> {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("steps.csv");
        std::fs::write(&p, text).unwrap();
        read_steps(&p)
    }

    #[test]
    fn steps_with_extra_columns_parse() {
        let v = steps("index,position_um,xl80_um\n0,0,0.4\n1,50,50.2\n2, 100 ,99.1\n").unwrap();
        assert_eq!(v, vec![0.0, 50.0, 100.0]);
    }

    #[test]
    fn bad_steps_name_the_line() {
        let e = steps("index,position_um\n0,0\n1,abc\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("steps.csv line 3") && e.contains("abc"), "{e}");
        let e = steps("index,position_um\n0,0\n2,100\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 3") && e.contains("out of order"), "{e}");
        let e = steps("idx,pos\n0,0\n").unwrap_err().to_string();
        assert!(e.contains("header"), "{e}");
        let e = steps("index,position_um\n0,0\n1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 3"), "{e}");
    }
}
