//! The pipeline's options and their limits: [`ProcessOptions`] as written (config, protocol,
//! command line), [`ValidOptions`] once checked. The pipeline owns every rule an option must
//! satisfy; callers check at the edge (a submit, a command line) with
//! [`ProcessOptions::validate`] and hand [`ValidOptions`] to [`Pipeline::new`], which then
//! cannot fail on an option later.
//!
//! [`Pipeline::new`]: super::Pipeline::new

use super::estimate::CentreEstimate;
use super::{Combine, Estimator, Registration};
use crate::board::Board;
use serde::{Deserialize, Serialize};
use std::ops::RangeInclusive;

/// Accepted upsampling factors. Above 32 a whole 1280x720 frame's reconstruction alone
/// would be 3.8 GB (see [`ValidOptions::peak_memory_bytes`]).
pub const K_RANGE: RangeInclusive<u32> = 1..=32;

/// Largest accepted upsampling factor: `K_RANGE.end()`.
pub const MAX_K: u32 = *K_RANGE.end();

/// Camera pixels kept around a target's outer rim in its reconstruction window: the
/// estimators want the rim plus 3.5 px, the cubic kernel 2 more.
pub(crate) const WINDOW_MARGIN_PX: f64 = 6.0;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[serde(default, deny_unknown_fields)]
pub struct ProcessOptions {
    pub scale_um_per_px: f64,
    /// Upsampling factor of the reconstruction (1 = none), in [`K_RANGE`].
    pub k: u32,
    pub estimator: Estimator,
    pub combine: Combine,
    pub registration: Registration,
    /// Image displacement (px per px of axis travel) of the scene when the axis moves +1:
    /// the camera rides the axis, so the scene moves the other way.
    pub axis_dir: [f64; 2],
    /// The same for the piezo when a run moves it besides its stage (a 2-D grid or a list
    /// of axis and piezo positions); absent for a run on one stage.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub piezo_dir: Option<[f64; 2]>,
    /// Also reconstruct the whole frame (not only per-target ROIs) and keep it.
    pub whole_frame: bool,
    /// The camera's output curve: frames are measured in linear light (`response`).
    pub response: super::Response,
    /// The print's ink density statistics, when known: the fit then also follows the ink's
    /// uneven density over each target, as a prior (docs/method.md, "The print as a
    /// prior"). Absent: the even-ink fit with its contrast planes.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ink_prior: Option<InkPrior>,
    /// Without `ink_prior`: take the statistics the applied calibration learnt from its
    /// scan, when it found the print measurably uneven (`calibration::ink`).
    #[serde(skip_serializing_if = "is_true")]
    pub calibration_ink: bool,
}

fn is_true(v: &bool) -> bool {
    *v
}

/// The statistics of a print's ink density `1 + ε`: ε a smooth random field of RMS
/// `density_rms` (relative) with a Gaussian correlation of length `corr_um` on the board
/// (measured once on a print: docs/calibration.md).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields)]
pub struct InkPrior {
    pub density_rms: f64,
    pub corr_um: f64,
}

impl InkPrior {
    /// Parse `RMS,CORR_UM` (the command line's form), e.g. `0.04,3000`.
    pub fn parse(s: &str) -> Result<InkPrior, String> {
        let bad = || format!("ink prior must be RMS,CORR_UM (e.g. 0.04,3000), got `{s}`");
        let (a, b) = s.split_once(',').ok_or_else(bad)?;
        let prior = InkPrior {
            density_rms: a.trim().parse().map_err(|_| bad())?,
            corr_um: b.trim().parse().map_err(|_| bad())?,
        };
        prior.check().map_err(|e| e.to_string())?;
        Ok(prior)
    }

    /// Whether the statistics are usable: 0 < `density_rms` ≤ 0.5, `corr_um` > 0.
    pub fn check(&self) -> Result<(), OptionError> {
        let (r, c) = (self.density_rms, self.corr_um);
        if r.is_finite() && r > 0.0 && r <= 0.5 && c.is_finite() && c > 0.0 {
            Ok(())
        } else {
            Err(OptionError::InkPrior { got: *self })
        }
    }
}

