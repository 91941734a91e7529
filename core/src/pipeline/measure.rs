//! A frame's targets measured where frame 0 put them, moved by the frame's predicted
//! displacement: what registration and the type-A scatter are made of.
//!
//! A [`Measurer`] is made from frame 0 and shared (`Clone`, `Sync`): the pipeline measures
//! with it, and so can the threads that decode frames ahead of the pipeline, each frame on
//! the thread that decoded it while the pipeline accumulates earlier ones
//! (`rigd::offline::push`). The prediction for frame i comes from frame i − [`PREDICT_LAG`]
//! (frame 0 for the first ones), never from frames pushed in between, so a frame's
//! estimates are the same bits whichever thread makes them and whenever.

use super::detect::Candidate;
use super::estimate::{
    estimate_from, ink_density, CentreEstimate, DensitySample, PlaneInk, Seed, Start,
};
use super::options::WINDOW_MARGIN_PX;
use super::plane::{Mix, Plane, Roi};
use super::register::{At, Dirs};
use super::{Estimator, Registration, Response};
use image::RgbImage;
use rayon::prelude::*;
use std::collections::VecDeque;
use std::sync::{Arc, RwLock};

/// How many frames back a frame's displacement is predicted from: that frame's measured
/// displacement plus the positions' change since. Frames decoded ahead of the pipeline (at
/// most 8: two per decoder, at most four decoders) can then be measured as they are
/// decoded; over 8 steps the stage's drift from its commanded moves stays far within the
/// 0.1 px a tracked fit's one step reaches (a start further off costs passes, not
/// accuracy).
pub const PREDICT_LAG: usize = 8;

/// Frame 0's targets and fits, and the displacement of every frame pushed since.
#[derive(Clone)]
pub struct Measurer(Arc<Inner>);

struct Inner {
    size: (u32, u32),
    mix: Mix,
    response: Response,
    estimator: Estimator,
    /// `[target]`: the print's density as a prior for every frame's fit, when the frames'
    /// own fits are the results (`combine = mean`).
    inks: Vec<Option<PlaneInk>>,
    registration: Registration,
    dirs: Dirs,
    targets: Vec<Candidate>,
    /// `[target]`: frame 0's fit, the start of every later one.
    seeds: Vec<Option<Seed>>,
    /// Frame 0's position, and the latest frames' displacements and positions.
    at_zero: At,
    registered: RwLock<Recent>,
}

/// The displacement and position of the last [`KEPT`] frames recorded: what predictions
/// can still ask for (a run of any length holds the same).
struct Recent {
    /// The index of `frames[0]`.
    first: usize,
    frames: VecDeque<([f64; 2], At)>,
}

/// Frames kept in [`Recent`]: a prediction reaches [`PREDICT_LAG`] back from a frame at most
/// [`PREDICT_LAG`] ahead of the last one recorded.
const KEPT: usize = 4 * PREDICT_LAG;

/// One frame's estimates, made by [`Measurer::measure`].
#[derive(Debug, Clone)]
pub struct FrameEstimates {
    pub index: usize,
    pub at: At,
    pub predicted_px: [f64; 2],
    pub est: Vec<Option<CentreEstimate>>,
}

/// What a [`Measurer`] is made of: frame 0's measurement and the run's settings.
pub struct FrameZero<'a> {
    pub size: (u32, u32),
    pub mix: Mix,
    pub response: Response,
    pub estimator: Estimator,
    /// `[target]` (none: no prior for any).
    pub inks: Vec<Option<PlaneInk>>,
    pub registration: Registration,
    pub dirs: Dirs,
    pub targets: &'a [Candidate],
    pub seeds: Vec<Option<Seed>>,
    pub at: At,
}

impl Measurer {
    pub fn new(f: FrameZero) -> Measurer {
        Measurer(Arc::new(Inner {
            size: f.size,
            mix: f.mix,
            response: f.response,
            estimator: f.estimator,
            inks: f.inks,
            registration: f.registration,
            dirs: f.dirs,
            targets: f.targets.to_vec(),
            seeds: f.seeds,
            at_zero: f.at,
            registered: RwLock::new(Recent {
                first: 0,
                frames: VecDeque::from([([0.0; 2], f.at)]),
            }),
        }))
    }

