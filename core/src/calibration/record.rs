//! The calibration record ([`Calibration`]: serde, versioned) and its two uses: fitting it
//! from a [`Scan`] and converting a measured offset with it.

use super::fit::{line_fit, FieldProblem, Layout, LineFit};
use super::ink::InkStatistics;
use super::ink_field::InkField;
use super::ink_margin::InkMargin;
use super::lm::LmResult;
use super::model::{FieldModel, PARAM_NAMES};
use super::outliers::{self, Rejected};
use super::scan::{CalibrationError, Reference, Scan};
use super::validation::{self, ModelCheck};
use crate::board::Board;
use crate::pipeline::lateral::LateralColourFit;
use nalgebra::{DMatrix, DVector, Matrix2, Vector2};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// The record's format; a reader refuses any other.
pub const CALIBRATION_VERSION: u32 = 1;
/// Relative standard uncertainty of the apparent-centre correction: it rests on the fitted
/// field's derivatives (the tilt's and the distortion's second-order effect on a circle's
/// image), which a scan measures less well than the field itself. On the sim's webcam,
/// rendered, the correction (3–16 µm) is off by up to 15 % of itself (docs/calibration.md).
/// With no board (free layout) the perspective is as open as the gauge, and the correction's
/// u is its whole size.
pub const APPARENT_CENTRE_REL_U: f64 = 0.25;
/// Fewest frames a scan needs (a line through each target's centres and its scatter).
pub const MIN_STEPS: usize = 5;
/// Fewest targets the field model needs (scale, perspective, distortion, direction: 6
/// parameters from each target's scale and direction, with redundancy).
pub const MIN_TARGETS: usize = 4;
/// Least image travel: below it the local scale is not measured to a per-mille.
pub const MIN_TRAVEL_PX: f64 = 5.0;

/// How to fit.
#[derive(Debug, Clone, Default)]
pub struct FitOptions {
    /// The board: its nominal layout fixes the field's shape (else it is assumed square
    /// at the frame centre) and names the targets.
    pub board: Option<Board>,
    /// When the calibration was made (RFC 3339, the caller's clock).
    pub date: String,
    /// The rig and camera, as the caller knows them.
    pub rig: Option<String>,
    /// Relative standard uncertainty of the reference's length scale; `None`:
    /// [`Reference::default_rel_u`].
    pub reference_rel_u: Option<f64>,
}

/// What a consumer checks a calibration against.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Fingerprint {
    pub frame_size: [u32; 2],
    /// The global scale the scan was processed with.
    pub scale_um_per_px: f64,
    pub board: Option<String>,
}

/// The scan in brief.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanSummary {
    pub frames: usize,
    /// Median step between frames, µm (stage).
    pub step_um: f64,
    pub travel_um: f64,
    pub piezo_travel_um: Option<f64>,
    /// The session the scan was recorded in, when a daemon's calibration job took it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub session: Option<String>,
}

/// A value with its standard uncertainty.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub name: String,
    pub value: f64,
    pub u: f64,
}

/// One target's calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TargetCalibration {
    pub name: Option<String>,
    /// Outer-circle centre in frame 0.
    pub centre_px: [f64; 2],
    pub steps: usize,
    /// Its own fit: image displacement per µm of stage travel (px/µm), over the travel.
    pub px_per_um: [f64; 2],
    /// Local scale along the stage's axis, µm per px, and its standard uncertainty (from
    /// the residuals of its own line).
    pub scale_um_per_px: f64,
    pub scale_u_um_per_px: f64,
    /// The axis' direction in the image here, rad (atan2 of `px_per_um`).
    pub axis_angle_rad: f64,
    pub axis_angle_u_rad: f64,
    /// The field model's local scale along the axis here, µm per px, its relative
    /// standard uncertainty and that of the axis' angle (rad): the type-B uncertainty a
    /// conversion here carries.
    pub model_scale_um_per_px: f64,
    pub model_scale_rel_u: f64,
    pub model_angle_u_rad: f64,
    /// Its own line's residuals per step: along and across the axis, µm.
    pub residuals_um: Vec<[f64; 2]>,
    pub residual_rms_um: f64,
    pub residual_max_um: f64,
    /// RMS of the field model's residuals at this target, µm.
    pub model_residual_rms_um: f64,
    /// Its own rate against the rate the model fitted without it predicts here, relative,
    /// along and across the axis (`validation`'s leave-one-out; absent with too few
    /// targets).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub left_out_rel_error: Option<[f64; 2]>,
}

