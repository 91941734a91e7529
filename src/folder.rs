//! The `rigctl process` folder contract (docs/folder-format.md): `DIR/frames/*.png`
//! (8-bit RGB, in file-name order) and `DIR/steps.csv` with the header `index,position_um`
//! (extra columns allowed), one row per frame, row i for frame i.
//!
//! Outputs go to an output folder through temporary names renamed at the very end, the
//! result file last, so a failed run leaves nothing that looks complete.

use crate::atomic_file;
use crate::bounds;
use crate::pipeline::run::NamedImage;
use crate::pipeline::ProcessResult;
use image::RgbImage;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};

#[derive(Debug, thiserror::Error)]
pub enum FolderError {
    #[error("{path}: {message}")]
    Io { path: PathBuf, message: String },
    #[error("{path}: no frames (*.png)")]
    NoFrames { path: PathBuf },
    #[error("{path}: not a readable PNG: {message}")]
    BadPng { path: PathBuf, message: String },
    /// A frame beyond the size limits, or not the size of its run's first frame.
    #[error("{path}: {message}")]
    FrameSize { path: PathBuf, message: String },
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
    /// The piezo's commanded positions, when `steps.csv` has a `piezo_commanded_um` column
    /// with a value in every row (a session of a plan that moved the piezo besides the axis).
    pub piezo_um: Option<Vec<f64>>,
}

/// List and check a folder; `limit` keeps the first N frames only. Frames are read later,
/// one at a time ([`load_frame`]).
pub fn open(dir: &Path, limit: Option<usize>) -> Result<Folder, FolderError> {
    if !dir.is_dir() {
        return Err(FolderError::Io {
            path: dir.to_path_buf(),
            message: match dir.exists() {
                true => "not a folder (give a session, or a folder of frames/*.png and steps.csv)",
                false => "no such folder",
            }
            .into(),
        });
    }
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
    let mut piezo_um = read_piezo(&steps)?;
    if let Some(p) = piezo_um.as_mut() {
        p.truncate(frames.len());
    }
    Ok(Folder {
        frames,
        positions_um,
        piezo_um,
    })
}

/// `steps.csv`'s bytes: a regular file (no symlink at its name, no FIFO or device) of at
/// most [`bounds::MAX_STEPS_BYTES`].
fn steps_bytes(path: &Path) -> Result<std::io::Cursor<Vec<u8>>, FolderError> {
    crate::nofollow::read_regular_max(path, bounds::MAX_STEPS_BYTES)
        .map(std::io::Cursor::new)
        .map_err(|e| FolderError::Io {
            path: path.to_path_buf(),
            message: format!("cannot open: {e}"),
        })
}

/// A position read from `steps.csv`, within [`bounds::MAX_POSITION_UM`].
fn position(v: &str) -> Option<f64> {
    let um = bounds::MAX_POSITION_UM;
    v.parse::<f64>().ok().filter(|v| (-um..=um).contains(v))
}

/// The cells of `steps.csv`'s column `name` with their line numbers, the first `rows` rows
/// (all with `None`); `None` if the file has no such column.
fn column(
    path: &Path,
    name: &str,
    rows: Option<usize>,
) -> Result<Option<Vec<(u64, String)>>, FolderError> {
    let open_err = |e: csv::Error| FolderError::Io {
        path: path.to_path_buf(),
        message: format!("cannot read: {e}"),
    };
    let mut rdr = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .from_reader(steps_bytes(path)?);
    let headers = rdr.headers().map_err(open_err)?;
    let Some(col) = headers.iter().position(|h| h == name) else {
        return Ok(None);
    };
    let mut cells = Vec::new();
    for rec in rdr.records().take(rows.unwrap_or(usize::MAX)) {
        let rec = rec.map_err(open_err)?;
        let line = rec.position().map(|p| p.line()).unwrap_or(0);
        cells.push((line, rec.get(col).unwrap_or("").to_string()));
    }
    Ok(Some(cells))
}

