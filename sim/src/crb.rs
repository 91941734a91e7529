//! The Cramér–Rao bound on a target's measured offset, from the renderer itself.
//!
//! The Fisher information of one frame's pixels about the parameters θ of what is rendered:
//! `F = Σ_pixels Σ_channels ∂μ/∂θ ∂μ/∂θᵀ / var(μ)`, with μ the expected DN from
//! `render::expected_rgb` (derivatives by central differences of real renders, so the bound
//! holds for exactly what the simulator draws, pixel area integration and all) and var(μ)
//! from `CameraModel::noise_var_dn2` (shot + read + quantisation noise). θ holds the
//! quantity of interest, both centres, and the nuisance parameters an estimator does not
//! know: the ring's and the inner shape's radii, the lens blur, the illumination level,
//! gradient and vignetting, and the ink's reflectance in each channel used. The bound on the
//! offset (inner minus outer centre) is `eᵀF⁻¹e` per axis.
//!
//! The signal-dependence of the noise variance also carries (a little) information; it is
//! left out, so this is the bound for estimators that treat the noise as a known-variance
//! Gaussian, which is what a least-squares fit is.

use crate::board::{Board, Shape};
use crate::camera::CameraModel;
use crate::render::{expected_rgb, View};
use nalgebra::{DMatrix, DVector};

/// What one parameter of θ changes, and by how much for the central difference.
#[derive(Debug, Clone, Copy)]
enum Param {
    OuterX,
    OuterY,
    InnerX,
    InnerY,
    /// Radius `i` of the outer ring (0 = hole, 1 = rim) or of the inner shape (2 = rim, 3 = hole).
    Radius(usize),
    Blur,
    Light,
    Gradient,
    Vignetting,
    Ink(usize),
}

/// One-sigma bound on the offset (inner minus outer centre) of target `target_index`, in µm
/// on the board, x and y, for an estimator that uses only the measurement channel (the one
/// with the most ink-to-paper contrast, as rigd picks it).
pub fn offset_crb_um(
    board: &Board,
    cam: &CameraModel,
    target_index: usize,
    view: View,
) -> [f64; 2] {
    let ch = measurement_channel(board);
    offset_crb_um_channels(board, cam, target_index, view, &[ch])
}

/// The channel with the most ink-to-paper contrast.
pub fn measurement_channel(board: &Board) -> usize {
    (0..3)
        .max_by(|&a, &b| {
            let ca = (board.paper_rgb[a] - board.ink_rgb[a]).abs();
            let cb = (board.paper_rgb[b] - board.ink_rgb[b]).abs();
            ca.total_cmp(&cb)
        })
        .unwrap_or(1)
}

/// The bound for an estimator that uses the given channels (0 = R, 1 = G, 2 = B).
///
/// # Panics
/// If `target_index` is not a target of `board` or a channel is not 0..3 (caller errors).
pub fn offset_crb_um_channels(
    board: &Board,
    cam: &CameraModel,
    target_index: usize,
    view: View,
    channels: &[usize],
) -> [f64; 2] {
    assert!(channels.iter().all(|&c| c < 3), "channels must be 0..3");
    let observe = |rgb: &[f32], _roi: [u32; 4]| -> Vec<f64> {
        rgb.iter()
            .enumerate()
            .filter(|(i, _)| channels.contains(&(i % 3)))
            .map(|(_, &v)| v as f64)
            .collect()
    };
    let var = |m: f64| cam.noise_var_dn2(m);
    offset_crb(board, cam, target_index, view, channels, &observe, &var)
}

/// The bound from the sensor's own samples, before any processing: one Bayer sample per
/// pixel (with the camera's colour crosstalk) for an RGGB sensor, all three channels
/// otherwise; shot and read noise, quantisation of the 10-bit raw. Whatever the camera does
/// afterwards (demosaicing, gamma, sharpening, MJPEG) only loses information, so this bounds
/// every estimator working on the delivered frames, for any camera profile. The lens
/// (tilt, distortion, lateral colour) and the print's roughness are rendered but taken as
/// known (not nuisance parameters): the bound is for an estimator that knows its lens.
pub fn offset_crb_um_raw(
    board: &Board,
    cam: &CameraModel,
    target_index: usize,
    view: View,
) -> [f64; 2] {
    let (observe, var) = raw_sensor(cam);
    offset_crb(board, cam, target_index, view, &[0, 1, 2], &observe, &var)
}

