//! The push-based pipeline: `new`, `push` each frame with its position, `finish`.
//!
//! Frame 0 is searched for targets ([`detect`]); later frames are not: each target is
//! measured where the displacement of the frame
//! [`PREDICT_LAG`](super::measure::PREDICT_LAG) back and the positions
//! since predict it, on a small window of the measurement plane, which keeps a frame to a
//! few milliseconds while the axis moves ([`Measurer`]: also on the threads that decode
//! frames ahead).
//! Everything a frame contributes is accumulated as it is pushed and the frame is then
//! dropped, so memory does not grow with a run's length: each target's reconstruction
//! window is cut (its displacement is known by then) and added to the target's
//! reconstruction ([`Accumulator`]), or with `combine = mean` its offset to a running mean
//! ([`OffsetMean`]); the whole-frame reconstruction accumulates likewise; the per-step
//! residuals go to a bounded [`StepLog`]. What is kept per run: frame 0's estimates (the
//! registration's reference) and the last few frames' displacements (the predictions).

use super::accumulate::{Accumulator, Method};
use super::detect::{self, Candidate, DetectConfig};
use super::estimate::{self, estimate_from, CentreEstimate, EvenInk, PlaneInk, Start};
use super::lateral::{LateralColourFit, LateralScan};
use super::mean::OffsetMean;
use super::measure::{
    density_in_frame, measure_in_frame, windows_bottom, FrameEstimates, FrameZero, Measurer,
};
use super::options::WINDOW_MARGIN_PX;
use super::plane::{Mix, Plane, Roi};
use super::reconstruct::{self, Fine, View};
use super::register::{self, At, Dirs, StepLog};
use super::*;
use crate::board::Board;
use crate::calibration::{
    Calibration, InkField, InkMap, Radii, TargetTrack, UNCALIBRATED_SCALE_REL_U,
};
use image::RgbImage;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

/// Vertical fine shifts whose row sums a whole-frame reconstruction keeps at once (each an
/// H x kW plane); a fourth flushes the least recently used into the fine sum. A horizontal
/// scan's frames share one to three (the image registration's vertical jitter).
pub const WHOLE_FRAME_OPEN_GROUPS: usize = 3;

/// What one pushed frame gave.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameReport {
    pub index: usize,
    pub targets_found: usize,
    /// Displacement of this frame from the first, measured in the image.
    pub image_shift_px: [f64; 2],
    pub process_ms: f64,
}

/// An image the pipeline made (a reconstruction), 16-bit grey.
pub struct NamedImage {
    /// File stem, e.g. `target-A` or `whole-frame`.
    pub name: String,
    pub image: image::ImageBuffer<image::Luma<u16>, Vec<u16>>,
}

pub struct Finished {
    pub result: ProcessResult,
    pub images: Vec<NamedImage>,
    /// Every target's outer centre in every frame, when asked for
    /// ([`Pipeline::record_tracks`]: a calibration scan); empty otherwise.
    pub tracks: Vec<TargetTrack>,
    /// Every target's ink density over the frames, read off its fits, with the tracks.
    pub ink_maps: Vec<InkMap>,
    /// The lens's lateral colour, measured at the targets over the frames, with the tracks
    /// (`None` without them, or when no channel was measured well enough).
    pub lateral_colour: Option<LateralColourFit>,
}

/// How one target's frames are being combined.
enum Combining {
    /// `combine = mean`: the running mean of its per-frame offsets.
    Mean(OffsetMean),
    /// A reconstruction: its window and the frames accumulated in it.
    Window(TargetWindow),
}

/// Push-based pipeline: `new`, `push` each frame with its position, `finish`.
pub struct Pipeline {
    opts: ValidOptions,
    board: Option<Board>,
    detect_cfg: DetectConfig,
    size: Option<(u32, u32)>,
    mix: Mix,
    targets: Vec<Candidate>,
    skipped: Vec<Skipped>,
    /// `[target]`: what its frames accumulate into, or why it cannot be measured.
    combining: Vec<Result<Combining, String>>,
    /// The whole-frame reconstruction being accumulated (when asked for and kept).
    whole: Option<Accumulator>,
    /// `[target]`: frame 0's estimate, in frame coordinates: the registration's reference.
    first: Vec<Option<CentreEstimate>>,
    frames: usize,
    /// Frame 0's and the last frame's positions (stage, piezo).
    first_position_um: Option<At>,
    last_position_um: Option<At>,
    last_image_shift_px: [f64; 2],
    steps: StepLog,
    /// Whether `finish` hands back the reconstructions as images.
    keep_images: bool,
    /// `[target]`: every frame's offset (any combine mode): the type-A uncertainty.
    scatter: Vec<OffsetMean>,
    /// `[target][frame]`: outer centres, when asked for.
    tracks: Option<Vec<Vec<Option<[f64; 2]>>>>,
    /// `[target]`: the ink density its fits read, with the tracks.
    ink_maps: Option<Vec<InkMap>>,
    /// The channels' shifts against green at the targets, with the tracks.
    lateral: Option<LateralScan>,
    /// The calibration the offsets are converted with, and where it came from.
    calibration: Option<(Arc<Calibration>, Option<String>)>,
    calibration_warnings: Vec<String>,
    /// Where [`Pipeline::rows_needed`] is kept for frame decoders, and its margin.
    rows_shared: Option<(Arc<AtomicU32>, u32)>,
    /// Later frames' measurer, from frame 0 on; and where it is handed to decoders.
    measurer: Option<Measurer>,
    measurer_shared: Option<Arc<OnceLock<Measurer>>>,
}

/// Rows added to the first estimate of [`Pipeline::rows_needed`], made from frame 0's
/// detection before its fits: the reconstruction windows are then placed on the fitted
/// centres and radii, within a pixel or two of the detected ones.
const DETECTION_SLACK_ROWS: u32 = 4;