/// The `piezo_commanded_um` column of `steps.csv` (read after [`read_steps`] checked the
/// file): `None` without the column or with it empty in every row (a one-stage scan).
pub fn read_piezo(path: &Path) -> Result<Option<Vec<f64>>, FolderError> {
    let row_err = |line: u64, message: String| FolderError::StepsRow {
        path: path.to_path_buf(),
        line,
        message,
    };
    let Some(cells) = column(path, "piezo_commanded_um", None)? else {
        return Ok(None);
    };
    let mut parsed = Vec::with_capacity(cells.len());
    for (line, v) in cells {
        let x = match v.as_str() {
            "" => None,
            _ => Some(position(&v).ok_or_else(|| {
                row_err(
                    line,
                    format!(
                        "piezo_commanded_um `{v}` is not a position (a number of µm within ±1e9)"
                    ),
                )
            })?),
        };
        parsed.push((line, x));
    }
    if parsed.iter().all(|(_, v)| v.is_none()) {
        return Ok(None);
    }
    parsed
        .into_iter()
        .map(|(line, v)| {
            v.ok_or_else(|| {
                row_err(
                    line,
                    "piezo_commanded_um is empty, and other rows have one".into(),
                )
            })
        })
        .collect::<Result<Vec<f64>, _>>()
        .map(Some)
}

/// The `interferometer_um` column of `steps.csv` (a session's), for the first `frames`
/// rows: registration by the interferometer needs a reading for every frame.
pub fn read_interferometer(path: &Path, frames: usize) -> Result<Vec<f64>, FolderError> {
    let err = |line: u64, message: String| FolderError::StepsRow {
        path: path.to_path_buf(),
        line,
        message,
    };
    let Some(cells) = column(path, "interferometer_um", Some(frames))? else {
        return Err(err(
            1,
            "no interferometer_um column: --registration interferometer needs one".into(),
        ));
    };
    cells
        .into_iter()
        .map(|(line, v)| {
            let x = position(&v);
            x.ok_or_else(|| err(line, format!("interferometer_um `{v}` is not a reading")))
        })
        .collect()
}

/// Read `steps.csv`: `index,position_um[,...]`, indices 0, 1, 2... in order.
pub fn read_steps(path: &Path) -> Result<Vec<f64>, FolderError> {
    let mut rdr = csv::ReaderBuilder::new()
        .has_headers(true)
        .flexible(false)
        .trim(csv::Trim::All)
        .from_reader(steps_bytes(path)?);
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
        let pos = position(pos_s).ok_or_else(|| {
            row_err(format!(
                "position_um `{pos_s}` is not a position (a number of µm within ±1e9)"
            ))
        })?;
        out.push(pos);
    }
    Ok(out)
}

/// Where a frame's PNG is: a path (a `rigctl process` folder), or a path below a folder
/// that is not left through a symlink at any step (a session's frame, read as the daemon
/// reads it: [`crate::nofollow`]).
#[derive(Debug, Clone, PartialEq)]
pub enum FrameFile {
    Path(PathBuf),
    Below { dir: PathBuf, rel: PathBuf },
}

impl FrameFile {
    /// The frame's path, for messages.
    pub fn path(&self) -> PathBuf {
        match self {
            FrameFile::Path(p) => p.clone(),
            FrameFile::Below { dir, rel } => dir.join(rel),
        }
    }

    /// The file's bytes: a regular file (no symlink at its name, no FIFO or device), of at
    /// most [`bounds::MAX_FRAME_BYTES`].
    fn read_into(&self, bytes: &mut Vec<u8>) -> std::io::Result<()> {
        use std::io::Read;
        let f = match self {
            FrameFile::Path(p) => crate::nofollow::open_regular(p)?,
            FrameFile::Below { dir, rel } => {
                crate::nofollow::open_in(dir, rel, crate::nofollow::Access::Read)?
            }
        };
        let max = bounds::MAX_FRAME_BYTES;
        let len = f.metadata()?.len();
        if len > max {
            return Err(std::io::Error::other(format!(
                "{len} bytes, over the {max}-byte limit for a frame"
            )));
        }
        f.take(max + 1).read_to_end(bytes)?;
        if bytes.len() as u64 > max {
            return Err(std::io::Error::other(format!(
                "over the {max}-byte limit for a frame"
            )));
        }
        Ok(())
    }