/// The field model as fitted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldFit {
    /// `free` (no board) or `board` (the print's layout gives the shape).
    pub layout: String,
    pub model: FieldModel,
    /// Covariance of [`FieldModel::params`] (8 x 8, their units).
    pub covariance: Vec<[f64; 8]>,
    /// Every fitted parameter but the targets' free places, with its uncertainty.
    pub parameters: Vec<Estimate>,
    /// Board displacement direction per µm of stage travel, rad on the board.
    pub stage_dir_rad: f64,
    /// The print's scale against the stage (board layout only; 1 = as designed).
    pub print_scale: Option<f64>,
    /// The image's zoom per µm of stage travel about the frame's centre (board layout
    /// only): the rail out of the board's plane, ~sin(angle)/distance. `model` is the field
    /// at the scan's first frame; a job elsewhere on the rail sees it zoomed by
    /// `1 − zoom·travel`, which the conversion carries as a type B over the scan's travel.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub zoom_per_um: Option<f64>,
    pub residual_rms_px: f64,
    pub residual_rms_um: f64,
    pub residual_max_um: f64,
    /// The model against what it was not fitted to, and its error carried into every
    /// conversion (`validation`). Absent in records made before it was checked: their
    /// residuals give it ([`Calibration::model_check`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub check: Option<ModelCheck>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    pub version: u32,
    /// Short content hash, names the calibration in results.
    pub id: String,
    pub date: String,
    pub method: Reference,
    pub rig: Option<String>,
    pub fingerprint: Fingerprint,
    pub scan: ScanSummary,
    /// Relative standard uncertainty of the reference's length scale, in every type B.
    pub reference_rel_u: f64,
    pub targets: Vec<TargetCalibration>,
    pub field: FieldFit,
    /// Centres and targets left out of the fit as outliers (`outliers`), with why.
    #[serde(default)]
    pub rejected: Vec<Rejected>,
    /// The print's ink density statistics, learnt from the scan's frames (absent when the
    /// scan did not resolve them): jobs take them as the fit's prior when the density is
    /// measurably uneven ([`InkStatistics::prior`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ink: Option<InkStatistics>,
    /// Each target's own density, mapped by the scan when its statistics were learnt: a
    /// job's prior is centred on its target's map ([`InkField`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub ink_fields: Vec<InkField>,
    /// How close to the shapes' edges the ink was read, and the bands it was chosen from
    /// ([`InkMargin`]). Absent in records made before it was chosen (read at 2 blur widths).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ink_margin: Option<InkMargin>,
    /// The lens's lateral colour, measured by the scan at its targets: jobs register the
    /// red and blue channels onto green with it before mixing them (docs/calibration.md).
    /// Absent in records made before it was measured, or when no channel was measured
    /// well enough to move by.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lateral_colour: Option<LateralColourFit>,
}

/// The circles' radii on the board, for the apparent-centre correction: the outer shape's
/// edges (a ring's two, a disk's one twice), the inner's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Radii {
    pub outer_um: [f64; 2],
    pub inner_um: [f64; 2],
}

/// A measured offset converted with the calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct Converted {
    /// Inner centre minus outer centre on the board, µm (board axes: the print's with a
    /// board, else the image's at the frame centre).
    pub offset_um: [f64; 2],
    /// Type-B standard uncertainty of `offset_um` from the calibration (the field model's
    /// covariance and the reference's scale), per axis.
    pub u_b_um: [f64; 2],
    /// d(offset µm)/d(offset px) here: carries a type-A covariance in px to µm.
    pub um_per_px: [[f64; 2]; 2],
    /// The apparent-centre correction applied (inner minus outer), µm.
    pub ellipse_correction_um: [f64; 2],
    /// Part of `u_b_um` per axis: what the field model cannot know (its checked error, the
    /// free layout's gauge and the rail's zoom over the travel, relative to the offset's
    /// length; a quarter of the apparent-centre correction, all of it with no board), µm.
    pub model_u_um: [f64; 2],
}

impl Calibration {
    /// Fit a calibration from a scan measured twice: once as `measure(None)` gives it, and
    /// again as `measure` gives it with that first fit, whose field tells the fits the
    /// ellipses each target's circles image as ([`Calibration::rectify_at`]). The scan's
    /// ink maps are read inside the shapes' edges, where a round model's misfit of an
    /// ellipse 3 % out of round reads as ~2 % of density; the second reading is the
    /// print's. `measure` must not take the first fit's ink as a prior.
    pub fn fit_twice<E: From<CalibrationError>>(
        mut measure: impl FnMut(Option<Arc<Calibration>>) -> Result<Scan, E>,
        opts: &FitOptions,
    ) -> Result<Calibration, E> {
        let first = Calibration::fit(&measure(None)?, opts)?;
        let scan = measure(Some(Arc::new(first)))?;
        Ok(Calibration::fit(&scan, opts)?)
    }