impl Pipeline {
    /// A pipeline for one run. The options were checked by [`ProcessOptions::validate`]:
    /// nothing about them can fail later.
    pub fn new(opts: ValidOptions, board: Option<Board>) -> Pipeline {
        Pipeline {
            opts,
            board,
            detect_cfg: DetectConfig::default(),
            size: None,
            mix: Mix::channel(1),
            targets: Vec::new(),
            skipped: Vec::new(),
            combining: Vec::new(),
            whole: None,
            first: Vec::new(),
            frames: 0,
            first_position_um: None,
            last_position_um: None,
            last_image_shift_px: [0.0; 2],
            steps: StepLog::default(),
            keep_images: true,
            scatter: Vec::new(),
            tracks: None,
            ink_maps: None,
            calibration: None,
            calibration_warnings: Vec::new(),
            rows_shared: None,
            measurer: None,
            measurer_shared: None,
            lateral: None,
        }
    }

    /// Keep every target's outer centre in every frame and hand them back
    /// (`Finished::tracks`) and each target's ink density read off its fits
    /// (`Finished::ink_maps`): what a calibration is fitted from. Set it before frame 0.
    pub fn record_tracks(&mut self, record: bool) {
        self.tracks = record.then(Vec::new);
        self.ink_maps = record.then(Vec::new);
        self.lateral = record.then(LateralScan::default);
    }

    /// Convert the offsets with `calibration` (its field model, not the global scale) and
    /// take its type-B uncertainty; `source` names where it was read from. Frame 0 checks
    /// it against the frames (`Calibration::check`): another frame size fails the run.
    pub fn set_calibration(
        &mut self,
        calibration: Option<Arc<Calibration>>,
        source: Option<String>,
    ) {
        self.calibration = calibration.map(|c| (c, source));
    }

    /// Whether `finish` hands back the reconstructions as 16-bit images (the default). A
    /// caller that writes no images saves their conversion (tens of megapixels at k = 10),
    /// and with `whole_frame` the whole-frame reconstruction itself. Set it before the
    /// first frame.
    pub fn keep_images(&mut self, keep: bool) {
        self.keep_images = keep;
    }

    /// Keep `cell` at [`Pipeline::rows_needed`]`(margin_rows)` (`u32::MAX` while every row is
    /// needed) as the pipeline learns it: first from frame 0's detection, before its fits,
    /// so that frames decoded meanwhile can stop there too, then after every frame.
    pub fn share_rows_needed(&mut self, cell: Arc<AtomicU32>, margin_rows: u32) {
        self.rows_shared = Some((cell, margin_rows));
        self.publish_rows(0);
    }

    /// Set `cell` to the [`Measurer`] of later frames once frame 0 is in: threads that
    /// decode frames ahead can measure them ([`Pipeline::push_measured`]).
    pub fn share_measurer(&mut self, cell: Arc<OnceLock<Measurer>>) {
        if let Some(m) = &self.measurer {
            let _ = cell.set(m.clone());
        }
        self.measurer_shared = Some(cell);
    }

    fn publish_rows(&self, slack_rows: u32) {
        if let Some((cell, margin)) = &self.rows_shared {
            let rows = self.rows_needed(margin + slack_rows);
            cell.store(rows.unwrap_or(u32::MAX), Ordering::Relaxed);
        }
    }

    /// Frames pushed so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The reconstruction method of a combine mode other than mean.
    fn method(&self) -> Method {
        match self.opts.combine {
            Combine::Splat => Method::Splat,
            _ => Method::Interp,
        }
    }

    /// How the positions move the image (a run on one stage has no piezo move: its
    /// direction does not matter).
    fn dirs(&self) -> Dirs {
        Dirs {
            scale_um_per_px: self.opts.scale_um_per_px,
            axis_dir: self.opts.axis_dir,
            piezo_dir: self.opts.piezo_dir.unwrap_or(self.opts.axis_dir),
        }
    }

    /// The displacement a reconstruction uses for a frame: the image's, or the positions'.
    fn recon_shift_px(&self, at: At, image_shift_px: [f64; 2]) -> [f64; 2] {
        match self.opts.registration {
            Registration::Positions => self
                .dirs()
                .shift_px(at, self.first_position_um.unwrap_or(at)),
            Registration::Image => image_shift_px,
        }
    }

    /// Add this frame's reconstruction window of every target still reconstructable to
    /// the target's reconstruction; the crop is dropped at once. On this thread: ~20 µs a
    /// target, less than waking rayon's threads costs while decoders hold the cores.
    fn add_windows(&mut self, frame: &RgbImage, shift_px: [f64; 2]) {
        let (w, h) = (frame.width() as usize, frame.height() as usize);
        let (mix, k, response) = (self.mix, self.opts.k as usize, self.opts.response);
        // The integer part of the displacement moves the window, the rest is resampled.
        let (cx, cy) = (shift_px[0].round(), shift_px[1].round());
        let fine = reconstruct::fine_shift([shift_px[0] - cx, shift_px[1] - cy], k);
        self.combining.iter_mut().for_each(|c| {
            let Ok(Combining::Window(tw)) = c else { return };
            let (rx, ry) = (tw.x0 + cx, tw.y0 + cy);
            let side = tw.side as usize;
            if rx < 0.0 || ry < 0.0 || rx as usize + side > w || ry as usize + side > h {
                *c = Err(format!(
                    "its window ({rx}, {ry}, {side}x{side} px) leaves the frame during the scan"
                ));
                return;
            }
            let roi = Roi {
                x: rx as u32,
                y: ry as u32,
                w: tw.side,
                h: tw.side,
            };
            let crop = Plane::from_mix_roi_in(frame, mix, roi, response);
            tw.acc
                .add(View::new(&crop.data, crop.width, crop.height), fine);
        });
    }