    /// The frame's size as its PNG header says (read bounded, nothing decoded).
    pub fn size(&self) -> Result<(u32, u32), FolderError> {
        let path = self.path();
        let mut bytes = Vec::new();
        self.read_into(&mut bytes).map_err(|e| FolderError::Io {
            path: path.clone(),
            message: format!("cannot read: {e}"),
        })?;
        let dec = png::Decoder::new(std::io::Cursor::new(&bytes[..]));
        let info = dec.read_info().map_err(|e| FolderError::BadPng {
            path: path.clone(),
            message: e.to_string(),
        })?;
        let (w, h) = info.info().size();
        bounds::frame_size(w, h).map_err(|message| FolderError::FrameSize { path, message })
    }
}

/// Read one frame: a PNG holding 8-bit RGB.
pub fn load_frame(path: &Path) -> Result<RgbImage, FolderError> {
    FrameReader::default().read(path, None)
}

/// Where frame decoders wait, between rows, while another step needs the cores: open
/// unless [`RowGate::close`]d. Closed only for a bounded step of the caller's own (frame
/// 0's detection and fits, a few ms), so a decoder never waits on anything else: unlike a
/// lower priority, it cannot starve when other processes load the machine.
#[derive(Debug, Default)]
pub struct RowGate {
    closed: std::sync::atomic::AtomicBool,
    lock: std::sync::Mutex<()>,
    opened: std::sync::Condvar,
}

impl RowGate {
    /// Decoders stop at their next row until [`RowGate::open`].
    pub fn close(&self) {
        self.closed.store(true, Ordering::Release);
    }

    /// Waiting decoders go on (nothing to do when it is open).
    pub fn open(&self) {
        if !self.closed.load(Ordering::Acquire) {
            return;
        }
        let _held = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        self.closed.store(false, Ordering::Release);
        self.opened.notify_all();
    }

    /// Wait here while the gate is closed (one atomic load when it is open).
    fn pass(&self) {
        if !self.closed.load(Ordering::Acquire) {
            return;
        }
        let mut held = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        while self.closed.load(Ordering::Acquire) {
            held = self.opened.wait(held).unwrap_or_else(|e| e.into_inner());
        }
    }
}

/// Reads frames one after another, reusing its buffers: the file's bytes here, the
/// pixels in the image handed back in (a 1280x720 frame is 2.7 MB: allocating it afresh
/// every frame costs page faults comparable to part of the decoding).
#[derive(Default)]
pub struct FrameReader {
    bytes: Vec<u8>,
    /// The size every frame must have (its run's first frame's), once known.
    expect: Option<(u32, u32)>,
}

impl FrameReader {
    /// A reader that refuses a frame not of `size` (its run's first frame's), when given.
    pub fn expecting(size: Option<(u32, u32)>) -> FrameReader {
        FrameReader {
            bytes: Vec::new(),
            expect: size,
        }
    }

    /// Read the frame at `path`, into `reuse`'s pixel buffer when given.
    pub fn read(&mut self, path: &Path, reuse: Option<RgbImage>) -> Result<RgbImage, FolderError> {
        self.read_rows(path, reuse, u32::MAX).map(|(img, _)| img)
    }

    /// [`FrameReader::read`] decoding only the first `max_rows` rows (PNG rows come in
    /// order: the rest are never inflated); the rows below hold whatever the buffer held.
    /// Returns the image and how many rows are decoded. An interlaced PNG is decoded whole.
    pub fn read_rows(
        &mut self,
        path: &Path,
        reuse: Option<RgbImage>,
        max_rows: u32,
    ) -> Result<(RgbImage, u32), FolderError> {
        self.read_file_rows(&FrameFile::Path(path.to_path_buf()), reuse, max_rows)
    }

    /// [`FrameReader::read_rows`] of a [`FrameFile`].
    pub fn read_file_rows(
        &mut self,
        file: &FrameFile,
        reuse: Option<RgbImage>,
        max_rows: u32,
    ) -> Result<(RgbImage, u32), FolderError> {
        self.read_file_rows_until(file, reuse, &AtomicU32::new(max_rows))
    }

    /// [`FrameReader::read_file_rows`] with a limit that may fall while the frame is being
    /// decoded (another thread learns how many rows it needs): it is read again before every
    /// row, so a frame started before the limit was known still stops there.
    pub fn read_file_rows_until(
        &mut self,
        file: &FrameFile,
        reuse: Option<RgbImage>,
        max_rows: &AtomicU32,
    ) -> Result<(RgbImage, u32), FolderError> {
        self.read_file_rows_gated(file, reuse, max_rows, &RowGate::default())
    }