    /// Fit a calibration from a scan.
    pub fn fit(scan: &Scan, opts: &FitOptions) -> Result<Calibration, CalibrationError> {
        scan.check()?;
        let frames = scan.positions_um.len();
        if frames < MIN_STEPS {
            return Err(CalibrationError::TooFewSteps {
                got: frames,
                need: MIN_STEPS,
            });
        }
        let summary = summarise(scan);
        let travel_px = summary.travel_um / scan.scale_um_per_px;
        if travel_px < MIN_TRAVEL_PX {
            return Err(CalibrationError::TooShortTravel {
                travel_px,
                need_px: MIN_TRAVEL_PX,
            });
        }
        let piezo = scan.moves_piezo();
        let min_steps = (frames / 2).max(MIN_STEPS);
        let (clean, mut rejected) = outliers::reject_points(scan, min_steps, piezo);
        let scan = &clean;
        let mut used = usable_targets(scan, opts, min_steps, piezo);
        let (mut problem, mut sol) = solve_field(scan, &used, opts, min_steps)?;
        while used.len() > MIN_TARGETS {
            let rms = target_rms_px(&problem, &sol.residuals);
            let Some((j, reason)) = outliers::worst_target(&rms) else {
                break;
            };
            let (t, _) = used.remove(j);
            rejected.push(Rejected {
                target_index: t,
                target: scan.targets[t].name.clone(),
                step: None,
                residual_px: rms[j],
                reason,
            });
            (problem, sol) = solve_field(scan, &used, opts, min_steps)?;
        }
        let reference_rel_u = opts
            .reference_rel_u
            .unwrap_or(scan.reference.default_rel_u());
        let mut field = field_fit(&problem, &sol.p, &sol.cov, &sol.residuals);
        let mut targets: Vec<TargetCalibration> = used
            .iter()
            .enumerate()
            .map(|(j, (t, l))| target_record(&problem, &sol, j, *t, l, reference_rel_u))
            .collect();
        field.check = Some(check_model(
            scan,
            &used,
            opts,
            min_steps,
            &mut targets,
            (&problem, &sol),
        ));
        let mut cal = Calibration {
            version: CALIBRATION_VERSION,
            id: String::new(),
            date: opts.date.clone(),
            method: scan.reference,
            rig: opts.rig.clone(),
            fingerprint: Fingerprint {
                frame_size: [scan.frame_size.0, scan.frame_size.1],
                scale_um_per_px: scan.scale_um_per_px,
                board: opts.board.as_ref().map(|b| b.name.clone()),
            },
            scan: summary,
            reference_rel_u,
            targets,
            field,
            rejected,
            ink: None,
            ink_fields: Vec::new(),
            ink_margin: None,
            lateral_colour: scan.lateral_colour,
        };
        if !scan.ink_maps.is_empty() {
            let margin = InkMargin::choose(&scan.ink_maps);
            cal.ink =
                InkStatistics::estimate(&scan.ink_maps, scan.scale_um_per_px, margin.margin_s);
            cal.ink_margin = Some(margin);
        }
        if let Some(stats) = &cal.ink {
            let margin_s = cal.ink_margin_s();
            cal.ink_fields = (scan.ink_maps.iter().zip(&scan.targets))
                .filter_map(|(m, t)| InkField::learn(m, t, stats, scan.scale_um_per_px, margin_s))
                .collect();
        }
        cal.id = cal.content_id();
        Ok(cal)
    }

    /// How far inside the shapes' edges the ink statistics and maps were read, blur widths
    /// (a record from before the scan chose it: 2, as they were read then).
    pub fn ink_margin_s(&self) -> f64 {
        (self.ink_margin.as_ref()).map_or(crate::pipeline::DENSITY_EDGE_MARGIN_S, |m| m.margin_s)
    }

    /// `cal-` and 8 hex digits of an FNV-1a hash of the date and the field model.
    fn content_id(&self) -> String {
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        let mut eat = |bytes: &[u8]| {
            for &b in bytes {
                h = (h ^ b as u64).wrapping_mul(0x0100_0000_01b3);
            }
        };
        eat(self.date.as_bytes());
        for p in self.field.model.params() {
            eat(&p.to_bits().to_le_bytes());
        }
        format!("cal-{:08x}", h >> 32)
    }

    /// Whether this calibration fits a run of `frame_size` frames processed at
    /// `scale_um_per_px` on `board`: an error for another frame size (the field is
    /// another), warnings for another scale or board (the conversion does not use them,
    /// but the run's registration and naming do).
    pub fn check(
        &self,
        frame_size: (u32, u32),
        scale_um_per_px: f64,
        board: Option<&str>,
    ) -> Result<Vec<String>, CalibrationError> {
        if self.version != CALIBRATION_VERSION {
            return Err(CalibrationError::Version {
                got: self.version,
                want: CALIBRATION_VERSION,
            });
        }
        let [cw, ch] = self.fingerprint.frame_size;
        if (cw, ch) != frame_size {
            return Err(CalibrationError::FrameSize {
                id: self.id.clone(),
                cal_w: cw,
                cal_h: ch,
                got_w: frame_size.0,
                got_h: frame_size.1,
            });
        }
        for (index, f) in self.ink_fields.iter().enumerate() {
            f.check().map_err(|what| CalibrationError::InkField {
                id: self.id.clone(),
                index,
                what,
            })?;
        }
        if let Some(l) = &self.lateral_colour {
            l.check().map_err(|what| CalibrationError::LateralColour {
                id: self.id.clone(),
                what,
            })?;
        }
        let mut warn = Vec::new();
        let s = self.fingerprint.scale_um_per_px;
        if (s - scale_um_per_px).abs() > 1e-9 * s {
            warn.push(format!(
                "calibration {} was fitted at scale {s} µm/px, this run uses {scale_um_per_px}",
                self.id
            ));
        }
        if let (Some(a), Some(b)) = (self.fingerprint.board.as_deref(), board) {
            if a != b {
                warn.push(format!(
                    "calibration {} was fitted on board {a}, this run has board {b}",
                    self.id
                ));
            }
        }
        Ok(warn)
    }