    /// Frame `index` (pushed next, or later) was displaced by `shift_px` at `at`.
    pub fn record(&self, index: usize, shift_px: [f64; 2], at: At) {
        let mut r = self.0.registered.write().unwrap_or_else(|e| e.into_inner());
        if r.first + r.frames.len() == index {
            r.frames.push_back((shift_px, at));
            if r.frames.len() > KEPT {
                r.frames.pop_front();
                r.first += 1;
            }
        }
    }

    /// Where frame `index` at `at` should be: frame 0's place moved by the positions'
    /// displacement (`registration = positions`), or by frame j = index − [`PREDICT_LAG`]'s
    /// measured one plus the positions' change since, turned and scaled as frame j's
    /// measured displacement is to its commanded one (once that is 2 px or more: a
    /// misconfigured scale or axis direction then costs a long step no more than a short
    /// one). `None` while frame j is not recorded (or not kept: far behind the last one).
    pub fn predicted(&self, index: usize, at: At) -> Option<[f64; 2]> {
        let dirs = &self.0.dirs;
        let (from_px, from_at) = match self.0.registration {
            Registration::Positions => ([0.0; 2], self.0.at_zero),
            Registration::Image => {
                let r = self.0.registered.read().unwrap_or_else(|e| e.into_inner());
                let j = index.saturating_sub(PREDICT_LAG).checked_sub(r.first)?;
                *r.frames.get(j)?
            }
        };
        let d = dirs.shift_px(at, from_at);
        let [zr, zi] = similarity(from_px, dirs.shift_px(from_at, self.0.at_zero));
        Some([
            from_px[0] + zr * d[0] - zi * d[1],
            from_px[1] + zi * d[0] + zr * d[1],
        ])
    }

    /// The last row (exclusive) the measurement windows reach at `predicted_px`.
    pub fn rows_read(&self, predicted_px: [f64; 2]) -> f64 {
        windows_bottom(&self.0.targets, predicted_px, self.0.size.1 as f64)
    }

    /// Measure frame `index` (its first `valid_rows` rows decoded) at `at`, on this thread
    /// alone: `None` when it cannot be done here (the frame's size, a position that is not
    /// a number, rows not decoded, the frame it is predicted from not pushed yet): the
    /// pipeline then measures it itself, and says what was wrong.
    pub fn measure(
        &self,
        frame: &RgbImage,
        valid_rows: u32,
        index: usize,
        at: At,
    ) -> Option<FrameEstimates> {
        let ok = frame.dimensions() == self.0.size && at.iter().all(|p| p.is_finite());
        let predicted_px = self.predicted(index, at).filter(|_| ok)?;
        if (valid_rows as f64) < self.rows_read(predicted_px) {
            return None;
        }
        let est = self.targets_at(frame, predicted_px, false);
        Some(FrameEstimates {
            index,
            at,
            predicted_px,
            est,
        })
    }

    /// Every target measured at `predicted_px`, on rayon's threads when `parallel`.
    pub fn targets_at(
        &self,
        frame: &RgbImage,
        predicted_px: [f64; 2],
        parallel: bool,
    ) -> Vec<Option<CentreEstimate>> {
        let m = &self.0;
        let one = |(t, (c, seed)): (usize, (&Candidate, &Option<Seed>))| {
            let how = (m.mix, m.response);
            let ink = m.inks.get(t).cloned().flatten();
            measure_in_frame(frame, how, (c, *seed), predicted_px, (m.estimator, ink))
        };
        let each = m.targets.iter().zip(&m.seeds).enumerate();
        if parallel {
            let each: Vec<_> = each.collect();
            each.into_par_iter().map(one).collect()
        } else {
            each.map(one).collect()
        }
    }
}

