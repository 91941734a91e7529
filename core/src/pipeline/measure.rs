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
use super::estimate::{estimate_from, CentreEstimate, Seed, Start};
use super::options::WINDOW_MARGIN_PX;
use super::plane::{Plane, Roi};
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
    channel: usize,
    response: Response,
    estimator: Estimator,
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
    pub channel: usize,
    pub response: Response,
    pub estimator: Estimator,
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
            channel: f.channel,
            response: f.response,
            estimator: f.estimator,
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
    /// displacement (`registration = positions`), or by frame index − [`PREDICT_LAG`]'s
    /// measured one plus the positions' change since. `None` while that frame is not
    /// recorded (or no longer: a frame far behind the last one recorded).
    pub fn predicted(&self, index: usize, at: At) -> Option<[f64; 2]> {
        let (from_px, from_at) = match self.0.registration {
            Registration::Positions => ([0.0; 2], self.0.at_zero),
            Registration::Image => {
                let r = self.0.registered.read().unwrap_or_else(|e| e.into_inner());
                let j = index.saturating_sub(PREDICT_LAG).checked_sub(r.first)?;
                *r.frames.get(j)?
            }
        };
        let d = self.0.dirs.shift_px(at, from_at);
        Some([from_px[0] + d[0], from_px[1] + d[1]])
    }

    /// The last row (exclusive) the measurement windows reach at `predicted_px`.
    pub fn rows_read(&self, predicted_px: [f64; 2]) -> f64 {
        let h = self.0.size.1 as f64;
        self.0
            .targets
            .iter()
            .map(|c| {
                let (_, y0, side) = measure_window(c, predicted_px);
                (y0 + side as f64).min(h)
            })
            .fold(0.0, f64::max)
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
        let one = |(c, seed): (&Candidate, &Option<Seed>)| {
            let how = (m.channel, m.response);
            measure_in_frame(frame, how, (c, *seed), predicted_px, m.estimator)
        };
        let each = m.targets.iter().zip(&m.seeds);
        if parallel {
            let each: Vec<_> = each.collect();
            each.into_par_iter().map(one).collect()
        } else {
            each.map(one).collect()
        }
    }
}

/// A target's measurement window at its frame-0 place moved by `shift_px`: left, top, side.
pub(super) fn measure_window(c: &Candidate, shift_px: [f64; 2]) -> (f64, f64, u32) {
    let reach = c.outer_radii_px[1] + WINDOW_MARGIN_PX;
    let cx = c.outer_centre_px[0] + shift_px[0];
    let cy = c.outer_centre_px[1] + shift_px[1];
    (
        (cx - reach).floor().max(0.0),
        (cy - reach).floor().max(0.0),
        (2.0 * reach).ceil() as u32 + 1,
    )
}

/// Measure one target in a frame at its frame-0 place moved by `shift_px`, on a window of
/// channel `ch`, the fit started from frame 0's `seed` (frame coordinates) when there is
/// one. `None` when it cannot be measured (out of frame, estimator failure).
pub(super) fn measure_in_frame(
    frame: &RgbImage,
    (ch, response): (usize, Response),
    (c, seed): (&Candidate, Option<Seed>),
    shift_px: [f64; 2],
    estimator: Estimator,
) -> Option<CentreEstimate> {
    let (x0, y0, side) = measure_window(c, shift_px);
    let roi = Roi {
        x: x0 as u32,
        y: y0 as u32,
        w: side,
        h: side,
    };
    let crop = Plane::from_channel_roi_in(frame, ch, roi, response);
    let mv = |p: [f64; 2]| [p[0] + shift_px[0] - x0, p[1] + shift_px[1] - y0];
    let guess = Candidate {
        outer_centre_px: mv(c.outer_centre_px),
        inner_centre_px: mv(c.inner_centre_px),
        outer_radii_px: c.outer_radii_px,
        inner_radii_px: c.inner_radii_px,
        roi: Roi {
            x: 0,
            y: 0,
            w: crop.width as u32,
            h: crop.height as u32,
        },
    };
    let seed = seed.map(|s| s.mapped(mv, 1.0));
    let start = seed.as_ref().map_or(Start::Guess, Start::Track);
    let mut e = estimate_from(&crop, &guess, estimator, 1.0, start).ok()?;
    let back = |p: [f64; 2]| [p[0] + x0, p[1] + y0];
    e.outer_px = back(e.outer_px);
    e.inner_px = back(e.inner_px);
    e.seed = e.seed.map(|s| s.mapped(back, 1.0));
    Some(e)
}