    /// The map of the target whose outer centre is at `centre_px` (outer rim `rim_px`): the
    /// one whose scan track passes nearest, within half the rim.
    pub fn ink_field_at(&self, centre_px: [f64; 2], rim_px: f64) -> Option<&InkField> {
        (self.ink_fields.iter())
            .map(|f| (f.distance_px(centre_px), f))
            .filter(|(d, _)| *d < 0.5 * rim_px)
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, f)| f)
    }

    /// The map (det 1, row-major) from image offsets about `centre_px` to offsets in which
    /// a printed circle there is round again: the field model's local Jacobian J inverted
    /// and scaled, `J⁻¹·√|det J|`. The fit measures its shapes in it (a circle images as an
    /// ellipse up to ~3 % out of round at a tilted board's corner, and a round model of
    /// it lets the ink's modes take the misfit into the centres). `None` where the model
    /// does not invert.
    pub fn rectify_at(&self, centre_px: [f64; 2]) -> Option<[[f64; 2]; 2]> {
        let m = &self.field.model;
        let j = m.jacobian(m.inverse(centre_px)?);
        let s = j.determinant().abs().sqrt();
        let a = j.try_inverse()? * s;
        Some([[a[(0, 0)], a[(0, 1)]], [a[(1, 0)], a[(1, 1)]]])
    }

    /// Convert an offset measured at `centre_px` (the outer circle's centre) of `offset_px`
    /// (inner minus outer) to µm on the board: the field model inverted exactly over the
    /// offset (not one global scale), the circles' apparent-centre shifts removed.
    pub fn convert(&self, centre_px: [f64; 2], offset_px: [f64; 2], radii: Radii) -> Converted {
        let m = &self.field.model;
        let (o, corr) = solve_offset(m, centre_px, offset_px, radii);
        let um_per_px = linear_part(m, centre_px, offset_px, radii);
        // Type B: the field model's covariance through the conversion, and the reference.
        let p = m.params();
        let grads: Vec<[f64; 2]> = (0..8)
            .map(|k| {
                let h = 1e-6 * p[k].abs().max(typical(m, k));
                let at = |s: f64| {
                    let mut q = p;
                    q[k] += s * h;
                    solve_offset(&m.with_params(&q), centre_px, offset_px, radii).0
                };
                let (a, b) = (at(1.0), at(-1.0));
                [(a[0] - b[0]) / (2.0 * h), (a[1] - b[1]) / (2.0 * h)]
            })
            .collect();
        let cov = &self.field.covariance;
        let length_u = self.model_rel_u(centre_px) * o[0].hypot(o[1]);
        // With no board the perspective the correction rests on is as open as the gauge.
        let corr_rel_u = match self.field.layout.as_str() {
            "free" => 1.0,
            _ => APPARENT_CENTRE_REL_U,
        };
        let model_u_um = corr.map(|c| length_u.hypot(corr_rel_u * c));
        let u_b_um = std::array::from_fn(|axis| {
            let mut v = 0.0;
            for i in 0..8 {
                for k in 0..8 {
                    v += grads[i][axis] * cov[i][k] * grads[k][axis];
                }
            }
            let reference = self.reference_rel_u * o[axis];
            let model = model_u_um[axis];
            (v.max(0.0) + reference * reference + model * model).sqrt()
        });
        Converted {
            offset_um: o,
            u_b_um,
            um_per_px,
            ellipse_correction_um: corr,
            model_u_um,
        }
    }

    /// The field model against its scan: the record's check, or for a record made before
    /// checks were recorded, its targets' residuals read as one.
    pub fn model_check(&self) -> ModelCheck {
        if let Some(c) = &self.field.check {
            return c.clone();
        }
        let per_target: Vec<_> = (self.targets.iter())
            .map(|t| {
                validation::residual_mismatch(
                    t.model_residual_rms_um,
                    t.residual_rms_um,
                    self.scan.travel_um,
                    t.steps,
                )
            })
            .collect();
        validation::summarise("residuals", &per_target)
    }

    /// The relative standard uncertainty a conversion at `centre_px` carries for what the
    /// field model cannot know: its checked error, and with no board the gauge a 1-D scan
    /// leaves open.
    pub fn model_rel_u(&self, centre_px: [f64; 2]) -> f64 {
        // The recorded check without a copy (this runs per converted offset).
        let checked = (self.field.check.as_ref())
            .map_or_else(|| self.model_check().model_rel_u, |c| c.model_rel_u);
        let gauge = match self.field.layout.as_str() {
            "free" => {
                validation::gauge_rel_u(&self.field.model, self.field.stage_dir_rad, centre_px)
            }
            _ => 0.0,
        };
        // A job anywhere on the calibrated travel: the zoom there, rectangular.
        let zoom = self.field.zoom_per_um.unwrap_or(0.0).abs() * self.scan.travel_um / 3f64.sqrt();
        (checked * checked + gauge * gauge + zoom * zoom).sqrt()
    }
}