/// The turn and scale (a complex number) that takes the commanded displacement
/// `commanded_px` to the measured `measured_px`; none (1 + 0i) while the commanded one is
/// under 2 px (too short to tell) or the two disagree wildly (a factor beyond 2, a turn
/// beyond 30°: something else moved the image).
fn similarity(measured_px: [f64; 2], commanded_px: [f64; 2]) -> [f64; 2] {
    let [mx, my] = measured_px;
    let [cx, cy] = commanded_px;
    let n = cx * cx + cy * cy;
    if n < 4.0 {
        return [1.0, 0.0];
    }
    let z = [(mx * cx + my * cy) / n, (my * cx - mx * cy) / n];
    let gain = z[0].hypot(z[1]);
    let plausible = (0.5..=2.0).contains(&gain) && z[0] >= gain * 30f64.to_radians().cos();
    if plausible {
        z
    } else {
        [1.0, 0.0]
    }
}

/// The last row (exclusive) the measurement windows of `targets` reach at `shift_px`, in a
/// frame `height` rows high.
pub(super) fn windows_bottom(targets: &[Candidate], shift_px: [f64; 2], height: f64) -> f64 {
    targets
        .iter()
        .map(|c| {
            let (_, y0, side) = measure_window(c, shift_px);
            (y0 + side as f64).min(height)
        })
        .fold(0.0, f64::max)
}

/// A target's measurement window at its frame-0 place moved by `shift_px`: left, top, side.
fn measure_window(c: &Candidate, shift_px: [f64; 2]) -> (f64, f64, u32) {
    let reach = c.outer_radii_px[1] + WINDOW_MARGIN_PX;
    let cx = c.outer_centre_px[0] + shift_px[0];
    let cy = c.outer_centre_px[1] + shift_px[1];
    (
        (cx - reach).floor().max(0.0),
        (cy - reach).floor().max(0.0),
        (2.0 * reach).ceil() as u32 + 1,
    )
}

/// The print's density inside target `c`'s shapes in `frame`, read off its fit `e` there
/// ([`ink_density`]), and that fit's blur width (px). `None` without a fit's state.
pub(super) fn density_in_frame(
    frame: &RgbImage,
    (mix, response): (Mix, Response),
    c: &Candidate,
    e: &CentreEstimate,
) -> Option<(Vec<DensitySample>, f64)> {
    let seed = e.seed?;
    let shift_px = [
        e.outer_px[0] - c.outer_centre_px[0],
        e.outer_px[1] - c.outer_centre_px[1],
    ];
    let (crop, guess, [x0, y0]) = crop_window(frame, (mix, response), c, shift_px);
    let seed = seed.mapped(|p| [p[0] - x0, p[1] - y0], 1.0);
    let samples = ink_density(&crop, &guess, 1.0, &seed).ok()?;
    Some((samples, seed.blur_px()))
}

/// Target `c`'s measurement window at its frame-0 place moved by `shift_px`: the crop of
/// the plane `mix`, the target's guess in it, and the crop's origin in the frame.
fn crop_window(
    frame: &RgbImage,
    (mix, response): (Mix, Response),
    c: &Candidate,
    shift_px: [f64; 2],
) -> (Plane, Candidate, [f64; 2]) {
    let (x0, y0, side) = measure_window(c, shift_px);
    let roi = Roi {
        x: x0 as u32,
        y: y0 as u32,
        w: side,
        h: side,
    };
    let crop = Plane::from_mix_roi_in(frame, mix, roi, response);
    let mv = |p: [f64; 2]| [p[0] + shift_px[0] - x0, p[1] + shift_px[1] - y0];
    let guess = Candidate {
        outer_centre_px: mv(c.outer_centre_px),
        inner_centre_px: mv(c.inner_centre_px),
        outer_radii_px: c.outer_radii_px,
        inner_radii_px: c.inner_radii_px,
        roi: Roi::whole(crop.width, crop.height),
        rectify: c.rectify,
    };
    (crop, guess, [x0, y0])
}

