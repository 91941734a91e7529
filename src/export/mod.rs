//! A session exported to the files labs open: OME-TIFF and OME-Zarr (docs/export.md), with
//! the physical pixel size (the rig's µm/px scale), each plane's positions and time, the
//! channel names (R, G, B) and the session's manifest.
//!
//! Frames are streamed: one is read (through [`crate::nofollow`]: never through a symlink
//! out of the data root), written and dropped before the next, so a session of thousands
//! of frames needs the memory of one. The output is written under a hidden temporary name
//! beside `out` and renamed into place once whole: an `out` that exists is complete.
//!
//! - `planes`: the per-plane table (positions, times) both formats carry;
//! - `ome_xml`: the OME-XML of an OME-TIFF; `tiff`: the OME-TIFF writer;
//! - `zarr`: the OME-Zarr 0.5 (Zarr v3) writer;
//! - `nexus`: the HDF5/NeXus writer (cargo feature `hdf5`: it links the system's libhdf5).

#[cfg(feature = "hdf5")]
pub mod nexus;
pub mod ome_xml;
pub mod planes;
pub mod tiff;
pub mod zarr;

use crate::session::{frame_name, Session, SessionError};
use image::RgbImage;
use std::path::{Path, PathBuf};

pub use planes::Planes;

/// The formats `rigctl export` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// OME-Zarr 0.5 (a Zarr v3 folder): `NAME.ome.zarr`.
    OmeZarr,
    /// OME-TIFF (one file, BigTIFF past 4 GB): `NAME.ome.tif`.
    OmeTiff,
    /// NeXus on HDF5 (NXentry/NXdata, NXinstrument): `NAME.nxs`. Needs a build with the
    /// cargo feature `hdf5`.
    Nexus,
}

impl Format {
    /// The file name extension, as OME's readers expect it.
    pub fn extension(self) -> &'static str {
        match self {
            Format::OmeZarr => "ome.zarr",
            Format::OmeTiff => "ome.tif",
            Format::Nexus => "nxs",
        }
    }
}

/// Whether this build writes NeXus (the cargo feature `hdf5`).
pub const NEXUS_BUILT: bool = cfg!(feature = "hdf5");

#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error(transparent)]
    Session(#[from] SessionError),
    #[error("session {session}: no frames to export ({why})")]
    NoFrames { session: String, why: String },
    #[error("session {session}: frame {index} ({file}): {message}")]
    Frame {
        session: String,
        index: u32,
        file: String,
        message: String,
    },
    #[error("session {session}: {message}")]
    Metadata { session: String, message: String },
    #[error("{path}: already exists (remove it or give another --out)")]
    Exists { path: PathBuf },
    #[error("{path}: {message}")]
    Output { path: PathBuf, message: String },
    #[error(
        "--format nexus: this rigctl was built without the cargo feature `hdf5` (HDF5 needs \
         the system's libhdf5): install libhdf5 (Debian: apt-get install libhdf5-dev), then \
         rigctl with it, from the clone: `cargo install --locked --path . --features hdf5` \
         (docs/export.md)"
    )]
    NoHdf5,
}

impl ExportError {
    pub(crate) fn output(path: &Path, e: impl std::fmt::Display) -> ExportError {
        ExportError::Output {
            path: path.to_path_buf(),
            message: e.to_string(),
        }
    }
}

/// What an export wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    pub out: PathBuf,
    pub frames: usize,
    /// Width, height in pixels.
    pub frame_size: (u32, u32),
    pub scale_um_per_px: f64,
}

/// A session opened for export: its manifest and steps, and its frames one at a time.
pub struct Source {
    pub session: Session,
    pub planes: Planes,
    pub frame_size: (u32, u32),
}

impl Source {
    /// Open the session in `dir` (nothing read through a symlink); its frame size is the
    /// first frame's, which every frame must have.
    pub fn open(dir: &Path) -> Result<Source, ExportError> {
        let session = Session::open(dir)?;
        let name = session.dir.display().to_string();
        let Some(index) = session.steps.first().map(|r| r.index) else {
            return Err(ExportError::NoFrames {
                session: name,
                why: "steps.csv lists none".into(),
            });
        };
        let scale = session.manifest.rig.scale_um_per_px;
        if !(scale.is_finite() && scale > 0.0) {
            return Err(ExportError::Metadata {
                session: name,
                message: format!(
                    "manifest.json rig.scale_um_per_px {scale} is not a positive number"
                ),
            });
        }
        let mut src = Source {
            planes: Planes::from_steps(&session.steps),
            session,
            frame_size: (0, 0),
        };
        let img = src.read_frame(index).map_err(|e| match e {
            ExportError::Frame { message, .. } if message.contains("No such file") => {
                ExportError::NoFrames {
                    session: name.clone(),
                    why: format!(
                        "{} is missing (`rigctl demo` removes frames/ unless --keep)",
                        Path::new("frames").join(frame_name(index)).display()
                    ),
                }
            }
            e => e,
        })?;
        src.frame_size = img.dimensions();
        Ok(src)
    }