    /// [`FrameReader::read_file_rows_until`] that waits at a row while `gate` is closed:
    /// the pipeline's one serial step (frame 0's detection) has the cores meanwhile.
    pub fn read_file_rows_gated(
        &mut self,
        file: &FrameFile,
        reuse: Option<RgbImage>,
        max_rows: &AtomicU32,
        gate: &RowGate,
    ) -> Result<(RgbImage, u32), FolderError> {
        let path = &file.path();
        self.bytes.clear();
        file.read_into(&mut self.bytes)
            .map_err(|e| FolderError::Io {
                path: path.to_path_buf(),
                message: format!("cannot read: {e}"),
            })?;
        let bad = |e: png::DecodingError| FolderError::BadPng {
            path: path.to_path_buf(),
            message: e.to_string(),
        };
        let limits = png::Limits {
            bytes: (bounds::MAX_FRAME_PIXELS * 8) as usize,
        };
        let mut dec = png::Decoder::new_with_limits(std::io::Cursor::new(&self.bytes[..]), limits);
        // As `image` decodes: palette and low bit depths expanded to 8 bits.
        dec.set_transformations(png::Transformations::EXPAND);
        let mut reader = dec.read_info().map_err(bad)?;
        let found = match reader.output_color_type() {
            (png::ColorType::Rgb, png::BitDepth::Eight) => None,
            // Named as `image` names them (`is L8`), the message docs/folder-format.md shows.
            (ct, bd) => Some(format!(
                "{}{}",
                match ct {
                    png::ColorType::Grayscale => "L",
                    png::ColorType::GrayscaleAlpha => "La",
                    png::ColorType::Rgb => "Rgb",
                    png::ColorType::Rgba => "Rgba",
                    png::ColorType::Indexed => "Indexed",
                },
                bd as u8
            )),
        };
        if let Some(found) = found {
            return Err(FolderError::NotRgb8 {
                path: path.to_path_buf(),
                found,
            });
        }
        let (w, h) = reader.info().size();
        // Checked before a pixel is allocated: a small file may declare a huge image.
        let sized = bounds::frame_size(w, h).and_then(|s| match self.expect {
            Some((ew, eh)) if (ew, eh) != s => Err(format!(
                "size {w}x{h} px differs from the run's first frame's, {ew}x{eh} px"
            )),
            _ => Ok(s),
        });
        sized.map_err(|message| FolderError::FrameSize {
            path: path.to_path_buf(),
            message,
        })?;
        let len = w as usize * h as usize * 3;
        let mut px = match reuse.map(RgbImage::into_raw) {
            // A reused buffer of the same size is not written here (its pages stay mapped).
            Some(mut px) => {
                px.resize(len, 0);
                px
            }
            // Zeroed pages from the allocator, faulted in as the rows are decoded: not
            // cleared first and then written again.
            None => vec![0; len],
        };
        let rows = if reader.info().interlaced {
            reader.next_frame(&mut px).map_err(bad)?;
            h
        } else {
            let mut done = 0;
            for row in px.chunks_exact_mut(w as usize * 3) {
                gate.pass();
                if done >= max_rows.load(Ordering::Relaxed) {
                    break;
                }
                reader.read_row(row).map_err(bad)?;
                done += 1;
            }
            if done < h {
                // The rows past `done` are never inflated, so check that the rest of the
                // file is whole instead: a truncated or damaged frame is still refused.
                check_chunks(&self.bytes).map_err(|message| FolderError::BadPng {
                    path: path.to_path_buf(),
                    message,
                })?;
            } else {
                reader.finish().map_err(bad)?;
            }
            done
        };
        let img = RgbImage::from_raw(w, h, px).expect("buffer matches the size");
        Ok((img, rows))
    }
}