/// The bound on the offset of target `target_index` over `frames` raw frames (the views'
/// information averaged, times `frames`) for an estimator that does not know the print's
/// ink density where the target is, only its statistics: the density `1 + ε` is a
/// Gaussian field of the camera's RMS and correlation length (`ink_density_rms`,
/// `ink_density_corr_um`), written in its Karhunen–Loève modes over the target, each mode
/// a nuisance parameter with its prior (a hybrid Cramér–Rao bound: Fisher information of
/// the samples plus the prior's, `J = N·F̄ + diag(0, I)`). Unlike the bound with the print
/// known, it bounds the whole mean squared error over prints, the bias an unknown density
/// leaves included. The modes' derivatives are taken at ε = 0 (the field is a few % of
/// the ink's depth), mapped to the image by the lens's local affine map at the target.
/// Equal to `offset_crb_um_raw / √frames` (one view) when the print's ink is even.
pub fn offset_hcrb_um_raw(
    board: &Board,
    cam: &CameraModel,
    target_index: usize,
    views: &[View],
    frames: usize,
) -> [f64; 2] {
    PrintUnknown::new(board, cam, target_index, views).offset_um(frames)
}

/// One frame's information about a target and the print's density modes there, averaged
/// over views, from which [`offset_hcrb_um_raw`] follows for any number of frames.
pub struct PrintUnknown {
    fisher: DMatrix<f64>,
    modes: usize,
}

impl PrintUnknown {
    pub fn new(board: &Board, cam: &CameraModel, target_index: usize, views: &[View]) -> Self {
        assert!(!views.is_empty(), "at least one view");
        let (observe, var) = raw_sensor(cam);
        let mut fisher: Option<DMatrix<f64>> = None;
        // The same modes on every view (a grid about the target's centre on the board).
        let modes = DensityModes::over(board, cam, target_index);
        for &view in views {
            let f = information(
                board,
                cam,
                (target_index, view),
                &[0, 1, 2],
                (&observe, &var),
                modes.as_ref(),
            ) / views.len() as f64;
            fisher = Some(match fisher {
                Some(s) => s + f,
                None => f,
            });
        }
        PrintUnknown {
            fisher: fisher.expect("a view"),
            modes: modes.map_or(0, |m| m.len()),
        }
    }

    /// The bound over `frames` frames: `J = frames·F̄ + diag(0, I)`.
    pub fn offset_um(&self, frames: usize) -> [f64; 2] {
        assert!(frames > 0, "at least one frame");
        let mut j = &self.fisher * frames as f64;
        let n = j.nrows();
        for i in n - self.modes..n {
            j[(i, i)] += 1.0;
        }
        offset_bound(j)
    }
}

/// The raw sensor's samples of a rendered ROI and their noise variance: one Bayer sample
/// per pixel (with the camera's colour crosstalk) for an RGGB sensor, all three channels
/// otherwise; shot and read noise, quantisation of the 10-bit raw.
fn raw_sensor(cam: &CameraModel) -> (Box<Observe<'_>>, Box<dyn Fn(f64) -> f64 + '_>) {
    let bayer = crate::isp::bayer(cam);
    let c = cam.crosstalk as f32;
    let observe = move |rgb: &[f32], roi: [u32; 4]| -> Vec<f64> {
        if !bayer {
            return rgb.iter().map(|&v| v as f64).collect();
        }
        let [x0, y0, w, _] = roi;
        rgb.chunks(3)
            .enumerate()
            .map(|(i, p)| {
                let (x, y) = (x0 as usize + i % w as usize, y0 as usize + i / w as usize);
                crate::isp::mixed(p, crate::isp::cfa_channel(x, y), c) as f64
            })
            .collect()
    };
    let q = (crate::isp::RAW_STEP_DN as f64).powi(2) / 12.0;
    let var = move |m: f64| cam.noise_var_dn2(m) - 1.0 / 12.0 + q;
    (Box::new(observe), Box::new(var))
}