    /// Frame 0: what each target's frames will accumulate into.
    fn start_combining(&mut self, est: &[Option<CentreEstimate>]) {
        let (method, k) = (self.method(), self.opts.k as usize);
        let mean = self.opts.combine == Combine::Mean;
        self.combining = self
            .targets
            .iter()
            .zip(est)
            .map(|(c, e)| {
                let first = e.as_ref().ok_or("not measurable in frame 0")?;
                if mean {
                    return Ok(Combining::Mean(OffsetMean::default()));
                }
                let reach = first.outer_radius_px.max(c.outer_radii_px[1]) + WINDOW_MARGIN_PX;
                let side = (2.0 * reach).ceil() as u32 + 1;
                // Shifts under half a pixel: at most k + 2 vertical fine shifts, none flushed.
                let s = side as usize;
                let origin = first.outer_px.map(|p| (p - reach).floor());
                let mut acc = Accumulator::new(method, s, s, k, k + 2);
                // Nobody looks at the reconstruction: compute only what the estimator reads.
                let guess = fine_guess(first, c, origin, k, s);
                let read = estimate::lattice_read(self.opts.estimator, &guess, k as f64);
                if let Some(l) = read.filter(|_| !self.keep_images && method == Method::Interp) {
                    acc = acc.only_at(l);
                }
                Ok(Combining::Window(TargetWindow {
                    x0: origin[0],
                    y0: origin[1],
                    side,
                    acc,
                }))
            })
            .collect();
        if self.opts.whole_frame && self.keep_images {
            let (w, h) = self.size.expect("frame 0's size is known");
            let (w, h) = (w as usize, h as usize);
            self.whole = Some(Accumulator::new(method, w, h, k, WHOLE_FRAME_OPEN_GROUPS));
        }
    }

    pub fn push(
        &mut self,
        frame: &RgbImage,
        position_um: f64,
    ) -> Result<FrameReport, PipelineError> {
        self.push_at(frame, position_um, None)
    }

    /// [`Pipeline::push`] for a run that moves the piezo besides its stage (`piezo_um`, in
    /// the direction of the options' `piezo_dir`): a 2-D grid or a list of positions.
    pub fn push_at(
        &mut self,
        frame: &RgbImage,
        position_um: f64,
        piezo_um: Option<f64>,
    ) -> Result<FrameReport, PipelineError> {
        let rows = frame.height();
        self.push_rows_at(frame, rows, position_um, piezo_um)
            .map(|r| r.expect("a whole frame has every row"))
    }

    /// How many leading rows of the next frame [`Pipeline::push_rows`] will read, if the
    /// frame moves at most `margin_rows` further down than the last one; `None` when it
    /// needs every row (no frame pushed yet, or a whole-frame reconstruction). A reader can
    /// stop decoding there: PNG rows come in order, so the rest is never inflated.
    pub fn rows_needed(&self, margin_rows: u32) -> Option<u32> {
        let (_, h) = self.size?;
        if self.opts.whole_frame {
            return None;
        }
        let mut shifts = vec![self.last_image_shift_px];
        if let Some(p) = self.last_position_um {
            shifts.push(self.recon_shift_px(p, shifts[0]));
        }
        let bottom = shifts
            .iter()
            .map(|&d| self.rows_read(d, Some(d)))
            .fold(0.0, f64::max);
        Some(((bottom.max(0.0) as u32).saturating_add(margin_rows)).min(h))
    }

    /// The last row (exclusive) a frame's windows reach: the measurement windows at
    /// `measure_px`, the reconstruction windows (if given) at `recon_px`.
    fn rows_read(&self, measure_px: [f64; 2], recon_px: Option<[f64; 2]>) -> f64 {
        let h = self.size.map_or(f64::INFINITY, |(_, h)| h as f64);
        let measured = windows_bottom(&self.targets, measure_px, h);
        let kept = recon_px.into_iter().flat_map(|d| {
            self.combining.iter().filter_map(move |c| match c {
                Ok(Combining::Window(w)) => Some(w.y0 + d[1].round() + w.side as f64),
                _ => None,
            })
        });
        kept.fold(measured, f64::max)
    }

    /// [`Pipeline::push`] for a frame of which only the first `valid_rows` rows are decoded.
    /// `Ok(None)` (and the pipeline unchanged) when it would read past them: push the whole
    /// frame then. Frame 0 and whole-frame runs always need the whole frame.
    pub fn push_rows(
        &mut self,
        frame: &RgbImage,
        valid_rows: u32,
        position_um: f64,
    ) -> Result<Option<FrameReport>, PipelineError> {
        self.push_rows_at(frame, valid_rows, position_um, None)
    }

    /// [`Pipeline::push_rows`] with the piezo's position ([`Pipeline::push_at`]).
    pub fn push_rows_at(
        &mut self,
        frame: &RgbImage,
        valid_rows: u32,
        position_um: f64,
        piezo_um: Option<f64>,
    ) -> Result<Option<FrameReport>, PipelineError> {
        self.push_measured(frame, valid_rows, (position_um, piezo_um), None)
    }