/// A parameter's typical size, for a finite-difference step where its value is 0.
fn typical(m: &FieldModel, k: usize) -> f64 {
    let s = m.a_px_per_um[0][0].abs();
    match k {
        0..=3 => s,
        4 | 5 => s / m.norm_radius_px,
        _ => 0.01,
    }
}

/// The board offset `o` with `apparent(inner at b + o) − apparent(outer at b) = offset`,
/// and the apparent-centre correction (µm) it removed.
fn solve_offset(
    m: &FieldModel,
    centre_px: [f64; 2],
    offset_px: [f64; 2],
    r: Radii,
) -> ([f64; 2], [f64; 2]) {
    let mean_shift = |b: [f64; 2], radii: [f64; 2]| {
        let (s0, s1) = (
            m.apparent_shift_px(b, radii[0]),
            m.apparent_shift_px(b, radii[1]),
        );
        [(s0[0] + s1[0]) / 2.0, (s0[1] + s1[1]) / 2.0]
    };
    // The outer circle's true centre: its apparent one less its shift (once is enough:
    // the shift changes by ~1e-5 px over the ~0.01 px it moves the point).
    let b0 = m.inverse(centre_px).unwrap_or([0.0; 2]);
    let so = mean_shift(b0, r.outer_um);
    let b = m
        .inverse([centre_px[0] - so[0], centre_px[1] - so[1]])
        .unwrap_or(b0);
    let x_out = m.forward(b);
    let j = m.jacobian(b);
    let ji = j.try_inverse().unwrap_or(Matrix2::zeros());
    let mut o = ji * Vector2::new(offset_px[0], offset_px[1]);
    let si = mean_shift([b[0] + o[0], b[1] + o[1]], r.inner_um);
    // Apparent inner minus apparent outer must equal the measured offset.
    let target = [
        x_out[0] + so[0] + offset_px[0] - si[0],
        x_out[1] + so[1] + offset_px[1] - si[1],
    ];
    for _ in 0..5 {
        let bi = [b[0] + o[0], b[1] + o[1]];
        let x = m.forward(bi);
        let r = Vector2::new(target[0] - x[0], target[1] - x[1]);
        o += m.jacobian(bi).try_inverse().unwrap_or(Matrix2::zeros()) * r;
    }
    let corr = ji * Vector2::new(so[0] - si[0], so[1] - si[1]);
    ([o[0], o[1]], [corr[0], corr[1]])
}

/// d(offset µm)/d(offset px) at this offset (central differences of the conversion).
fn linear_part(m: &FieldModel, c: [f64; 2], off: [f64; 2], r: Radii) -> [[f64; 2]; 2] {
    let h = 1e-3;
    let col = |k: usize| {
        let (mut a, mut b) = (off, off);
        a[k] += h;
        b[k] -= h;
        let (oa, ob) = (solve_offset(m, c, a, r).0, solve_offset(m, c, b, r).0);
        [(oa[0] - ob[0]) / (2.0 * h), (oa[1] - ob[1]) / (2.0 * h)]
    };
    let (cx, cy) = (col(0), col(1));
    [[cx[0], cy[0]], [cx[1], cy[1]]]
}

/// The targets with a line over at least `min_steps` centres (and, with a board, a name on
/// it), by scan index.
fn usable_targets(
    scan: &Scan,
    opts: &FitOptions,
    min_steps: usize,
    piezo: bool,
) -> Vec<(usize, LineFit)> {
    let mut used: Vec<(usize, LineFit)> = (0..scan.targets.len())
        .filter_map(|t| Some((t, line_fit(scan, t, min_steps, piezo)?)))
        .collect();
    if opts.board.is_some() {
        used.retain(|(t, _)| nominal_um(scan, opts, *t).is_some());
    }
    used
}

/// Target `t`'s centre on the board's print, when it is named on it.
fn nominal_um(scan: &Scan, opts: &FitOptions, t: usize) -> Option<[f64; 2]> {
    let b = opts.board.as_ref()?;
    Some(b.target(scan.targets[t].name.as_deref()?)?.centre_um)
}