/// What an estimator sees of a rendered ROI (RGB f32, its box): the samples it gets.
type Observe<'a> = dyn Fn(&[f32], [u32; 4]) -> Vec<f64> + 'a;

/// The bound for samples `observe(rendered RGB of the ROI, roi)` with noise variance
/// `var(expected sample)`; `channels` are the ink reflectances taken as unknown.
fn offset_crb(
    board: &Board,
    cam: &CameraModel,
    target_index: usize,
    view: View,
    channels: &[usize],
    observe: &Observe,
    var: &dyn Fn(f64) -> f64,
) -> [f64; 2] {
    let f = information(
        board,
        cam,
        (target_index, view),
        channels,
        (observe, var),
        None,
    );
    offset_bound(f)
}

/// θ: both centres (outer first: indices 0..4 are outer x, y, inner x, y), the radii, the
/// blur, the light, and the ink's reflectance in `channels`.
fn parameters(board: &Board, target_index: usize, channels: &[usize]) -> Vec<Param> {
    let mut params = vec![
        Param::OuterX,
        Param::OuterY,
        Param::InnerX,
        Param::InnerY,
        Param::Radius(0),
        Param::Radius(1),
        Param::Radius(2),
    ];
    if matches!(board.targets[target_index].inner, Shape::Ring { .. }) {
        params.push(Param::Radius(3));
    }
    params.extend([
        Param::Blur,
        Param::Light,
        Param::Gradient,
        Param::Vignetting,
    ]);
    params.extend(channels.iter().map(|&c| Param::Ink(c)));
    params
}

/// The ROI that holds all of a target's blurred edges.
fn target_roi(cam: &CameraModel, target: &crate::board::Target, view: View) -> [u32; 4] {
    let (c, grow) = if cam.needs_warp() {
        let lens = crate::optics::Lens::new(cam);
        (
            view.project(cam, 1, target.centre_um),
            lens.max_scale_ratio(cam),
        )
    } else {
        (view.board_to_image(cam, target.centre_um), 1.0)
    };
    let half = grow * target.outer.outer_radius_um() / cam.scale_um_per_px
        + 5.0 * cam.psf_sigma_px
        + 3.0
        + if grow > 1.0 { 2.0 } else { 0.0 };
    let x0 = (c[0] - half).floor().max(0.0) as u32;
    let y0 = (c[1] - half).floor().max(0.0) as u32;
    let x1 = ((c[0] + half).ceil() as u32).min(cam.width.saturating_sub(1));
    let y1 = ((c[1] + half).ceil() as u32).min(cam.height.saturating_sub(1));
    [x0, y0, x1 + 1 - x0, y1 + 1 - y0]
}