    /// [`Pipeline::push_rows_at`] of a frame whose targets may have been measured already
    /// by [`Measurer::measure`] (on a decoder's thread: [`Pipeline::share_measurer`]): those
    /// estimates are used when they are this frame's at this prediction, else the frame is
    /// measured here.
    pub fn push_measured(
        &mut self,
        frame: &RgbImage,
        valid_rows: u32,
        (position_um, piezo_um): (f64, Option<f64>),
        pre: Option<FrameEstimates>,
    ) -> Result<Option<FrameReport>, PipelineError> {
        let t0 = Instant::now();
        let partial = valid_rows < frame.height();
        if partial && (self.size.is_none() || self.opts.whole_frame) {
            return Ok(None);
        }
        let index = self.frames;
        if let Some(p) = [Some(position_um), piezo_um]
            .into_iter()
            .flatten()
            .find(|p| !p.is_finite())
        {
            return Err(PipelineError::Other(format!(
                "frame {index}: position {p} µm is not a number"
            )));
        }
        let at: At = [position_um, piezo_um.unwrap_or(0.0)];
        match self.size {
            None => self.detect_frame_zero(frame)?,
            Some(want) if want != frame.dimensions() => {
                let got = frame.dimensions();
                return Err(PipelineError::FrameSize { index, got, want });
            }
            Some(_) => {}
        }
        let predicted = self.predicted(index, at);
        if partial && self.rows_read(predicted, None) > valid_rows as f64 {
            return Ok(None);
        }
        let est = match (&self.measurer, pre) {
            // Measured ahead by a decoder: the same function of the same inputs.
            (_, Some(p)) if p.index == index && p.at == at && p.predicted_px == predicted => p.est,
            (Some(m), _) => m.targets_at(frame, predicted, true),
            (None, _) => self.frame_zero_estimates(frame),
        };
        let found = est.iter().filter(|e| e.is_some()).count();
        let shift = self.image_shift_px(index, &est)?;
        let recon_px = self.recon_shift_px(at, shift);
        if partial && self.rows_read(predicted, Some(recon_px)) > valid_rows as f64 {
            return Ok(None);
        }
        self.accumulate(frame, &est, recon_px);
        self.observe(&est);
        self.read_ink(frame, &est);
        self.read_lateral(frame, &est);
        self.record(index, at, shift, piezo_um.is_some(), est);
        Ok(Some(FrameReport {
            index,
            targets_found: found,
            image_shift_px: shift,
            process_ms: t0.elapsed().as_secs_f64() * 1e3,
        }))
    }

    /// Frame 0: find the targets (and name those of the board in view that were not
    /// found), fix the frame size and the measurement plane.
    fn detect_frame_zero(&mut self, frame: &RgbImage) -> Result<(), PipelineError> {
        let got = frame.dimensions();
        let det = detect::detect(frame, &self.detect_cfg);
        if det.targets.is_empty() {
            return Err(PipelineError::NoTarget { index: 0 });
        }
        self.mix = detect::measurement_mix(frame, &det);
        let mut skipped = det.skipped;
        if let Some(board) = &self.board {
            // A board target in view that detection neither found nor reported.
            let found: Vec<[f64; 2]> = det.targets.iter().map(|t| t.outer_centre_px).collect();
            let reported: Vec<[f64; 2]> = skipped.iter().map(|s| s.centre_px).collect();
            let scale = self.opts.scale_um_per_px;
            let unseen = super::layout::unseen_targets(&found, &reported, board, scale, got);
            skipped.extend(unseen);
        }
        self.check_calibration(got)?;
        self.targets = det.targets;
        if let Some((cal, _)) = &self.calibration {
            // The channels registered onto green for the lens's lateral colour.
            self.mix = self.mix.registered(cal.lateral_colour.map(|l| l.model));
            // The fit measures each target's circles as the ellipses they image as.
            for c in &mut self.targets {
                c.rectify = cal.rectify_at(c.outer_centre_px);
            }
        }
        self.skipped = skipped;
        self.size = Some(got);
        self.publish_rows(DETECTION_SLACK_ROWS);
        Ok(())
    }

    /// Frame 0's targets measured where detection found them, from its guesses.
    fn frame_zero_estimates(&self, frame: &RgbImage) -> Vec<Option<CentreEstimate>> {
        let how = (self.mix, self.opts.response);
        let inks = self.frames_inks();
        (self.targets.par_iter().enumerate())
            .map(|(t, c)| {
                let fit = (self.opts.estimator, inks[t].clone());
                measure_in_frame(frame, how, (c, None), [0.0; 2], fit)
            })
            .collect()
    }

    /// Each target's prior for the frames' own fits: only when they are the results
    /// (`combine = mean`). Otherwise they register the frames against frame 0, all with one
    /// model.
    fn frames_inks(&self) -> Vec<Option<PlaneInk>> {
        (0..self.targets.len())
            .map(|t| self.ink_in(t, 1.0))
            .map(|i| i.filter(|_| self.opts.combine == Combine::Mean))
            .collect()
    }

    /// The print's density statistics the fit takes: the options', else (unless they say
    /// not to) those the calibration learnt, when it found the print uneven.
    fn ink_prior(&self) -> Option<InkPrior> {
        self.opts.ink_prior.or_else(|| self.calibration_ink())
    }

    /// The calibration's learnt statistics, when they are the ones taken.
    fn calibration_ink(&self) -> Option<InkPrior> {
        let (cal, _) = self.calibration.as_ref()?;
        let taken = self.opts.calibration_ink && self.opts.ink_prior.is_none();
        cal.ink.as_ref().filter(|_| taken)?.prior()
    }

    /// Target `t`'s density prior in the pixels of a plane `k` times finer than the
    /// camera's: centred on the density the calibration mapped on it, when it did (and the
    /// statistics are the calibration's).
    fn ink_in(&self, t: usize, k: f64) -> Option<PlaneInk> {
        let p = self.ink_prior()?;
        let px_per_um = k / self.opts.scale_um_per_px;
        let mapped = self.ink_field_taken(t);
        Some(PlaneInk {
            density_rms: mapped.map_or(p.density_rms, |f| f.residual_rms),
            corr_px: p.corr_um * px_per_um,
            mean: mapped.map(|f| Arc::new(f.in_plane(px_per_um))),
        })
    }

    /// The calibration's map of target `t`'s ink, when the calibration's statistics are the
    /// prior taken: the map whose scan track passes through the target's place in frame 0.
    fn ink_field_taken(&self, t: usize) -> Option<&InkField> {
        self.calibration_ink()?;
        let (cal, _) = self.calibration.as_ref()?;
        let c = self.targets.get(t)?;
        cal.ink_field_at(c.outer_centre_px, c.outer_radii_px[1])
    }

