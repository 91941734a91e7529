//! `rigctl export SESSION --format ome-zarr|ome-tiff|nexus [--out PATH]`: a recorded session
//! as OME-Zarr, OME-TIFF or NeXus/HDF5 (the last with the cargo feature `hdf5`), with units, per-plane positions and times (docs/export.md). Runs
//! offline on the session folder: no daemon needed.

use crate::export::{self, Format};
use anyhow::Context;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct ExportArgs {
    /// The session folder (under the data root: `<data root>/YYYYMMDDTHHMMSSZ-jobN`).
    pub session: PathBuf,
    /// The file format to write.
    #[arg(long, value_enum)]
    pub format: Format,
    /// Where to write (must not exist) [default: NAME.ome.zarr, NAME.ome.tif or NAME.nxs here].
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print what was written as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: ExportArgs) -> anyhow::Result<()> {
    let out = match a.out {
        Some(p) => p,
        None => {
            let name = a
                .session
                .file_name()
                .with_context(|| format!("{}: not a session folder", a.session.display()))?;
            export::default_out(&name.to_string_lossy(), a.format)
        }
    };
    let s = export::export(&a.session, a.format, &out)?;
    if a.json {
        let v = serde_json::json!({
            "out": s.out, "frames": s.frames, "frame_size": [s.frame_size.0, s.frame_size.1],
            "scale_um_per_px": s.scale_um_per_px,
        });
        println!("{v}");
    } else {
        println!(
            "{}: {} frames of {}x{} px (3 channels), {} µm/px",
            s.out.display(),
            s.frames,
            s.frame_size.0,
            s.frame_size.1,
            s.scale_um_per_px
        );
    }
    Ok(())
}