    pub fn name(&self) -> &str {
        &self.session.manifest.name
    }

    pub fn scale_um_per_px(&self) -> f64 {
        self.session.manifest.rig.scale_um_per_px
    }

    /// Frame `index` as 8-bit RGB, read without following a symlink.
    pub fn read_frame(&self, index: u32) -> Result<RgbImage, ExportError> {
        let rel = Path::new("frames").join(frame_name(index));
        let bad = |message: String| ExportError::Frame {
            session: self.session.dir.display().to_string(),
            index,
            file: rel.display().to_string(),
            message,
        };
        let max = crate::bounds::MAX_FRAME_BYTES;
        let bytes = crate::nofollow::read_in_max(&self.session.dir, &rel, max)
            .map_err(|e| bad(e.to_string()))?;
        let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
            .map_err(|e| bad(format!("not a readable PNG: {e}")))?
            .into_rgb8();
        if self.frame_size != (0, 0) && img.dimensions() != self.frame_size {
            let (w, h) = img.dimensions();
            let (fw, fh) = self.frame_size;
            return Err(bad(format!(
                "{w}x{h} pixels where the first frame has {fw}x{fh}"
            )));
        }
        Ok(img)
    }

    /// Every frame in steps.csv's order, each with its plane number (0, 1, ...), as planar
    /// bytes (channel, row, column: R then G then B), read and handed to `f` one at a time.
    pub fn for_each_frame(
        &self,
        mut f: impl FnMut(usize, &[u8]) -> Result<(), ExportError>,
    ) -> Result<(), ExportError> {
        let mut planar = Vec::new();
        self.for_each_rgb(|t, img| {
            to_planar(img, &mut planar);
            f(t, &planar)
        })
    }

    /// Every frame in steps.csv's order, each with its plane number, as the PNG's
    /// interleaved RGB (row, column, channel), read and handed to `f` one at a time.
    pub fn for_each_rgb(
        &self,
        mut f: impl FnMut(usize, &RgbImage) -> Result<(), ExportError>,
    ) -> Result<(), ExportError> {
        for (t, &index) in self.planes.index.iter().enumerate() {
            f(t, &self.read_frame(index)?)?;
        }
        Ok(())
    }
}

/// Interleaved RGB into channel planes (R, then G, then B), into `out`'s buffer.
pub fn to_planar(img: &RgbImage, out: &mut Vec<u8>) {
    let n = img.as_raw().len() / 3;
    out.clear();
    out.resize(3 * n, 0);
    let (r, rest) = out.split_at_mut(n);
    let (g, b) = rest.split_at_mut(n);
    for (i, p) in img.as_raw().chunks_exact(3).enumerate() {
        r[i] = p[0];
        g[i] = p[1];
        b[i] = p[2];
    }
}

/// Where `rigctl export` writes by default: `NAME.EXT` in the current folder.
pub fn default_out(session_name: &str, format: Format) -> PathBuf {
    PathBuf::from(format!("{session_name}.{}", format.extension()))
}

/// Export the session in `dir` as `format` to `out`, which must not exist.
pub fn export(dir: &Path, format: Format, out: &Path) -> Result<Summary, ExportError> {
    // Before anything is read: a build without HDF5 says so whatever the session.
    if format == Format::Nexus && !NEXUS_BUILT {
        return Err(ExportError::NoHdf5);
    }
    if std::fs::symlink_metadata(out).is_ok() {
        return Err(ExportError::Exists {
            path: out.to_path_buf(),
        });
    }
    let src = Source::open(dir)?;
    match format {
        Format::OmeTiff => tiff::write(&src, out)?,
        Format::OmeZarr => zarr::write(&src, out)?,
        #[cfg(feature = "hdf5")]
        Format::Nexus => nexus::write(&src, out)?,
        #[cfg(not(feature = "hdf5"))]
        Format::Nexus => return Err(ExportError::NoHdf5),
    }
    Ok(Summary {
        out: out.to_path_buf(),
        frames: src.planes.len(),
        frame_size: src.frame_size,
        scale_um_per_px: src.scale_um_per_px(),
    })
}

/// The hidden temporary beside `out` an export is written to before the rename
/// (`.NAME.partial`); one left by an export that was killed is removed first.
pub(crate) fn partial_path(out: &Path) -> PathBuf {
    let name = out.file_name().and_then(|n| n.to_str()).unwrap_or("export");
    out.with_file_name(format!(".{name}.partial"))
}

/// Put the finished temporary in place: `out` must still not exist (a rename would
/// replace a file, and fail on a folder that is not empty).
pub(crate) fn put_in_place(tmp: &Path, out: &Path) -> Result<(), ExportError> {
    if std::fs::symlink_metadata(out).is_ok() {
        return Err(ExportError::Exists {
            path: out.to_path_buf(),
        });
    }
    std::fs::rename(tmp, out)
        .map_err(|e| ExportError::output(out, format!("cannot rename into place: {e}")))?;
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    crate::atomic_file::sync_dir(parent).map_err(|e| ExportError::output(out, e))
}