    /// Where frame `index` at `at` should be ([`Measurer::predicted`]); frame 0 where it is.
    fn predicted(&self, index: usize, at: At) -> [f64; 2] {
        self.measurer.as_ref().map_or([0.0; 2], |m| {
            m.predicted(index, at)
                .expect("every frame before this one is recorded")
        })
    }

    /// Frame `index`'s displacement from frame 0, measured on the targets found in both.
    fn image_shift_px(
        &self,
        index: usize,
        est: &[Option<CentreEstimate>],
    ) -> Result<[f64; 2], PipelineError> {
        let found = est.iter().any(|e| e.is_some());
        if index == 0 {
            return if found {
                Ok([0.0; 2])
            } else {
                Err(PipelineError::NoTarget { index })
            };
        }
        let pairs: Vec<([f64; 2], [f64; 2])> = self
            .first
            .iter()
            .zip(est)
            .filter_map(|(a, b)| Some((a.as_ref()?.outer_px, b.as_ref()?.outer_px)))
            .collect();
        register::image_shift_px(&pairs).ok_or(PipelineError::NoTarget { index })
    }

    /// Frame `index` is in: its step's residual, the registration's record of it (frame 0
    /// makes the [`Measurer`] later frames are measured with).
    fn record(
        &mut self,
        index: usize,
        at: At,
        shift: [f64; 2],
        piezo: bool,
        est: Vec<Option<CentreEstimate>>,
    ) {
        let p0 = *self.first_position_um.get_or_insert(at);
        let residual = register::residual_at(index, (at, p0), shift, &self.dirs(), piezo);
        self.steps.push(residual);
        if index == 0 {
            self.first = est;
            self.start_measuring(at);
        } else if let Some(m) = &self.measurer {
            m.record(index, shift, at);
        }
        self.frames += 1;
        self.last_position_um = Some(at);
        self.last_image_shift_px = shift;
        self.publish_rows(0);
    }

    /// After frame 0: the measurer of later frames, from frame 0's fits (with the even-ink
    /// model where a reconstruction measures the target: see `Seed::even_ink`), shared
    /// with whoever asked ([`Pipeline::share_measurer`]).
    fn start_measuring(&mut self, at: At) {
        let seeds = self
            .first
            .iter()
            .map(|e| {
                let seed = e.as_ref()?.seed?;
                Some(match self.opts.combine {
                    Combine::Mean => seed,
                    _ => seed.even_ink(),
                })
            })
            .collect();
        let m = Measurer::new(FrameZero {
            size: self.size.expect("frame 0 detected"),
            mix: self.mix,
            response: self.opts.response,
            estimator: self.opts.estimator,
            inks: self.frames_inks(),
            registration: self.opts.registration,
            dirs: self.dirs(),
            targets: &self.targets,
            seeds,
            at,
        });
        if let Some(cell) = &self.measurer_shared {
            let _ = cell.set(m.clone());
        }
        self.measurer = Some(m);
    }

    /// Each target's offset into its scatter, its centre into its track.
    fn observe(&mut self, est: &[Option<CentreEstimate>]) {
        if self.scatter.is_empty() {
            self.scatter = vec![OffsetMean::default(); est.len()];
        }
        for (m, e) in self.scatter.iter_mut().zip(est) {
            if let Some(e) = e {
                m.add(e);
            }
        }
        if let Some(tracks) = self.tracks.as_mut() {
            tracks.resize(est.len(), Vec::new());
            for (t, e) in tracks.iter_mut().zip(est) {
                t.push(e.as_ref().map(|e| e.outer_px));
            }
        }
    }

    /// A calibration scan's frame: each target's ink density, read off its fit, into its
    /// map (what the print's statistics are learnt from: `calibration::ink`).
    fn read_ink(&mut self, frame: &RgbImage, est: &[Option<CentreEstimate>]) {
        let Some(maps) = self.ink_maps.as_mut() else {
            return;
        };
        maps.resize_with(est.len(), InkMap::default);
        let how = (self.mix, self.opts.response);
        let read: Vec<_> = self
            .targets
            .par_iter()
            .zip(est)
            .map(|(c, e)| density_in_frame(frame, how, c, e.as_ref()?))
            .collect();
        for (map, r) in maps.iter_mut().zip(read) {
            if let Some((samples, blur_px)) = r {
                map.add(&samples, blur_px);
            }
        }
    }

    /// A calibration scan's frame: each measured target's red and blue images against its
    /// green one (the lens's lateral colour: `lateral`).
    fn read_lateral(&mut self, frame: &RgbImage, est: &[Option<CentreEstimate>]) {
        let Some(lateral) = self.lateral.as_mut() else {
            return;
        };
        let at: Vec<_> = (est.iter().flatten())
            .map(|e| (e.outer_px, e.outer_radius_px))
            .collect();
        lateral.add_frame(frame, self.opts.response.table(), &at);
    }

    /// Add the frame to what its targets (and the whole frame) accumulate.
    fn accumulate(&mut self, frame: &RgbImage, est: &[Option<CentreEstimate>], recon_px: [f64; 2]) {
        if self.frames == 0 {
            self.start_combining(est);
        }
        if self.opts.combine == Combine::Mean {
            for (c, e) in self.combining.iter_mut().zip(est) {
                if let (Ok(Combining::Mean(m)), Some(e)) = (c, e) {
                    m.add(e);
                }
            }
        } else {
            self.add_windows(frame, recon_px);
        }
        if let Some(whole) = self.whole.as_mut() {
            let plane = Plane::from_mix_in(frame, self.mix, self.opts.response);
            let fine = reconstruct::fine_shift(recon_px, self.opts.k as usize);
            whole.add(View::new(&plane.data, plane.width, plane.height), fine);
        }
    }