/// The field model fitted over the `used` targets.
fn solve_field<'a>(
    scan: &'a Scan,
    used: &[(usize, LineFit)],
    opts: &FitOptions,
    min_steps: usize,
) -> Result<(FieldProblem<'a>, LmResult), CalibrationError> {
    if used.len() < MIN_TARGETS {
        return Err(CalibrationError::TooFewTargets {
            got: used.len(),
            need: MIN_TARGETS,
            steps: min_steps,
        });
    }
    let layout = match &opts.board {
        Some(_) => Layout::Board {
            nominal_um: used
                .iter()
                .map(|(t, _)| nominal_um(scan, opts, *t).expect("usable_targets kept named ones"))
                .collect(),
        },
        None => Layout::Free,
    };
    let problem = FieldProblem {
        scan,
        targets: used.iter().map(|(t, _)| *t).collect(),
        layout,
        piezo: scan.moves_piezo(),
        base: FieldModel::plain(scan.frame_size, scan.scale_um_per_px),
    };
    let lines: Vec<LineFit> = used.iter().map(|(_, l)| l.clone()).collect();
    let sol = problem.solve(&lines)?;
    Ok((problem, sol))
}

/// Each fitted target's RMS residual (px, per centre) against the model, from the fit's
/// residual vector (`FieldProblem::residuals`' order: target by target, x and y).
fn target_rms_px(problem: &FieldProblem, residuals: &[f64]) -> Vec<f64> {
    let mut at = 0;
    problem
        .targets
        .iter()
        .map(|&t| {
            let n = problem.scan.targets[t].centres_px.iter().flatten().count();
            let r = &residuals[at..at + 2 * n];
            at += 2 * n;
            (r.iter().map(|v| v * v).sum::<f64>() / n.max(1) as f64).sqrt()
        })
        .collect()
}

fn summarise(scan: &Scan) -> ScanSummary {
    let mut steps: Vec<f64> = scan
        .positions_um
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .collect();
    steps.sort_by(f64::total_cmp);
    let span = |v: &[f64]| {
        let (lo, hi) = v
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        hi - lo
    };
    ScanSummary {
        frames: scan.positions_um.len(),
        step_um: steps.get(steps.len() / 2).copied().unwrap_or(0.0),
        travel_um: span(&scan.positions_um),
        piezo_travel_um: scan.piezo_um.as_deref().map(span),
        session: None,
    }
}

/// The field model's record: parameters, covariance, residuals.
fn field_fit(pr: &FieldProblem, p: &[f64], cov: &DMatrix<f64>, res: &[f64]) -> FieldFit {
    let model = pr.model(p);
    let t = pr.model_selection(p.len());
    let mc = &t * cov * t.transpose();
    let covariance = (0..8)
        .map(|i| std::array::from_fn(|k| mc[(i, k)]))
        .collect();
    let ix = pr.ix();
    let u = |k: usize| cov[(k, k)].max(0.0).sqrt();
    let mut parameters: Vec<Estimate> = PARAM_NAMES
        .iter()
        .enumerate()
        .map(|(k, n)| Estimate {
            name: n.to_string(),
            value: model.params()[k],
            u: mc[(k, k)].max(0.0).sqrt(),
        })
        .collect();
    let mut named = |name: &str, k: usize| {
        parameters.push(Estimate {
            name: name.into(),
            value: p[k],
            u: u(k),
        })
    };
    named("stage_dir_rad", ix.stage_dir);
    if let Some(k) = ix.piezo_dir {
        named("piezo_dir_rad", k);
    }
    if let Some(k) = ix.zoom {
        named("rail_zoom_per_um", k);
    }
    let print_scale = match pr.layout {
        Layout::Board { .. } => {
            named("board_ox_um", ix.layout);
            named("board_oy_um", ix.layout + 1);
            named("print_scale", ix.layout + 2);
            Some(p[ix.layout + 2])
        }
        Layout::Free => None,
    };
    let scale = 1.0 / model.a_px_per_um[0][0].hypot(model.a_px_per_um[1][0]);
    let rms = (res.iter().map(|r| r * r).sum::<f64>() / (res.len() / 2).max(1) as f64).sqrt();
    let max = res.chunks(2).map(|r| r[0].hypot(r[1])).fold(0.0, f64::max);
    FieldFit {
        layout: match pr.layout {
            Layout::Free => "free".into(),
            Layout::Board { .. } => "board".into(),
        },
        model,
        covariance,
        parameters,
        stage_dir_rad: p[ix.stage_dir],
        zoom_per_um: ix.zoom.map(|k| p[k]),
        print_scale,
        residual_rms_px: rms,
        residual_rms_um: rms * scale,
        residual_max_um: max * scale,
        check: None,
    }
}