/// The Fisher information of one frame's samples of target `t` about θ ([`parameters`])
/// and, after them, the print's density `modes` when given.
fn information(
    board: &Board,
    cam: &CameraModel,
    (target_index, view): (usize, View),
    channels: &[usize],
    (observe, var): (&Observe, &dyn Fn(f64) -> f64),
    modes: Option<&DensityModes>,
) -> DMatrix<f64> {
    let target = &board.targets[target_index];
    // Render only this target, in a window that holds all of its blurred edges.
    let mut base = board.clone();
    base.targets = vec![target.clone()];
    base.clutter.clear();
    let roi = target_roi(cam, target, view);
    let params = parameters(board, target_index, channels);

    let render = |b: &Board, cm: &CameraModel, light: f64| expected_rgb(b, cm, &view, roi, light);
    let mu = observe(&render(&base, cam, 1.0), roi);
    let step_um = 0.02 * cam.scale_um_per_px;
    // Derivatives of every pixel's channels, per unit of each parameter (µm for lengths).
    let mut derivs: Vec<Vec<f64>> = params
        .iter()
        .map(|&p| {
            let (h, plus, minus) = perturb(&base, cam, p, step_um);
            let (lp, lm) = match p {
                Param::Light => (1.0 + h, 1.0 - h),
                _ => (1.0, 1.0),
            };
            let a = observe(&render(&plus.0, &plus.1, lp), roi);
            let b = observe(&render(&minus.0, &minus.1, lm), roi);
            a.iter()
                .zip(&b)
                .map(|(&a, &b)| (a - b) / (2.0 * h))
                .collect()
        })
        .collect();
    if let Some(m) = modes {
        // The samples are linear in the density: a sample's change per unit of ε is minus
        // the ink's depth there (paper minus the evenly inked render, both through the
        // lens), blurred with it (`InkDepth`).
        let even = CameraModel {
            ink_density_rms: 0.0,
            ..cam.clone()
        };
        let mut paper = base.clone();
        paper.targets.clear();
        let depth_seen = |dx_um: f64, dy_um: f64| -> Vec<f64> {
            let v = View {
                camera_um: [view.camera_um[0] + dx_um, view.camera_um[1] + dy_um],
                ..view
            };
            let at = |b: &Board| expected_rgb(b, &even, &v, roi, 1.0);
            at(&paper)
                .iter()
                .zip(at(&base))
                .map(|(p, i)| (p - i) as f64)
                .collect()
        };
        let to_board = Affine::at(cam, view, target.centre_um);
        let depth = InkDepth::seen(depth_seen, step_um, to_board.a, cam.psf_sigma_px.powi(2));
        derivs.extend(m.derivatives(&depth, (roi, to_board), observe));
    }

    // F = Dᵀ·W·D: each sample's derivatives scaled by its noise's 1/σ, one matrix product.
    let d = DMatrix::from_fn(mu.len(), derivs.len(), |i, j| {
        derivs[j][i] / var(mu[i]).sqrt()
    });
    d.transpose() * d
}

/// `eᵀ J⁻¹ e` per axis, e = inner − outer centre (θ's first four entries).
fn offset_bound(j: DMatrix<f64>) -> [f64; 2] {
    let n = j.nrows();
    let inv = j
        .cholesky()
        .map(|c| c.inverse())
        .expect("the Fisher information of a rendered target is positive definite");
    let var = |outer: usize, inner: usize| {
        let mut e = DVector::<f64>::zeros(n);
        e[outer] = -1.0;
        e[inner] = 1.0;
        (e.transpose() * &inv * &e)[(0, 0)]
    };
    [var(0, 2).sqrt(), var(1, 3).sqrt()]
}

/// The print's ink density over one target as a Gaussian field (`ink_density_rms`,
/// correlation `ink_density_corr_um`: the sim's covariance `rms² exp(−d²/2ℓ²)`), in its
/// Karhunen–Loève modes on a grid ℓ/2 apart over the target, each scaled to unit prior
/// variance and extended between grid points by the covariance (kriging). The pipeline's
/// prior (`fit::prior`) builds its own, coarser basis: the bound shares no code with the
/// estimator it judges.
///
/// The Gaussian covariance on a square grid is separable, `rms²·K ⊗ K` with `K` the 1-D
/// grid's: its modes are products of the 1-D modes, `v_a ⊗ v_b` with variance
/// `rms²·μ_a·μ_b`, and a mode extended to a board point p is `rms·X_a(p_x)·X_b(p_y)`,
/// `X_a(x) = Σ_i exp(−(x − g_i)²/2ℓ²)·v_a(i)/√μ_a`. So the decomposition is of the 1-D
/// grid's small matrix, and each pixel costs a few hundred operations, not the full grid's.
struct DensityModes {
    /// The target's centre on the board (µm); the grid is `centre + (i, j)·spacing`.
    centre_um: [f64; 2],
    /// The 1-D grid's offsets from the centre (µm), the same along x and y.
    axis_um: Vec<f64>,
    /// The 1-D modes' kriging weights `v_a / √μ_a`, one per kept 1-D mode.
    axis_weights: Vec<DVector<f64>>,
    /// The kept 2-D modes: pairs (x mode, y mode) of the 1-D ones.
    pairs: Vec<(usize, usize)>,
    rms: f64,
    corr_um: f64,
}