/// Measure one target in a frame at its frame-0 place moved by `shift_px`, on a window of
/// the plane `mix`, the fit started from frame 0's `seed` (frame coordinates) when there is
/// one. `None` when it cannot be measured (out of frame, estimator failure).
pub(super) fn measure_in_frame(
    frame: &RgbImage,
    (mix, response): (Mix, Response),
    (c, seed): (&Candidate, Option<Seed>),
    shift_px: [f64; 2],
    (estimator, ink): (Estimator, Option<PlaneInk>),
) -> Option<CentreEstimate> {
    let (crop, guess, [x0, y0]) = crop_window(frame, (mix, response), c, shift_px);
    let mv = |p: [f64; 2]| [p[0] + shift_px[0] - x0, p[1] + shift_px[1] - y0];
    let seed = seed.map(|s| s.mapped(mv, 1.0));
    let start = seed.as_ref().map_or(Start::Guess, Start::Track);
    let mut e = estimate_from(&crop, &guess, estimator, 1.0, start, ink).ok()?;
    let back = |p: [f64; 2]| [p[0] + x0, p[1] + y0];
    e.outer_px = back(e.outer_px);
    e.inner_px = back(e.inner_px);
    e.seed = e.seed.map(|s| s.mapped(back, 1.0));
    Some(e)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn measurer(registration: Registration, scale_um_per_px: f64) -> Measurer {
        Measurer::new(FrameZero {
            size: (100, 100),
            mix: Mix::channel(0),
            response: Response::Linear,
            estimator: Estimator::Fit,
            inks: Vec::new(),
            registration,
            dirs: Dirs {
                scale_um_per_px,
                axis_dir: [1.0, 0.0],
                piezo_dir: [0.0, 1.0],
            },
            targets: &[],
            seeds: Vec::new(),
            at: [0.0, 0.0],
        })
    }

    #[test]
    fn a_misconfigured_scale_and_direction_are_learnt_from_the_scan() {
        // 1 mm steps; the configured scale is 25 % off and the axis turned by 3°: the
        // image really moves 1000/1000 px a step at 3°, the configuration says 1000/750.
        let m = measurer(Registration::Image, 750.0);
        let truth = |i: usize| {
            let (s, c) = 3f64.to_radians().sin_cos();
            [i as f64 * c, i as f64 * s]
        };
        for i in 1..40 {
            let at = [1000.0 * i as f64, 0.0];
            let p = m.predicted(i, at).expect("frame i − PREDICT_LAG recorded");
            let err = (p[0] - truth(i)[0]).hypot(p[1] - truth(i)[1]);
            // Until frame j has moved 2 px the commanded step is taken as it is: 8 steps
            // 33 % long; from there on the prediction is the scan's own.
            let j = i.saturating_sub(PREDICT_LAG);
            let within = if 1000.0 * j as f64 / 750.0 >= 2.0 {
                1e-9
            } else {
                3.0
            };
            assert!(
                err < within,
                "frame {i}: predicted {p:?}, truth {:?}",
                truth(i)
            );
            m.record(i, truth(i), at);
        }
        // Frames not recorded yet, or long dropped, cannot be predicted from.
        assert!(m.predicted(40 + PREDICT_LAG + 1, [0.0; 2]).is_none());
        assert!(
            m.predicted(PREDICT_LAG + 1, [0.0; 2]).is_none(),
            "frame 1 was dropped"
        );
    }

    #[test]
    fn positions_registration_predicts_from_frame_zero_and_a_wild_scan_is_not_learnt() {
        let m = measurer(Registration::Positions, 500.0);
        assert_eq!(m.predicted(99, [1000.0, 500.0]), Some([2.0, 1.0]));
        // Measured 5x the commanded: not a scale error, the step is taken as commanded.
        let m = measurer(Registration::Image, 500.0);
        for i in 1..=PREDICT_LAG {
            m.record(i, [10.0 * i as f64, 0.0], [1000.0 * i as f64, 0.0]);
        }
        let at = [1000.0 * (2 * PREDICT_LAG) as f64, 0.0];
        let p = m.predicted(2 * PREDICT_LAG, at).unwrap();
        assert_eq!(
            p,
            [10.0 * PREDICT_LAG as f64 + 2.0 * PREDICT_LAG as f64, 0.0]
        );
    }
}
