//! A calibration fitted from a folder of frames (`frames/*.png` + `steps.csv`): what
//! `rigctl calibrate DIR` does, and what the daemon's calibration job does on the session
//! it has just recorded (a session is such a folder). One code path: every frame measured
//! by [`process_folder`] with the `fit` estimator (k = 1, per-frame centres recorded), the
//! field fitted by `Calibration::fit` (docs/calibration.md).

use crate::board::Board;
use crate::calibration::{Calibration, FitOptions, Reference, Scan};
use crate::folder::{self, FrameFile};
use crate::offline::push::{process_folder, FrameIn};
use crate::pipeline::{Combine, Estimator, Pipeline, ProcessOptions, Registration};
use anyhow::Context;
use std::path::Path;
use std::sync::Arc;

/// How to fit a folder's scan.
#[derive(Debug, Clone)]
pub struct FolderFit {
    /// The global scale the runs it will convert are processed with, µm per px.
    pub scale_um_per_px: f64,
    /// The board: its layout fixes the field's shape and names the targets.
    pub board: Option<Board>,
    /// The length reference: steps.csv's `position_um` or `interferometer_um`.
    pub reference: Reference,
    /// Image displacement per unit of axis travel (a starting guess).
    pub axis_dir: [f64; 2],
    /// Relative standard uncertainty of the reference's scale (None: its default).
    pub reference_rel_u: Option<f64>,
    /// The rig as the caller knows it (None: the frame size, folder and scale).
    pub rig: Option<String>,
    /// The camera's output curve: the scan is measured in linear light.
    pub response: crate::pipeline::Response,
}

/// Measure every frame of `dir` and fit its calibration (twice: `Calibration::fit_twice`);
/// errors name `dir`.
pub fn fit_folder(dir: &Path, fit: &FolderFit) -> anyhow::Result<Calibration> {
    let folder = folder::open(dir, None)?;
    let positions = match fit.reference {
        Reference::Interferometer => {
            folder::read_interferometer(&dir.join("steps.csv"), folder.frames.len())?
        }
        Reference::Commanded => folder.positions_um.clone(),
    };
    let frames: Vec<FrameIn> = folder
        .frames
        .iter()
        .zip(&positions)
        .map(|(p, &x)| FrameIn {
            file: FrameFile::Path(p.clone()),
            position_um: x,
            piezo_um: None,
        })
        .collect();
    let measure = |first: Option<Arc<Calibration>>| -> anyhow::Result<Scan> {
        let done = process_folder(scan_pipeline(fit, first)?, &frames, dir)?;
        Ok(Scan {
            frame_size: (done.result.width, done.result.height),
            scale_um_per_px: fit.scale_um_per_px,
            axis_dir: fit.axis_dir,
            reference: fit.reference,
            positions_um: positions.clone(),
            piezo_um: folder.piezo_um.clone(),
            targets: done.tracks,
            ink_maps: done.ink_maps,
            lateral_colour: done.lateral_colour,
        })
    };
    let first_frame = folder.frames.first().context("a scan has frames")?;
    // Read as every frame is: a regular file, bounded, its header's size within the limits.
    let (w, h) = FrameFile::Path(first_frame.clone()).size()?;
    let rig = fit.rig.clone().unwrap_or_else(|| {
        format!(
            "{w}x{h} frames from {}, {} µm/px given",
            dir.display(),
            fit.scale_um_per_px
        )
    });
    let opts = FitOptions {
        board: fit.board.clone(),
        date: crate::timestamps::rfc3339(std::time::SystemTime::now()),
        rig: Some(rig),
        reference_rel_u: fit.reference_rel_u,
    };
    Calibration::fit_twice(measure, &opts).with_context(|| dir.display().to_string())
}

/// The pipeline a scan's frames are measured with: `fit` at k = 1, per-frame centres and
/// ink recorded; with `first`, each target's circles measured as the ellipses its field
/// images them as (its ink is not taken: the scan maps it).
fn scan_pipeline(fit: &FolderFit, first: Option<Arc<Calibration>>) -> anyhow::Result<Pipeline> {
    let options = ProcessOptions {
        scale_um_per_px: fit.scale_um_per_px,
        k: 1,
        estimator: Estimator::Fit,
        combine: Combine::Mean,
        registration: Registration::Image,
        axis_dir: fit.axis_dir,
        piezo_dir: None,
        whole_frame: false,
        response: fit.response,
        // The print's density moves with the board: displacements do not see it.
        ink_prior: None,
        calibration_ink: false,
    }
    .validate()?;
    let mut pipeline = Pipeline::new(options, fit.board.clone());
    pipeline.keep_images(false);
    pipeline.record_tracks(true);
    pipeline.set_calibration(first, None);
    Ok(pipeline)
}