impl DensityModes {
    /// Modes whose variance is at least 10⁻⁶ of the largest's; `None` when the ink is even.
    fn over(board: &Board, cam: &CameraModel, t: usize) -> Option<DensityModes> {
        let (rms, corr_um) = (cam.ink_density_rms, cam.ink_density_corr_um);
        if rms == 0.0 {
            return None;
        }
        let target = &board.targets[t];
        // The grid covers every ROI of the target (`target_roi`: the rim grown by the lens,
        // 5 blur widths and 5 px), the same on every view, and half a correlation length.
        let reach = 1.1 * target.outer.outer_radius_um()
            + (5.0 * cam.psf_sigma_px + 6.0) * cam.scale_um_per_px
            + corr_um / 2.0;
        let spacing = corr_um / 2.0;
        let k = (reach / spacing).ceil() as i64;
        let axis_um: Vec<f64> = (-k..=k).map(|i| i as f64 * spacing).collect();
        let n = axis_um.len();
        let kernel = DMatrix::from_fn(n, n, |a, b| gauss(axis_um[a] - axis_um[b], corr_um));
        let eig = kernel.symmetric_eigen();
        let mu = &eig.eigenvalues;
        let top = mu.max();
        // A 1-D mode that no pair keeps (μ_a·top < 10⁻⁶·top²) is dropped at once.
        let kept: Vec<usize> = (0..n).filter(|&a| mu[a] >= 1e-6 * top).collect();
        let axis_weights = kept
            .iter()
            .map(|&a| eig.eigenvectors.column(a) / mu[a].sqrt())
            .collect();
        let pairs = (0..kept.len())
            .flat_map(|a| (0..kept.len()).map(move |b| (a, b)))
            .filter(|&(a, b)| mu[kept[a]] * mu[kept[b]] >= 1e-6 * top * top)
            .collect();
        Some(DensityModes {
            centre_um: target.centre_um,
            axis_um,
            axis_weights,
            pairs,
            rms,
            corr_um,
        })
    }

    /// How many 2-D modes the basis keeps.
    fn len(&self) -> usize {
        self.pairs.len()
    }

    /// Each kept 1-D mode's kriged value and derivative at offset `x` (µm) from the centre.
    fn along(&self, x: f64) -> (Vec<f64>, Vec<f64>) {
        let l2 = self.corr_um * self.corr_um;
        let n = self.axis_um.len();
        let (mut e, mut de) = (DVector::zeros(n), DVector::zeros(n));
        for (i, &g) in self.axis_um.iter().enumerate() {
            let k = gauss(x - g, self.corr_um);
            (e[i], de[i]) = (k, -(x - g) / l2 * k);
        }
        (self.axis_weights.iter())
            .map(|w| (e.dot(w), de.dot(w)))
            .unzip()
    }

    /// Each mode's derivative column: the RGB of pixel q changes by
    /// `−(depth(q)·φ_j(p) + σ²·∇φ_j·∇depth(q))`, p the board point `to_board` puts q at
    /// (the lens blurs the inked density whole: `warp::InkTaylor`'s first-order term; the
    /// mode's own blur, ~3 % of its amplitude inside the ink, is left out), then observed
    /// as the samples are.
    fn derivatives(
        &self,
        depth: &InkDepth,
        (roi, to_board): ([u32; 4], Affine),
        observe: &Observe,
    ) -> Vec<Vec<f64>> {
        let [x0, y0, w, h] = roi;
        let n = (w * h) as usize;
        let mut cols = vec![vec![0.0f32; 3 * n]; self.len()];
        // The image gradient of a function of the board point: Aᵀ·∇_board.
        let at = to_board.a.transpose();
        for px in 0..n {
            let (x, y) = (px % w as usize, px / w as usize);
            let p = to_board.board([(x0 as usize + x) as f64, (y0 as usize + y) as f64]);
            let (fx, dfx) = self.along(p[0] - self.centre_um[0]);
            let (fy, dfy) = self.along(p[1] - self.centre_um[1]);
            for (col, &(a, b)) in cols.iter_mut().zip(&self.pairs) {
                let phi = self.rms * fx[a] * fy[b];
                let gb = nalgebra::Vector2::new(dfx[a] * fy[b], fx[a] * dfy[b]) * self.rms;
                let gi = at * gb;
                for ch in 0..3 {
                    let gd = depth.grad[3 * px + ch];
                    let blur = depth.var_px2 * (gi[0] * gd[0] + gi[1] * gd[1]);
                    col[3 * px + ch] = (-(depth.rgb[3 * px + ch] * phi + blur)) as f32;
                }
            }
        }
        cols.iter().map(|rgb| observe(rgb, roi)).collect()
    }
}