    pub fn finish(mut self) -> Result<Finished, PipelineError> {
        let n = self.frames;
        let (width, height) = self.size.ok_or(PipelineError::NoFrames)?;
        let (steps, step_summary) = std::mem::take(&mut self.steps).finish();
        let k = match self.opts.combine {
            Combine::Mean => 1,
            _ => self.opts.k as usize,
        };
        let mut skipped = self.skipped.clone();
        let mut images = Vec::new();
        let combining = std::mem::take(&mut self.combining);
        // Reconstructions nobody keeps hand their memory on (a few buffers, not one each).
        let spare = Mutex::new(Vec::new());
        let measured: Vec<Result<Measured, String>> = combining
            .into_par_iter()
            .enumerate()
            .map(|(t, c)| self.measure_target(t, c?, k, &spare))
            .collect();
        let mut objects = Vec::new();
        let mut uncertain = Vec::new();
        for (t, m) in measured.into_iter().enumerate() {
            match m {
                Ok((o, fine, u)) => {
                    if let Some(f) = fine.filter(|_| self.keep_images) {
                        images.push((objects.len(), f));
                    }
                    objects.push(o);
                    uncertain.push(u);
                }
                Err(reason) => skipped.push(Skipped {
                    centre_px: self.targets[t].outer_centre_px,
                    reason,
                }),
            }
        }
        if objects.is_empty() {
            return Err(PipelineError::Other(format!(
                "no target could be measured ({} found in frame 0: {})",
                self.targets.len(),
                skipped
                    .iter()
                    .map(|s| s.reason.as_str())
                    .collect::<Vec<_>>()
                    .join("; ")
            )));
        }
        if let Some(board) = &self.board {
            name_objects(&mut objects, board, self.opts.scale_um_per_px);
        }
        self.convert_objects(&mut objects, &uncertain);
        let tracks = self.take_tracks();
        let ink_maps = self.ink_maps.take().unwrap_or_default();
        let lateral_colour = self.lateral.take().and_then(|l| l.finish());
        let mut named: Vec<NamedImage> = images
            .into_iter()
            .map(|(i, f)| NamedImage {
                name: match &objects[i].name {
                    Some(name) => format!("target-{name}"),
                    None => format!("target-{i:02}"),
                },
                image: f.to_png16(),
            })
            .collect();
        if let Some(whole) = self.whole.take().filter(|_| self.keep_images) {
            named.push(NamedImage {
                name: "whole-frame".into(),
                image: whole.finish().to_png16(),
            });
        }
        Ok(Finished {
            result: ProcessResult {
                options: self.opts.clone().into_inner(),
                frames: n,
                width,
                height,
                objects,
                skipped,
                steps,
                step_summary,
                calibration: self.calibration_used(),
            },
            images: named,
            tracks,
            ink_maps,
            lateral_colour,
        })
    }

    /// Frame 0: whether the calibration fits these frames (its warnings kept).
    fn check_calibration(&mut self, frame_size: (u32, u32)) -> Result<(), PipelineError> {
        if let Some((cal, _)) = &self.calibration {
            let board = self.board.as_ref().map(|b| b.name.as_str());
            self.calibration_warnings = cal.check(frame_size, self.opts.scale_um_per_px, board)?;
        }
        Ok(())
    }

    /// The calibration the result names.
    fn calibration_used(&self) -> Option<CalibrationUsed> {
        self.calibration
            .as_ref()
            .map(|(c, source)| CalibrationUsed {
                id: c.id.clone(),
                date: c.date.clone(),
                method: c.method,
                source: source.clone(),
                warnings: self.calibration_warnings.clone(),
                ink_prior: self.calibration_ink(),
                ink_maps: self.ink_maps_taken(),
            })
    }

    /// How many targets' priors are centred on the calibration's map of their ink.
    fn ink_maps_taken(&self) -> usize {
        (0..self.targets.len())
            .filter(|&t| self.ink_field_taken(t).is_some())
            .count()
    }

    /// The recorded tracks, named by the board as the objects are.
    fn take_tracks(&mut self) -> Vec<TargetTrack> {
        let Some(tracks) = self.tracks.take() else {
            return Vec::new();
        };
        let centres: Vec<[f64; 2]> = self.targets.iter().map(|c| c.outer_centre_px).collect();
        let names = match &self.board {
            Some(b) => super::layout::name_targets(&centres, b, self.opts.scale_um_per_px),
            None => vec![None; centres.len()],
        };
        tracks
            .into_iter()
            .zip(names)
            .zip(&self.first)
            .map(|((centres_px, name), first)| TargetTrack {
                name,
                centres_px,
                outer_radius_px: first.as_ref().map_or(f64::NAN, |e| e.outer_radius_px),
                inner_radius_px: first.as_ref().map_or(f64::NAN, |e| e.inner_radius_px),
            })
            .collect()
    }

    /// Each object's offset in µm (through the calibration when there is one) and its
    /// uncertainty: type A from the frames, type B from the calibration or the global
    /// scale's assumed uncertainty, and from the ink model.
    fn convert_objects(&self, objects: &mut [ObjectResult], uncertain: &[Uncertain]) {
        let s = self.opts.scale_um_per_px;
        for (o, u) in objects.iter_mut().zip(uncertain) {
            let a = &u.type_a_px;
            let (m, u_b) = match &self.calibration {
                Some((cal, _)) => {
                    let c = cal.convert(o.centre_px, o.offset_px, self.radii(o));
                    o.offset_global_um = Some(o.offset_um);
                    o.offset_um = c.offset_um;
                    (c.um_per_px, c.u_b_um)
                }
                None => {
                    let len = o.offset_um[0].hypot(o.offset_um[1]);
                    ([[s, 0.0], [0.0, s]], [UNCALIBRATED_SCALE_REL_U * len; 2])
                }
            };
            let through = |q: [f64; 2]| -> [f64; 2] {
                std::array::from_fn(|i| (m[i][0] * q[0]).hypot(m[i][1] * q[1]))
            };
            o.u_a_um = a.map(through);
            // σ in the offset's own scale: the calibration's local one when it converted.
            o.sigma_um = o.sigma_um.map(|q| through([q[0] / s, q[1] / s]));
            // The ink's: a length in any direction, through the local scale of each axis.
            o.u_ink_um = u
                .ink_px
                .map(|d| std::array::from_fn(|i| d * m[i][0].hypot(m[i][1])));
            let ink = o.u_ink_um.unwrap_or([0.0; 2]);
            let u_b = [u_b[0].hypot(ink[0]), u_b[1].hypot(ink[1])];
            o.u_b_um = Some(u_b);
            o.u_um = o.u_a_um.map(|a| [a[0].hypot(u_b[0]), a[1].hypot(u_b[1])]);
        }
    }