/// Target `j` of the fit (`t` in the scan): its own line and the model's view of it.
fn target_record(
    pr: &FieldProblem,
    sol: &super::lm::LmResult,
    j: usize,
    t: usize,
    l: &LineFit,
    reference_rel_u: f64,
) -> TargetCalibration {
    let speed = l.v.norm();
    let along = l.v / speed;
    let across = Vector2::new(-along[1], along[0]);
    let residuals_um: Vec<[f64; 2]> = l
        .residuals_px
        .iter()
        .map(|(_, r)| {
            let r = Vector2::new(r[0], r[1]);
            [r.dot(&along) / speed, r.dot(&across) / speed]
        })
        .collect();
    let n = residuals_um.len().max(1) as f64;
    let rms = (residuals_um
        .iter()
        .map(|r| r[0] * r[0] + r[1] * r[1])
        .sum::<f64>()
        / n)
        .sqrt();
    let max = residuals_um
        .iter()
        .map(|r| r[0].hypot(r[1]))
        .fold(0.0, f64::max);
    let u_speed = (along.transpose() * l.v_cov * along)[0].max(0.0).sqrt();
    let u_angle = (across.transpose() * l.v_cov * across)[0].max(0.0).sqrt() / speed;
    // The model here, at the middle of the travel; its uncertainty from the fit's.
    let frames = pr.scan.positions_um.len();
    let model_v = |p: &[f64]| -> Vector2<f64> {
        let s = pr.scan.travel_um(frames / 2)[0];
        let b = pr.point(p, j, frames / 2);
        let (d, _) = pr.dirs(p);
        pr.velocity(p, [b[0] - s * d[0], b[1] - s * d[1]], s)
    };
    let v0 = model_v(&sol.p);
    let (grad_s, grad_a) = model_gradients(&sol.p, &sol.typ, &model_v, v0);
    let var = |g: &DVector<f64>| (g.transpose() * &sol.cov * g)[0].max(0.0);
    let rel_u = (var(&grad_s) + reference_rel_u * reference_rel_u).sqrt();
    let model_res = model_residual_rms_um(pr, sol, j, 1.0 / v0.norm());
    TargetCalibration {
        name: pr.scan.targets[t].name.clone(),
        centre_px: pr.scan.targets[t].centres_px[0].unwrap_or(l.x0_px),
        steps: l.residuals_px.len(),
        px_per_um: [l.v[0], l.v[1]],
        scale_um_per_px: 1.0 / speed,
        scale_u_um_per_px: u_speed / (speed * speed),
        axis_angle_rad: l.v[1].atan2(l.v[0]),
        axis_angle_u_rad: u_angle,
        model_scale_um_per_px: 1.0 / v0.norm(),
        model_scale_rel_u: rel_u,
        model_angle_u_rad: var(&grad_a).sqrt(),
        residuals_um,
        residual_rms_um: rms,
        residual_max_um: max,
        model_residual_rms_um: model_res,
        left_out_rel_error: None,
    }
}

/// Check the field model fitted over `used` (`validation`): each target left out in turn
/// and predicted by the others when there are enough, else the residuals. Records each
/// target's mismatch in `targets` (in `used`'s order).
fn check_model(
    scan: &Scan,
    used: &[(usize, LineFit)],
    opts: &FitOptions,
    min_steps: usize,
    targets: &mut [TargetCalibration],
    (problem, sol): (&FieldProblem, &LmResult),
) -> ModelCheck {
    let left_out: Option<Vec<_>> = (used.len() >= validation::MIN_LEAVE_ONE_OUT)
        .then(|| {
            (0..used.len())
                .map(|j| predict_left_out(scan, used, j, opts, min_steps))
                .collect()
        })
        .flatten();
    let per_target: Vec<_> = (0..used.len())
        .map(|j| residual_parts(problem, sol, used, j))
        .collect();
    let residuals = validation::summarise("residuals", &per_target);
    let Some(left_out) = left_out else {
        return residuals;
    };
    for (t, (e, _)) in targets.iter_mut().zip(&left_out) {
        t.left_out_rel_error = Some(*e);
    }
    validation::summarise("leave-one-out", &left_out).and(residuals)
}