/// The ink's depth over a ROI (paper minus the evenly inked render, RGB per pixel), its
/// image gradient, and the lens's blur variance, from which the density's derivatives
/// follow.
struct InkDepth {
    rgb: Vec<f64>,
    /// Per pixel and channel, d(depth)/d(image x, y).
    grad: Vec<[f64; 2]>,
    var_px2: f64,
}

impl InkDepth {
    /// From `seen(dx, dy)`, the depth with the camera moved by (dx, dy) µm on the board:
    /// the image then shows what was `M·(dx, dy)` px further on (M = A⁻¹, A the board µm per
    /// image px), so `∇depth = Aᵀ·∂depth/∂(camera)`, by central differences `h_um` wide.
    fn seen(
        seen: impl Fn(f64, f64) -> Vec<f64>,
        h_um: f64,
        a: nalgebra::Matrix2<f64>,
        var_px2: f64,
    ) -> InkDepth {
        let d = |plus: Vec<f64>, minus: Vec<f64>| -> Vec<f64> {
            plus.iter()
                .zip(&minus)
                .map(|(p, m)| (p - m) / (2.0 * h_um))
                .collect()
        };
        let dx = d(seen(h_um, 0.0), seen(-h_um, 0.0));
        let dy = d(seen(0.0, h_um), seen(0.0, -h_um));
        let at = a.transpose();
        let grad = dx
            .iter()
            .zip(&dy)
            .map(|(&x, &y)| {
                let g = at * nalgebra::Vector2::new(x, y);
                [g[0], g[1]]
            })
            .collect();
        InkDepth {
            rgb: seen(0.0, 0.0),
            grad,
            var_px2,
        }
    }
}

/// The sim's correlation of the density at two points `d` µm apart along one axis: the
/// 2-D covariance is `rms²·gauss(dx)·gauss(dy)`.
fn gauss(d: f64, corr_um: f64) -> f64 {
    (-d * d / (2.0 * corr_um * corr_um)).exp()
}

/// The lens's local affine map from the image to the board about a board point `c`:
/// `p = c + A·(q − q_c)`, with `q_c` the image of c.
#[derive(Debug, Clone, Copy)]
struct Affine {
    a: nalgebra::Matrix2<f64>,
    q_c: [f64; 2],
    c: [f64; 2],
}

impl Affine {
    fn at(cam: &CameraModel, view: View, c: [f64; 2]) -> Affine {
        let img = |p: [f64; 2]| {
            if cam.needs_warp() {
                view.project(cam, 1, p)
            } else {
                view.board_to_image(cam, p)
            }
        };
        let h = 1000.0;
        let (q_c, qx, qy) = (img(c), img([c[0] + h, c[1]]), img([c[0], c[1] + h]));
        // Image change per µm on the board, inverted.
        let m = nalgebra::Matrix2::new(
            (qx[0] - q_c[0]) / h,
            (qy[0] - q_c[0]) / h,
            (qx[1] - q_c[1]) / h,
            (qy[1] - q_c[1]) / h,
        );
        let a = m.try_inverse().expect("the lens maps the board one to one");
        Affine { a, q_c, c }
    }

    fn board(&self, q: [f64; 2]) -> [f64; 2] {
        let d = self.a * nalgebra::Vector2::new(q[0] - self.q_c[0], q[1] - self.q_c[1]);
        [self.c[0] + d[0], self.c[1] + d[1]]
    }
}