impl Default for ProcessOptions {
    fn default() -> Self {
        ProcessOptions {
            scale_um_per_px: 774.0,
            k: 1,
            estimator: Estimator::default(),
            combine: Combine::default(),
            registration: Registration::default(),
            axis_dir: [-1.0, 0.0],
            piezo_dir: None,
            whole_frame: false,
            response: super::Response::Linear,
            ink_prior: None,
            calibration_ink: true,
        }
    }
}

/// An option outside its limits. The message names the option as it is spelled in the
/// config, the protocol and on the command line.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OptionError {
    #[error("`k` must be {}..={}, got {got}", K_RANGE.start(), K_RANGE.end())]
    K { got: u32 },
    #[error("`scale_um_per_px` must be finite and positive, got {got}")]
    Scale { got: f64 },
    #[error("`axis_dir` must be a finite non-zero vector, got {got:?}")]
    AxisDir { got: [f64; 2] },
    #[error("`piezo_dir` must be a finite non-zero vector, got {got:?}")]
    PiezoDir { got: [f64; 2] },
    #[error(
        "`ink_prior` must have 0 < density_rms <= 0.5 and a finite positive corr_um, got {got:?}"
    )]
    InkPrior { got: InkPrior },
}

impl OptionError {
    /// The option's name: `k`, `scale_um_per_px` or `axis_dir`.
    pub fn option(&self) -> &'static str {
        match self {
            OptionError::K { .. } => "k",
            OptionError::Scale { .. } => "scale_um_per_px",
            OptionError::AxisDir { .. } => "axis_dir",
            OptionError::PiezoDir { .. } => "piezo_dir",
            OptionError::InkPrior { .. } => "ink_prior",
        }
    }
}

impl ProcessOptions {
    /// Check every limit the pipeline relies on.
    pub fn validate(self) -> Result<ValidOptions, OptionError> {
        self.check()?;
        Ok(ValidOptions(self))
    }

    /// [`ProcessOptions::validate`] without giving the options up.
    pub fn check(&self) -> Result<(), OptionError> {
        let s = self.scale_um_per_px;
        if !(s.is_finite() && s > 0.0) {
            return Err(OptionError::Scale { got: s });
        }
        if !K_RANGE.contains(&self.k) {
            return Err(OptionError::K { got: self.k });
        }
        if !usable_dir(self.axis_dir) {
            return Err(OptionError::AxisDir { got: self.axis_dir });
        }
        if let Some(d) = self.piezo_dir.filter(|&d| !usable_dir(d)) {
            return Err(OptionError::PiezoDir { got: d });
        }
        if let Some(p) = &self.ink_prior {
            p.check()?;
        }
        Ok(())
    }

    /// Whether the run's frames move vertically in the image (their vertical fine shifts
    /// then take any of k values, not the few of a horizontal line's jitter).
    pub fn moves_vertically(&self) -> bool {
        self.axis_dir[1] != 0.0 || self.piezo_dir.is_some_and(|d| d[1] != 0.0)
    }
}

fn usable_dir([x, y]: [f64; 2]) -> bool {
    x.is_finite() && y.is_finite() && x.hypot(y) != 0.0
}

/// Options the pipeline accepts: the only way to build one is [`ProcessOptions::validate`]
/// (or `TryFrom`, or deserialising, which validates too). Reads as a [`ProcessOptions`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "ProcessOptions", into = "ProcessOptions")]
pub struct ValidOptions(ProcessOptions);

impl Default for ValidOptions {
    fn default() -> Self {
        ProcessOptions::default()
            .validate()
            .expect("the default options are valid")
    }
}

impl std::ops::Deref for ValidOptions {
    type Target = ProcessOptions;
    fn deref(&self) -> &ProcessOptions {
        &self.0
    }
}