    /// The object's circles on the board: the board's shapes when it is named, else its
    /// measured rims at the global scale.
    fn radii(&self, o: &ObjectResult) -> Radii {
        let named = o
            .name
            .as_deref()
            .and_then(|n| self.board.as_ref()?.target(n));
        match named {
            Some(t) => Radii {
                outer_um: t.outer.edges_um(),
                inner_um: t.inner.edges_um(),
            },
            None => {
                let s = self.opts.scale_um_per_px;
                Radii {
                    outer_um: [o.outer_radius_px * s; 2],
                    inner_um: [o.inner_radius_px * s; 2],
                }
            }
        }
    }

    /// One target's result with the chosen combine mode (and its reconstruction, if any).
    fn measure_target(
        &self,
        t: usize,
        combining: Combining,
        k: usize,
        spare: &Spare,
    ) -> Result<Measured, String> {
        let s = self.opts.scale_um_per_px;
        let first = self.first[t].as_ref().ok_or("not measurable in frame 0")?;
        let (est, sigma_px, frames, fine) = match combining {
            Combining::Mean(m) => {
                let (offset, sigma) = m.result();
                let mut e = first.clone();
                e.inner_px = [e.outer_px[0] + offset[0], e.outer_px[1] + offset[1]];
                (e, sigma, m.frames(), None)
            }
            Combining::Window(tw) => {
                let (e, fine) = self.reconstruct_target(t, tw, k, spare)?;
                let sigma = e
                    .offset_cov_px2
                    .map(|c| [c[0][0].max(0.0).sqrt(), c[1][1].max(0.0).sqrt()]);
                (e, sigma, self.frames, fine)
            }
        };
        let off = est.offset_px();
        let type_a = type_a_px(self.scatter.get(t), &est, sigma_px);
        Ok((
            ObjectResult {
                name: None,
                centre_px: est.outer_px,
                offset_px: off,
                offset_um: [off[0] * s, off[1] * s],
                sigma_um: sigma_px.map(|q| [q[0] * s, q[1] * s]),
                nominal_um: None,
                outer_radius_px: est.outer_radius_px,
                inner_radius_px: est.inner_radius_px,
                frames,
                effective_pixel_um: s / k as f64,
                ..ObjectResult::default()
            },
            fine,
            Uncertain {
                type_a_px: type_a,
                ink_px: ink_model_px(&est),
            },
        ))
    }

    /// The target's window, reconstructed on the k-times finer grid and measured there.
    /// The estimate comes back in camera pixels of frame 0, with the reconstruction when
    /// images are kept (else its memory goes back to `spare`).
    fn reconstruct_target(
        &self,
        t: usize,
        tw: TargetWindow,
        k: usize,
        spare: &Spare,
    ) -> Result<(CentreEstimate, Option<Fine>), String> {
        let first = self.first[t].as_ref().ok_or("not measurable in frame 0")?;
        let c = &self.targets[t];
        let (x0, y0) = (tw.x0, tw.y0);
        let buf = spare.lock().ok().and_then(|mut s| s.pop());
        let fine = tw.acc.finish_in(buf.unwrap_or_default());
        let (fine_w, fine_h) = (fine.width, fine.height);
        let plane = Plane {
            width: fine.width,
            height: fine.height,
            data: fine.data,
        };
        let kf = k as f64;
        let to_fine = to_fine_grid([x0, y0], kf);
        let guess = fine_guess(first, c, [x0, y0], k, tw.side as usize);
        let seed = first.seed.map(|s| s.mapped(to_fine, kf));
        let start = seed.as_ref().map_or(Start::Guess, Start::Near);
        let e = estimate_from(
            &plane,
            &guess,
            self.opts.estimator,
            kf,
            start,
            self.ink_in(t, kf),
        );
        if !self.keep_images {
            if let Ok(mut s) = spare.lock() {
                s.push(plane.data);
            }
            let e = e.map_err(|e| format!("on its reconstruction: {e}"))?;
            return Ok((in_frame(&e, [x0, y0], kf), None));
        }
        let e = e.map_err(|e| format!("on its reconstruction: {e}"))?;
        let fine = Fine {
            width: fine_w,
            height: fine_h,
            k,
            data: plane.data,
        };
        Ok((in_frame(&e, [x0, y0], kf), Some(fine)))
    }
}

/// Buffers of reconstructions already measured, for the next ones.
type Spare = Mutex<Vec<Vec<f32>>>;

/// An estimate on the fine grid of a window at `origin`, back in camera pixels of frame 0.
fn in_frame(e: &CentreEstimate, [x0, y0]: [f64; 2], kf: f64) -> CentreEstimate {
    let from_fine = |p: [f64; 2]| [(p[0] + 0.5) / kf - 0.5 + x0, (p[1] + 0.5) / kf - 0.5 + y0];
    CentreEstimate {
        outer_px: from_fine(e.outer_px),
        inner_px: from_fine(e.inner_px),
        outer_radius_px: e.outer_radius_px / kf,
        inner_radius_px: e.inner_radius_px / kf,
        offset_cov_px2: e
            .offset_cov_px2
            .map(|c| c.map(|r| r.map(|v| v / (kf * kf)))),
        seed: None,
        even_ink: e.even_ink.map(|v| EvenInk {
            offset_px: v.offset_px.map(|o| o / kf),
            offset_cov_px2: v
                .offset_cov_px2
                .map(|c| c.map(|r| r.map(|x| x / (kf * kf)))),
        }),
    }
}