/// The board and camera moved by +h and −h in parameter `p`, and h.
#[allow(clippy::type_complexity)]
fn perturb(
    board: &Board,
    cam: &CameraModel,
    p: Param,
    step_um: f64,
) -> (f64, (Board, CameraModel), (Board, CameraModel)) {
    let h = match p {
        Param::OuterX | Param::OuterY | Param::InnerX | Param::InnerY | Param::Radius(_) => step_um,
        Param::Blur => 0.01,
        Param::Light | Param::Gradient | Param::Vignetting | Param::Ink(_) => 1e-3,
    };
    let make = |sign: f64| {
        let mut b = board.clone();
        let mut c = cam.clone();
        let d = sign * h;
        let t = &mut b.targets[0];
        match p {
            // Move the outer shape only: the centre moves, the offset compensates.
            Param::OuterX => {
                t.centre_um[0] += d;
                t.offset_um[0] -= d;
            }
            Param::OuterY => {
                t.centre_um[1] += d;
                t.offset_um[1] -= d;
            }
            Param::InnerX => t.offset_um[0] += d,
            Param::InnerY => t.offset_um[1] += d,
            Param::Radius(i) => {
                let shape = if i < 2 { &mut t.outer } else { &mut t.inner };
                grow(shape, i, d);
            }
            Param::Blur => c.psf_sigma_px += d,
            Param::Light => {}
            Param::Gradient => c.light_gradient += d,
            Param::Vignetting => c.vignetting += d,
            Param::Ink(k) => b.ink_rgb[k] += d,
        }
        (b, c)
    };
    (h, make(1.0), make(-1.0))
}