impl TryFrom<ProcessOptions> for ValidOptions {
    type Error = OptionError;
    fn try_from(o: ProcessOptions) -> Result<Self, OptionError> {
        o.validate()
    }
}

impl From<ValidOptions> for ProcessOptions {
    fn from(v: ValidOptions) -> Self {
        v.0
    }
}

/// Bytes frame 0's estimate of one target takes (the estimate, its covariance), and a
/// target's running mean.
const ESTIMATE_BYTES: u64 = std::mem::size_of::<Option<CentreEstimate>>() as u64 + 120;
/// One listed step of a result (`StepResidual`).
const STEP_BYTES: u64 = std::mem::size_of::<super::StepResidual>() as u64;
/// One tap of the separable cubic kernel (4 indices, 4 weights); splat's are smaller.
const TAP_BYTES: u64 = 32;
/// Frame 0's detection: an ink mask (1 byte) and component labels (4 bytes) per pixel, and
/// room for the components and first estimates (measured: 5.06 bytes per pixel).
const DETECT_BYTES_PER_PX: u64 = 6;
/// Vertical fine shifts a horizontal scan's frames fall in (the image registration's jitter
/// across the scan): each one a reconstruction's row-pass sum.
const HORIZONTAL_SCAN_GROUPS: u64 = 3;

impl ValidOptions {
    /// The same options, taking (or not) a calibration's learnt ink statistics: no limit
    /// bears on it.
    pub fn with_calibration_ink(mut self, take: bool) -> ValidOptions {
        self.0.calibration_ink = take;
        self
    }

    pub fn into_inner(self) -> ProcessOptions {
        self.0
    }

    /// The print's prior's working set: a fit's on each thread measuring a target at once
    /// (what [`Self::peak_memory_bytes`] adds with `ink_prior`; a caller that knows a
    /// calibration's learnt prior will be taken adds it too).
    pub fn ink_prior_bytes(&self, frame_size: (u32, u32), board: Option<&Board>) -> u64 {
        let targets = self.window_sides_px(frame_size, board).len().max(1);
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        threads.min(targets) as u64 * super::estimate::PRIOR_PEAK_BYTES
    }

    /// The pipeline's peak heap use for one run of `frames` frames of `frame_size` (w, h)
    /// px, the caller's frames not counted, images kept (`Pipeline::keep_images`, the
    /// default). The targets' windows come from `board` (its outer rims at this scale);
    /// without a board they are bounded by the frame, which overestimates a lot.
    ///
    /// Processing streams (docs/reconstruction.md): beyond the listed steps (at most
    /// `register::MAX_LISTED_STEPS`) nothing grows with `frames`. What dominates: a
    /// whole-frame reconstruction, k² x frame pixels x f32 plus its 16-bit copy
    /// (6 k² w h bytes) and its open row-pass sums (4 k w h each); else the targets'
    /// reconstructions (4 k² s² bytes for a window of side s) and their row-pass sums.
    /// tests/pipeline_memory.rs holds it to the measured peak.
    pub fn peak_memory_bytes(
        &self,
        frame_size: (u32, u32),
        frames: u32,
        board: Option<&Board>,
    ) -> u64 {
        let (w, h, f) = (frame_size.0 as u64, frame_size.1 as u64, frames as u64);
        let sides = self.window_sides_px(frame_size, board);
        let reconstructs = self.combine != Combine::Mean;
        let listed = f.min(super::register::MAX_LISTED_STEPS as u64);
        // Held from push to the end of finish: frame 0's estimates, the listed steps.
        let held = sides.len() as u64 * ESTIMATE_BYTES + listed * STEP_BYTES;
        let (targets_peak, kept_png) = match reconstructs {
            true => self.targets_bytes(&sides, f),
            false => (0, 0),
        };
        // Then the whole frame: the fine sum with the open row-pass sums, then its copy.
        let whole_peak = match self.whole_frame {
            true => self.whole_frame_bytes(frame_size, f, targets_peak, kept_png),
            false => 0,
        };
        let detect = DETECT_BYTES_PER_PX * w * h + if self.whole_frame { 4 * w * h } else { 0 };
        let prior = match self.ink_prior {
            Some(_) => self.ink_prior_bytes(frame_size, board),
            None => 0,
        };
        let model = (held + prior + targets_peak.max(whole_peak)).max(detect);
        // 2% for what the model leaves out: the thread pool's jobs, small vectors.
        model + model / 50
    }