/// Walk a PNG's chunks checking every CRC and that the stream ends with `IEND`: at about
/// 10 GB/s this catches a truncated file or flipped bits without inflating the image data.
/// (What it cannot catch: compressed data that is invalid yet carries correct CRCs, which
/// only a broken encoder writes.)
fn check_chunks(bytes: &[u8]) -> Result<(), String> {
    let mut at = 8; // past the PNG signature, which the decoder has checked
    loop {
        let Some(head) = bytes.get(at..at + 8) else {
            return Err(format!("truncated: no chunk header at byte {at}"));
        };
        let len = u32::from_be_bytes([head[0], head[1], head[2], head[3]]) as usize;
        let kind = &head[4..8];
        let end = at + 8 + len;
        let Some(crc) = bytes.get(end..end + 4) else {
            return Err(format!(
                "truncated: chunk {} at byte {at} runs past the end of the file",
                String::from_utf8_lossy(kind)
            ));
        };
        let want = u32::from_be_bytes([crc[0], crc[1], crc[2], crc[3]]);
        if crc32fast::hash(&bytes[at + 4..end]) != want {
            return Err(format!(
                "CRC error in chunk {} at byte {at}",
                String::from_utf8_lossy(kind)
            ));
        }
        if kind == b"IEND" {
            return Ok(());
        }
        at = end + 4;
    }
}

/// Write the result (`result.json`, and its flat table `results.csv`) and images
/// (`<name>.png`, 16-bit) into `out`:
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
    // The flat table (docs/sessions.md's results.csv): one run, no case, no repeat.
    let table =
        crate::results_csv::to_bytes(&crate::results_csv::rows_of((0, "", 0), result, None));
    let csv_path = out.join(crate::results_csv::FILE);
    staged.push(atomic_file::stage(&csv_path, &table).map_err(atomic)?);
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
    fn frame_reader_reads_rows_into_a_reused_buffer() {
        let d = tempfile::tempdir().unwrap();
        let img = RgbImage::from_fn(7, 5, |x, y| image::Rgb([x as u8, y as u8, 9]));
        let p = d.path().join("a.png");
        img.save(&p).unwrap();
        let mut r = FrameReader::default();
        let whole = r.read(&p, None).unwrap();
        assert_eq!(whole, img);
        // A buffer of another size is reused; rows past the asked ones keep what it held.
        let junk = RgbImage::from_pixel(5, 7, image::Rgb([200, 200, 200]));
        let (part, rows) = r.read_rows(&p, Some(junk), 2).unwrap();
        assert_eq!((rows, part.dimensions()), (2, (7, 5)));
        assert_eq!(part.get_pixel(3, 1), img.get_pixel(3, 1));
        assert_eq!(part.get_pixel(3, 4), &image::Rgb([200, 200, 200]));
        let grey = d.path().join("g.png");
        image::GrayImage::new(4, 4).save(&grey).unwrap();
        let e = load_frame(&grey).unwrap_err().to_string();
        assert!(e.ends_with("must be 8-bit RGB, is L8"), "{e}");
        std::fs::write(&grey, b"not a png").unwrap();
        let e = r.read(&grey, None).unwrap_err().to_string();
        assert!(e.contains("not a readable PNG"), "{e}");
    }

    #[test]
    fn a_partial_read_still_refuses_a_damaged_or_truncated_file() {
        let d = tempfile::tempdir().unwrap();
        let img = RgbImage::from_fn(64, 48, |x, y| image::Rgb([x as u8, y as u8, (x ^ y) as u8]));
        let p = d.path().join("a.png");
        img.save(&p).unwrap();
        let good = std::fs::read(&p).unwrap();
        let mut r = FrameReader::default();
        assert_eq!(r.read_rows(&p, None, 3).unwrap().1, 3);
        // Cut off near the end: the rows read are intact, the file is not.
        std::fs::write(&p, &good[..good.len() - 20]).unwrap();
        let e = r.read_rows(&p, None, 3).unwrap_err().to_string();
        assert!(e.contains("a.png") && e.contains("truncated"), "{e}");
        // One flipped bit in the last image data, past anything a 3-row decode inflates.
        let mut bad = good.clone();
        let at = bad.len() - 12 - 8;
        bad[at] ^= 0x10;
        std::fs::write(&p, &bad).unwrap();
        let e = r.read_rows(&p, None, 3).unwrap_err().to_string();
        assert!(e.contains("a.png") && e.contains("CRC error"), "{e}");
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
