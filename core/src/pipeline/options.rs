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
    /// Also reconstruct the whole frame (not only per-target ROIs) and keep it.
    pub whole_frame: bool,
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
            whole_frame: false,
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
}

impl OptionError {
    /// The option's name: `k`, `scale_um_per_px` or `axis_dir`.
    pub fn option(&self) -> &'static str {
        match self {
            OptionError::K { .. } => "k",
            OptionError::Scale { .. } => "scale_um_per_px",
            OptionError::AxisDir { .. } => "axis_dir",
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
        let [ax, ay] = self.axis_dir;
        if !(ax.is_finite() && ay.is_finite()) || ax.hypot(ay) == 0.0 {
            return Err(OptionError::AxisDir { got: self.axis_dir });
        }
        Ok(())
    }
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

/// Bytes a frame's estimate of one target takes (the estimate, its covariance).
const ESTIMATE_BYTES: u64 = std::mem::size_of::<Option<CentreEstimate>>() as u64;
/// One tap of the separable cubic kernel (4 indices, 4 weights); splat's are smaller.
const TAP_BYTES: u64 = 32;
/// Frame 0's detection: an ink mask (1 byte) and component labels (4 bytes) per pixel, and
/// room for the components and first estimates (measured: 5.06 bytes per pixel).
const DETECT_BYTES_PER_PX: u64 = 6;

impl ValidOptions {
    pub fn into_inner(self) -> ProcessOptions {
        self.0
    }

    /// The pipeline's peak heap use for one run of `frames` frames of `frame_size` (w, h)
    /// px, the caller's frames not counted, images kept (`Pipeline::keep_images`, the
    /// default). The targets' windows come from `board` (its outer rims at this scale);
    /// without a board they are bounded by the frame, which overestimates a lot.
    ///
    /// What dominates: a whole-frame reconstruction, k² x frame pixels x f32 plus its 16-bit
    /// copy (6 k² w h bytes), and with it every frame's f32 plane; else every frame's window
    /// around every target (4 s² bytes for a window of side s) and their reconstructions.
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
        // Held from push to the end of finish: per-frame estimates, crops, whole planes.
        let mut held = f * (sides.len() as u64 * ESTIMATE_BYTES + 24);
        if reconstructs {
            held += f * sides.iter().map(|s| 4 * s * s).sum::<u64>();
        }
        if self.whole_frame {
            held += f * 4 * w * h;
        }
        let (targets_peak, kept_png) = match reconstructs {
            true => self.targets_finish_bytes(&sides, f),
            false => (0, 0),
        };
        // Then the whole frame: the fine frame, its row pass and tap tables, then its copy.
        let mut whole_peak = 0;
        if self.whole_frame {
            let k = self.k as u64;
            let fine = 4 * k * k * w * h;
            let building = 4 * k * w * h + TAP_BYTES * f * k * w;
            whole_peak = kept_png + fine + building.max(fine / 2);
        }
        let detect = DETECT_BYTES_PER_PX * w * h + if self.whole_frame { 4 * w * h } else { 0 };
        let model = (held + targets_peak.max(whole_peak)).max(detect);
        // 2% for what the model leaves out: the thread pool's jobs, small vectors.
        model + model / 50
    }

    /// `finish`'s per-target reconstructions: (peak bytes, bytes of their 16-bit images).
    /// Every target's f32 reconstruction is kept until all are made, then each is turned into
    /// its 16-bit image in turn. While one is made (on each of rayon's threads): its row
    /// pass, tap tables and the estimator's sample of the fine window.
    fn targets_finish_bytes(&self, sides: &[u64], frames: u64) -> (u64, u64) {
        let k = self.k as u64;
        let fine: u64 = sides.iter().map(|s| 4 * k * k * s * s).sum();
        let largest = sides.iter().copied().max().unwrap_or(0);
        // The fit samples the fine window every k/3 pixels, the paper's estimator every one.
        let stride = match self.estimator {
            Estimator::Fit => (k / 3).max(1),
            Estimator::Paper => 1,
        };
        let sample = 4 * (k * largest).div_ceil(stride).pow(2);
        let building = 4 * k * largest * largest + TAP_BYTES * frames * k * largest + sample;
        let threads = (rayon::current_num_threads() as u64).min(sides.len() as u64);
        let png_largest = 2 * k * k * largest * largest;
        (fine + (threads * building).max(png_largest), fine / 2)
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
        // Whole frame: 6 k² w h (fine f32 + its 16-bit copy) = 553 MB, plus 40 planes of
        // 3.7 MB = 147 MB: about 0.7 GB, the whole frame dominating.
        let whole = opts(10, Combine::Interp, true).peak_memory_bytes(size, n, Some(&board));
        let floor = 6 * 100 * wh + 40 * 4 * wh;
        assert!(
            whole >= floor && whole < floor + floor / 20,
            "{whole} vs {floor}"
        );
        // Per target only: 12 windows of 2 (17000/774 + 7) + 1 = 59 px at k = 10: their
        // f32 reconstructions are 12 x 590² x 4 = 16.7 MB, the crops 6.7 MB, and one
        // 16-bit copy or a reconstruction being made (on each thread) on top.
        let targets = opts(10, Combine::Interp, false).peak_memory_bytes(size, n, Some(&board));
        assert_eq!(
            opts(10, Combine::Interp, false).window_sides_px(size, Some(&board))[0],
            59
        );
        let kept = 12 * 590 * 590 * 4 + 590 * 590 * 2 + 40 * 12 * 59 * 59 * 4;
        // Making one: a row pass (139 kB), tap tables (755 kB), the fit's sample (155 kB),
        // on as many threads as there are (at most one per target).
        let making = 590 * 59 * 4 + 32 * 40 * 590 + 4 * 197 * 197;
        let threads = rayon::current_num_threads().min(12) as u64;
        let want = kept - 590 * 590 * 2 + (threads * making).max(590 * 590 * 2);
        let want = want + want / 50;
        assert!(
            targets >= want && targets < want + want / 50,
            "{targets} vs {want}"
        );
        // Mean: per-frame estimates only; frame 0's detection is the peak.
        let mean = opts(1, Combine::Mean, false).peak_memory_bytes(size, n, Some(&board));
        assert_eq!(mean, 6 * wh + 6 * wh / 50);
        // k = 32 on the whole frame: the 3.8 GB K_RANGE's doc speaks of (and more).
        let k32 = opts(32, Combine::Interp, true).peak_memory_bytes(size, n, None);
        assert!(k32 > 4 * 32 * 32 * wh, "{k32}");
    }
}