    /// The whole-frame reconstruction's peak, the targets' (`targets_peak`, their images
    /// `kept_png`) included: its open row-pass sums (at most `WHOLE_FRAME_OPEN_GROUPS`, a
    /// horizontal scan's fewer) are held from frame 0 while the targets finish; a scan with
    /// vertical motion flushes sums into a fine sum (splat: and a fine plane of counts)
    /// before the end; then the fine grid and its 16-bit copy.
    fn whole_frame_bytes(&self, size: (u32, u32), f: u64, targets_peak: u64, kept_png: u64) -> u64 {
        let (w, h, k) = (size.0 as u64, size.1 as u64, self.k as u64);
        let fine = 4 * k * k * w * h;
        let open = super::run::WHOLE_FRAME_OPEN_GROUPS as u64;
        let splat = self.combine == Combine::Splat;
        let (g, flushes) = match !self.moves_vertically() {
            true => (f.min(HORIZONTAL_SCAN_GROUPS).min(open), false),
            false => (f.min(open), f > open),
        };
        let sums = g * 4 * k * w * h + if splat { 4 * w * h + g * 4 * k * w } else { 0 };
        let flushed = if flushes {
            fine * (1 + splat as u64)
        } else {
            0
        };
        let pushing = sums + flushed + 4 * w * h;
        let finishing = kept_png + sums + flushed.max(fine) + TAP_BYTES * k * h;
        (targets_peak + sums + flushed)
            .max(pushing)
            .max(finishing)
            .max(kept_png + fine + fine / 2)
    }

    /// Vertical fine shifts a target's frames fall in: below half a pixel (the window moves
    /// by the whole pixels), so at most k + 2; a horizontal scan's jitter only a few.
    fn target_groups(&self, frames: u64) -> u64 {
        let k = self.k as u64;
        let most = if !self.moves_vertically() {
            HORIZONTAL_SCAN_GROUPS.min(k + 2)
        } else {
            k + 2
        };
        most.min(frames.max(1))
    }

    /// The targets' reconstructions: (peak bytes, bytes of their 16-bit images). Each
    /// target keeps its row-pass sums (4 k s² bytes each; splat also frame 0's window) from
    /// frame 0 on; `finish` makes each fine grid while its sums are still held, keeps every
    /// fine grid until all are made, then turns each into its 16-bit image in turn. While
    /// one is made (on each of rayon's threads): its column taps and the estimator's sample
    /// of the fine window.
    fn targets_bytes(&self, sides: &[u64], frames: u64) -> (u64, u64) {
        let k = self.k as u64;
        let g = self.target_groups(frames);
        let splat = self.combine == Combine::Splat;
        let sums = |s: u64| g * 4 * k * s * s + if splat { 4 * s * s + g * 4 * k * s } else { 0 };
        let fine_of = |s: u64| 4 * k * k * s * s;
        let fine: u64 = sides.iter().map(|&s| fine_of(s)).sum();
        let largest = sides.iter().copied().max().unwrap_or(0);
        // The fit samples the fine window every k/2 pixels, the paper's estimator every one.
        let stride = match self.estimator {
            Estimator::Fit => (k / 2).max(1),
            Estimator::Paper => 1,
        };
        let sample = 4 * (k * largest).div_ceil(stride).pow(2);
        let making = TAP_BYTES * k * largest + sample;
        // Making target t: the fine grids of those before it, the sums of it and those after.
        let mut peak = 0;
        let (mut done, mut left) = (0u64, sides.iter().map(|&s| sums(s)).sum::<u64>());
        for &s in sides {
            peak = peak.max(done + fine_of(s) + left);
            done += fine_of(s);
            left -= sums(s);
        }
        let threads = (rayon::current_num_threads() as u64).min(sides.len() as u64);
        let png_largest = 2 * k * k * largest * largest;
        let peak = (peak + threads * making).max(fine + png_largest);
        (peak, fine / 2)
    }