/// Grow one radius of a shape: for the outer ring 0 = hole, 1 = rim; for the inner shape
/// 2 = rim (a disk's radius), 3 = an inner ring's hole.
fn grow(shape: &mut Shape, i: usize, d: f64) {
    match (shape, i) {
        (
            Shape::Ring {
                inner_radius_um, ..
            },
            0 | 3,
        ) => *inner_radius_um += d,
        (
            Shape::Ring {
                outer_radius_um, ..
            },
            1 | 2,
        ) => *outer_radius_um += d,
        (Shape::Disk { radius_um }, 2) => *radius_um += d,
        (s, i) => unreachable!("radius {i} of {s:?}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bound_is_microns_and_shrinks_with_less_noise() {
        let board = Board::paper();
        let cam = CameraModel::default();
        let view = View::at([0.3 * 774.0, 0.6 * 774.0]);
        let b = offset_crb_um(&board, &cam, 6, view);
        // Deterministic (expected values, no noise drawn): 3.44 µm per axis for one frame of
        // the paper's rig, green channel (docs/method.md). 5 % either way.
        let near = |v: f64, want: f64| (v / want - 1.0).abs() < 0.05;
        assert!(near(b[0], 3.44) && near(b[1], 3.44), "{b:?}");
        let quiet = CameraModel {
            gain_e_per_dn: 4.0 * cam.gain_e_per_dn,
            read_noise_dn: 0.0,
            ..cam.clone()
        };
        let q = offset_crb_um(&board, &quiet, 6, view);
        // 4x the gain halves a shot-noise-limited bound; no read noise takes it lower still:
        // 1.52 µm.
        assert!(near(q[0], 1.52) && q[0] < 0.5 * b[0], "{q:?} vs {b:?}");
        // All three channels know more than the best one alone: 2.48 µm.
        let all = offset_crb_um_channels(&board, &cam, 6, view, &[0, 1, 2]);
        eprintln!("CRB target A: green {b:?} µm, R+G+B {all:?} µm, 4x less noise {q:?} µm");
        assert!(near(all[0], 2.48) && all[0] < b[0], "{all:?} vs {b:?}");
    }

    /// The depth's gradient from moving the camera is the image's own: against central
    /// differences of neighbouring pixels, through a tilted lens, 7.1 % RMS apart (the
    /// differences' own error on an edge blurred by 1.2 px: f‴/6f′ ≈ 1/6σ², 12 % at its
    /// steepest). A flipped one would be 200 % apart.
    #[test]
    fn the_inks_depth_gradient_is_the_images() {
        let board = Board::paper();
        let cam = CameraModel {
            tilt_x_deg: 3.0,
            psf_sigma_px: 1.2,
            ..CameraModel::default()
        };
        let view = View::at([0.3 * 774.0, 0.6 * 774.0]);
        let target = &board.targets[6];
        let roi = target_roi(&cam, target, view);
        let mut base = board.clone();
        base.targets = vec![target.clone()];
        base.clutter.clear();
        let seen = |dx: f64, dy: f64| {
            let v = View::at([view.camera_um[0] + dx, view.camera_um[1] + dy]);
            expected_rgb(&base, &cam, &v, roi, 1.0)
                .iter()
                .map(|&i| -(i as f64))
                .collect()
        };
        let a = Affine::at(&cam, view, target.centre_um).a;
        let depth = InkDepth::seen(seen, 15.0, a, 1.0);
        let w = roi[2] as usize;
        let (mut err, mut norm) = (0.0, 0.0);
        for y in 1..roi[3] as usize - 1 {
            for x in 1..w - 1 {
                let at = |x: usize, y: usize| depth.rgb[3 * (y * w + x) + 1];
                let want = [
                    (at(x + 1, y) - at(x - 1, y)) / 2.0,
                    (at(x, y + 1) - at(x, y - 1)) / 2.0,
                ];
                let got = depth.grad[3 * (y * w + x) + 1];
                err += (got[0] - want[0]).powi(2) + (got[1] - want[1]).powi(2);
                norm += want[0].powi(2) + want[1].powi(2);
            }
        }
        let rel = (err / norm).sqrt();
        assert!(rel < 0.09, "the gradients differ by {rel:.3} RMS");
    }

    #[test]
    fn not_knowing_the_print_raises_the_bound_more_the_more_frames() {
        let board = Board::paper();
        let view = View::at([0.3 * 774.0, 0.6 * 774.0]);
        let webcam = CameraModel::profile("webcam").unwrap();
        // Even ink: nothing to learn about the print, the bound with it known over √N.
        let even = CameraModel {
            ink_density_rms: 0.0,
            ..webcam.clone()
        };
        let raw = offset_crb_um_raw(&board, &even, 6, view);
        let h = offset_hcrb_um_raw(&board, &even, 6, &[view], 20);
        for a in 0..2 {
            assert!(
                (h[a] * 20f64.sqrt() / raw[a] - 1.0).abs() < 1e-9,
                "{h:?} {raw:?}"
            );
        }
        let raw = offset_crb_um_raw(&board, &webcam, 6, view);
        let unknown = PrintUnknown::new(&board, &webcam, 6, &[view]);
        let per_n: Vec<[f64; 2]> = [1, 10, 20, 200]
            .iter()
            .map(|&n| unknown.offset_um(n))
            .collect();
        let ratio: Vec<f64> = per_n
            .iter()
            .zip([1.0, 10.0, 20.0, 200.0f64])
            .map(|(b, n)| b[0].hypot(b[1]) * n.sqrt() / raw[0].hypot(raw[1]))
            .collect();
        eprintln!("raw {raw:?} µm; hybrid {per_n:?} µm; × √N / raw {ratio:?}");
        // Never below the bound with the print known; the unknown density weighs more as
        // the frames beat the noise down.
        assert!(ratio.windows(2).all(|r| r[1] >= r[0]), "{ratio:?}");
        assert!(ratio[0] >= 1.0, "{ratio:?}");
        // A density twice as uneven is harder still.
        let rougher = CameraModel {
            ink_density_rms: 0.08,
            ..webcam.clone()
        };
        let r = offset_hcrb_um_raw(&board, &rougher, 6, &[view], 20);
        assert!(
            r[0] > per_n[2][0] && r[1] > per_n[2][1],
            "{r:?} vs {:?}",
            per_n[2]
        );
    }
}