/// Fitted target `j`'s model residuals split into a ramp over the travel and a constant:
/// (mismatch, noise) with the ramp read as a rate error (relative to the rate) and the
/// constant as a scale error over the distance to the nearest other target (a misplaced
/// print moves one target; a field the model misdescribes moves them by their distances).
fn residual_parts(
    pr: &FieldProblem,
    sol: &LmResult,
    used: &[(usize, LineFit)],
    j: usize,
) -> ([f64; 2], [f64; 2]) {
    let m = pr.model(&sol.p);
    let line = &used[j].1;
    let pts: Vec<(f64, Vector2<f64>)> = (pr.scan.targets[pr.targets[j]].centres_px.iter())
        .enumerate()
        .filter_map(|(i, c)| {
            let c = (*c)?;
            let x = pr.image(&sol.p, &m, j, i);
            Some((
                pr.scan.travel_um(i)[0],
                Vector2::new(c[0] - x[0], c[1] - x[1]),
            ))
        })
        .collect();
    let n = pts.len().max(1) as f64;
    let s_mean = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let r_mean = pts.iter().map(|p| p.1).sum::<Vector2<f64>>() / n;
    let s_var = pts.iter().map(|p| (p.0 - s_mean).powi(2)).sum::<f64>() / n;
    let slope = pts
        .iter()
        .map(|p| (p.1 - r_mean) * (p.0 - s_mean))
        .sum::<Vector2<f64>>()
        / (n * s_var.max(1e-300));
    // The line's own scatter per component, px.
    let sigma = (line.residuals_px.iter())
        .map(|(_, r)| (r[0] * r[0] + r[1] * r[1]) / 2.0)
        .sum::<f64>()
        .sqrt()
        / n.sqrt();
    let speed = line.v.norm();
    let spacing = (used.iter().enumerate())
        .filter(|(k, _)| *k != j)
        .map(|(_, (_, l))| (Vector2::from(l.x0_px) - Vector2::from(line.x0_px)).norm())
        .fold(f64::INFINITY, f64::min);
    let ramp = slope.norm() / speed;
    let ramp_noise = sigma / (s_var.sqrt() * n.sqrt() * speed);
    let place = r_mean.norm() / spacing;
    let place_noise = sigma / (n.sqrt() * spacing);
    ([ramp, place], [ramp_noise, place_noise])
}

/// Target `j` of `used` against the model fitted without it: (mismatch, noise), relative.
fn predict_left_out(
    scan: &Scan,
    used: &[(usize, LineFit)],
    j: usize,
    opts: &FitOptions,
    min_steps: usize,
) -> Option<([f64; 2], [f64; 2])> {
    let others: Vec<(usize, LineFit)> = (used.iter().enumerate())
        .filter(|(k, _)| *k != j)
        .map(|(_, u)| u.clone())
        .collect();
    let (pr, sol) = solve_field(scan, &others, opts, min_steps).ok()?;
    let line = &used[j].1;
    // The line's slope is the rate at the middle of its travel (its path curves where the
    // scale changes): predict it there.
    let mid = scan.travel_um(scan.positions_um.len() / 2);
    // (The piezo's travel does not move the point's rate along the stage: stage only.)
    let predict = |p: &[f64]| -> Option<Vector2<f64>> {
        let b = pr.model(p).inverse(line.x0_px)?;
        Some(pr.velocity(p, b, mid[0]))
    };
    let v0 = predict(&sol.p)?;
    // The prediction's own variance: the left-out fit's covariance through it.
    let (along, across) = validation::axes(v0);
    let (mut ga, mut gc) = (DVector::zeros(sol.p.len()), DVector::zeros(sol.p.len()));
    for k in 0..sol.p.len() {
        let h = 1e-6 * sol.typ[k];
        let mut q = sol.p.clone();
        q[k] += h;
        let dv = (predict(&q)? - v0) / (h * v0.norm());
        (ga[k], gc[k]) = (dv.dot(&along), dv.dot(&across));
    }
    let var = |g: &DVector<f64>| (g.transpose() * &sol.cov * g)[0].max(0.0);
    Some(validation::rate_mismatch(line, v0, [var(&ga), var(&gc)]))
}

/// Gradients over the fit's parameters of ln|v| and of v's angle.
fn model_gradients(
    p: &[f64],
    typ: &[f64],
    model_v: &dyn Fn(&[f64]) -> Vector2<f64>,
    v0: Vector2<f64>,
) -> (DVector<f64>, DVector<f64>) {
    let mut gs = DVector::zeros(p.len());
    let mut ga = DVector::zeros(p.len());
    for k in 0..p.len() {
        let h = 1e-6 * typ[k];
        let mut q = p.to_vec();
        q[k] += h;
        let v = model_v(&q);
        gs[k] = (v.norm().ln() - v0.norm().ln()) / h;
        let da = (v[1].atan2(v[0]) - v0[1].atan2(v0[0]) + std::f64::consts::PI)
            .rem_euclid(std::f64::consts::TAU)
            - std::f64::consts::PI;
        ga[k] = da / h;
    }
    (gs, ga)
}

/// RMS of the field model's residuals at fitted target `j`, µm at `scale` µm/px.
fn model_residual_rms_um(
    pr: &FieldProblem,
    sol: &super::lm::LmResult,
    j: usize,
    scale: f64,
) -> f64 {
    // The residual vector is laid out target by target, two numbers per measured centre.
    let start: usize = pr.targets[..j]
        .iter()
        .map(|&t| pr.scan.targets[t].centres_px.iter().flatten().count() * 2)
        .sum();
    let n = pr.scan.targets[pr.targets[j]]
        .centres_px
        .iter()
        .flatten()
        .count();
    let r = &sol.residuals[start..start + 2 * n];
    (r.iter().map(|x| x * x).sum::<f64>() / n.max(1) as f64).sqrt() * scale
}