    /// Bytes of the 16-bit images one run hands back (`Finished::images`, kept images):
    /// every target's reconstruction and, with `whole_frame`, the whole frame's (2 k² w h).
    /// A caller keeping them all (the daemon writes them when the job ends) holds this much
    /// per run, and a PNG of them takes about as much on disk (16-bit noise barely
    /// compresses).
    pub fn kept_image_bytes(&self, frame_size: (u32, u32), board: Option<&Board>) -> u64 {
        let k2 = (self.k as u64).pow(2);
        let mut px = 0;
        if self.combine != Combine::Mean {
            px += self
                .window_sides_px(frame_size, board)
                .iter()
                .map(|s| s * s)
                .sum::<u64>();
        }
        if self.whole_frame {
            px += frame_size.0 as u64 * frame_size.1 as u64;
        }
        2 * k2 * px
    }

    /// Side of each target's reconstruction window in camera pixels, as the pipeline cuts
    /// them (rim + margin each way, one pixel of slack for the blur-widened measured rim).
    fn window_sides_px(&self, frame_size: (u32, u32), board: Option<&Board>) -> Vec<u64> {
        let side = |rim_px: f64| (2.0 * (rim_px + 1.0 + WINDOW_MARGIN_PX)).ceil() as u64 + 1;
        match board {
            Some(b) => b
                .targets
                .iter()
                .map(|t| side(t.outer.outer_radius_um() / self.scale_um_per_px))
                .collect(),
            // Targets do not overlap, so their windows (squares around circles) together
            // cover at most 4/pi of the frame: one window of that area stands for them all.
            None => {
                let area = 4.0 / std::f64::consts::PI * frame_size.0 as f64 * frame_size.1 as f64;
                vec![area.sqrt().ceil() as u64]
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_ink_prior_is_read_from_the_command_line_and_checked() {
        let p = InkPrior::parse("0.04, 3000").unwrap();
        assert_eq!((p.density_rms, p.corr_um), (0.04, 3000.0));
        for bad in [
            "0.04", "x,3000", "0,3000", "0.6,3000", "0.04,-1", "0.04,inf",
        ] {
            let e = InkPrior::parse(bad).unwrap_err();
            assert!(e.contains("ink"), "{bad}: {e}");
        }
        let opts = ProcessOptions {
            ink_prior: Some(InkPrior {
                density_rms: 0.04,
                corr_um: 0.0,
            }),
            ..ProcessOptions::default()
        };
        assert_eq!(opts.validate().unwrap_err().option(), "ink_prior");
    }

    #[test]
    fn each_limit_is_refused_with_the_options_name() {
        let with = |f: fn(&mut ProcessOptions)| {
            let mut o = ProcessOptions::default();
            f(&mut o);
            o.validate().unwrap_err()
        };
        let e = with(|o| o.k = 40);
        assert_eq!(e.to_string(), "`k` must be 1..=32, got 40");
        assert_eq!(e.option(), "k");
        assert_eq!(with(|o| o.k = 0), OptionError::K { got: 0 });
        assert_eq!(
            with(|o| o.scale_um_per_px = f64::NAN).option(),
            "scale_um_per_px"
        );
        assert_eq!(
            with(|o| o.scale_um_per_px = -1.0).option(),
            "scale_um_per_px"
        );
        assert_eq!(
            with(|o| o.axis_dir = [0.0, 0.0]).to_string(),
            "`axis_dir` must be a finite non-zero vector, got [0.0, 0.0]"
        );
        assert_eq!(
            with(|o| o.axis_dir = [f64::INFINITY, 0.0]).option(),
            "axis_dir"
        );
        for k in [1, 10, 32] {
            let o = ProcessOptions {
                k,
                ..ProcessOptions::default()
            };
            assert_eq!(o.clone().validate().unwrap().into_inner(), o);
        }
    }

    #[test]
    fn deserialising_validates() {
        let v: ValidOptions = toml::from_str("k = 10\ncombine = \"splat\"").unwrap();
        assert_eq!((v.k, v.combine), (10, Combine::Splat));
        let e = toml::from_str::<ValidOptions>("k = 33").unwrap_err();
        assert!(e.to_string().contains("`k` must be 1..=32, got 33"), "{e}");
    }

    fn opts(k: u32, combine: Combine, whole_frame: bool) -> ValidOptions {
        ProcessOptions {
            k,
            combine,
            whole_frame,
            ..ProcessOptions::default()
        }
        .validate()
        .unwrap()
    }

    /// The estimate by hand for the paper's rig: 1280x720 frames, 40 of them, k = 10.
    #[test]
    fn peak_memory_of_the_papers_runs() {
        let board = Board::paper();
        let (size, n) = ((1280, 720), 40);
        let wh: u64 = 1280 * 720;
        // Whole frame: 6 k² w h (fine f32 + its 16-bit copy) = 553 MB, plus the targets'
        // 16-bit images (8.4 MB): the whole frame dominating, whatever the frame count.
        let whole = opts(10, Combine::Interp, true).peak_memory_bytes(size, n, Some(&board));
        let floor = 6 * 100 * wh;
        assert!(
            whole >= floor && whole < floor + floor / 20,
            "{whole} vs {floor}"
        );
        // Per target only: 12 windows of 2 (17000/774 + 7) + 1 = 59 px at k = 10: their
        // f32 reconstructions are 12 x 590² x 4 = 16.7 MB, made while the last one's
        // row-pass sums (3 groups of 59 x 590 x 4 = 139 kB) are held, with one being made
        // (on each thread) on top, or one 16-bit copy (696 kB).
        let targets = opts(10, Combine::Interp, false).peak_memory_bytes(size, n, Some(&board));
        assert_eq!(
            opts(10, Combine::Interp, false).window_sides_px(size, Some(&board))[0],
            59
        );
        let fine = 12 * 590 * 590 * 4;
        // Making one: column taps (19 kB), the fit's sample (every 5th pixel: 56 kB).
        let making = 32 * 10 * 59 + 4 * 118 * 118;
        let threads = rayon::current_num_threads().min(12) as u64;
        let held = 12 * ESTIMATE_BYTES + 40 * STEP_BYTES;
        let want = held + (fine + 3 * 59 * 590 * 4 + threads * making).max(fine + 590 * 590 * 2);
        let want = want + want / 50;
        assert!(
            targets >= want && targets < want + want / 50,
            "{targets} vs {want}"
        );
        // Flat in the frame count: 100 000 frames (the plan's limit) cost what 1000 do, and
        // those only their listed steps more than 40.
        let o = opts(10, Combine::Interp, false);
        let at = |n| o.peak_memory_bytes(size, n, Some(&board));
        assert_eq!(at(100_000), at(1000));
        assert!(
            at(1000) - at(40) <= 2 * 960 * STEP_BYTES,
            "{} {}",
            at(1000),
            at(40)
        );
        let w = opts(10, Combine::Splat, true);
        assert_eq!(
            w.peak_memory_bytes(size, 100_000, None),
            w.peak_memory_bytes(size, 1000, None)
        );
        // Mean: per-frame estimates only; frame 0's detection is the peak.
        let mean = opts(1, Combine::Mean, false).peak_memory_bytes(size, n, Some(&board));
        assert_eq!(mean, 6 * wh + 6 * wh / 50);
        // k = 32 on the whole frame: the 3.8 GB K_RANGE's doc speaks of (and more).
        let k32 = opts(32, Combine::Interp, true).peak_memory_bytes(size, n, None);
        assert!(k32 > 4 * 32 * 32 * wh, "{k32}");
    }
}