/// Camera coordinates of frame 0 to the fine grid of a window at `origin`: x maps to
/// (x − x0 + 0.5)·k − 0.5.
fn to_fine_grid(origin: [f64; 2], kf: f64) -> impl Fn([f64; 2]) -> [f64; 2] {
    move |p| [0, 1].map(|a| (p[a] - origin[a] + 0.5) * kf - 0.5)
}

/// Where a target's reconstruction (window at `origin`, `side` px, on the `k`-times finer
/// grid) is measured from: frame 0's fitted centres, the detected radii.
fn fine_guess(
    first: &CentreEstimate,
    c: &Candidate,
    origin: [f64; 2],
    k: usize,
    side: usize,
) -> Candidate {
    let kf = k as f64;
    let to_fine = to_fine_grid(origin, kf);
    Candidate {
        outer_centre_px: to_fine(first.outer_px),
        inner_centre_px: to_fine(first.inner_px),
        outer_radii_px: c.outer_radii_px.map(|r| r * kf),
        inner_radii_px: c.inner_radii_px.map(|r| r * kf),
        roi: Roi {
            x: 0,
            y: 0,
            w: (side * k) as u32,
            h: (side * k) as u32,
        },
        rectify: c.rectify,
    }
}

/// One target's result, its reconstruction (if any) and its uncertainties in px.
type Measured = (ObjectResult, Option<Fine>, Uncertain);

/// A target's uncertainties in camera pixels, before the conversion to µm.
#[derive(Debug, Clone, Copy, Default)]
struct Uncertain {
    type_a_px: Option<[f64; 2]>,
    /// The ink model's standard uncertainty (type B), on each axis.
    ink_px: Option<f64>,
}

/// Type A: the per-frame offsets' standard error, never below the fit's own figure. The
/// frames are registered with the even-ink model; when the measuring fit freed the contrast
/// planes, their scatter is scaled by how much noisier the planes' offset is on the same
/// pixels (the ratio of the two fits' standard deviations).
fn type_a_px(
    scatter: Option<&OffsetMean>,
    est: &CentreEstimate,
    fit_sigma_px: Option<[f64; 2]>,
) -> Option<[f64; 2]> {
    let ratio = |i: usize| -> f64 {
        let planes = est.offset_cov_px2.map(|c| c[i][i]);
        let even = est.even_ink.and_then(|e| e.offset_cov_px2).map(|c| c[i][i]);
        match (planes, even) {
            (Some(p), Some(e)) if e > 0.0 && p > e => (p / e).sqrt(),
            _ => 1.0,
        }
    };
    let scatter = scatter
        .and_then(|m| m.scatter_sigma())
        .map(|a| [a[0] * ratio(0), a[1] * ratio(1)]);
    match (scatter, fit_sigma_px) {
        (Some(a), Some(b)) => Some([a[0].max(b[0]), a[1].max(b[1])]),
        (a, b) => a.or(b),
    }
}

/// The ink model's type-B uncertainty: where the fit had to free the contrast planes, the
/// print is uneven in a way only partly modelled, and the offset is known no better than
/// the correction the planes made. GUM's rectangular distribution of that half-width
/// (|planes − even| / √3), on each axis.
fn ink_model_px(est: &CentreEstimate) -> Option<f64> {
    let even = est.even_ink?;
    let off = est.offset_px();
    let d = (off[0] - even.offset_px[0]).hypot(off[1] - even.offset_px[1]);
    Some(d / 3f64.sqrt())
}

/// A target's reconstruction window: its place in frame 0 and the reconstruction its
/// frames' crops (moved by each frame's whole-pixel displacement) accumulate into.
struct TargetWindow {
    x0: f64,
    y0: f64,
    side: u32,
    acc: Accumulator,
}

/// Mean of per-frame offsets: inverse-covariance weighted when every frame has a
/// covariance, else plain with the standard error of the scatter. Returns (offset, sigma).
/// The pipeline keeps the same as a running [`OffsetMean`].
pub fn mean_offset(ests: &[&CentreEstimate]) -> ([f64; 2], Option<[f64; 2]>) {
    let mut m = OffsetMean::default();
    for e in ests {
        m.add(e);
    }
    m.result()
}

/// Name the measured targets after the board's, and give their nominal offsets.
fn name_objects(objects: &mut [ObjectResult], board: &Board, scale_um_per_px: f64) {
    let found: Vec<[f64; 2]> = objects.iter().map(|o| o.centre_px).collect();
    let m = super::layout::match_board(&found, board, scale_um_per_px);
    for (o, j) in objects.iter_mut().zip(m) {
        if let Some(j) = j {
            o.name = Some(board.targets[j].name.clone());
            o.nominal_um = Some(board.targets[j].offset_um);
        }
    }
}

/// Process frames already in memory (the options are validated here).
pub fn process_frames(
    frames: &[RgbImage],
    positions_um: &[f64],
    opts: &ProcessOptions,
    board: Option<Board>,
) -> Result<Finished, PipelineError> {
    if frames.len() != positions_um.len() {
        return Err(PipelineError::Other(format!(
            "{} frames but {} positions",
            frames.len(),
            positions_um.len()
        )));
    }
    let mut p = Pipeline::new(opts.clone().validate()?, board);
    for (f, &x) in frames.iter().zip(positions_um) {
        p.push(f, x)?;
    }
    p.finish()
}
